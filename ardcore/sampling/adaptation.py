"""Inter-chain adaptation (INCA, Craiu et al. 2009) and the Brooks-Gelman-Rubin R-hat: the coordinator
that pools every chain's recent rounds into one proposal covariance and decides when burn-in is over."""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from .chains import ChainReport, RoundStats, pool_stats
from .proposal import Jump


# --------------------------------------------------------------------------- coordinator
class AdaptationPool:
    """The INCA coordinator as a sans-IO state machine.

    Chains report the statistics of each burn-in round (two half-round
    :class:`RoundStats` and their best point); once every chain has reported a
    round, the round is committed: the proposal covariance is re-estimated from
    the pooled latter half of all chains' rounds, split R-hat is computed from
    the same statistics and the global best point is updated. Reports are
    idempotent (a re-run task reporting the same round again changes nothing),
    and the whole state is a plain dict (:meth:`to_dict`) for checkpoints.
    In-process it is called directly; on Dask it is the coordinator actor.
    """

    def __init__(self, n_chains: int, d: int, cov, *, inca: bool = True, rhat_threshold: float = 1.1,
                 min_rounds: int = 1, outlier_nats: float = 0.0):
        self.n_chains, self.d, self.inca = n_chains, d, inca
        self.rhat_threshold, self.min_rounds = rhat_threshold, min_rounds
        self.outlier_nats = outlier_nats
        self.resets: list[list[int]] = []  # [round, chain, source chain]
        cov = np.asarray(cov, dtype=float)
        self.cov = cov
        self.chain_covs = [cov.copy() for _ in range(n_chains)]
        self.halves: list[list[RoundStats]] = [[] for _ in range(n_chains)]
        self.rounds = 0
        self.pending: dict[int, dict[int, tuple]] = {}
        self.best = None
        self.rhat_history: list[list[float]] = []

    # -- chain side
    def proposal(self, chain: int) -> np.ndarray:
        """The covariance chain ``chain`` should use for its next round."""
        return self.cov if self.inca else self.chain_covs[chain]

    def report(self, chain: int, round_index: int, halves, best) -> bool:
        """Record round ``round_index`` (1-based) of ``chain``; True when that round is committed."""
        if round_index <= self.rounds:
            return True  # already committed: a re-run task reporting again
        best = ChainReport(*best) if best is not None else None  # over the wire it may arrive as a plain tuple
        self.pending.setdefault(round_index, {}).setdefault(chain, (tuple(halves), best))  # first report wins
        if round_index == self.rounds + 1 and len(self.pending[round_index]) == self.n_chains:
            self._commit(self.pending.pop(round_index))
            return True
        return False

    def _commit(self, reports: dict) -> None:
        for c in range(self.n_chains):
            halves, best = reports[c]
            self.halves[c].extend(halves)
            if best is not None and best.lp > self.best_lp:
                self.best = (list(best.x), float(best.lp), float(best.ll))
        self.rounds += 1
        self._reset_outliers(reports)
        fallback = self.cov
        self.cov = self._proposal_from([h for h in self.halves], fallback)
        if not self.inca:
            self.chain_covs = [self._proposal_from([self.halves[c]], self.chain_covs[c])
                               for c in range(self.n_chains)]
        self.rhat_history.append(self.rhat().tolist())

    def _reset_outliers(self, reports: dict) -> None:
        """Chains whose round sat ``outlier_nats`` below the best chain's level are moved to it.

        A chain stuck in a minor mode during burn-in inflates the pooled covariance with the distance
        between modes, and every chain's acceptance collapses (the outlier-chain correction of
        DREAM, Vrugt et al. 2009). The outlier's history is dropped from the pool; the driver moves
        its state to the source chain's and it continues on its own random stream.
        """
        if not self.outlier_nats > 0:
            return
        levels = [reports[c][1].level if reports[c][1] is not None else math.nan for c in range(self.n_chains)]
        if not all(math.isfinite(v) for v in levels):
            return
        src = int(np.argmax(levels))
        for c, v in enumerate(levels):
            if v < levels[src] - self.outlier_nats:
                self.halves[c] = []
                self.resets.append([self.rounds, c, src])

    def moved(self, round_index: int) -> dict[int, int]:
        """Chain -> source chain for the outliers moved when ``round_index`` was committed."""
        return {c: src for r, c, src in self.resets if r == round_index}

    def _window(self, halves: list[RoundStats]) -> list[RoundStats]:
        keep = max(1, self.rounds - self.rounds // 2)
        return halves[-2 * keep:]

    def _proposal_from(self, per_chain: list[list[RoundStats]], fallback: np.ndarray) -> np.ndarray:
        d = self.d
        n, _, C = pool_stats([s for h in per_chain for s in self._window(h)])
        if C is None or n <= d + 1 or not np.all(np.isfinite(C)):
            return fallback
        try:
            np.linalg.cholesky(C + 1e-300 * np.eye(d))
        except np.linalg.LinAlgError:
            return fallback
        scale = np.sqrt(np.diag(C))
        return (2.38**2 / d) * C + np.diag((1e-8 * scale) ** 2)

    def jump(self, weight: float, df: float) -> Jump | None:
        """The independence half of the proposal (:class:`~ardcore.sampling.proposal.Jump`), fitted to the pooled latter
        half of every chain's rounds: their mean and covariance as the t's centre and scale. None before
        there are enough draws for a covariance (or with ``weight`` 0)."""
        if not weight > 0 or self.rounds == 0 or not all(self.halves):
            return None
        n, mean, C = pool_stats([s for h in self.halves for s in self._window(h)])
        if C is None or n <= 10 * self.d or not np.all(np.isfinite(C)):
            return None
        try:
            np.linalg.cholesky(C)
        except np.linalg.LinAlgError:
            return None
        return Jump(mean, C, float(weight), float(df))

    # -- driver side
    @property
    def best_lp(self) -> float:
        """The highest ln posterior any chain has reported (-inf before the first round)."""
        return float(self.best[1]) if self.best else -math.inf

    def rhat(self) -> np.ndarray:
        """Split R-hat per parameter over the latter half of the committed rounds."""
        if self.rounds == 0 or not all(self.halves):
            return np.full(self.d, np.inf)  # a chain just moved has no history yet
        seqs = []
        for h in self.halves:
            w = self._window(h)
            k = len(w) // 2
            seqs += [pool_stats(w[:k]), pool_stats(w[k:])]
        return rhat_from_stats([(n, m, c) for n, m, c in seqs])

    def converged(self) -> bool:
        return self.rounds >= self.min_rounds and bool(np.all(self.rhat() < self.rhat_threshold))

    def to_dict(self) -> dict:
        enc = lambda s: {"n": s.n, "mean": s.mean.tolist(), "scatter": s.scatter.tolist()}  # noqa: E731
        return {
            "n_chains": self.n_chains, "d": self.d, "inca": self.inca, "rhat_threshold": self.rhat_threshold,
            "min_rounds": self.min_rounds, "cov": self.cov.tolist(), "chain_covs": [c.tolist() for c in self.chain_covs],
            "halves": [[enc(s) for s in h] for h in self.halves], "rounds": self.rounds, "best": self.best,
            "rhat_history": self.rhat_history, "outlier_nats": self.outlier_nats, "resets": self.resets,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "AdaptationPool":
        p = cls(d["n_chains"], d["d"], np.array(d["cov"]), inca=d["inca"], rhat_threshold=d["rhat_threshold"],
                min_rounds=d["min_rounds"], outlier_nats=d.get("outlier_nats", 0.0))
        p.resets = [list(r) for r in d.get("resets", [])]
        p.chain_covs = [np.array(c) for c in d["chain_covs"]]
        p.halves = [[RoundStats(s["n"], np.array(s["mean"]), np.array(s["scatter"])) for s in h] for h in d["halves"]]
        p.rounds, p.best, p.rhat_history = d["rounds"], d["best"], d["rhat_history"]
        return p


def rhat_from_stats(seqs: list[tuple]) -> np.ndarray:
    """Gelman-Rubin R-hat from per-sequence (n, mean, covariance) statistics."""
    ns = np.array([s[0] for s in seqs], dtype=float)
    if len(seqs) < 2 or np.any(ns < 2) or any(s[2] is None for s in seqs):
        return np.full(seqs[0][1].size if seqs and seqs[0][1] is not None else 1, np.inf)
    h = ns.mean()
    means = np.array([s[1] for s in seqs])
    variances = np.array([np.diag(s[2]) for s in seqs])
    W = variances.mean(axis=0)
    B = h * means.var(axis=0, ddof=1)
    var = (h - 1) / h * W + B / h
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.sqrt(var / W)
    return np.where(W > 0, r, np.where(B > 0, np.inf, 1.0))


# --------------------------------------------------------------------------- diagnostics
def rhat(chains: Sequence[np.ndarray]) -> np.ndarray:
    """Split Brooks-Gelman-Rubin R-hat per parameter.

    Parameters
    ----------
    chains : sequence of ndarray, each (n, d)
        Equal-length samples of each chain; each is split in two halves.
    """
    n = min(c.shape[0] for c in chains)
    h = n // 2
    if h < 2:
        return np.full(chains[0].shape[1], np.inf)
    seqs = []
    for c in chains:
        c = c[-2 * h:]
        seqs += [c[:h], c[h:]]
    X = np.stack(seqs)  # (m, h, d)
    means = X.mean(axis=1)
    W = X.var(axis=1, ddof=1).mean(axis=0)
    B = h * means.var(axis=0, ddof=1)
    var = (h - 1) / h * W + B / h
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.sqrt(var / W)
    return np.where(W > 0, r, np.where(B > 0, np.inf, 1.0))


