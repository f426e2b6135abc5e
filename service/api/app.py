"""The REST service (FastAPI), versioned under ``/v1``.

Studies run on a Dask cluster (embedded LocalCluster or an existing scheduler)
in background threads, so the event loop never blocks. The registry is
durable: every study is a directory under the service root holding its zarr
store, so a restarted service reattaches to its studies and resumes those that
were running.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import functools
import json
import logging
import re
import secrets
import shutil
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response, StreamingResponse

from ardflow.ardcore.errors import ArdflowError
from ardflow.ardcore.selection.spec import PLAIN_TEXT, StudySpec

from ardflow.service.api.auth import StudyAccess, TokenAuth
from ardflow.service.api.guard import RequestGuard
from ardflow.service.api.page import docs_router, page_router
from ardflow.service.api.diagnoses import diagnoses_router
from ardflow.service.api.results import results_router
from ardflow.service.api.validate import Rejected, check_budget, check_models
from ardflow.service.api.schemas import (
    API_VERSION, FINAL, DashboardLink, DatasetInfo, Health, Settings, StudyCreated, StudyStatus,
)
from ardflow.service.api.registry import ProgressCache, Registry, Runner

log = logging.getLogger("ardflow.service")
COLUMN_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]{0,63}$")

# ------------------------------------------------------------------ the app
class Admission:
    """The queue and per-token limits, counted and reserved in one step under one lock, before the
    submission awaits anything: a burst of parallel submissions cannot all see room that only one has.
    A reservation lasts until the study is written and queued (or refused), so for a moment a study may
    count twice: stricter, never looser."""

    def __init__(self, reg: Registry, runner: Runner, settings: Settings):
        self.reg, self.runner, self.settings = reg, runner, settings
        self.lock = threading.Lock()
        self.pending: dict[str, int] = {}

    @contextlib.contextmanager
    def slot(self, owner: str):
        s = self.settings
        with self.lock:
            waiting = len(self.runner.queue) + sum(self.pending.values())
            if waiting >= s.max_queued:
                raise HTTPException(429, f"{waiting} studies are waiting already; try again later",
                                    headers={"Retry-After": "60"})
            # the runner's queue and drivers are the queued and running studies: their owners are read from
            # the registry's small entries (cached), never from every store (a scan grew with the registry)
            active = self.pending.get(owner, 0) + sum(
                1 for sid in [*self.runner.queue, *self.runner.running()] if self.reg.owner(sid) == owner)
            if active >= s.max_active_per_token:
                raise HTTPException(429, f"{active} of your studies are queued or running (at most "
                                         f"{s.max_active_per_token} per token); try again later",
                                    headers={"Retry-After": "60"})
            self.pending[owner] = self.pending.get(owner, 0) + 1
        try:
            yield
        finally:
            with self.lock:
                self.pending[owner] -= 1


class _Service:
    """What the routes share: the registry, the runner, the settings, the token check, one thread for
    heavy work, the Dask client, and a short-lived cache of study status."""

    STATUS_TTL = 0.2  # s: clients polling faster than this share one read of the registry and the logs
    CLOSE_WAIT_S = 3.0  # s: how long a stopping service waits for its parser process to leave

    def __init__(self, settings: Settings, client):
        self.settings, self.client = settings, client
        self.reg = Registry(settings.root)
        self.runner = Runner(self.reg, client, max_running=settings.max_running,
                             cancel_grace_s=settings.cancel_grace_s, max_task_s=settings.max_task_s)
        self.progress_cache = ProgressCache(self.reg)
        self.max_body = int(settings.max_body_mb * 1024 * 1024)
        # parsing, data loading and store creation hold the GIL for long stretches: one thread for them, so a
        # burst of submissions cannot starve the event loop that answers status requests
        self._heavy_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="submit")
        self._parse_pool = None
        tokens = dict(settings.tokens or {})
        if settings.token is not None:
            tokens.setdefault("default", settings.token)
        self.auth = TokenAuth(tokens)
        self._recent: dict[str, tuple[float, StudyStatus]] = {}
        self._final: dict[str, tuple] = {}  # finished studies' listing rows and their files' times (:meth:`listed`)
        self.admission = Admission(self.reg, self.runner, settings)
        self.access = StudyAccess(self.auth, self.reg, settings.admins)

    async def heavy(self, fn, *args, **kw):
        return await asyncio.get_running_loop().run_in_executor(self._heavy_pool, functools.partial(fn, *args, **kw))

    async def parse(self, fn, *args):
        """``fn(*args)`` in the service's parser process (started on first use, spawned: the API process has
        threads, which a fork would copy mid-lock)."""
        if self._parse_pool is None:
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            from ardflow.workers.cluster import deaf_to_ctrl_c, die_with_parent

            # the service stops its parser: a Ctrl-C in its terminal must not, and a killed service takes it along
            with deaf_to_ctrl_c():
                self._parse_pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("spawn"),
                                                       initializer=die_with_parent)
                self._parse_pool.submit(int).result()  # started now, inside the ignoring window
        return await asyncio.get_running_loop().run_in_executor(self._parse_pool, fn, *args)

    def close(self) -> None:
        """Stop the parser process and the submission thread, waiting for the parser: its queues' semaphores are
        then released while the resource tracker the service shares with its children still holds them (left to
        the interpreter's exit, the tracker was told to release one it no longer held and printed a traceback)."""
        pool, self._parse_pool = self._parse_pool, None
        if pool is not None:
            # a parse still running holds the exit for at most a few seconds (its process dies with the service)
            waiter = threading.Thread(target=pool.shutdown, kwargs={"wait": True, "cancel_futures": True}, daemon=True)
            waiter.start()
            waiter.join(self.CLOSE_WAIT_S)
        self._heavy_pool.shutdown(wait=False, cancel_futures=True)

    def status(self, sid: str, progress: bool = True) -> StudyStatus:
        now = time.monotonic()
        hit = self._recent.get(sid) if progress else None
        if hit is not None and now - hit[0] < self.STATUS_TTL:
            return hit[1]
        m = self.reg.meta(sid)
        if m.get("status") in ("queued", "running") and sid in self.runner.lost:
            # its driver died and its failure could not be written (a full disk): said here until it can be
            m = {**m, "status": "failed", "error": self.runner.lost[sid]}
        live = progress and m["status"] != "damaged"
        st = StudyStatus(id=sid, name=m.get("name", sid), status=m.get("status", "unknown"),
                         created=m.get("created", 0.0), error=m.get("error"),
                         models=self.progress_cache.get(sid) if live else {})
        if progress:
            self._recent[sid] = (now, st)
        return st

    def forget(self, sid: str) -> None:
        self._recent.pop(sid, None)
        self._final.pop(sid, None)

    def listed(self, sid: str) -> StudyStatus:
        """A study's status for the listing (without progress): a finished one is kept while its two files of
        record (``meta.json`` and the store's ``zarr.json``) are unchanged, checked by their times (a stat each,
        not a read); a file changed or damaged since is read again."""
        d = self.reg.study_dir(sid)
        try:
            stamp = ((d / "meta.json").stat().st_mtime_ns, (d / "store" / "zarr.json").stat().st_mtime_ns)
        except OSError:
            stamp = None
        hit = self._final.get(sid)
        if hit is not None and stamp is not None and hit[0] == stamp:
            return hit[1]
        st = self.status(sid, progress=False)
        if st.status in FINAL and stamp is not None:
            self._final[sid] = (stamp, st)
        return st

    def dataset_visible(self, did: str, owner: str) -> bool:
        """Whether the uploaded data set ``did`` exists and ``owner`` may use it: it is owned like a study
        (:meth:`StudyAccess.sees`; one without a readable owner record, the admins only)."""
        d = self.reg.root / "datasets"
        if not re.fullmatch(r"[a-f0-9]{16}", did or "") or self.reg.file(d / f"{did}.csv") is None:
            return False  # none, or a symbolic link placed among the uploads: never read
        try:
            meta = json.loads((d / f"{did}.json").read_text())
        except (OSError, ValueError):
            meta = {}
        return self.access.sees(owner, meta if isinstance(meta, dict) else {})


def create_app(settings: Settings, client) -> FastAPI:
    """The FastAPI app over a Dask ``client`` (which it never exposes)."""
    # the modules the request paths import (zarr, the study graph, the store) are loaded now: the first
    # request would otherwise load them on the event loop, and every status request waits behind it
    from importlib import import_module

    for name in ("ardflow.workers.graph", "ardflow.workers.store", "ardflow.workers.inference"):
        import_module(name)
    c = _Service(settings, client)
    # the API docs come from the installed Swagger UI (page.docs_router), never from a CDN on the cookie's origin
    app = FastAPI(title="ardflow", version="0.1.0", docs_url=None, redoc_url=None,
                  description="Bayesian model selection (ARD, EKF likelihood, parallel adaptive MCMC) on Dask.")
    app.state.registry, app.state.runner, app.state.settings = c.reg, c.runner, settings
    app.state.close = c.close
    app.add_middleware(RequestGuard, max_body=c.max_body, allowed_hosts=settings.allowed_hosts,
                       csv_paths=(f"/{API_VERSION}/datasets",))
    _error_handlers(app)
    for router in (_service_router(c), _submit_router(c), _studies_router(c), diagnoses_router(c),
                   results_router(c.reg, c.access), page_router(c.auth), docs_router()):
        app.include_router(router)
    _reattach(c.reg, c.runner)
    return app


def _error_handlers(app: FastAPI) -> None:
    """Domain errors are 422s, malformed requests 422s with their fields, anything else a 500 with no traceback."""

    @app.exception_handler(Exception)
    async def unexpected(request: Request, exc: Exception):
        # never a traceback to the caller; the log keeps it
        log.exception("unexpected error on %s %s", request.method, request.url.path)
        return JSONResponse({"detail": f"internal error ({type(exc).__name__}); see the service log"}, 500)

    @app.exception_handler(OSError)
    async def disk(request: Request, exc: OSError):
        if exc.errno in (errno.ENOSPC, errno.EDQUOT):
            # nothing half-written stays behind (each writer cleans up or writes atomically): the caller may retry
            return JSONResponse({"detail": "the service's disk is full: nothing was changed; try again when its "
                                           "operator has made room"}, 507)
        return await unexpected(request, exc)

    @app.exception_handler(RequestValidationError)
    async def bad_request(request: Request, exc: RequestValidationError):
        errs = [{"type": str(e.get("type", "value_error")), "loc": [x if isinstance(x, int) else str(x)
                                                                      for x in e.get("loc", [])],
                 "msg": str(e.get("msg", ""))} for e in exc.errors()]
        return JSONResponse({"detail": errs}, 422)

    @app.exception_handler(ArdflowError)
    async def user_error(request: Request, exc: ArdflowError):
        return JSONResponse({"detail": app.state.registry.public(str(exc))}, 422)

    @app.exception_handler(HTTPException)
    async def http_error(request: Request, exc: HTTPException):
        detail = app.state.registry.public(exc.detail) if isinstance(exc.detail, str) else exc.detail
        return JSONResponse({"detail": detail}, exc.status_code, headers=getattr(exc, "headers", None))


def read_upload(path: str, text: str) -> tuple[int, list[str]]:
    """Write an uploaded CSV to ``path`` (owner-only) and read it as a data set: its rows and columns (in the
    parser process)."""
    import os

    from ardflow.ardcore.data import read_dataset

    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as fh:
        fh.write(text)
    ds = read_dataset(path)
    return len(ds), list(ds.columns)


def prepare_study(spec: dict, store: str, datasets: str, sid: str) -> None:
    """:func:`workers.graph.prepare_store` of a submitted study (in the parser process)."""
    from ardflow.workers.graph import prepare_store

    prepare_store(StudySpec.model_validate(spec), store, datasets=Path(datasets), study_id=sid)


def _service_router(c: _Service) -> APIRouter:
    """Health, the dashboard link and data-set upload."""
    r = APIRouter()
    v1 = f"/{API_VERSION}"

    @r.get(f"{v1}/health", response_model=Health)
    def health() -> Health:
        try:
            n = len(c.client.scheduler_info(n_workers=-1)["workers"])
        except Exception:  # noqa: BLE001 - health reports what it can
            n = 0
        return Health(status="ok" if n else "degraded", version="0.1.0", workers=n)

    @r.get(f"{v1}/dashboard", response_model=DashboardLink)
    def dashboard(owner: str = Depends(c.auth)) -> DashboardLink:
        # the dashboard names the scheduler, and a client of the scheduler runs code as the service: the
        # cluster is the operator's (an admin, or the one user of a single-token service), never a user's
        if len(c.auth.tokens) > 1 and owner not in c.access.admins:
            return DashboardLink(url=None)
        return DashboardLink(url=getattr(c.client, "dashboard_link", None))

    @r.post(f"{v1}/datasets", response_model=DatasetInfo, status_code=201,
              openapi_extra={"requestBody": {"content": {"text/csv": {"schema": {"type": "string"}}},
                                             "required": True},
                             "parameters": [{"name": "name", "in": "query", "required": False,
                                             "description": "what the reports call it (its file name)",
                                             "schema": {"type": "string", "maxLength": 120,
                                                        "pattern": PLAIN_TEXT}}]})
    async def upload_dataset(request: Request, owner: str = Depends(c.auth)) -> DatasetInfo:
        # read by hand: the body is CSV, and every refusal of this route is one message (the `detail` string)
        name = request.query_params.get("name")
        if name is not None and (len(name) > 120 or not re.fullmatch(PLAIN_TEXT, name)):
            raise HTTPException(422, "name: at most 120 printable characters, without '$'")
        body = await request.body()
        if len(body) > c.max_body:
            raise HTTPException(413, f"data set larger than {c.settings.c.max_body_mb:g} MB")
        if not body.strip():
            raise HTTPException(422, "empty data set")
        try:
            text = body.decode("utf-8")
        except UnicodeDecodeError:
            raise HTTPException(422, "data set must be UTF-8 CSV text") from None
        rows = max(text.count("\n"), text.count("\r"))
        if rows > c.settings.max_upload_rows:
            raise HTTPException(413, f"data set has more than {c.settings.max_upload_rows} rows")
        head = text.lstrip("\ufeff")[:70_000]  # the header line only: splitting the whole text would block
        header = head.splitlines()[0] if head.strip() else ""
        for column in (h.strip().strip('"') for h in header.split(",")):
            if not COLUMN_RE.match(column):
                raise HTTPException(422, f"column name {column[:40]!r} is not allowed: letters, digits and "
                                         "underscores, starting with a letter (at most 64)")
        did = secrets.token_hex(8)
        tmp = c.reg.root / "datasets" / f".{did}.csv"
        try:
            # written and parsed in a child process: a large upload's parse holds no GIL the event loop needs
            n, columns = await c.parse(read_upload, str(tmp), text)
        except Exception as exc:  # noqa: BLE001 - csv.Error (a field over its size limit) and friends: a 422
            tmp.unlink(missing_ok=True)  # never a temporary file left behind
            msg = (str(exc).replace(str(tmp), "data set") if isinstance(exc, ArdflowError)
                   else f"cannot read the data set: {str(exc)[:200] or type(exc).__name__}")
            raise HTTPException(422, msg) from None
        if n > c.settings.max_upload_rows:
            tmp.unlink(missing_ok=True)
            raise HTTPException(413, f"data set has more than {c.settings.max_upload_rows} rows")
        from ardflow.ardcore.jsonio import atomic_write_text

        # the owner first: a data set is never visible without one
        atomic_write_text(c.reg.root / "datasets" / f"{did}.json", json.dumps({"owner": owner, "name": name}))
        tmp.replace(c.reg.root / "datasets" / f"{did}.csv")
        return DatasetInfo(id=did, rows=n, columns=["t", *columns])

    return r


def _submit_router(c: _Service) -> APIRouter:
    """Study submission: checked (limits, models compiled in a sandbox, cost), stored, then queued."""
    r = APIRouter()
    v1 = f"/{API_VERSION}"

    @r.post(f"{v1}/studies", response_model=StudyCreated, status_code=202)
    async def submit(spec: StudySpec, owner: str = Depends(c.auth)) -> StudyCreated:
        for rec in spec.records:
            if rec.path is not None:
                raise HTTPException(422, "data.path is not accepted over the API: upload the data set "
                                         "(POST /v1/datasets) and give data.dataset")
            if rec.dataset is not None and not c.dataset_visible(rec.dataset, owner):
                raise HTTPException(422, f"data.dataset: no uploaded data set {rec.dataset!r}")  # another's: as for none
        with c.admission.slot(owner):
            return await _admitted(spec, owner)

    async def _admitted(spec: StudySpec, owner: str) -> StudyCreated:
        try:
            # compiled in a child process with limits: a poison model is a 422 now, never a busy worker later
            await c.heavy(check_models, spec, timeout_s=c.settings.check_timeout_s, memory_mb=c.settings.check_memory_mb)
        except Rejected as exc:
            raise HTTPException(exc.status, str(exc)) from None
        sid = f"{spec.name}-{secrets.token_hex(4)}"
        d = c.reg.study_dir(sid)
        d.mkdir(parents=True)
        from ardflow.workers.store import StudyStore

        try:
            # the data set is generated or read and the store written in the parser process (no GIL shared
            # with the event loop that answers status requests)
            await c.parse(prepare_study, spec.model_dump(mode="json"), str(d / "store"), str(c.reg.root / "datasets"),
                          sid)
            store = StudyStore(d / "store")
            estimate = check_budget(spec, int(store.meta.get("data", {}).get("n") or 0), c.settings.max_study_cost)
            c.reg.write_meta(sid, {"id": sid, "name": spec.name, "created": time.time(),
                                 "estimate": estimate, "owner": owner})
        except Rejected as exc:
            shutil.rmtree(d, ignore_errors=True)
            raise HTTPException(exc.status, str(exc)) from None
        except ArdflowError as exc:
            shutil.rmtree(d, ignore_errors=True)
            raise HTTPException(422, str(exc)) from None
        except BaseException:
            shutil.rmtree(d, ignore_errors=True)  # never a half-made study directory
            raise
        c.runner.start(sid)
        return StudyCreated(id=sid, status="queued")

    return r


def _studies_router(c: _Service) -> APIRouter:
    """The studies: list, status, live progress events, cancel, delete."""
    r = APIRouter()
    v1 = f"/{API_VERSION}"

    @r.get(f"{v1}/studies", response_model=list[StudyStatus])
    def list_studies(owner: str = Depends(c.auth), limit: int = Query(200, ge=1, le=10_000),
                     offset: int = Query(0, ge=0)) -> list[StudyStatus]:
        """The caller's own studies (an admin's: all), newest first, ``limit`` of them from ``offset``. Found by
        the registry's index of owners (:meth:`Registry.entry`): another user's files are not read."""
        mine = []
        for sid in c.reg.ids():
            who, created = c.reg.entry(sid)
            if c.access.sees(owner, {"owner": who}):
                mine.append((-created, sid))
        mine.sort()
        return [c.listed(sid) for _, sid in mine[offset:offset + limit]]

    @r.get(f"{v1}/studies/{{sid}}", response_model=StudyStatus, dependencies=[Depends(c.access)])
    async def status(sid: str) -> StudyStatus:
        # small local reads, folded incrementally: cheaper on the event loop than a thread hop
        return c.status(sid)

    @r.get(f"{v1}/studies/{{sid}}/events", dependencies=[Depends(c.access)],
             responses={200: {"content": {"text/event-stream": {}}}})
    async def events(sid: str, request: Request):
        c.reg.readable(sid)

        async def gen():
            from ardflow.workers.graph import read_progress

            offsets: dict[str, int] = {}
            store = c.reg.store(sid)
            while True:
                if await request.is_disconnected():
                    return
                evs = await asyncio.to_thread(read_progress, store, offsets) if store.exists() else []
                for ev in evs:
                    yield f"event: progress\ndata: {json.dumps(ev.to_json())}\n\n"
                st = c.reg.status(sid)["status"]
                if st in FINAL:
                    yield f"event: end\ndata: {json.dumps({'status': st})}\n\n"
                    return
                await asyncio.sleep(0.5)

        return StreamingResponse(gen(), media_type="text/event-stream")

    @r.post(f"{v1}/studies/{{sid}}/cancel", response_model=StudyStatus, dependencies=[Depends(c.access)])
    def cancel(sid: str) -> StudyStatus:
        m = c.reg.meta(sid)
        if m.get("status") in FINAL:
            raise HTTPException(409, f"study {sid} is already {m['status']}")
        c.runner.cancel(sid)  # recorded durably before this answer
        c.forget(sid)
        return c.status(sid)

    @r.delete(f"{v1}/studies/{{sid}}", status_code=204, dependencies=[Depends(c.access)])
    def delete(sid: str) -> Response:
        m = c.reg.meta(sid)
        if m.get("status") not in FINAL:
            raise HTTPException(409, f"study {sid} is {m.get('status')}: cancel it first")
        # a study reads done a moment before its driver has exited (it writes the report last): wait for it
        deadline = time.monotonic() + 15
        while sid in c.runner.running() and time.monotonic() < deadline:
            time.sleep(0.2)
        if sid in c.runner.running():
            raise HTTPException(409, f"study {sid} is {m.get('status')} and its driver is still writing its report: "
                                     "delete it again in a few seconds", headers={"Retry-After": "5"})
        busy = c.runner.diagnosing(sid)
        if busy:
            raise HTTPException(409, f"a diagnosis of {busy[0]} is running in study {sid}: cancel it first "
                                     f"(POST .../diagnoses/{busy[0]}/cancel)")
        shutil.rmtree(c.reg.study_dir(sid), ignore_errors=True)
        c.progress_cache.forget(sid)
        c.forget(sid)
        c.reg.drop(sid)
        return Response(status_code=204)

    return r


def _reattach(reg: Registry, runner: Runner) -> None:
    """Studies that were queued or running when the service stopped continue; damaged ones are reported."""
    waiting = []
    for m in reg.metas():
        sid = m["id"]
        if m["status"] == "damaged":
            log.warning("study %s is damaged (%s): listed as such; delete it", sid, m["error"])
        if m.get("status") in ("queued", "running"):
            waiting.append((m.get("created", 0.0), sid))
    for _, sid in sorted(waiting):
        runner.start(sid)
