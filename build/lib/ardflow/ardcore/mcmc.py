"""Parallel adaptive MCMC (method.md section 6).

DRAM (adaptive Metropolis + delayed rejection, Haario et al. 2006) on n_c
chains with inter-chain adaptation (INCA, Craiu et al. 2009): after every
round of W samples per chain, the proposal covariance is re-estimated from
the pooled recent history of **all** chains, phi_MAP is updated from all
chains, and the Brooks-Gelman-Rubin R-hat decides whether burn-in is over.
Then M stationary samples per chain are drawn by plain random-walk
Metropolis with the **fixed** final covariance (no adaptation, no delayed
rejection), which the Chib-Jeliazkov estimator needs.

Everything a chain carries between rounds is a :class:`ChainState` (plain
numbers and lists, JSON-serialisable, including the RNG state), and every
unit of work is a module-level function of picklable arguments, so rounds can
run serially, on any ``concurrent.futures`` executor, or on Dask.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Sequence

import numpy as np

from .errors import ArdflowError

Map = Callable[..., list]
"""``map_fn(func, items, label=...) -> list``: how independent per-chain tasks are run.

``label`` names the step (``"start"``, ``"burnin-r3"``, ``"stationary-d1000"``,
``"cj"``); item ``c`` belongs to chain ``c``. Orchestrators use it for task
keys and for streaming; plain maps ignore it."""


def serial_map(func, items, label: str = ""):
    return [func(it) for it in items]


def executor_map(executor) -> Map:
    """Adapt a ``concurrent.futures`` executor to :data:`Map`."""
    return lambda func, items, label="": list(executor.map(func, items))


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


@dataclass
class RoundResult:
    state: ChainState
    samples: np.ndarray
    lp: np.ndarray
    ll: np.ndarray
    accepted: int
    dr_accepted: int
    halves: tuple  # RoundStats of the first and second half of the round (split R-hat)

    @property
    def best(self) -> tuple:
        """What a chain reports with its round: best point, its ln posterior and ln L, and the mean
        ln posterior of the round's latter half (the level the coordinator compares across chains)."""
        h = self.lp.size // 2
        level = float(np.mean(self.lp[h:])) if self.lp.size else -math.inf
        return (self.state.best_x, self.state.best_lp, self.state.best_ll, level)

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
    acc = dr = 0
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
                                                 else RoundStats.of(S[:h])))


def _round_task(args):
    target, state, cov, n, adaptive, dr_scale = args
    return run_round(target, state, cov, n, adaptive=adaptive, dr_scale=dr_scale)


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
        self.pending.setdefault(round_index, {}).setdefault(chain, (tuple(halves), best))  # first report wins
        if round_index == self.rounds + 1 and len(self.pending[round_index]) == self.n_chains:
            self._commit(self.pending.pop(round_index))
            return True
        return False

    def _commit(self, reports: dict) -> None:
        for c in range(self.n_chains):
            halves, best = reports[c]
            self.halves[c].extend(halves)
            if best is not None and (self.best is None or best[1] > self.best[1]):
                self.best = (list(best[0]), float(best[1]), float(best[2]))
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
        levels = [reports[c][1][3] if reports[c][1] is not None and len(reports[c][1]) > 3 else math.nan
                  for c in range(self.n_chains)]
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

    # -- driver side
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


# --------------------------------------------------------------------------- starts
def _neg_lp(target, center, scale):
    def f(z):
        v = target(center + scale * z)[0]
        return -v if v > -math.inf else 1e300
    return f


def fd_hessian(f: Callable[[np.ndarray], float], x: np.ndarray, h: np.ndarray) -> np.ndarray:
    """Central finite-difference Hessian of ``f`` at ``x`` with steps ``h``."""
    d = x.size
    H = np.empty((d, d))
    f0 = f(x)
    E = np.diag(h)
    fp = [f(x + E[i]) for i in range(d)]
    fm = [f(x - E[i]) for i in range(d)]
    for i in range(d):
        H[i, i] = (fp[i] - 2 * f0 + fm[i]) / h[i] ** 2
        for j in range(i + 1, d):
            v = (f(x + E[i] + E[j]) - f(x + E[i] - E[j]) - f(x - E[i] + E[j]) + f(x - E[i] - E[j])) / (4 * h[i] * h[j])
            H[i, j] = H[j, i] = v
    return H


def local_mode(target, x0: np.ndarray, scale: np.ndarray, maxfev: int) -> tuple[np.ndarray, float]:
    """Nelder-Mead (in coordinates scaled by ``scale``) from ``x0``, restarted once."""
    from scipy.optimize import minimize

    f = _neg_lp(target, x0, scale)
    z = np.zeros(x0.size)
    best = f(z)
    for _ in range(2):
        simplex = np.vstack([z] + [z + 0.5 * e for e in np.eye(z.size)])
        r = minimize(f, z, method="Nelder-Mead",
                     options={"initial_simplex": simplex, "maxfev": maxfev // 2, "xatol": 1e-6, "fatol": 1e-8})
        if r.fun <= best:
            z, best = r.x, r.fun
    return x0 + scale * z, -best


def posterior_cov_estimate(target, x: np.ndarray, scale: np.ndarray) -> np.ndarray | None:
    """Inverse of the finite-difference Hessian of -log posterior (None if not positive definite)."""
    f = lambda v: -target(v)[0]  # noqa: E731
    h = 1e-3 * scale
    for _ in range(2):
        H = fd_hessian(f, x, h)
        if not np.all(np.isfinite(H)):
            return None
        try:
            C = np.linalg.inv(H)
            np.linalg.cholesky(C)
        except np.linalg.LinAlgError:
            return None
        h = 0.05 * np.sqrt(np.diag(C))  # refine the steps to the posterior's own scale
    return 0.5 * (C + C.T)


class _Counted:
    """A target that counts its calls (likelihood evaluations), for the cost figures."""

    def __init__(self, target):
        self.target, self.calls = target, 0

    def __call__(self, x):
        self.calls += 1
        return self.target(x)

    def __getattr__(self, name):
        return getattr(self.target, name)


def _start_task(args):
    target, x0, scale, maxfev, seed, overdispersion = args
    target = _Counted(target)
    rng = np.random.default_rng(seed)
    xm, lpm = local_mode(target, x0, scale, maxfev)
    C = posterior_cov_estimate(target, xm, scale)
    if C is None:
        C = np.diag((0.01 * scale) ** 2)
    L = safe_cholesky(C)
    for k in range(30):
        # overdispersed start around the local mode, so R-hat is meaningful
        x = xm + (overdispersion * 0.8**k) * (L @ rng.standard_normal(xm.size))
        lp, ll = target(x)
        if lp > -math.inf:
            break
    else:
        x = xm
        lp, ll = target(x)
    return x, lp, ll, xm, lpm, C, target.calls


# --------------------------------------------------------------------------- settings and results
@dataclass
class SamplerConfig:
    """Sampler settings (the study spec's ``sampler`` section maps onto this).

    Attributes
    ----------
    n_chains : int
    round_size : int
        W, samples per chain per round.
    min_burnin_rounds, max_burnin_rounds : int
    rhat_threshold : float
    n_stationary : int
        M, stationary samples per chain.
    n_proposal : int
        J, proposal draws at phi* per chain for Chib-Jeliazkov.
    dr_scale : float
    start_maxfev : int
        Budget of the local optimisation that places each chain's start.
    overdispersion : float
        Starts are drawn at this many posterior standard deviations around each local mode.
    inca : bool
        Pool the adaptation over all chains (INCA); False adapts each chain on its own history
        (for comparison only).
    outlier_nats : float
        During burn-in, a chain whose mean ln posterior over a round's latter half lies more than
        this many nats below the best chain's is moved to that chain's position (0 turns it off).
        Within one mode the round means of the chains differ by well under a nat for the
        models here; 10 nats is a chain stuck in a minor mode.
    """

    n_chains: int = 4
    round_size: int = 500
    min_burnin_rounds: int = 4
    max_burnin_rounds: int = 60
    rhat_threshold: float = 1.1
    n_stationary: int = 5000
    n_proposal: int = 5000
    dr_scale: float = 0.1
    start_maxfev: int = 3000
    overdispersion: float = 2.0
    inca: bool = True
    outlier_nats: float = 10.0


@dataclass
class SamplerResult:
    """Output of :func:`sample`: stationary samples, phi*, diagnostics and the state to warm-start from."""

    names: list
    samples: np.ndarray          # (n_chains, M, d)
    lp: np.ndarray               # (n_chains, M)
    ll: np.ndarray               # (n_chains, M)
    phi_star: np.ndarray
    lp_star: float
    ll_star: float
    proposal_cov: np.ndarray
    states: list                 # ChainState
    rhat: np.ndarray
    rhat_history: list
    burnin_rounds: int
    converged: bool
    acceptance: float
    burnin_acceptance: float
    n_evaluations: int
    warnings: list = field(default_factory=list)


def initial_scale(prior) -> np.ndarray:
    """A length scale per parameter for optimisation steps and fallbacks."""
    out = []
    for p in prior.priors:
        try:
            s = (p.quantile(0.75) - p.quantile(0.25)) / 1.349
        except ValueError:
            s = 1.0
        out.append(s if np.isfinite(s) and s > 0 else 1.0)
    return np.minimum(np.array(out), 1e3)


def initial_points(prior, n: int, rng: np.random.Generator, start_sd: dict | None = None) -> np.ndarray:
    """Dispersed initial points: essential parameters from the central 80 % of their priors,
    ARD parameters near 0 (their prior bulk is uninformative)."""
    pts = np.zeros((n, len(prior.priors)))
    for j, (name, p) in enumerate(zip(prior.names, prior.priors)):
        if p.kind == "ard" or p.kind == "flat":
            sd = (start_sd or {}).get(name, 0.0)
            pts[:, j] = sd * rng.standard_normal(n)
        else:
            pts[:, j] = [p.quantile(q) for q in rng.uniform(0.1, 0.9, n)]
    return pts


def run_burnin(target, states: list, pool: AdaptationPool, config: SamplerConfig, map_fn: Map = serial_map, *,
               progress=None, cancel=None, checkpoint=None) -> tuple[list, int, int, int]:
    """Burn-in rounds until R-hat is below the threshold or the round budget is spent.

    Returns the chain states, accepted and proposed counts, and likelihood evaluations.
    """
    b_acc = b_n = n_eval = 0
    nc = len(states)
    while pool.rounds < config.max_burnin_rounds:
        if cancel is not None and cancel():
            raise Cancelled("cancelled during burn-in")
        rnd = pool.rounds + 1
        results = map_fn(_round_task, [(target, s, pool.proposal(c), config.round_size, True, config.dr_scale)
                                       for c, s in enumerate(states)], label=f"burnin-r{rnd}")
        states = [q.state for q in results]
        for c, q in enumerate(results):
            pool.report(c, rnd, q.halves, q.best)
        moved = pool.moved(rnd)
        for c, src in moved.items():
            s, o = states[c], states[src]
            s.x, s.lp, s.ll = list(o.x), o.lp, o.ll
        if moved and progress:
            progress({"stage": "note", "message": f"burn-in round {rnd}: chains {sorted(moved)} sat over "
                      f"{config.outlier_nats:g} nats below chain {max(moved.values())}; moved to it"})
        n_eval += sum(q.samples.shape[0] + (q.samples.shape[0] - q.accepted) for q in results)
        acc = sum(q.accepted + q.dr_accepted for q in results)
        n = sum(q.samples.shape[0] for q in results)
        b_acc, b_n = b_acc + acc, b_n + n
        if progress:
            progress({"stage": "burnin", "round": pool.rounds, "rhat": pool.rhat().tolist(),
                      "best_lp": pool.best[1] if pool.best else -math.inf, "acceptance": acc / max(1, n)})
        if checkpoint:
            checkpoint({"stage": "burnin", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
                        "counters": [b_acc, b_n, n_eval]})
        if pool.converged():
            break
    assert len(states) == nc
    return states, b_acc, b_n, n_eval


def initial_states(target, config: SamplerConfig, *, seed: int, map_fn: Map = serial_map,
                   warm: SamplerResult | None = None, starts: np.ndarray | None = None) -> tuple[list, np.ndarray, int]:
    """Chain states, the first proposal covariance (cold, warm or explicit starts) and the likelihood
    evaluations that took."""
    names = list(target.names)
    d = len(names)
    nc = config.n_chains
    child = np.random.SeedSequence(seed).spawn(nc + 1)
    scale = initial_scale(target.prior)
    n_eval = nc
    if warm is not None:
        idx = {n: i for i, n in enumerate(warm.names)}
        states = []
        for c in range(nc):
            ws = warm.states[c % len(warm.states)]
            x = np.array([ws.x[idx[n]] if n in idx else 0.0 for n in names])
            lp, ll = target(x)
            if not lp > -math.inf:
                x = np.array([warm.phi_star[idx[n]] if n in idx else 0.0 for n in names])
                lp, ll = target(x)
            states.append(ChainState(c, x.tolist(), lp, ll, np.random.PCG64(child[c]).state, x.tolist(), lp, ll))
        sel = [idx.get(n) for n in names]
        cov = np.diag((0.01 * scale) ** 2)
        for i, a in enumerate(sel):
            for j, b in enumerate(sel):
                if a is not None and b is not None:
                    cov[i, j] = warm.proposal_cov[a, b]
        for i, a in enumerate(sel):
            if a is None:  # a new parameter: a small step, not the prior's width
                cov[i, i] = (0.01 * scale[i]) ** 2
    elif starts is None:
        pts = initial_points(target.prior, nc, np.random.default_rng(child[nc]))
        tasks = [(target, pts[c], scale, config.start_maxfev, child[c].generate_state(1)[0] + c,
                  config.overdispersion) for c in range(nc)]
        res = map_fn(_start_task, tasks, label="start")
        n_eval = sum(int(r[6]) for r in res)
        cov = (2.38**2 / d) * np.mean([r[5] for r in res], axis=0)
        states = []
        for c, r in enumerate(res):
            x, lp, ll, xm, lpm, *_ = r
            # phi* comes from what the chains visit, never from the start optimiser alone (method.md 4):
            # a spike it found and no chain returns to would make every chain's posterior ordinate ~0
            states.append(ChainState(c, list(map(float, x)), float(lp), float(ll),
                                     np.random.PCG64(child[c]).state, list(map(float, x)), float(lp), float(ll)))
    else:
        states = []
        for c in range(nc):
            x = np.asarray(starts[c], dtype=float)
            lp, ll = target(x)
            states.append(ChainState(c, x.tolist(), lp, ll, np.random.PCG64(child[c]).state, x.tolist(), lp, ll))
        cov = np.diag((0.1 * scale) ** 2)
    if not any(s.lp > -math.inf for s in states):
        raise SamplerError("no chain could start at a point of finite posterior density: "
                           "check the priors against the data and model")
    for s in states:
        if not s.lp > -math.inf:
            good = max(states, key=lambda q: q.lp)
            s.x, s.lp, s.ll = list(good.x), good.lp, good.ll
    return states, cov, n_eval


def sample(target, config: SamplerConfig, *, seed: int, map_fn: Map = serial_map,
           warm: SamplerResult | None = None, starts: np.ndarray | None = None,
           progress: Callable[[dict], None] | None = None,
           cancel: Callable[[], bool] | None = None,
           pool_factory: Callable[..., AdaptationPool] | None = None,
           checkpoint: Callable[[dict], None] | None = None,
           resume: dict | None = None) -> SamplerResult:
    """Run parallel DRAM with INCA, then the fixed-proposal stationary stage.

    Parameters
    ----------
    target : callable
        ``x -> (log_posterior, log_likelihood)`` with ``names`` and ``prior``.
    config : SamplerConfig
    seed : int
        Every random number derives from it (chain c uses an independent stream).
    map_fn : callable
        Runs the per-chain tasks of a step (serial by default); see :data:`Map`.
    warm : SamplerResult, optional
        Warm start: chains continue from these states (positions mapped by
        parameter name; parameters absent from ``warm`` start at 0) with its
        proposal covariance.
    starts : ndarray, optional
        Explicit initial points (n_chains, d), skipping the start optimisation.
    progress : callable, optional
        Called after every round with a dict (stage, round, rhat, best log posterior, acceptance).
    cancel : callable, optional
        Checked between rounds; when it returns True, :class:`Cancelled` is raised.
    pool_factory : callable, optional
        ``pool_factory(state_dict) -> pool`` for the INCA coordinator (default: an
        in-process :class:`AdaptationPool` rebuilt from the dict); orchestrators
        return a proxy to a remote actor.
    checkpoint : callable, optional
        Called with a JSON-able dict after every round (stage, chain states,
        coordinator state, counters); together with the stationary samples
        written so far it is enough to resume.
    resume : dict, optional
        A checkpoint dict to continue from; for the stationary stage it must also
        hold ``samples``, ``lp`` and ``ll`` arrays of the draws done so far.
    """
    names = list(target.names)
    d = len(names)
    nc = config.n_chains
    warnings: list[str] = []
    factory = pool_factory or AdaptationPool.from_dict
    if resume is None:
        states, cov, n_start = initial_states(target, config, seed=seed, map_fn=map_fn, warm=warm, starts=starts)
        pool0 = AdaptationPool(nc, d, cov, inca=config.inca, rhat_threshold=config.rhat_threshold,
                               min_rounds=config.min_burnin_rounds, outlier_nats=config.outlier_nats)
        pool = factory(pool0.to_dict())
        stage, counters = "burnin", [0, 0, n_start]
        if checkpoint:
            checkpoint({"stage": "burnin", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
                        "counters": counters})
    else:
        states = [ChainState.from_dict(q) for q in resume["states"]]
        pool = factory(resume["pool"])
        stage, counters = resume["stage"], list(resume.get("counters", [0, 0, 0]))

    # ---- burn-in: DRAM rounds, the pool is the INCA coordinator
    if stage == "burnin":
        states, b_acc, b_n, n_b = run_burnin(target, states, pool, config, map_fn, progress=progress, cancel=cancel,
                                             checkpoint=checkpoint)
        counters = [counters[0] + b_acc, counters[1] + b_n, counters[2] + n_b]
    b_acc, b_n, n_eval = counters
    rounds, converged, r, cov = pool.rounds, pool.converged(), pool.rhat(), pool.cov
    if not converged:
        warnings.append(f"burn-in did not reach R-hat < {config.rhat_threshold} in {rounds} rounds "
                        f"(max R-hat {np.max(r):.3g} for {names[int(np.argmax(r))]}); results may be unreliable")

    # ---- stationary stage: fixed proposal, plain RWM
    M = config.n_stationary
    samples = np.full((nc, M, d), np.nan)
    lps = np.full((nc, M), np.nan)
    lls = np.full((nc, M), np.nan)
    done, s_acc = 0, 0
    if resume is not None and resume["stage"] == "stationary":
        done, s_acc = int(resume["done"]), int(resume["s_acc"])
        samples[:, :done], lps[:, :done], lls[:, :done] = (resume["samples"][:, :done], resume["lp"][:, :done],
                                                           resume["ll"][:, :done])
    while done < M:
        if cancel is not None and cancel():
            raise Cancelled("cancelled during stationary sampling")
        n = min(config.round_size, M - done)
        results = map_fn(_round_task, [(target, s, cov, n, False, 0.0) for s in states], label=f"stationary-d{done}")
        states = [q.state for q in results]
        n_eval += nc * n
        for c, q in enumerate(results):
            samples[c, done:done + n], lps[c, done:done + n], lls[c, done:done + n] = q.samples, q.lp, q.ll
        s_acc += sum(q.accepted for q in results)
        done += n
        if progress:
            progress({"stage": "stationary", "round": done // config.round_size, "done": done, "of": M,
                      "acceptance": sum(q.accepted for q in results) / (nc * n)})
        if checkpoint:
            checkpoint({"stage": "stationary", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
                        "counters": [b_acc, b_n, n_eval], "done": done, "s_acc": s_acc})
    best = max(states, key=lambda q: q.best_lp)
    r_final = rhat(list(samples))
    if np.any(r_final > config.rhat_threshold):
        warnings.append(f"stationary samples: max R-hat {np.max(r_final):.3g} ({names[int(np.argmax(r_final))]}) "
                        f"exceeds {config.rhat_threshold}")
    return SamplerResult(
        names=names, samples=samples, lp=lps, ll=lls,
        phi_star=np.array(best.best_x), lp_star=best.best_lp, ll_star=best.best_ll,
        proposal_cov=cov, states=states, rhat=r_final, rhat_history=list(pool.rhat_history),
        burnin_rounds=rounds, converged=converged,
        acceptance=s_acc / max(1, nc * M), burnin_acceptance=b_acc / max(1, b_n),
        n_evaluations=n_eval, warnings=warnings)


class Cancelled(ArdflowError):
    """A run was cancelled cooperatively."""
