"""Closing the loop (docs/method.md section 8): residuals, tests, trace, add, report.

:func:`diagnose` takes a study spec with one candidate model and its data:

1. fits the candidate (ARD evidence maximisation as in any study);
2. computes the **residuals** at the posterior mean: standardised EKF
   innovations; the free-run (deterministic simulation) error; and the
   process noise the filter had to inject, per dynamic state, from an RTS
   smoother on the model with a small diagnostic noise (its level fitted by
   maximum likelihood) on every dynamic state;
3. **tests** them: whiteness (autocorrelation with 95 % bands, Ljung-Box),
   normality (Jarque-Bera), spectral peaks of the innovations;
4. **traces** the residual to an effect: every candidate of
   :mod:`ardcore.effects.base` on every dynamic state (and every measurement effect
   on every observed channel) is **screened by evidence** (:mod:`ardcore.screening.screen`:
   a Laplace log Bayes factor from the EKF's own score and information, the
   model's parameters profiled out, terms normalised, shape parameters such as a
   free-play width or a forcing frequency profiled); the best few are
   **confirmed** by the full ARD re-selection: each is added (normalised) under
   an ARD prior and the candidate re-selected, so ARD decides whether the new
   term survives;
5. **decides** by one criterion: a move the evidence supports is taken only when
   its model free-runs better on held-out blocks of the estimation record
   (:mod:`ardcore.loop.criterion`); the loop stops when
   none does;
6. **reports** the error before and after.

When no move is taken, the result says so and describes the residual
structure that remains (spectral peaks, the states that needed noise).

Rooms: the residuals and their tests live in :mod:`ardcore.loop.residuals`, the free run and its
prediction band in :mod:`ardcore.loop.freerun`, the evidence screen in :mod:`ardcore.screening.screen` (its EKF score machinery in :mod:`ardcore.screening.score`),
the library in :mod:`ardcore.effects.base`, the confirmations (re-selection, halves check, joint
fit, process pool) in :mod:`ardcore.loop.confirm`, the criterion and the round's decision in
:mod:`ardcore.loop.criterion`, the verdict's words in
:mod:`ardcore.loop.verdict`; this module holds the loop.
"""

from __future__ import annotations

import math
import os
import time
from typing import Callable

import numpy as np

from .checks import Added, backward_check, brought, not_degenerate, replace_laws
from .confirm import Fit, confirm, hidden, pool_mapper, trace_and_confirm
from .states import LAG_KINDS, STATE_KINDS, best_state, lines, state_moves
from .replace import best_laws
from ..data import Dataset
from ..effects.base import Effect, with_columns
from ..errors import DataError, FitError, LoopFailed, SpecError
from ..jsonio import to_jsonable
from .criterion import Criterion, Move, contest, decide, held_out_record, stable
from .simulation_fit import reported_model
from .verdict import Diagnosis, FittedModel, LoopRound
from .freerun import Band, fitted, free_run, posterior_draws
from ..selection.hold import with_holds
from ..selection.initial import data_informed_initial
from .config import DiagnoseConfig, LoopContext
from ..model.declaration import ModelSpec
from .residuals import Residuals, residuals
from ..selection.fit import ModelFit
from ..selection.spec import StudySpec
from ..selection.study import run_candidate
from .verdict import character, report, strip_tests, unexplained



# --------------------------------------------------------------------------- fit, free run, loop


def _measure(ctx: LoopContext, held: Fit, fspec, phi, test, rnd: int) -> tuple[Residuals, dict, dict]:
    """The fitted model's residuals on the estimation data, its free run (with a band) on the test record
    and the errors reported for both; ``fspec, phi``: the held model with its pruned terms fixed, at its
    posterior mean."""
    config = ctx.config
    res = residuals(fspec, phi, held.data, config, substeps=held.cand.substeps)
    fr = free_run(fspec, phi, test, init_samples=config.init_samples, substeps=held.cand.substeps,
                  band=Band(posterior_draws(held.mr, fspec, config.band_draws, seed=rnd), seed=rnd))
    return res, fr, _errors(res, fr, held.row, ctx.column)


def _errors(res: Residuals, fr: dict, row: ModelFit, col: str) -> dict:
    t = res.tests[col]
    keep = ("rms_error", "relative_rms_error", "frequency_error", "amplitude_error", "harmonic_error",
            "band_coverage", "band_expected", "band_diverged", "band_halfwidth_rms", "draws_rms_error", "n_draws",
            "band_factor", "band_calibration")
    # the first innovations carry the initial-state uncertainty, not the model's error
    skip = min(10, max(0, res.raw_innovations.shape[0] // 10))
    out = {"innovation_rms": float(np.sqrt(np.nanmean(res.raw_innovations[skip:, 0] ** 2))),
           # what the model had to be pushed by (smoothed process noise, per unit time), per dynamic state
           "injected_noise_rms": {s: float(np.sqrt(np.nanmean(r ** 2))) for s, r in res.process_noise_rate.items()},
           "standardized_rms": t["rms"], "ljung_box": t["ljung_box"], "ljung_box_p": t["ljung_box_p"],
           "free_run": {k: fr[k] for k in keep if k in fr},
           "log_evidence": row.log_evidence, "log_evidence_se": row.log_evidence_se}
    if res.records:  # several estimation records: each one's innovation tests
        out["records"] = [dict(r) for r in res.records]
    if fr.get("records"):  # several test records: each one's free run
        out["free_run"]["records"] = fr["records"]
    return out


def diagnose(spec: StudySpec, data: Dataset, *, test_data: Dataset | None = None,
             config: DiagnoseConfig | None = None, progress: Callable[[str], None] | None = None,
             extra_effects: list[Effect] = (), base: tuple[ModelFit, object] | None = None) -> Diagnosis:
    """Run the closed loop on the single candidate of ``spec`` (see module docstring).

    Parameters
    ----------
    spec : StudySpec
        Exactly one candidate: the model to diagnose, with its priors (ARD terms allowed).
    data : Dataset
        Estimation data.
    test_data : Dataset, optional
        Held-out record for the free-run error (default: ``data``).
    extra_effects : list of Effect
        Added to the built-in library.
    base : (ModelFit, MaximiserResult), optional
        An existing fit of the candidate (skips step 1).

    Returns
    -------
    Diagnosis
        Its ``report`` (``to_json``): ``before``/``after`` residual tests and errors, ``candidates``
        (ranked), ``confirmed`` (evidence for the top few), ``added`` (the effects kept), ``verdict``
        (text); the arrays for the figures; the initial and final models (``FittedModel``, for free runs
        on further held-out records).
    """
    config = config or DiagnoseConfig()
    t_start = time.perf_counter()

    def say(msg: str) -> None:
        if progress:
            progress(f"[{time.perf_counter() - t_start:6.0f} s] {msg}")

    if len(spec.models) != 1:
        raise SpecError(f"diagnose: the spec must have exactly one model (it has {len(spec.models)})")
    test_data = spec.held_out(test_data) if test_data is not None else data
    _check_columns(spec.models[0].model_spec(), data, test_data)
    spec, hold = (spec, []) if base is not None else with_holds(spec, data)
    for n in hold:
        say(n)
    spec, notes = _informed_start(spec, data, base, say)
    cand = spec.models[0]
    say(f"fitting {cand.label} ...")
    row, bmr = base or run_candidate(cand, data, spec, 0, final_posterior=config.posterior)
    check_fitted(cand.label, row, data)
    col = cand.model_spec().observed_columns[0]
    first = None
    rounds, arrays = [], {}
    cur_test = test_data
    workers = config.workers or min(os.cpu_count() or 1, max(config.top_k, 2))
    mapper, close = pool_mapper(workers)
    ctx = LoopContext(spec, config, say, mapper, tuple(extra_effects), col)
    held = Fit(cand, row, bmr, data)
    crit = Criterion(config, mapper, say)
    judged: list[dict] = []  # per round: the held model's held-out score and every move's
    try:
        spent = 0  # rounds that moved the dynamics: a measurement-noise level taken alone is not one
        last = 2 * config.max_rounds  # a hard bound: the loop always ends on a measured round
        for rnd in range(last + 1):
            fspec, phi = fitted(held.cand, held.row)
            say(f"round {rnd}: {held.cand.label} ln Z = {held.row.log_evidence:.3f}; computing residuals")
            res, fr, err = _measure(ctx, held, fspec, phi, cur_test, rnd)
            if first is None:
                initial = FittedModel(fspec, phi, (), held.cand.substeps)
                first = {"before": err, "tests_before": strip_tests(res.tests), "noise_std_before": res.noise_std,
                         "base_fit": held.row.summary(_BASE_FIT), "initial_state": notes, "input_hold": hold,
                         "max_rounds": config.max_rounds, "seed": spec.seed}
                arrays["before"] = _arrays(res, fr)
            else:
                arrays["after"] = _arrays(res, fr)
                rounds[-1].record["after"] = err
            if spent == config.max_rounds or rnd == last:
                # the cap, not the criterion, ended the loop: the report says so (more rounds may still help)
                first["stopped_by"] = "round_cap" if rnd else "no_round"
                break
            t_round = time.perf_counter()
            swap = best_laws(ctx, held, brought(rounds), [x for r in rounds for x in r.record.get("replaced", [])
                                                          if x.get("form")], crit)
            # a state: a declared quantity, or a state in another's equation, acting through a lag
            lagged = best_state(ctx, held, LAG_KINDS)
            if lagged is not None and (swap is None or lagged[2] > swap[2]):
                swap = lagged
            rec, survivors, deferred, proposals = _trace_round(ctx, held, fspec, phi, res, rounds)
            rounds.append(rec)
            move, judged_round = decide(ctx, crit, held, swap, survivors, deferred, rec)
            rec.record["terms_s"] = time.perf_counter() - t_round
            if config.states and (move is None or not move.nuisance):
                # the states compete with the terms: a slow store the model lacks is otherwise taken up first by
                # terms that stand in for it (on the two-mass record an overflow, a cube and a forcing together
                # free-ran its held-out blocks 5.3/3.6 K, the second store it lacked 0.14/0.18 K)
                t_states = time.perf_counter()
                move, swap = contest(ctx, crit, held, (move, swap), state_moves(ctx, held, STATE_KINDS,
                                                                                 lines(res.tests)), rec, judged_round)
                rec.record["states_s"] = time.perf_counter() - t_states  # the cost the bench holds to the terms'
            if move is None:
                t_next = time.perf_counter()
                move = _next_proposals(ctx, crit, held, proposals, rec, judged_round)
                rec.record["terms_s"] += time.perf_counter() - t_next
            judged.append(judged_round)
            if move is None:
                ctx.say("no move free-runs better held out: the loop stops")
                first["stopped_by"] = "criterion"
                break
            # a noise level changes what the filter trusts, not the model's dynamics: the round it took (alone, so
            # that the others are screened again under it) does not count against the cap
            spent += not move.nuisance
            if move.kind == "replace":
                rec.record["replaced"] = swap[1]
                rec.record.pop("verdict", None)
                # what earlier rounds added stood in beside the wrong law: each must still earn its place
                held = backward_check(ctx, swap[0], [x for r in rounds[:-1] for x in r.added], rnd, crit)
                continue
            held = _adopt(ctx, held, move, fspec, phi, rec)
            for e in rec.effects:
                cur_test = with_columns(cur_test, e)
            earlier = [x for r in rounds[:-1] for x in r.added]
            held = backward_check(ctx, held, earlier, rnd, crit)
            held = replace_laws(ctx, held, rounds, crit)
        score = crit.score(held)
        first["held_out"] = held_out_record(config, judged, score)
        final = FittedModel(fspec, phi, tuple(e for r in rounds for e in r.effects), held.cand.substeps)
        # the measure of the model reported: the last round's that changed it (or, with none, the first), which
        # its free run with the calibrated band replaces
        last = next((r.record for r in reversed(rounds) if r.record.get("added") or r.record.get("replaced")), None)
        shown = (last["after"], arrays["after"]) if last is not None else (first["before"], arrays["before"])
        first["reported"], reported = reported_model(ctx, final, held, cur_test, shown, len(rounds), score.held)
        out = report(ctx.spec, data, test_data, first, rounds, arrays, held)
    except Exception as exc:  # noqa: BLE001 - any failure after the first fit, a defect included
        # never lose the work: what the loop had, with the reason, for the caller to write before it says so
        raise LoopFailed(f"diagnose failed in round {len(rounds)} ({type(exc).__name__}: {exc}); the rounds so far "
                         "and the last model held are written", _partial(ctx, first, rounds, held, exc, judged)) from exc
    finally:
        close()
    out["wall_s"] = time.perf_counter() - t_start
    return Diagnosis(out, arrays, initial, reported, final)


def _partial(ctx: LoopContext, first: dict | None, rounds: list[LoopRound], held: Fit, exc: Exception,
             judged: list) -> dict:
    """What a failed loop had: the first measures, the rounds so far, the held-out judgements, the last model it
    held (its fit's summary) and why it stopped."""
    out = {"status": "failed", "reason": f"{type(exc).__name__}: {exc}", "model": ctx.spec.models[0].label,
           "last_model": held.cand.label, **(first or {}),
           "rounds": [r.record for r in rounds], "held_out_moves": judged,
           "last_fit": held.row.summary(("log_evidence", "log_evidence_se", "mean", "sd", "q005", "q995"))}
    return to_jsonable(out)


_BASE_FIT = ("log_evidence", "log_evidence_se", "psi_opt", "kept", "pruned", "mean", "sd")


def _informed_start(spec: StudySpec, data: Dataset, base, say) -> tuple[StudySpec, list[str]]:
    """The spec with its candidate's initial-state prior re-centred on the record where the declared one is
    far off (not when an existing fit is given), and the notes saying so."""
    if base is not None:
        return spec, []
    cand, notes = data_informed_initial(spec.models[0], data)
    for n in notes:
        say(n)
    return (spec.model_copy(update={"models": [cand]}) if notes else spec), notes


def _check_columns(ms: ModelSpec, data: Dataset, test_data: Dataset) -> None:
    """Before any fit: a free run at the end must not be what finds a missing column, an input with a gap or an
    observed column without a value (a test record that diverged in its simulation, a wrong file)."""
    for what, d in (("data", data), ("held-out data", test_data)):
        missing = [c for c in list(ms.observed_columns) + list(ms.inputs) if c not in d.columns]
        if missing:
            raise SpecError(f"diagnose: the {what} ({d.meta.get('source', 'given')}) has no column "
                            f"{missing[0]!r} (it has {sorted(d.columns)}); rename its columns")
        try:
            d.arrays(list(ms.observed_columns), list(ms.inputs))
        except DataError as exc:
            raise DataError(f"diagnose: the {what}: {exc}") from exc


def check_fitted(label: str, row: ModelFit, data: Dataset) -> None:
    """The loop starts from a fit with a finite evidence and a posterior that moved; without them every
    residual, score and comparison is NaN or meaningless."""
    if math.isfinite(row.log_evidence):
        why = row.degenerate()
        if why is not None:
            raise FitError(f"diagnose: {why}")
        return
    big = max((float(np.nanmax(np.abs(v))) for v in data.columns.values() if np.any(np.isfinite(v))), default=0.0)
    raise FitError(f"diagnose: {label} has no finite evidence on these data (ln Z = {row.log_evidence}): its "
                   f"likelihood is not finite anywhere the fit reached. Check the data (largest |value| "
                   f"{big:.3g}) against the model's priors, initial state and noise levels")


def _present(rounds: list[LoopRound]) -> set:
    """(library name, target) of the effects the model holds: not screened again (a second saturating flow
    beside the first, its width already fitted, is a basis expansion, not an effect)."""
    return {x.key for r in rounds for x in r.added if not x.record.get("removed")}


def _closed(rounds: list[LoopRound]) -> set:
    """The states added with an equation of fixed form (a hysteresis, a sensor, an actuator, a store, a relaxation,
    a mode): the screen leaves them alone."""
    return {n for r in rounds for x in r.record.get("replaced", []) if x.get("state") and x["state"]["kind"] != "lag"
            for n in x["state"].get("states", [x["state"]["name"]])}


def _trace_round(ctx: LoopContext, held: Fit, fspec, phi, res, rounds: list[LoopRound]) -> tuple:
    """One round's trace after ``rounds``: screen (not what the model holds already, nothing on a state of fixed
    form), confirm, check the survivors' stability; the round's record, the survivors (best first), those
    deferred behind a measurement-noise level (the noise rule, :func:`_survivors`) and the evidence's next
    proposals (:func:`_next_proposals`). With no survivor, the record carries the verdict on what remains."""
    config, rnd = ctx.config, len(rounds)
    screening, confirmed = trace_and_confirm(ctx, held, fspec, phi, res, _present(rounds), _closed(rounds))
    ranked = screening.screened
    survivors, deferred = _survivors(ctx, confirmed)
    # final ranking: what evidence confirmed (by ln Bayes factor), then the rest by regression score
    tried = {(c.screened.effect.name, c.target) for c in confirmed}
    order = sorted(confirmed, key=lambda c: (not c.survives, -c.log_bayes_factor))
    ranking = [{"effect": c.effect, "target": c.target, "log_bayes_factor": c.log_bayes_factor,
                "survives": c.survives} for c in order]
    ranking += [{"effect": c.effect.name, "target": c.target, "score": c.log_bayes_factor,
                 "screened_log_bayes_factor": c.log_bayes_factor} for c in ranked
                if (c.effect.name, c.target) not in tried]
    candidates, confirmations = [c.to_json() for c in ranked], [c.to_json() for c in confirmed]
    rec = {"round": rnd, "model": held.cand.label, "ranking": ranking, "deferred": [c.effect for c in deferred],
           "candidates": candidates, "confirmed": confirmations, "added": None}
    if not survivors:
        rec["verdict"] = unexplained(res, candidates, confirmations, ctx.column, config)
    return LoopRound(rec), survivors, deferred, (screening, hidden(screening, confirmed))


def _survivors(ctx: LoopContext, confirmed: list) -> tuple[list, list]:
    """The confirmations that survive (best first, stable over the record's halves) and those deferred behind a
    measurement-noise level off by more than 2x (then the survivors are that level alone)."""
    survivors = sorted([c for c in confirmed if c.survives], key=lambda c: -c.log_evidence)
    survivors = not_degenerate(survivors, ctx.say)
    noise = [c for c in survivors if c.fitted_effect.where == "noise"
             and any(abs(c.fit.row.mean.get(n, 0.0)) > math.log(2) for n in c.scales)]
    deferred = [c for c in survivors if c not in noise] if noise else []
    if deferred:
        # a noise level off by more than 2x changed what every dynamic candidate was screened and confirmed
        # against (a filter that takes the misfit for process noise): the noise goes in alone, the others
        # are screened again under it next round (a cubic and a sine stiffness tie until then)
        ctx.say("the measurement noise changes by more than 2x: " + ", ".join(c.effect for c in deferred)
                + " screened again under it next round")
        return noise, deferred
    return stable(ctx, survivors), []


def _next_proposals(ctx: LoopContext, crit: Criterion, held: Fit, proposals: tuple, rnd: LoopRound,
                    judged: dict) -> Move | None:
    """The round's move among the evidence's next proposals, when the criterion took none of its first: the
    candidates the forward selection set aside as explained by those it picked (``proposals``: the round's
    screen and them), confirmed and judged the same way, once. A candidate the picked ones explained is no
    longer explained once they are out, and a refused proposal must not hide the next (on the cascaded tanks an
    overflow into tank 2 from tank 1's level is screened above the overflow flow between them, which it
    explains; the criterion refuses it, and the flow is the move)."""
    screening, rest = proposals
    if not rest:
        return None
    ctx.say("the candidates the refused ones explained, confirmed now: "
            + ", ".join(f"{c.effect.name} -> {c.target}" for c in rest[:5]))
    confirmed = confirm(ctx, held, screening.inp, rest, len(screening.screened))
    rec = rnd.record
    rec["confirmed"] = rec["confirmed"] + [c.to_json() for c in confirmed]
    survivors, deferred = _survivors(ctx, confirmed)
    move, more = decide(ctx, crit, held, None, survivors, deferred, rnd)
    judged["moves"] += more["moves"]
    if move is not None:
        rec.pop("verdict", None)
    return move


def _adopt(ctx: LoopContext, held: Fit, move: Move, fspec, phi, rnd: LoopRound) -> Fit:
    """Add the effects of ``move`` (one survivor, or the survivors fitted together); record what was added in
    ``rnd``. Returns the model then held (with the data its effects need)."""
    say, row = ctx.say, held.row
    chosen, fit = move.chosen, move.fit
    jrow = fit.row
    recs = []
    for c in chosen:
        eff = c.fitted_effect
        post = {n: jrow.physical(n, c.scales[n]) for n in c.scales if n in jrow.mean}
        shape = {n: jrow.physical(n, 1.0) for n in c.shape_prior if n in jrow.mean}
        recs.append({"effect": c.effect, "kind": eff.kind, "target": c.target, "terms": list(eff.terms),
                     "posterior": post, "shape": shape, "log_bayes_factor": c.log_bayes_factor,
                     "character": character(fspec, phi, eff, {"posterior": post, "target": c.target})})
    rec = rnd.record
    rec["added"], rec["added_with"] = recs[0], recs[1:]
    rnd.effects = [c.fitted_effect for c in chosen]
    # what each must keep earning beside later effects: its threshold and coloured-innovation factor
    rnd.added = [Added(a, rec["round"], list(c.scales), c.threshold, c.inflation, (c.fitted_effect.name, c.target))
                 for a, c in zip(recs, chosen)]
    say(f"round {rec['round']}: added " + ", ".join(f"{r['effect']} to {r['target']} "
                                                   f"(ln BF {r['log_bayes_factor']:.1f})" for r in recs)
        + (f"; together ln BF {jrow.log_evidence - row.log_evidence:.1f}" if len(recs) > 1 else ""))
    return fit


def _arrays(res: Residuals, fr: dict) -> dict:
    return {"tests": res.tests, "innovations": res.innovations, "process_noise_rate": res.process_noise_rate,
            "free_run": fr}

