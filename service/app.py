"""The REST service (FastAPI), versioned under ``/v1``.

Studies run on a Dask cluster (embedded LocalCluster or an existing scheduler)
in background threads, so the event loop never blocks. The registry is
durable: every study is a directory under the service root holding its zarr
store, so a restarted service reattaches to its studies and resumes those that
were running.
"""

from __future__ import annotations

import asyncio
import hmac
import io
import json
import logging
import math
import re
import secrets
import threading
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np
from fastapi import Depends, FastAPI, HTTPException, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field

from ardcore.errors import ArdflowError
from ardcore.study import StudySpec

log = logging.getLogger("ardflow.service")

API_VERSION = "v1"
ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")
FINAL = {"done", "failed", "cancelled"}


class Settings(BaseModel):
    """Service settings (``ardflow serve`` options)."""

    model_config = ConfigDict(extra="forbid")
    root: Path = Field(description="directory holding the registry, data sets and study stores")
    token: Optional[str] = Field(None, description="API token; None disables authentication")
    max_body_mb: float = Field(20.0, gt=0)
    max_upload_rows: int = Field(2_000_000, gt=0)


# ------------------------------------------------------------------ response schemas
class Health(BaseModel):
    status: str
    version: str
    workers: int


class DatasetInfo(BaseModel):
    id: str
    rows: int
    columns: list[str]


class StudyCreated(BaseModel):
    id: str
    status: str


class Progress(BaseModel):
    model: Optional[str] = None
    stage: Optional[str] = None
    iteration: Optional[int] = None
    psi: Optional[dict[str, Any]] = None
    best_log_evidence: Optional[float] = None
    rhat: Optional[list[Optional[float]]] = None
    trials_done: int = 0
    elapsed_s: float = 0.0
    eta_s: Optional[float] = None


class StudyStatus(BaseModel):
    id: str
    name: str
    status: str
    created: float
    error: Optional[str] = None
    models: dict[str, Progress] = Field(default_factory=dict)


class DiagnoseRequest(BaseModel):
    """Close the loop on one model of a finished study (``ardflow diagnose`` on the study's store)."""

    model_config = ConfigDict(extra="forbid")
    model: Optional[str] = Field(None, pattern=r"^[A-Za-z][A-Za-z0-9_]{0,31}$",
                                 description="default: the study's best model")
    top_k: int = Field(3, ge=1, le=10, description="candidates confirmed by evidence per round")
    max_rounds: int = Field(3, ge=1, le=10, description="effects added one after another at most")
    test_dataset: Optional[str] = Field(None, pattern=r"^[a-f0-9]{16}$",
                                        description="uploaded held-out record for the free run")


class DiagnosisStatus(BaseModel):
    model: str
    status: str
    error: Optional[str] = None
    verdict: Optional[str] = None
    figures: list[str] = Field(default_factory=list)


class DashboardLink(BaseModel):
    url: Optional[str]


def _finite(x):
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    if isinstance(x, float) and not math.isfinite(x):
        return None
    return x


# ------------------------------------------------------------------ the study registry
class Registry:
    """Durable registry: ``root/studies/<id>/{meta.json, store/}``, ``root/datasets/<id>.csv``."""

    def __init__(self, root: Path):
        self.root = Path(root)
        (self.root / "studies").mkdir(parents=True, exist_ok=True)
        (self.root / "datasets").mkdir(parents=True, exist_ok=True)

    def study_dir(self, sid: str) -> Path:
        if not ID_RE.match(sid):
            raise HTTPException(404, f"no study {sid!r}")
        return self.root / "studies" / sid

    def ids(self) -> list[str]:
        return sorted(p.name for p in (self.root / "studies").iterdir() if (p / "meta.json").exists())

    def meta(self, sid: str) -> dict:
        p = self.study_dir(sid) / "meta.json"
        if not p.exists():
            raise HTTPException(404, f"no study {sid!r}")
        return json.loads(p.read_text())

    def write_meta(self, sid: str, meta: dict) -> None:
        from workers.store import atomic_write_text

        atomic_write_text(self.study_dir(sid) / "meta.json", json.dumps(meta))

    def store(self, sid: str):
        from workers.store import StudyStore

        return StudyStore(self.study_dir(sid) / "store")


class Runner:
    """Runs each study's driver (``ardflow resume STORE --scheduler ADDR``) as a child process.

    The API process only serves requests; the maximisers' work never competes with
    the event loop. A driver that dies is relaunched on the next service start from
    the durable registry, and continues from the store.
    """

    def __init__(self, registry: Registry, client):
        self.registry, self.client = registry, client
        self.threads: dict[str, threading.Thread] = {}
        self.procs: dict[str, Any] = {}
        self.closing = False

    def start(self, sid: str) -> None:
        if sid in self.threads and self.threads[sid].is_alive():
            return
        th = threading.Thread(target=self._run, args=(sid,), name=f"study-{sid}", daemon=True)
        self.threads[sid] = th
        th.start()

    def _run(self, sid: str) -> None:
        import subprocess
        import sys

        reg = self.registry
        meta = reg.meta(sid)
        meta["status"] = "running"
        reg.write_meta(sid, meta)
        store = reg.store(sid)
        log_path = reg.study_dir(sid) / "driver.log"
        with open(log_path, "a") as logf:
            p = subprocess.Popen([sys.executable, "-m", "service.cli", "resume", str(store),
                                  "--scheduler", self.client.scheduler.address],
                                 stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
            self.procs[sid] = p
            rc = p.wait()
        if self.closing:
            return  # the service is stopping: the study resumes on the next start
        st = store.meta.get("status")
        if rc == 0 and st == "done":
            meta["status"] = "done"
        elif st == "cancelled":
            meta["status"] = "cancelled"
        else:
            tail = log_path.read_text()[-2000:].strip().splitlines()
            meta["status"] = "failed"
            meta["error"] = store.meta.get("error") or (tail[-1] if tail else f"driver exit {rc}")
        reg.write_meta(sid, meta)

    def cancel(self, sid: str) -> None:
        from workers.graph import cancel_study

        study_id = self.registry.store(sid).meta.get("study_id")
        if study_id:
            cancel_study(self.client, study_id)

    def diagnose(self, sid: str, model: str, req: "DiagnoseRequest") -> None:
        """``ardflow diagnose STORE --model M --out studies/<id>/diagnoses/<M>`` in a child process."""
        import subprocess
        import sys

        reg = self.registry
        out = reg.study_dir(sid) / "diagnoses" / model
        out.mkdir(parents=True, exist_ok=True)
        (out / "status.json").write_text(json.dumps({"status": "running", "started": time.time()}))
        cmd = [sys.executable, "-m", "service.cli", "diagnose", str(reg.store(sid)), "--model", model,
               "--out", str(out), "--top-k", str(req.top_k), "--max-rounds", str(req.max_rounds)]
        if req.test_dataset:
            cmd += ["--test-data", str(reg.root / "datasets" / f"{req.test_dataset}.csv")]

        def run():
            with open(out / "diagnose.log", "w") as logf:
                p = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL)
                self.procs[f"{sid}/diagnose/{model}"] = p
                rc = p.wait()
            if self.closing:
                return
            if rc == 0 and (out / "diagnosis.json").exists():
                st = {"status": "done"}
            else:
                tail = (out / "diagnose.log").read_text()[-2000:].strip().splitlines()
                st = {"status": "failed", "error": tail[-1] if tail else f"exit {rc}"}
            (out / "status.json").write_text(json.dumps(st))

        threading.Thread(target=run, name=f"diagnose-{sid}-{model}", daemon=True).start()

    def stop(self) -> None:
        self.closing = True
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

    def get(self, sid: str) -> dict[str, Progress]:
        from workers.graph import read_progress

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
            if e["started"] is None:
                e["started"] = store.meta.get("started")
            started = e["started"] or time.time()
            out = e["models"]
            for ev in read_progress(store, e["offsets"]):
                m = ev.get("model")
                p = out.setdefault(m, Progress(model=m))
                if ev.get("stage") != "note":
                    p.stage = ev.get("stage")
                p.elapsed_s = max(0.0, float(ev.get("time", started)) - started)
                if ev.get("stage") == "burnin":
                    p.rhat = _finite(ev.get("rhat"))
                if ev.get("stage") == "trial":
                    p.trials_done += 1
                    p.iteration = ev.get("iteration")
                    p.psi = _finite(ev.get("psi"))
                    le = ev.get("log_evidence")
                    if ev.get("accepted") and isinstance(le, (int, float)) and math.isfinite(le):
                        p.best_log_evidence = le if p.best_log_evidence is None else max(p.best_log_evidence, le)
                if ev.get("stage") == "model_done":
                    p.eta_s = 0.0
                elif p.trials_done:
                    # an upper bound: the maximiser stops at max_trials at the latest
                    p.eta_s = p.elapsed_s / p.trials_done * max(0, e["max_trials"] - p.trials_done)
            return {k: v.model_copy() for k, v in out.items()}


# ------------------------------------------------------------------ the app
def create_app(settings: Settings, client) -> FastAPI:
    """The FastAPI app over a Dask ``client`` (which it never exposes)."""
    reg = Registry(settings.root)
    runner = Runner(reg, client)
    progress_cache = ProgressCache(reg)
    app = FastAPI(title="ardflow", version="0.1.0",
                  description="Bayesian model selection (ARD, EKF likelihood, parallel adaptive MCMC) on Dask.")
    app.state.registry, app.state.runner, app.state.settings = reg, runner, settings
    max_body = int(settings.max_body_mb * 1024 * 1024)

    @app.middleware("http")
    async def limit_body(request: Request, call_next):
        cl = request.headers.get("content-length")
        if cl is not None:
            try:
                if int(cl) > max_body:
                    return JSONResponse({"detail": f"request body larger than {settings.max_body_mb:g} MB"}, 413)
            except ValueError:
                return JSONResponse({"detail": "invalid Content-Length"}, 400)
        return await call_next(request)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError):
        errs = [{"type": str(e.get("type", "value_error")), "loc": [x if isinstance(x, int) else str(x)
                                                                      for x in e.get("loc", [])],
                 "msg": str(e.get("msg", ""))} for e in exc.errors()]
        return JSONResponse({"detail": errs}, 422)

    @app.exception_handler(ArdflowError)
    async def user_error(request: Request, exc: ArdflowError):
        return JSONResponse({"detail": str(exc)}, 422)

    async def auth(request: Request) -> None:
        if settings.token is None:
            return
        given = request.headers.get("x-api-token")
        if given is None:
            h = request.headers.get("authorization", "")
            given = h[7:] if h.lower().startswith("bearer ") else None
        if given is None or not hmac.compare_digest(given.encode(), settings.token.encode()):
            raise HTTPException(401, "missing or wrong API token", headers={"WWW-Authenticate": "Bearer"})

    v1 = f"/{API_VERSION}"

    @app.get(f"{v1}/health", response_model=Health)
    def health() -> Health:
        try:
            n = len(client.scheduler_info(n_workers=-1)["workers"])
        except Exception:  # noqa: BLE001 - health reports what it can
            n = 0
        return Health(status="ok" if n else "degraded", version="0.1.0", workers=n)

    @app.get(f"{v1}/dashboard", response_model=DashboardLink, dependencies=[Depends(auth)])
    def dashboard() -> DashboardLink:
        return DashboardLink(url=getattr(client, "dashboard_link", None))

    @app.post(f"{v1}/datasets", response_model=DatasetInfo, status_code=201, dependencies=[Depends(auth)],
              openapi_extra={"requestBody": {"content": {"text/csv": {"schema": {"type": "string"}}},
                                             "required": True}})
    async def upload_dataset(request: Request) -> DatasetInfo:
        body = await request.body()
        if len(body) > max_body:
            raise HTTPException(413, f"data set larger than {settings.max_body_mb:g} MB")
        if not body.strip():
            raise HTTPException(422, "empty data set")
        try:
            text = body.decode("utf-8")
        except UnicodeDecodeError:
            raise HTTPException(422, "data set must be UTF-8 CSV text") from None
        if text.count("\n") > settings.max_upload_rows:
            raise HTTPException(413, f"data set has more than {settings.max_upload_rows} rows")
        did = secrets.token_hex(8)
        tmp = reg.root / "datasets" / f".{did}.csv"
        tmp.write_text(text)
        try:
            from ardcore.data import read_dataset

            ds = await asyncio.to_thread(read_dataset, tmp)
        except ArdflowError as exc:
            tmp.unlink(missing_ok=True)
            raise HTTPException(422, str(exc).replace(str(tmp), "data set")) from None
        tmp.replace(reg.root / "datasets" / f"{did}.csv")
        return DatasetInfo(id=did, rows=len(ds), columns=["t", *ds.columns])

    @app.post(f"{v1}/studies", response_model=StudyCreated, status_code=202, dependencies=[Depends(auth)])
    async def submit(spec: StudySpec) -> StudyCreated:
        if spec.data.path is not None:
            raise HTTPException(422, "data.path is not accepted over the API: upload the data set "
                                     "(POST /v1/datasets) and give data.dataset")
        sid = f"{spec.name}-{secrets.token_hex(4)}"
        d = reg.study_dir(sid)
        d.mkdir(parents=True)
        from workers.graph import prepare_store

        try:
            await asyncio.to_thread(prepare_store, spec, d / "store", datasets=reg.root / "datasets", study_id=sid)
        except ArdflowError as exc:
            import shutil

            shutil.rmtree(d, ignore_errors=True)
            raise HTTPException(422, str(exc)) from None
        reg.write_meta(sid, {"id": sid, "name": spec.name, "status": "queued", "created": time.time()})
        runner.start(sid)
        return StudyCreated(id=sid, status="queued")

    @app.get(f"{v1}/studies", response_model=list[StudyStatus], dependencies=[Depends(auth)])
    def list_studies() -> list[StudyStatus]:
        return [_status(sid, progress=False) for sid in reg.ids()]

    def _status(sid: str, progress: bool = True) -> StudyStatus:
        m = reg.meta(sid)
        return StudyStatus(id=sid, name=m.get("name", sid), status=m.get("status", "unknown"),
                           created=m.get("created", 0.0), error=m.get("error"),
                           models=progress_cache.get(sid) if progress else {})

    @app.get(f"{v1}/studies/{{sid}}", response_model=StudyStatus, dependencies=[Depends(auth)])
    async def status(sid: str) -> StudyStatus:
        # small local reads, folded incrementally: cheaper on the event loop than a thread hop
        return _status(sid)

    @app.get(f"{v1}/studies/{{sid}}/events", dependencies=[Depends(auth)],
             responses={200: {"content": {"text/event-stream": {}}}})
    async def events(sid: str, request: Request):
        reg.meta(sid)

        async def gen():
            from workers.graph import read_progress

            offsets: dict[str, int] = {}
            store = reg.store(sid)
            while True:
                if await request.is_disconnected():
                    return
                evs = await asyncio.to_thread(read_progress, store, offsets) if store.exists() else []
                for ev in evs:
                    yield f"event: progress\ndata: {json.dumps(_finite(ev))}\n\n"
                st = reg.meta(sid).get("status")
                if st in FINAL:
                    yield f"event: end\ndata: {json.dumps({'status': st})}\n\n"
                    return
                await asyncio.sleep(0.5)

        return StreamingResponse(gen(), media_type="text/event-stream")

    @app.post(f"{v1}/studies/{{sid}}/cancel", response_model=StudyStatus, dependencies=[Depends(auth)])
    def cancel(sid: str) -> StudyStatus:
        m = reg.meta(sid)
        if m.get("status") in FINAL:
            raise HTTPException(409, f"study {sid} is already {m['status']}")
        runner.cancel(sid)
        return _status(sid)

    @app.get(f"{v1}/studies/{{sid}}/summary", dependencies=[Depends(auth)])
    def summary(sid: str) -> JSONResponse:
        reg.meta(sid)
        text = reg.store(sid).read_text("summary.json")
        if text is None:
            raise HTTPException(409, f"study {sid} has no summary yet (status {reg.meta(sid).get('status')})")
        return JSONResponse(json.loads(text))

    def _best_trial(sid: str, model: str) -> int:
        if not ID_RE.match(model):
            raise HTTPException(404, f"no model {model!r}")
        store = reg.store(sid)
        try:
            g = store.group("r")
            mg = g[f"models/{model}"]
        except Exception:  # noqa: BLE001 - missing group
            raise HTTPException(404, f"study {sid} has no model {model!r}") from None
        it = mg.attrs.get("best_iteration")
        if it is None:
            raise HTTPException(409, f"model {model!r} of study {sid} is not finished")
        return int(it)

    @app.get(f"{v1}/studies/{{sid}}/posterior/{{model}}", dependencies=[Depends(auth)],
             responses={200: {"content": {"application/json": {}, "application/octet-stream": {}}}})
    def posterior(sid: str, model: str, format: str = "json", max_draws: int = 2000):
        reg.meta(sid)
        if format not in ("json", "npz"):
            raise HTTPException(422, "format must be 'json' or 'npz'")
        if not 1 <= max_draws <= 1_000_000:
            raise HTTPException(422, "max_draws must be between 1 and 1000000")
        it = _best_trial(sid, model)
        try:
            samples, lp, ll, names = reg.store(sid).read_samples(model, it)
        except (KeyError, FileNotFoundError):
            raise HTTPException(409, f"model {model!r} of study {sid} has no stored samples") from None
        if format == "npz":
            buf = io.BytesIO()
            np.savez_compressed(buf, names=np.array(names), samples=samples, log_posterior=lp, log_likelihood=ll)
            return Response(buf.getvalue(), media_type="application/octet-stream",
                            headers={"Content-Disposition": f'attachment; filename="{sid}_{model}.npz"'})
        flat = samples.reshape(-1, samples.shape[-1])
        step = max(1, flat.shape[0] // max_draws)
        return JSONResponse({"model": model, "iteration": it, "names": names, "n_chains": samples.shape[0],
                             "thin": step, "samples": _finite(flat[::step].tolist())})

    @app.get(f"{v1}/studies/{{sid}}/figures/{{name}}", dependencies=[Depends(auth)],
             responses={200: {"content": {"image/png": {}}}})
    def figure(sid: str, name: str):
        reg.meta(sid)
        from service.figures import FIGURES, render

        if name not in FIGURES:
            raise HTTPException(404, f"no figure {name!r} (available: {sorted(FIGURES)})")
        try:
            png = render(name, reg.store(sid))
        except LookupError as exc:
            raise HTTPException(409, str(exc)) from None
        return Response(png, media_type="image/png")

    @app.get(f"{v1}/studies/{{sid}}/report/{{name}}", dependencies=[Depends(auth)],
             responses={200: {"content": {"text/html": {}, "image/png": {}}}})
    def report_file(sid: str, name: str):
        """The study's report (``report.html``) and its figures (PNG), as written when the study finished."""
        meta = reg.meta(sid)
        d = reg.store(sid).path / "report"
        if not re.match(r"^[A-Za-z0-9_]{1,60}\.(png|html)$", name) or not (d / name).is_file():
            if meta.get("status") != "done":
                raise HTTPException(409, f"study {sid} is {meta.get('status')}: the report is written when it finishes")
            raise HTTPException(404, f"no report file {name!r}")
        kind = "text/html; charset=utf-8" if name.endswith(".html") else "image/png"
        return Response((d / name).read_bytes(), media_type=kind)

    def _diag_dir(sid: str, model: str) -> Path:
        if not re.match(r"^[A-Za-z][A-Za-z0-9_]{0,31}$", model):
            raise HTTPException(404, f"no model {model!r}")
        reg.meta(sid)
        return reg.study_dir(sid) / "diagnoses" / model

    @app.post(f"{v1}/studies/{{sid}}/diagnoses", response_model=DiagnosisStatus, status_code=202,
              dependencies=[Depends(auth)])
    def diagnose(sid: str, req: DiagnoseRequest) -> DiagnosisStatus:
        meta = reg.meta(sid)
        if meta.get("status") != "done":
            raise HTTPException(409, f"study {sid} is {meta.get('status')}: diagnose a finished study")
        summary = reg.store(sid).meta.get("summary") or {}
        models = [r["name"] for r in summary.get("models", [])]
        model = req.model or summary.get("best_model")
        if model not in models:
            raise HTTPException(404, f"study {sid} has no model {model!r} (models: {models})")
        if req.test_dataset and not (reg.root / "datasets" / f"{req.test_dataset}.csv").exists():
            raise HTTPException(404, f"no uploaded data set {req.test_dataset!r}")
        d = _diag_dir(sid, model)
        if (d / "status.json").exists() and json.loads((d / "status.json").read_text())["status"] == "running":
            raise HTTPException(409, f"a diagnosis of {model} is already running")
        runner.diagnose(sid, model, req)
        return DiagnosisStatus(model=model, status="running")

    @app.get(f"{v1}/studies/{{sid}}/diagnoses/{{model}}", dependencies=[Depends(auth)])
    def diagnosis(sid: str, model: str) -> JSONResponse:
        d = _diag_dir(sid, model)
        if not (d / "status.json").exists():
            raise HTTPException(404, f"no diagnosis of {model!r} in study {sid} (POST .../diagnoses first)")
        st = json.loads((d / "status.json").read_text())
        body = {"model": model, **st}
        if st["status"] == "done":
            body["report"] = json.loads((d / "diagnosis.json").read_text())
            body["figures"] = sorted(p.name for p in d.glob("*.png"))
        return JSONResponse(body)

    @app.get(f"{v1}/studies/{{sid}}/diagnoses/{{model}}/figures/{{name}}", dependencies=[Depends(auth)],
             responses={200: {"content": {"image/png": {}}}})
    def diagnosis_figure(sid: str, model: str, name: str):
        d = _diag_dir(sid, model)
        if not re.match(r"^[a-z_]{1,40}\.png$", name) or not (d / name).exists():
            raise HTTPException(404, f"no figure {name!r}")
        return Response((d / name).read_bytes(), media_type="image/png")

    # reattach: studies that were queued or running when the service stopped continue
    for sid in reg.ids():
        try:
            st = reg.meta(sid).get("status")
        except Exception:  # noqa: BLE001 - a damaged entry must not stop the service
            continue
        if st in ("queued", "running"):
            runner.start(sid)
    return app
