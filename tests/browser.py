"""Open a page in headless Chromium (Debian's /usr/bin/chromium, driven by Playwright) with the network cut off."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

FLAGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking",
         "--disable-component-update", "--disable-sync"]


def chromium_path() -> str:
    """The Chromium binary; a missing browser fails the test under CI (``.ci/run`` installs it) and skips locally."""
    exe = os.environ.get("ARDFLOW_CHROMIUM") or shutil.which("chromium") or shutil.which("chromium-browser")
    if not exe:
        msg = "headless Chromium not installed (apt-get install chromium)"
        if os.environ.get("CI"):
            pytest.fail(msg)
        pytest.skip(msg)
    return exe


def load_page(path: Path) -> dict:
    """Load ``path`` from file://, block every non-file request, and report what each image did.

    Returns
    -------
    dict
        ``images``: list of {src, complete, width}; ``blocked``: URLs the page tried to fetch off disk;
        ``failed``: requests that failed; ``errors``: uncaught page errors.
    """
    sync_api = pytest.importorskip("playwright.sync_api")
    out = {"blocked": [], "failed": [], "errors": []}
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium_path(), headless=True, args=FLAGS)
        try:
            page = browser.new_page()

            def route(r):
                if r.request.url.startswith("file://"):
                    r.continue_()
                else:
                    out["blocked"].append(r.request.url)
                    r.abort()

            page.route("**/*", route)
            page.on("requestfailed", lambda r: out["failed"].append(r.url))
            page.on("pageerror", lambda e: out["errors"].append(str(e)))
            page.goto(Path(path).resolve().as_uri(), wait_until="load")
            out["images"] = page.eval_on_selector_all(
                "img", "els => els.map(e => ({src: e.getAttribute('src'), complete: e.complete, "
                       "width: e.naturalWidth}))")
        finally:
            browser.close()
    return out
