"""A real external cluster: ``dask scheduler`` and two ``dask worker`` processes started from another working
directory, as a user's own cluster would be; the study runs through ``ardflow select --scheduler`` and
through ``ardflow serve --scheduler``, and a worker killed mid-study does not change the result."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from ardflow.ardcore.selection.spec import load_spec
from ardflow.ardcore.selection.study import select

ROOT = Path(__file__).resolve().parents[2]
SPEC = ROOT / "tests" / "workers" / "small_study.json"
BIN = Path(sys.executable).parent
TOKEN = "ext-token"


def _port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _spawn(args, cwd, log):
    return subprocess.Popen(args, cwd=cwd, stdout=open(log, "w"), stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, start_new_session=True)


@pytest.fixture()
def cluster(tmp_path):
    """A scheduler and two single-threaded workers, each its own process group, in a foreign directory."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    port = _port()
    addr = f"tcp://127.0.0.1:{port}"
    env_note = elsewhere / "logs"
    env_note.mkdir()
    procs = [_spawn([str(BIN / "dask"), "scheduler", "--host", "127.0.0.1", "--port", str(port),
                     "--dashboard-address", "127.0.0.1:0"], elsewhere, env_note / "scheduler.log")]
    from distributed import Client

    deadline = time.time() + 60
    while True:
        try:
            with Client(addr, timeout=2):
                break
        except OSError:
            if time.time() > deadline:
                raise
            time.sleep(0.3)
    workers = [_spawn([str(BIN / "dask"), "worker", addr, "--nthreads", "1", "--nworkers", "1",
                       "--name", f"w{i}", "--local-directory", str(elsewhere / f"w{i}")],
                      elsewhere, env_note / f"worker{i}.log") for i in range(2)]
    procs += workers
    with Client(addr) as c:
        c.wait_for_workers(2, timeout=60)
    try:
        yield addr, workers, elsewhere
    finally:
        for p in procs:
            try:
                os.killpg(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def rows(summary):
    return {r["name"]: r for r in summary["models"]}


@pytest.fixture(scope="module")
def reference_summary():
    return select(load_spec(SPEC))


def test_select_on_an_external_scheduler_with_a_worker_killed(cluster, tmp_path, reference_summary):
    addr, workers, elsewhere = cluster
    out = tmp_path / "study"
    p = subprocess.Popen([sys.executable, "-m", "ardflow.service.cli", "select", str(SPEC), "--out", str(out),
                          "--scheduler", addr], cwd=elsewhere, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         text=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
    # kill one worker once the study has trials in its store
    deadline = time.time() + 300
    while time.time() < deadline and p.poll() is None:
        logs = list((out / "progress").glob("*.jsonl")) if (out / "progress").exists() else []
        trials = sum(f.read_text().count('"stage": "trial"') for f in logs)
        if trials >= 2:
            os.killpg(workers[0].pid, signal.SIGKILL)
            break
        time.sleep(0.2)
    assert workers[0].poll() is not None or workers[0].wait(10) is not None, "the worker was not killed"
    stdout, _ = p.communicate(timeout=600)
    assert p.returncode == 0, stdout[-2000:]
    s = json.loads((out / "summary.json").read_text())
    a, b = rows(s), rows(reference_summary)
    assert set(a) == set(b)
    for k in a:
        assert a[k]["pruned"] == b[k]["pruned"]
        assert abs(a[k]["log_evidence"] - b[k]["log_evidence"]) < 5 * max(b[k]["log_evidence_se"], 0.05)


def test_serve_on_an_external_scheduler(cluster, tmp_path, reference_summary):
    addr, _, elsewhere = cluster
    port = _port()
    p = _spawn([sys.executable, "-m", "ardflow.service.cli", "serve", "--port", str(port), "--root", str(tmp_path / "svc"),
                "--scheduler", addr, "--token", TOKEN], ROOT, tmp_path / "serve.log")
    base = f"http://127.0.0.1:{port}/v1"
    h = {"X-API-Token": TOKEN}
    try:
        deadline = time.time() + 120
        while True:
            try:
                r = httpx.get(f"{base}/health", timeout=2)
                if r.status_code == 200 and r.json()["workers"] == 2:
                    break
            except httpx.HTTPError:
                pass
            assert time.time() < deadline, (tmp_path / "serve.log").read_text()[-2000:]
            time.sleep(0.3)
        sid = httpx.post(f"{base}/studies", json=json.loads(SPEC.read_text()), headers=h, timeout=60).json()["id"]
        deadline = time.time() + 400
        while (st := httpx.get(f"{base}/studies/{sid}", headers=h).json())["status"] not in ("done", "failed"):
            assert time.time() < deadline
            time.sleep(0.5)
        assert st["status"] == "done", st
        a, b = rows(httpx.get(f"{base}/studies/{sid}/summary", headers=h).json()), rows(reference_summary)
        for k in a:
            assert a[k]["pruned"] == b[k]["pruned"]
            assert abs(a[k]["log_evidence"] - b[k]["log_evidence"]) < 5 * max(b[k]["log_evidence_se"], 0.05)
    finally:
        os.killpg(p.pid, signal.SIGKILL)
