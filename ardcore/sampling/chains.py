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

from ..errors import ArdflowError
from .proposal import Jump, MixedProposal, safe_cholesky
from .transform import free_coordinates

@dataclass(frozen=True)
class Step:
    """Which step of a trial a batch of per-chain tasks is: ``kind`` is ``"start"`` (start optimisation),
    ``"warm"`` (a warm-started chain's first density),
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
    """``[func(it) for it in items]``, in this process one after another (``step`` ignored): the default
    :data:`Map`, and the loop's pool when it has one worker."""
    return [func(it) for it in items]


@dataclass(frozen=True)
class Batch:
    """Per-chain tasks a sans-IO generator waits for: ``func`` over ``items`` (item ``c`` belongs to chain
    ``c``) at ``step``. The generator yields it and is sent the list of results; whoever drives it decides
    where the tasks run (:func:`run` with a :data:`Map`, or an orchestrator's event loop)."""

    func: Callable
    items: list
    step: Step | None = None


def run(steps, map_fn: Map = serial_map):
    """Drive the generator ``steps`` to its return value: a :class:`Batch` it yields is answered with
    ``map_fn``; anything else it yields (a batch an orchestrator has already submitted) with its
    ``result()``, which blocks until the tasks are done. A task's error is raised inside ``steps`` where
    it waits, as a direct call would raise it."""
    answered = relay(steps, lambda item: map_fn(item.func, item.items, step=item.step) if isinstance(item, Batch)
                     else item.result())
    reply = None
    while True:
        try:
            reply = answered.send(reply)  # each answer goes straight back
        except StopIteration as done:
            return done.value


def relay(steps, answer):
    """A generator that yields ``answer(item)`` for each item the generator ``steps`` yields and sends
    ``steps`` what it is sent back (an error thrown into it is raised inside ``steps`` where it waits);
    returns what ``steps`` returns. How an orchestrator puts its own handle (e.g. submitted futures) in place
    of each :class:`Batch`."""
    reply, error = None, None
    while True:
        try:
            item = steps.throw(error) if error is not None else steps.send(reply)
        except StopIteration as done:
            return done.value
        reply, error = None, None
        try:
            reply = yield answer(item)
        except Exception as exc:  # noqa: BLE001 - raised inside ``steps`` where it waits
            error = exc


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
    free: dict | None = None

    def to_dict(self) -> dict:
        return asdict(self)

    def free_point(self, free) -> tuple[np.ndarray, float]:
        """The chain's point in the sampler's unconstrained coordinates (``free``, :mod:`.transform`) and its log
        posterior there, ``lp + ln|dx/dz|``: as the last round left them while the chain is still at that ``x``
        (``self.free``), else converted from ``x``. The conversion back and forth is not exact in the last
        bits, so a chain continued in another task, or resumed from a checkpoint, draws what it would have
        drawn in one."""
        if self.free is not None and self.free.get("x") == list(self.x):
            return np.array(self.free["z"], dtype=float), float(self.free["lpz"])
        x = np.array(self.x, dtype=float)
        return free.to_free(x), self.lp + free.log_jacobian(x)

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


# --------------------------------------------------------------------------- one round
def run_round(target, state: ChainState, cov: np.ndarray, n: int, *, adaptive: bool,
              dr_scale: float = 0.1, jump: Jump | None = None) -> RoundResult:
    """Advance one chain by ``n`` samples.

    Parameters
    ----------
    target : callable
        ``x -> (log_posterior, log_likelihood)``.
    state : ChainState
    cov : ndarray
        Proposal covariance for this round (fixed within the round), in the unconstrained coordinates of
        :mod:`.transform`.
    n : int
        Samples to draw.
    adaptive : bool
        Burn-in (delayed rejection on) or stationary (plain random-walk Metropolis).
    dr_scale : float
        The second-stage proposal covariance is ``dr_scale**2 * cov``.
    jump : Jump, optional
        Mix this independence proposal into every step (:class:`Jump`); delayed rejection is then off.
    """
    rng = state.generator()
    free = free_coordinates(target)
    x = np.array(state.x, dtype=float)
    lp, ll = state.lp, state.ll
    # the chain moves in unconstrained coordinates (:mod:`.transform`): lpz = lp + ln|dx/dz|
    z, lpz = state.free_point(free)
    best_x, best_lp, best_ll = np.array(state.best_x), state.best_lp, state.best_ll
    d = x.size
    L = safe_cholesky(cov)
    S = np.empty((n, d))
    Z = np.empty((n, d))
    LP = np.empty(n)
    LL = np.empty(n)
    acc = dr = n_second = 0

    def at(zy):
        y = free.from_free(zy)
        lpy, lly = target(y)
        return y, lpy, lly, (lpy + free.log_jacobian(y) if lpy > -math.inf else -math.inf)

    mix = MixedProposal(cov, jump) if jump is not None and jump.weight > 0 else None
    tz = None  # ln t(z) under the mixture's independence proposal, once the chain has moved to a proposal
    for i in range(n):
        if mix is not None:
            w1 = mix.draw(rng, z)
        else:
            z1 = rng.standard_normal(d)
            w1 = z + L @ z1
        y1, lp1, ll1, lpz1 = at(w1)
        # the mixture is not symmetric: its proposal ratio enters the acceptance
        ratio, t0, t1 = mix.ratio_and_t(w1, z, tz) if mix is not None and lpz1 > -math.inf else (0.0, tz, None)
        tz = t0
        log_a1 = (lpz1 - lpz + ratio) if lpz1 > -math.inf else -math.inf
        if math.log(rng.random() + 1e-300) < log_a1:
            x, lp, ll, lpz, z, tz = y1, lp1, ll1, lpz1, w1, t1
            acc += 1
        elif mix is None and adaptive and dr_scale > 0:
            z2 = rng.standard_normal(d)
            w2 = z + dr_scale * (L @ z2)
            y2, lp2, ll2, lpz2 = at(w2)
            n_second += 1
            if lpz2 > -math.inf:
                # Delayed-rejection acceptance (Tierney & Mira 1999) for a symmetric second stage:
                # a2 = pi(y2) q1(y2->y1) (1 - a1(y2,y1)) / [pi(x) q1(x->y1) (1 - a1(x,y1))]
                w = z1 - dr_scale * z2  # L^{-1}(y1 - y2)
                log_q_ratio = -0.5 * (w @ w - z1 @ z1)
                a1_y2 = math.exp(min(0.0, lpz1 - lpz2)) if lpz1 > -math.inf else 0.0
                a1_x = math.exp(min(0.0, log_a1)) if lpz1 > -math.inf else 0.0
                if a1_y2 < 1.0:
                    log_a2 = (lpz2 - lpz) + log_q_ratio + math.log1p(-a1_y2) - math.log1p(-a1_x)
                    if math.log(rng.random() + 1e-300) < log_a2:
                        x, lp, ll, lpz, z = y2, lp2, ll2, lpz2, w2
                        dr += 1
        if lp > best_lp:
            best_x, best_lp, best_ll = x.copy(), lp, ll
        S[i], Z[i], LP[i], LL[i] = x, z, lp, ll
    new = ChainState(state.chain, x.tolist(), float(lp), float(ll), rng.bit_generator.state,
                     best_x.tolist(), float(best_lp), float(best_ll),
                     state.n_prop + S.shape[0], state.n_acc + acc, state.n_dr + dr,
                     {"x": x.tolist(), "z": z.tolist(), "lpz": float(lpz)})
    # the halves' statistics (the pooled proposal, burn-in R-hat) are taken in the chain's coordinates z
    h = max(1, Z.shape[0] // 2)
    return RoundResult(new, S, LP, LL, acc, dr, (RoundStats.of(Z[:h]), RoundStats.of(Z[h:]) if Z.shape[0] > h
                                                 else RoundStats.of(Z[:h])), n + n_second)


def round_task(args):
    target, state, cov, n, adaptive, dr_scale, *rest = args
    return run_round(target, state, cov, n, adaptive=adaptive, dr_scale=dr_scale, jump=rest[0] if rest else None)

