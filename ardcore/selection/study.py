"""Study specification and the serial/executor-driven model-selection run.

A study names a data set, candidate models (built-in names or full inline
declarations) with their essential priors and ARD parameters, sampler and
maximiser settings, and a seed. :func:`select` runs it: per model the ARD
evidence maximisation, then the comparison of the optimal nested models
(Eq. 7). The same spec is accepted unchanged by the REST API.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import math
import time
from pathlib import Path
from typing import Callable, Generator

import numpy as np

from ..evidence.estimators import COLLAPSED
from ..evidence.evaluate import EvidenceEvaluator, EvidenceSettings
from .maximiser import iter_maximise
from .trial import MaximiserResult, posterior_summary
from ..data import Dataset
from ..errors import FitError
from ..events import ModelEvent, ProgressEvent, TrialDone
from .fit import ModelFit
from .hold import with_holds
from .summary import ComparedModel, StudySummary
from ..jsonio import to_jsonable
from ..sampling.chains import Map, SamplerError, run, serial_map
from ..sampling.driver import Runtime
from .spec import (
    CandidateSpec,
    StudySpec,
)


# --------------------------------------------------------------------------- running
def model_probabilities(log_z: list[float], se: list[float], prior: list[float] | None = None,
                        n_draws: int = 4000, seed: int = 0) -> tuple[list[float], list[float]]:
    """P(M_r | d) by Eq. 7 and its standard deviation from the evidence standard errors."""
    lz = np.asarray(log_z, dtype=float)
    lp = np.log(np.asarray(prior, dtype=float) / np.sum(prior)) if prior else np.full(lz.size, -math.log(lz.size))
    w = lz + lp
    p = np.exp(w - np.logaddexp.reduce(w))
    rng = np.random.default_rng(seed)
    draws = lz[None, :] + np.asarray(se)[None, :] * rng.standard_normal((n_draws, lz.size)) + lp
    pd = np.exp(draws - np.logaddexp.reduce(draws, axis=1, keepdims=True))
    return p.tolist(), pd.std(axis=0).tolist()


@dataclass(frozen=True)
class CandidateHooks:
    """How one candidate's maximisation runs and reports, each optional: ``map_fn`` runs the chains' tasks,
    ``progress`` receives :class:`~ardcore.events.ModelEvent` s, ``cancel`` is asked between rounds,
    ``evaluator_factory`` (same arguments as :class:`EvidenceEvaluator`) lets an orchestrator substitute its
    own evaluator (caching, checkpoints, remote chains), ``on_trial`` is called with every finished
    :class:`~ardcore.selection.trial.Trial`."""

    map_fn: Map = serial_map
    progress: Callable[[ModelEvent], None] | None = None
    cancel: Callable[[], bool] | None = None
    evaluator_factory: Callable[..., EvidenceEvaluator] | None = None
    on_trial: Callable | None = None


def run_candidate(cand: CandidateSpec, data: Dataset, spec: StudySpec, index: int, *,
                  hooks: CandidateHooks = CandidateHooks(), warm=None,
                  final_posterior: str = "sample") -> tuple[ModelFit, MaximiserResult]:
    """ARD evidence maximisation for one candidate; returns its :class:`~ardcore.selection.fit.ModelFit` and the
    full result: :func:`iter_candidate` with the chain tasks on ``hooks.map_fn``.

    ``hooks`` (:class:`CandidateHooks`): how it runs and reports; ``warm`` (a
    :class:`~ardcore.sampling.driver.SamplerResult`) warm-starts the first trial. With Laplace evidence,
    ``final_posterior="laplace"`` reports the Laplace posterior N(MAP, H^-1) instead of sampling it.
    """
    return run(iter_candidate(cand, data, spec, index, hooks=hooks, warm=warm, final_posterior=final_posterior),
               hooks.map_fn)


def iter_study_candidate(cand: CandidateSpec, data: Dataset, spec: StudySpec, index: int, *,
                         hooks: CandidateHooks = CandidateHooks()) -> Generator:
    """:func:`iter_candidate` as a study runs it: a candidate that no chain can fit (no finite posterior where
    the starts reach) is refused with the reason (:meth:`ModelFit.failed`) and the study compares the others.
    Returns (:class:`ModelFit`, :class:`MaximiserResult` or None when refused)."""
    t0 = time.perf_counter()
    try:
        return (yield from iter_candidate(cand, data, spec, index, hooks=hooks))
    except (SamplerError, FitError) as exc:
        return ModelFit.failed(cand.label, str(exc), time.perf_counter() - t0), None


def iter_candidate(cand: CandidateSpec, data: Dataset, spec: StudySpec, index: int, *,
                   hooks: CandidateHooks = CandidateHooks(), warm=None,
                   final_posterior: str = "sample") -> Generator:
    """:func:`run_candidate` as a generator of the chain tasks its trials wait for (what the evaluator's
    :meth:`~ardcore.evidence.evaluate.EvidenceEvaluator.trial` yields): an event loop advances many
    candidates at once, each as its tasks finish. Returns (:class:`ModelFit`, :class:`MaximiserResult`)."""
    t0 = time.perf_counter()
    label = cand.label
    progress, on_trial = hooks.progress, hooks.on_trial

    def prog(p: ProgressEvent):
        if progress:
            progress(ModelEvent(label, p))

    factory = hooks.evaluator_factory or EvidenceEvaluator
    ev = factory(cand.model_spec(), dict(cand.priors), data,
                 EvidenceSettings(spec.sampler, spec.evidence, final_posterior), substeps=cand.substeps,
                 runtime=Runtime(map_fn=hooks.map_fn, progress=prog, cancel=hooks.cancel))

    def trial_done(tr):
        prog(TrialDone(tr.iteration, tr.action, dict(tr.psi), tr.evidence.log_evidence, tr.evidence.log_evidence_se,
                       tr.accepted, tr.bound))
        if on_trial:
            on_trial(tr)

    seed = spec.seed * 1_000_003 + 7919 * index
    mr = yield from iter_maximise(ev.trial, cand.thresholds(), spec.maximiser, seed=seed, on_trial=trial_done,
                                  warm=warm, budget=ev.stationary_budget)
    res, target = mr.sampler, mr.target
    if spec.evidence == "laplace":
        target, _, res = yield from ev.trial(mr.psi_opt, seed + 99991, mr.sampler, final=True)
        mr.sampler = res
    flat = res.samples.reshape(-1, len(res.names))
    post = posterior_summary(res.names, flat)
    best = mr.best
    row = ModelFit(
        name=label,
        log_evidence=best.evidence.log_evidence,
        log_evidence_se=best.evidence.log_evidence_se,
        goodness_of_fit=best.evidence.goodness_of_fit,
        information_gain=best.evidence.information_gain,
        evidence_method=best.evidence.method,
        psi_opt=dict(mr.psi_opt),
        kept=list(mr.kept),
        pruned=list(mr.pruned),
        map=dict(zip(res.names, map(float, res.phi_star))),
        mean={k: v["mean"] for k, v in post.items()},
        sd={k: v["sd"] for k, v in post.items()},
        q005={k: v["q005"] for k, v in post.items()},
        q995={k: v["q995"] for k, v in post.items()},
        rhat=dict(zip(res.names, map(float, res.rhat))),
        diagnostics=_diagnostics(res),
        # draws whose spread the posterior's density contradicts are not converged, whatever R-hat says
        converged=bool(getattr(res, "quality_met", True)) and not any(COLLAPSED in w for w in best.evidence.warnings),
        iterations=len(mr.history),
        sampled_trials=sum(1 for t in mr.history if t.sampled),
        reweighted_trials=sum(1 for t in mr.history if not t.sampled),
        n_evaluations=sum(int(t.diagnostics.get("n_evaluations", 0)) for t in mr.history),
        wall_s=time.perf_counter() - t0,
        warnings=list(best.evidence.warnings),
        per_chain_log_evidence=[c.log_evidence for c in best.evidence.per_chain],
    )
    why = row.degenerate()
    if why is not None:  # reported as what it is, never as a converged result
        row = dataclasses.replace(row, warnings=[*row.warnings, f"degenerate fit: {why}"], converged=False)
    return row, mr


def _diagnostics(res) -> dict:
    """ArviZ's diagnostics of the reported draws: the sampler's own, else computed from them (a Laplace
    posterior's independent draws)."""
    from ..sampling.diagnostics import convergence

    if getattr(res, "diagnostics", None):
        return res.diagnostics
    if res.samples.ndim == 3 and res.samples.shape[0] >= 2 and res.samples.shape[1] >= 4:
        return convergence(list(res.names), res.samples)
    return {}


def data_meta(data: Dataset, hold: list[str]) -> dict:
    """What a study's summary says of its data: the source, the length and, when the record decided how the
    models take their inputs between samples, the notes saying so (:func:`~.hold.with_holds`)."""
    return {"source": data.meta.get("source"), "n": len(data), **({"input_hold": hold} if hold else {})}


def compare(fits: list[ModelFit], spec: StudySpec, data_meta: dict, wall_s: float) -> StudySummary:
    """The comparison of the optimal nested models (Eq. 7): the study's :class:`StudySummary`.

    A fit that is no result (:meth:`ModelFit.degenerate`: an evidence that is not a finite number, a collapsed
    posterior, chains that never moved) is refused with its reason and takes no part: the others are compared
    among themselves.

    Raises
    ------
    FitError
        When no candidate gave a result (a summary is never "done" on evidences that are not numbers).
    """
    refused = [f.degenerate() for f in fits]
    ok = [i for i, why in enumerate(refused) if why is None]
    if not ok:
        raise FitError("no candidate gave a result: " + "; ".join(refused))
    probs, psd = model_probabilities([fits[i].log_evidence for i in ok], [fits[i].log_evidence_se for i in ok],
                                     seed=spec.seed)
    prob, sd = dict(zip(ok, probs)), dict(zip(ok, psd))
    models = tuple(ComparedModel(f, prob.get(i, 0.0), sd.get(i, 0.0), refused[i]) for i, f in enumerate(fits))
    best = max((fits[i] for i in ok), key=lambda f: f.log_evidence).name
    return StudySummary(spec.name, dict(data_meta), models, best, spec.seed, wall_s, spec.model_dump(mode="json"))


def select(spec: StudySpec, *, map_fn: Map = serial_map, progress: Callable[[ModelEvent], None] | None = None,
           base: Path | None = None, cancel=None) -> dict:
    """Run a study in this process (or with ``map_fn`` over any executor), in memory.

    Returns the summary dict with every trial of every model under ``"_history"``. Nothing is written:
    files are the study store's (``ardflow select`` with any executor writes one zarr layout, see
    :mod:`workers.store`).
    """
    t0 = time.perf_counter()
    data = spec.load_data(base)
    spec, hold = with_holds(spec, data)
    rows, results = [], {}
    for i, cand in enumerate(spec.models):
        row, mr = run(iter_study_candidate(cand, data, spec, i, hooks=CandidateHooks(map_fn, progress, cancel)),
                      map_fn)
        rows.append(row)
        results[cand.label] = mr.history if mr is not None else []
    summary = compare(rows, spec, data_meta(data, hold),
                      time.perf_counter() - t0).to_json()
    summary["_history"] = to_jsonable({k: [t.to_dict() for t in history] for k, history in results.items()})
    return summary
