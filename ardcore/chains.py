"""One chain's state and one round of DRAM (Haario et al. 2006), and how per-chain tasks are mapped.

Everything a chain carries between rounds is a :class:`ChainState` (plain numbers and lists,
JSON-serialisable, including the RNG state), and every unit of work is a module-level function of
picklable arguments, so rounds can run serially, on any ``concurrent.futures`` executor, or on Dask.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Callable, NamedTuple, Sequence

import numpy as np

from .errors import ArdflowError

@dataclass(frozen=True)
class Step:
    """Which step of a trial a batch of per-chain tasks is: ``kind`` is ``"start"`` (start optimisation),
    ``"burnin"`` (``index``: the 1-based round), ``"stationary"`` (``index``: the first draw of the round)
    or ``"cj"`` (Chib-Jeliazkov ordinates). Orchestrators route on it (burn-in tasks report to the trial's
    coordinator, stationary tasks write their draws) and name their tasks after it; plain maps ignore it."""

    kind: str
    index: int | None = None

    def __str__(self) -> str:
        return self.kind if self.index is None else f"{self.kind}-{self.index}"


Map = Callable[..., list]
"""``map_fn(func, items, step=Step(...)) -> list``: how independent per-chain tasks are run; item ``c``
belongs to chain ``c`` (see :class:`Step`)."""


def serial_map(func, items, step: Step | None = None):
    return [func(it) for it in items]


def executor_map(executor) -> Map:
    """Adapt a ``concurrent.futures`` executor to :data:`Map`."""
    return lambda func, items, step=None: list(executor.map(func, items))


class SamplerError(ArdflowError):
    """The sampler cannot proceed (e.g. no chain finds a finite posterior)."""


# --------------------------------------------------------------------------- state
@dataclass
class ChainState:
    """Everything one chain carries between rounds (serialisable)."""

    chain: int
    x: list
    lp: float
    ll: float
    rng: dict
    best_x: list
    best_lp: float
    best_ll: float
    n_prop: int = 0
    n_acc: int = 0
    n_dr: int = 0

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "ChainState":
        return cls(**d)

    def generator(self) -> np.random.Generator:
        g = np.random.Generator(np.random.PCG64())
        g.bit_generator.state = self.rng
        return g


@dataclass
class RoundStats:
    """Centred sufficient statistics of one round of one chain (for pooling)."""

    n: int
    mean: np.ndarray
    scatter: np.ndarray

    @staticmethod
    def of(samples: np.ndarray) -> "RoundStats":
        m = samples.mean(axis=0)
        c = samples - m
        return RoundStats(samples.shape[0], m, c.T @ c)


def pool_stats(stats: Sequence[RoundStats]) -> tuple[int, np.ndarray, np.ndarray]:
    """Combine centred statistics (parallel-variance formula). Returns n, mean, covariance."""
    n, mean, sc = 0, None, None
    for s in stats:
        if s.n == 0:
            continue
        if n == 0:
            n, mean, sc = s.n, s.mean.copy(), s.scatter.copy()
            continue
        tot = n + s.n
        d = s.mean - mean
        sc = sc + s.scatter + np.outer(d, d) * (n * s.n / tot)
        mean = mean + d * (s.n / tot)
        n = tot
    if n < 2:
        return n, mean, None
    return n, mean, sc / (n - 1)


class ChainReport(NamedTuple):
    """What a chain reports to the coordinator with each burn-in round."""

    x: list        # the best point the chain has visited
    lp: float      # its ln posterior
    ll: float      # its ln likelihood
    level: float = math.nan  # the mean ln posterior of the round's latter half (compared across chains)


@dataclass
class RoundResult:
    state: ChainState
    samples: np.ndarray
    lp: np.ndarray
    ll: np.ndarray
    accepted: int
    dr_accepted: int
    halves: tuple  # RoundStats of the first and second half of the round (split R-hat)
    evaluations: int = 0  # likelihood evaluations (a delayed-rejection second stage is one more)

    @property
    def best(self) -> ChainReport:
        """What a chain reports with its round (:class:`ChainReport`)."""
        h = self.lp.size // 2
        level = float(np.mean(self.lp[h:])) if self.lp.size else -math.inf
        return ChainReport(self.state.best_x, self.state.best_lp, self.state.best_ll, level)

    @property
    def stats(self) -> RoundStats:
        n, mean, cov = pool_stats(self.halves)
        sc = cov * (n - 1) if cov is not None else np.zeros((mean.size, mean.size))
        return RoundStats(n, mean, sc)


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


# --------------------------------------------------------------------------- one round
def run_round(target, state: ChainState, cov: np.ndarray, n: int, *, adaptive: bool,
              dr_scale: float = 0.1) -> RoundResult:
    """Advance one chain by ``n`` samples.

    Parameters
    ----------
    target : callable
        ``x -> (log_posterior, log_likelihood)``.
    state : ChainState
    cov : ndarray
        Proposal covariance for this round (fixed within the round).
    n : int
        Samples to draw.
    adaptive : bool
        Burn-in (delayed rejection on) or stationary (plain random-walk Metropolis).
    dr_scale : float
        The second-stage proposal covariance is ``dr_scale**2 * cov``.
    """
    rng = state.generator()
    x = np.array(state.x, dtype=float)
    lp, ll = state.lp, state.ll
    best_x, best_lp, best_ll = np.array(state.best_x), state.best_lp, state.best_ll
    d = x.size
    L = safe_cholesky(cov)
    S = np.empty((n, d))
    LP = np.empty(n)
    LL = np.empty(n)
    acc = dr = n_second = 0
    for i in range(n):
        z1 = rng.standard_normal(d)
        y1 = x + L @ z1
        lp1, ll1 = target(y1)
        log_a1 = lp1 - lp if lp1 > -math.inf else -math.inf
        if math.log(rng.random() + 1e-300) < log_a1:
            x, lp, ll = y1, lp1, ll1
            acc += 1
        elif adaptive and dr_scale > 0:
            z2 = rng.standard_normal(d)
            y2 = x + dr_scale * (L @ z2)
            lp2, ll2 = target(y2)
            n_second += 1
            if lp2 > -math.inf:
                # Delayed-rejection acceptance (Tierney & Mira 1999) for a symmetric second stage:
                # a2 = pi(y2) q1(y2->y1) (1 - a1(y2,y1)) / [pi(x) q1(x->y1) (1 - a1(x,y1))]
                w = z1 - dr_scale * z2  # L^{-1}(y1 - y2)
                log_q_ratio = -0.5 * (w @ w - z1 @ z1)
                a1_y2 = math.exp(min(0.0, lp1 - lp2)) if lp1 > -math.inf else 0.0
                a1_x = math.exp(min(0.0, log_a1)) if lp1 > -math.inf else 0.0
                if a1_y2 < 1.0:
                    log_a2 = (lp2 - lp) + log_q_ratio + math.log1p(-a1_y2) - math.log1p(-a1_x)
                    if math.log(rng.random() + 1e-300) < log_a2:
                        x, lp, ll = y2, lp2, ll2
                        dr += 1
        if lp > best_lp:
            best_x, best_lp, best_ll = x.copy(), lp, ll
        S[i], LP[i], LL[i] = x, lp, ll
    new = ChainState(state.chain, x.tolist(), float(lp), float(ll), rng.bit_generator.state,
                     best_x.tolist(), float(best_lp), float(best_ll),
                     state.n_prop + S.shape[0], state.n_acc + acc, state.n_dr + dr)
    h = max(1, S.shape[0] // 2)
    return RoundResult(new, S, LP, LL, acc, dr, (RoundStats.of(S[:h]), RoundStats.of(S[h:]) if S.shape[0] > h
                                                 else RoundStats.of(S[:h])), n + n_second)


def _round_task(args):
    target, state, cov, n, adaptive, dr_scale = args
    return run_round(target, state, cov, n, adaptive=adaptive, dr_scale=dr_scale)

