"""A study on this machine (serially or on a process pool) written to the same zarr store as on Dask.

``ardflow select --executor serial|processes`` runs here: the chains go to a local map instead of Dask
tasks, and every trial, history, result and the summary land in the store exactly as
:mod:`workers.graph` writes them, so the report, the figures, ``ardflow loo`` and the service's routes read
either the same way.
"""

from __future__ import annotations

import time
from functools import partial
from typing import Callable

from ardflow.ardcore.evidence.evaluate import EvidenceEvaluator
from ardflow.ardcore.events import ModelEvent
from ardflow.ardcore.sampling.chains import Map
from ardflow.ardcore.selection.spec import StudySpec
from ardflow.ardcore.selection.study import CandidateHooks

from .graph import compare_task, fit_model, progress_writer, trial_json
from .store import StudyStore


class LocalStoredEvaluator(EvidenceEvaluator):
    """Evidence at psi on a local map; each sampled trial's draws and record go to the store."""

    def __init__(self, spec, essential, data, settings, *, store: StudyStore, model: str, **kw):
        super().__init__(spec, essential, data, settings, **kw)
        self.store, self.model = store, model

    def trial(self, psi: dict, seed: int, warm, *, final: bool = False, iteration: int | None = None,
              extend: bool = False, bound: bool = False):
        target, ev, res = yield from super().trial(psi, seed, warm, final=final, iteration=iteration, extend=extend,
                                                   bound=bound)
        if self.method == "laplace" or iteration is None or res is None or not res.samples.size:
            return target, ev, res
        nc, M, _ = res.samples.shape
        self.store.create_trial(self.model, iteration, list(res.names), nc, M, self.sampler.round_size, psi)
        for c in range(nc):
            self.store.write_round(self.model, iteration, c, 0, res.samples[c], res.lp[c], res.ll[c])
        self.store.finish_trial(self.model, iteration, trial_json(psi, ev, res))
        return target, ev, res


def run_study_local(store: StudyStore, map_fn: Map, *, progress: Callable[[ModelEvent], None] | None = None,
                    done: bool = True) -> dict:
    """Run the study in ``store`` model after model, chains on ``map_fn``; returns the summary (``done``:
    as :func:`workers.graph.run_study`; one driver per store, as there)."""
    with store.driver_lock():
        return _drive_local(store, map_fn, progress, done)


def _drive_local(store: StudyStore, map_fn: Map, progress, done: bool) -> dict:
    spec = StudySpec.model_validate(store.meta["spec"])
    data = store.load_data()
    start = time.time()
    store.update_meta(status="running", started=start)
    rows = []
    try:
        for i, cand in enumerate(spec.models):
            model = cand.label
            write = progress_writer(store, model)

            def prog(p: ModelEvent, write=write) -> None:
                write(p)
                if progress:
                    progress(p)

            rows.append(fit_model(store, spec, data, i, CandidateHooks(
                map_fn=map_fn, progress=prog,
                evaluator_factory=partial(LocalStoredEvaluator, store=store, model=model))))
    except BaseException as exc:
        from ardflow.ardcore.sampling.driver import Cancelled

        store.update_meta(status="cancelled" if isinstance(exc, Cancelled) else "failed", error=str(exc))
        raise
    return compare_task(str(store), start, *rows, done=done)
