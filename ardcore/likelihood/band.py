"""The 90 % posterior predictive band of a free run, from its simulated draws (draws x samples).

A pointwise band holds a new draw of its model at each sample with probability 90 %. On one record that is
an average over the record's samples, and where the errors are slow and unevenly spread (a limit cycle whose
phase drifts: most draws sit well inside the envelope, a few far off it) a typical record holds 98 % and a
rare one half. Users judge a band by the share of one new record inside it, so the band's level is chosen
from the draws themselves: the level at which half the draws lie inside the band of the others on at least
90 % of their samples (:func:`typical_level`). Where the errors are fast it is the pointwise level.
"""

from __future__ import annotations

import math

import numpy as np

COVERAGE = 0.9
"""The share of a typical record the band holds."""

MAX_DIVERGED = 0.05
"""The largest share of a band's draws that may diverge: beyond it the bounds are infinite (:func:`band_of`), so
no scale is taken at which more do."""


def band_level(n: int, coverage: float = COVERAGE) -> float:
    """The lower quantile level of ``n`` draws whose interval to the matching upper one holds a new draw of the
    same distribution with probability ``coverage``. The sample's 5 % and 95 % quantiles do not: a new draw falls
    outside the k-th smallest of n with probability k / (n + 1), so 40 draws' 5-95 % interpolated quantiles make
    an 86 % band. The level puts the bound at order statistic ``(1 - coverage) / 2 * (n + 1)`` (interpolated),
    the draws' own extremes when ``n`` is too small for it."""
    k = (1.0 - coverage) / 2.0 * (n + 1)
    return float(min(max(k - 1.0, 0.0) / max(n - 1, 1), 0.5))


class _Sorted:
    """Draws (draws x samples) sorted once per sample for bounds at any level: a non-finite draw counts below the
    lower bound and above the upper one from where it diverged (not dropped)."""

    def __init__(self, ys: np.ndarray):
        self.ys = ys
        fin = np.isfinite(ys)
        self.sides = []
        for fill in (-np.inf, np.inf):
            v = np.where(fin, ys, fill)
            order = np.argsort(v, axis=0, kind="stable")
            rank = np.empty_like(order)
            np.put_along_axis(rank, order, np.arange(len(ys))[:, None], axis=0)
            self.sides.append((fill, np.take_along_axis(v, order, axis=0), rank))

    def bounds(self, level: float, leave_out: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """The bounds at quantile ``level`` (linear interpolation between order statistics, as ``np.quantile``);
        a bound whose order statistics reach a diverged draw is infinite. With ``leave_out``, each draw's band of
        the other draws (draws x samples)."""
        n = len(self.ys)
        m = n - 1 if leave_out else n
        out = []
        for (fill, s, rank), p in zip(self.sides, (level, 1.0 - level)):
            h = p * (m - 1)
            k = min(int(math.floor(h)), m - 1)
            f = h - k
            k1 = min(k + 1, m - 1)
            if leave_out:
                # the others' k-th value: the sorted k-th, or the next one where the draw itself is at or below it
                a = np.take_along_axis(s, k + (k >= rank), axis=0)
                b = np.take_along_axis(s, k1 + (k1 >= rank), axis=0)
            else:
                a, b = s[k], s[k1]
            if f > 0:
                with np.errstate(invalid="ignore"):
                    q = np.where(np.isinf(a) | np.isinf(b), fill, a + f * (b - a))
            else:
                q = np.where(np.isinf(a), fill, a)
            out.append(q)
        return out[0], out[1]

    def own_coverage(self, level: float) -> np.ndarray:
        """Each draw's share of samples inside the band of the other draws at ``level``."""
        lo, hi = self.bounds(level, leave_out=True)
        return np.mean(inside(self.ys, lo, hi), axis=1)


def inside(y: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Where ``y`` lies inside the band ``lo``-``hi`` (False where ``y`` is not finite: a diverged draw)."""
    return (y >= lo) & (y <= hi)


def typical_level(ys: np.ndarray, coverage: float = COVERAGE) -> float:
    """The narrowest band's level (its lower quantile) at which half the draws lie inside the band of the
    others on at least ``coverage`` of their samples: the band a typical record of the model fills to
    ``coverage``. Independent errors give the pointwise level (:func:`band_level`); slow, unevenly spread ones
    a narrower or wider band."""
    sorted_ = ys if isinstance(ys, _Sorted) else _Sorted(np.asarray(ys, dtype=float))
    n = len(sorted_.ys)
    if n < 5:
        return band_level(n, coverage)
    tie = 0.5 / max(sorted_.ys.shape[1], 1)  # coverages are shares of the samples: within half a sample is equal

    def holds(level: float) -> bool:
        # at least half the draws hold ``coverage``, a draw exactly at it counted half (its coverage is discrete)
        c = sorted_.own_coverage(level)
        return np.mean(c > coverage + tie) + 0.5 * np.mean(np.abs(c - coverage) <= tie) >= 0.5

    lo, hi = 0.0, 0.5  # the share that holds falls as the level rises; at 0.5 the band is a line
    if not holds(lo):
        return 0.0  # even the draws' full range holds less: the widest band there is
    for _ in range(30):
        mid = 0.5 * (lo + hi)
        if holds(mid):
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-4:
            break
    return float(lo)


def band_of(ys: np.ndarray, level: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The pointwise bounds of the 90 % predictive band of draws ``ys`` (draws x samples), at quantile ``level``
    (default :func:`typical_level`: the band holds 90 % of a typical record). A draw that diverged is beyond
    either bound from where it did, not dropped (dropping it would narrow the band of a model that diverges):
    where more than the level's share of the draws have, the bound is infinite."""
    sorted_ = _Sorted(np.asarray(ys, dtype=float))
    return sorted_.bounds(typical_level(sorted_) if level is None else level)


def expected_coverage(ys: np.ndarray, level: float | None = None) -> list[float]:
    """The coverage the band's own model expects on one record: each predictive draw's share inside the band of
    the others (at the band's ``level``, default :func:`typical_level`), its 5 %, 50 % and 95 % quantiles over
    the draws. A record's coverage varies a lot about 90 % when its errors are slow (a lightly damped response
    holds few independent stretches); a coverage outside this range is one the model did not expect."""
    sorted_ = _Sorted(np.asarray(ys, dtype=float))
    cover = sorted_.own_coverage(typical_level(sorted_) if level is None else level)
    return [float(x) for x in np.quantile(cover, [0.05, 0.5, 0.95])]


def diverged(ys: np.ndarray) -> float:
    """The share of predictive draws ``ys`` (draws x samples) that diverged somewhere."""
    return float(np.mean(~np.all(np.isfinite(ys), axis=1))) if len(ys) else 0.0
