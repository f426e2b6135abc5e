"""Confirmation of screened candidates by the full ARD re-selection (docs/method.md section 8, step 4).

:func:`trace_and_confirm` screens the library (:mod:`ardcore.screening.screen`) and re-selects the model with each of
the best distinct candidates added under ARD, side by side on a process pool;
:func:`~ardcore.loop.checks.split_stability` and :func:`~ardcore.loop.checks.joint_fit` check the survivors;
:func:`ardcore.loop.diagnose.diagnose` runs the loop around them.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ..data import Dataset
from ..evidence.estimators import DOMINATED
from ..effects.base import (Effect, augment, dynamic_states, shape_parameter_name, shape_prior, user_inputs,
                      with_columns)
from ..model.declaration import ModelSpec
from ..effects.families import candidate_effects
from ..jsonio import is_pruned, to_jsonable
from ..screening.screen import ScreenInput, Screened, distinct_candidates, screen_effects
from ..selection.fit import ModelFit
from ..selection.spec import CandidateSpec
from ..sampling.chains import Batch, serial_map
from ..selection.study import CandidateHooks, iter_candidate, run_candidate

INF = math.inf


class Fit(NamedTuple):
    """A candidate re-selected on its data: the candidate, its summary row, its maximiser result, the data
    (with any columns its effects need)."""

    cand: CandidateSpec
    row: dict
    mr: object
    data: Dataset


@dataclass
class Confirmation:
    """One screened candidate re-selected with its terms under ARD against the current model.

    Attributes
    ----------
    effect : str
        The effect's name as reported (a fitted shape at its posterior mean, e.g. ``sine_stiffness(y,L=1.04)``).
    target : str
    screened : Screened
        What the screen found (its ln BF is ``score``).
    log_bayes_factor : float
        ln Z gained over the current model (less a profiled shape's Occam factor); ``adjusted_log_bayes_factor``
        divides a positive gain by the screen's coloured-innovation factor ``inflation``.
    threshold : float
        What the adjusted gain must exceed (``min_log_bf`` + ln N candidates).
    kept_terms, psi_opt, posterior, shape, scales
        The ARD result: terms kept, their optimal alphas, coefficients in physical units, a fitted shape's
        posterior, each term's normalisation.
    survives : bool
        Kept terms and an adjusted gain over the threshold (then possibly lost to a twin or the halves check).
    fit : Fit
        The re-selected candidate, its ModelFit, maximiser result and data.
    fitted_effect : Effect
        What was added (its shape written as a parameter when fitted); ``shape_prior`` that parameter's prior.
    """

    effect: str
    target: str
    screened: Screened
    log_evidence: float
    log_evidence_se: float
    log_bayes_factor: float
    adjusted_log_bayes_factor: float
    threshold: float
    kept_terms: list
    psi_opt: dict
    posterior: dict
    shape: dict
    scales: dict
    survives: bool
    fit: Fit
    fitted_effect: Effect
    shape_prior: dict
    rival_of: str | None = None
    rejected: str | None = None
    """Why a confirmed effect was not added although the evidence supports it (its model free-runs worse or
    its fit is degenerate, :func:`ardcore.loop.diagnose._no_worse`)."""
    stability: dict | None = None
    forced: bool = False
    """A noise level confirmed although it screened under ``min_score`` (a quiet channel, :func:`quiet_channels`):
    the criterion takes it only when it free-runs better held out, never merely no worse."""

    @property
    def score(self) -> float:
        return self.screened.log_bayes_factor

    @property
    def inflation(self) -> float:
        return self.screened.inflation

    def to_json(self) -> dict:
        out = {"effect": self.effect, "target": self.target, "screened_effect": self.screened.effect.name,
               "score": self.score,
               "screened_log_bayes_factor": self.score, "log_evidence": self.log_evidence,
               "log_evidence_se": self.log_evidence_se, "log_bayes_factor": self.log_bayes_factor,
               "adjusted_log_bayes_factor": self.adjusted_log_bayes_factor, "inflation": self.inflation,
               "threshold": self.threshold, "kept_terms": self.kept_terms, "psi_opt": self.psi_opt,
               "posterior": self.posterior, "shape": self.shape, "scales": self.scales, "survives": self.survives}
        if self.rival_of is not None:
            out["rival_of"] = self.rival_of
        if self.rejected is not None:
            out["rejected"] = self.rejected
        if self.stability is not None:
            out["stability"] = self.stability
        if self.forced:
            out["forced"] = True
        return to_jsonable(out)


def essential_from_row(cand: CandidateSpec, row: ModelFit) -> tuple[dict, dict]:
    """Priors of the fitted model with kept ARD terms frozen at their optimal alpha; pruned terms fixed."""
    from ..model.priors import frozen_ard

    priors = dict(cand.priors)
    fixed = dict(cand.fixed)
    for k, a in row.psi_opt.items():
        if is_pruned(a):
            fixed[k] = 0.0
        else:
            priors[k] = frozen_ard(a)
    return priors, fixed


def warm_with(sampler, names: list[str], values: list[float]):
    """``sampler`` (a SamplerResult) that also carries ``names`` at ``values`` (for warm starts): in its best
    point, in every chain's position and in its proposal (a small independent step, 1 % of the value), so a
    Laplace search and the MCMC chains both start the new terms there."""
    import dataclasses

    keep = [i for i, n in enumerate(sampler.names) if n not in names]
    vals = [float(v) for v in values]
    P = np.asarray(sampler.proposal_cov, float)
    k, m = len(keep), len(vals)
    cov = np.zeros((k + m, k + m))
    cov[:k, :k] = P[np.ix_(keep, keep)] if P.ndim == 2 and P.shape[0] == len(sampler.names) else 0.0
    cov[k:, k:] = np.diag([(0.01 * abs(v) if v else 1e-3) ** 2 for v in vals])

    def ext(x):
        return [float(x[i]) for i in keep] + vals

    states = [dataclasses.replace(st, x=ext(st.x), best_x=ext(st.best_x)) for st in sampler.states]
    return dataclasses.replace(sampler, names=[sampler.names[i] for i in keep] + list(names),
                               phi_star=np.concatenate([np.asarray(sampler.phi_star)[keep], np.asarray(vals)]),
                               proposal_cov=cov, states=states)


def fit_task(args):
    """One re-selection (a picklable unit of work for the confirmation pool): ``(cand, data, spec, warm,
    posterior)``, and optionally the results of its first batch of tasks, run beforehand (:func:`fit_all`)."""
    cand, data, spec, warm, posterior, *first = args
    hooks = CandidateHooks(map_fn=Answered(first[0])) if first else CandidateHooks()
    return run_candidate(cand, data, spec, 0, warm=warm, final_posterior=posterior, hooks=hooks)


class Answered:
    """A :data:`~ardcore.sampling.chains.Map` that answers the first batch it is given with ``results`` (that
    batch's tasks, run beforehand on a pool: a fit is deterministic, so its first batch is the one they were)
    and runs every later batch in this process."""

    def __init__(self, results: list):
        self.results = results

    def __call__(self, func, items, step=None) -> list:
        if self.results is None:
            return [func(it) for it in items]
        out, self.results = self.results, None
        if len(out) != len(items):
            raise RuntimeError(f"a fit's first batch has {len(items)} tasks, not the {len(out)} run beforehand")
        return out


def fit_all(mapper, tasks: list) -> list:
    """:func:`fit_task` of each of ``tasks`` on the pool ``mapper``, every fit from the prior (``warm`` None)
    first running the searches that place its start (its first batch of tasks) spread over the pool: the same
    fits, but a fit from the prior no longer searches its four starts one after another while the pool's other
    workers wait for it."""
    firsts = []
    for cand, data, spec, warm, posterior in tasks:
        first = None
        if warm is None:
            steps = iter_candidate(cand, data, spec, 0, final_posterior=posterior)
            first = next(steps, None)  # a Batch (a generator that returned at once yields none)
            steps.close()
        firsts.append(first if isinstance(first, Batch) else None)
    todo = [(i, it) for i, b in enumerate(firsts) if b is not None for it in b.items]
    done = mapper(_batch_task, [(firsts[i].func, it) for i, it in todo]) if todo else []
    answers = {i: [] for i, b in enumerate(firsts) if b is not None}
    for (i, _), r in zip(todo, done):
        answers[i].append(r)
    return mapper(fit_task, [(*t, answers[i]) if i in answers else t for i, t in enumerate(tasks)])


def _batch_task(args):
    """One task of a fit's batch (a picklable unit of work): ``(func, item)``."""
    func, item = args
    return func(item)


def pool_mapper(workers: int):
    """(map function, closer): confirmations and halves run side by side on ``workers`` processes."""
    if workers <= 1:
        return serial_map, (lambda: None)
    import multiprocessing as mp

    # fork from a single-threaded process: a plain script without a __main__ guard keeps working (spawn
    # re-runs the script in every worker) and compiled kernels come along; with other threads alive (a host
    # application) a fork could copy a held lock, so spawn, which loads kernels from the on-disk cache
    import threading
    from concurrent.futures import ProcessPoolExecutor

    method = "fork" if threading.active_count() == 1 and "fork" in mp.get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context(method))

    def run(fn, tasks):
        if len(tasks) <= 1:
            return [fn(t) for t in tasks]
        return list(pool.map(fn, tasks))
    # one task started now, its result read later (a Future): the pool works while this process fits something else
    run.submit = pool.submit
    return run, (lambda: pool.shutdown(cancel_futures=True))


def trace_and_confirm(ctx, held: Fit, fspec, phi, res, present: set = frozenset(), closed: set = frozenset()):
    """Screen the whole library by evidence, then confirm the best few by the full ARD re-selection.

    ``ctx``: the loop's :class:`~ardcore.loop.config.LoopContext`; ``held``: the model held, ``fspec, phi``
    with its pruned terms fixed, at its posterior mean; ``res``: its residuals. ``present``: (library name,
    target) of the effects the model holds already; they are not screened again. ``closed``: states whose
    equation has a fixed form (a hysteresis, a sensor, :mod:`.states`): nothing is added to them or built
    on them (a term of a Bouc-Wen state is a basis expansion of it, not an effect). Returns the
    :class:`Screening` and the confirmations (:func:`confirm`)."""
    say, mapper, col = ctx.say, ctx.mapper, ctx.column
    cand, data = held.cand, held.data
    extra_effects = ctx.extra_effects
    spectrum = res.tests[col]["spectrum"]
    peaks = forcing_peaks(fspec, spectrum, res.noise_spectra)
    scales = {s: float(np.nanstd(res.smoothed[:, i])) for i, s in enumerate(fspec.states)}
    levels = {s: (float(np.nanmin(res.smoothed[:, i])), float(np.nanmedian(res.smoothed[:, i])),
                  float(np.nanmax(res.smoothed[:, i]))) for i, s in enumerate(fspec.states)}
    # forcing frequencies: the peaks forcing_peaks picks (each refined by the screen)
    effects = candidate_effects(fspec, scales=scales, levels=levels, frequencies=[(p["f"], p["resolution"])
                                                                               for p in peaks],
                                extra=list(extra_effects), declared=ctx.spec.models[0].model_spec())
    if closed:
        pattern = re.compile(r"\b(" + "|".join(map(re.escape, closed)) + r")\b")
        effects = [e for e in effects if not any(pattern.search(t) for t in (*e.terms, *e.between))]
    inp = ScreenInput(fspec, phi, data, cand.substeps)
    targets = [s for s in dynamic_states(fspec) if s not in closed]
    screened = screen_effects(inp, effects, targets, list(fspec.observed_columns), progress=say,
                              map_fn=mapper)
    screened = [c for c in screened if ((c.source or c.effect).name, c.target) not in present]
    say("screen: " + ", ".join(f"{c.effect.name} -> {c.target} (ln BF ~ {c.log_bayes_factor:.1f})"
                               for c in screened[:5]))
    return Screening(inp, screened), confirm(ctx, held, inp, screened, len(screened))


class Screening(NamedTuple):
    """A round's screen: what it read (``inp``) and every candidate it scored, best first (``screened``)."""

    inp: ScreenInput
    screened: list


def hidden(screening: Screening, confirmed: list) -> list:
    """The screened candidates the forward selection set aside as explained by those it picked
    (``conditional_on``), not confirmed themselves. Once the picked ones are out (the evidence or the criterion
    refused them), what they explained is no longer explained: these are the evidence's next proposals."""
    tried = {id(c.screened) for c in confirmed}
    return [c for c in screening.screened if getattr(c, "conditional_on", None) and id(c) not in tried]


NOISE_SHARE = 0.1
"""A declared measurement noise whose variance is under this share of the innovations' (the median over the
record) is one the screen cannot see raised: its score is taken at the declared level, where the measurement's
term in the innovations' variance vanishes beside the state's, so it is ~0 where the level is worth hundreds of
nats (a clean oscillator declared 25 times too quiet screened it at 0.1 and took a forcing, a mode and an
actuator in its place). Such a level, when it screened under ``min_score``, is confirmed once all the same, and
taken only when it free-runs better held out. A declared level the record's noise is far below is seen by the
score (its term dominates): forcing it would let a coloured, filtered noise (the reference LCO records: ln BF
19,000 for a tenth of the declared level) decide a round."""


def quiet_channels(inp: ScreenInput) -> dict:
    """The observed columns whose declared measurement noise is under :data:`NOISE_SHARE` of the innovations'
    variance at the model ``inp`` screens from: {column: that share}."""
    from ..likelihood.ekf import compile_model

    cm = compile_model(inp.spec)
    R = np.asarray(cm.obs_std(inp.phi), dtype=float).reshape(-1) ** 2
    S = np.asarray(cm.filter(inp.phi, inp.data, inp.substeps).innovation_var, dtype=float)
    S = S.reshape(S.shape[0], -1)
    out = {}
    for j, col in enumerate(inp.spec.observed_columns):
        s = S[:, j][np.isfinite(S[:, j]) & (S[:, j] > 0)]
        share = float(np.median(R[j] / s)) if s.size else math.nan
        if share < NOISE_SHARE:  # a NaN level or no innovation: nothing to judge
            out[col] = share
    return out


def confirm(ctx, held: Fit, inp: ScreenInput, screened: list, n_tried: int) -> list:
    """The best distinct candidates of ``screened`` (forward selection on the screened evidence, with their
    twins) re-selected under ARD side by side: their confirmations (:class:`Confirmation`). ``n_tried``: the
    candidates the screen tried, whose number sets the threshold each must gain (``library_prior``)."""
    spec, config, say, mapper = ctx.spec, ctx.config, ctx.say, ctx.mapper
    cand, row, bmr, data = held
    priors, fixed = essential_from_row(cand, row)
    cspec = spec.model_copy(update={"maximiser": spec.maximiser.model_copy(
        update={"alpha_start": max(config.alpha_start, spec.maximiser.alpha_start)})})
    confirmed = []
    picked = distinct_candidates(inp, screened, config.top_k, config.min_score)
    # a noise level the screen scored under min_score on a quiet channel is one it is blind to (:data:`NOISE_SHARE`);
    # a level it scored (Silverbox's, 17,800 nats, set aside as explained by an offset) is the forward selection's
    blind = [c for c in screened if c.effect.where == "noise" and c.log_bayes_factor < config.min_score
             and c.target not in ctx.forced and not any(c is p for p in picked)]
    quiet = quiet_channels(inp) if blind else {}
    forced = [c for c in blind if c.target in quiet]
    if forced:
        say("  the declared measurement noise is under " f"{NOISE_SHARE:.0%} of the innovations' variance on "
            + ", ".join(f"{c.target} ({quiet[c.target]:.2g})" for c in forced)
            + ": the screen cannot see its level, which is confirmed all the same")
        ctx.forced.update(c.target for c in forced)
        picked += forced
    rivals = _rivals(screened, picked, config, say)
    by_id = {id(c): c for c in screened}
    chosen = list(picked) + [by_id[i] for i in rivals]

    def task(sc: Screened, fit_shape: bool = True):
        eff, shape = fitted_effect(cand.model_spec(), sc, sc.target) if fit_shape else (sc.effect, {})
        aspec, names = augment(cand.model_spec(), eff, sc.target, sc.scales)
        acand = CandidateSpec(model=aspec, name=aspec.name, priors={**priors, **shape}, fixed=fixed,
                              ard=names, substeps=cand.substeps)
        # new terms start at the screen's estimate (a Laplace search from 0 would walk there by Nelder-Mead),
        # a fitted shape at the profile's maximum
        warm = warm_with(bmr.sampler, names + list(shape), sc.coefficients + [sc.shape_value] * len(shape)) \
            if spec.evidence == "laplace" or shape else bmr.sampler
        return (eff, shape), (acand, with_columns(data, eff), cspec, warm, config.posterior)

    fitted, tasks = map(list, zip(*[task(sc) for sc in chosen])) if chosen else ([], [])
    if chosen:
        say("confirming by evidence: " + ", ".join(f"{c.effect.name} -> {c.target}" for c in chosen))
    # a shape profiled to the edge of its range may leave it when fitted: its fit at the screen's shape runs
    # beside it (in the same batch, not after it)
    edge = [i for i, (_, shape) in enumerate(fitted)
            if shape and at_range_edge(chosen[i].source, chosen[i].shape_value)]
    hedge = {i: task(chosen[i], fit_shape=False) for i in edge}
    results = mapper(fit_task, tasks + [tk for _, tk in hedge.values()])
    hedged = dict(zip(edge, results[len(tasks):]))
    results = results[:len(tasks)]
    # a fitted shape that leaves the library's range has become another effect (a saturation level near 0 is
    # an offset, which the library has on its own): that candidate is confirmed at the screen's shape instead
    outside = [i for i, ((_, shape), (arow, _)) in enumerate(zip(fitted, results))
               if shape and not _within(chosen[i].source, arow.mean.get(next(iter(shape)), math.nan))]
    if outside:
        say("  fitted shape outside the library's range, confirmed at the screen's shape instead: "
            + ", ".join(chosen[i].effect.name for i in outside))
        redo = [i for i in outside if i not in hedged]
        hedge.update({i: task(chosen[i], fit_shape=False) for i in redo})
        hedged.update(zip(redo, mapper(fit_task, [hedge[i][1] for i in redo])))
        for i in outside:
            (fitted[i], tasks[i]), results[i] = hedge[i], hedged[i]
    # the prior odds of each of the N candidates tried (Scott and Berger 2010): its ln BF also pays ln N
    threshold = config.min_log_bf + (math.log(max(1, n_tried)) if config.library_prior else 0.0)
    if chosen and config.library_prior:
        say(f"  an effect must gain {threshold:.1f} nats: {config.min_log_bf:g} + ln {n_tried} "
            f"(the prior odds of one of the {n_tried} candidates tried)")
    for sc, (eff, shape), (acand, adata, *_), (arow, amr) in zip(chosen, fitted, tasks, results):
        confirmed.append(_confirmation(sc, eff, shape, Fit(acand, arow, amr, adata), row, threshold, say))
        confirmed[-1].forced = any(sc is c for c in forced)
    _resolve_twins(confirmed, rivals, config, say)
    return confirmed


def forcing_peaks(spec: ModelSpec, spectrum: dict, noise_spectra: dict | None = None) -> list[dict]:
    """The peaks a periodic forcing is screened at, each with its spectrum's resolution: of the innovations'
    spectrum the two strongest that are not harmonics of the record's dominant oscillation and, in a model
    driven by inputs, the peak at that oscillation itself (a driven response peaks at its resonance, where a
    periodic disturbance near it shows too; in a self-excited oscillation the fundamental and its harmonics
    are the missing nonlinearity's); and the strongest non-harmonic peak of the process noise the filter
    injected into each state (:func:`~ardcore.loop.residuals.noise_peaks`: a slow forcing the filter follows
    by that noise is faint in the innovations), unless a peak already picked lies within its resolution. The
    coherence test and the evidence decide."""
    peaks = [{**p, "resolution": spectrum.get("resolution", 0.0)} for p in spectrum["peaks"]]
    out = [p for p in peaks if not p.get("harmonic")][:2]
    out += [p for p in peaks if p.get("harmonic") == 1][:1] if user_inputs(spec) else []
    for sp_ in (noise_spectra or {}).values():
        top = next((p for p in sp_["peaks"] if not p.get("harmonic")), None)
        if top and all(abs(top["f"] - p["f"]) > max(sp_["resolution"], p["resolution"]) for p in out):
            out.append({**top, "resolution": sp_["resolution"]})
    return out


def _rivals(screened: list, picked: list, config, say) -> dict:
    """{id of a redundant candidate: id of the picked one it is a twin of}. A redundant candidate the screen
    cannot tell from the one it was dropped for (a saturating stiffness and a free-play; a smooth sign of two
    widths) is confirmed too: the full evidence decides between the twins."""
    redundant = [c for c in screened[:12] if getattr(c, "conditional_on", None)]
    rivals = {}
    for c in redundant:
        near = [p for p in picked if p.effect.name in c.conditional_on
                and list(rivals.values()).count(id(p)) < config.rivals
                and abs(p.log_bayes_factor - c.log_bayes_factor) <= config.rival_nats]
        if near:
            rivals[id(c)] = id(near[0])
    redundant = [c for c in redundant if id(c) not in rivals]
    if redundant:
        say("not confirmed (explained by a better candidate): " + ", ".join(
            f"{c.effect.name} -> {c.target}" for c in redundant))
    return rivals


def _resolve_twins(confirmed: list, rivals: dict, config, say) -> None:
    """Of twins only the one with the higher evidence goes on (the others' ``survives`` is cleared)."""
    by_screen = {id(c.screened): c for c in confirmed}
    for pid in dict.fromkeys(rivals.values()):
        twins = [by_screen.get(i) for i in [pid] + [r for r, p in rivals.items() if p == pid]]
        twins = [c for c in twins if c and c.survives]
        if len(twins) < 2:
            continue
        # one base: the evidence (less a profile's Occam) decides; within twin_nats, the twin with fewer
        # parameters (a cubic and a sine stiffness whose period the data do not reach tie; take the cubic)
        top = max(c.log_bayes_factor for c in twins)
        hi = min((c for c in twins if c.log_bayes_factor >= top - config.twin_nats),
                 key=lambda c: (len(c.fit.cand.model_spec().parameters), -c.log_bayes_factor))
        for lo in twins:
            if lo is not hi:
                lo.survives, lo.rival_of = False, hi.effect
        say(f"  {', '.join(c.effect for c in twins if c is not hi)} and {hi.effect} explain the same; "
            f"{hi.effect} has the higher evidence")


def _within(effect: Effect, value: float) -> bool:
    """``value`` inside ``effect``'s shape range (the library's)."""
    _, lo, hi = effect.shape
    return lo <= value <= hi


EDGE = 0.05
"""A profiled shape within this distance (in log) of its range's end is at the edge (the golden-section
refinement of :func:`ardcore.screening.screen._screen_shape` ends within ~0.04 of an end it climbs to): its fit may
leave the range."""


def at_range_edge(effect: Effect, value: float, end: str = "") -> str:
    """Which end (``"low"``, ``"high"``) of ``effect``'s shape range ``value`` is at or beyond ("" for none);
    with ``end``, only that one counts."""
    _, lo, hi = effect.shape
    log = lo > 0
    high = value >= (hi * math.exp(-EDGE) if log else hi)
    low = value <= (lo * math.exp(EDGE) if log else lo)
    at = "high" if high else "low" if low else ""
    return at if not end or at == end else ""


def fitted_effect(ms, sc: Screened, target: str) -> tuple[Effect, dict]:
    """The effect a confirmation fits and the prior of its shape parameter ({} for none): a width, a friction
    velocity or a stiffness period is fitted with the coefficients (the screen's profile maximum is only
    where it starts), so its posterior is reported and its evidence integrates over it; a forcing
    frequency stays at the screen's refined value (its sine and cosine are input columns)."""
    src = sc.source
    if src is None or not src.shape or src.shape[0] == "f" or sc.shape_value is None:
        return sc.effect, {}
    if src.degenerate and at_range_edge(src, sc.shape_value, src.degenerate):
        # the profile climbs to where the effect becomes a simpler family (the model's own or the library's):
        # the data want that family, and a fitted shape would walk along the ridge beyond the range
        return sc.effect, {}
    pname = shape_parameter_name(ms, src, target)
    return src.with_shape_parameter(pname), {pname: shape_prior(src)}


def _confirmation(sc: Screened, eff: Effect, shape: dict, fit: Fit, row: ModelFit, threshold: float,
                  say) -> Confirmation:
    """One confirmation: the screened candidate ``sc`` re-selected with its terms under ARD (``fit``) against
    the current model's ``row``."""
    arow = fit.row
    names = list(fit.cand.ard_names)
    # a shape picked by the screen's profile (a forcing frequency found in the spectrum) pays its Occam
    # factor; a fitted shape has paid it through its prior
    gain = arow.log_evidence - row.log_evidence - (0.0 if shape else sc.shape_occam)
    why = arow.degenerate() or next((f"{arow.name}: {w}" for w in arow.warnings if DOMINATED in str(w)), None)
    if not math.isfinite(gain) or why is not None:
        gain = -math.inf  # the re-selection failed (no evidence that is a result): it confirms nothing, and says so
    kept = [n for n in names if n in arow.kept]
    scale = dict(zip(names, sc.scales))
    # the EKF evidence takes coloured innovations as white: the support it gives is divided by the factor
    # the screen found the score's variance understated by (1 for white innovations)
    adjusted = gain / sc.inflation if gain > 0 else gain
    if gain == -math.inf:
        say(f"  {sc.effect.name}: the re-selection gave no evidence that is a result ({why or 'not finite'}): "
            "not confirmed")
    else:
        say(f"  {eff.name}: ln BF = {gain:.2f}" + (f" ({adjusted:.2f} adjusted for coloured innovations, "
                                                     f"x 1/{sc.inflation:.2g})" if sc.inflation > 1.05 else "")
            + f", ARD keeps {kept or 'nothing'}")
    # a fitted shape is shown at its posterior mean, e.g. sine_stiffness(y,L=1.07)
    shown = next((sc.source.at(arow.mean[n]).name for n in shape if n in arow.mean), eff.name)
    return Confirmation(
        effect=shown, target=sc.target, screened=sc, log_evidence=arow.log_evidence,
        log_evidence_se=arow.log_evidence_se, log_bayes_factor=gain, adjusted_log_bayes_factor=adjusted,
        threshold=threshold, kept_terms=kept, psi_opt=dict(arow.psi_opt),
        # coefficients in the term's own units (the fit uses the normalised ones)
        posterior={n: arow.physical(n, scale[n]) for n in names if n in arow.mean},
        shape={n: arow.physical(n, 1.0) for n in shape if n in arow.mean}, scales=scale,
        survives=bool(kept) and adjusted > threshold, fit=fit, fitted_effect=eff, shape_prior=shape)
