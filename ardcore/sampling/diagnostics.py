"""Convergence diagnostics of today's standard (Vehtari et al. 2021), computed by ArviZ.

Every reported posterior carries, per parameter, the rank-normalised split R-hat, the bulk and tail
effective sample sizes and the Monte Carlo standard errors of the mean and the sd, exactly as
``az.summary(..., kind="diagnostics")`` gives them to a user who opens the draws. The stationary stage
stops on them (:class:`Quality`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FIELDS = ("r_hat", "ess_bulk", "ess_tail", "mcse_mean", "mcse_sd")


def convergence(names: list[str], samples: np.ndarray) -> dict[str, dict[str, float]]:
    """ArviZ's diagnostics of draws ``samples`` (chain, draw, param): parameter -> {r_hat, ess_bulk,
    ess_tail, mcse_mean, mcse_sd}. A parameter that does not move (a constant) gets r_hat NaN and ESS 0."""
    import warnings

    import arviz as az

    samples = np.asarray(samples, dtype=float)
    if samples.ndim != 3 or samples.shape[1] < 4 or not names:
        return {n: {k: math.nan for k in FIELDS} for n in names}
    post = {f"p{i}": samples[..., i] for i in range(len(names))}  # ArviZ's names need not be the user's
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        table = az.summary(az.from_dict({"posterior": post}), kind="diagnostics", round_to="none")
    out = {}
    for i, n in enumerate(names):
        row = table.loc[f"p{i}"]
        out[n] = {k: float(row[k]) for k in FIELDS}
    return out


@dataclass(frozen=True)
class Quality:
    """The stopping rule of the stationary stage: every parameter at R-hat <= ``max_rhat`` and bulk and tail
    ESS >= ``min_ess``."""

    max_rhat: float = 1.01
    min_ess: float = 400.0

    def worst(self, diag: dict) -> tuple[float, float, str, str]:
        """The largest R-hat and the smallest ESS (bulk or tail) with the parameters they belong to."""
        if not diag:
            return 1.0, math.inf, "", ""
        # an undefined diagnostic (ArviZ's NaN, JSON's null: a parameter that never moved) is the worst case
        rh = {n: _number(v.get("r_hat"), math.inf) for n, v in diag.items()}
        es = {n: min(_number(v.get("ess_bulk"), 0.0), _number(v.get("ess_tail"), 0.0)) for n, v in diag.items()}
        r_name, e_name = max(rh, key=rh.get), min(es, key=es.get)
        return rh[r_name], es[e_name], r_name, e_name

    def met(self, diag: dict) -> bool:
        r, e, _, _ = self.worst(diag)
        return r <= self.max_rhat and e >= self.min_ess

    def describe(self, diag: dict) -> str:
        r, e, rn, en = self.worst(diag)
        return f"max R-hat {r:.3f} ({rn}), min ESS {e:.0f} ({en})"


def _number(v, undefined: float) -> float:
    return float(v) if v is not None and math.isfinite(v) else undefined
