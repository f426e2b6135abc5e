"""Parallel adaptive MCMC (method.md section 6).

DRAM (adaptive Metropolis + delayed rejection, Haario et al. 2006) on n_c
chains with inter-chain adaptation (INCA, Craiu et al. 2009): after every
round of W samples per chain, the proposal covariance is re-estimated from
the pooled recent history of **all** chains, phi_MAP is updated from all
chains, and the Brooks-Gelman-Rubin R-hat decides whether burn-in is over.
Then M stationary samples per chain are drawn by plain random-walk
Metropolis with the **fixed** final covariance (no adaptation, no delayed
rejection), which the Chib-Jeliazkov estimator needs.

The pieces live in :mod:`.chains` (chain state, one DRAM round, maps),
:mod:`.adaptation` (the INCA coordinator, R-hat) and :mod:`.starts` (start
points and the first covariance); this module holds the settings, the result
and the driver (:func:`sample`), and re-exports the pieces.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Generator

import numpy as np

from .adaptation import AdaptationPool, rhat, rhat_from_stats  # noqa: F401
from .chains import (  # noqa: F401
    ChainState,
    Map,
    RoundResult,
    RoundStats,
    SamplerError,
    Step,
    _round_task,
    executor_map,
    pool_stats,
    run_round,
    safe_cholesky,
    serial_map,
)
from .errors import ArdflowError
from .events import BurninRound, Note, ProgressEvent, StationaryRound
from .sampling import SamplerConfig, SamplerResult  # noqa: F401
from .starts import (  # noqa: F401
    _Counted,
    _start_task,
    fd_hessian,
    initial_points,
    initial_scale,
    initial_states,
    local_mode,
    posterior_cov_estimate,
)


@dataclass(frozen=True)
class RoundEvent:
    """One round of the sampler, as :func:`iter_sample` yields it: the stage (``"burnin"`` or
    ``"stationary"``), the round, what it reports (the :mod:`ardcore.events` progress callbacks get: a burn-in
    round's R-hat, best ln posterior and acceptance, a note when chains were moved) and the JSON-able state to
    resume from (chain states, the coordinator, counters; a stationary round's draws are in the caller's store)."""

    stage: str
    round: int
    reports: tuple
    checkpoint: dict


def burnin_rounds(target, states: list, pool: AdaptationPool, config: SamplerConfig, map_fn: Map = serial_map,
                  counters: tuple = (0, 0, 0), dr_scale: float | None = None
                  ) -> Generator[RoundEvent, None, tuple[list, int, int, int]]:
    """Burn-in rounds until R-hat is below the threshold or the round budget is spent, one event each.

    Returns the chain states, accepted and proposed counts, and likelihood evaluations (``counters``: those
    of the stages before, for the checkpoints). ``dr_scale`` (default ``config.dr_scale``; 0 for a warm
    start, see :class:`SamplerConfig`) is the delayed-rejection second stage of the first
    ``config.dr_rounds`` rounds.
    """
    dr = config.dr_scale if dr_scale is None else dr_scale
    b_acc = b_n = n_eval = 0
    while pool.rounds < config.max_burnin_rounds:
        rnd = pool.rounds + 1
        dr_r = dr if rnd <= config.dr_rounds else 0.0
        results = map_fn(_round_task, [(target, s, pool.proposal(c), config.round_size, True, dr_r)
                                       for c, s in enumerate(states)], step=Step("burnin", rnd))
        states = [q.state for q in results]
        for c, q in enumerate(results):
            pool.report(c, rnd, q.halves, q.best)
        moved = pool.moved(rnd)
        for c, src in moved.items():
            s, o = states[c], states[src]
            s.x, s.lp, s.ll = list(o.x), o.lp, o.ll
        reports = [Note(f"burn-in round {rnd}: chains {sorted(moved)} sat over {config.outlier_nats:g} nats "
                        f"below chain {max(moved.values())}; moved to it")] if moved else []
        n_eval += sum(q.evaluations for q in results)
        acc = sum(q.accepted + q.dr_accepted for q in results)
        n = sum(q.samples.shape[0] for q in results)
        b_acc, b_n = b_acc + acc, b_n + n
        reports.append(BurninRound(pool.rounds, pool.rhat().tolist(), pool.best_lp, acc / max(1, n)))
        yield RoundEvent("burnin", pool.rounds, tuple(reports), {
            "stage": "burnin", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
            "counters": [counters[0] + b_acc, counters[1] + b_n, counters[2] + n_eval], "dr_scale": dr})
        if pool.converged():
            break
    return states, b_acc, b_n, n_eval


def stationary_rounds(target, states: list, cov: np.ndarray, config: SamplerConfig, map_fn: Map = serial_map, *,
                      pool: AdaptationPool, counters: list, resume: dict | None = None) -> Generator:
    """The stationary stage: M draws per chain by random-walk Metropolis with the fixed covariance ``cov``,
    one event per round.

    When the M draws' split R-hat exceeds ``config.rhat_threshold`` they are counted as more burn-in and
    drawn again from where the chains are (at most ``config.stationary_restarts`` times); each pass writes
    the same M slots, and its rounds are numbered on (:class:`Step` index ``pass * M + draw``, so no task of
    a later pass shares a key with one of an earlier pass).

    Returns samples (n_chains, M, d), their log posteriors and log likelihoods, the chain states, the
    accepted count and the running count of likelihood evaluations (``counters``: accepted, proposed and
    evaluated so far). ``resume`` (a checkpoint of this stage with the draws so far) continues it.
    """
    nc, d, M = len(states), len(target.names), config.n_stationary
    samples = np.full((nc, M, d), np.nan)
    lps = np.full((nc, M), np.nan)
    lls = np.full((nc, M), np.nan)
    done, s_acc, n_eval, passes = 0, 0, counters[2], 0
    if resume is not None and resume["stage"] == "stationary":
        done, s_acc, passes = int(resume["done"]), int(resume["s_acc"]), int(resume.get("pass", 0))
        samples[:, :done], lps[:, :done], lls[:, :done] = (resume["samples"][:, :done], resume["lp"][:, :done],
                                                           resume["ll"][:, :done])
    while True:
        while done < M:
            n = min(config.round_size, M - done)
            results = map_fn(_round_task, [(target, s, cov, n, False, 0.0) for s in states],
                             step=Step("stationary", passes * M + done))
            states = [q.state for q in results]
            n_eval += sum(q.evaluations for q in results)
            for c, q in enumerate(results):
                samples[c, done:done + n], lps[c, done:done + n], lls[c, done:done + n] = q.samples, q.lp, q.ll
            s_acc += sum(q.accepted for q in results)
            done += n
            yield RoundEvent("stationary", done // config.round_size, (
                StationaryRound(done // config.round_size, done, M, sum(q.accepted for q in results) / (nc * n)),), {
                "stage": "stationary", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
                "counters": [counters[0], counters[1], n_eval], "done": done, "s_acc": s_acc, "pass": passes})
        r = rhat(list(samples))
        if passes >= config.stationary_restarts or not np.any(r > config.rhat_threshold):
            return samples, lps, lls, states, s_acc, n_eval
        passes, done, s_acc = passes + 1, 0, 0
        worst = int(np.argmax(r))
        note = Note(f"stationary draws: R-hat {r[worst]:.3g} for {target.names[worst]} over {M} draws per chain; "
                    f"counted as burn-in and drawn again (pass {passes + 1} of at most "
                    f"{config.stationary_restarts + 1})")
        yield RoundEvent("stationary", 0, (note,), {
            "stage": "stationary", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
            "counters": [counters[0], counters[1], n_eval], "done": 0, "s_acc": 0, "pass": passes})


def _begin(target, config: SamplerConfig, seed: int, map_fn: Map, warm, starts, factory, resume):
    """Chain states, the INCA coordinator, the stage and the counters to start (or resume) from."""
    if resume is not None:
        return ([ChainState.from_dict(q) for q in resume["states"]], factory(resume["pool"]), resume["stage"],
                list(resume.get("counters", [0, 0, 0])))
    states, cov, n_start = initial_states(target, config, seed=seed, map_fn=map_fn, warm=warm, starts=starts)
    pool0 = AdaptationPool(config.n_chains, len(target.names), cov, inca=config.inca,
                           rhat_threshold=config.burnin_rhat, min_rounds=config.min_burnin_rounds,
                           outlier_nats=config.outlier_nats)
    return states, factory(pool0.to_dict()), "burnin", [0, 0, n_start]


def iter_sample(target, config: SamplerConfig, *, seed: int, map_fn: Map = serial_map,
                warm: SamplerResult | None = None, starts: np.ndarray | None = None,
                pool_factory: Callable[..., AdaptationPool] | None = None,
                resume: dict | None = None) -> Generator[RoundEvent, None, SamplerResult]:
    """Parallel DRAM with INCA, then the fixed-proposal stationary stage, as a generator: one
    :class:`RoundEvent` per round (a fresh start first yields the state it starts from); its return value
    (``StopIteration.value``) is the :class:`SamplerResult`. Arguments as :func:`sample`."""
    names = list(target.names)
    warnings: list[str] = []
    states, pool, stage, counters = _begin(target, config, seed, map_fn, warm, starts,
                                           pool_factory or AdaptationPool.from_dict, resume)
    # a warm start's first proposal is the previous posterior's covariance: no delayed rejection (SamplerConfig)
    dr = (config.dr_scale if warm is None or config.warm_dr else 0.0) if resume is None \
        else float(resume.get("dr_scale", config.dr_scale))
    if resume is None:
        yield RoundEvent("burnin", 0, (), {"stage": "burnin", "states": [q.to_dict() for q in states],
                                           "pool": pool.to_dict(), "counters": list(counters), "dr_scale": dr})
    # ---- burn-in: DRAM rounds, the pool is the INCA coordinator
    if stage == "burnin":
        states, b_acc, b_n, n_b = yield from burnin_rounds(target, states, pool, config, map_fn, tuple(counters), dr)
        counters = [counters[0] + b_acc, counters[1] + b_n, counters[2] + n_b]
    b_acc, b_n, _ = counters
    rounds, converged, r, cov = pool.rounds, pool.converged(), pool.rhat(), pool.cov
    # ---- stationary stage: fixed proposal, plain RWM
    samples, lps, lls, states, s_acc, n_eval = yield from stationary_rounds(
        target, states, cov, config, map_fn, pool=pool, counters=counters, resume=resume)
    best = max(states, key=lambda q: q.best_lp)
    r_final = rhat(list(samples))
    if np.any(r_final > config.rhat_threshold):
        # the stationary draws are what the results rest on: a short burn-in whose draws then pass is no concern
        if not converged:
            warnings.append(f"burn-in did not reach R-hat < {config.burnin_rhat} in {rounds} rounds "
                            f"(max R-hat {np.max(r):.3g} for {names[int(np.argmax(r))]})")
        warnings.append(f"stationary samples: max R-hat {np.max(r_final):.3g} ({names[int(np.argmax(r_final))]}) "
                        f"exceeds {config.rhat_threshold}")
    return SamplerResult(
        names=names, samples=samples, lp=lps, ll=lls,
        phi_star=np.array(best.best_x), lp_star=best.best_lp, ll_star=best.best_ll,
        proposal_cov=cov, states=states, rhat=r_final, rhat_history=list(pool.rhat_history),
        burnin_rounds=rounds, converged=converged,
        acceptance=s_acc / max(1, config.n_chains * config.n_stationary), burnin_acceptance=b_acc / max(1, b_n),
        n_evaluations=n_eval, warnings=warnings)


def sample(target, config: SamplerConfig, *, seed: int, map_fn: Map = serial_map,
           warm: SamplerResult | None = None, starts: np.ndarray | None = None,
           progress: Callable[[ProgressEvent], None] | None = None,
           cancel: Callable[[], bool] | None = None,
           pool_factory: Callable[..., AdaptationPool] | None = None,
           checkpoint: Callable[[dict], None] | None = None,
           resume: dict | None = None) -> SamplerResult:
    """Run parallel DRAM with INCA, then the fixed-proposal stationary stage: :func:`iter_sample` driven
    with callbacks.

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
        Warm start: chains continue from these states (positions mapped by parameter name; a parameter
        now fixed conditions them, see :func:`~ardcore.starts.warm_positions`) with its proposal covariance.
    starts : ndarray, optional
        Explicit initial points (n_chains, d), skipping the start optimisation.
    progress : callable, optional
        Called with each of a round's reports (:mod:`ardcore.events`: a burn-in round's R-hat, best ln
        posterior and acceptance; a stationary round's draws; a note).
    cancel : callable, optional
        Checked between rounds; when it returns True, :class:`Cancelled` is raised.
    pool_factory : callable, optional
        ``pool_factory(state_dict) -> pool`` for the INCA coordinator (default: an in-process
        :class:`AdaptationPool` rebuilt from the dict); orchestrators return a proxy to a remote actor.
    checkpoint : callable, optional
        Called with each round's JSON-able state (stage, chain states, coordinator state, counters);
        together with the stationary samples written so far it is enough to resume.
    resume : dict, optional
        A checkpoint dict to continue from; for the stationary stage it must also hold ``samples``, ``lp``
        and ``ll`` arrays of the draws done so far.
    """
    rounds = iter_sample(target, config, seed=seed, map_fn=map_fn, warm=warm, starts=starts,
                         pool_factory=pool_factory, resume=resume)
    stage = resume["stage"] if resume is not None else "burnin"
    while True:
        if cancel is not None and cancel():
            rounds.close()
            raise Cancelled("cancelled during " + ("burn-in" if stage == "burnin" else "stationary sampling"))
        try:
            ev = next(rounds)
        except StopIteration as done:
            return done.value
        stage = ev.stage
        for rep in ev.reports if progress else ():
            progress(rep)
        if checkpoint:
            checkpoint(ev.checkpoint)


class Cancelled(ArdflowError):
    """A run was cancelled cooperatively."""
