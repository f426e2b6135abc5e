"""The residuals of a fitted model (docs/method.md section 8, step 2): standardised EKF innovations with their
tests, and the process noise the filter had to inject per dynamic state, from an RTS smoother on the model
with a small diagnostic noise (its level fitted by maximum likelihood) on every dynamic state."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize

from ..data import Dataset
from ..effects.base import dynamic_states
from ..likelihood.ekf import compile_model
from .config import DiagnoseConfig
from ..model.declaration import ModelSpec
from .residual_tests import dominant_frequency, residual_tests


@dataclass
class Residuals:
    """The residuals of a fitted model on one data set (see module docstring)."""

    innovations: np.ndarray          # standardised, (n, m)
    raw_innovations: np.ndarray      # (n, m)
    smoothed: np.ndarray             # (n, n_x)
    process_noise_rate: dict         # state -> (n-1,) injected drift w_k / dt
    noise_std: dict                  # state -> fitted diagnostic noise std (or the model's own)
    tests: dict                      # per observation channel
    loglik: float
    states: tuple = ()               # names of the smoothed columns
    dt: float = 1.0                  # median sample interval


def _diagnostic_spec(spec: ModelSpec, states: list[str]) -> tuple[ModelSpec, list[str]]:
    """``spec`` with a noise parameter on every listed state that has none."""
    add = [s for s in states if not spec.diffusion.get(s)]
    names = [f"q_diag_{s}" for s in add]
    if not add:
        return spec, []
    diff = dict(spec.diffusion)
    diff.update({s: n for s, n in zip(add, names)})
    new = spec.model_copy(update={"name": f"{spec.name}_diag", "diffusion": diff,
                                  "parameters": list(spec.parameters) + names})
    return new.revalidate(), names


def residuals(spec: ModelSpec, phi: dict, data: Dataset, config: DiagnoseConfig, *,
              substeps: int | None = None) -> Residuals:
    """Residuals of ``spec`` at parameter values ``phi`` (dict over its free parameters)."""
    cm = compile_model(spec)
    fr = cm.filter(phi, data, substeps)
    fs = 1.0 / float(np.median(np.diff(data.t)))
    e = fr.standardized
    fund = dominant_frequency(data.columns[spec.observed_columns[0]], fs)
    tests = {c: residual_tests(e[:, j], fs, config, fundamental=fund) for j, c in enumerate(spec.observed_columns)}
    dyn = dynamic_states(spec)
    dspec, qnames = _diagnostic_spec(spec, dyn)
    dcm = compile_model(dspec)
    scale = np.nanstd(fr.filtered, axis=0)
    q0 = {}
    if qnames:
        lik = dcm.bind(data, substeps)
        idx = [spec.states.index(n[len("q_diag_"):]) for n in qnames]
        # the injected noise is at most of the order of the state's rate of change
        hi = np.log10(np.maximum(scale[idx] * fs, 1e-12))
        lo = hi - 8

        def nll(z):
            z = np.clip(z, lo, hi)
            v = lik({**phi, **{n: 10.0 ** zi for n, zi in zip(qnames, z)}})
            return -v if np.isfinite(v) else 1e300

        best = min((optimize.minimize(nll, np.full(len(qnames), s), method="Nelder-Mead",
                                      options={"xatol": 0.05, "fatol": 0.05, "maxfev": 400})
                    for s in (lo + 2, hi - 3)), key=lambda r: r.fun)
        q0 = {n: float(10.0 ** np.clip(best.x, lo, hi)[i]) for i, n in enumerate(qnames)}
    _, sm = dcm.smooth({**phi, **q0}, data, substeps)
    dt = np.diff(data.t)
    rates = {s: sm.process_noise[1:, spec.states.index(s)] / dt for s in dyn}
    noise_std = {s: q0.get(f"q_diag_{s}") for s in dyn}
    return Residuals(e, fr.innovations, sm.smoothed, rates, noise_std, tests, fr.loglik, tuple(spec.states),
                     float(np.median(dt)))
