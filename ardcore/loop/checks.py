"""The loop's checks on what it adds (docs/method.md section 8, step 4): a survivor's stability over the two
halves of the record (:func:`split_stability`), the round's survivors fitted together (:func:`joint_fit`)
and, after each round, whether effects of earlier rounds are
still worth their place beside the later ones (:func:`backward_check`, with the Savage-Dickey shortcut
:func:`savage_dickey` for effects far above their threshold), and which of the user's declared terms an added
effect may replace (:func:`declared_rivals`, :func:`replace_laws`); and that a survivor's fit is a result
(:func:`not_degenerate`). What is dropped must also free-run no worse held out (the loop's criterion,
:meth:`~.criterion.Criterion.refuses_removal`).
"""

from __future__ import annotations

import math
import re
from typing import NamedTuple

import numpy as np

from .confirm import Confirmation, Fit, fit_task, essential_from_row, warm_with
from ..effects.base import Effect, augment, with_columns
from ..jsonio import is_pruned
from ..model.declaration import ModelSpec
from ..data import Dataset
from .replace import linear_terms
from ..selection.fit import ModelFit
from ..selection.spec import CandidateSpec, StudySpec
from ..selection.study import run_candidate


def _continued_half(half: CandidateSpec, row: ModelFit, data: Dataset, mid: int) -> tuple[CandidateSpec, Dataset]:
    """The second half as a continuation of the record: its filter starts from the state the full-record
    filter (at the full fit's posterior mean) holds at sample ``mid - 1``, that sample's observations
    removed (already used). A record rarely stops at rest in the middle; starting the second half from
    the model's declared initial state, which is set in absolute units, biases its fit whenever the
    signal's scale differs from those units (the halves then disagree for a reason that is not the effect).
    The filtered standard deviations are doubled: the start must not hold the half to the full fit."""
    from ..likelihood.ekf import compile_model

    ms = half.model_spec()
    phi = {k: float(row.mean[k]) for k in ms.free_parameters if k in row.mean}
    if len(phi) != len(ms.free_parameters) or mid < 2:
        return half, data.slice(mid, None)
    fr = compile_model(ms).filter(phi, data, half.substeps)
    x, P = fr.filtered[mid - 1], fr.filtered_cov[mid - 1]
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
        return half, data.slice(mid, None)
    model = half.resolved().model_copy(update={
        "initial_mean": {s: float(x[i]) for i, s in enumerate(ms.states)},
        "initial_std": {s: 2.0 * math.sqrt(max(float(P[i, i]), 0.0)) + 1e-12 for i, s in enumerate(ms.states)},
    }).revalidate()
    d2 = data.slice(mid - 1, None)
    for o in ms.observed_columns:
        d2.columns[o][0] = np.nan
    return half.model_copy(update={"model": model}), d2


def split_stability(spec: StudySpec, c: Confirmation, config, say, mapper) -> dict:
    """Refit the augmented model on each half of the record, the new terms' ARD priors frozen at psi_opt."""
    from ..model.priors import frozen_ard

    acand, data = c.fit.cand, c.fit.data
    priors = dict(acand.priors)
    for n in c.kept_terms:
        priors[n] = frozen_ard(c.psi_opt[n])
    fixed = dict(acand.fixed)
    fixed.update({n: 0.0 for n in acand.ard_names if n not in c.kept_terms})
    half = CandidateSpec(model=acand.model, name=acand.label, priors=priors, fixed=fixed, ard=[],
                         substeps=acand.substeps)
    # halves of the *observed* samples (a record may end in missing values)
    seen = np.flatnonzero(np.any(np.column_stack([np.isfinite(data.columns[o])
                                                  for o in acand.model_spec().observed_columns]), axis=1))
    n = len(data)
    mid = int(seen[seen.size // 2]) if seen.size >= 4 else n // 2
    parts = []
    warm = c.fit.mr.sampler
    second, data2 = _continued_half(half, c.fit.row, data, mid)
    tasks = [(half, data.slice(0, mid), spec, warm, config.posterior), (second, data2, spec, warm, config.posterior)]
    for r, _ in mapper(fit_task, tasks):
        parts.append({k: (r.mean[k], r.sd[k]) for k in c.kept_terms})
    z = {k: abs(parts[0][k][0] - parts[1][k][0]) / math.hypot(parts[0][k][1], parts[1][k][1])
         for k in c.kept_terms}
    rel = {k: abs(parts[0][k][0] - parts[1][k][0]) / max(abs(parts[0][k][0]), abs(parts[1][k][0]), 1e-300)
           for k in c.kept_terms}
    same_sign = all(parts[0][k][0] * parts[1][k][0] > 0 for k in c.kept_terms)
    # disagreement beyond the noise AND large against the effect's own size (long records have tiny se)
    stable = all(z[k] <= config.split_z or (same_sign and rel[k] <= config.split_rel) for k in z)
    say(f"  {c.effect}: halves give " + ", ".join(
        f"{k} = {parts[0][k][0]:.4g} +- {parts[0][k][1]:.2g} / {parts[1][k][0]:.4g} +- {parts[1][k][1]:.2g} "
        f"(z = {z[k]:.1f})" for k in z) + ("" if stable else ": NOT stable over the record"))
    return {"stable": stable, "z": z, "relative_difference": rel, "halves": parts}


class Added(NamedTuple):
    """An effect the loop added: its report record, the round, its coefficients' names, and what it must keep
    earning (the threshold it passed and the coloured-innovation factor its ln BF was divided by)."""

    record: dict
    round: int
    params: list
    threshold: float
    inflation: float
    key: tuple = ()
    """(the library's name of the effect, its target): what the model now holds."""


SD_MARGIN = 20.0
"""Nats by which a Savage-Dickey estimate must clear a threshold for the backward check to trust it."""


def savage_dickey(cand: CandidateSpec, row: ModelFit, mr, names: list[str]) -> float | None:
    """ln Bayes factor of the fitted model against it with ``names`` fixed at 0, by the Savage-Dickey density
    ratio ln p(0) - ln p(0 | d) with the posterior of those terms taken Gaussian (their draws' mean and
    covariance; an ARD term's prior is N(0, 1/alpha) at its optimal alpha); None where it does not apply
    (a term without a normal prior, no draws)."""
    from scipy.stats import multivariate_normal

    from ..model.priors import Normal

    res = getattr(mr, "sampler", None)
    priors, _ = essential_from_row(cand, row)
    pri = [priors.get(n) for n in names]
    if res is None or res.samples.size == 0 or not names or not all(isinstance(p, Normal) for p in pri) \
            or any(n not in res.names for n in names):
        return None
    X = res.samples.reshape(-1, len(res.names))[:, [list(res.names).index(n) for n in names]]
    m, C = X.mean(axis=0), np.atleast_2d(np.cov(X.T))
    try:
        ln_post0 = float(multivariate_normal(m, C).logpdf(np.zeros(len(names))))
    except (ValueError, np.linalg.LinAlgError):
        return None
    return float(sum(p.logpdf(0.0) for p in pri)) - ln_post0


LAPLACE_MARGIN = 1000.0
"""Nats a declared term's Laplace estimate (:func:`needed`) must show for it to stay without a refit: the
Gaussian marginal is a rough guide where an effect can take the term's role through its shape, so only a term
worth orders of magnitude more than any Occam factor is spared the refit (Silverbox's k and c: 10^5 nats)."""


def needed(cand: CandidateSpec, row: ModelFit, name: str) -> float | None:
    """The Laplace estimate of the ln Bayes factor for keeping the declared parameter ``name`` (its essential
    prior) against fixing it at 0, from its marginal posterior taken Gaussian (mean m, sd s): the
    likelihood lost at 0, (m/s)^2 / 2, less its Occam factor, -ln(p(m) sqrt(2 pi) s). A declared stiffness
    whose posterior sits hundreds of sd from 0 is worth that many nats without a refit to say so; None
    where it does not apply (no essential prior, no spread, 0 outside the prior's support: fixing it there is
    not a nested model of this prior)."""
    prior = cand.priors.get(name)
    m, sd = row.mean.get(name), row.sd.get(name)
    if prior is None or m is None or not sd or not math.isfinite(sd) or sd <= 0:
        return None
    lp = prior.logpdf(float(m))
    if not math.isfinite(lp):
        return None
    return 0.5 * (m / sd) ** 2 + lp + 0.5 * math.log(2 * math.pi) + math.log(sd)


def backward_check(ctx, held: Fit, earlier_added: list[Added], this_round: int, crit=None) -> Fit:
    """Effects added in earlier rounds that the later ones made redundant are dropped again.

    Forward selection adds what the screen ranks first; a later effect can explain the same residual better
    (a tank's input nonlinearity added first, its square-root outflow next: at equilibrium the level follows
    the input). Each effect of an earlier round is refitted out (its terms fixed at 0, side by side on the
    loop's pool); one whose ln Bayes factor (adjusted for coloured innovations as when it was added) no
    longer reaches the threshold it passed then (``min_log_bf`` + ln N: its prior odds as one of N library
    candidates have not changed) is dropped, the weakest first, and the rest are checked again. An effect
    whose Savage-Dickey ln Bayes factor (:func:`savage_dickey`) clears its threshold by ``SD_MARGIN`` nats
    is kept without a refit (an offset worth 60,000 nats does not need one to say so). ``earlier_added``: the
    effects of the rounds before ``this_round``. With ``crit`` (the loop's :class:`~.criterion.Criterion`) an
    effect is dropped only when the model without it also free-runs no worse held out. Returns the model then
    held.
    """
    spec, config, say, mapper = ctx.spec, ctx.config, ctx.say, ctx.mapper
    cand, row, bmr, data = held
    said = set()
    while True:
        earlier = [x for x in earlier_added if not x.record.get("removed")]
        sd = [savage_dickey(cand, row, bmr, x.params) for x in earlier]
        clear = [x.record["effect"] for x, b in zip(earlier, sd)
                 if b is not None and b / x.inflation >= x.threshold + SD_MARGIN]
        if set(clear) - said:  # said once, not again after each effect dropped
            say(f"  kept without a refit (Savage-Dickey ln BF clears the threshold by {SD_MARGIN:g} nats): "
                + ", ".join(c for c in clear if c not in said))
            said.update(clear)
        earlier = [x for x, b in zip(earlier, sd) if b is None or b / x.inflation < x.threshold + SD_MARGIN]
        if not earlier:
            return Fit(cand, row, bmr, data)
        tasks = [(cand.model_copy(update={"fixed": {**cand.fixed, **{n: 0.0 for n in x.params}}}), data, spec,
                  bmr.sampler, config.posterior) for x in earlier]
        fits = mapper(fit_task, tasks)
        gain = [row.log_evidence - frow.log_evidence for frow, _ in fits]
        # a model without the effect that has no finite evidence cannot argue for dropping it
        worth = [(g / x.inflation if g > 0 else g) if math.isfinite(g) else math.inf for g, x in zip(gain, earlier)]
        k = int(np.argmin([w - x.threshold for w, x in zip(worth, earlier)]))
        x = earlier[k]
        if worth[k] >= x.threshold:
            return Fit(cand, row, bmr, data)
        why = crit.refuses_removal(Fit(cand, row, bmr, data), Fit(tasks[k][0], *fits[k], data)) if crit else None
        if why is not None:
            say(f"  {x.record['effect']} (added in round {x.round}) is worth {worth[k]:.2f} nats beside the later "
                f"effects, but {why}: kept")
            return Fit(cand, row, bmr, data)
        x.record["removed"], x.record["log_bayes_factor_after"] = this_round, float(worth[k])
        say(f"  {x.record['effect']} (added in round {x.round}) is worth {worth[k]:.2f} nats beside the later "
            f"effects, below the {x.threshold:.1f} it passed: dropped")
        cand, (row, bmr) = tasks[k][0], fits[k]


def joint_fit(ctx, held: Fit, survivors) -> Fit:
    """The current model with every surviving effect added, each new term at the ARD precision its own
    re-selection found (pruned terms fixed at 0); one evidence evaluation checks they hold together.

    Returns the :class:`Fit` of the model with all of them."""
    from ..model.priors import frozen_ard

    spec, config, say = ctx.spec, ctx.config, ctx.say
    cand, row, _, data = held
    priors, fixed = essential_from_row(cand, row)
    aspec, adata = cand.model_spec(), data
    for c in survivors:
        n = list(c.scales)
        aspec, n = augment(aspec, c.fitted_effect, c.target, [c.scales[k] for k in n], names=n)
        adata = with_columns(adata, c.fitted_effect)
        priors.update(c.shape_prior)
        for k in n:
            a = c.psi_opt.get(k, 0.0)
            if k not in c.kept_terms or is_pruned(a):
                fixed[k] = 0.0
            else:
                priors[k] = frozen_ard(a)
    acand = CandidateSpec(model=aspec, name=aspec.name, priors=priors, fixed=fixed, ard=[], substeps=cand.substeps)
    say("fitting the distinct survivors together: " + ", ".join(c.effect for c in survivors))
    arow, amr = run_candidate(acand, adata, spec, 0, warm=joint_start(acand, adata, survivors, fixed),
                              final_posterior=config.posterior)
    say(f"  together: ln BF = {arow.log_evidence - row.log_evidence:.2f}")
    return Fit(acand, arow, amr, adata)


def joint_start(acand: CandidateSpec, adata, survivors, fixed: dict):
    """The warm start of a joint fit: of the survivors' own posteriors, each carrying every other survivor's
    terms (and fitted shape) at that one's posterior mean, the one where the joint posterior is highest.

    The model's shared parameters (stiffness, input gain, process noise) move with each effect added, so
    the survivors' fits disagree on them by many standard deviations; from the wrong one a Laplace search
    walks to the joint mode by thousands of Nelder-Mead evaluations."""
    from ..evidence.evaluate import warm_point, build_target

    target = build_target(acand.model_spec(), dict(acand.priors), {}, adata, acand.substeps)
    best, best_lp = None, -math.inf
    for s in survivors:
        others = {n: v for c in survivors if c is not s
                  for n, v in c.fit.row.mean.items() if n not in s.fit.row.mean and n not in fixed}
        warm = warm_with(s.fit.mr.sampler, list(others), list(others.values())) if others else s.fit.mr.sampler
        lp = target(warm_point(target, warm)).log_posterior
        if best is None or lp > best_lp:
            best, best_lp = warm, lp
    return best


class Rival(NamedTuple):
    """A declared term an added effect competes with: ``parameter`` times ``term`` in ``target``'s drift."""

    parameter: str
    term: str
    target: str
    effect: str


def declared_rivals(spec: ModelSpec, added: list[tuple[Effect, str]], new_parameters: set) -> list[Rival]:
    """The user's declared terms that an effect just added may replace.

    Forward selection can only add: when the declared law is wrong (a linear outflow where the physics is a
    square root of the level, a linear spring where the restoring force saturates, a linear pipe between two
    tanks where the flow follows a power of the level), the added effect carries the right law and the
    declared term lingers beside it. A rival is a free parameter of the user's (not one an effect brought)
    that appears only in the drifts the effect acts on (its target's; a flow's source and receiver), linearly,
    its terms depending on the states of the effect's terms and on no input, and nowhere else in the model
    (so fixing it to 0 removes exactly that law). The evidence of the model without it decides
    (:func:`replace_laws`).
    """
    states, inputs = set(spec.states), set(spec.inputs)
    laws = linear_terms(spec, new_parameters)
    out = []
    for eff, target in added:
        acts_on = list(eff.between) if eff.where == "flow" else [target] if eff.where == "drift" else []
        if not acts_on or any(s not in states for s in acts_on):
            continue
        states_of_effect = {x for x in states if any(re.search(rf"\b{re.escape(x)}\b", t) for t in eff.terms)}
        for lt in laws:
            if acts_on[0] not in lt.terms or any(s not in acts_on for s in lt.terms):
                continue
            used = lt.names & states
            if lt.names & inputs or not used or not used <= states_of_effect:
                continue
            term = next(iter(lt.terms.values()))
            out.append(Rival(lt.parameter, str(-term if term.could_extract_minus_sign() else term), acts_on[0],
                             eff.name))
    return out


def not_degenerate(survivors: list, say) -> list:
    """The survivors whose fit is a result (:meth:`ModelFit.degenerate`: a posterior that moved, an evidence with
    a real error); the others are marked and say why."""
    kept = []
    for c in survivors:
        why = c.fit.row.degenerate()
        if why is None:
            kept.append(c)
            continue
        c.survives, c.rejected = False, why
        say(f"  {c.effect}: not added: {why}")
    return kept


def brought(rounds: list) -> set:
    """The parameters the loop's effects and states brought (coefficients, shapes, a lag's rate): never a
    declared law."""
    return {n for r in rounds for x in r.added for n in x.params} | {
        n for r in rounds for x in r.added for n in x.record.get("shape", {})} | {
        n for r in rounds for x in r.record.get("replaced", []) if x.get("state") for n in x["state"]["parameters"]}


def _nats(v: float) -> str:
    """A Laplace estimate as a reader takes it: far past any threshold it says only that (a coefficient many
    hundred sd from 0 gives a number of thirty digits)."""
    return f"~{v:.1f}" if v < 1e4 else "over 10,000"


def replace_laws(ctx, held: Fit, rounds: list, crit=None) -> Fit:
    """Drop the declared terms this round's effects replace (:func:`declared_rivals`): each is refitted out
    (its parameter fixed at 0, side by side on the loop's pool); the one whose removal raises ln Z most is
    dropped when the model without it is more probable (ln Bayes factor > 0 for the smaller model, equal
    prior odds) and, with ``crit`` (the loop's :class:`~.criterion.Criterion`), free-runs no worse held out.
    Repeats while one goes. Recorded in the
    round as ``replaced``. Returns the model then held."""
    spec, config, say, mapper = ctx.spec, ctx.config, ctx.say, ctx.mapper
    cand, row, bmr, data = held
    rnd = rounds[-1]
    new_params = brought(rounds)
    added = [(e, x.record["target"]) for e, x in zip(rnd.effects, rnd.added)]
    replaced = rnd.record.setdefault("replaced", [])
    said = set()
    while True:
        rivals = declared_rivals(cand.model_spec(), added, new_params)
        worth = {r.parameter: needed(cand, row, r.parameter) for r in rivals}
        clear = [r for r in rivals if (worth[r.parameter] or -math.inf) >= LAPLACE_MARGIN and r.parameter not in said]
        for r in clear:
            say(f"  the declared {r.parameter}*({r.term}) in {r.target}'s equation stays beside {r.effect} without a "
                f"refit (its posterior excludes 0: worth {_nats(worth[r.parameter])} nats by the Laplace estimate)")
            said.add(r.parameter)
        rivals = [r for r in rivals if (worth[r.parameter] or -math.inf) < LAPLACE_MARGIN]
        if not rivals:
            return Fit(cand, row, bmr, data)
        tasks = [(cand.model_copy(update={"fixed": {**cand.fixed, r.parameter: 0.0}}), data, spec, bmr.sampler,
                  config.posterior) for r in rivals]
        fits = mapper(fit_task, tasks)
        gain = [frow.log_evidence - row.log_evidence for frow, _ in fits]
        k = int(np.nanargmax(gain)) if np.isfinite(gain).any() else 0
        r = rivals[k]
        if not gain[k] > 0:
            worth = (f"worth {-gain[k]:.1f} nats" if math.isfinite(gain[k]) else
                     "the model without it could not be fitted to a finite evidence")
            say(f"  the declared {r.parameter}*({r.term}) in {r.target}'s equation stays beside {r.effect} "
                f"({worth})")
            return Fit(cand, row, bmr, data)
        fit = Fit(tasks[k][0], fits[k][0], fits[k][1], data)
        why = crit.refuses_removal(Fit(cand, row, bmr, data), fit) if crit else None
        if why is not None:
            say(f"  the declared {r.parameter}*({r.term}) stays: {why}")
            return Fit(cand, row, bmr, data)
        replaced.append({"parameter": r.parameter, "term": r.term, "target": r.target, "by": r.effect,
                         "log_bayes_factor": float(gain[k])})
        say(f"  {r.effect} replaces the declared {r.parameter}*({r.term}) in {r.target}'s equation "
            f"(ln BF {gain[k]:.1f} for the model without it)")
        cand, (row, bmr) = tasks[k][0], fits[k]
