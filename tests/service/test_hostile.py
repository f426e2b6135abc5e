"""Hostile and careless requests against the real app over HTTP: every one answered at request time with a
4xx naming the problem, never a 5xx; poison models rejected at submit; a real queue; cancel that holds."""

import copy
import json
import os
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import httpx
import pytest

from ardflow.service.api.schemas import Settings
from ardflow.service.api.app import create_app
from ardflow.service.client import APIError, Client

from .test_api import ROOT, SPEC, TOKEN, Server, ServiceProcess, free_port, served

H = {"X-API-Token": TOKEN}
POLY = {"name": "poly", "states": ["z"], "drift": {"z": 0.0},
        "observations": [{"column": "y", "expr": "a0 + a1*x", "noise_std": "gamma"}],
        "parameters": ["a0", "a1", "gamma"], "inputs": ["x"], "initial_std": {"z": 0.0}, "substeps": 1,
        "integrator": "euler"}


def poly_study(**model_update):
    m = dict(copy.deepcopy(POLY), **model_update)
    return {"name": "poison", "data": {"generator": "appendix_a", "seed": 2},
            "models": [{"model": m, "priors": {"a0": {"kind": "normal", "mean": 0, "sd": 10},
                                               "a1": {"kind": "normal", "mean": 0, "sd": 10},
                                               "gamma": {"kind": "lognormal", "median": 0.3, "cov": 50}}}],
            "sampler": SPEC["sampler"], "maximiser": SPEC["maximiser"], "seed": 1}


def obs(expr=None, noise=None):
    o = dict(POLY["observations"][0])
    if expr is not None:
        o["expr"] = expr
    if noise is not None:
        o["noise_std"] = noise
    return [o]


POISON_EXPRESSIONS = [
    "9**9**9**9", "2**2000*x", "x/0", "a0/(x-x)", "sqrt(-1)*x", "(-8)**(1/3)*x", "exp(1000)*x",
    "x*10**300*10**300", "x**100000", "x**-100000", "+".join(["x"] * 1000), "-" * 1999 + "x",
    "sin(" * 120 + "x" + ")" * 120, "__import__('os')", "x.real", "lambda: x", "'a'*3", "[x]", "x if x else a0",
    "x < a0", "x // 2", "x % 2", "x @ x", "~x", "not x", "x & 1", "x ^ 2", "open('f')", "eval('1')", "a0 + b9",
    "sin(x, x)", "sin", "exp(x=1)", "1e309*x", "x ** x ** x ** x ** 1000", "",
]


@pytest.fixture(scope="module")
def hostile(tmp_path_factory):
    root = tmp_path_factory.mktemp("hostile")
    with served(root, max_running=1, max_upload_rows=5000, max_body_mb=1.0, allowed_hosts=["127.0.0.1", "localhost"],
                max_study_cost=1e10, check_timeout_s=20) as (url, app, dc):
        yield url, root, app, dc


def _answers(url):
    """(description, httpx request kwargs) of every bad request; none may get a 2xx or a 5xx."""
    v1 = f"{url}/v1"
    J = dict(H, **{"Content-Type": "application/json"})
    C = dict(H, **{"Content-Type": "text/csv"})
    out = []
    # -- poison models, in every field an expression can sit in
    for e in POISON_EXPRESSIONS:
        out.append((f"obs expr {e[:20]!r}", dict(method="POST", url=f"{v1}/studies", headers=J,
                                                 content=json.dumps(poly_study(observations=obs(expr=e))))))
    for e in POISON_EXPRESSIONS[:12]:
        out.append((f"noise_std {e[:20]!r}", dict(method="POST", url=f"{v1}/studies", headers=J,
                                                  content=json.dumps(poly_study(observations=obs(noise=e))))))
        out.append((f"drift {e[:20]!r}", dict(method="POST", url=f"{v1}/studies", headers=J,
                                              content=json.dumps(poly_study(drift={"z": e})))))
    for e in POISON_EXPRESSIONS[:8]:
        out.append((f"initial_std {e[:20]!r}", dict(method="POST", url=f"{v1}/studies", headers=J,
                                                    content=json.dumps(poly_study(initial_std={"z": e})))))
        out.append((f"derived {e[:20]!r}", dict(method="POST", url=f"{v1}/studies", headers=J, content=json.dumps(
            poly_study(derived={"q": e}, observations=obs("a0 + q*a1"))))))
    chain = {f"d{i}": (f"d{i - 1}*d{i - 1} + d{i - 1}" if i else "x*x") for i in range(64)}
    out.append(("derived chain", dict(method="POST", url=f"{v1}/studies", headers=J,
                                      content=json.dumps(poly_study(derived=chain, observations=obs("a0 + d63"))))))
    # -- schema: wrong types, NaN, extra fields, limits
    bad_specs = [
        {}, {"name": "x"}, dict(SPEC, name="../x"), dict(SPEC, name="a" * 200), dict(SPEC, seed="one"),
        dict(SPEC, extra=1), dict(SPEC, models=[]), dict(SPEC, models="quad"),
        dict(SPEC, sampler=dict(SPEC["sampler"], n_chains=1)), dict(SPEC, sampler=dict(SPEC["sampler"], n_chains=65)),
        dict(SPEC, sampler=dict(SPEC["sampler"], round_size=-5)), dict(SPEC, maximiser=dict(max_trials=0)),
        dict(SPEC, data={"path": "/etc/passwd"}), dict(SPEC, data={"dataset": "../../etc/passwd"}),
        dict(SPEC, data={"dataset": "0123456789abcdef"}), dict(SPEC, data={"generator": "nope"}),
        dict(SPEC, models=[dict(SPEC["models"][0], model="no_such_model")]),
        dict(SPEC, models=[dict(SPEC["models"][0], priors={"zz": {"kind": "normal", "mean": 0, "sd": 1}})]),
        dict(SPEC, models=[dict(SPEC["models"][0], fixed={"a3": "inf"})]),
    ]
    for i, b in enumerate(bad_specs):
        out.append((f"bad spec {i}", dict(method="POST", url=f"{v1}/studies", headers=J, content=json.dumps(b))))
    for i, raw in enumerate(["{", "[]", "null", "1", '{"name": NaN}', json.dumps(SPEC).replace('"sd": 10', '"sd": NaN', 1),
                             json.dumps(SPEC).replace('"sd": 10', '"sd": Infinity', 1), "\xff\xfe", "{" * 5000]):
        out.append((f"bad json {i}", dict(method="POST", url=f"{v1}/studies", headers=J, content=raw)))
    # -- the compute budget: the largest settings the schema allows
    huge = dict(SPEC, sampler=dict(SPEC["sampler"], n_chains=64, n_stationary=10_000_000, n_proposal=10_000_000,
                                   max_burnin_rounds=10_000))
    out.append(("budget", dict(method="POST", url=f"{v1}/studies", headers=J, content=json.dumps(huge))))
    # -- content types and sizes, before authentication
    out += [
        ("text/plain study", dict(method="POST", url=f"{v1}/studies", headers=dict(H, **{"Content-Type": "text/plain"}),
                                  content=json.dumps(SPEC))),
        ("form study", dict(method="POST", url=f"{v1}/studies",
                            headers=dict(H, **{"Content-Type": "application/x-www-form-urlencoded"}), content="a=1")),
        ("no content type", dict(method="POST", url=f"{v1}/studies", headers=H, content=json.dumps(SPEC).encode())),
        ("json data set", dict(method="POST", url=f"{v1}/datasets", headers=J, content="t,y\n0,1\n")),
        ("text/plain data set", dict(method="POST", url=f"{v1}/datasets",
                                     headers=dict(H, **{"Content-Type": "text/plain"}), content="t,y\n0,1\n")),
        ("big body declared", dict(method="POST", url=f"{v1}/studies", headers=J, content=b"x" * (2 * 2**20))),
        ("big body chunked, no token", dict(method="POST", url=f"{v1}/studies",
                                            headers={"Content-Type": "application/json"},
                                            content=(b"x" * 65536 for _ in range(40)))),
        ("big csv chunked", dict(method="POST", url=f"{v1}/datasets", headers=C,
                                 content=(b"1,2\n" * 16384 for _ in range(40)))),
    ]
    # -- authentication
    for route in ("studies", "datasets", "dashboard", "studies/x-1"):
        out.append((f"no token {route}", dict(method="GET", url=f"{v1}/{route}")))
        out.append((f"wrong token {route}", dict(method="GET", url=f"{v1}/{route}", headers={"X-API-Token": "nope"})))
        out.append((f"bearer wrong {route}", dict(method="GET", url=f"{v1}/{route}",
                                                   headers={"Authorization": "Bearer nope"})))
    # -- the Host header (DNS rebinding)
    for host in ("evil.example", "127.0.0.1.evil.example", "localhost.evil"):
        out.append((f"host {host}", dict(method="GET", url=f"{v1}/health", headers={"Host": host})))
    # -- data sets
    csvs = {
        "empty": "", "blank": "\n\n  \n", "header only": "t,y\n", "numbers header": "1,2\n3,4\n",
        "non numeric": "t,y\n0,a\n1,b\n", "not increasing": "t,y\n0,1\n0,2\n", "inf": "t,y\n0,inf\n1,2\n",
        "zarr.json column": "t,zarr.json\n0,1\n1,2\n2,3\n", "traversal column": "t,../../../../tmp/x\n0,1\n1,2\n",
        "slash column": "t,a/b\n0,1\n1,2\n", "dup columns": "t,y,y\n0,1,2\n1,2,3\n",
        "space column": "t,y z\n0,1\n1,2\n", "dot column": "t,.y\n0,1\n1,2\n",
        "long cell": "t,y\n0," + "9" * 140_000 + "\n",
        "quote cell": 't,y\n0,"' + "9" * 140_000 + '\n',
        "CR rows": "t,y\r" + "".join(f"{i},1\r" for i in range(6000)),
        "LF rows": "t,y\n" + "".join(f"{i},1\n" for i in range(6000)),
        "nul": "t,y\n0,\x001\n", "no time": "a,y\n0,1\n1,2\n", "ragged": "t,y\n0,1,5\n1,2\n",
        "unnamed values": "t,,y\n0,1,2\n1,2,3\n",
    }
    for k, text in csvs.items():
        out.append((f"csv {k}", dict(method="POST", url=f"{v1}/datasets", headers=C, content=text.encode())))
    out.append(("csv latin-1", dict(method="POST", url=f"{v1}/datasets", headers=C, content="t,\xe9\n0,1\n".encode("latin-1"))))
    # -- paths and parameters
    for p in ("studies/..%2F..%2Fetc", "studies/a%00b", "studies/" + "a" * 100, "studies/nope-1",
              "studies/nope-1/summary", "studies/nope-1/posterior/quad", "studies/nope-1/figures/evidence.png",
              "studies/nope-1/report/report.html", "studies/nope-1/diagnoses/quad", "studies/nope-1/events"):
        out.append((f"path {p[:30]}", dict(method="GET", url=f"{v1}/{p}", headers=H)))
    missing = dict(SPEC, data={"dataset": "0123456789abcdef"})
    out.append(("missing data set", dict(method="POST", url=f"{v1}/studies", headers=J, content=json.dumps(missing))))
    for p in ("studies/nope-1/cancel", "studies/nope-1/diagnoses"):
        out.append((f"post {p}", dict(method="POST", url=f"{v1}/{p}", headers=J, content="{}")))
    out.append(("delete unknown", dict(method="DELETE", url=f"{v1}/studies/nope-1", headers=H)))
    out.append(("wrong method", dict(method="PUT", url=f"{v1}/studies", headers=J, content="{}")))
    out.append(("unknown route", dict(method="GET", url=f"{v1}/nothing", headers=H)))
    return out


def test_hostile_requests_get_4xx_at_request_time(hostile):
    url, root, app, _ = hostile
    cases = _answers(url)
    assert len(cases) >= 150
    bad = []
    with httpx.Client(timeout=60) as c:
        for what, kw in cases:
            r = c.request(**kw)
            detail = r.json().get("detail") if r.headers.get("content-type", "").startswith("application/json") else None
            if not (400 <= r.status_code < 500) or not detail:
                bad.append((what, r.status_code, r.text[:200]))
            if str(root) in r.text or str(root.resolve()) in r.text:  # the server's paths never leak
                bad.append((what, "path leaked", r.text[:300]))
    assert not bad, bad
    # nothing half-made: no study directory without its meta.json, no temporary data file
    studies = [p for p in (root / "studies").iterdir()]
    assert all((p / "meta.json").exists() for p in studies), studies
    assert not list((root / "datasets").glob(".*"))
    assert app.state.runner.queue == [] and not app.state.runner.running()


def test_poison_rejected_at_submit_naming_the_field(hostile):
    url, _, _, _ = hostile
    with httpx.Client(timeout=60, headers=H) as c:
        for expr, words in (("9**9**9**9", "finite"), ("2**2000*x", "finite"), ("x/0", "finite"),
                            ("sqrt(-1)*x", "real"), ("__import__('os')", "not allowed"), ("x**100000", "exponent")):
            t0 = time.perf_counter()
            r = c.post(f"{url}/v1/studies", json=poly_study(observations=obs(expr=expr)))
            assert r.status_code == 422 and words in r.text and "observations[0].expr" in r.text, r.text
            assert time.perf_counter() - t0 < 20
        chain = {f"d{i}": (f"d{i - 1}*d{i - 1} + d{i - 1}" if i else "x*x") for i in range(64)}
        r = c.post(f"{url}/v1/studies", json=poly_study(derived=chain, observations=obs("a0 + d63")))
        assert r.status_code == 422 and "derived" in r.text


def test_queue_cancel_delete_and_concurrent_figures(hostile):
    """max_running=1: the second study waits queued; a queued study cancelled never runs; a running one
    cancelled stops; finished ones are deleted; 12 concurrent figure requests all succeed."""
    url, root, app, _ = hostile
    with httpx.Client(timeout=60, headers=H) as c:
        a = c.post(f"{url}/v1/studies", json=dict(SPEC, seed=11)).json()["id"]
        b = c.post(f"{url}/v1/studies", json=dict(SPEC, seed=12)).json()["id"]
        d = c.post(f"{url}/v1/studies", json=dict(SPEC, seed=13)).json()["id"]
        assert c.get(f"{url}/v1/studies/{d}").json()["status"] == "queued"
        r = c.post(f"{url}/v1/studies/{d}/cancel", json={})
        assert r.status_code == 200 and r.json()["status"] == "cancelled"
        assert (root / "studies" / d / "store" / "CANCELLED").exists()
        assert c.delete(f"{url}/v1/studies/{a}").status_code == 409  # running or queued: cancel first
        deadline = time.time() + 300
        while c.get(f"{url}/v1/studies/{b}").json()["status"] != "done" and time.time() < deadline:
            time.sleep(0.5)
        assert c.get(f"{url}/v1/studies/{a}").json()["status"] == "done"
        assert c.get(f"{url}/v1/studies/{b}").json()["status"] == "done"
        assert c.get(f"{url}/v1/studies/{d}").json()["status"] == "cancelled"
        assert app.state.runner.peak_running == 1
        with ThreadPoolExecutor(12) as ex:
            codes = list(ex.map(lambda _: httpx.get(f"{url}/v1/studies/{a}/figures/data.png", headers=H,
                                                    timeout=120).status_code, range(12)))
        assert codes == [200] * 12
        assert c.delete(f"{url}/v1/studies/{b}").status_code == 204
        assert c.get(f"{url}/v1/studies/{b}").status_code == 404
        assert not (root / "studies" / b).exists()


def test_cancel_survives_sigkill_and_restart(tmp_path):
    """Cancel, SIGKILL the whole service, restart: the study stays cancelled and is never relaunched."""
    root = tmp_path / "svc"
    with ServiceProcess(root) as svc:
        studies = f"{svc.url}/v1/studies"
        with httpx.Client(timeout=60, headers=H) as c:
            sid = c.post(studies, json=dict(SPEC, seed=21)).json()["id"]
            while c.get(f"{studies}/{sid}").json()["status"] != "running":
                time.sleep(0.2)
            assert c.post(f"{studies}/{sid}/cancel", json={}).json()["status"] == "cancelled"
        svc.kill_and_restart()
        time.sleep(3)
        with httpx.Client(timeout=60, headers=H) as c:
            st = c.get(f"{studies}/{sid}").json()
        assert st["status"] == "cancelled"
        log = (root / "studies" / sid / "driver.log").read_text()
        assert log.count("resuming study") <= 1  # the driver was never launched again
        # and the store refuses a manual resume
        r = subprocess.run([sys.executable, "-m", "ardflow.service.cli", "resume", str(root / "studies" / sid / "store")],
                           cwd=ROOT, capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and "cancelled" in r.stderr


def test_cancel_frees_a_worker_busy_inside_a_task(hostile, tmp_path):
    """A study whose every likelihood takes seconds (the reference data at 2000 sub-steps): its start
    optimisation keeps a worker busy for many minutes inside one task. Cancelled, the task itself stops
    (the target reads the study's cancel event every 2 s) and the workers are free within the grace period."""
    _, _, _, dc = hostile
    port = free_port()
    app = create_app(Settings(root=tmp_path, token=TOKEN, max_running=1, cancel_grace_s=5.0), dc)
    slow = {"name": "slow", "data": {"generator": "reference", "seed": 1},
            "models": [{"model": "M2true", "substeps": 2000, "priors": {
                "B": {"kind": "lognormal", "median": 0.2, "cov": 50}, "a1": {"kind": "uniform", "low": -2, "high": 0},
                "a2": {"kind": "uniform", "low": -2, "high": 0}, "a3": {"kind": "uniform", "low": -250, "high": 250},
                "a4": {"kind": "uniform", "low": -1000, "high": 0},
                "sigma": {"kind": "lognormal", "median": 0.002, "cov": 50}}}],
            "sampler": {"n_chains": 2, "round_size": 50, "n_stationary": 100, "n_proposal": 100, "start_maxfev": 400,
                        "max_burnin_rounds": 5},
            "maximiser": {"max_trials": 2}, "seed": 1}
    with Server(app, port), httpx.Client(timeout=60, headers=H) as c:
        base = f"http://127.0.0.1:{port}/v1"
        r = c.post(f"{base}/studies", json=slow)
        assert r.status_code == 202, r.text
        sid = r.json()["id"]
        deadline = time.time() + 120
        while not any(dc.processing().values()) and time.time() < deadline:
            time.sleep(0.5)
        assert any(dc.processing().values()), "the study never started a task"
        time.sleep(3)
        t0 = time.time()
        assert c.post(f"{base}/studies/{sid}/cancel", json={}).json()["status"] == "cancelled"
        def busy():  # tasks a worker thread is still executing (the scheduler forgets a dead client's at once)
            return sum(dc.run(lambda dask_worker: len(dask_worker.state.executing)).values())

        while busy() and time.time() - t0 < 30:
            time.sleep(0.25)
        freed = time.time() - t0
        assert not busy()
        assert freed < 5.0 + 2.0 + 3.0, freed  # grace period + one check interval + slack
        assert c.get(f"{base}/studies/{sid}").json()["status"] == "cancelled"
        app.state.runner.stop()


def test_active_studies_are_limited_per_token(hostile, tmp_path):
    _, _, _, dc = hostile
    port = free_port()
    app = create_app(Settings(root=tmp_path, tokens={"alice": "tok-a", "bob": "tok-b"}, max_running=1,
                              max_active_per_token=1), dc)
    with Server(app, port), httpx.Client(timeout=60) as c:
        base = f"http://127.0.0.1:{port}/v1"
        first = c.post(f"{base}/studies", json=dict(SPEC, seed=31), headers={"X-API-Token": "tok-a"})
        again = c.post(f"{base}/studies", json=dict(SPEC, seed=32), headers={"X-API-Token": "tok-a"})
        other = c.post(f"{base}/studies", json=dict(SPEC, seed=33), headers={"X-API-Token": "tok-b"})
        assert first.status_code == 202 and other.status_code == 202
        assert again.status_code == 429 and "per token" in again.json()["detail"]
        assert c.get(f"{base}/studies", headers={"X-API-Token": "nope"}).status_code == 401
        for r in (first, other):
            c.post(f"{base}/studies/{r.json()['id']}/cancel", headers={"X-API-Token": "tok-a"}, json={})
        app.state.runner.stop()


def test_cross_site_changes_with_the_cookie_are_refused(hostile):
    """The page's sign-in cookie with a foreign Origin (another site, ``null``, another port of this host) or a
    cross-site Sec-Fetch-Site, or with neither header, cannot cancel, submit or sign out; from the page's own
    origin it can; a token header is not a cookie and is not checked."""
    url, _, _, _ = hostile
    host = url.split("://")[1]
    with httpx.Client(timeout=60) as c:
        sid = c.post(f"{url}/v1/studies", json=dict(SPEC, seed=21), headers=H).json()["id"]
        r = c.post(f"{url}/v1/session", json={"token": TOKEN}, headers={"Origin": url})
        assert r.status_code in (200, 204), r.text
        cookie = {"Cookie": f"ardflow_token={c.cookies.get('ardflow_token')}"}
        c.cookies.clear()
        J = {"Content-Type": "application/json"}
        foreign = [{"Origin": "http://evil.example"}, {"Origin": "null"},
                   {"Origin": f"http://127.0.0.1:{int(host.split(':')[1]) + 1}"},
                   {"Origin": url, "Sec-Fetch-Site": "cross-site"}, {"Sec-Fetch-Site": "same-site"}, {}]
        for h in foreign:
            for method, path, body in (("POST", f"studies/{sid}/cancel", "{}"),
                                       ("POST", "studies", json.dumps(dict(SPEC, seed=22))),
                                       ("DELETE", "session", None)):
                r = c.request(method, f"{url}/v1/{path}", headers={**cookie, **J, **h}, content=body)
                assert r.status_code == 403 and "cross-site" in r.json()["detail"], (h, method, path, r.text)
        assert c.get(f"{url}/v1/studies/{sid}", headers=H).json()["status"] not in ("cancelled",)
        # the page itself: same origin
        r = c.post(f"{url}/v1/studies/{sid}/cancel", headers={**cookie, **J, "Origin": url,
                                                               "Sec-Fetch-Site": "same-origin"}, content="{}")
        assert r.status_code == 200 and r.json()["status"] == "cancelled", r.text
        # a token header from anywhere: not forgeable cross-site, so not checked
        other = c.post(f"{url}/v1/studies", json=dict(SPEC, seed=23), headers=H).json()["id"]
        r = c.post(f"{url}/v1/studies/{other}/cancel", headers={**H, **J, "Origin": "http://evil.example"},
                   content="{}")
        assert r.status_code == 200


def test_every_post_declares_json_and_the_host_header_is_parsed_strictly(hostile):
    url, _, _, _ = hostile
    with httpx.Client(timeout=60) as c:
        r = c.post(f"{url}/v1/studies/nope-1/cancel", headers=H)  # an empty body, no Content-Type
        assert r.status_code == 415 and "application/json" in r.json()["detail"]
        for bad in ("127.0.0.1:1@evil.example", "127.0.0.1 evil.example", "127.0.0.1:", "evil.example",
                    "127.0.0.1:80:80"):
            r = c.get(f"{url}/v1/health", headers={"Host": bad})
            assert r.status_code == 400, (bad, r.status_code)
        assert c.get(f"{url}/v1/health", headers={"Host": "localhost:1234"}).status_code == 200


def test_damaged_studies_are_listed_readable_as_errors_and_deletable(tmp_path):
    """A truncated meta.json, a meta.json that is not an object, a garbage store zarr.json: the listing
    still answers, each such study is ``damaged`` with a reason that names no server path, its results are a
    409 that says so, it can be deleted; a restarted service lists them too."""
    root = tmp_path / "svc"
    with served(root, max_running=1) as (url, app, dc):
        with httpx.Client(timeout=60, headers=H) as c:
            ids = [c.post(f"{url}/v1/studies", json=dict(SPEC, seed=40 + i)).json()["id"] for i in range(4)]
            for sid in ids:
                c.post(f"{url}/v1/studies/{sid}/cancel", json={})
            d = root / "studies"
            # the first one ran (max_running 1): it stays intact; the others never started
            (d / ids[1] / "meta.json").write_text('{"id": "x", "na')
            (d / ids[2] / "meta.json").write_text("[1, 2]")
            (d / ids[3] / "store" / "zarr.json").write_text("\x00garbage{")
            time.sleep(0.3)  # past the status cache's lifetime
            r = c.get(f"{url}/v1/studies")
            assert r.status_code == 200, r.text
            st = {s["id"]: s for s in r.json()}
            for sid in ids[1:]:
                assert st[sid]["status"] == "damaged" and st[sid]["error"], st[sid]
                assert str(root) not in st[sid]["error"] and "/" not in st[sid]["error"], st[sid]["error"]
                one = c.get(f"{url}/v1/studies/{sid}")
                assert one.status_code == 200 and one.json()["status"] == "damaged"
                for path in ("summary", "posterior/quad", "figures/evidence.png", "report/report.html", "events"):
                    r = c.get(f"{url}/v1/studies/{sid}/{path}")
                    assert r.status_code == 409 and "damaged" in r.json()["detail"], (path, r.status_code, r.text)
            assert st[ids[0]]["status"] == "cancelled"
            assert c.delete(f"{url}/v1/studies/{ids[1]}").status_code == 204
    # a restart with the damaged files: the service starts and lists them
    with served(root, max_running=1) as (url, app, dc):
        with httpx.Client(timeout=60, headers=H) as c:
            st = {s["id"]: s["status"] for s in c.get(f"{url}/v1/studies").json()}
            assert ids[1] not in st and st[ids[2]] == st[ids[3]] == "damaged" and st[ids[0]] == "cancelled"
            for sid in ids[2:]:
                assert c.delete(f"{url}/v1/studies/{sid}").status_code == 204


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    status = Path(f"/proc/{pid}/status")
    return not (status.exists() and "\nState:\tZ" in status.read_text())


def test_a_killed_service_takes_its_driver_along_and_files_are_private(tmp_path):
    """SIGKILL of the API process alone (its driver and cluster survive in the group): the driver dies with
    it, the restarted service resumes the study with one driver, and every file under the root is the
    service user's alone (0600, folders 0700)."""
    import signal
    import stat

    root = tmp_path / "svc"
    with ServiceProcess(root) as svc:
        studies = f"{svc.url}/v1/studies"
        with httpx.Client(timeout=60, headers=H) as c:
            sid = c.post(studies, json=dict(SPEC, seed=31)).json()["id"]
            lock = root / "studies" / sid / "store" / "DRIVER.lock"
            deadline = time.time() + 120
            while not (lock.exists() and lock.read_text().strip()) and time.time() < deadline:
                time.sleep(0.2)
            driver = int(lock.read_text())
        os.kill(svc.p.pid, signal.SIGKILL)  # the API process only
        svc.p.wait()
        deadline = time.time() + 20
        while _alive(driver) and time.time() < deadline:
            time.sleep(0.2)
        assert not _alive(driver), "the driver outlived the service"
        svc.kill_and_restart()
        with httpx.Client(timeout=60, headers=H) as c:
            deadline = time.time() + 300
            while c.get(f"{studies}/{sid}").json()["status"] not in ("done", "failed") and time.time() < deadline:
                time.sleep(0.5)
            assert c.get(f"{studies}/{sid}").json()["status"] == "done"
    loose = [(str(p.relative_to(root)), oct(p.stat().st_mode & 0o777)) for p in [root, *root.rglob("*")]
             if not p.is_symlink() and p.stat().st_mode & (stat.S_IRWXG | stat.S_IRWXO)]
    assert not loose, loose[:10]


def test_a_second_driver_on_one_store_is_refused(tmp_path):
    from ardflow.ardcore.selection.spec import load_spec
    from ardflow.workers.graph import prepare_store

    store = prepare_store(load_spec(ROOT / "tests" / "workers" / "small_study.json"), tmp_path / "st")
    with store.driver_lock():
        r = subprocess.run([sys.executable, "-m", "ardflow.service.cli", "resume", str(tmp_path / "st"),
                            "--workers", "1"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "another driver is running this study" in r.stderr, r.stderr[-2000:]
    assert "Traceback" not in r.stderr


def test_a_burst_of_submissions_cannot_pass_the_limits(hostile, tmp_path):
    """30 parallel submissions from one token against a limit of 5, and from two tokens against a queue of
    8: never more admitted than the limits, whatever the interleaving."""
    _, _, _, dc = hostile
    port = free_port()
    app = create_app(Settings(root=tmp_path, tokens={"alice": "tok-a", "bob": "tok-b"}, max_running=1,
                              max_active_per_token=5, max_queued=8), dc)
    with Server(app, port), httpx.Client(timeout=120) as c:
        base = f"http://127.0.0.1:{port}/v1"

        def submit(i, tok):
            return c.post(f"{base}/studies", json=dict(SPEC, seed=100 + i), headers={"X-API-Token": tok})

        with ThreadPoolExecutor(30) as ex:
            answers = list(ex.map(lambda i: submit(i, "tok-a"), range(30)))
        ok = [r for r in answers if r.status_code == 202]
        assert len(ok) == 5 and all(r.status_code == 429 for r in answers if r.status_code != 202)
        waiting = len(app.state.runner.queue)  # alice's: one runs, the others wait
        with ThreadPoolExecutor(30) as ex:
            answers = list(ex.map(lambda i: submit(100 + i, "tok-b"), range(30)))
        ok_b = [r for r in answers if r.status_code == 202]
        # bob's own limit is 5 too, but the queue holds 8 at most
        assert len(ok_b) == min(5, 8 - waiting) and len(app.state.runner.queue) <= 8
        for r in ok + ok_b:
            c.post(f"{base}/studies/{r.json()['id']}/cancel", headers={"X-API-Token": "tok-a"}, json={})
        app.state.runner.stop()


def test_studies_belong_to_the_token_that_made_them(hostile, tmp_path):
    """Two users and an admin: a user lists, reads and acts on their own studies only (another's answers 404,
    as for no study at all); the admin sees and acts on all."""
    _, _, _, dc = hostile
    port = free_port()
    app = create_app(Settings(root=tmp_path, tokens={"alice": "tok-a", "bob": "tok-b", "admin": "tok-root"},
                              max_running=1), dc)
    A, B, R = ({"X-API-Token": t} for t in ("tok-a", "tok-b", "tok-root"))
    with Server(app, port), httpx.Client(timeout=60) as c:
        base = f"http://127.0.0.1:{port}/v1"
        a = c.post(f"{base}/studies", json=dict(SPEC, seed=51), headers=A).json()["id"]
        b = c.post(f"{base}/studies", json=dict(SPEC, seed=52), headers=B).json()["id"]
        assert [s["id"] for s in c.get(f"{base}/studies", headers=A).json()] == [a]
        assert [s["id"] for s in c.get(f"{base}/studies", headers=B).json()] == [b]
        assert {s["id"] for s in c.get(f"{base}/studies", headers=R).json()} == {a, b}
        # paged, newest first
        assert [s["id"] for s in c.get(f"{base}/studies?limit=1", headers=R).json()] == [b]
        assert [s["id"] for s in c.get(f"{base}/studies?limit=1&offset=1", headers=R).json()] == [a]
        for method, path in (("GET", ""), ("GET", "/summary"), ("GET", "/events"), ("GET", "/figures/evidence.png"),
                             ("GET", "/posterior/quad"), ("POST", "/cancel"), ("DELETE", "")):
            r = c.request(method, f"{base}/studies/{a}{path}", headers=B, json={} if method == "POST" else None)
            assert r.status_code == 404 and "no study" in r.json()["detail"], (method, path, r.status_code)
        assert c.get(f"{base}/studies/{a}", headers=A).status_code == 200
        # the dashboard (and with it the scheduler's address) is the operator's, not a user's
        assert c.get(f"{base}/dashboard", headers=A).json()["url"] is None
        assert c.get(f"{base}/dashboard", headers=R).json()["url"]
        # data sets are owned too: bob cannot study alice's upload (as for none), alice and the admin can
        csv = b"t,y\n" + b"".join(f"{i},{i % 3}\n".encode() for i in range(30))
        did = c.post(f"{base}/datasets", content=csv, headers={**A, "Content-Type": "text/csv"}).json()["id"]
        on = dict(SPEC, seed=53, data={"dataset": did})
        r = c.post(f"{base}/studies", json=on, headers=B)
        assert r.status_code == 422 and "no uploaded data set" in r.json()["detail"], r.text
        assert "no uploaded data set" not in c.post(f"{base}/studies", json=on, headers=R).text
        assert "no uploaded data set" not in c.post(f"{base}/studies", json=dict(on, seed=54), headers=A).text
        assert c.post(f"{base}/studies/{a}/cancel", headers=R, json={}).json()["status"] == "cancelled"
        assert c.post(f"{base}/studies/{b}/cancel", headers=B, json={}).json()["status"] == "cancelled"
        app.state.runner.stop()


def test_data_and_priors_no_model_can_use_are_refused_at_submit(hostile):
    """A short CSV row is refused at upload; an input with a gap, an observed column with no value and an
    improper prior are refused at submit (422 naming the model and the column or prior), never inside a
    worker later."""
    url, root, _, _ = hostile
    v1 = f"{url}/v1"
    C = dict(H, **{"Content-Type": "text/csv"})

    def upload(rows):
        return httpx.post(f"{v1}/datasets", headers=C, content=("t,y,x\n" + rows).encode(), timeout=60)

    r = upload("".join(f"{i},{i},{i}\n" for i in range(30)) + "30,1\n")
    assert r.status_code == 422 and "row 32 has 2 cells" in r.json()["detail"], r.text
    gap = upload("".join(f"{i},{i % 3},{'' if i == 7 else i}\n" for i in range(30))).json()["id"]
    blind = upload("".join(f"{i},,{i}\n" for i in range(30))).json()["id"]
    with httpx.Client(timeout=60, headers=H) as c:
        for did, words in ((gap, "input column 'x' has NaN at row 8"), (blind, "observed column 'y' has no values")):
            spec = dict(poly_study(), data={"dataset": did})
            r = c.post(f"{v1}/studies", json=spec)
            assert r.status_code == 422 and words in r.json()["detail"] and "poly" in r.json()["detail"], r.text
            assert str(root) not in r.text
        flat = poly_study()
        flat["models"][0]["priors"]["a0"] = {"kind": "flat"}
        r = c.post(f"{v1}/studies", json=flat)
        assert r.status_code == 422 and "priors.a0" in r.text and "improper" in r.text, r.text


def test_slow_headers_are_cut_off(tmp_path):
    """Connections sending their headers a byte a second are closed after the header deadline (10 s by
    default), while the service keeps answering others."""
    import socket

    with ServiceProcess(tmp_path / "svc") as svc:
        port = int(svc.url.rsplit(":", 1)[1])
        socks = []
        for _ in range(20):
            s = socket.create_connection(("127.0.0.1", port))
            s.sendall(b"GET /v1/health HTTP/1.1\r\nHo")
            socks.append(s)
        t0, closed = time.time(), set()
        while len(closed) < len(socks) and time.time() - t0 < 25:
            for i, s in enumerate(socks):
                if i in closed:
                    continue
                try:
                    s.sendall(b"s")
                    s.settimeout(0.01)
                    if s.recv(1) == b"":
                        closed.add(i)
                except (BlockingIOError, socket.timeout):
                    pass
                except OSError:
                    closed.add(i)
            assert httpx.get(f"{svc.url}/v1/health", timeout=5).status_code == 200
            time.sleep(1.0)
        elapsed = time.time() - t0
        for s in socks:
            s.close()
        assert len(closed) == len(socks) and 8 <= elapsed <= 20, (len(closed), elapsed)


def test_a_json_body_with_a_repeated_key_is_refused(hostile):
    url, _, _, _ = hostile
    body = json.dumps(dict(SPEC, seed=61))[:-1] + ', "seed": 62}'
    r = httpx.post(f"{url}/v1/studies", content=body, headers={**H, "Content-Type": "application/json"}, timeout=60)
    assert r.status_code == 422 and "duplicate key 'seed'" in r.json()["detail"], r.text
    nested = json.dumps(dict(SPEC, seed=63)).replace('"n_chains": 3', '"n_chains": 3, "n_chains": 4')
    assert '"n_chains": 3, "n_chains": 4' in nested
    r = httpx.post(f"{url}/v1/studies", content=nested, headers={**H, "Content-Type": "application/json"}, timeout=60)
    assert r.status_code == 422 and "n_chains" in r.json()["detail"]


def test_diagnoses_are_jobs_like_studies(hostile, tmp_path):
    """A diagnosis takes a slot of --max-running like a study's driver (a study submitted meanwhile waits),
    it can be cancelled, and its study cannot be deleted under it."""
    from tests.ardcore.test_diagnose import duffing_free_decay, duffing_spec

    _, _, _, dc = hostile
    port = free_port()
    app = create_app(Settings(root=tmp_path, token=TOKEN, max_running=1), dc)
    rec = duffing_free_decay(-4.0, 3)
    csv = tmp_path / "est.csv"
    rec.slice(0, 1000).to_csv(csv)
    spec = duffing_spec().model_dump(mode="json", exclude_none=True)
    spec.update(name="osc", data={})
    with Server(app, port), Client(f"http://127.0.0.1:{port}", token=TOKEN) as c:
        sid = c.submit(spec, csv=csv)
        assert c.wait(sid, poll_s=0.3, timeout=300, progress=False)["status"] == "done"
        d = c.diagnose(sid, top_k=2, max_rounds=3, wait=False)
        model = d["model"]
        deadline = time.time() + 30
        while c.diagnosis(sid, model)["status"] != "running" and time.time() < deadline:
            time.sleep(0.1)
        assert c.diagnosis(sid, model)["status"] == "running"
        other = c.submit(dict(SPEC, seed=71))
        time.sleep(1.5)
        assert c.status(other)["status"] == "queued"  # the one slot is the diagnosis's
        with pytest.raises(APIError) as e:
            c._check(c.http.delete(f"/studies/{sid}"))
        assert e.value.status == 409 and "diagnosis" in e.value.message
        with pytest.raises(APIError) as e:
            c.diagnose(sid, model, wait=False)
        assert e.value.status == 409 and "already running" in e.value.message
        assert c.cancel_diagnosis(sid, model)["status"] == "cancelled"
        assert c.diagnosis(sid, model)["status"] == "cancelled"
        deadline = time.time() + 30
        while c.status(other)["status"] == "queued" and time.time() < deadline:
            time.sleep(0.2)
        assert c.status(other)["status"] in ("running", "done")  # the slot went to the waiting study
        c.cancel(other)
        c._check(c.http.delete(f"/studies/{sid}"))
        app.state.runner.stop()


def test_a_full_disk_is_a_507_and_a_failed_study_never_running(hostile, tmp_path, monkeypatch):
    """ENOSPC at the writes (simulated: the test runner has no tmpfs to fill): a submission and a cancel answer
    507 and leave nothing half-made; a study whose driver died and whose failure could not be written reads
    failed, not running."""
    import errno

    from ardflow.ardcore import jsonio
    from ardflow.service.api.registry import Registry
    from ardflow.workers.store import StudyStore

    _, _, _, dc = hostile
    port = free_port()
    app = create_app(Settings(root=tmp_path, token=TOKEN, max_running=1), dc)

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    with Server(app, port), httpx.Client(timeout=60, headers=H) as c:
        base = f"http://127.0.0.1:{port}/v1"
        # a study that runs for minutes: it must still be running when its driver is killed below
        sid = c.post(f"{base}/studies", json=dict(SPEC, seed=81, maximiser=dict(SPEC["maximiser"], max_trials=40),
                                                  sampler=dict(SPEC["sampler"], n_stationary=400_000))).json()["id"]
        with monkeypatch.context() as m:
            m.setattr(Registry, "write_meta", full)
            r = c.post(f"{base}/studies", json=dict(SPEC, seed=82))
            assert r.status_code == 507 and "disk is full" in r.json()["detail"], r.text
            assert sorted(p.name for p in (tmp_path / "studies").iterdir()) == [sid]  # nothing half-made
        # "running" is written just before the driver's process is started: wait for the process too (on a loaded
        # machine the test once reached the kill below first, a KeyError)
        deadline = time.time() + 60
        while (c.get(f"{base}/studies/{sid}").json()["status"] != "running"
               or sid not in app.state.runner.procs) and time.time() < deadline:
            time.sleep(0.2)
        with monkeypatch.context() as m:
            m.setattr(jsonio, "atomic_write_text", full)
            r = c.post(f"{base}/studies/{sid}/cancel", json={})
            assert r.status_code == 507 and "disk is full" in r.json()["detail"], r.text
        with monkeypatch.context() as m:
            real = StudyStore.update_meta
            m.setattr(StudyStore, "update_meta", lambda self, **kw: full() if kw.get("status") == "failed"
                      else real(self, **kw))
            app.state.runner.procs[sid].kill()  # the driver dies (as of ENOSPC) and its failure cannot be written
            deadline = time.time() + 30
            while c.get(f"{base}/studies/{sid}").json()["status"] == "running" and time.time() < deadline:
                time.sleep(0.2)
            st = c.get(f"{base}/studies/{sid}").json()
            assert st["status"] == "failed" and "could not be recorded" in st["error"], st
        app.state.runner.stop()


def test_delete_right_after_done_and_a_linked_data_set(hostile, tmp_path):
    """A study deleted the moment it reads done is deleted (its driver is waited for, never 'cancel it
    first' while cancel says 'already done'); a data set id that is a symbolic link placed among the uploads
    is no data set, and nothing of the linked file is echoed."""
    url, root, _, _ = hostile
    with httpx.Client(timeout=120, headers=H) as c:
        sid = c.post(f"{url}/v1/studies", json=dict(SPEC, seed=91)).json()["id"]
        deadline = time.time() + 300
        while c.get(f"{url}/v1/studies/{sid}").json()["status"] != "done" and time.time() < deadline:
            time.sleep(0.05)
        r = c.delete(f"{url}/v1/studies/{sid}")
        assert r.status_code == 204, r.text
        secret = tmp_path / "secret.csv"
        secret.write_text("t,y\nSECRET-LINE,1\n")
        did = "ab" * 8
        (root / "datasets" / f"{did}.csv").symlink_to(secret)
        r = c.post(f"{url}/v1/studies", json=dict(SPEC, seed=92, data={"dataset": did}))
        assert r.status_code == 422 and "no uploaded data set" in r.text and "SECRET" not in r.text, r.text
