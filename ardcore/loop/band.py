"""The 90 % posterior predictive band's statistics: its bounds from the draws, and where data lie in it.

A pointwise band (at each time the draws' quantiles) holds 90 % of the draws at each time; what a user checks
is the share of *one record's* points inside it. The two agree on average over records, but not for a typical
record when the draws' errors are slow: on a free oscillation whose draws drift out of phase, a few draws far
off widen the band and every other draw, the data among them, sits inside it nearly all the time (their
share inside: median 0.97 over the draws, the mean 0.90 carried by a few at 0.4). So the band is set at the
level at which a **typical draw** (the median over the draws, each judged against the others) has 90 % of its
points inside (:func:`typical_level`); for errors independent from sample to sample this is the pointwise
level (:func:`band_level`), for slow errors a narrower band, for errors that leave most draws outside for long
stretches a wider one.
"""

from __future__ import annotations

import numpy as np

COVERAGE = 0.9
"""The band's nominal coverage: the share of a typical record's points it holds."""

MAX_DIVERGED = 0.05
"""The largest share of a band's draws that may diverge: beyond it the bounds are infinite (:func:`band_of`), so
no scale is taken at which more do."""


def inside(y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Where ``y`` lies inside the band ``lo``-``hi`` (False where ``y`` is not finite: a diverged draw)."""
    return (y >= lo) & (y <= hi)


def diverged(ys: np.ndarray) -> float:
    """The share of predictive draws ``ys`` (draws x samples) that diverged somewhere."""
    return float(np.mean(~np.all(np.isfinite(ys), axis=1))) if len(ys) else 0.0


def band_level(n: int, coverage: float = COVERAGE) -> float:
    """The lower quantile level of ``n`` draws whose interval to the matching upper one holds a new draw of the
    same distribution with probability ``coverage``. The sample's 5 % and 95 % quantiles do not: a new draw falls
    outside the k-th smallest of n with probability k / (n + 1), so 40 draws' 5-95 % interpolated quantiles make
    an 86 % band. The level puts the bound at order statistic ``(1 - coverage) / 2 * (n + 1)`` (interpolated),
    the draws' own extremes when ``n`` is too small for it."""
    return _level((1.0 - coverage) / 2.0 * (n + 1), n)


def _level(k: float, n: int) -> float:
    """The quantile level of ``n`` draws at (interpolated) order statistic ``k`` from either end."""
    return float(min(max(k - 1.0, 0.0) / max(n - 1, 1), 0.5))


def depths(ys: np.ndarray) -> np.ndarray:
    """For each draw and sample (draws x samples), how many of the *other* draws lie beyond it on its nearer side:
    a draw is inside the band whose bounds are the k-th smallest and k-th largest of the others where its depth is
    at least k. A diverged draw (non-finite) counts beyond both bounds of the others (as :func:`band_of` counts it)
    and has depth -1 itself."""
    n = len(ys)
    fin = np.isfinite(ys)
    lost = (~fin).sum(axis=0)
    rank = np.empty(ys.shape, dtype=np.int64)
    np.put_along_axis(rank, np.argsort(np.where(fin, ys, np.inf), axis=0, kind="stable"),
                      np.broadcast_to(np.arange(n)[:, None], ys.shape), axis=0)
    # the rank among the finite draws (they sort first), the lost ones beyond either side
    below = rank + lost
    above = (n - lost - 1 - rank) + lost
    return np.where(fin, np.minimum(below, above), -1)


def typical_level(ys: np.ndarray, coverage: float = COVERAGE) -> float:
    """The quantile level of the draws ``ys`` (draws x samples) at which a typical draw has ``coverage`` of its
    points inside the band of the others.

    Each draw's share inside the band at order statistic k of the others (its :func:`depths` at least k) falls
    with k; the median of that share over the draws, interpolated between the integers, reaches ``coverage`` at
    some k* (the middle of the stretch where it equals it). Judged against n - 1 draws, k* is order statistic
    k* (n + 1) / n of n (a new draw falls below the k-th of n with probability k / (n + 1), below the k-th of
    n - 1 with k / n). For independent draws the median share is the mean, and the level is
    :func:`band_level`'s."""
    n, m = ys.shape
    if n < 3 or m == 0:
        return band_level(n, coverage)
    d = depths(ys) + 1  # 0 for a lost point, then 1 + depth
    top = int(d.max()) + 2
    counts = np.bincount((np.arange(n)[:, None] * top + d).ravel(), minlength=n * top).reshape(n, top)
    share = counts[:, ::-1].cumsum(axis=1)[:, ::-1] / m  # share[:, k + 1]: the share of points at depth >= k
    typical = np.median(share[:, 1:], axis=0)  # typical[k], k = 0, 1, ...: falls with k
    if not typical[0] >= coverage:  # a typical draw is lost more often than the band may miss: the draws' extremes
        return 0.0
    # where the median, linear between the integers, reaches the coverage; the middle of the stretch where it
    # equals it (a short record's shares are discrete, so the median can sit on the coverage over a range of k)
    k = (_crossing(typical, coverage, strict=True) + _crossing(typical, coverage, strict=False)) / 2.0
    return _level(max(k, 1.0) * (n + 1) / n, n)


def _crossing(f: np.ndarray, level: float, strict: bool) -> float:
    """Where the falling series ``f`` (linear between its integers) leaves ``level``: past the last index at
    which it is above it (``strict``) or at least at it; its last index when it never falls below."""
    above = np.flatnonzero(f > level if strict else f >= level)
    if not above.size:  # f starts at the level (strict): the stretch starts at 0
        return 0.0
    k = int(above[-1])
    if k + 1 >= f.size:
        return float(k)
    return k + float((f[k] - level) / (f[k] - f[k + 1])) if f[k] > f[k + 1] else float(k)


def band_of(ys: np.ndarray, level: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The 90 % predictive band of draws ``ys`` (draws x samples): at each sample their quantiles at ``level``
    and 1 - ``level`` (default :func:`typical_level`: a typical record of the model has 90 % of its points
    inside). A draw that diverged is beyond either bound from where it did, not dropped (dropping it would narrow
    the band of a model that diverges): where more than the pointwise level's share of the draws have (5 %), the
    bound is infinite."""
    n = len(ys)
    fin = np.isfinite(ys)
    q = typical_level(ys) if level is None else level
    # an interpolation that touches an infinite draw is NaN: the bound there is the infinite one
    with np.errstate(invalid="ignore"):
        lo = np.quantile(np.where(fin, ys, -np.inf), q, axis=0)
        hi = np.quantile(np.where(fin, ys, np.inf), 1.0 - q, axis=0)
    lost = (~fin).sum(axis=0) > band_level(n) * (n - 1)
    lo = np.where(np.isnan(lo) | lost, -np.inf, lo)
    hi = np.where(np.isnan(hi) | lost, np.inf, hi)
    return lo, hi


def expected_coverage(ys: np.ndarray, level: float | None = None) -> list[float]:
    """The coverage the band's own model expects on one record: each predictive draw's share inside the band of
    the others (at the band's ``level``, default :func:`typical_level`), its 5 %, 50 % and 95 % quantiles over
    the draws. A record's coverage varies about its median when its errors are slow (a lightly damped response
    holds few independent stretches); a coverage outside this range is one the model did not expect."""
    q = typical_level(ys) if level is None else level
    cover = []
    for i in range(len(ys)):
        lo, hi = band_of(np.delete(ys, i, axis=0), q)
        cover.append(float(np.mean(inside(ys[i], lo, hi))))
    return [float(x) for x in np.quantile(cover, [0.05, 0.5, 0.95])]
