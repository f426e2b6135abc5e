"""Continuous-discrete extended Kalman filter likelihood (docs/method.md section 2).

Between observations the filter takes ``substeps`` Euler steps of the mean and
of the covariance (``P <- A P A^T + G G^T dt`` with the exact Jacobian
``A = I + J dt``); at each observation all channels are linearised at the
forecast and assimilated (a NaN skips that channel). Known inputs are held
constant between samples. Irregular sampling is handled interval by interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..model.codegen import kernel_module
from ..data import Dataset
from ..errors import ModelError
from ..model.declaration import ModelSpec


@dataclass
class FilterResult:
    """Everything the filter saw.

    Attributes
    ----------
    loglik : float
        ln p(d | phi).
    innovations, innovation_var : ndarray, shape (n, m)
        d_k - h(u_k^f) and its variance S_k (NaN where no observation).
    forecast : ndarray, shape (n, n_x)
        Forecast (prior) state means u_k^f.
    filtered : ndarray, shape (n, n_x)
        Filtered state means.
    filtered_cov : ndarray, shape (n, n_x, n_x)
    forecast_cov, transition : ndarray, shape (n, n_x, n_x), optional
        Forecast covariances P_k^f and the linearised transition Phi_k from
        sample k-1 to k (identity at k = 0); only from :meth:`Likelihood.trace`.
    """

    loglik: float
    innovations: np.ndarray
    innovation_var: np.ndarray
    forecast: np.ndarray
    filtered: np.ndarray
    filtered_cov: np.ndarray
    forecast_cov: np.ndarray | None = None
    transition: np.ndarray | None = None
    starts: tuple = (0,)
    """First row of each record (the filter restarts there)."""

    @property
    def standardized(self) -> np.ndarray:
        """Standardised innovations e_k / sqrt(S_k)."""
        return self.innovations / np.sqrt(self.innovation_var)


_EMPTY2 = np.zeros((0, 0))
_EMPTY3 = np.zeros((0, 0, 0))


class CompiledModel:
    """A model compiled to numba kernels.

    Parameters
    ----------
    spec : ModelSpec
        The declarative model. Compilation is cached by structure, on disk and
        in memory.

    Attributes
    ----------
    param_names : list of str
        The free parameters, in the order ``phi`` vectors use.
    """

    def __init__(self, spec: ModelSpec):
        self.spec = spec
        self.param_names = spec.free_parameters
        self.state_names = list(spec.states)
        self._mod = kernel_module(spec)

    def _phi(self, phi) -> np.ndarray:
        if isinstance(phi, dict):
            missing = [p for p in self.param_names if p not in phi]
            if missing:
                raise ModelError(f"model {self.spec.name!r}: no value for parameter {missing[0]!r}")
            phi = [phi[p] for p in self.param_names]
        a = np.ascontiguousarray(phi, dtype=float)
        if a.shape != (len(self.param_names),):
            raise ModelError(f"model {self.spec.name!r}: expected {len(self.param_names)} parameters "
                             f"{self.param_names}, got shape {a.shape}")
        return a

    def bind(self, data: Dataset, substeps: int | None = None) -> "Likelihood":
        """A fast ``phi -> ln p(d | phi)`` callable over ``data``."""
        return Likelihood(self, data, substeps or self.spec.substeps)

    def loglik(self, phi, data: Dataset, substeps: int | None = None) -> float:
        """ln p(d | phi) by the EKF."""
        return self.bind(data, substeps)(phi)

    def filter(self, phi, data: Dataset, substeps: int | None = None) -> FilterResult:
        """Run the filter and keep innovations and state estimates."""
        return self.bind(data, substeps).filter(phi)

    def smooth(self, phi, data: Dataset, substeps: int | None = None) -> tuple[FilterResult, SmootherResult]:
        """Filter, then RTS-smooth: states given all the data and the process noise they imply."""
        fr = self.bind(data, substeps).trace(phi)
        return fr, rts_smooth(fr)

    def initial(self, phi) -> tuple[np.ndarray, np.ndarray]:
        """Initial state mean and covariance at ``phi``."""
        n = len(self.state_names)
        x, P = np.zeros(n), np.zeros((n, n))
        self._mod.initial(self._phi(phi), x, P)
        return x, P

    def simulate(self, phi, t: np.ndarray, *, x0=None, inputs: np.ndarray | None = None, nsub: int = 1,
                 rng: np.random.Generator | None = None, noise: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """Euler-Maruyama simulation sampled at ``t``.

        Parameters
        ----------
        phi : array_like or dict
        t : ndarray, shape (n,)
            Sample times (strictly increasing).
        x0 : array_like, optional
            Initial state (default: the model's initial mean).
        inputs : ndarray, shape (n, q), optional
            Input columns, held between samples.
        nsub : int
            Integration steps per sample interval.
        rng : numpy.random.Generator, optional
            Source of the Wiener increments (required when ``noise``).
        noise : bool
            False gives the deterministic (free-run) trajectory.

        Returns
        -------
        X : ndarray, shape (n, n_x)
            States at ``t``.
        H : ndarray, shape (n, m)
            Noise-free observations h(X).
        """
        p = self._phi(phi)
        t = np.ascontiguousarray(t, dtype=float)
        n, nx = t.size, len(self.state_names)
        sm = self.spec.sym
        nw = sum(1 for g in sm.diffusion if g != 0)
        steps = (n - 1) * nsub
        if noise and nw:
            if rng is None:
                raise ValueError("simulate(noise=True) needs rng")
            W = rng.standard_normal((steps, nw))
        else:
            W = np.zeros((steps, max(nw, 1)))
        q = len(self.spec.inputs)
        U = np.zeros((n, max(q, 1))) if inputs is None else np.ascontiguousarray(
            np.asarray(inputs, dtype=float).reshape(n, -1))
        if q and inputs is None:
            raise ModelError(f"model {self.spec.name!r} needs inputs {self.spec.inputs}")
        x = self.initial(p)[0] if x0 is None else np.asarray(x0, dtype=float)
        X = np.empty((n, nx))
        Hh = np.empty((n, len(self.spec.observations)))
        self._mod.simulate(p, x, t, U, nsub, W, X, Hh)
        return X, Hh

    def obs_std(self, phi) -> np.ndarray:
        return self._mod.obs_std(self._phi(phi))


class Likelihood:
    """``phi -> ln p(d | phi)`` with the data arrays prepared once."""

    def __init__(self, model: CompiledModel, data: Dataset, substeps: int):
        if int(substeps) < 1:
            raise ModelError("substeps must be >= 1")
        self.model = model
        self.data = data
        self.substeps = int(substeps)
        self.t, self.Y, self.U = data.arrays(model.spec.observed_columns, model.spec.inputs)
        self.records = record_priors(data, model.state_names, model.spec.name)
        self._ekf = model._mod.ekf

    def __call__(self, phi) -> float:
        p = self.model._phi(phi)
        return float(self._ekf(p, self.t, self.Y, self.U, self.substeps, False,
                               _EMPTY2, _EMPTY3, _EMPTY2, _EMPTY2, _EMPTY2, *self.records))

    def filter(self, phi) -> FilterResult:
        p = self.model._phi(phi)
        n, nx, m = self.t.size, len(self.model.state_names), self.Y.shape[1]
        XF, PF, XP = np.full((n, nx), np.nan), np.full((n, nx, nx), np.nan), np.full((n, nx), np.nan)
        IN, SV = np.full((n, m), np.nan), np.full((n, m), np.nan)
        ll = self._ekf(p, self.t, self.Y, self.U, self.substeps, True, XF, PF, XP, IN, SV, *self.records)
        return FilterResult(float(ll), IN, SV, XP, XF, PF, starts=self.data.starts)

    def trace(self, phi) -> FilterResult:
        """:meth:`filter` plus forecast covariances and transitions (what a smoother needs)."""
        p = self.model._phi(phi)
        n, nx, m = self.t.size, len(self.model.state_names), self.Y.shape[1]
        XF, PF, XP = np.full((n, nx), np.nan), np.full((n, nx, nx), np.nan), np.full((n, nx), np.nan)
        PP, PHI = np.full((n, nx, nx), np.nan), np.full((n, nx, nx), np.nan)
        IN, SV = np.full((n, m), np.nan), np.full((n, m), np.nan)
        ll = self.model._mod.ekf_trace(p, self.t, self.Y, self.U, self.substeps, XF, PF, XP, PP, PHI, IN, SV,
                                       *self.records)
        return FilterResult(float(ll), IN, SV, XP, XF, PF, PP, PHI, starts=self.data.starts)


def record_priors(data: Dataset, states: list[str], model: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The kernel's record arguments: each record's first row (and the end), and its initial-state mean and
    std by state (NaN: the model's own). A record's initial state named for a state the model lacks is an
    error."""
    K = data.n_records
    starts = np.array([*data.starts, len(data)], dtype=np.int64)
    M0, S0 = np.full((K, len(states)), np.nan), np.full((K, len(states)), np.nan)
    for r, info in enumerate(data.meta.get("records") or [data.meta]):
        for key, out in (("initial_mean", M0), ("initial_std", S0)):
            for name, v in (info.get(key) or {}).items():
                if name not in states:
                    raise ModelError(f"{info.get('name', f'record {r}')}: {key} names {name!r}, not a state of "
                                     f"model {model!r} (states: {states})")
                out[r, states.index(name)] = float(v)
    return starts, M0, S0


@dataclass
class SmootherResult:
    """Rauch-Tung-Striebel smoothed states and the process noise they imply.

    Attributes
    ----------
    smoothed, smoothed_cov : ndarray, shapes (n, n_x), (n, n_x, n_x)
    process_noise : ndarray, shape (n, n_x)
        w_k = u_k^s - u_k^f - Phi_k (u_{k-1}^s - u_{k-1}^a): what the model had to be pushed by
        between samples k-1 and k beyond its own dynamics (row 0 is zero).
    """

    smoothed: np.ndarray
    smoothed_cov: np.ndarray
    process_noise: np.ndarray


def rts_smooth(fr: FilterResult) -> SmootherResult:
    """RTS smoother on a :meth:`Likelihood.trace` result (linearised at the filter's estimates)."""
    if fr.forecast_cov is None or fr.transition is None:
        raise ModelError("rts_smooth needs Likelihood.trace() output (forecast covariances and transitions)")
    XF, PF, XP, PP, PHI = fr.filtered, fr.filtered_cov, fr.forecast, fr.forecast_cov, fr.transition
    n, nx = XF.shape
    XS, PS = XF.copy(), PF.copy()
    W = np.zeros((n, nx))
    first = set(fr.starts)
    for k in range(n - 2, -1, -1):
        if k + 1 in first:  # the next record starts afresh: this one's last row is its own smoothed end
            continue
        # C = P_k^a Phi^T (P_{k+1}^f)^-1, through a least-squares solve (P^f can be singular in noiseless directions)
        C = np.linalg.lstsq(PP[k + 1].T, (PF[k] @ PHI[k + 1].T).T, rcond=1e-12)[0].T
        d = XS[k + 1] - XP[k + 1]
        XS[k] = XF[k] + C @ d
        PS[k] = PF[k] + C @ (PS[k + 1] - PP[k + 1]) @ C.T
        W[k + 1] = d - PHI[k + 1] @ (XS[k] - XF[k])
    return SmootherResult(XS, PS, W)


_compiled: dict[str, CompiledModel] = {}


def compile_model(spec: ModelSpec) -> CompiledModel:
    """Compiled model for ``spec``, shared by all specs of the same structure in this process."""
    key = spec.structure_hash()
    cm = _compiled.get(key)
    if cm is None or cm.spec.substeps != spec.substeps:
        cm = _compiled[key] = CompiledModel(spec)
    return cm
