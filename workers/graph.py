"""A study as Dask tasks.

* one **maximiser** per candidate model, a sans-IO generator advanced by the
  driver's one event loop as its tasks finish (the decision logic is cheap; the
  work is in the chain tasks it submits, so a lost worker never takes a
  maximiser with it);
* per trial psi, **chain tasks** for every step: start optimisation, each
  burn-in round (which reports to the trial's coordinator actor), each
  stationary round (which writes its samples to the zarr store), and the
  Chib-Jeliazkov ordinates;
* a **comparison task** that depends on every maximiser task.

Task keys are deterministic and readable on the dashboard, e.g.
``burnin-<study>-M2-it003-r004-c1``. Everything a task needs to restart is in
the store: finished trials are read back, the trial in flight resumes from its
last checkpoint, so a lost worker costs at most one round and a killed
driver continues with :func:`resume_study`.
"""

from __future__ import annotations

import json
import logging
import os
import time
import uuid
from concurrent.futures import CancelledError
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Callable, NamedTuple


from ardflow.ardcore.evidence.evaluate import EvidenceEvaluator, build_target
from ardflow.ardcore.events import ModelDone, ModelEvent
from ardflow.ardcore.evidence.estimators import Evidence, iter_chib_jeliazkov
from ardflow.ardcore.sampling.config import SamplerResult
from ardflow.ardcore.sampling.chains import relay, run
from ardflow.ardcore.sampling.driver import Runtime, Start, continuation, continued, sample_batches
from ardflow.ardcore.selection.fit import ModelFit
from ardflow.ardcore.selection.hold import with_holds
from ardflow.ardcore.selection.trial import MaximiserResult, Trial
from ardflow.ardcore.selection.spec import StudySpec
from ardflow.ardcore.selection.study import CandidateHooks, compare, data_meta, iter_study_candidate

from .coordinator import ActorPool, wait_connected
from ardflow.ardcore.jsonio import decode_alpha, to_jsonable
from .store import StudyStore
from .tasks import DaskMap, StoppableTarget, Submitted, cancel_event_name

log = logging.getLogger("ardflow.workers")

# --------------------------------------------------------------------------- trials with a store


def trial_json(psi: dict, ev: Evidence, res: SamplerResult) -> dict:
    """A finished trial's record in the store: psi, its evidence and its sampler result without the draws
    (each type writes its own JSON)."""
    return to_jsonable({"psi": psi, "evidence": ev.to_dict(), **res.to_json()})


def trial_from_json(rec: dict, store: StudyStore, model: str, iteration: int) -> tuple[Evidence, SamplerResult]:
    """The evidence and sampler result of a finished trial, its draws read from ``store``."""
    samples, lp, ll, _ = store.read_samples(model, iteration)
    return Evidence.from_dict(rec["evidence"]), SamplerResult.from_json(rec, samples, lp, ll)


class TrialSite(NamedTuple):
    """Where a model's trials run and are kept: the Dask ``client``, the ``store``, the study and the model."""

    client: object
    store: StudyStore
    study_id: str
    model: str


class StoredEvaluator(EvidenceEvaluator):
    """Evidence at psi with chains on Dask, samples and checkpoints in the store (``site``).

    A trial already finished in the store is read back instead of recomputed;
    a trial with a checkpoint resumes from it.
    """

    def __init__(self, spec, essential, data, settings, *, site: TrialSite, **kw):
        super().__init__(spec, essential, data, settings, **kw)
        self.client, self.store, self.study_id, self.model = site
        # the in-process stages (a Laplace trial's final chains, start optimisations) map onto the cluster too
        self.runtime = replace(self.runtime, map_fn=DaskMap(site.client, f"{site.study_id}-{site.model}"))

    def trial(self, psi: dict, seed: int, warm, *, final: bool = False, iteration: int | None = None,
              extend: bool = False, bound: bool = False):
        """:meth:`EvidenceEvaluator.trial` with its chain tasks submitted to the cluster: it yields each
        batch as :class:`~workers.tasks.Submitted` futures (an event loop advances it when they finish;
        called directly, it waits). A bound (no chains, nothing stored but the history) and a Laplace trial
        take their searches to the cluster as plain tasks."""
        if bound:
            # keys of their own: a later bound's searches under the model's keys would be handed this one's results
            dmap = DaskMap(self.client, f"{self.study_id}-{self.model}-it{iteration:03d}-bound")
            return (yield from submitted(super().trial(psi, seed, warm, iteration=iteration, bound=True), dmap))
        if self.method == "laplace" or iteration is None:
            return (yield from submitted(super().trial(psi, seed, warm, final=final, iteration=iteration,
                                                       extend=extend), self.runtime.map_fn))
        model, store = self.model, self.store
        target = StoppableTarget(build_target(self.spec, self.essential, psi, self.data, self.substeps),
                                 self.study_id, max_task_s=float(os.environ.get("ARDFLOW_MAX_TASK_S", 21600)))
        rec = store.trial_record(model, iteration)
        if rec is not None and rec["psi"] == to_jsonable(psi):
            ev, res = trial_from_json(rec, store, model, iteration)
            return target, ev, res
        # search trials draw the judged M; the reported one continues its chains to the quality target
        cfg = self.config(extend)
        prefix = f"{self.study_id}-{model}-it{iteration:03d}"
        ck = store.read_checkpoint(model, iteration)
        if ck is not None and ck.get("psi") != to_jsonable(psi):
            ck = None
        if ck is None and extend:
            # the continued chains' draws so far are this trial's first draws
            ck = continuation(warm)
            nc, m = warm.samples.shape[:2]
            store.create_trial(model, iteration, list(target.names), nc, m, cfg.round_size, psi)
            for c in range(nc):
                store.write_round(model, iteration, c, 0, warm.samples[c], warm.lp[c], warm.ll[c])
        else:
            store.create_trial(model, iteration, list(target.names), cfg.n_chains, cfg.n_stationary,
                               cfg.round_size, psi)
        if ck is not None and ck["stage"] == "stationary" and "samples" not in ck:
            s, lp, ll, _ = store.read_samples(model, iteration)
            ck.update(samples=s, lp=lp, ll=ll)
        dmap = DaskMap(self.client, prefix, store, model, iteration, coordinator=True)
        pools: list[ActorPool] = []

        def factory(state):
            p = ActorPool(self.client, state, prefix)
            pools.append(p)
            return p

        def checkpoint(d):
            store.write_checkpoint(model, iteration, {**d, "psi": to_jsonable(psi)})

        try:
            res = yield from submitted(sample_batches(
                target, cfg, seed=seed, start=Start(warm=warm, resume=ck),
                runtime=Runtime(progress=self.progress, cancel=self.cancel, pool_factory=factory,
                                checkpoint=checkpoint)), dmap)
        finally:
            for p in pools:
                p.close()
        if extend:
            res = continued(res, warm)
        store.resize_draws(model, iteration, res.samples.shape[1])  # exactly the draws kept
        ev = yield from submitted(iter_chib_jeliazkov(target, res, n_proposal=cfg.n_proposal, seed=seed + 7,
                                                      proposal_se_ratio=cfg.proposal_se_ratio), dmap)
        ev.warnings = list(res.warnings) + ev.warnings
        if pools and pools[0].restarts:
            ev.warnings.append(f"coordinator actor restored {pools[0].restarts} time(s) after a lost worker")
        store.finish_trial(model, iteration, trial_json(psi, ev, res))
        return target, ev, res


def submitted(steps, dmap: DaskMap):
    """The sans-IO generator ``steps`` with each :class:`~ardcore.sampling.chains.Batch` it yields
    submitted through ``dmap``: this yields the :class:`~workers.tasks.Submitted` futures instead and sends
    their results (or raises their error) back into ``steps``."""
    return relay(steps, dmap.submit)


def stored_fit(store: StudyStore, model: str) -> tuple[ModelFit, MaximiserResult] | None:
    """The finished fit of ``model`` in ``store``: its summary row and its maximisation's result (the best
    trial, whose chains warm-start refits; the trial history stays in the store), or None when the model is
    not finished (or was fitted by Laplace)."""
    try:
        it, row = store.model_result(model)
    except Exception:  # noqa: BLE001 - no such model
        return None
    rec = store.trial_record(model, it) if it is not None else None
    if not row or rec is None or "states" not in rec:
        return None
    ev, res = trial_from_json(rec, store, model, it)
    spec = StudySpec.model_validate(store.meta["spec"])
    cand = next(c for c in spec.models if c.label == model)
    psi = {k: decode_alpha(v) for k, v in rec["psi"].items()}
    target = build_target(cand.model_spec(), dict(cand.priors), psi, store.load_data(), cand.substeps)
    best = Trial(it, psi, ev, True, "stored", 0.0, {}, {})
    return row, MaximiserResult(psi, best, res, target)


# --------------------------------------------------------------------------- study tasks


def progress_writer(store: StudyStore, model: str) -> Callable[[ModelEvent], None]:
    """Progress events of ``model`` appended to the store, stamped with the time (what ``read_progress`` and
    the service stream)."""
    rel = f"progress/{model}.jsonl"

    def write(ev: ModelEvent) -> None:
        store.append_line(rel, json.dumps(replace(ev, model=model, time=time.time()).to_json()))
    return write


def fit_model(store: StudyStore, spec: StudySpec, data, index: int, hooks: CandidateHooks) -> ModelFit:
    """One candidate's ARD evidence maximisation with its trials recorded in ``store``: :func:`iter_fit` with
    the chain tasks on ``hooks.map_fn`` (batches an evaluator submitted itself are waited for)."""
    return run(iter_fit(store, spec, data, index, hooks), hooks.map_fn)


def iter_fit(store: StudyStore, spec: StudySpec, data, index: int, hooks: CandidateHooks):
    """One candidate's ARD evidence maximisation (:func:`~ardcore.selection.study.iter_study_candidate`, the same
    generator of chain tasks) with its trials recorded in ``store``: the history as each trial finishes, the
    result and best iteration at the end; the same layout whatever runs the chains. Returns its
    :class:`ModelFit`."""
    cand = spec.models[index]
    model = cand.label
    history: list[dict] = []

    def on_trial(tr):
        history.append(tr.to_dict())
        store.set_model_attrs(model, history=history)

    row, mr = yield from iter_study_candidate(cand, data, spec, index, hooks=replace(hooks, on_trial=on_trial))
    if mr is None:  # refused: no chain could fit it; the comparison says why
        store.set_model_attrs(model, result=row, history=history)
        if hooks.progress:
            hooks.progress(ModelEvent(cand.label, ModelDone(row.log_evidence)))
        return row
    best_iteration = mr.best.iteration
    if spec.evidence == "laplace":
        # Laplace trials sample nothing; the posterior drawn at psi_opt gets a trial group of its own
        res = mr.sampler
        best_iteration = len(mr.history)
        nc, M, d = res.samples.shape
        store.create_trial(model, best_iteration, list(res.names), nc, M, M, mr.psi_opt)
        for c in range(nc):
            store.write_round(model, best_iteration, c, 0, res.samples[c], res.lp[c], res.ll[c])
        store.finish_trial(model, best_iteration, {"psi": to_jsonable(mr.psi_opt), "final_laplace_posterior": True})
    store.set_model_attrs(model, result=row, history=[t.to_dict() for t in mr.history],
                          best_iteration=best_iteration)
    if hooks.progress:
        hooks.progress(ModelEvent(cand.label, ModelDone(row.log_evidence)))
    return row


def compare_task(store_path: str, wall_start: float, *rows: ModelFit, done: bool = True) -> dict:
    """Comparison of the optimal nested models; writes the :class:`StudySummary` to the store (``done``: and
    marks the study done) and returns its JSON."""
    store = StudyStore(store_path)
    spec = StudySpec.model_validate(store.meta["spec"])
    meta = store.meta
    summary = compare(list(rows), spec, meta.get("data", {}), time.time() - wall_start).with_study_id(
        meta.get("study_id"))
    history = store.histories([r.name for r in rows])
    store.write_text("history.json", json.dumps(to_jsonable(history), indent=2))
    store.write_summary(summary, done=done)
    return summary.to_json()


# --------------------------------------------------------------------------- driver side


def prepare_store(spec: StudySpec, store_path: str | Path, *, base: Path | None = None,
                  datasets: Path | None = None, study_id: str | None = None) -> StudyStore:
    """Create the store with the spec and the data set (a new study id unless given); a data set the models
    cannot be fitted to is refused first (:meth:`StudySpec.check_data`)."""
    data = spec.load_data(base, datasets)
    spec.check_data(data)
    spec, hold = with_holds(spec, data)  # stored as it runs: the workers read the hold from the stored spec
    store = StudyStore.create(store_path, spec.model_dump(mode="json"), data)
    meta = store.meta
    if not meta.get("study_id"):
        store.update_meta(study_id=study_id or f"{spec.name}-{uuid.uuid4().hex[:8]}", status="created",
                          data=data_meta(data, hold))
    return store


def read_progress(store: StudyStore, offsets: dict[str, int]) -> list[ModelEvent]:
    """New progress events since ``offsets`` (updated in place)."""
    out = []
    for name in store.list_files("progress", ".jsonl"):
        model = name[: -len(".jsonl")]
        chunk = store.read_from(f"progress/{name}", offsets.get(model, 0))
        complete = chunk[: chunk.rfind(b"\n") + 1]
        offsets[model] = offsets.get(model, 0) + len(complete)
        for line in complete.decode(errors="ignore").splitlines():
            try:
                ev = ModelEvent.from_json({**json.loads(line), "model": model})
            except (json.JSONDecodeError, TypeError, ValueError):
                continue  # a torn or foreign line
            if ev is not None:
                out.append(ev)
    return out


def run_study(client, store: StudyStore, *, progress: Callable[[ModelEvent], None] | None = None,
              poll_s: float = 1.0, done: bool = True) -> dict:
    """Run (or continue) the study in ``store`` on ``client``; blocks until the summary exists. With
    ``done`` False the caller marks the study done (after its report). One driver per store: a second one
    is refused (:meth:`StudyStore.driver_lock`)."""
    with store.driver_lock():
        try:
            return _drive(client, store, progress, poll_s, done)
        except BaseException as exc:
            from ardflow.ardcore.sampling.driver import Cancelled

            store.update_meta(status="cancelled" if isinstance(exc, Cancelled) else "failed", error=str(exc))
            raise


def _drive(client, store: StudyStore, progress, poll_s: float, done: bool) -> dict:
    """The study as one loop over events (no thread): every model's maximisation is a generator of chain
    batches (:func:`iter_fit`); the loop submits each batch, waits for the first of all submitted tasks to
    finish, streams the progress, sends every finished batch's results back to its model (which decides its
    next batch: a round, a trial, the next psi) and, when every model is done, submits the comparison."""
    from distributed import Event, wait

    meta = store.meta
    study_id = meta["study_id"]
    spec = StudySpec.model_validate(meta["spec"])
    start = meta.get("started") or time.time()
    store.update_meta(status="running", started=start)
    data = store.load_data()
    flag = Event(cancel_event_name(study_id), client=client)

    def cancel() -> bool:
        try:
            return flag.is_set()
        except Exception:  # noqa: BLE001 - a dropped scheduler connection is not a cancellation
            return False

    models = [c.label for c in spec.models]
    fits = {m: iter_fit(store, spec, data, i, CandidateHooks(
        progress=progress_writer(store, m), cancel=cancel,
        evaluator_factory=partial(StoredEvaluator, site=TrialSite(client, store, study_id, m))))
        for i, m in enumerate(models)}
    waiting: dict[str, Submitted] = {}
    rows: dict[str, ModelFit] = {}
    offsets: dict[str, int] = {}

    def advance(model: str, reply=None, error: BaseException | None = None) -> None:
        try:
            gen = fits[model]
            waiting[model] = gen.throw(error) if error is not None else gen.send(reply)
        except StopIteration as finished:
            rows[model] = finished.value

    streamed = [0.0]

    def stream(force: bool = False) -> None:
        # the progress files are read at most every poll_s (tasks finish far more often)
        if force or time.monotonic() - streamed[0] >= poll_s:
            streamed[0] = time.monotonic()
            for ev in read_progress(store, offsets):
                if progress:
                    progress(ev)

    try:
        for m in models:
            advance(m)
        while waiting:
            futures = [f for sub in waiting.values() for f in sub.futures if not f.done()]
            if futures:
                try:
                    wait(futures, timeout=poll_s, return_when="FIRST_COMPLETED")
                except (TimeoutError, CancelledError):
                    pass  # nothing finished yet, or a dropped connection (each batch recovers below)
            stream()
            for m, sub in list(waiting.items()):
                try:
                    out = sub.gather()  # None while running (or when a dropped connection cancelled it)
                except Exception as exc:  # noqa: BLE001 - a task's error, raised in the model that waits
                    del waiting[m]
                    advance(m, error=exc)
                    continue
                if out is not None:
                    del waiting[m]
                    advance(m, out)
                elif sub.stalled():
                    sub.recover()
    finally:
        for gen in fits.values():
            gen.close()
    stream(force=True)
    results = [rows[m] for m in models]
    for attempt in range(3):
        wait_connected(client)
        comp = client.submit(compare_task, str(store), start, *results, done=done,
                             key=f"compare-{study_id}" + (f"-a{attempt}" if attempt else ""))
        try:
            return comp.result()
        except CancelledError:
            continue
    raise RuntimeError("the comparison task was cancelled three times (scheduler connection lost)")


def cancel_study(client, study_id: str) -> None:
    """Cooperative cancellation: chains stop at the end of their current round."""
    from distributed import Event

    Event(cancel_event_name(study_id), client=client).set()
