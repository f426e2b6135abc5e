"""Diagnoses as jobs of the service's :class:`~service.api.registry.Runner`: queued beside the studies'
drivers, run as ``ardflow diagnose`` processes, cancelled, and their durable status."""

from __future__ import annotations

import json
import time
from pathlib import Path

from ardflow.workers.cluster import die_with_parent

from ardflow.service.api.schemas import DiagnoseRequest


def job_key(sid: str, model: str) -> str:
    """A diagnosis's key among the runner's jobs (a study's own key is its id: a key with a '/' is a diagnosis)."""
    return f"{sid}/diagnose/{model}"


class DiagnosisJobs:
    """The diagnosis half of the runner: it shares the runner's ``registry``, ``lock``, ``threads``, ``procs``,
    ``diag_queue``, ``instance``, ``closing``, ``cancel_grace_s`` and its ``_pump``, which starts a queued
    diagnosis when fewer than ``max_running`` drivers and diagnoses run."""

    def diagnose(self, sid: str, model: str, req: "DiagnoseRequest") -> None:
        """Queue ``ardflow diagnose STORE --model M --out studies/<id>/diagnoses/<M>``: a job like a study's
        driver, started when fewer than ``max_running`` drivers and diagnoses run."""
        out = self.registry.study_dir(sid) / "diagnoses" / model
        out.mkdir(parents=True, exist_ok=True)
        with self.lock:
            write_diagnosis_status(out, {"status": "queued", "queued": time.time(), "service": self.instance})
            self.diag_queue.append((sid, model, req))
        self._pump()

    def _diagnose(self, sid: str, model: str, req: "DiagnoseRequest") -> None:
        import subprocess
        import sys

        reg = self.registry
        out = reg.study_dir(sid) / "diagnoses" / model
        key = job_key(sid, model)
        try:
            with self.lock:
                if (self.diagnosis_status(out) or {}).get("status") != "queued":  # cancelled meanwhile
                    return
                write_diagnosis_status(out, {"status": "running", "started": time.time(), "service": self.instance})
            cmd = [sys.executable, "-m", "ardflow.service.cli", "diagnose", str(reg.store(sid)), "--model", model,
                   "--out", str(out), "--top-k", str(req.top_k), "--max-rounds", str(req.max_rounds)]
            for ds in req.test_datasets:
                cmd += ["--test-data", str(reg.root / "datasets" / f"{ds}.csv")]
            with open(out / "diagnose.log", "w") as logf:
                p = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                     preexec_fn=die_with_parent)
                self.procs[key] = p
                rc = p.wait()
            if self.closing or (self.diagnosis_status(out) or {}).get("status") == "cancelled":
                return
            if rc == 0 and (out / "diagnosis.json").exists():
                st = {"status": "done"}
            else:
                tail = (out / "diagnose.log").read_text()[-2000:].strip().splitlines()
                st = {"status": "failed", "error": reg.public(tail[-1] if tail else f"exit {rc}")}
            write_diagnosis_status(out, st)
        finally:
            with self.lock:
                self.threads.pop(key, None)
            self._pump()

    def diagnosing(self, sid: str) -> list[str]:
        """The models of ``sid`` whose diagnosis is queued or runs now."""
        pre = job_key(sid, "")
        with self.lock:
            return [m for s, m, _ in self.diag_queue if s == sid] + [
                k[len(pre):] for k, t in self.threads.items() if k.startswith(pre) and t.is_alive()]

    def cancel_diagnosis(self, sid: str, model: str) -> None:
        """Stop the diagnosis of ``model`` in ``sid``: marked cancelled durably, then its process ended."""
        out = self.registry.study_dir(sid) / "diagnoses" / model
        with self.lock:
            write_diagnosis_status(out, {"status": "cancelled"})
            self.diag_queue = [q for q in self.diag_queue if q[:2] != (sid, model)]
        p = self.procs.get(job_key(sid, model))
        if p is not None and p.poll() is None:
            p.terminate()
            try:
                p.wait(self.cancel_grace_s)
            except Exception:  # noqa: BLE001 - subprocess.TimeoutExpired: it did not stop in time
                p.kill()

    def diagnosis_status(self, folder: Path) -> dict | None:
        """The status of the diagnosis in ``folder`` (None when none was started): ``running``, ``done`` or
        ``failed`` with its ``error``. A status file that cannot be read (a write cut short by a full disk) is a
        failed diagnosis saying so; one left ``running`` by a service that has since stopped (its process died
        with it) is failed with that reason, so it can be started again."""
        from ardflow.service.api.registry import _why

        f = folder / "status.json"
        if not f.exists() and not f.is_symlink():
            return None
        try:
            if self.registry.file(f) is None:
                raise OSError("not a file of the study")
            st = json.loads(f.read_text())
            if not isinstance(st, dict) or st.get("status") not in ("queued", "running", "done", "failed", "cancelled"):
                raise ValueError(f"status {str(st)[:40]!r}")
        except (OSError, ValueError) as exc:
            return {"status": "failed", "error": f"its status file cannot be read ({_why(exc)}): start it again"}
        if st["status"] in ("queued", "running") and st.get("service") != self.instance:
            return {"status": "failed", "error": f"the service stopped while it was {st['status']}: start it again"}
        if st["status"] == "done" and not (folder / "diagnosis.json").is_file():
            return {"status": "failed", "error": "its report is missing: start it again"}
        return {k: v for k, v in st.items() if k != "service"}


def write_diagnosis_status(folder: Path, st: dict) -> None:
    """Write a diagnosis's ``status.json`` whole or not at all."""
    from ardflow.ardcore.jsonio import atomic_write_text

    atomic_write_text(folder / "status.json", json.dumps(st))
