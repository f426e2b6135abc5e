"""Convergence diagnostics of today's standard (Vehtari et al. 2021), as ArviZ computes them.

Every reported posterior carries, per parameter, the rank-normalised split R-hat, the bulk and tail
effective sample sizes and the Monte Carlo standard errors of the mean and the sd, as
``az.summary(..., kind="diagnostics")`` gives them to a user who opens the draws (the same formulas, equal to
ArviZ's to rounding: ``tests/statistical/test_quality.py``). The stationary stage stops on them
(:class:`Quality`), after every extension of every trial, on the study's driver: ArviZ's summary walks Geyer's
sequence one lag at a time in Python (0.4 s for 4 chains of 4,000 draws of 9 parameters); here every lag is
taken at once.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

FIELDS = ("r_hat", "ess_bulk", "ess_tail", "mcse_mean", "mcse_sd")


def convergence(names: list[str], samples: np.ndarray) -> dict[str, dict[str, float]]:
    """The diagnostics of draws ``samples`` (chain, draw, param): parameter -> {r_hat, ess_bulk, ess_tail,
    mcse_mean, mcse_sd}, as ArviZ's ``az.summary(kind="diagnostics")`` has them. A parameter that does not
    move (a constant) gets r_hat NaN."""
    samples = np.asarray(samples, dtype=float)
    if samples.ndim != 3 or samples.shape[1] < 4 or not names:
        return {n: {k: math.nan for k in FIELDS} for n in names}
    return {n: _diagnostics(samples[..., i]) for i, n in enumerate(names)}


TAIL_PROB = 0.89
"""The tail ESS is the smaller of the ESS of the indicators below the (1 - p) / 2 and (1 + p) / 2 quantiles at this
``p``: ArviZ's default interval (``rcParams["stats.ci_prob"]``), which its summary's ``ess_tail`` uses."""


def _diagnostics(x: np.ndarray) -> dict[str, float]:
    """:func:`convergence`'s fields of one parameter's draws ``x`` (chain, draw)."""
    if not np.all(np.isfinite(x)):
        return {k: math.nan for k in FIELDS}
    split = _split(x)
    bulk = _z_scale(split)  # the rank-normalised draws: the bulk R-hat and the bulk ESS read them
    low, high = np.quantile(x, sorted((TAIL_PROB, 1.0 - TAIL_PROB)))
    centred = x - x.mean()
    with np.errstate(invalid="ignore", divide="ignore"):  # a constant: NaN, as ArviZ has it
        r_hat = math.nan
        if x.shape[0] >= 2:
            r_hat = max(_rhat(bulk), _rhat(_z_scale(np.abs(split - np.median(split)))))
        var = (centred ** 2).mean()
        varvar = ((centred ** 4).mean() - var ** 2) / _ess(_split(centred ** 2))
        mcse_sd = np.sqrt(varvar / var / 4)
    return {"r_hat": float(r_hat),
            "ess_bulk": float(_ess(bulk)),
            "ess_tail": float(min(_ess(_split(x <= low)), _ess(_split(x <= high)))),
            "mcse_mean": float(np.std(x, ddof=1) / np.sqrt(_ess(split))),
            "mcse_sd": float(mcse_sd)}


def _split(x: np.ndarray) -> np.ndarray:
    """Each chain's first and last halves as chains of their own (a chain's middle draw dropped when odd)."""
    half = x.shape[1] // 2
    return np.vstack((x[:, :half], x[:, -half:]))


def _z_scale(x: np.ndarray) -> np.ndarray:
    """The draws' ranks (average ties) as normal quantiles, Blom's offset 3/8."""
    from scipy import stats

    rank = stats.rankdata(x, method="average").reshape(x.shape)
    return stats.norm.ppf((rank - 0.375) / (x.size - 0.75 + 1))


def _rhat(x: np.ndarray) -> float:
    """The potential scale reduction of chains ``x`` (chain, draw)."""
    n = x.shape[1]
    between = n * np.var(np.mean(x, axis=1), ddof=1)
    within = np.mean(np.var(x, axis=1, ddof=1))
    return float(np.sqrt((between / within + n - 1) / n))


def _ess(x: np.ndarray) -> float:
    """The effective sample size of chains ``x`` (chain, draw): Geyer's initial positive and then monotone
    sequence of the chains' mean autocorrelation (Vehtari et al. 2021), the autocorrelations of every lag at once."""
    from scipy.fft import irfft, next_fast_len, rfft

    x = np.asarray(x, dtype=float)
    if np.max(x) - np.min(x) < np.finfo(float).resolution:
        return float(x.size)
    m, n = x.shape
    f = next_fast_len(2 * n)
    spec = rfft(x - x.mean(axis=1, keepdims=True), n=f, axis=1)
    spec *= np.conjugate(spec)
    acov = irfft(spec, n=f, axis=1)[:, :n] / n
    mean_var = np.mean(acov[:, 0]) * n / (n - 1.0)
    var_plus = mean_var * (n - 1.0) / n
    if m > 1:
        var_plus += np.var(x.mean(axis=1), ddof=1)
    rho = 1.0 - (mean_var - acov.mean(axis=0)) / var_plus
    # the initial positive sequence: pair j = (rho[2j], rho[2j+1]), j = 1, 2, ..., read while the pair before
    # summed above 0 (pair 0 is (1, rho[1])) and 2j - 1 < n - 3; the last pair read is kept if it sums to >= 0
    k_max = max((n - 3) // 2, 0)
    pairs = rho[2:2 * k_max + 2].reshape(-1, 2).sum(axis=1)
    if not 1.0 + rho[1] > 0.0:
        read = 0
    else:
        below = np.flatnonzero(~(pairs > 0.0))
        read = int(below[0]) + 1 if below.size else k_max
    last = read if read >= 1 and pairs[read - 1] >= 0.0 else read - 1
    out = np.zeros(n)
    out[:max(2 * last + 2, 2)] = rho[:max(2 * last + 2, 2)]
    out[0] = 1.0
    max_t = 2 * read - 1
    even = rho[2 * read] if read >= 1 else 1.0
    if even > 0:  # the last even lag read, kept when positive
        out[max_t + 1] = even
    # the initial monotone sequence: a pair summing more than the one before takes that one's mean
    for j in range(1, read):
        a, b = 2 * j - 2, 2 * j
        if out[b] + out[b + 1] > out[a] + out[a + 1]:
            out[b] = out[b + 1] = (out[a] + out[a + 1]) / 2.0
    ess = m * n
    tau = -1.0 + 2.0 * np.sum(out[:max_t + 1]) + np.sum(out[max_t + 1:max_t + 2])
    tau = max(tau, 1.0 / np.log10(ess))
    return math.nan if np.isnan(out).any() else ess / tau


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
