"""Diagnoses in the service: jobs of its :class:`~service.api.registry.Runner` (queued beside the studies'
drivers, run as ``ardflow diagnose`` processes, cancelled, with a durable status) and their routes."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

from fastapi import APIRouter, Depends, HTTPException
from fastapi.responses import JSONResponse, Response

from ardflow.workers.cluster import die_with_parent

from ardflow.service.api.schemas import API_VERSION, DiagnoseRequest, DiagnosisStatus, reason


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
            return {"status": "failed", "error": f"its status file cannot be read ({reason(exc)}): start it again"}
        if st["status"] in ("queued", "running") and st.get("service") != self.instance:
            return {"status": "failed", "error": f"the service stopped while it was {st['status']}: start it again"}
        if st["status"] == "done" and not (folder / "diagnosis.json").is_file():
            return {"status": "failed", "error": "its report is missing: start it again"}
        return {k: v for k, v in st.items() if k != "service"}


def write_diagnosis_status(folder: Path, st: dict) -> None:
    """Write a diagnosis's ``status.json`` whole or not at all."""
    from ardflow.ardcore.jsonio import atomic_write_text

    atomic_write_text(folder / "status.json", json.dumps(st))


def diagnoses_router(c) -> APIRouter:
    """The closed loop on a finished study's model over HTTP: start it, cancel it, read its report and figures.
    ``c``: the service's state (its registry ``reg``, ``runner``, ``auth``, ``access`` and ``dataset_visible``)."""
    r = APIRouter()
    v1 = f"/{API_VERSION}"

    def _diag_dir(sid: str, model: str) -> Path:
        if not re.match(r"^[A-Za-z][A-Za-z0-9_]{0,31}$", model):
            raise HTTPException(404, f"no model {model!r}")
        c.reg.readable(sid)
        return c.reg.study_dir(sid) / "diagnoses" / model

    @r.post(f"{v1}/studies/{{sid}}/diagnoses", response_model=DiagnosisStatus, status_code=202,
              dependencies=[Depends(c.access)])
    def diagnose(sid: str, req: DiagnoseRequest, owner: str = Depends(c.auth)) -> DiagnosisStatus:
        meta = c.reg.meta(sid)
        if meta.get("status") != "done":
            raise HTTPException(409, f"study {sid} is {meta.get('status')}: diagnose a finished study")
        summary = c.reg.store(sid).meta.get("summary") or {}
        models = [r["name"] for r in summary.get("models", [])]
        model = req.model or summary.get("best_model")
        if model not in models:
            raise HTTPException(404, f"study {sid} has no model {model!r} (models: {models})")
        for ds in req.test_datasets:
            if not c.dataset_visible(ds, owner):
                raise HTTPException(404, f"no uploaded data set {ds!r}")
        d = _diag_dir(sid, model)
        now = (c.runner.diagnosis_status(d) or {}).get("status")
        if now in ("queued", "running"):
            raise HTTPException(409, f"a diagnosis of {model} is already {now}")
        c.runner.diagnose(sid, model, req)
        return DiagnosisStatus(model=model, status=c.runner.diagnosis_status(d)["status"])

    @r.post(f"{v1}/studies/{{sid}}/diagnoses/{{model}}/cancel", response_model=DiagnosisStatus,
            dependencies=[Depends(c.access)])
    def cancel_diagnosis(sid: str, model: str) -> DiagnosisStatus:
        d = _diag_dir(sid, model)
        st = c.runner.diagnosis_status(d)
        if st is None:
            raise HTTPException(404, f"no diagnosis of {model!r} in study {sid}")
        if st["status"] not in ("queued", "running"):
            raise HTTPException(409, f"the diagnosis of {model} is already {st['status']}")
        c.runner.cancel_diagnosis(sid, model)
        return DiagnosisStatus(model=model, status="cancelled")

    @r.get(f"{v1}/studies/{{sid}}/diagnoses/{{model}}", dependencies=[Depends(c.access)])
    def diagnosis(sid: str, model: str) -> JSONResponse:
        d = _diag_dir(sid, model)
        st = c.runner.diagnosis_status(d)
        if st is None:
            raise HTTPException(404, f"no diagnosis of {model!r} in study {sid} (POST .../diagnoses first)")
        body = {"model": model, **st}
        if st["status"] == "done":
            try:
                f = c.reg.file(d / "diagnosis.json")
                if f is None:
                    raise OSError("not a file of the study")
                body["report"] = json.loads(f.read_text())
            except (OSError, ValueError) as exc:
                body.update(status="failed", error=f"its report (diagnosis.json) cannot be read ({type(exc).__name__}): "
                                                   "start it again")
            body["figures"] = sorted(p.name for p in d.glob("*.png") if c.reg.file(p))
        return JSONResponse(body)

    @r.get(f"{v1}/studies/{{sid}}/diagnoses/{{model}}/report/{{name}}", dependencies=[Depends(c.access)],
             responses={200: {"content": {"text/html": {}, "image/png": {}}}})
    def diagnosis_report(sid: str, model: str, name: str):
        """The diagnosis report (``diagnosis.html``) and its figures, beside each other as the report links them."""
        d = _diag_dir(sid, model)
        f = c.reg.file(d / name) if re.match(r"^[a-z_]{1,40}\.(png|html)$", name) else None
        if f is None:
            raise HTTPException(404, f"no diagnosis report file {name!r} (a diagnosis writes it when it finishes)")
        kind = "text/html; charset=utf-8" if name.endswith(".html") else "image/png"
        return Response(f.read_bytes(), media_type=kind)

    @r.get(f"{v1}/studies/{{sid}}/diagnoses/{{model}}/figures/{{name}}", dependencies=[Depends(c.access)],
             responses={200: {"content": {"image/png": {}}}})
    def diagnosis_figure(sid: str, model: str, name: str):
        d = _diag_dir(sid, model)
        f = c.reg.file(d / name) if re.match(r"^[a-z_]{1,40}\.png$", name) else None
        if f is None:
            raise HTTPException(404, f"no figure {name!r}")
        return Response(f.read_bytes(), media_type="image/png")

    return r
