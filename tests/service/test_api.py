"""The real FastAPI app over HTTP (uvicorn) with a real LocalCluster."""

import json
import os
import random
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import uvicorn
from distributed import Client as DaskClient
from distributed import LocalCluster

from ardflow.service.api.schemas import Settings
from ardflow.service.api.app import create_app
from ardflow.service.client import APIError, Client

ROOT = Path(__file__).resolve().parents[2]
SPEC = json.loads((ROOT / "tests" / "workers" / "small_study.json").read_text())
TOKEN = "test-token-123"


def free_port():
    """A free port below the kernel's ephemeral range (32768 up), so no other process's bind to port 0 or
    outgoing connection takes it between this pick and a service's restart on it."""
    rng = random.Random(os.getpid() ^ time.monotonic_ns())
    while True:
        port = rng.randrange(20000, 32000)
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                continue
            return port


class Server:
    def __init__(self, app, port):
        self.server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, log_level="warning"))
        self.thread = threading.Thread(target=self.server.run, daemon=True)

    def __enter__(self):
        self.thread.start()
        while not self.server.started:
            time.sleep(0.05)
        return self

    def __exit__(self, *exc):
        self.server.should_exit = True
        self.thread.join(10)


@contextmanager
def served(root: Path, **settings):
    """The app (``Settings(root, token=TOKEN, **settings)``) on a LocalCluster of 2 worker threads, served over
    HTTP on a free port; yields (url, app, Dask client)."""
    port = free_port()
    # threads for workers, but TCP: the service's study drivers are child processes that connect to it
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, protocol="tcp", dashboard_address=":0") as cl, \
            DaskClient(cl) as dc:
        app = create_app(Settings(root=root, token=TOKEN, **settings), dc)
        with Server(app, port):
            yield f"http://127.0.0.1:{port}", app, dc


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    root = tmp_path_factory.mktemp("svc")
    with served(root) as (url, _, _):
        yield url, root


def test_submit_watch_summary_posterior(service, tmp_path):
    url, root = service
    with Client(url, token=TOKEN) as c:
        assert c.health()["status"] == "ok"
        sid = c.submit(SPEC)
        st = c.wait(sid, poll_s=0.3, timeout=300, progress=False)
        assert st["status"] == "done"
        s = c.summary(sid)
        assert st == {**s, "status": "done"}  # wait returns the summary, as the README promises
        assert {r["name"] for r in s["models"]} == {"quad", "cubic"}
        assert abs(sum(r["probability"] for r in s["models"]) - 1) < 1e-9
        names, samples = c.posterior(sid, "quad")
        assert samples.ndim == 3 and samples.shape[2] == len(names)
        ds = c.posterior(sid, "quad", as_xarray=True)
        assert ds["samples"].dims == ("chain", "draw", "param")
        # ArviZ over HTTP: the same draws, with the EKF's pointwise log-likelihood for LOO
        az = pytest.importorskip("arviz")
        dt = c.posterior(sid, "quad", as_inference_data=True, log_likelihood=True, max_draws=60)
        assert dt["log_likelihood"]["y"].dims == ("chain", "draw", "time")
        np.testing.assert_allclose(dt["log_likelihood"]["y"].sum("time").values,
                                   dt["sample_stats"]["log_likelihood"].values, rtol=1e-9)
        assert np.isfinite(float(az.loo(dt).elpd)) and "r_hat" in az.summary(dt).columns
        with pytest.raises(APIError) as e:
            c.posterior(sid, "quad", as_inference_data=True, log_likelihood=True, max_draws=10**5)
        assert e.value.status == 422
        png = c.figure(sid, "evidence.png")
        assert png[:8] == b"\x89PNG\r\n\x1a\n"
        st = c.status(sid)
        assert st["models"]["quad"]["trials_done"] >= 2 and st["models"]["quad"]["best_log_evidence"] is not None
        assert any(x["id"] == sid for x in c.studies())
        # the same report as the CLI writes, fetched over HTTP: every figure it shows comes along
        page = c.report(sid, tmp_path / "report")
        text = page.read_text()
        imgs = re.findall(r"<img src='([^']+)'", text)
        assert "Model comparison" in text and len(imgs) >= 4
        assert all((page.parent / f).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for f in imgs)
        with pytest.raises(APIError) as e:
            c._check(c.http.get(f"/studies/{sid}/report/../meta.json"))
        assert e.value.status == 404
        # damaged files: a garbled chunk of draws, a removed one, a garbage summary: each a 409 that says
        # damaged, never a 500 and never NaN passed on as draws
        by_model = {}
        for model in ("quad", "cubic"):  # the chunks of the draws each model reports (its best trial's)
            it = c._check(c.http.get(f"/studies/{sid}/posterior/{model}", params={"max_draws": 1})).json()["iteration"]
            trial = root / "studies" / sid / "store" / "models" / model / "trials" / f"{it:03d}" / "samples"
            by_model[model] = sorted(p for p in trial.rglob("*") if p.is_file() and p.name != "zarr.json")
            assert by_model[model], trial
        by_model["quad"][0].write_bytes(by_model["quad"][0].read_bytes()[:7])  # cut short
        by_model["cubic"][0].unlink()  # removed: zarr would fill it in silently
        for model in ("quad", "cubic"):
            for path in (f"/studies/{sid}/posterior/{model}", f"/studies/{sid}/posterior/{model}?format=npz",
                         f"/studies/{sid}/inference_data/{model}"):
                r = c.http.get(path)
                assert r.status_code == 409 and "damaged" in r.json()["detail"], (path, r.status_code, r.text[:200])
        (root / "studies" / sid / "store" / "summary.json").write_text("{garbage")
        r = c.http.get(f"/studies/{sid}/summary")
        assert r.status_code == 409 and "damaged" in r.json()["detail"], r.text


def test_uploaded_csv_study(service, tmp_path):
    url, _ = service
    from ardflow.ardcore.selection.spec import appendix_a_data

    ds = appendix_a_data(3)
    csv = tmp_path / "d.csv"
    ds.to_csv(csv)
    spec = dict(SPEC, models=SPEC["models"][:1], name="uploaded")
    with Client(url, token=TOKEN) as c:
        sid = c.submit(spec, csv=csv)
        assert c.wait(sid, poll_s=0.3, timeout=300, progress=False)["status"] == "done"
        assert c.summary(sid)["data"]["source"].startswith("d.csv (uploaded data set ")  # its name, not a hash


def test_server_sent_events(service):
    import httpx

    url, _ = service
    with Client(url, token=TOKEN) as c:
        sid = c.submit(dict(SPEC, models=SPEC["models"][:1], name="sse"))
    events = []
    with httpx.stream("GET", f"{url}/v1/studies/{sid}/events", headers={"X-API-Token": TOKEN}, timeout=300) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        for line in r.iter_lines():
            if line.startswith("event:"):
                events.append(line.split(":", 1)[1].strip())
            if events and events[-1] == "end":
                break
    assert "progress" in events and events[-1] == "end"


def test_cancel_running_study(service):
    url, _ = service
    spec = dict(SPEC, name="tocancel", maximiser=dict(SPEC["maximiser"], max_trials=40),
                sampler=dict(SPEC["sampler"], n_stationary=4000))
    with Client(url, token=TOKEN) as c:
        sid = c.submit(spec)
        while c.status(sid)["status"] != "running":
            time.sleep(0.1)
        c.cancel(sid)
        st = c.wait(sid, poll_s=0.2, timeout=120, progress=False)
        assert st["status"] == "cancelled"
        with pytest.raises(APIError) as ei:
            c.cancel(sid)
        assert ei.value.status == 409


@pytest.mark.parametrize("method,path,body,status,msg", [
    ("post", "/studies", {"name": "x"}, 422, "data"),
    ("post", "/studies", dict(SPEC, bogus=1), 422, "bogus"),
    ("post", "/studies", dict(SPEC, data={"path": "/etc/passwd"}), 422, "not accepted over the API"),
    ("post", "/studies", dict(SPEC, data={"dataset": "0123456789abcdef"}), 422, "no uploaded data set"),
    ("get", "/studies/nope", None, 404, "no study"),
    ("get", "/studies/../../etc", None, 404, ""),
    ("get", "/studies/nope/summary", None, 404, "no study"),
])
def test_bad_requests_are_4xx_with_a_message(service, method, path, body, status, msg):
    import httpx

    url, _ = service
    r = getattr(httpx, method)(f"{url}/v1{path}", headers={"X-API-Token": TOKEN},
                               **({"json": body} if body is not None else {}))
    assert r.status_code == status, r.text
    assert msg in r.text


def test_auth_and_limits(service):
    import httpx

    url, _ = service
    assert httpx.get(f"{url}/v1/studies").status_code == 401
    assert httpx.get(f"{url}/v1/studies", headers={"X-API-Token": "wrong"}).status_code == 401
    assert httpx.get(f"{url}/v1/studies", headers={"Authorization": f"Bearer {TOKEN}"}).status_code == 200
    assert httpx.get(f"{url}/v1/health").status_code == 200  # health is open
    big = b"t,y\n" + b"0,1\n" * (6 * 1024 * 1024)
    r = httpx.post(f"{url}/v1/datasets", content=big, headers={"X-API-Token": TOKEN, "Content-Type": "text/csv"})
    assert r.status_code == 413
    r = httpx.post(f"{url}/v1/datasets", content=b"t,y\n1,2\n0,3\n" + b"2,1\n" * 20,
                   headers={"X-API-Token": TOKEN, "Content-Type": "text/csv"})
    assert r.status_code == 422 and "not strictly increasing" in r.text
    nan = json.dumps(dict(SPEC, seed=1)).replace('"sd": 10', '"sd": NaN', 1)
    r = httpx.post(f"{url}/v1/studies", content=nan, headers={"X-API-Token": TOKEN, "Content-Type": "application/json"})
    assert r.status_code == 422


def start_service(root: Path, port: int):
    """``ardflow serve`` (2 workers, the test token) on ``root`` as its own process group; returns the
    process once /v1/health answers."""
    cmd = [sys.executable, "-m", "ardflow.service.cli", "serve", "--port", str(port), "--root", str(root), "--workers", "2",
           "--token", TOKEN]
    # its output goes to a log beside the root, so a service that does not start says why
    log = root.parent / f"serve-{port}-{time.monotonic_ns()}.log"
    with open(log, "wb") as out:
        p = subprocess.Popen(cmd, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.time() + 120
    while time.time() < deadline and p.poll() is None:
        try:
            with Client(f"http://127.0.0.1:{port}", token=TOKEN, timeout=2) as c:
                c.health()
                return p
        except Exception:
            time.sleep(0.3)
    tail = log.read_text(errors="replace")[-3000:]
    raise RuntimeError(f"service did not start (exit {p.poll()}); its output ends:\n{tail}")


class ServiceProcess:
    """``ardflow serve`` on ``root`` as its own process group, started on entering the ``with``;
    :meth:`kill_and_restart` SIGKILLs the whole group (API, drivers and embedded cluster) and starts it again;
    leaving the ``with`` kills it."""

    def __init__(self, root: Path):
        self.root, self.port = root, free_port()
        self.url = f"http://127.0.0.1:{self.port}"

    def __enter__(self):
        self.p = start_service(self.root, self.port)
        return self

    def kill_and_restart(self) -> None:
        os.killpg(self.p.pid, signal.SIGKILL)
        self.p.wait()
        self.p = start_service(self.root, self.port)

    def __exit__(self, *exc):
        try:
            os.killpg(self.p.pid, signal.SIGKILL)
        except ProcessLookupError:  # it had already exited (a service that did not start): its error stands
            pass


def test_service_restart_mid_study(tmp_path):
    """Kill the whole service (API and its embedded cluster) mid-study; a restarted service finishes it."""
    with ServiceProcess(tmp_path / "svc") as svc:
        with Client(svc.url, token=TOKEN) as c:
            sid = c.submit(SPEC)
            while sum(m["trials_done"] for m in c.status(sid)["models"].values()) < 3:
                time.sleep(0.2)
        svc.kill_and_restart()
        with Client(svc.url, token=TOKEN) as c:
            st = c.wait(sid, poll_s=0.5, timeout=300, progress=False)
            assert st["status"] == "done"
            assert {r["name"] for r in c.summary(sid)["models"]} == {"quad", "cubic"}


def test_appendix_a_study_over_http(service):
    url, _ = service
    spec = json.loads((ROOT / "examples" / "polynomial.json").read_text())
    with Client(url, token=TOKEN) as c:
        sid = c.submit(spec)
        seen = set()
        while True:
            st = c.status(sid)
            seen.add(st["status"])
            if st["status"] in ("done", "failed", "cancelled"):
                break
            time.sleep(0.2)
        assert st["status"] == "done", st
        r = c.summary(sid)["models"][0]
        assert sorted(r["pruned"]) == ["a2", "a3", "a4"]
        names, samples = c.posterior(sid, "polynomial")
        a1 = samples[..., names.index("a1")].ravel()
        assert np.quantile(a1, 0.005) < 5.0 < np.quantile(a1, 0.995)


def test_cli_submit_status_fetch(service, tmp_path):
    url, _ = service
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(dict(SPEC, models=SPEC["models"][:1], name="cli")))
    base = [sys.executable, "-m", "ardflow.service.cli"]
    common = ["--url", url, "--token", TOKEN]
    r = subprocess.run(base + ["submit", str(spec), "--wait"] + common, cwd=ROOT, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    sid = r.stdout.splitlines()[0].strip()
    r = subprocess.run(base + ["status", sid, "--json"] + common, cwd=ROOT, capture_output=True, text=True,
                       timeout=60)
    st = json.loads(r.stdout)
    assert r.returncode == 0 and st["status"] == "done" and st["best_model"] == "quad" and st["probability"] == 1.0
    assert st["models"]["quad"]["trials_done"] >= 1
    r = subprocess.run(base + ["status", "--json"] + common, cwd=ROOT, capture_output=True, text=True, timeout=60)
    row = next(x for x in json.loads(r.stdout) if x["id"] == sid)
    assert row["best_model"] == "quad" and row["models"], row  # the listing as data: what the table shows
    r = subprocess.run(base + ["status", "--url", url, "--token", "wrong"], cwd=ROOT, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "HTTP 401" in r.stderr and "ARDFLOW_TOKEN" in r.stderr, r.stderr
    # for people: a table with the best model and its probability, when it was submitted
    r = subprocess.run(base + ["status"] + common, cwd=ROOT, capture_output=True, text=True, timeout=60)
    line = next(x for x in r.stdout.splitlines() if x.startswith(sid))
    assert r.returncode == 0 and "done" in line and "quad (P 1.00)" in line and " ago" in line, r.stdout
    r = subprocess.run(base + ["fetch", sid, "--out", str(tmp_path / "f")] + common, cwd=ROOT, capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "f" / "summary.json").exists() and (tmp_path / "f" / "posterior_quad.npz").exists()
    assert (tmp_path / "f" / "evidence.png").read_bytes()[:4] == b"\x89PNG"
    r = subprocess.run(base + ["status", "no-such-study"] + common, cwd=ROOT, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2 and "HTTP 404" in r.stderr and "Traceback" not in r.stderr


def test_diagnose_over_http(service, tmp_path):
    """Fit a linear oscillator to Duffing data over the API, then close the loop over the API."""
    from tests.ardcore.test_diagnose import duffing_free_decay, duffing_spec

    url, root = service
    data = duffing_free_decay(-4.0, 3)
    est, held = tmp_path / "est.csv", [tmp_path / "held1.csv", tmp_path / "held2.csv"]
    data.slice(0, 1000).to_csv(est)
    data.slice(1000, 1250).to_csv(held[0])  # two held-out records, each free-run from its own start
    data.slice(1250, None).to_csv(held[1])
    spec = duffing_spec().model_dump(mode="json", exclude_none=True)
    spec["name"] = "osc"
    spec["data"] = {}
    with Client(url, token=TOKEN) as c:
        sid = c.submit(spec, csv=est)
        assert c.wait(sid, poll_s=0.3, timeout=300, progress=False)["status"] == "done"
        with pytest.raises(APIError) as e:
            c.diagnose(sid, "nosuchmodel")
        assert e.value.status == 404
        d = c.diagnose(sid, top_k=1, max_rounds=1, test_csv=held, poll_s=0.5, timeout=300)
        rep = d["report"]
        assert rep["added"][0]["effect"] == "cubic_stiffness(y)" and rep["added"][0]["character"] == "hardening"
        assert rep["after"]["free_run"]["rms_error"] < rep["before"]["free_run"]["rms_error"]
        assert rep["n_test"] == len(data) - 1000
        assert [r["name"] for r in rep["after"]["free_run"]["records"]] == ["held1.csv", "held2.csv"]
        assert set(d["figures"]) >= {"tests.png", "free_run.png", "candidates.png", "process_noise.png"}
        assert c.diagnosis_figure(sid, d["model"], "free_run.png")[:8] == b"\x89PNG\r\n\x1a\n"
        # no server path in what a user reads: the data are named as the study names them
        assert rep["data"].startswith("est.csv (uploaded data set ") and str(root) not in json.dumps(rep)
        # a damaged status file (a write cut short) and one left "running" by a service that stopped are
        # failed diagnoses that say so, never a 500 and never "running" forever; a new one can be started
        status = root / "studies" / sid / "diagnoses" / d["model"] / "status.json"
        for text, why in (("", "cannot be read"), ('{"status": "runn', "cannot be read"),
                          ('{"status": "running", "service": "gone"}', "service stopped while it was running")):
            status.write_text(text)
            got = c._check(c.http.get(f"/studies/{sid}/diagnoses/{d['model']}")).json()
            assert got["status"] == "failed" and why in got["error"], got
        again = c.diagnose(sid, top_k=1, max_rounds=1, poll_s=0.5, timeout=300)
        assert again["status"] == "done"
        # a symbolic link placed in a study is never followed, to a file outside or inside the registry
        outside = tmp_path / "secret.html"
        outside.write_text("secret")
        diag = status.parent
        for link, target in ((diag / "leak.png", outside), (diag / "evil.html", outside),
                             (root / "studies" / sid / "store" / "report" / "evil.html", outside),
                             (diag / "twin.png", diag / "free_run.png")):
            link.symlink_to(target)
        for path in (f"/studies/{sid}/diagnoses/{d['model']}/figures/leak.png",
                     f"/studies/{sid}/diagnoses/{d['model']}/figures/twin.png",
                     f"/studies/{sid}/diagnoses/{d['model']}/report/evil.html", f"/studies/{sid}/report/evil.html"):
            r = c.http.get(path)
            assert r.status_code == 404 and b"secret" not in r.content, (path, r.status_code)
        assert "leak.png" not in c.diagnosis(sid, d["model"])["figures"]
        status.unlink()
        status.symlink_to(outside)
        assert c.diagnosis(sid, d["model"])["status"] == "failed"
