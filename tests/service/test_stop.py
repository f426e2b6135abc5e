"""Stopping ``ardflow serve`` in any way stops every process it started (scheduler, nannies, workers, the parser
pool, drivers), quickly and quietly: a Ctrl-C in its terminal (SIGINT to the whole foreground process group),
SIGTERM from a service manager, and SIGKILL of the service alone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ardflow.service.client import Client

from .test_api import ROOT, TOKEN, free_port


def _descendants(pid: int) -> set[int]:
    """Every living process below ``pid`` (by /proc's parent links)."""
    parents = {}
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                stat = (d / "stat").read_text()
                parents[int(d.name)] = int(stat.rsplit(")", 1)[1].split()[1])
            except (OSError, ValueError, IndexError):
                continue
    out, todo = set(), [pid]
    while todo:
        p = todo.pop()
        kids = [c for c, pp in parents.items() if pp == p]
        out.update(kids)
        todo += kids
    return out


def _alive(pids: set[int]) -> set[int]:
    alive = set()
    for p in pids:
        try:
            state = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:
            continue
        if state != "Z":
            alive.add(p)
    return alive


def _serve(tmp_path: Path, log: Path) -> tuple[subprocess.Popen, int]:
    """``ardflow serve`` in its own session (as a terminal's foreground job is: a Ctrl-C reaches every process
    of the group), its output in ``log``; returns it with its port once it answers and its parser pool runs."""
    port = free_port()
    with open(log, "w") as fh:
        p = subprocess.Popen([sys.executable, "-m", "ardflow.service.cli", "serve", "--port", str(port), "--root",
                              str(tmp_path / "root"), "--workers", "2", "--token", TOKEN], cwd=ROOT, stdout=fh,
                             stderr=subprocess.STDOUT, start_new_session=True)
    deadline = time.time() + 120
    while True:
        try:
            with Client(f"http://127.0.0.1:{port}", token=TOKEN, timeout=2) as c:
                c.health()
                # an upload starts the parser pool too
                csv = tmp_path / "d.csv"
                csv.write_text("t,y\n" + "".join(f"{i},{i % 3}\n" for i in range(30)))
                c.upload(csv)
            return p, port
        except Exception:
            if time.time() > deadline or p.poll() is not None:
                os.killpg(p.pid, signal.SIGKILL)
                raise
            time.sleep(0.3)


def test_no_one_but_the_service_reaches_its_scheduler(tmp_path):
    """The scheduler's address is no key to it: its comms are TLS with the service's own certificates, so a
    plain client and a client with certificates of its own are both refused."""
    import asyncio
    import json
    import urllib.request

    from distributed import Client as DaskClient, Security

    p, port = _serve(tmp_path, tmp_path / "serve.log")
    try:
        with Client(f"http://127.0.0.1:{port}", token=TOKEN) as c:
            link = c._check(c.http.get("/dashboard")).json()["url"]  # the one user of a single-token service
        ident = json.load(urllib.request.urlopen(link.replace("/status", "/json/identity.json"), timeout=10))
        addr = ident["address"]
        assert addr.startswith("tls://127.0.0.1:") and ident["n_workers"] == 2, ident

        async def reach(a, sec):
            # an asynchronous client: a synchronous one that failed to connect can deadlock in its __del__
            # (its loop runner's lock), which held this test for its whole timeout
            c = DaskClient(a, asynchronous=True, timeout=5, security=sec)
            try:
                await c
                await c.run(os.getpid)
            finally:
                await c.close()  # on its own loop (the refused client's __del__ would find it closed)

        for a, sec in ((addr, None), (addr.replace("tls://", "tcp://"), None), (addr, Security.temporary())):
            with pytest.raises(Exception):
                asyncio.run(asyncio.wait_for(reach(a, sec), 60))
    finally:
        os.killpg(p.pid, signal.SIGKILL)


def _private_key(pid: int) -> str | None:
    """The cluster's private key as a process below ``pid`` holds it in its environment (None if none does)."""
    for q in _descendants(pid):
        try:
            env = Path(f"/proc/{q}/environ").read_bytes().split(b"\0")
        except OSError:
            continue
        for kv in env:
            k, _, v = kv.decode(errors="replace").partition("=")
            if k == "DASK_DISTRIBUTED__COMM__TLS__SCHEDULER__KEY":
                return v
    return None


def _files_holding(text: str, roots: list[Path], since: float) -> list[Path]:
    """Files under ``roots`` written since ``since`` that hold ``text`` (directories untouched since then are
    passed over: a file written into one would have touched it)."""
    found = []
    for root in roots:
        for d, dirs, files in os.walk(root):
            dirs[:] = [x for x in dirs if os.path.getmtime(os.path.join(d, x)) >= since - 1]
            for f in files:
                path = Path(d, f)
                try:
                    st = path.stat()
                    if st.st_mtime >= since - 1 and st.st_size < 1 << 20 and text in path.read_text(errors="replace"):
                        found.append(path)
                except OSError:
                    continue
    return found


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process tree from /proc")
def test_a_killed_service_leaves_its_cluster_s_key_on_no_disk(tmp_path):
    """The certificates of the service's cluster live in its processes' environments only: a SIGKILLed service
    (no exit handler runs) leaves no file with its private key behind."""
    import tempfile

    t0 = time.time()
    p, _ = _serve(tmp_path, tmp_path / "serve.log")
    try:
        key = _private_key(p.pid)
        assert key is not None and "PRIVATE KEY" in key
        body = key.strip().splitlines()[1]  # a line of the key itself, not its header
        assert _files_holding(body, [Path(tempfile.gettempdir()), tmp_path], t0) == []
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait(timeout=30)
    assert _files_holding(body, [Path(tempfile.gettempdir()), tmp_path], t0) == []


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="reads the process tree from /proc")
@pytest.mark.parametrize("how", ["ctrl-c", "sigterm", "sigkill"])
def test_stopping_the_service_leaves_no_process_and_little_output(tmp_path, how):
    log = tmp_path / "serve.log"
    p, _ = _serve(tmp_path, log)
    try:
        started = log.read_text().count("\n")
        children = _descendants(p.pid)
        assert len(children) >= 4, children  # scheduler, two nannies (with their workers), the parser pool
        t0 = time.monotonic()
        if how == "ctrl-c":
            os.killpg(p.pid, signal.SIGINT)
        else:
            os.kill(p.pid, signal.SIGTERM if how == "sigterm" else signal.SIGKILL)
        p.wait(timeout=30)
        stopped = time.monotonic() - t0
        deadline = time.time() + 20
        while _alive(children) and time.time() < deadline:
            time.sleep(0.2)
        assert not _alive(children), [Path(f"/proc/{q}/cmdline").read_bytes()[:80] for q in _alive(children)]
        if how != "sigkill":  # a killed process says nothing; its children go on SIGTERM from the kernel
            after = log.read_text().splitlines()[started:]
            assert stopped < 10, stopped
            assert len(after) <= 3 and "Traceback" not in log.read_text(), after
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
