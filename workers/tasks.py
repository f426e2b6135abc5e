"""The Dask side of one trial: chain-round tasks, the map that submits them under deterministic keys, and
the posterior target that stops its task when the study is cancelled."""

from __future__ import annotations

import logging
import time
from concurrent.futures import CancelledError

from ardflow.ardcore.sampling.chains import Batch, Step, round_task

from .coordinator import actor_variable_name, wait_connected
from .store import StudyStore

log = logging.getLogger("ardflow.workers")


def cancel_event_name(study_id: str) -> str:
    return f"cancel-{study_id}"


# --------------------------------------------------------------------------- chain tasks


class StoppableTarget:
    """A posterior target that stops the task running it when its study is cancelled.

    Cancellation is otherwise seen by the driver between rounds; a round (or a start optimisation, or the
    Chib-Jeliazkov proposals) of a slow likelihood can take minutes, during which the worker would stay
    busy after a cancel. Every ``check_s`` seconds of calls the study's cancel event is read (one small
    scheduler request), and a set event raises :class:`~ardcore.sampling.driver.Cancelled` in the task, which frees
    the worker at once.
    """

    check_s = 2.0

    def __init__(self, target, study_id: str, max_task_s: float | None = None):
        self.target, self.study_id, self.max_task_s = target, study_id, max_task_s
        self._last, self._event = time.monotonic(), None

    def __getstate__(self):
        return {"target": self.target, "study_id": self.study_id, "max_task_s": self.max_task_s}

    def __setstate__(self, d):
        self.target, self.study_id, self.max_task_s = d["target"], d["study_id"], d.get("max_task_s")
        self._last, self._event = time.monotonic(), None

    def __getattr__(self, name):
        if name in ("target", "study_id", "max_task_s"):
            raise AttributeError(name)
        return getattr(self.target, name)

    def __call__(self, x):
        now = time.monotonic()
        if now - self._last > self.check_s:
            self._last = now
            if self._cancelled():
                from ardflow.ardcore.sampling.driver import Cancelled

                raise Cancelled(f"study {self.study_id} was cancelled")
            self._check_wall_clock()
        return self.target(x)

    def _check_wall_clock(self) -> None:
        """The backstop: a task running longer than ``max_task_s`` (as the worker timed it) fails the trial
        with a message, instead of holding its worker indefinitely."""
        if not self.max_task_s:
            return
        from distributed.worker import thread_state

        start = getattr(thread_state, "start_time", None)
        if start is not None and time.time() - start > self.max_task_s:
            from ardflow.ardcore.sampling.chains import SamplerError

            raise SamplerError(f"a task of study {self.study_id} ran longer than its limit of "
                               f"{self.max_task_s:g} s (ARDFLOW_MAX_TASK_S); use fewer sub-steps or rows per "
                               f"likelihood, or raise the limit")

    def _cancelled(self) -> bool:
        try:
            if self._event is None:
                from distributed import Event

                self._event = Event(cancel_event_name(self.study_id))
            return bool(self._event.is_set())
        except Exception:  # noqa: BLE001 - no cluster reachable (a local run): nothing to stop for
            return False


def _burnin_round_task(args, prefix: str, chain: int, round_index: int):
    """One burn-in round of one chain; the statistics go to the coordinator actor."""
    res = round_task(args)
    try:
        from distributed import Variable

        fut = Variable(actor_variable_name(prefix)).get(timeout=5)
        fut.result(timeout=10).report(chain, round_index, res.halves, res.best).result(timeout=30)
    except Exception:
        pass  # the driver re-reports; a missing actor is restored there
    return res


def _stationary_round_task(args, store_path: str, model: str, iteration: int, chain: int, start: int):
    """One stationary round of one chain, streamed into its own chunk of the store."""
    res = round_task(args)
    StudyStore(store_path).write_round(model, iteration, chain, start, res.samples, res.lp, res.ll)
    return res


class DaskMap:
    """:data:`ardcore.sampling.driver.Map` on a Dask client with deterministic task keys."""

    def __init__(self, client, prefix: str, store: StudyStore | None = None, model: str | None = None,
                 iteration: int | None = None, coordinator: bool = False):
        self.client, self.prefix = client, prefix
        self.store, self.model, self.iteration = store, model, iteration
        self.coordinator = coordinator  # burn-in tasks report to the trial's coordinator actor
        self._slots: tuple[int, float] | None = None  # (worker threads, when asked): :meth:`slots`

    stall_s = 20.0
    """After this long without progress, check that the scheduler still knows every key being waited for."""

    slots_s = 10.0
    """How long the cluster's thread count (:meth:`slots`) is taken as known before it is asked again."""

    def slots(self) -> int:
        """Worker threads in the cluster: how many of a batch's tasks run at once (:class:`Submitted`). Asked of
        the scheduler at most every ``slots_s`` (workers come and go with an adaptive cluster)."""
        now = time.monotonic()
        known = self._slots
        if known is None or now - known[1] > self.slots_s:
            try:
                n = sum(self.client.nthreads().values())
            except Exception:  # noqa: BLE001 - no answer (a dropped connection): no limit, as before
                n = 0
            known = self._slots = (n or 1 << 20, now)
        return known[0]

    def _submit(self, func, it, ch: int, step: Step | None, attempt: int):
        c = self.client
        sfx = f"-a{attempt}" if attempt else ""
        if step is not None and step.kind == "burnin" and self.coordinator:
            return c.submit(_burnin_round_task, it, self.prefix, ch, step.index,
                            key=f"burnin-{self.prefix}-r{step.index:03d}-c{ch}{sfx}")
        if step is not None and step.kind == "stationary" and self.store is not None:
            return c.submit(_stationary_round_task, it, str(self.store), self.model, self.iteration,
                            ch, step.index, key=f"stationary-{self.prefix}-d{step.index:06d}-c{ch}{sfx}")
        name = step.kind if step is not None else getattr(func, "__name__", "task").strip("_")
        rest = f"-{step.index}" if step is not None and step.index is not None else ""
        return c.submit(func, it, key=f"{name}-{self.prefix}{rest}-c{ch}{sfx}")

    def submit(self, batch: Batch) -> "Submitted":
        """The batch's tasks submitted (the stationary rounds' store made room for first); nothing waits."""
        step, items = batch.step, batch.items
        if step is not None and step.kind == "stationary" and self.store is not None and items:
            from ardflow.ardcore.sampling.driver import STRIDE

            # the stage continues past its first M draws while their quality is short: make room first
            # (item[3] is the round's length, the same for every chain)
            self.store.resize_draws(self.model, self.iteration, step.index % STRIDE + int(items[0][3]),
                                    grow_only=True)
        return Submitted(self, batch)

    def __call__(self, func, items, step: Step | None = None):
        return self.submit(Batch(func, items, step)).result()


EVEN_STEPS = ("warm", "burnin", "stationary")
"""Steps whose chain tasks cost about the same (a round of the same number of draws per chain); a start
optimisation's searches and the evidence's adaptive proposal draws do not."""


class Submitted:
    """One batch's tasks on the cluster, as an event loop tracks them: ``futures`` (those submitted so far),
    :meth:`done` when every task has finished (or failed), :meth:`result` the results in chain order.

    A batch of tasks of unequal cost (start optimisations, the evidence's adaptive proposal draws: not
    :data:`EVEN_STEPS`) has at most as many tasks on the cluster at once as it has worker threads
    (:meth:`DaskMap.slots`); the next is submitted as one finishes (:meth:`done` tops up). Dask places a
    batch's few tasks on workers as they are submitted, half on each of two workers, and a worker whose
    tasks finished early would idle while the other works through its queue; handed out one per free
    thread they pack as a process pool packs them. A task the scheduler lost (a worker killed at the wrong
    moment, a dropped scheduler connection) is submitted again under a new key (suffix ``-a<attempt>``) by
    :meth:`recover`, which the loop calls when nothing has moved for ``DaskMap.stall_s``."""

    def __init__(self, dmap: DaskMap, batch: Batch):
        self.dmap, self.batch = dmap, batch
        n = len(batch.items)
        # a round of every chain is the same number of draws: submitted at once, each worker has its next
        # task at hand (a top-up costs a round trip through the driver)
        even = batch.step is not None and batch.step.kind in EVEN_STEPS
        self.slots = n if even else max(1, min(n, dmap.slots()))
        self._futures: list = [None] * n
        self.attempts = [0] * n
        self.since = time.monotonic()
        self._top_up()

    @property
    def futures(self) -> list:
        return [f for f in self._futures if f is not None]

    def _top_up(self) -> None:
        running = sum(f is not None and f.status not in ("finished", "error") for f in self._futures)
        for i, f in enumerate(self._futures):
            if running >= self.slots:
                break
            if f is None:
                self._futures[i] = self.dmap._submit(self.batch.func, self.batch.items[i], i, self.batch.step, 0)
                running += 1

    def done(self) -> bool:
        self._top_up()
        return all(f is not None and f.status in ("finished", "error") for f in self._futures)

    def stalled(self) -> bool:
        return time.monotonic() - self.since > self.dmap.stall_s

    def gather(self) -> list | None:
        """The results when every task is done (a task's error is raised), None when the connection
        dropped under them (:meth:`recover` resubmits)."""
        if not self.done():
            return None
        try:
            return self.dmap.client.gather(self._futures)
        except CancelledError:
            return None

    def recover(self) -> None:
        """Submit again what the scheduler no longer knows (after waiting for a dropped connection to
        come back)."""
        d = self.dmap
        self.since = time.monotonic()
        wait_connected(d.client)
        pending = [f for f in self.futures if f.status not in ("finished", "error")]
        known = d.client.run_on_scheduler(_known_keys, keys=[f.key for f in pending])
        for i, f in enumerate(self._futures):
            if f is None:
                continue
            if f.status in ("lost", "cancelled") or (f.status == "pending" and not known.get(f.key, False)):
                self.attempts[i] += 1
                log.warning("task %s was lost (%s); submitting it again", f.key, f.status)
                self._futures[i] = d._submit(self.batch.func, self.batch.items[i], i, self.batch.step,
                                             self.attempts[i])

    def result(self) -> list:
        """Block until every task is done: the results in chain order."""
        from distributed import wait

        while True:
            stalled = False
            live = [f for f in self.futures if not f.done()]
            if live:
                try:
                    wait(live, timeout=self.dmap.stall_s, return_when="FIRST_COMPLETED")
                except TimeoutError:
                    stalled = True
                except CancelledError:
                    pass  # a dropped scheduler connection: handled below
            out = self.gather()  # tops up the batch as its tasks finish
            if out is not None:
                return out
            if stalled or all(f.done() for f in self.futures):
                self.recover()  # nothing moved, or the results went with a dropped connection


def _known_keys(dask_scheduler=None, keys=()):
    return {k: k in dask_scheduler.tasks for k in keys}
