"""Confirmation of screened candidates by the full ARD re-selection (method.md section 9, step 4).

:func:`trace_and_confirm` screens the library (:mod:`ardcore.screen`) and re-selects the model with each of
the best distinct candidates added under ARD, side by side on a process pool; :func:`split_stability`
refits a survivor on each half of the record; :func:`joint_fit` fits the distinct survivors of a round
together. :func:`ardcore.diagnose.diagnose` runs the loop around them.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .data import Dataset
from .effects import Effect, augment, dynamic_states, shape_parameter_name, shape_prior, with_columns
from .families import candidate_effects
from .jsonio import is_pruned
from .screen import Screened, distinct_candidates, screen_effects
from .fit import ModelFit
from .study import CandidateSpec, StudySpec, run_candidate

INF = math.inf


class Fit(NamedTuple):
    """A candidate re-selected on its data: the candidate, its summary row, its maximiser result, the data
    (with any columns its effects need)."""

    cand: CandidateSpec
    row: dict
    mr: object
    data: Dataset


def essential_from_row(cand: CandidateSpec, row: ModelFit) -> tuple[dict, dict]:
    """Priors of the fitted model with kept ARD terms frozen at their optimal alpha; pruned terms fixed."""
    from .priors import Flat, Normal

    priors = dict(cand.priors)
    fixed = dict(cand.fixed)
    for k, a in row.psi_opt.items():
        if is_pruned(a):
            fixed[k] = 0.0
        else:
            a = float(a)
            priors[k] = Normal(mean=0.0, sd=1.0 / math.sqrt(a)) if a > 0 else Flat()
    return priors, fixed


def warm_with(sampler, names: list[str], values: list[float]):
    """``sampler`` (a SamplerResult) whose best point also carries ``names`` at ``values`` (for warm starts)."""
    import dataclasses

    keep = [i for i, n in enumerate(sampler.names) if n not in names]
    return dataclasses.replace(sampler, names=[sampler.names[i] for i in keep] + list(names),
                               phi_star=np.concatenate([np.asarray(sampler.phi_star)[keep], np.asarray(values, float)]))


def _fit_task(args):
    """One re-selection (a picklable unit of work for the confirmation pool)."""
    cand, data, spec, warm, posterior = args
    return run_candidate(cand, data, spec, 0, warm=warm, final_posterior=posterior)


def pool_mapper(workers: int):
    """(map function, closer): confirmations and halves run side by side on ``workers`` processes."""
    if workers <= 1:
        return (lambda fn, tasks: [fn(t) for t in tasks]), (lambda: None)
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
    return run, (lambda: pool.shutdown(cancel_futures=True))


def trace_and_confirm(spec, cand, row, bmr, fspec, phi, data, res, col, config, extra_effects, say, mapper):
    """Screen the whole library by evidence, then confirm the best few by the full ARD re-selection."""
    peaks = [p for p in res.tests[col]["spectrum"]["peaks"] if not p.get("harmonic")]
    scales = {s: float(np.nanstd(res.smoothed[:, i])) for i, s in enumerate(fspec.states)}
    # forcing frequencies: innovation peaks that are not harmonics of the oscillation (refined by the screen)
    effects = candidate_effects(fspec, scales=scales, frequencies=[p["f"] for p in peaks[:2]],
                                extra=list(extra_effects))
    screened = screen_effects(fspec, phi, data, effects, dynamic_states(fspec), list(fspec.observed_columns),
                              substeps=cand.substeps, progress=say)
    ranked = [{**c.to_json(), "_screened": c} for c in screened]
    say("screen: " + ", ".join(f"{c['effect']} -> {c['target']} (ln BF ~ {c['log_bayes_factor']:.1f})"
                               for c in ranked[:5]))
    priors, fixed = essential_from_row(cand, row)
    cspec = spec.model_copy(update={"maximiser": spec.maximiser.model_copy(
        update={"alpha_start": max(config.alpha_start, spec.maximiser.alpha_start)})})
    confirmed = []
    picked = distinct_candidates(fspec, phi, data, screened, config.top_k, config.min_score, substeps=cand.substeps)
    redundant = [c for c in screened[:12] if getattr(c, "conditional_on", None)]
    # a redundant candidate the screen cannot tell from the one it was dropped for (a saturating stiffness and
    # a free-play; a smooth sign of two widths) is confirmed too: the full evidence decides between the twins
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
    by_id = {id(c["_screened"]): c for c in ranked}
    chosen = [by_id[id(p)] for p in picked] + [by_id[i] for i in rivals]
    tasks = []
    for c in chosen:
        sc: Screened = c["_screened"]
        eff, shape = fitted_effect(cand.model_spec(), sc, c["target"])
        aspec, names = augment(cand.model_spec(), eff, c["target"], sc.scales)
        acand = CandidateSpec(model=aspec, name=aspec.name, priors={**priors, **shape}, fixed=fixed,
                              ard=names, substeps=cand.substeps)
        # new terms start at the screen's estimate (a Laplace search from 0 would walk there by Nelder-Mead),
        # a fitted shape at the profile's maximum
        warm = warm_with(bmr.sampler, names + list(shape), sc.coefficients + [sc.shape_value] * len(shape)) \
            if spec.evidence == "laplace" or shape else bmr.sampler
        c["_effect"], c["_shape_prior"] = eff, shape
        tasks.append((acand, with_columns(data, eff), cspec, warm, config.posterior))
    if chosen:
        say("confirming by evidence: " + ", ".join(f"{c['effect']} -> {c['target']}" for c in chosen))
    results = mapper(_fit_task, tasks)
    # the prior odds of each of the N candidates tried (Scott and Berger 2010): its ln BF also pays ln N
    threshold = config.min_log_bf + (math.log(max(1, len(screened))) if config.library_prior else 0.0)
    if chosen and config.library_prior:
        say(f"  an effect must gain {threshold:.1f} nats: {config.min_log_bf:g} + ln {len(screened)} "
            f"(the prior odds of one of the {len(screened)} candidates tried)")
    for c, (acand, adata, *_), (arow, amr) in zip(chosen, tasks, results):
        confirmed.append(_confirmation(c, acand, adata, arow, amr, row, threshold, say))
    # of twins only the one with the higher evidence goes on
    by_screen = {id(c["_screened"]): c for c in confirmed}
    for pid in dict.fromkeys(rivals.values()):
        twins = [by_screen.get(i) for i in [pid] + [r for r, p in rivals.items() if p == pid]]
        twins = [c for c in twins if c and c["survives"]]
        if len(twins) < 2:
            continue
        # one base: the evidence (less a profile's Occam) decides; within twin_nats, the twin with fewer
        # parameters (a cubic and a sine stiffness whose period the data do not reach tie; take the cubic)
        top = max(c["log_bayes_factor"] for c in twins)
        hi = min((c for c in twins if c["log_bayes_factor"] >= top - config.twin_nats),
                 key=lambda c: (len(c["_cand"].model_spec().parameters), -c["log_bayes_factor"]))
        for lo in twins:
            if lo is not hi:
                lo["survives"], lo["rival_of"] = False, hi["effect"]
        say(f"  {', '.join(c['effect'] for c in twins if c is not hi)} and {hi['effect']} explain the same; "
            f"{hi['effect']} has the higher evidence")
    return ranked, confirmed


def fitted_effect(ms, sc: Screened, target: str) -> tuple[Effect, dict]:
    """The effect a confirmation fits and the prior of its shape parameter ({} for none): a width, a friction
    velocity or a stiffness period is fitted with the coefficients (the screen's profile maximum is only
    where it starts), so its posterior is reported and its evidence integrates over it; a forcing
    frequency stays at the screen's refined value (its sine and cosine are input columns)."""
    src = sc.source
    if src is None or not src.shape or src.shape[0] == "f" or sc.shape_value is None:
        return sc.effect, {}
    pname = shape_parameter_name(ms, src, target)
    return src.with_shape_parameter(pname), {pname: shape_prior(src)}


def _confirmation(c: dict, acand: CandidateSpec, adata: Dataset, arow: ModelFit, amr, row: ModelFit, threshold: float,
                  say) -> dict:
    """The record of one confirmation: the candidate ``c`` re-selected with its terms under ARD (``arow``)
    against the base model's ``row``."""
    sc = c["_screened"]
    eff: Effect = c["_effect"]
    shape = c["_shape_prior"]
    names = list(acand.ard_names)
    # a shape picked by the screen's profile (a forcing frequency found in the spectrum) pays its Occam
    # factor; a fitted shape has paid it through its prior
    gain = arow.log_evidence - row.log_evidence - (0.0 if shape else sc.shape_occam)
    if not math.isfinite(gain):
        gain = -math.inf  # the re-selection failed (no finite evidence): it confirms nothing, and says so
    kept = [n for n in names if n in arow.kept]
    scale = dict(zip(names, sc.scales))
    # the EKF evidence takes coloured innovations as white: the support it gives is divided by the factor
    # the screen found the score's variance understated by (1 for white innovations)
    adjusted = gain / sc.inflation if gain > 0 else gain
    if gain == -math.inf:
        say(f"  {sc.effect.name}: the re-selection found no finite evidence (fit failed): not confirmed")
    else:
        say(f"  {eff.name}: ln BF = {gain:.2f}" + (f" ({adjusted:.2f} adjusted for coloured innovations, "
                                                     f"x 1/{sc.inflation:.2g})" if sc.inflation > 1.05 else "")
            + f", ARD keeps {kept or 'nothing'}")
    # a fitted shape is shown at its posterior mean, e.g. sine_stiffness(y,L=1.07)
    shown = next((sc.source.at(arow.mean[n]).name for n in shape if n in arow.mean), eff.name)
    return {"effect": shown, "target": c["target"], "score": c["log_bayes_factor"],
            "screened_log_bayes_factor": c["log_bayes_factor"],
            "log_evidence": arow.log_evidence, "log_evidence_se": arow.log_evidence_se,
            "log_bayes_factor": gain, "adjusted_log_bayes_factor": adjusted,
            "inflation": sc.inflation, "threshold": threshold, "kept_terms": kept,
            "psi_opt": arow.psi_opt,
            # coefficients in the term's own units (the fit uses the normalised ones)
            "posterior": {n: arow.physical(n, scale[n]) for n in names if n in arow.mean},
            "shape": {n: arow.physical(n, 1.0) for n in shape if n in arow.mean},
            "scales": scale,
            "survives": bool(kept) and adjusted > threshold,
            "_row": arow, "_mr": amr, "_cand": acand, "_data": adata, "_effect": eff, "_shape_prior": shape,
            "_screened": sc}


def joint_fit(spec, cand, row, best, survivors, data, config, say):
    """The current model with every surviving effect added, each new term at the ARD precision its own
    re-selection found (pruned terms fixed at 0); one evidence evaluation checks they hold together.

    Returns the :class:`Fit` of the model with all of them."""
    from .priors import Flat, Normal

    priors, fixed = essential_from_row(cand, row)
    aspec, adata = cand.model_spec(), data
    for c in survivors:
        n = list(c["scales"])
        aspec, n = augment(aspec, c["_effect"], c["target"], [c["scales"][k] for k in n], names=n)
        adata = with_columns(adata, c["_effect"])
        priors.update(c["_shape_prior"])
        for k in n:
            a = c["psi_opt"].get(k, 0.0)
            if k not in c["kept_terms"] or is_pruned(a):
                fixed[k] = 0.0
            else:
                a = float(a)
                priors[k] = Normal(mean=0.0, sd=1.0 / math.sqrt(a)) if a > 0 else Flat()
    acand = CandidateSpec(model=aspec, name=aspec.name, priors=priors, fixed=fixed, ard=[], substeps=cand.substeps)
    say("fitting the distinct survivors together: " + ", ".join(c["effect"] for c in survivors))
    arow, amr = run_candidate(acand, adata, spec, 0, warm=best["_mr"].sampler, final_posterior=config.posterior)
    say(f"  together: ln BF = {arow.log_evidence - row.log_evidence:.2f}")
    return Fit(acand, arow, amr, adata)


def _continued_half(half: CandidateSpec, row: ModelFit, data: Dataset, mid: int) -> tuple[CandidateSpec, Dataset]:
    """The second half as a continuation of the record: its filter starts from the state the full-record
    filter (at the full fit's posterior mean) holds at sample ``mid - 1``, that sample's observations
    removed (already used). A record rarely stops at rest in the middle; starting the second half from
    the model's declared initial state, which is set in absolute units, biases its fit whenever the
    signal's scale differs from those units (the halves then disagree for a reason that is not the effect).
    The filtered standard deviations are doubled: the start must not hold the half to the full fit."""
    from .ekf import compile_model

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


def split_stability(spec: StudySpec, c: dict, config, say, mapper) -> dict:
    """Refit the augmented model on each half of the record, the new terms' ARD priors frozen at psi_opt."""
    from .priors import Flat, Normal

    acand: CandidateSpec = c["_cand"]
    data: Dataset = c["_data"]
    priors = dict(acand.priors)
    for n in c["kept_terms"]:
        a = float(c["psi_opt"][n])
        priors[n] = Normal(mean=0.0, sd=1.0 / math.sqrt(a)) if a > 0 else Flat()
    fixed = dict(acand.fixed)
    fixed.update({n: 0.0 for n in acand.ard_names if n not in c["kept_terms"]})
    half = CandidateSpec(model=acand.model, name=acand.label, priors=priors, fixed=fixed, ard=[],
                         substeps=acand.substeps)
    # halves of the *observed* samples (a record may end in missing values)
    seen = np.flatnonzero(np.any(np.column_stack([np.isfinite(data.columns[o])
                                                  for o in acand.model_spec().observed_columns]), axis=1))
    n = len(data)
    mid = int(seen[seen.size // 2]) if seen.size >= 4 else n // 2
    parts = []
    warm = c["_mr"].sampler
    second, data2 = _continued_half(half, c["_row"], data, mid)
    tasks = [(half, data.slice(0, mid), spec, warm, config.posterior), (second, data2, spec, warm, config.posterior)]
    for r, _ in mapper(_fit_task, tasks):
        parts.append({k: (r.mean[k], r.sd[k]) for k in c["kept_terms"]})
    z = {k: abs(parts[0][k][0] - parts[1][k][0]) / math.hypot(parts[0][k][1], parts[1][k][1])
         for k in c["kept_terms"]}
    rel = {k: abs(parts[0][k][0] - parts[1][k][0]) / max(abs(parts[0][k][0]), abs(parts[1][k][0]), 1e-300)
           for k in c["kept_terms"]}
    same_sign = all(parts[0][k][0] * parts[1][k][0] > 0 for k in c["kept_terms"])
    # disagreement beyond the noise AND large against the effect's own size (long records have tiny se)
    stable = all(z[k] <= config.split_z or (same_sign and rel[k] <= config.split_rel) for k in z)
    say(f"  {c['effect']}: halves give " + ", ".join(
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


SD_MARGIN = 20.0
"""Nats by which a Savage-Dickey estimate must clear a threshold for the backward check to trust it."""


def savage_dickey(cand: CandidateSpec, row: ModelFit, mr, names: list[str]) -> float | None:
    """ln Bayes factor of the fitted model against it with ``names`` fixed at 0, by the Savage-Dickey density
    ratio ln p(0) - ln p(0 | d) with the posterior of those terms taken Gaussian (their draws' mean and
    covariance; an ARD term's prior is N(0, 1/alpha) at its optimal alpha); None where it does not apply
    (a term without a normal prior, no draws)."""
    from scipy.stats import multivariate_normal

    from .priors import Normal

    def prior(n):
        a = row.psi_opt.get(n)
        if n in cand.ard_names and a is not None and 0 < a < math.inf:
            return Normal(mean=0.0, sd=1.0 / math.sqrt(a))
        return cand.priors.get(n)

    res = getattr(mr, "sampler", None)
    pri = [prior(n) for n in names]
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


def backward_check(spec, cand, row, bmr, data, rounds, config, say, mapper):
    """Effects added in earlier rounds that the later ones made redundant are dropped again.

    Forward selection adds what the screen ranks first; a later effect can explain the same residual better
    (a tank's input nonlinearity added first, its square-root outflow next: at equilibrium the level follows
    the input). Each effect of an earlier round is refitted out (its terms fixed at 0, side by side on the
    loop's pool); one whose ln Bayes factor (adjusted for coloured innovations as when it was added) no
    longer reaches the threshold it passed then (``min_log_bf`` + ln N: its prior odds as one of N library
    candidates have not changed) is dropped, the weakest first, and the rest are checked again. An effect
    whose Savage-Dickey ln Bayes factor (:func:`savage_dickey`) clears its threshold by ``SD_MARGIN`` nats
    is kept without a refit (an offset worth 60,000 nats does not need one to say so).
    """
    while True:
        earlier = [x for r in rounds[:-1] for x in r.get("_added", []) if not x.record.get("removed")]
        sd = [savage_dickey(cand, row, bmr, x.params) for x in earlier]
        clear = [x.record["effect"] for x, b in zip(earlier, sd)
                 if b is not None and b / x.inflation >= x.threshold + SD_MARGIN]
        if clear:
            say(f"  kept without a refit (Savage-Dickey ln BF clears the threshold by {SD_MARGIN:g} nats): " + ", ".join(clear))
        earlier = [x for x, b in zip(earlier, sd) if b is None or b / x.inflation < x.threshold + SD_MARGIN]
        if not earlier:
            return cand, row, bmr
        tasks = [(cand.model_copy(update={"fixed": {**cand.fixed, **{n: 0.0 for n in x.params}}}), data, spec,
                  bmr.sampler, config.posterior) for x in earlier]
        fits = mapper(_fit_task, tasks)
        gain = [row.log_evidence - frow.log_evidence for frow, _ in fits]
        worth = [g / x.inflation if g > 0 else g for g, x in zip(gain, earlier)]
        k = int(np.argmin([w - x.threshold for w, x in zip(worth, earlier)]))
        x = earlier[k]
        if worth[k] >= x.threshold:
            return cand, row, bmr
        x.record["removed"], x.record["log_bayes_factor_after"] = rounds[-1]["round"], float(worth[k])
        say(f"  {x.record['effect']} (added in round {x.round}) is worth {worth[k]:.2f} nats beside the later "
            f"effects, below the {x.threshold:.1f} it passed: dropped")
        cand, (row, bmr) = tasks[k][0], fits[k]
