"""The EKF's score and information for candidate terms (the machinery of :mod:`ardcore.screening.screen`).

At the fitted parameters and zero coefficients of the new terms, the innovations and their variances are
differentiated (central differences of the filter) with respect to every model parameter and every new
coefficient; that gives the score and the Gauss-Newton information of the EKF likelihood, from which
:func:`bayes_factor` computes a candidate's Laplace log Bayes factor with the model's own parameters
profiled out, adjusted to the innovations' own spectrum (:mod:`ardcore.screening.robust`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import sympy as sp

from ..data import Dataset
from ..effects.base import Effect, augment, feature_functions, with_columns
from ..likelihood.ekf import compile_model
from ..model.declaration import ModelSpec
from .robust import innovation_background, sandwich, spectral_score_cov

PRIOR_SD = 1.0
"""Prior sd of a normalised coefficient in the screen (1 = an effect the size of the target's dynamics)."""


def rms(a: np.ndarray) -> float:
    a = np.asarray(a, dtype=float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a ** 2))) if a.size else 0.0


def eval_exprs(spec: ModelSpec, exprs: list[str], X: np.ndarray, U: np.ndarray) -> list[np.ndarray]:
    _, fns = feature_functions(spec, exprs)
    n = X.shape[0]
    out = []
    for f in fns:
        v = np.asarray(f(*X.T, *U.T), dtype=float)
        out.append(np.broadcast_to(v, (n,)).copy() if v.ndim == 0 else v)
    return out


def target_scale(spec: ModelSpec, phi: dict, target: str, X: np.ndarray, U: np.ndarray, data: Dataset) -> float:
    """Size of what an effect on ``target`` competes with: rms of its drift, or of the observed signal."""
    if target in spec.states:
        sm = spec.sym
        i = spec.states.index(target)
        e = sm.drift[i].subs({p: phi[str(p)] for p in sm.params if str(p) in phi})
        syms = list(sm.states) + list(sm.inputs)
        f = sp.lambdify(syms, e, modules=[{"sign": np.sign}, "numpy"])
        v = np.asarray(f(*X.T, *U.T), dtype=float)
        r = rms(v - np.nanmean(v)) if v.ndim else 0.0
        if r > 0:
            return r
        # a state with no drift yet: its rate of change in the data
        x = X[:, i]
        dt = float(np.median(np.diff(data.t)))
        return max(rms(np.diff(x)) / dt, 1e-12)
    y = data.columns[target]
    return max(rms(y - np.nanmean(y)), 1e-12)


@dataclass
class Basis:
    """The model's own sensitivities and innovations at the fit: with any candidates' sensitivity rows
    (:attr:`Screened.rows`) they give the joint score and information, with no further filter pass."""

    De: np.ndarray
    DS: np.ndarray
    e0: np.ndarray
    S0: np.ndarray
    ok: np.ndarray
    eps: np.ndarray | None

    @property
    def k(self) -> int:
        return self.De.shape[0]

    def score(self, De: np.ndarray, DS: np.ndarray):
        """Score g, information and standardised sensitivities on the time grid (None without ``eps``) of the
        parameters whose innovation sensitivities are the rows of ``De``, ``DS``."""
        e0, S0 = self.e0, self.S0
        g = -(De @ (e0 / S0)) - 0.5 * (DS @ (1 / S0 - e0 ** 2 / S0 ** 2))
        Inf = (De / S0) @ De.T + 0.5 * (DS / S0 ** 2) @ DS.T
        psi = None
        if self.eps is not None:
            # the innovations' sensitivities on the time grid (zero where there is no observation), standardised
            psi = np.zeros((De.shape[0], self.ok.size))
            psi[:, self.ok] = De / np.sqrt(S0)
        return g, Inf, psi


class Screener:
    """Score/information of the EKF likelihood for a batch of normalised candidate terms."""

    def __init__(self, spec: ModelSpec, phi: dict, data: Dataset, substeps: int | None, robust: bool = True):
        self.spec, self.phi, self.data, self.substeps = spec, dict(phi), data, substeps
        fr = compile_model(spec).filter(phi, data, substeps)
        e, S = fr.innovations.ravel(), fr.innovation_var.ravel()
        self._ref_ok = np.isfinite(e) & np.isfinite(S) & (S > 0)
        self.X = np.where(np.isfinite(fr.filtered), fr.filtered, 0.0)
        self.U = (np.column_stack([data.columns[u] for u in spec.inputs]) if spec.inputs
                  else np.zeros((len(data), 0)))
        self.theta = list(spec.free_parameters)
        self._models: dict = {}
        self.basis: Basis | None = None
        self.last_rows: list = []
        # the standardised innovations on the time grid (zero where there is no observation): their actual
        # spectrum, which the likelihood takes as flat, is what each candidate's score really varies by
        self.eps = None
        if robust and fr.standardized.ndim == 2 and fr.standardized.shape[1] == 1:
            e = fr.standardized[:, 0]
            self.eps = np.where(np.isfinite(e), e, 0.0)

    def __getstate__(self) -> dict:
        # the compiled screening models stay behind: a pool worker loads them from the on-disk kernel cache
        return {**self.__dict__, "_models": {}}

    def term_scale(self, effect: Effect, target: str, data: Dataset) -> list[float] | None:
        """scale per term so that scale * term has the rms of the target's dynamics (None if a term is ~0)."""
        if effect.where == "noise":
            return [1.0]  # k is already dimensionless: the log of the noise factor
        # columns the model has already (an input's rate added in an earlier round) are in self.U
        cols = {c: v for c, v in effect.columns_for(data.t, data.columns).items() if c not in self.spec.inputs}
        U = np.column_stack([self.U] + [cols[c] for c in cols]) if cols else self.U
        fspec = self.spec.model_copy(update={"inputs": list(self.spec.inputs) + list(cols)}) if cols else self.spec
        vals = eval_exprs(fspec, list(effect.terms), self.X, U)
        R = target_scale(self.spec, self.phi, target, self.X, self.U, data)
        out = []
        for v in vals:
            if not np.all(np.isfinite(v)):
                return None
            r = rms(v)
            if r <= 1e-300 * max(R, 1e-300) or r == 0:
                return None
            out.append(R / r)
        return out

    def batch(self, items: list[tuple[Effect, str, list[float]]], shape_values: list | None = None,
              data: Dataset | None = None) -> tuple[list[np.ndarray], np.ndarray, np.ndarray]:
        """Score g and information I over (theta, every item's coefficients); returns per-item index lists.

        Scales and shape values are parameters of the screening model (not literals), so one
        compiled kernel serves every value a shape profile tries.
        """
        shape_values = shape_values or [None] * len(items)
        key = tuple((e.name if not e.shape else e.name + "#" + e.shape[0], t, len(s)) for e, t, s in items)
        spec = self.spec
        data = data or self.data
        names, values = [], {}
        for j, ((eff, target, scales), sv) in enumerate(zip(items, shape_values)):
            nm = [f"zq{j}_{i}" for i in range(len(eff.terms))]
            cn = [f"zc{j}_{i}" for i in range(len(eff.terms))]
            e2 = eff
            if eff.shape and eff.shape[0] != "f":
                pname = f"zs{j}"
                e2 = replace(eff, terms=tuple(t.replace("{" + eff.shape[0] + "}", pname) for t in eff.terms),
                             shape=())
                values[pname] = float(sv)
            spec, _ = augment(spec, e2, target, cn, names=nm)
            extra = [f"zs{j}"] if f"zs{j}" in values else []
            spec = spec.model_copy(update={"name": "screen", "parameters": list(spec.parameters) + cn + extra})
            values.update({c: float(s) for c, s in zip(cn, scales)})
            names.append(nm)
            data = with_columns(data, eff if not eff.shape or eff.shape[0] != "f" else eff.at(float(sv)))
        if key not in self._models:
            self._models[key] = compile_model(spec.revalidate())
        lik = self._models[key].bind(data, self.substeps)
        allp = self.theta + [n for nm in names for n in nm]
        base = {**{p: self.phi[p] for p in self.theta}, **{n: 0.0 for nm in names for n in nm}, **values}
        f0 = lik.filter(base)
        e0, S0 = f0.innovations.ravel(), f0.innovation_var.ravel()
        ok = np.isfinite(e0) & np.isfinite(S0) & (S0 > 0)
        e0, S0 = e0[ok], S0[ok]
        k = len(self.theta)
        # at zero coefficients a candidate's filter is the model's own, so the model's sensitivities and
        # innovations are the same in every batch and any set of candidates can be scored jointly later --
        # unless a term is not finite somewhere (0 * inf): then that batch's rows are not stored
        same = ok.shape == self._ref_ok.shape and bool(np.array_equal(ok, self._ref_ok))
        if same and self.basis is not None:
            # the model's own rows are known: only the new coefficients are differentiated (a shape profile
            # calls this for every value it tries, and the model's own 2k filter runs dominated it)
            De, DS = self._sensitivities(lik, base, allp[k:], ok)
            De, DS = np.vstack([self.basis.De, De]), np.vstack([self.basis.DS, DS])
        else:
            De, DS = self._sensitivities(lik, base, allp, ok)
        own = Basis(De[:k], DS[:k], e0, S0, ok, self.eps)
        if same and self.basis is None:
            self.basis = Basis(De[:k].copy(), DS[:k].copy(), e0, S0, ok, self.eps)
        groups, pos = [], k
        for nm in names:
            groups.append(np.arange(pos, pos + len(nm)))
            pos += len(nm)
        self.last_rows = [(De[gr], DS[gr]) if same else None for gr in groups]
        g, Inf, psi = own.score(De, DS)
        return groups, g, Inf, psi


    @staticmethod
    def _sensitivities(lik, base: dict, params: list[str], ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Central differences of the innovations and their variances (where ``ok``) in each of ``params``."""
        D_e, D_S = [], []
        for p in params:
            v = base[p]
            h = 1e-4 * abs(v) if v != 0 else 1e-5
            r = []
            for sgn in (1, -1):
                fr = lik.filter({**base, p: v + sgn * h})
                r.append((fr.innovations.ravel()[ok], fr.innovation_var.ravel()[ok]))
            D_e.append((r[0][0] - r[1][0]) / (2 * h))
            D_S.append((r[0][1] - r[1][1]) / (2 * h))
        De, DS = np.array(D_e).reshape(len(params), -1), np.array(D_S).reshape(len(params), -1)
        bad = ~np.all(np.isfinite(De), axis=0) | ~np.all(np.isfinite(DS), axis=0)
        De[:, bad], DS[:, bad] = 0.0, 0.0
        return De, DS


def nuisance_map(Inf: np.ndarray, k: int, grp: np.ndarray) -> np.ndarray:
    """I_bt I_tt^-1: how a group's score and sensitivities are projected off the first k (the model's own)
    parameters, whose refit would absorb that much of the group."""
    th = np.arange(k)
    Itt = Inf[np.ix_(th, th)]
    d = np.sqrt(np.maximum(np.diag(Itt), 1e-300))
    Itt_inv = np.linalg.pinv(Itt / np.outer(d, d), rcond=1e-10) / np.outer(d, d)
    return Inf[np.ix_(grp, th)] @ Itt_inv


def bayes_factor(g: np.ndarray, Inf: np.ndarray, k: int, grp: np.ndarray, psi: np.ndarray | None = None,
                  eps: np.ndarray | None = None) -> tuple[float, float, np.ndarray, float]:
    """Laplace ln BF, profile gain and coefficients of one group, the first k parameters profiled out.

    With the innovations' sensitivities ``psi`` and the standardised innovations ``eps`` themselves, the
    likelihood is first adjusted to the score's actual variance (:func:`~ardcore.screening.robust.sandwich`,
    :func:`~ardcore.screening.robust.spectral_score_cov`): the spectrum is that of the innovations *with the candidate fitted*
    (linearised, ``eps + psi' k``), as a sandwich variance is estimated from the residuals of the
    fitted model, so that a real effect's own signature (a chirp of a decaying oscillation, which a
    running median does not step over as it does a line) does not count as noise against it.
    """
    th = np.arange(k)
    A = nuisance_map(Inf, k, grp)
    H = Inf[np.ix_(grp, grp)] - A @ Inf[np.ix_(grp, th)].T
    H = 0.5 * (H + H.T)
    gb = g[grp] - A @ g[th]
    inflation = 1.0
    if psi is not None and eps is not None:
        # the efficient score's sensitivities (what a refit of the model's own parameters cannot absorb); their
        # Gram matrix is H, so only the colour of the innovations is added: V = H + psi (S - 1) psi'
        eff = psi[grp] - A @ psi[th]
        k_hat = np.linalg.pinv(H, rcond=1e-10) @ gb
        psd = innovation_background(eps + eff.T @ k_hat)
        if psd is not None:
            V = H + spectral_score_cov(eff, psd) - eff @ eff.T
            H, gb, inflation = sandwich(H, gb, V)
    w, V = np.linalg.eigh(H)
    w = np.maximum(w, 0.0)
    z = V.T @ gb
    s2 = PRIOR_SD ** 2
    lbf = float(0.5 * np.sum(z ** 2 / (w + 1 / s2)) - 0.5 * np.sum(np.log1p(s2 * w)))
    gain = float(0.5 * np.sum(np.where(w > 1e-12 * max(w.max(), 1e-300), z ** 2 / np.maximum(w, 1e-300), 0.0)))
    coef = V @ (z / (w + 1 / s2))
    return lbf, gain, coef, inflation
