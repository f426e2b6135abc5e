"""``ardflow`` commands of the service: serve the REST API, and its client (submit, status, fetch)."""

from __future__ import annotations

import json
import signal
import sys
import time
from pathlib import Path

import numpy as np
from ardflow.workers.cluster import ClusterClient

from ardflow.service.commands.progress import print_table


def _is_loopback(host: str) -> bool:
    import ipaddress

    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def cmd_serve(a) -> int:
    import os
    import secrets

    import uvicorn
    from ardflow.ardcore.errors import SpecError

    from ardflow.service.api.schemas import Settings
    from ardflow.service.api.app import create_app
    from ardflow.service.commands.deadline import with_header_deadline

    # everything under the root (studies, uploads, logs, reports) is the service user's alone: 0700/0600 at
    # creation, in this process and in the drivers it starts
    os.umask(0o077)
    root = Path(a.root)
    root.mkdir(parents=True, exist_ok=True)
    os.chmod(root, 0o700)
    token = a.token or os.environ.get("ARDFLOW_TOKEN")
    loopback = _is_loopback(a.host)
    if a.insecure_no_auth and not loopback:
        raise SpecError(f"--insecure-no-auth is only allowed on a loopback address, not {a.host}")
    if token is None and not a.insecure_no_auth:
        # a token always, unless asked otherwise on loopback: any local process or web page could talk to us
        tf = root / "token"
        token = tf.read_text().strip() if tf.exists() else secrets.token_urlsafe(24)
        # readable by the owner only from the moment it exists (never written first, restricted after)
        fd = os.open(tf, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        os.fchmod(fd, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(token)
        print(f"[ardflow] API token required (X-API-Token or Bearer); it is in {tf} "
              f"(export ARDFLOW_TOKEN=$(cat {tf}))", flush=True)
    # a page in the user's browser may not reach a loopback service under another name (DNS rebinding)
    hosts = ["127.0.0.1", "localhost", "[::1]", "::1"] if loopback else None
    # the API's event loop gets the GIL back every 1 ms (not 5) from the threads that parse submissions
    sys.setswitchinterval(0.001)
    with ClusterClient(a.scheduler, a.workers, scheduler_process=True) as client:
        tokens = json.loads(Path(a.tokens_file).read_text()) if a.tokens_file else None
        app = create_app(Settings(root=root, token=token, tokens=tokens, max_body_mb=a.max_body_mb,
                                  max_running=a.max_running, allowed_hosts=hosts), client)
        print(f"[ardflow] API on http://{a.host}:{a.port}/v1 (OpenAPI: /docs), registry {root.resolve()}", flush=True)
        # uvicorn stops serving on SIGTERM, then raises the signal again: with this handler that ends in the
        # `finally` and the cluster's exit below (stopping scheduler and workers), not in a bare kill
        signal.signal(signal.SIGTERM, _stop)
        try:
            # X-Forwarded-* are believed only from the proxies named (never by default, loopback included)
            uvicorn.run(app, host=a.host, port=a.port, log_level="warning",
                        proxy_headers=bool(a.forwarded_allow_ips), forwarded_allow_ips=a.forwarded_allow_ips or "",
                        limit_concurrency=a.max_connections, timeout_keep_alive=5,
                        http=with_header_deadline(a.header_timeout))
        finally:
            app.state.runner.stop()
            app.state.close()
    print("[ardflow] service stopped (its scheduler, workers and drivers with it)", flush=True)
    return 0


def _stop(signum, frame):
    """SIGTERM: leave by the normal exits (every ``finally`` and context manager runs)."""
    raise SystemExit(0)


def _client(a):
    import os

    from ardflow.service.client import Client

    a.url = a.url or os.environ.get("ARDFLOW_URL") or "http://127.0.0.1:8000"
    token = a.token or os.environ.get("ARDFLOW_TOKEN")
    if token is None:
        found = token_file()
        token = found.read_text().strip() if found else None
    return Client(a.url, token=token)


def token_file() -> Path | None:
    """The token `ardflow serve` wrote with its default ``--root`` (``runs/service/token``), looked for in this
    directory and each one above it (a user in a subfolder of the project finds it too), or None."""
    here = Path.cwd().resolve()
    for d in (here, *here.parents):
        f = d / "runs" / "service" / "token"
        if f.is_file():
            return f
    return None


def cmd_submit(a) -> int:
    from ardflow.service.client import APIError

    with _client(a) as c:
        try:
            sid = c.submit(a.spec, csv=a.csv)
            print(sid, flush=True)
            if a.wait:
                done = c.wait(sid)
                if "models" in done and isinstance(done["models"], list):
                    print_table(done)
        except APIError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    return 0


def cmd_status(a) -> int:
    from ardflow.service.client import APIError

    with _client(a) as c:
        try:
            st = c.status(a.id) if a.id else c.studies()
            rows = [st] if a.id else st
            best = {r["id"]: _best(c, r) for r in rows if r["status"] == "done"}
            if getattr(a, "json", False):
                # what the table shows, as data: each study's models and, when done, its best model
                for r in rows:
                    if not r.get("models") and r["status"] != "damaged":
                        r["models"] = c.status(r["id"]).get("models", {})
                    if r["id"] in best:
                        r["best_model"], r["probability"] = best[r["id"]]
                print(json.dumps(st, indent=2))
                return 0
        except APIError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    print(status_table(rows, {k: _best_text(*v) for k, v in best.items()}, time.time()))
    return 0


def _best(c, row: dict) -> tuple[str | None, float | None]:
    """A finished study's best model and that model's probability (None, None when its summary cannot be read:
    a damaged study is listed, not a failed listing)."""
    from ardflow.service.client import APIError

    try:
        s = c.summary(row["id"])
    except APIError:
        return None, None
    p = {m["name"]: m.get("probability") for m in s.get("models", [])}
    b = s.get("best_model")
    return b, p.get(b)


def _best_text(model, probability) -> str:
    """'M2 (P 1.00)'."""
    return f"{model} (P {probability:.2f})" if probability is not None else ("-" if model is None else str(model))


def _ago(seconds: float) -> str:
    s = max(0, int(seconds))
    return (f"{s} s" if s < 60 else f"{s // 60} min" if s < 3600 else f"{s // 3600} h {s % 3600 // 60} min") + " ago"


def status_table(rows: list[dict], best: dict, now: float) -> str:
    """Studies as a table a person reads: id, state, best model with its probability (when done), when it
    was submitted, how long its longest model has run while it runs (no time left is promised: the search
    stops when the evidence stops rising), and its error."""
    head = f"{'study':<28s} {'state':<10s} {'best model':<16s} {'submitted':<16s} {'running':<10s}"
    out = [head]
    for r in rows:
        ran = [m.get("elapsed_s") for m in (r.get("models") or {}).values() if m.get("elapsed_s")]
        eta = f"{max(ran) / 60:.0f} min" if ran and r["status"] == "running" else "-"
        out.append(f"{r['id']:<28s} {r['status']:<10s} {best.get(r['id'], '-'):<16s} "
                   f"{_ago(now - r.get('created', now)):<16s} {eta:<10s}"
                   + (f" {r['error']}" if r.get("error") else ""))
    return "\n".join(out) if rows else "no studies"


def cmd_fetch(a) -> int:
    from ardflow.service.client import APIError

    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    with _client(a) as c:
        try:
            summary = c.summary(a.id)
            (out / "summary.json").write_text(json.dumps(summary, indent=2))
            for r in summary["models"]:
                names, samples = c.posterior(a.id, r["name"])
                np.savez(out / f"posterior_{r['name']}.npz", names=np.array(names), samples=samples)
            for fig in ("data.png", "evidence.png"):
                (out / fig).write_bytes(c.figure(a.id, fig))
        except APIError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    print(f"fetched {a.id} into {out.resolve()}")
    return 0
