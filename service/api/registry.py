"""The service's durable registry of studies, the queue that runs their drivers, and their progress."""

from __future__ import annotations

import json
import logging
import math
import os
import re
import secrets
import threading
import time
from pathlib import Path
from typing import Any

from fastapi import HTTPException

from ardflow.ardcore.events import BurninRound, ModelDone, Note, TrialDone
from ardflow.ardcore.jsonio import to_jsonable
from ardflow.workers.cluster import die_with_parent

from ardflow.service.api.diagnoses import DiagnosisJobs, job_key
from ardflow.service.api.schemas import ID_RE, Progress, finite_or_none, reason

log = logging.getLogger("ardflow.service")

LIFECYCLE = ("status", "error")
"""What the study's store owns, never the registry's meta.json (:meth:`Registry.status`)."""

DAMAGED = "damaged"
"""The status of a study whose registry entry or store cannot be read."""


def _mtime(p: Path) -> float:
    try:
        return p.stat().st_mtime
    except OSError:
        return 0.0

# ------------------------------------------------------------------ the study registry
class Registry:
    """Durable registry: ``root/studies/<id>/{meta.json, store/}``, ``root/datasets/<id>.csv``."""

    def __init__(self, root: Path):
        self.root = Path(root)
        (self.root / "studies").mkdir(parents=True, exist_ok=True)
        (self.root / "datasets").mkdir(parents=True, exist_ok=True)
        self._owners: dict[str, tuple] = {}  # sid -> (owner, created): :meth:`entry`

    def study_dir(self, sid: str) -> Path:
        if not ID_RE.match(sid):
            raise HTTPException(404, f"no study {sid!r}")
        return self.root / "studies" / sid

    def ids(self) -> list[str]:
        return sorted(p.name for p in (self.root / "studies").iterdir() if (p / "meta.json").exists())

    def meta(self, sid: str) -> dict:
        """The study's registry entry (id, name, owner, created, estimate) with its ``status`` and ``error``,
        which its store owns (:meth:`status`). A study whose files cannot be read is ``damaged`` (listed,
        its error readable, deletable), never an exception."""
        p = self.study_dir(sid) / "meta.json"
        if not p.exists():
            raise HTTPException(404, f"no study {sid!r}")
        try:
            m = json.loads(p.read_text())
            if not isinstance(m, dict):
                raise ValueError("not a JSON object")
        except (OSError, ValueError) as exc:
            return {"id": sid, "name": sid, "created": _mtime(p), "status": DAMAGED,
                    "error": f"its registry entry (meta.json) cannot be read: {reason(exc)}"}
        m = {k: v for k, v in m.items() if k not in LIFECYCLE}
        st = self.status(sid)
        return {**m, **st, "error": self.public(st["error"])}

    def public(self, text: str | None) -> str | None:
        """``text`` (an error) as a user may read it: an uploaded data set is named by its id, a study's
        files by their place in the study, and no path of this server remains."""
        if not text:
            return text
        for root in {str(self.root.resolve()), str(self.root)}:
            text = re.sub(re.escape(root) + r"/datasets/\.?([0-9a-f]+)\.csv", r"data set \1", text)
            text = re.sub(re.escape(root) + r"/studies/([^/\s'\"]+)/?", r"study \1: ", text)
            text = text.replace(root, "<registry>")
        return text

    def file(self, path: Path) -> Path | None:
        """``path`` when it is a regular file under this registry reached without a symbolic link (a link placed
        in a study, to the token registry or any file outside, is never followed), else None."""
        try:
            rel = path.absolute().relative_to(self.root.absolute())
        except ValueError:
            return None
        p = self.root.absolute()
        for part in rel.parts:
            p = p / part
            if p.is_symlink():
                return None
        return p if p.is_file() else None

    def owner(self, sid: str) -> str | None:
        """Who submitted ``sid`` (None when its entry cannot be read). An entry's owner never changes: cached."""
        return self.entry(sid)[0]

    def entry(self, sid: str) -> tuple[str | None, float]:
        """``(owner, created)`` of ``sid``: what never changes in an entry, read once and kept (the listing's
        index: a user's studies are found without reading anyone else's files). ``(None, 0)`` when the entry
        cannot be read (then read again next time: it may be being written)."""
        if sid not in self._owners:
            try:
                m = json.loads((self.study_dir(sid) / "meta.json").read_text())
                self._owners[sid] = (m.get("owner"), float(m.get("created", 0.0)))
            except (OSError, ValueError, AttributeError, TypeError, HTTPException):
                return None, 0.0
        return self._owners[sid]

    def drop(self, sid: str) -> None:
        """Forget a deleted study's entry."""
        self._owners.pop(sid, None)

    def readable(self, sid: str) -> dict:
        """:meth:`meta` of a study whose files can be read; a damaged one is a 409 that says so."""
        m = self.meta(sid)
        if m["status"] == DAMAGED:
            raise HTTPException(409, f"study {sid} is damaged ({m['error']}); delete it")
        return m

    def damaged(self) -> list[tuple[str, str]]:
        """(id, why) of every damaged study (the service reports them when it starts)."""
        return [(m["id"], m["error"]) for m in self.metas() if m["status"] == DAMAGED]

    def status(self, sid: str) -> dict:
        """``{status, error}`` of a study, read from its store alone (the one owner of the study's status).

        The store's ``CANCELLED`` marker (the service writes it, while a driver may be writing the store's
        attributes) means cancelled; otherwise the store's own status: ``running``, ``done``, ``failed``
        (with its error), ``cancelled``; ``created`` (no driver has started on it yet) is ``queued``.
        """
        store = self.store(sid)
        for attempt in range(2):
            try:
                m = store.meta if store.exists() else {}
                if not isinstance(m, dict):
                    raise ValueError("its attributes are not a JSON object")
                break
            except Exception as exc:  # noqa: BLE001 - whatever a damaged zarr.json raises, the study is damaged
                if attempt:  # (read twice: a driver may be rewriting the file this instant)
                    return {"status": DAMAGED, "error": f"its store cannot be read: {reason(exc)}"}
                time.sleep(0.05)
        if store.read_text("CANCELLED") is not None:
            return {"status": "cancelled", "error": None}
        st = m.get("status", "created")
        return {"status": "queued" if st == "created" else st, "error": m.get("error") if st == "failed" else None}

    def metas(self) -> list[dict]:
        """Every study's meta (a damaged one with status ``damaged``; one deleted meanwhile is left out)."""
        out = []
        for sid in self.ids():
            try:
                out.append({**self.meta(sid), "id": sid})
            except HTTPException:
                continue
        return out

    def write_meta(self, sid: str, meta: dict) -> None:
        """Write the registry entry; the status and error are the store's and are not written here."""
        from ardflow.ardcore.jsonio import atomic_write_text

        atomic_write_text(self.study_dir(sid) / "meta.json",
                          json.dumps({k: v for k, v in meta.items() if k not in LIFECYCLE}))

    def store(self, sid: str):
        from ardflow.workers.store import StudyStore

        return StudyStore(self.study_dir(sid) / "store")


class Runner(DiagnosisJobs):
    """Runs each study's driver (``ardflow resume STORE --scheduler ADDR``) as a child process, at most
    ``max_running`` at once; the others wait ``queued`` in submission order.

    The API process only serves requests; the maximisers' work never competes with the event loop. A
    driver that dies is relaunched on the next service start from the durable registry and continues
    from the store. A cancelled study is marked durably first (registry and a ``CANCELLED`` file in its
    store, which ``ardflow resume`` refuses), then its driver is asked to stop and, after
    ``cancel_grace_s``, killed; it is never relaunched.
    """

    def __init__(self, registry: Registry, client, *, max_running: int = 2, cancel_grace_s: float = 10.0,
                 max_task_s: float = 21600.0):
        self.registry, self.client = registry, client
        self.max_running, self.cancel_grace_s, self.max_task_s = max_running, cancel_grace_s, max_task_s
        self.threads: dict[str, threading.Thread] = {}
        self.procs: dict[str, Any] = {}
        self.queue: list[str] = []
        self.diag_queue: list[tuple] = []  # (sid, model, request): diagnoses waiting for a free slot
        self.lost: dict[str, str] = {}  # studies failed whose store could not record it (a full disk): why
        self.lock = threading.RLock()
        self.closing = False
        self.peak_running = 0
        self.instance = secrets.token_hex(8)  # which service started a diagnosis: another's died with it

    def running(self) -> list[str]:
        """The studies whose driver runs now."""
        with self.lock:
            return [s for s, t in self.threads.items() if t.is_alive() and "/" not in s]

    def busy(self) -> int:
        """Drivers and diagnoses running now: together at most ``max_running``."""
        with self.lock:
            return sum(t.is_alive() for t in self.threads.values())

    def start(self, sid: str) -> None:
        """Queue ``sid``; it starts when fewer than ``max_running`` drivers run."""
        with self.lock:
            if sid not in self.queue and sid not in self.running():
                self.queue.append(sid)
        self._pump()

    def _pump(self) -> None:
        with self.lock:
            while (self.queue or self.diag_queue) and not self.closing and self.busy() < self.max_running:
                if self.queue:
                    sid = self.queue.pop(0)
                    if self.registry.status(sid)["status"] in ("cancelled", DAMAGED):
                        continue
                    key, th = sid, threading.Thread(target=self._run, args=(sid,), name=f"study-{sid}", daemon=True)
                else:
                    sid, model, req = self.diag_queue.pop(0)
                    key = job_key(sid, model)
                    th = threading.Thread(target=self._diagnose, args=(sid, model, req), name=f"diagnose-{key}",
                                          daemon=True)
                self.threads[key] = th
                th.start()
                self.peak_running = max(self.peak_running, self.busy())

    def _run(self, sid: str) -> None:
        try:
            self._drive(sid)
        finally:
            with self.lock:  # this thread is still alive: it must not count as running when it starts the next
                self.threads.pop(sid, None)
            self._pump()

    def _drive(self, sid: str) -> None:
        import subprocess
        import sys

        reg = self.registry
        store = reg.store(sid)
        with self.lock:
            if reg.status(sid)["status"] == "cancelled":
                return
            store.update_meta(status="running")  # no driver writes the store yet
        log_path = reg.study_dir(sid) / "driver.log"
        with open(log_path, "a") as logf:
            # the driver yields to the API process (status requests stay quick under load)
            p = subprocess.Popen(["nice", "-n", "5", sys.executable, "-m", "ardflow.service.cli", "resume", str(store),
                                  "--scheduler", self.client.scheduler.address],
                                 stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                 env={**os.environ, **getattr(self.client, "ardflow_env", {}),
                                      "ARDFLOW_MAX_TASK_S": str(self.max_task_s)},
                                 preexec_fn=die_with_parent)
            self.procs[sid] = p
            rc = p.wait()
        if self.closing:
            return  # the service is stopping: the study resumes on the next start
        with self.lock:
            st = reg.status(sid)["status"]
            if st == "cancelled" or (rc == 0 and st == "done"):
                return
            # the driver stopped without finishing (killed, out of memory, an error): its store says why
            try:
                tail = log_path.read_text()[-2000:].strip().splitlines()
                why = store.meta.get("error") or (tail[-1] if tail else f"driver exit {rc}")
            except (OSError, ValueError) as exc:
                why = f"driver exit {rc} ({reason(exc)})"
            try:
                store.update_meta(status="failed", error=why)
            except OSError as exc:  # a full disk: the store cannot say it, the service does (Runner.lost)
                self.lost[sid] = f"{why} (and its failure could not be recorded: {reason(exc)})"

    def cancel(self, sid: str) -> None:
        """Mark ``sid`` cancelled durably, then stop its driver (cooperatively, then by force)."""
        from ardflow.workers.graph import cancel_study
        from ardflow.ardcore.jsonio import atomic_write_text

        reg = self.registry
        with self.lock:
            meta = reg.meta(sid)
            meta["cancelled"] = time.time()
            # the marker is the status (Registry.status): a driver may be writing the store's attributes now
            atomic_write_text(reg.study_dir(sid) / "store" / "CANCELLED", str(meta["cancelled"]))
            reg.write_meta(sid, meta)
            if sid in self.queue:
                self.queue.remove(sid)
                return
        study_id = reg.store(sid).meta.get("study_id")
        if study_id:
            try:
                cancel_study(self.client, study_id)
            except Exception:  # noqa: BLE001 - the driver is killed below in any case
                log.warning("could not signal cancellation of %s to the cluster", sid)
        p = self.procs.get(sid)
        if p is not None and p.poll() is None:
            threading.Thread(target=self._stop, args=(p,), name=f"cancel-{sid}", daemon=True).start()

    def _stop(self, p) -> None:
        import subprocess

        try:
            p.wait(self.cancel_grace_s)
        except subprocess.TimeoutExpired:
            p.terminate()
            try:
                p.wait(5)
            except subprocess.TimeoutExpired:
                p.kill()

    def stop(self) -> None:
        self.closing = True
        self.queue.clear()
        for p in self.procs.values():
            if p.poll() is None:
                p.terminate()


# ------------------------------------------------------------------ progress
class ProgressCache:
    """Per-study progress folded incrementally from the store's progress logs (status stays cheap)."""

    def __init__(self, reg: Registry):
        self.reg = reg
        self.lock = threading.Lock()
        self.entries: dict[str, dict] = {}

    def forget(self, sid: str) -> None:
        with self.lock:
            self.entries.pop(sid, None)

    def get(self, sid: str) -> dict[str, Progress]:
        from ardflow.workers.graph import read_progress

        with self.lock:
            e = self.entries.get(sid)
            if e is None:
                store = self.reg.store(sid)
                if not store.exists():
                    return {}
                meta = store.meta
                e = self.entries[sid] = {
                    "store": store, "offsets": {}, "models": {},
                    "max_trials": meta.get("spec", {}).get("maximiser", {}).get("max_trials", 60),
                    "started": meta.get("started")}
            store = e["store"]
            events = read_progress(store, e["offsets"])
            if e["started"] is None and events:
                # the store's attributes are a zarr read: only once the driver has written something
                e["started"] = store.meta.get("started")
            started = e["started"] or time.time()
            out = e["models"]
            for ev in events:
                m, x = ev.model, ev.event
                p = out.setdefault(m, Progress(model=m, max_trials=e["max_trials"]))
                if not isinstance(x, Note):
                    p.stage = x.stage
                p.elapsed_s = max(0.0, float(ev.time if ev.time is not None else started) - started)
                if isinstance(x, BurninRound):
                    p.rhat = finite_or_none(x.rhat)
                if isinstance(x, TrialDone):
                    p.trials_done += 1
                    p.iteration = x.iteration
                    p.psi = to_jsonable(x.psi)  # a pruned alpha as JSON spells it
                    if x.accepted and math.isfinite(x.log_evidence):
                        le = x.log_evidence
                        p.best_log_evidence = le if p.best_log_evidence is None else max(p.best_log_evidence, le)
                if isinstance(x, ModelDone):
                    p.eta_s = 0.0
                elif p.trials_done:
                    # an upper bound: the maximiser stops at max_trials at the latest
                    p.eta_s = p.elapsed_s / p.trials_done * max(0, e["max_trials"] - p.trials_done)
            return {k: v.model_copy() for k, v in out.items()}


