"""Evidence between ARD trials without new likelihood evaluations (importance reweighting).

Moving from psi to psi' changes only the ARD prior factors, so

    Z(psi') / Z(psi) = E_post(psi)[ p(phi | psi') / p(phi | psi) ]

is an average over the draws already made at psi. With an ARD prior N(0, 1/alpha) the weight of a
draw is ``prod_k sqrt(alpha'_k / alpha_k) exp(-(alpha'_k - alpha_k) phi_k^2 / 2)``. While alpha_k is far
below the posterior precision of phi_k the weights are nearly equal (the estimate is exact to Monte
Carlo noise: ln Z rises by 1/2 ln(alpha'/alpha)); as alpha' approaches it the weights spread and
their effective sample size falls, which is when a real trial must run.

The maximiser (:func:`ardcore.selection.maximiser.maximise`) uses this for line-search steps, never for a prune test
(alpha = inf puts all prior mass at one point no draw sits on) and never for the accepted optimum.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

INF = math.inf


@dataclass(frozen=True)
class Reweighted:
    """The reweighted estimate of ln Z(psi') - ln Z(psi) from the draws at psi.

    Attributes
    ----------
    log_ratio : float
        ln of the mean weight.
    se : float
        Monte Carlo standard error of ``log_ratio`` (batch means over every chain, so the chains'
        autocorrelation counts).
    ess : float
        Kish effective sample size of the weights, ``(sum w)^2 / sum w^2``.
    n : int
        Draws used.
    weights : ndarray, shape (n_chains, M)
        Normalised weights (sum 1).
    """

    log_ratio: float
    se: float
    ess: float
    n: int
    weights: np.ndarray

    def reliable(self, min_ess: float, max_se: float) -> bool:
        """ESS at least ``min_ess`` of the draws and Monte Carlo se at most ``max_se`` nats."""
        return self.ess >= min_ess * self.n and self.se <= max_se


def _ard_logpdf_change(x: np.ndarray, a: float, b: float) -> np.ndarray:
    """ln N(x; 0, 1/b) - ln N(x; 0, 1/a) for finite positive a, b."""
    return 0.5 * math.log(b / a) - 0.5 * (b - a) * x * x


def reweight(names: list[str], samples: np.ndarray, psi_from: dict, psi_to: dict, *,
             batches: int = 5) -> Reweighted | None:
    """Importance weights taking the posterior at ``psi_from`` (``samples``, shape (chains, M, d), columns
    ``names``) to the one at ``psi_to``; None where reweighting does not apply (no draws, a term switched
    on or off, a flat prior alpha = 0, a psi key the draws lack)."""
    samples = np.asarray(samples, float)
    if samples.ndim != 3 or samples.shape[1] < 2 * batches or set(psi_from) != set(psi_to):
        return None
    changed = [k for k in psi_to if psi_to[k] != psi_from[k]]
    idx = {n: i for i, n in enumerate(names)}
    for k in changed:
        a, b = float(psi_from[k]), float(psi_to[k])
        if k not in idx or not (0 < a < INF and 0 < b < INF):
            return None
    if not np.all(np.isfinite(samples)):
        return None
    nc, M, _ = samples.shape
    logw = np.zeros((nc, M))
    for k in changed:
        logw += _ard_logpdf_change(samples[:, :, idx[k]], float(psi_from[k]), float(psi_to[k]))
    top = float(logw.max())
    w = np.exp(logw - top)
    mean = float(w.mean())
    ess = float(w.sum() ** 2 / np.sum(w * w))
    m = (M // batches) * batches
    bm = w[:, :m].reshape(nc, batches, m // batches).mean(axis=2).ravel()
    se = float(bm.std(ddof=1) / math.sqrt(bm.size) / mean) if bm.size > 1 else INF
    return Reweighted(top + math.log(mean), se, ess, nc * M, w / w.sum())


def resample_states(res, weights: np.ndarray, seed: int, free=None):
    """``res`` (a SamplerResult) whose chain states sit at draws resampled with ``weights`` (systematic
    resampling) and whose proposal covariance is the weighted draws' (scaled 2.38^2 / d, as the adaptation
    scales it): the next sampled trial starts dispersed, already near its posterior, with a step fitted to it.
    ``free`` (:class:`~ardcore.sampling.transform.Unconstrained`) gives the sampler's coordinates, in which the
    covariance is taken (default: the draws' own)."""
    nc, M, d = res.samples.shape
    flat = res.samples.reshape(nc * M, d)
    p = np.asarray(weights, float).ravel()
    n = len(res.states)
    u = (np.random.default_rng(seed).uniform() + np.arange(n)) / n
    pick = np.minimum(np.searchsorted(np.cumsum(p), u), p.size - 1)
    lp, ll = res.lp.reshape(-1), res.ll.reshape(-1)
    states = [dataclasses.replace(s, x=[float(v) for v in flat[i]], lp=float(lp[i]), ll=float(ll[i]))
              for s, i in zip(res.states, pick)]
    w = p / p.sum()
    flat = free.to_free(flat) if free is not None else flat
    m = w @ flat
    C = (flat - m).T @ ((flat - m) * w[:, None])
    cov = res.proposal_cov
    try:
        np.linalg.cholesky(C)
        if np.all(np.isfinite(C)):
            cov = (2.38**2 / d) * C
    except np.linalg.LinAlgError:
        pass
    return dataclasses.replace(res, states=states, proposal_cov=cov)


def weighted_summary(names: list[str], samples: np.ndarray, weights: np.ndarray) -> dict:
    """mean, sd and 0.5 / 99.5 % quantiles per parameter of weighted draws (the reweighted posterior)."""
    X = np.asarray(samples, float).reshape(-1, len(names))
    w = np.asarray(weights, float).ravel()
    w = w / w.sum()
    out = {}
    for i, n in enumerate(names):
        x = X[:, i]
        m = float(w @ x)
        order = np.argsort(x)
        c = np.cumsum(w[order])
        q = [float(x[order][min(np.searchsorted(c, p), x.size - 1)]) for p in (0.005, 0.995)]
        out[n] = {"mean": m, "sd": float(math.sqrt(max(w @ (x - m) ** 2, 0.0))), "q005": q[0], "q995": q[1]}
    return out
