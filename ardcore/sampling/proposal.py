"""The sampler's proposal: a random walk mixed with an independence proposal (:class:`Jump`), its draws and its
exact density (:class:`MixedProposal`), which the Metropolis-Hastings ratio and the Chib-Jeliazkov ordinate both
read."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np


def safe_cholesky(cov: np.ndarray) -> np.ndarray:
    """Cholesky factor, adding diagonal jitter if needed."""
    cov = 0.5 * (cov + cov.T)
    scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
    for j in (0.0, 1e-12, 1e-10, 1e-8, 1e-6, 1e-4):
        try:
            return np.linalg.cholesky(cov + np.diag((j * scale) ** 2 + (1e-300 if j else 0)))
        except np.linalg.LinAlgError:
            continue
    return np.diag(scale)


class Jump(NamedTuple):
    """The independence half of the sampler's proposal: a multivariate t around the posterior's centre.

    A random walk with one fixed covariance crawls along a curved or stretched posterior (Sec 3.6's M3:
    integrated autocorrelation times of ~200 draws with a well adapted covariance). Each step therefore
    proposes, with probability ``weight``, a draw of this heavy-tailed independence proposal fitted to
    the burn-in draws, and otherwise the random walk. The mixture q(y|x) = (1 - w) N(y; x, C_rw) +
    w t(y; mean, cov, df) is fixed in the stationary stage and has a density, so the Metropolis-Hastings
    ratio (q is not symmetric) and the Chib-Jeliazkov ordinate both use it exactly. Coordinates are the
    sampler's unconstrained ones (:mod:`.transform`).
    """

    mean: np.ndarray
    cov: np.ndarray
    weight: float = 0.5
    df: float = 5.0

    def to_dict(self) -> dict:
        return {"mean": np.asarray(self.mean).tolist(), "cov": np.asarray(self.cov).tolist(),
                "weight": float(self.weight), "df": float(self.df)}

    @classmethod
    def from_dict(cls, d: dict | None) -> "Jump | None":
        if not d:
            return None
        return cls(np.asarray(d["mean"], float), np.asarray(d["cov"], float), float(d["weight"]), float(d["df"]))


def _solve_lower(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """L^-1 b for a lower-triangular L: LAPACK's trtrs called as ``scipy.linalg.solve_triangular`` calls it
    (the same operations, so the same bits), without its per-call checks, which cost ten times the solve of a
    few parameters and ran at every step of a chain that mixes in an independence proposal."""
    from scipy.linalg.lapack import dtrtrs

    x, info = dtrtrs(L.T, b, lower=0, trans=1)
    if info != 0:
        from scipy.linalg import solve_triangular

        return solve_triangular(L, b, lower=True)  # its error names the singular pivot
    return x


class MixedProposal:
    """q(y|x) = (1 - w) N(y; x, L L^T) + w t(y; jump): draws and log densities (w = 0: the random walk)."""

    def __init__(self, cov: np.ndarray, jump: Jump | None):
        self.L = safe_cholesky(cov)
        self.d = self.L.shape[0]
        self.w = float(jump.weight) if jump is not None and jump.weight > 0 else 0.0
        self.rw_const = -np.sum(np.log(np.diag(self.L))) - 0.5 * self.d * math.log(2 * math.pi)
        if self.w:
            from scipy.special import gammaln

            self.mean, self.df = np.asarray(jump.mean, float), float(jump.df)
            self.Lj = safe_cholesky(jump.cov)
            d, v = self.d, self.df
            self.t_const = (gammaln((v + d) / 2) - gammaln(v / 2) - 0.5 * d * math.log(v * math.pi)
                            - np.sum(np.log(np.diag(self.Lj))))

    def log_t(self, y: np.ndarray) -> np.ndarray:
        u = _solve_lower(self.Lj, (np.atleast_2d(y) - self.mean).T)
        return self.t_const - 0.5 * (self.df + self.d) * np.log1p(np.sum(u * u, axis=0) / self.df)

    def log_rw(self, diff: np.ndarray) -> np.ndarray:
        u = _solve_lower(self.L, np.atleast_2d(diff).T)
        return self.rw_const - 0.5 * np.sum(u * u, axis=0)

    def log_q(self, y: np.ndarray, x: np.ndarray) -> np.ndarray:
        """ln q(y | x) for rows of y and x (broadcast)."""
        y, x = np.atleast_2d(y), np.atleast_2d(x)
        if not self.w:
            return self.log_rw(y - x)
        return np.logaddexp(math.log1p(-self.w) + self.log_rw(y - x), math.log(self.w) + self.log_t(y))

    def draw(self, rng: np.random.Generator, x: np.ndarray) -> np.ndarray:
        if self.w and rng.random() < self.w:
            g = rng.chisquare(self.df) / self.df
            return self.mean + (self.Lj @ rng.standard_normal(self.d)) / math.sqrt(g)
        return x + self.L @ rng.standard_normal(self.d)

    def log_ratio(self, y: np.ndarray, x: np.ndarray) -> float:
        """ln q(x|y) - ln q(y|x) (0 for the pure random walk: it is symmetric)."""
        return self.ratio_and_t(y, x)[0]

    def ratio_and_t(self, y: np.ndarray, x: np.ndarray, tx: float | None = None) -> tuple:
        """:meth:`log_ratio` with ln t(x) and ln t(y), the independence density at both (None for the pure
        random walk). ``tx``: ln t(x) when known, as this returned it before: a chain reads its point's there
        (from the step that proposed the point, or the last one that stayed at it) instead of solving for it
        at every step (the same number)."""
        if not self.w:
            return 0.0, None, None
        r = math.log1p(-self.w) + float(self.log_rw(y - x)[0])
        tx = float(self.log_t(x)[0]) if tx is None else tx
        ty = float(self.log_t(y)[0])
        lw = math.log(self.w)
        return float(np.logaddexp(r, lw + tx) - np.logaddexp(r, lw + ty)), tx, ty
