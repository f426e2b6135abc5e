"""The sampler's driver: parallel adaptive MCMC (docs/method.md, section 5).

DRAM (adaptive Metropolis + delayed rejection, Haario et al. 2006) on n_c
chains with inter-chain adaptation (INCA, Craiu et al. 2009): after every
round of W samples per chain, the proposal covariance is re-estimated from
the pooled recent history of **all** chains, phi_MAP is updated from all
chains, and the Brooks-Gelman-Rubin R-hat decides whether burn-in is over.
Then M stationary samples per chain are drawn by plain random-walk
Metropolis with the **fixed** final covariance (no adaptation, no delayed
rejection), which the Chib-Jeliazkov estimator needs.

The pieces live beside it in this package: :mod:`.chains` (chain state, one DRAM round, maps),
:mod:`.adaptation` (the INCA coordinator, R-hat), :mod:`.starts` (start points and the first
covariance), :mod:`.config` (settings and result); this module holds the driver
(:func:`iter_sample`, :func:`sample`).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, Generator

import numpy as np

from .adaptation import AdaptationPool
from .chains import (
    ChainReport,
    ChainState,
    Map,
    RoundStats,
    SamplerError,
    Step,
    Batch,
    round_task,
    run,
    serial_map,
)
from ..errors import ArdflowError
from .diagnostics import Quality, convergence
from ..events import BurninRound, Note, ProgressEvent, StationaryRound
from .config import SamplerConfig, SamplerResult
from .transform import free_coordinates
from .starts import iter_initial_states


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


@dataclass(frozen=True)
class Start:
    """Where a run's chains start: fresh (the start optimisation), from explicit ``points`` (n_chains, d), warm
    from an earlier result (positions mapped by parameter name, its proposal covariance), or ``resume``: a
    checkpoint dict (:func:`sample`)."""

    warm: SamplerResult | None = None
    points: np.ndarray | None = None
    resume: dict | None = None


@dataclass(frozen=True)
class Runtime:
    """How a run executes and reports, each optional: ``map_fn`` runs a step's per-chain tasks (serial by
    default; :data:`Map`), ``pool_factory(state_dict)`` makes the INCA coordinator (an orchestrator returns a
    proxy to a remote actor), ``progress`` receives each round's reports, ``cancel`` is asked between rounds,
    ``checkpoint`` receives each round's JSON-able state."""

    map_fn: Map = serial_map
    pool_factory: Callable[..., AdaptationPool] | None = None
    progress: Callable[[ProgressEvent], None] | None = None
    cancel: Callable[[], bool] | None = None
    checkpoint: Callable[[dict], None] | None = None


STUCK_ACCEPTANCE = 0.02
"""A burn-in round whose acceptance is below this has chains that cannot move (see :func:`burnin_rounds`)."""


def burnin_rounds(target, states: list, pool: AdaptationPool, config: SamplerConfig, counters: tuple = (0, 0, 0),
                  dr_scale: float | None = None,
                  shrink: float = 1.0) -> Generator[Batch | RoundEvent, list, tuple[list, int, int, int]]:
    """Burn-in rounds until R-hat is below the threshold or the round budget is spent: each round's chain
    tasks as one :class:`~.chains.Batch`, then its event.

    Returns the chain states, accepted and proposed counts, and likelihood evaluations (``counters``: those
    of the stages before, for the checkpoints). ``dr_scale`` (default ``config.dr_scale``; 0 for a warm
    start, see :class:`SamplerConfig`) is the delayed-rejection second stage of the first
    ``config.dr_rounds`` rounds.

    Chains that cannot move (a round's acceptance below :data:`STUCK_ACCEPTANCE`) sit where the pooled
    covariance is far wider than the posterior: pooled over chains in separate modes, or kept from before
    because chains that never move give no covariance to refit. Their random walk is shrunk tenfold in
    variance each such round (``shrink``, carried in the checkpoints) until they move, and widened back once
    they accept freely; a run whose chains move never shrinks.
    """
    dr = config.dr_scale if dr_scale is None else dr_scale
    b_acc = b_n = n_eval = 0
    # a checkpoint of the round that converged resumes into the stationary stage, as the run it was taken from did
    while pool.rounds < config.max_burnin_rounds and not (pool.rounds and pool.converged()):
        rnd = pool.rounds + 1
        dr_r = dr if rnd <= config.dr_rounds else 0.0
        jump = pool.jump(config.jump_weight, config.jump_df) if dr_r == 0 else None
        results = yield Batch(round_task, [(target, s, shrink * np.asarray(pool.proposal(c)), config.round_size,
                                            True, dr_r, jump) for c, s in enumerate(states)], Step("burnin", rnd))
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
        rate = acc / max(1, n)
        if rate < STUCK_ACCEPTANCE:
            shrink = max(shrink * 0.1, 1e-8)
        elif rate > 10 * STUCK_ACCEPTANCE:
            shrink = min(shrink * 10.0, 1.0)
        reports.append(BurninRound(pool.rounds, pool.rhat().tolist(), pool.best_lp, rate))
        yield RoundEvent("burnin", pool.rounds, tuple(reports), {
            "stage": "burnin", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
            "counters": [counters[0] + b_acc, counters[1] + b_n, counters[2] + n_eval], "dr_scale": dr,
            "shrink": shrink})
    return states, b_acc, b_n, n_eval


STATIONARY_ROUNDS = 4
"""Rounds of draws a stationary task carries per chain: each task is a trip through the scheduler, the driver
and the store, which on the demo's 250-draw rounds cost about a tenth of the cores besides the likelihoods."""


STRIDE = 10_000_000
"""A stationary round's :class:`Step` index is ``pass * STRIDE + first draw`` (no task of a later pass shares
a key with one of an earlier pass; the store's slot is the index modulo STRIDE)."""


def stationary_rounds(target, states: list, config: SamplerConfig, *, pool: AdaptationPool, counters: list,
                      resume: dict | None = None) -> Generator:
    """The stationary stage: draws by Metropolis-Hastings with the fixed proposal (the random walk with
    the pool's covariance mixed with the pool's independence proposal, :class:`~ardcore.sampling.proposal.Jump`), one
    :class:`~.chains.Batch` and one event per round, until the draws meet the quality target or the budget is
    spent.

    After ``config.n_stationary`` draws per chain (and after each extension) ArviZ's diagnostics are taken
    (:mod:`.diagnostics`). When the rank R-hat of some parameter exceeds ``config.rhat_threshold`` the chains
    had not settled; when the ESS per draw is so low that the budget cannot reach ``config.min_ess`` at that
    rate the kernel is poor. Either way the draws count as more burn-in (the pool refits the kernel to them)
    and are drawn again from where the chains are (at most ``config.stationary_restarts`` times).
    Otherwise, while R-hat exceeds ``config.max_rhat`` or a bulk or tail ESS is below ``config.min_ess``, the
    same chains continue with the same kernel (the draws so far stay: one longer stationary run) by as many
    draws as the ESS says are missing, up to
    ``config.stationary_budget`` draws per chain.

    Returns samples (n_chains, draws, d), their log posteriors and log likelihoods, the chain states, the
    accepted count, the running count of likelihood evaluations (``counters``: accepted, proposed and
    evaluated so far) and the draws' diagnostics. ``resume`` (a checkpoint of this stage with the draws so
    far) continues it.
    """
    names = list(target.names)
    nc, d, M = len(states), len(names), config.n_stationary
    budget = config.stationary_budget
    quality = Quality(config.max_rhat, config.min_ess)
    goal, done, s_acc, n_eval, passes = M, 0, 0, counters[2], 0
    refit = False
    if resume is not None and resume["stage"] == "stationary":
        done, s_acc, passes = int(resume["done"]), int(resume["s_acc"]), int(resume.get("pass", 0))
        goal = int(resume.get("goal", M))
        refit = bool(resume.get("refit"))
    samples = np.full((nc, goal, d), np.nan)
    lps = np.full((nc, goal), np.nan)
    lls = np.full((nc, goal), np.nan)
    if done:
        samples[:, :done], lps[:, :done], lls[:, :done] = (resume["samples"][:, :done], resume["lp"][:, :done],
                                                           resume["ll"][:, :done])
    cov, jump = pool.cov, pool.jump(config.jump_weight, config.jump_df)

    def checkpoint() -> dict:
        return {"stage": "stationary", "states": [q.to_dict() for q in states], "pool": pool.to_dict(),
                "counters": [counters[0], counters[1], n_eval], "done": done, "s_acc": s_acc, "pass": passes,
                "goal": goal}

    while True:
        while done < goal:
            # the kernel is fixed here, so a chain's draws do not depend on how they are cut into tasks (its
            # random numbers travel with it): a task carries up to STATIONARY_ROUNDS rounds, and the stage's
            # goals stay whole rounds
            n = min(STATIONARY_ROUNDS * config.round_size, goal - done)
            results = yield Batch(round_task, [(target, s, cov, n, False, 0.0, jump) for s in states],
                                  Step("stationary", passes * STRIDE + done))
            states = [q.state for q in results]
            n_eval += sum(q.evaluations for q in results)
            for c, q in enumerate(results):
                samples[c, done:done + n], lps[c, done:done + n], lls[c, done:done + n] = q.samples, q.lp, q.ll
            s_acc += sum(q.accepted for q in results)
            done += n
            yield RoundEvent("stationary", -(-done // config.round_size), (
                StationaryRound(-(-done // config.round_size), done, goal,
                                sum(q.accepted for q in results) / (nc * n)),), checkpoint())
        diag = convergence(names, samples[:, :done])
        r_max, e_min, r_name, e_name = quality.worst(diag)
        if quality.met(diag):
            return samples[:, :done], lps[:, :done], lls[:, :done], states, s_acc, n_eval, diag
        # a kernel fitted to chains that had not settled (R-hat), or one so poor that the budget cannot reach
        # the ESS target at the rate its draws give (ESS grows about linearly with the draws): these draws
        # become one more adaptation round (the pool refits the random walk's covariance and the
        # independence proposal to them) and the stage is drawn again
        unsettled = r_max > config.rhat_threshold
        # judged once per pass, with a factor 2 to spare: an ESS from few draws is pessimistic
        hopeless = done == M < budget and 2 * e_min * budget / done < quality.min_ess
        if refit or ((unsettled or hopeless) and passes < config.stationary_restarts):
            why = (f"R-hat {r_max:.3g} for {r_name}" if unsettled else
                   f"ESS {e_min:.0f} for {e_name} after {done} draws per chain, too slow for ESS "
                   f"{quality.min_ess:g} within {budget}" if hopeless else
                   f"{quality.describe(diag)} after {done} draws per chain")
            refit = False
            states = _adapt_on(target, pool, states, samples[:, :done], lps[:, :done])
            cov, jump = pool.cov, pool.jump(config.jump_weight, config.jump_df)
            passes, done, s_acc, goal = passes + 1, 0, 0, M
            samples, lps, lls = samples[:, :M], lps[:, :M], lls[:, :M]
            note = Note(f"stationary draws: {why}; counted as burn-in (the proposal refitted to them) and drawn "
                        f"again (pass {passes + 1} of at most {config.stationary_restarts + 1})")
            yield RoundEvent("stationary", 0, (note,), checkpoint())
            continue
        if done >= budget:
            return samples[:, :done], lps[:, :done], lls[:, :done], states, s_acc, n_eval, diag
        # the draws a chain still needs for the ESS target (ESS grows with the draws), plus a tenth
        # (at most doubling: an ESS from few draws is pessimistic)
        need = min(2 * done, done * 1.1 * quality.min_ess / max(e_min, 1.0)) if e_min < quality.min_ess \
            else done * 1.25
        rs = config.round_size
        goal = int(min(budget, max(done + rs, -(-int(need) // rs) * rs)))
        grow = goal - samples.shape[1]
        samples = np.concatenate([samples, np.full((nc, grow, d), np.nan)], axis=1)
        lps = np.concatenate([lps, np.full((nc, grow), np.nan)], axis=1)
        lls = np.concatenate([lls, np.full((nc, grow), np.nan)], axis=1)
        note = Note(f"stationary draws: {quality.describe(diag)} after {done} draws per chain; continuing to "
                    f"{goal} (target R-hat <= {quality.max_rhat:g}, ESS >= {quality.min_ess:g}; budget {budget})")
        yield RoundEvent("stationary", 0, (note,), checkpoint())


def _adapt_on(target, pool, states: list, samples: np.ndarray, lps: np.ndarray) -> list:
    """Report stationary draws that had not settled to the INCA pool as one more burn-in round (each chain's
    two halves, in the sampler's coordinates); chains the pool finds stuck far below the best are moved."""
    free = free_coordinates(target)
    rnd = pool.rounds + 1
    h = samples.shape[1] // 2
    for c, st in enumerate(states):
        z = free.to_free(samples[c])
        pool.report(c, rnd, (RoundStats.of(z[:h]), RoundStats.of(z[h:])),
                    ChainReport(st.best_x, st.best_lp, st.best_ll, float(np.mean(lps[c, h:]))))
    for c, src in pool.moved(rnd).items():
        s, o = states[c], states[src]
        s.x, s.lp, s.ll = list(o.x), o.lp, o.ll
    return states


def _begin(target, config: SamplerConfig, seed: int, start: Start, runtime: Runtime):
    """Chain states, the INCA coordinator, the stage and the counters to start (or resume) from (a
    generator: a cold start's optimisations are a :class:`~.chains.Batch`)."""
    factory = runtime.pool_factory or AdaptationPool.from_dict
    resume = start.resume
    if resume is not None:
        return ([ChainState.from_dict(q) for q in resume["states"]], factory(resume["pool"]), resume["stage"],
                list(resume.get("counters", [0, 0, 0])))
    states, cov, n_start = yield from iter_initial_states(target, config, seed=seed, warm=start.warm,
                                                          starts=start.points)
    pool0 = AdaptationPool(config.n_chains, len(target.names), cov, inca=config.inca,
                           rhat_threshold=config.burnin_rhat, min_rounds=config.min_burnin_rounds,
                           outlier_nats=config.outlier_nats)
    return states, factory(pool0.to_dict()), "burnin", [0, 0, n_start]


def sampler_steps(target, config: SamplerConfig, *, seed: int, start: Start = Start(),
                  runtime: Runtime = Runtime()) -> Generator[Batch | RoundEvent, list, SamplerResult]:
    """Parallel DRAM with INCA, then the fixed-proposal stationary stage, sans IO: every step's chain tasks
    are a :class:`~.chains.Batch` the generator yields and is sent the results of, and every round ends with
    a :class:`RoundEvent` (a fresh start first yields the state it starts from); its return value
    (``StopIteration.value``) is the :class:`SamplerResult`. Of ``runtime`` only the pool factory is used:
    whoever drives it runs the batches and handles the events (:func:`iter_sample`, :func:`sample_batches`)."""
    names = list(target.names)
    warnings: list[str] = []
    states, pool, stage, counters = yield from _begin(target, config, seed, start, runtime)
    warm, resume = start.warm, start.resume
    # a warm start's first proposal is the previous posterior's covariance: no delayed rejection (SamplerConfig)
    dr = (config.dr_scale if warm is None or config.warm_dr else 0.0) if resume is None \
        else float(resume.get("dr_scale", config.dr_scale))
    if resume is None:
        yield RoundEvent("burnin", 0, (), {"stage": "burnin", "states": [q.to_dict() for q in states],
                                           "pool": pool.to_dict(), "counters": list(counters), "dr_scale": dr})
    # ---- burn-in: DRAM rounds, the pool is the INCA coordinator
    if stage == "burnin":
        shrink = float(resume.get("shrink", 1.0)) if resume is not None else 1.0
        states, b_acc, b_n, n_b = yield from burnin_rounds(target, states, pool, config, tuple(counters), dr, shrink)
        counters = [counters[0] + b_acc, counters[1] + b_n, counters[2] + n_b]
    b_acc, b_n, _ = counters
    rounds, converged, r = pool.rounds, pool.converged(), pool.rhat()
    # ---- stationary stage: fixed proposal, plain RWM
    samples, lps, lls, states, s_acc, n_eval, diag = yield from stationary_rounds(
        target, states, config, pool=pool, counters=counters, resume=resume)
    # the kernel of the pass that was kept (a redrawn stage refits the pool), which Chib-Jeliazkov needs
    cov, jump = pool.cov, pool.jump(config.jump_weight, config.jump_df)
    best = max(states, key=lambda q: q.best_lp)
    r_final = np.array([diag[n]["r_hat"] for n in names]) if names else np.ones(0)
    quality = Quality(config.max_rhat, config.min_ess)
    if not quality.met(diag):
        # the stationary draws are what the results rest on: a short burn-in whose draws then pass is no concern
        if not converged:
            warnings.append(f"burn-in did not reach R-hat < {config.burnin_rhat} in {rounds} rounds "
                            f"(max R-hat {np.max(r):.3g} for {names[int(np.argmax(r))]})")
        warnings.append(f"not converged: stationary draws reach {quality.describe(diag)} against R-hat <= "
                        f"{quality.max_rhat:g} and ESS >= {quality.min_ess:g} within the budget of "
                        f"{config.stationary_budget} draws per chain (sampler.max_stationary)")
    return SamplerResult(
        names=names, samples=samples, lp=lps, ll=lls,
        phi_star=np.array(best.best_x), lp_star=best.best_lp, ll_star=best.best_ll,
        proposal_cov=cov, states=states, rhat=r_final, rhat_history=list(pool.rhat_history),
        burnin_rounds=rounds, converged=converged,
        acceptance=s_acc / max(1, samples.shape[0] * samples.shape[1]), burnin_acceptance=b_acc / max(1, b_n),
        n_evaluations=n_eval, warnings=warnings,
        jump=jump.to_dict() if jump is not None else None,
        diagnostics=diag, quality_met=quality.met(diag), adaptation=pool.to_dict())


def continuation(res: SamplerResult) -> dict:
    """The checkpoint from which :func:`sample` (``resume=``) continues the stationary stage of ``res``: the
    same chains (their random streams included), whose stationary draws become one more adaptation round
    (the kernel refitted to them: a search trial's kernel comes from a short burn-in, and its draws cost
    nothing more now), then M draws judged and extended to the quality target within the budget of the
    settings it is resumed with.

    The continued result counts only the new likelihood evaluations; its burn-in acceptance is unknown
    here (0): :func:`continued` carries it over.
    """
    if res.adaptation is None or not res.samples.size:
        raise SamplerError("these draws cannot be continued: the result carries no coordinator state")
    nc, m = res.samples.shape[:2]
    return {"stage": "stationary", "states": [s.to_dict() for s in res.states], "pool": res.adaptation,
            "counters": [0, 0, 0], "done": m, "goal": m, "pass": 0, "refit": True,
            "s_acc": int(round(res.acceptance * nc * m)),
            "samples": res.samples.copy(), "lp": res.lp.copy(), "ll": res.ll.copy()}


def continued(res: SamplerResult, before: SamplerResult) -> SamplerResult:
    """``res``, sampled from :func:`continuation` of ``before``, with the burn-in acceptance of ``before``
    (the rest of the burn-in's record travels in the chain states and the coordinator)."""
    return replace(res, burnin_acceptance=before.burnin_acceptance)


def iter_sample(target, config: SamplerConfig, *, seed: int, start: Start = Start(),
                runtime: Runtime = Runtime()) -> Generator[RoundEvent, None, SamplerResult]:
    """:func:`sampler_steps` with its batches run on ``runtime.map_fn``: one :class:`RoundEvent` per round;
    the return value (``StopIteration.value``) is the :class:`SamplerResult`. Arguments as :func:`sample`."""
    steps = sampler_steps(target, config, seed=seed, start=start, runtime=runtime)
    reply = None
    while True:
        try:
            item = steps.send(reply)
        except StopIteration as done:
            return done.value
        if isinstance(item, Batch):
            reply = runtime.map_fn(item.func, item.items, step=item.step)
        else:
            reply = None
            yield item


def sample_batches(target, config: SamplerConfig, *, seed: int, start: Start = Start(),
                   runtime: Runtime = Runtime()) -> Generator[Batch, list, SamplerResult]:
    """:func:`sampler_steps` with its events handled by the runtime's hooks (``cancel`` asked before every
    step, ``progress`` and ``checkpoint`` given every round's reports and state): what is left to yield are
    the batches, for an event loop to run wherever it likes. Arguments as :func:`sample`."""
    steps = sampler_steps(target, config, seed=seed, start=start, runtime=runtime)
    stage = start.resume["stage"] if start.resume is not None else "burnin"
    progress, cancel, checkpoint = runtime.progress, runtime.cancel, runtime.checkpoint
    reply, error = None, None
    while True:
        if cancel is not None and cancel():
            steps.close()
            raise Cancelled("cancelled during " + ("burn-in" if stage == "burnin" else "stationary sampling"))
        try:
            item = steps.throw(error) if error is not None else steps.send(reply)
        except StopIteration as done:
            return done.value
        reply, error = None, None
        if isinstance(item, Batch):
            try:
                reply = yield item
            except Exception as exc:  # noqa: BLE001 - a task's error, raised where the sampler waits for it
                error = exc
            continue
        stage = item.stage
        for rep in item.reports if progress else ():
            progress(rep)
        if checkpoint:
            checkpoint(item.checkpoint)


def sample(target, config: SamplerConfig, *, seed: int, start: Start = Start(),
           runtime: Runtime = Runtime()) -> SamplerResult:
    """Run parallel DRAM with INCA, then the fixed-proposal stationary stage: :func:`sample_batches` with its
    batches run on ``runtime.map_fn``.

    Parameters
    ----------
    target : callable
        ``x -> (log_posterior, log_likelihood)`` with ``names`` and ``prior``.
    config : SamplerConfig
    seed : int
        Every random number derives from it (chain c uses an independent stream).
    start : Start
        Where the chains start. ``warm``: chains continue from these states (positions mapped by parameter
        name; a parameter now fixed conditions them, see :func:`~ardcore.sampling.starts.warm_positions`)
        with its proposal covariance; ``points``: explicit initial points (n_chains, d), skipping the start
        optimisation; ``resume``: a checkpoint dict to continue from (for the stationary stage it must also
        hold ``samples``, ``lp`` and ``ll`` arrays of the draws done so far).
    runtime : Runtime
        ``map_fn`` runs the per-chain tasks of a step (:data:`Map`); ``pool_factory(state_dict) -> pool``
        makes the INCA coordinator; ``progress`` is called with each of a round's reports
        (:mod:`ardcore.events`); ``cancel`` is checked between rounds (True raises :class:`Cancelled`);
        ``checkpoint`` is called with each round's JSON-able state (stage, chain states, coordinator state,
        counters), which with the stationary samples written so far is enough to resume.
    """
    return run(sample_batches(target, config, seed=seed, start=start, runtime=runtime), runtime.map_fn)


class Cancelled(ArdflowError):
    """A run was cancelled cooperatively."""
