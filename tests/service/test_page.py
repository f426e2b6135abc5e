"""The study page in headless Chromium against the real service (``ardflow serve`` over HTTP):
sign in, submit a spec and a CSV through the form, watch the live progress reach done, open the report."""

from __future__ import annotations

import json
import re
import os
import signal

import httpx
import pytest

from ardflow.ardcore.selection.spec import DataSpec
from tests.browser import FLAGS, chromium_path
from tests.service.test_api import SPEC, TOKEN, free_port, start_service


@pytest.fixture
def service(tmp_path):
    port = free_port()
    p = start_service(tmp_path / "svc", port)
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()


def _sign_in_and_submit(page, spec, csv) -> str:
    """Sign in with the token, submit ``spec`` and ``csv`` through the page's form; the new study's id."""
    page.fill("#token", TOKEN)
    page.click("#signin button")
    page.wait_for_selector("#main:not([hidden])")
    page.set_input_files("#spec", str(spec))
    page.set_input_files("#csv", [str(c) for c in csv] if isinstance(csv, list) else str(csv))
    page.click("#submit button")
    page.wait_for_selector("#msg:has-text('submitted')", timeout=60_000)
    return page.inner_text("#msg").split("submitted: ")[1].strip()


def test_page_headers_and_session(service):
    r = httpx.get(service + "/")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
    csp = r.headers["content-security-policy"]
    assert "script-src 'nonce-" in csp and "__NONCE__" not in r.text
    assert "http://" not in r.text.replace(service, "") and "https://" not in r.text  # no CDN
    # the API docs load nothing from another origin (Swagger UI from the installed package)
    docs = httpx.get(service + "/docs")
    assert docs.status_code == 200 and "cdn" not in docs.text.lower()
    for src in re.findall(r"(?:src|href)=['\"]([^'\"]+)['\"]", docs.text):
        assert src.startswith("/"), src
        assert httpx.get(service + src).status_code == 200, src
    # every answer, JSON, HTML or an error, is never sniffed and never framed by another origin
    for path in ("/", "/v1/health", "/v1/studies", "/v1/no-such-route"):
        h = httpx.get(service + path).headers
        assert h["x-content-type-options"] == "nosniff" and h["x-frame-options"] == "DENY", (path, h)
        assert "frame-ancestors 'none'" in h["content-security-policy"], (path, h)
    with httpx.Client(base_url=service) as c:
        assert c.get("/v1/studies").status_code == 401
        assert c.post("/v1/session", json={"token": "wrong"}).status_code == 401
        # a foreign page cannot sign a browser in (login CSRF)
        r = c.post("/v1/session", json={"token": TOKEN}, headers={"Origin": "http://evil.example"})
        assert r.status_code == 403 and "set-cookie" not in r.headers
        r = c.post("/v1/session", json={"token": TOKEN})
        assert r.status_code == 204
        cookie = r.headers["set-cookie"].lower()
        assert "httponly" in cookie and "samesite=strict" in cookie
        session = c.cookies.get("ardflow_token")
        assert session and TOKEN not in r.headers["set-cookie"]  # the cookie is a session, not the token
        assert c.get("/v1/studies").status_code == 200  # the cookie authenticates
        assert c.delete("/v1/session").status_code == 403  # a cookie change without the page's Origin
        assert c.delete("/v1/session", headers={"Origin": service}).status_code == 204
        assert c.get("/v1/studies").status_code == 401
    # signing out revokes the session: its cookie, replayed, authenticates nothing
    assert httpx.get(service + "/v1/studies", cookies={"ardflow_token": session}).status_code == 401


def test_page_submit_watch_report(service, tmp_path):
    """Two records, one CSV each, submitted through the form: the study fits both, the report shows each."""
    sync_api = pytest.importorskip("playwright.sync_api")
    exe = chromium_path()
    data = DataSpec.model_validate(SPEC["data"]).load()
    half = len(data) // 2
    csv = [tmp_path / "first.csv", tmp_path / "second.csv"]
    data.slice(0, half).to_csv(csv[0])
    data.slice(half, None).to_csv(csv[1])
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps(dict(SPEC, name="pagetest")))
    errors: list[str] = []
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=exe, headless=True, args=FLAGS)
        try:
            page = browser.new_page()
            page.on("pageerror", lambda e: errors.append(str(e)))
            # nothing leaves the machine: only the service itself is reachable
            page.route("**/*", lambda r: r.continue_() if r.request.url.startswith(service) else r.abort())
            page.goto(service + "/")
            page.wait_for_selector("#signin:not([hidden])")
            page.fill("#token", "wrong")
            page.click("#signin button")
            page.wait_for_selector("#signin-msg:has-text('401')")
            sid = _sign_in_and_submit(page, spec, csv)
            row = f"tr[data-id='{sid}']"
            # live progress: per-model lines appear while it runs, then the status reaches done
            page.wait_for_selector(f"{row} .model", timeout=180_000)
            # the first study replaces the "no studies yet" line: no row is left that is not a study's
            assert page.locator("#studies tr:not([data-id])").count() == 0
            page.wait_for_selector(f"{row} td.status.done", timeout=300_000)
            assert page.locator(f"{row} .model").count() == 2
            assert "done" in page.inner_text(f"{row} .model >> nth=0")
            # each model's convergence, as the summary's ArviZ diagnostics say
            page.wait_for_selector(f"{row} .conv", timeout=30_000)
            lines = page.locator(f"{row} .conv").all_inner_texts()
            assert len(lines) == 2 and all("R-hat" in t and "ESS" in t for t in lines), lines
            with page.expect_popup() as pop:
                page.click(f"{row} a.report")
            report = pop.value
            report.wait_for_load_state("load")
            imgs = report.eval_on_selector_all("img", "els => els.map(e => e.naturalWidth)")
            assert imgs and all(w > 0 for w in imgs), imgs
            assert "pagetest" in report.content() or "quad" in report.content()
            assert "Convergence (ArviZ)" in report.content()
            # each record by its name (not its hash), with its own fit and its own prediction figure
            text = report.content()
            assert "first.csv (uploaded data set" in text and "second.csv (uploaded data set" in text
            assert "<h2>Records</h2>" in text and report.locator("img[src^='prediction_']").count() == 2
        finally:
            browser.close()
    assert not errors, errors
    # the study ran on the uploaded data set, not on the spec's generator
    with httpx.Client(base_url=service, headers={"X-API-Token": TOKEN}) as c:
        meta = c.get(f"/v1/studies/{sid}/summary").json()
        records = meta["spec"]["data"]
        assert len(records) == 2 and all(r.get("dataset") and not r.get("generator") for r in records)
        assert [r["name"] for r in records] == ["first.csv", "second.csv"]
        assert meta["data"]["n"] == len(data)


def test_page_submit_done_diagnose_reports_delete(service, tmp_path):
    """The whole job on the page: submit a spec and a CSV through the form, watch it to done, read its result
    (best model, P(M|d), kept and pruned terms), start a diagnosis with its options (model, rounds, held-out
    record) and watch it to its report, open both reports (served as HTML with their figures), delete; nothing
    on the way is raw JSON or an error page."""
    from tests.ardcore.test_diagnose import duffing_free_decay, duffing_spec

    sync_api = pytest.importorskip("playwright.sync_api")
    rec = duffing_free_decay(-4.0, 3)
    est, held = tmp_path / "est.csv", tmp_path / "held.csv"
    rec.slice(0, 1000).to_csv(est)
    rec.slice(1000, 1600).to_csv(held)
    spec = duffing_spec().model_dump(mode="json", exclude_none=True)
    spec.update(name="osc", data={})
    spec_file = tmp_path / "osc.json"
    spec_file.write_text(json.dumps(spec))
    errors: list[str] = []
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), headless=True, args=FLAGS)
        try:
            page = browser.new_page()
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.on("dialog", lambda d: d.accept())  # the delete confirmation
            page.route("**/*", lambda r: r.continue_() if r.request.url.startswith(service) else r.abort())
            page.goto(service + "/")
            sid = _sign_in_and_submit(page, spec_file, est)
            row = f"tr[data-id='{sid}']"
            page.wait_for_selector(f"{row} td.status.done", timeout=300_000)
            page.wait_for_selector(f"{row} .result", timeout=30_000)
            result = page.inner_text(f"{row} .result")
            assert "best model" in result and "P(M|d)" in result and "kept:" in result, result
            assert "about" not in page.inner_text(f"{row} .model >> nth=0")  # no ETA once done
            # the diagnosis's options: one round, the held-out part of the record for the free run
            page.fill(f"{row} .diag-rounds", "1")
            page.set_input_files(f"{row} .diag-test", str(held))
            page.click(f"{row} button.diagnose")
            page.wait_for_selector(f"{row} a.diagnosis-report", timeout=300_000)
            for link, must in ((f"{row} a.diagnosis-report", "Verdict"), (f"{row} a.report", "Convergence (ArviZ)")):
                with page.expect_popup() as pop:
                    page.click(link)
                rep = pop.value
                rep.wait_for_load_state("load")
                text = rep.inner_text("body")
                assert must in text and not text.lstrip().startswith("{"), text[:300]
                assert "Internal Server Error" not in text and "Traceback" not in text
                imgs = rep.eval_on_selector_all("img", "els => els.map(e => e.naturalWidth)")
                assert imgs and all(w > 0 for w in imgs), imgs
                rep.close()
            page.click(f"{row} button.delete")
            page.wait_for_selector(row, state="detached", timeout=30_000)
        finally:
            browser.close()
    assert not errors, errors
    with httpx.Client(base_url=service, headers={"X-API-Token": TOKEN}) as c:
        assert c.get(f"/v1/studies/{sid}").status_code == 404
