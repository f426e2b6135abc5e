"""Closing the loop (method.md section 9): residuals, tests, trace, add, report.

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
   :mod:`ardcore.effects` on every dynamic state (and every measurement effect
   on every observed channel) is **screened by evidence** (:mod:`ardcore.screen`:
   a Laplace log Bayes factor from the EKF's own score and information, the
   model's parameters profiled out, terms normalised, shape parameters such as a
   free-play width or a forcing frequency profiled); the best few are
   **confirmed** by the full ARD re-selection: each is added (normalised) under
   an ARD prior and the candidate re-selected, so ARD decides whether the new
   term survives;
5. **reports** the error before and after.

When no candidate survives, the result says so and describes the residual
structure that remains (spectral peaks, the states that needed noise).

Rooms: the residual tests live in :mod:`ardcore.residual_tests`, the free run and its
prediction band in :mod:`ardcore.freerun`, the evidence screen in :mod:`ardcore.screen`,
the library in :mod:`ardcore.effects`; this module holds the loop.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np
import sympy as sp
from scipy import optimize

from .data import Dataset
from .ekf import compile_model
from .effects import Effect, augment, candidate_effects, dynamic_states, oscillator_pairs, with_columns
from .errors import SpecError
from .model import ModelSpec
from .freerun import _posterior_draws, free_run, free_run_of  # noqa: F401
from .residual_tests import acf, dominant_frequency, harmonics, residual_tests, spectral_peaks  # noqa: F401
from .screen import Screened, distinct_candidates, screen_effects
from .study import CandidateSpec, StudySpec, run_candidate, to_jsonable

INF = math.inf


@dataclass
class DiagnoseConfig:
    """Settings of :func:`diagnose` (documented defaults).

    Attributes
    ----------
    max_lag : int
        Autocorrelation lags shown and tested.
    ljung_box_lags : int
        Lags in the Ljung-Box statistic.
    peak_p : float
        A spectral bin is a peak when its power exceeds the local background by the
        (1 - peak_p) chi-square quantile (2 degrees of freedom per Welch segment pair).
    min_score : float
        Screened ln Bayes factor (nats, :mod:`ardcore.screen`) a candidate needs to be confirmed by
        the full ARD re-selection (default 3: Kass and Raftery's "positive" evidence).
    top_k : int
        Candidates confirmed by the full re-selection per round (the best screened ones above
        ``min_score``).
    min_log_bf : float
        Evidence gain (nats) over the base model an added effect needs, on top of ARD keeping it.
    init_samples : int
        Samples of a held-out record used to initialise the free run (filtered state).
    max_rounds : int
        Effects added one after another at most (each round re-traces the new model's residual).
    split_z : float or None
        Stability check of a surviving effect: its coefficients are refitted (at the optimal alpha) on
        the first and the second half of the record. They disagree when they differ by more than
        ``split_z`` standard errors *and* by more than ``split_rel`` of their size (or change sign): a
        term that compensates for something that changes over the record rather than explaining it.
        On a long record the standard errors are tiny and any small misfit shows, so the size of
        the disagreement is judged against the effect's own size. None skips the check.
    split_rel : float
        Relative disagreement of the halves (|a - b| / max(|a|, |b|)) that still counts as stable.
    alpha_start : float
        Starting ARD precision of a new (normalised) term in its confirmation. A new term's coefficient
        is 1 for an effect as large as the target's whole dynamics, so prior sd 1/sqrt(1e-2) = 10 is
        already flat for it; starting at the study's 1e-10 would only add trials in which ln Z climbs by
        the known 2.3 nats per two decades.
    posterior : {"laplace", "sample"}
        With a Laplace-evidence spec, the loop's fits report the Laplace posterior N(MAP, H^-1) that
        their evidence assumes ("laplace", default: it costs nothing) or sample it by MCMC ("sample").
        Chib-Jeliazkov specs always sample.
    joint : bool
        Add every distinct, stable survivor of a round at once: they are re-selected together under ARD
        (which prunes what the others make redundant) and added when that beats the best single effect by
        ``min_log_bf``. False adds one effect per round.
    workers : int
        Processes that run a round's confirmations and halves checks side by side (0: one per core, at
        most ``top_k``; 1: in this process).
    band_draws : int
        Posterior draws whose free runs make the 90 % prediction band of the free run (0: none).
    rival_nats : float
        A candidate the screen found redundant with a better one is still confirmed when their screened
        ln Bayes factors are within this many nats (the screen cannot tell the twins apart; the full
        evidence does). Of two surviving twins the one with the higher evidence goes on.
    """

    max_lag: int = 40
    ljung_box_lags: int = 20
    peak_p: float = 1e-4
    min_score: float = 3.0
    top_k: int = 3
    min_log_bf: float = 3.0
    init_samples: int = 50
    max_rounds: int = 3
    split_z: float | None = 3.0
    split_rel: float = 0.3
    alpha_start: float = 1e-2
    posterior: str = "laplace"
    joint: bool = True
    workers: int = 0
    band_draws: int = 40
    rival_nats: float = 5.0


# --------------------------------------------------------------------------- residuals


@dataclass
class Residuals:
    """The residuals of a fitted model on one data set (see module docstring)."""

    innovations: np.ndarray          # standardised, (n, m)
    raw_innovations: np.ndarray      # (n, m)
    smoothed: np.ndarray             # (n, n_x)
    process_noise_rate: dict         # state -> (n-1,) injected drift w_k / dt
    noise_std: dict                  # state -> fitted diagnostic noise std (or the model's own)
    tests: dict                      # per observation channel
    loglik: float
    states: tuple = ()               # names of the smoothed columns
    dt: float = 1.0                  # median sample interval


def _diagnostic_spec(spec: ModelSpec, states: list[str]) -> tuple[ModelSpec, list[str]]:
    """``spec`` with a noise parameter on every listed state that has none."""
    add = [s for s in states if not spec.diffusion.get(s)]
    names = [f"q_diag_{s}" for s in add]
    if not add:
        return spec, []
    diff = dict(spec.diffusion)
    diff.update({s: n for s, n in zip(add, names)})
    new = spec.model_copy(update={"name": f"{spec.name}_diag", "diffusion": diff,
                                  "parameters": list(spec.parameters) + names})
    return new.revalidate(), names


def residuals(spec: ModelSpec, phi: dict, data: Dataset, config: DiagnoseConfig, *,
              substeps: int | None = None) -> Residuals:
    """Residuals of ``spec`` at parameter values ``phi`` (dict over its free parameters)."""
    cm = compile_model(spec)
    fr = cm.filter(phi, data, substeps)
    fs = 1.0 / float(np.median(np.diff(data.t)))
    e = fr.standardized
    fund = dominant_frequency(data.columns[spec.observed_columns[0]], fs)
    tests = {c: residual_tests(e[:, j], fs, config, fundamental=fund) for j, c in enumerate(spec.observed_columns)}
    dyn = dynamic_states(spec)
    dspec, qnames = _diagnostic_spec(spec, dyn)
    dcm = compile_model(dspec)
    scale = np.nanstd(fr.filtered, axis=0)
    q0 = {}
    if qnames:
        lik = dcm.bind(data, substeps)
        idx = [spec.states.index(n[len("q_diag_"):]) for n in qnames]
        # the injected noise is at most of the order of the state's rate of change
        hi = np.log10(np.maximum(scale[idx] * fs, 1e-12))
        lo = hi - 8

        def nll(z):
            z = np.clip(z, lo, hi)
            v = lik({**phi, **{n: 10.0 ** zi for n, zi in zip(qnames, z)}})
            return -v if np.isfinite(v) else 1e300

        best = min((optimize.minimize(nll, np.full(len(qnames), s), method="Nelder-Mead",
                                      options={"xatol": 0.05, "fatol": 0.05, "maxfev": 400})
                    for s in (lo + 2, hi - 3)), key=lambda r: r.fun)
        q0 = {n: float(10.0 ** np.clip(best.x, lo, hi)[i]) for i, n in enumerate(qnames)}
    _, sm = dcm.smooth({**phi, **q0}, data, substeps)
    dt = np.diff(data.t)
    rates = {s: sm.process_noise[1:, spec.states.index(s)] / dt for s in dyn}
    noise_std = {s: q0.get(f"q_diag_{s}") for s in dyn}
    return Residuals(e, fr.innovations, sm.smoothed, rates, noise_std, tests, fr.loglik, tuple(spec.states),
                     float(np.median(dt)))


# --------------------------------------------------------------------------- fit, free run, loop


def _fitted(cand: CandidateSpec, row: dict) -> tuple[ModelSpec, dict]:
    """The candidate's model with pruned terms fixed at 0, and its posterior mean."""
    spec = cand.model_spec()
    pruned = {k: 0.0 for k, v in row["psi_opt"].items() if v == "inf" or v == INF}
    if pruned:
        spec = spec.with_fixed(**pruned)
    phi = {k: float(row["mean"][k]) for k in spec.free_parameters}
    return spec, phi


def _essential_from_row(cand: CandidateSpec, row: dict) -> tuple[dict, dict]:
    """Priors of the fitted model with kept ARD terms frozen at their optimal alpha; pruned terms fixed."""
    from .priors import Flat, Normal

    priors = dict(cand.priors)
    fixed = dict(cand.fixed)
    for k, a in row["psi_opt"].items():
        if a == "inf" or a == INF:
            fixed[k] = 0.0
        else:
            a = float(a)
            priors[k] = Normal(mean=0.0, sd=1.0 / math.sqrt(a)) if a > 0 else Flat()
    return priors, fixed


def _errors(res: Residuals, fr: dict, row: dict, col: str) -> dict:
    t = res.tests[col]
    keep = ("rms_error", "relative_rms_error", "frequency_error", "amplitude_error", "harmonic_error",
            "band_coverage", "band_halfwidth_rms", "draws_rms_error", "n_draws")
    # the first innovations carry the initial-state uncertainty, not the model's error
    skip = min(10, max(0, res.raw_innovations.shape[0] // 10))
    return {"innovation_rms": float(np.sqrt(np.nanmean(res.raw_innovations[skip:, 0] ** 2))),
            # what the model had to be pushed by (smoothed process noise, per unit time), per dynamic state
            "injected_noise_rms": {s: float(np.sqrt(np.nanmean(r ** 2))) for s, r in res.process_noise_rate.items()},
            "standardized_rms": t["rms"], "ljung_box": t["ljung_box"], "ljung_box_p": t["ljung_box_p"],
            "free_run": {k: fr[k] for k in keep if k in fr},
            "log_evidence": row["log_evidence"], "log_evidence_se": row["log_evidence_se"]}


def diagnose(spec: StudySpec, data: Dataset, *, test_data: Dataset | None = None,
             config: DiagnoseConfig | None = None, progress: Callable[[str], None] | None = None,
             extra_effects: list[Effect] = (), base: tuple[dict, object] | None = None) -> dict:
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
    base : (row, MaximiserResult), optional
        An existing fit of the candidate (skips step 1).

    Returns
    -------
    dict
        ``before``/``after`` residual tests and errors, ``candidates`` (ranked), ``confirmed``
        (evidence for the top few), ``added`` (the effect kept, or None), ``verdict`` (text),
        and arrays for the figures under ``_arrays``.
    """
    config = config or DiagnoseConfig()
    t_start = time.perf_counter()

    def say(msg: str) -> None:
        if progress:
            progress(f"[{time.perf_counter() - t_start:6.0f} s] {msg}")

    if len(spec.models) != 1:
        raise SpecError(f"diagnose: the spec must have exactly one model (it has {len(spec.models)})")
    t0 = time.perf_counter()
    cand = spec.models[0]
    test_data = test_data or data
    ms = cand.model_spec()
    for what, d in (("data", data), ("held-out data", test_data)):
        missing = [c for c in list(ms.observed_columns) + list(ms.inputs) if c not in d.columns]
        if missing:  # before any fit: a free run at the end must not be what finds it
            raise SpecError(f"diagnose: the {what} ({d.meta.get('source', 'given')}) has no column "
                            f"{missing[0]!r} (it has {sorted(d.columns)}); rename its columns")
    say(f"fitting {cand.label} ...")
    row, bmr = base or run_candidate(cand, data, spec, 0, final_posterior=config.posterior)
    col = cand.model_spec().observed_columns[0]
    first = None
    rounds, arrays = [], {}
    cur_data, cur_test = data, test_data
    workers = config.workers or min(os.cpu_count() or 1, max(config.top_k, 2))
    mapper, close = _pool_mapper(workers)
    try:
        for rnd in range(config.max_rounds + 1):
            fspec, phi = _fitted(cand, row)
            say(f"round {rnd}: {cand.label} ln Z = {row['log_evidence']:.3f}; computing residuals")
            res = residuals(fspec, phi, cur_data, config, substeps=cand.substeps)
            fr = free_run(fspec, phi, cur_test, init_samples=config.init_samples, substeps=cand.substeps,
                          draws=_posterior_draws(bmr, fspec, config.band_draws, seed=rnd))
            err = _errors(res, fr, row, col)
            if first is None:
                initial = {"spec": fspec, "phi": phi, "effects": [], "substeps": cand.substeps}
                first = {"before": err, "tests_before": _strip(res.tests), "noise_std_before": res.noise_std,
                         "base_fit": {k: row[k] for k in ("log_evidence", "log_evidence_se", "psi_opt", "kept", "pruned",
                                                           "mean", "sd")}}
                arrays["before"] = _arrays(res, fr)
            else:
                arrays["after"] = _arrays(res, fr)
                rounds[-1]["after"] = err
            if rnd == config.max_rounds:
                break
            ranked, confirmed = _trace_and_confirm(spec, cand, row, bmr, fspec, phi, cur_data, res, col, config,
                                                   extra_effects, say, mapper)
            survivors = sorted([c for c in confirmed if c["survives"]], key=lambda c: -c["log_evidence"])
            if config.split_z is not None:
                for c in survivors:
                    if c["_effect"].where == "noise":
                        continue  # a noise level is a nuisance that may drift over a record; the check is for dynamics
                    c["stability"] = _split_stability(spec, c, config, say, mapper)
                    c["survives"] = c["stability"]["stable"]
                    if c["survives"] and not config.joint:
                        break  # the best stable one is added
                survivors = [c for c in survivors if c.get("stability", {}).get("stable", True) and c["survives"]]
            # final ranking: what evidence confirmed (by ln Bayes factor), then the rest by regression score
            tried = {(c["effect"], c["target"]): c for c in confirmed}
            order = sorted(confirmed, key=lambda c: (not c["survives"], -c["log_bayes_factor"]))
            ranking = [{"effect": c["effect"], "target": c["target"], "log_bayes_factor": c["log_bayes_factor"],
                        "survives": c["survives"]} for c in order]
            ranking += [{"effect": c["effect"], "target": c["target"], "score": c["score"],
                         "screened_log_bayes_factor": c["log_bayes_factor"]} for c in ranked
                        if (c["effect"], c["target"]) not in tried]
            rec = {"round": rnd, "model": cand.label, "ranking": ranking,
                   "candidates": [{k: v for k, v in c.items() if not k.startswith("_")} for c in ranked],
                   "confirmed": [{k: v for k, v in c.items() if not k.startswith("_")} for c in confirmed],
                   "added": None}
            rounds.append(rec)
            if not survivors:
                rec["verdict"] = _unexplained(res, ranked, confirmed, col, config)
                break
            best = survivors[0]
            chosen, fit = [best], (best["_cand"], best["_row"], best["_mr"], best["_data"])
            if config.joint and len(survivors) > 1:
                # the survivors were screened as distinct: fit them together under ARD, which prunes any that the
                # others make redundant; taken when it beats the best single effect by more than min_log_bf
                j = _joint_fit(spec, cand, row, best, survivors, cur_data, config, say)
                if j is not None and j[1]["log_evidence"] > best["log_evidence"] + config.min_log_bf:
                    chosen, fit = j[4], j[:4]
            jrow = fit[1]
            recs = []
            for c in chosen:
                eff = c["_effect"]
                names = list(c["scales"])
                post = {n: _physical(jrow, n, c["scales"][n]) for n in names if n in jrow["mean"]}
                recs.append({"effect": eff.name, "kind": eff.kind, "target": c["target"], "terms": list(eff.terms),
                             "posterior": post, "log_bayes_factor": c["log_bayes_factor"],
                             "character": _character(fspec, phi, eff, {"posterior": post, "target": c["target"]})})
            rec["added"], rec["added_with"] = recs[0], recs[1:]
            rec["_effects"] = [c["_effect"] for c in chosen]
            say(f"round {rnd}: added " + ", ".join(f"{r['effect']} to {r['target']} (ln BF {r['log_bayes_factor']:.1f})"
                                                    for r in recs)
                + (f"; together ln BF {jrow['log_evidence'] - row['log_evidence']:.1f}" if len(recs) > 1 else ""))
            cand, row, bmr, cur_data = fit
            for e in rec["_effects"]:
                cur_test = with_columns(cur_test, e)
    finally:
        close()
    added = [a for r in rounds if r["added"] for a in [r["added"], *r.get("added_with", [])]]
    out = {"model": spec.models[0].label, "final_model": cand.label, "data": data.meta.get("source"),
           "n": len(data), "n_test": len(test_data), **first,
           "rounds": [{k: v for k, v in r.items() if not k.startswith("_")} for r in rounds],
           "candidates": rounds[0]["candidates"] if rounds else [],
           "confirmed": rounds[0]["confirmed"] if rounds else [],
           "added": added, "after": [r for r in rounds if r["added"]][-1]["after"] if added else None,
           "tests_after": None, "final_fit": {k: row[k] for k in ("log_evidence", "log_evidence_se", "mean", "sd",
                                                                    "q005", "q995")}}
    if added:
        a, b = out["after"], out["before"]
        out["tests_after"] = _strip(arrays["after"]["tests"])
        out["verdict"] = ("added " + ", then ".join(f"{x['effect']} ({x['target']} equation, ln BF "
                                                     f"{x['log_bayes_factor']:.1f}"
                                                     + (f", {x['character']}" if x.get("character") else "") + ")"
                                                     for x in added)
                          + f"; innovation RMS {b['innovation_rms']:.4g} -> {a['innovation_rms']:.4g}; free-run RMS "
                          f"error {b['free_run']['rms_error']:.4g} -> {a['free_run']['rms_error']:.4g}; ln Z "
                          f"{b['log_evidence']:.2f} -> {a['log_evidence']:.2f}"
                          + (f"; then: {rounds[-1]['verdict']}" if rounds[-1].get("verdict") else ""))
    else:
        out["verdict"] = rounds[0]["verdict"] if rounds else "no rounds run"
    out["wall_s"] = time.perf_counter() - t0
    out["_arrays"] = arrays
    # the initial and final models, for free runs on further held-out records: free_run_of(out["_final"], record)
    out["_initial"] = initial
    out["_final"] = {"spec": fspec, "phi": phi, "effects": [e for r in rounds for e in r.get("_effects", [])],
                     "substeps": cand.substeps}
    return out


def _warm_with(sampler, names: list[str], values: list[float]):
    """``sampler`` (a SamplerResult) whose best point also carries ``names`` at ``values`` (for warm starts)."""
    import dataclasses

    keep = [i for i, n in enumerate(sampler.names) if n not in names]
    return dataclasses.replace(sampler, names=[sampler.names[i] for i in keep] + list(names),
                               phi_star=np.concatenate([np.asarray(sampler.phi_star)[keep], np.asarray(values, float)]))


def _fit_task(args):
    """One re-selection (a picklable unit of work for the confirmation pool)."""
    cand, data, spec, warm, posterior = args
    return run_candidate(cand, data, spec, 0, warm=warm, final_posterior=posterior)


def _pool_mapper(workers: int):
    """(map function, closer): confirmations and halves run side by side on ``workers`` processes."""
    if workers <= 1:
        return (lambda fn, tasks: [fn(t) for t in tasks]), (lambda: None)
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    # fork from a single-threaded process: a plain script without a __main__ guard keeps working (spawn
    # re-runs the script in every worker) and compiled kernels come along; with other threads alive (a host
    # application) a fork could copy a held lock, so spawn, which loads kernels from the on-disk cache
    import threading

    method = "fork" if threading.active_count() == 1 and "fork" in mp.get_all_start_methods() else "spawn"
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context(method))

    def run(fn, tasks):
        if len(tasks) <= 1:
            return [fn(t) for t in tasks]
        return list(pool.map(fn, tasks))
    return run, (lambda: pool.shutdown(cancel_futures=True))


def _trace_and_confirm(spec, cand, row, bmr, fspec, phi, data, res, col, config, extra_effects, say, mapper):
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
    priors, fixed = _essential_from_row(cand, row)
    cspec = spec.model_copy(update={"maximiser": spec.maximiser.model_copy(
        update={"alpha_start": max(config.alpha_start, spec.maximiser.alpha_start)})})
    confirmed = []
    picked = distinct_candidates(fspec, phi, data, screened, config.top_k, config.min_score, substeps=cand.substeps)
    redundant = [c for c in screened[:12] if getattr(c, "conditional_on", None)]
    # a redundant candidate the screen cannot tell from the one it was dropped for (a saturating stiffness and
    # a free-play; a smooth sign of two widths) is confirmed too: the full evidence decides between the twins
    rivals = {}
    for c in redundant:
        near = [p for p in picked if p.effect.name in c.conditional_on and id(p) not in rivals.values()
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
        aspec, names = augment(cand.model_spec(), sc.effect, c["target"], sc.scales)
        acand = CandidateSpec(model=aspec, name=aspec.name, priors=priors, fixed=fixed,
                              ard=names, substeps=cand.substeps)
        # new terms start at the screen's estimate (a Laplace search from 0 would walk there by Nelder-Mead)
        warm = _warm_with(bmr.sampler, names, sc.coefficients) if spec.evidence == "laplace" else bmr.sampler
        tasks.append((acand, with_columns(data, sc.effect), cspec, warm, config.posterior))
    if chosen:
        say("confirming by evidence: " + ", ".join(f"{c['effect']} -> {c['target']}" for c in chosen))
    results = mapper(_fit_task, tasks)
    for c, (acand, adata, *_), (arow, amr) in zip(chosen, tasks, results):
        sc = c["_screened"]
        eff: Effect = sc.effect
        names = list(acand.ard_names)
        # a shape picked by the screen's profile (a forcing frequency found in the spectrum) pays its Occam factor
        gain = arow["log_evidence"] - row["log_evidence"] - sc.shape_occam
        kept = [n for n in names if n in arow["kept"]]
        scale = dict(zip(names, sc.scales))
        confirmed.append({"effect": eff.name, "target": c["target"], "score": c["log_bayes_factor"],
                          "screened_log_bayes_factor": c["log_bayes_factor"],
                          "log_evidence": arow["log_evidence"], "log_evidence_se": arow["log_evidence_se"],
                          "log_bayes_factor": gain, "kept_terms": kept, "psi_opt": arow["psi_opt"],
                          # coefficients in the term's own units (the fit uses the normalised ones)
                          "posterior": {n: _physical(arow, n, scale[n]) for n in names if n in arow["mean"]},
                          "scales": scale,
                          "survives": bool(kept) and gain > config.min_log_bf,
                          "_row": arow, "_mr": amr, "_cand": acand, "_data": adata, "_effect": eff,
                          "_screened": sc})
        say(f"  {eff.name}: ln BF = {gain:.2f}, ARD keeps {kept or 'nothing'}")
    # of two twins only the one with the higher evidence goes on
    by_screen = {id(c["_screened"]): c for c in confirmed}
    for rid, pid in rivals.items():
        a, b = by_screen.get(rid), by_screen.get(pid)
        if a and b and a["survives"] and b["survives"]:
            lo, hi = sorted((a, b), key=lambda c: c["log_evidence"])
            lo["survives"] = False
            lo["rival_of"] = hi["effect"]
            say(f"  {lo['effect']} and {hi['effect']} explain the same; {hi['effect']} has the higher evidence")
    return ranked, confirmed


def _joint_fit(spec, cand, row, best, survivors, data, config, say):
    """The current model with every surviving effect added, each new term at the ARD precision its own
    re-selection found (pruned terms fixed at 0); one evidence evaluation checks they hold together.

    Returns (candidate, row, maximiser result, data, survivors) or None."""
    from .priors import Flat, Normal

    priors, fixed = _essential_from_row(cand, row)
    aspec, adata = cand.model_spec(), data
    for c in survivors:
        n = list(c["scales"])
        aspec, n = augment(aspec, c["_effect"], c["target"], [c["scales"][k] for k in n], names=n)
        adata = with_columns(adata, c["_effect"])
        for k in n:
            a = c["psi_opt"].get(k, 0.0)
            if k not in c["kept_terms"] or a == "inf" or a == INF:
                fixed[k] = 0.0
            else:
                a = float(a)
                priors[k] = Normal(mean=0.0, sd=1.0 / math.sqrt(a)) if a > 0 else Flat()
    acand = CandidateSpec(model=aspec, name=aspec.name, priors=priors, fixed=fixed, ard=[], substeps=cand.substeps)
    say("fitting the distinct survivors together: " + ", ".join(c["effect"] for c in survivors))
    arow, amr = run_candidate(acand, adata, spec, 0, warm=best["_mr"].sampler, final_posterior=config.posterior)
    say(f"  together: ln BF = {arow['log_evidence'] - row['log_evidence']:.2f}")
    return acand, arow, amr, adata, survivors


def _physical(row: dict, name: str, scale: float) -> dict:
    """Posterior summary of a normalised coefficient in physical units (scale > 0)."""
    return {"mean": row["mean"][name] * scale, "sd": row["sd"][name] * scale,
            "q005": row["q005"][name] * scale, "q995": row["q995"][name] * scale}


def _split_stability(spec: StudySpec, c: dict, config: DiagnoseConfig, say, mapper) -> dict:
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
    tasks = [(half, data.slice(lo, hi), spec, warm, config.posterior) for lo, hi in ((0, mid), (mid, n))]
    for r, _ in mapper(_fit_task, tasks):
        parts.append({k: (r["mean"][k], r["sd"][k]) for k in c["kept_terms"]})
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


_ODD = ("cubic_stiffness", "quintic_stiffness", "saturation")


def _character(spec: ModelSpec, phi: dict, eff: Effect, best: dict) -> str | None:
    """'hardening' or 'softening' for an odd stiffness term (its sign against the linear restoring slope);
    even and asymmetric terms (x^2, x|x|, x^4) make the stiffness differ between the two sides instead."""
    if eff.kind != "stiffness" or len(eff.terms) != 1 or not best["posterior"]:
        return None
    if not eff.name.startswith(_ODD):
        return "asymmetric (stiffer on one side)"
    pairs = oscillator_pairs(spec)
    if not pairs:
        return None
    x, v = pairs[0]
    sm = spec.sym
    i = spec.states.index(best["target"])
    xs = sp.Symbol(x, real=True)
    slope = sp.diff(sm.drift[i], xs).subs({p: phi[str(p)] for p in sm.params})
    slope = slope.subs({s: 0 for s in sm.states}).subs({u: 0 for u in sm.inputs})
    try:
        slope = float(slope)
    except TypeError:
        return None
    coef = next(iter(best["posterior"].values()))["mean"]
    if slope == 0 or coef == 0:
        return None
    return "hardening" if np.sign(coef) == np.sign(slope) else "softening"


def _unexplained(res: Residuals, ranked: list, confirmed: list, col: str, config: DiagnoseConfig) -> str:
    t = res.tests[col]
    white = t["ljung_box_p"] > 0.01
    parts = []
    if white and not t["spectrum"]["peaks"]:
        parts.append("the innovations are white (Ljung-Box p = %.3g) with no spectral peak: "
                     "no evidence of a missing effect" % t["ljung_box_p"])
    else:
        parts.append("the residual is NOT explained by any effect in the library")
        parts.append("Ljung-Box Q = %.1f (p = %.2g)" % (t["ljung_box"], t["ljung_box_p"]))
        if t["spectrum"]["peaks"]:
            parts.append("innovation spectral peaks at " + ", ".join(
                "%.4g%s" % (p["f"], f" (harmonic {p['harmonic']})" if p.get("harmonic") else "")
                for p in t["spectrum"]["peaks"][:5]))
        var = {s: float(np.nanvar(r)) for s, r in res.process_noise_rate.items()}
        if var:
            parts.append("injected process noise per state (variance of rate): " + ", ".join(
                f"{s} {v:.3g}" for s, v in var.items()))
        share = _injected_share(res)
        if share:
            parts.append("the noise the filter injects is " + ", ".join(
                f"{100 * v:.2g} % of the rms rate of change of {s}" for s, v in share.items())
                + ("" if max(share.values()) > 0.1 else
                   " (small: the model's dynamics carry the data; what remains is small or outside the dynamics, "
                   "e.g. coloured measurement noise)"))
        if ranked and not any(c["log_bayes_factor"] > config.min_score for c in ranked):
            parts.append("no effect of the library is supported by the evidence, so the model is adequate as far "
                         "as the library can tell")
    unstable = [c for c in confirmed if c.get("stability") and not c["stability"]["stable"]]
    if unstable:
        parts.append("supported by evidence but NOT stable between the two halves of the record (a term "
                     "compensating for something that changes over time, not the missing effect): " + ", ".join(
                         f"{c['effect']} (ln BF {c['log_bayes_factor']:.1f}, z = "
                         f"{max(c['stability']['z'].values()):.1f})" for c in unstable))
    rest = [c for c in confirmed if c not in unstable]
    if rest:
        parts.append("tested by evidence and rejected: " + ", ".join(
            f"{c['effect']} (ln BF {c['log_bayes_factor']:.1f})" for c in rest))
    elif ranked and not confirmed:
        parts.append(f"no candidate's screened ln Bayes factor reaches {config.min_score:g} (best: "
                     f"{ranked[0]['effect']} on {ranked[0]['target']}, {ranked[0]['log_bayes_factor']:.1f})")
    return "; ".join(parts)


def _injected_share(res: Residuals) -> dict:
    """rms of the injected noise rate / rms rate of change of each dynamic state (how much the filter had to push)."""
    out = {}
    for s, r in res.process_noise_rate.items():
        if s not in res.states:
            continue
        rate = np.diff(res.smoothed[:, res.states.index(s)]) / res.dt
        d = float(np.sqrt(np.nanmean((rate - np.nanmean(rate)) ** 2)))
        if d > 0 and np.isfinite(d):
            out[s] = float(np.sqrt(np.nanmean(r ** 2))) / d
    return out


def _strip(tests: dict) -> dict:
    """JSON part of the tests (the spectrum arrays go to the figures)."""
    out = {}
    for c, t in tests.items():
        d = {k: v for k, v in t.items() if k not in ("spectrum", "acf")}
        d["acf"] = [float(x) for x in t["acf"]]
        d["spectral_peaks"] = t["spectrum"]["peaks"]
        out[c] = d
    return out


def _arrays(res: Residuals, fr: dict) -> dict:
    return {"tests": res.tests, "innovations": res.innovations, "process_noise_rate": res.process_noise_rate,
            "free_run": fr}


def jsonable(report: dict) -> dict:
    """The report without its arrays, ready for ``json.dump``."""
    return to_jsonable({k: v for k, v in report.items() if not k.startswith("_")})
