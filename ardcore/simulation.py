"""A model for simulation: the loop's final structure fitted at the process-noise level that free-runs best.

The evidence and the posterior are the EKF's: parameters that predict the next sample given the filtered
state. When the model still lacks something, the fitted process noise stands in for it (the filter corrects
the state at every sample), and the parameters that set the long-horizon behaviour of a lightly damped
system (its damping terms, the height of its resonance) are weakly pinned and pulled by the misfit: on
Silverbox the evidence adds quadratic or cubic damping by thousands of nats, yet the posterior mean then
free-runs worse than without it. At a smaller process noise the filter trusts the model over more samples
and the likelihood weighs multi-step predictions; at zero it becomes the output-error (free-run) fit.

So the free run is also reported for a **simulation fit**: the same structure, its noise parameters scaled
by a factor chosen on held-out data (fit on the first part of the estimation record by maximum likelihood
at each factor, free run on the rest; factor 1 is the posterior's own noise and wins unless another is
better by ``min_gain``), then refitted on the whole record at that factor. This is a predictive choice,
not an evidence one; model selection, the posterior and its intervals are unchanged, and the report
labels which figure is which.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import sympy as sp
from scipy.optimize import minimize

from .data import Dataset
from .ekf import compile_model
from .freerun import free_run
from .model import ModelSpec


@dataclass
class SimulationFit:
    """The chosen noise factor, the parameters fitted at it and the held-out free-run error of each factor."""

    factor: float
    phi: dict
    noise_parameters: list
    held_out_rms: dict = field(default_factory=dict)
    fit_samples: int = 0
    held_out_samples: int = 0

    def to_json(self) -> dict:
        return {"factor": self.factor, "noise_parameters": self.noise_parameters,
                "held_out_rms": {f"{k:g}": v for k, v in self.held_out_rms.items()},
                "fit_samples": self.fit_samples, "held_out_samples": self.held_out_samples,
                "chosen_by": "held-out free run on the estimation record (a predictive choice, not the evidence)"}


def noise_parameters(spec: ModelSpec) -> list[str]:
    """Free parameters that scale the process noise: each diffusion expression is proportional to them
    (sigma, 2*sigma: scaling the parameter scales the noise). Empty when a diffusion term depends on a
    free parameter in another way (exp(s), s + 1), where scaling it would not scale the noise."""
    sm = spec.sym  # parsed, with constants, fixed values and derived quantities substituted
    out: list[str] = []
    for e in sm.diffusion:
        ps = [p for p in sm.params if p in e.free_symbols]
        if not ps:
            continue
        if len(ps) != 1 or sp.simplify(e - ps[0] * sp.diff(e, ps[0])) != 0:
            return []
        out += [str(p) for p in ps if str(p) not in out]
    return out


def _fit(task) -> dict:
    """Maximum likelihood of ``names`` (scaled by their magnitude) from ``phi``, the rest held; the noise
    parameters at ``factor`` x their value in ``phi``. One task of a process pool: (spec, phi, noise, factor,
    record, names, substeps, maxfun)."""
    spec, phi, noise, factor, data, names, substeps, maxfun = task
    phi = {**phi, **{p: phi[p] * factor for p in noise}}
    lik = compile_model(spec).bind(data, substeps)
    scale = np.array([abs(phi[p]) if phi[p] != 0 else 1.0 for p in names])

    def nll(z):
        q = dict(phi)
        q.update({p: float(v) for p, v in zip(names, z * scale)})
        v = lik(q)
        return -v if np.isfinite(v) else 1e300

    z0 = np.array([phi[p] for p in names]) / scale
    sol = minimize(nll, z0, method="L-BFGS-B", options={"maxfun": maxfun, "eps": 1e-7})
    out = dict(phi)
    if np.isfinite(sol.fun) and sol.fun < nll(z0):
        out.update({p: float(v) for p, v in zip(names, sol.x * scale)})
    return out


def simulation_fit(spec: ModelSpec, phi: dict, data: Dataset, *, substeps: int | None = None,
                   factors: tuple = (0.3, 0.1, 0.03), held_out: float = 0.3, min_gain: float = 0.05,
                   init_samples: int = 50, maxfun: int = 3000, map_fn=None) -> SimulationFit | None:
    """Choose the process-noise factor for simulation on held-out data (see module docstring).

    Parameters
    ----------
    spec, phi : the fitted model and its posterior mean.
    data : Dataset
        The estimation record (with any columns the model's effects need).
    factors : tuple of float
        Factors of the noise parameters tried besides 1.
    held_out : float
        Share of the record, at its end, that the free runs are scored on.
    min_gain : float
        Relative reduction of the held-out free-run error a factor needs over factor 1.
    map_fn : callable, optional
        ``map_fn(fn, tasks)`` runs the factors' fits (a process pool's map; default: one after another).

    Returns
    -------
    SimulationFit or None
        None when the model has no noise parameter that scales its process noise, or the record is too
        short to hold part of it out.
    """
    noise = noise_parameters(spec)
    n = len(data)
    n_fit = int(round(n * (1 - held_out)))
    if not noise or not factors or n_fit < 4 * init_samples or n - n_fit < 4 * init_samples:
        return None
    fit_part, test_part = data.slice(0, n_fit), data.slice(n_fit, None)
    names = [p for p in spec.free_parameters if p not in noise]
    run = map_fn or (lambda fn, tasks: [fn(t) for t in tasks])
    grid = (1.0, *[f for f in factors if f != 1.0])
    fitted = dict(zip(grid, run(_fit, [(spec, phi, noise, f, fit_part, names, substeps, maxfun) for f in grid])))
    rms = {}
    for f, q in fitted.items():
        r = free_run(spec, q, test_part, init_samples=init_samples, substeps=substeps)["rms_error"]
        rms[f] = float(r) if np.isfinite(r) else float("inf")
    best = min(rms, key=rms.get)
    if best == 1.0 or not rms[best] < (1 - min_gain) * rms[1.0]:
        return SimulationFit(1.0, dict(phi), noise, rms, n_fit, n - n_fit)
    # the whole record at the chosen factor, from the held-out fit (its noise parameters back at 1 x phi's)
    start = {**fitted[best], **{p: phi[p] for p in noise}}
    return SimulationFit(best, _fit((spec, start, noise, best, data, names, substeps, maxfun)), noise, rms,
                         n_fit, n - n_fit)
