"""The ``ardflow`` command line.

Every user error is printed as one ``error: ...`` line with exit status 2;
tracebacks are for bugs only.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .progress import LiveProgress, _num, _print_table, print_progress  # noqa: F401


def _kv(items: list[str] | None, what: str) -> dict[str, str]:
    from ardflow.ardcore.errors import SpecError

    out = {}
    for it in items or []:
        if "=" not in it:
            raise SpecError(f"{what}: expected NAME=VALUE, got {it!r}")
        k, v = it.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def _floats(d: dict[str, str], what: str) -> dict[str, float]:
    from ardflow.ardcore.errors import SpecError

    out = {}
    for k, v in d.items():
        try:
            x = float(v)
        except ValueError:
            raise SpecError(f"{what} {k}: {v!r} is not a number") from None
        if not np.isfinite(x):
            raise SpecError(f"{what} {k}: must be finite, got {v!r}")
        out[k] = x
    return out


def _load_model(name_or_file: str):
    from ardflow.ardcore.errors import ModelError
    from ardflow.ardcore.library import BUILTINS, builtin
    from ardflow.ardcore.model import ModelSpec

    if name_or_file in BUILTINS:
        return builtin(name_or_file)
    p = Path(name_or_file)
    if p.suffix == ".json" and p.exists():
        try:
            return ModelSpec.model_validate_json(p.read_text())
        except ValueError as exc:
            raise ModelError(f"{p}: {exc}") from None
    raise ModelError(f"unknown model {name_or_file!r}: give a built-in name ({', '.join(BUILTINS)}) "
                     "or a model JSON file")


def _write_sidecar(path: Path, meta: dict) -> None:
    meta = {k: v for k, v in meta.items() if k != "theta_clean"}
    path.with_suffix(".json").write_text(json.dumps(meta, indent=2, default=float))


def cmd_simulate(a) -> int:
    from ardflow.ardcore.errors import SpecError
    from ardflow.ardcore.simulate import simulate_model, simulate_reference

    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    if a.model == "reference":
        ds = simulate_reference(a.seed)
    else:
        spec = _load_model(a.model)
        params = _floats(_kv(a.param, "--param"), "parameter")
        missing = [p for p in spec.free_parameters if p not in params]
        if missing:
            raise SpecError(f"--param: no value for {missing[0]!r} (parameters: {spec.free_parameters})")
        if a.n < 10 or not (a.dt > 0):
            raise SpecError("--n must be >= 10 and --dt > 0")
        t = np.arange(a.n) * a.dt
        inputs = {}
        rng = np.random.default_rng(a.seed + 1_000_003)
        for c in spec.inputs:
            from ardflow.ardcore.simulate import lowpass

            inputs[c] = a.input_std * lowpass(rng.standard_normal(a.n), 1.0 / a.dt, 0.2 / a.dt) * np.sqrt(5.0)
        ds = simulate_model(spec, params, t, a.seed, nsub=a.nsub, inputs=inputs)
    ds.to_csv(out)
    _write_sidecar(out, ds.meta)
    print(f"wrote {out} ({len(ds)} rows) and {out.with_suffix('.json')}")
    return 0


def cmd_loglik(a) -> int:
    from ardflow.ardcore.ekf import compile_model
    from ardflow.ardcore.errors import SpecError

    ds = _read_data(a)
    spec = _load_model(a.model)
    params = _floats(_kv(a.param, "--param"), "parameter")
    missing = [p for p in spec.free_parameters if p not in params]
    if missing:
        raise SpecError(f"--param: no value for {missing[0]!r} (parameters: {spec.free_parameters})")
    unknown = [p for p in params if p not in spec.free_parameters]
    if unknown:
        raise SpecError(f"--param: {unknown[0]!r} is not a free parameter of {spec.name}")
    cm = compile_model(spec)
    ll = cm.loglik(params, ds, substeps=a.substeps)
    print(json.dumps({"model": spec.name, "loglik": ll, "substeps": a.substeps or spec.substeps}))
    return 0


def _read_data(a):
    from ardflow.ardcore.data import read_dataset

    rename = _kv(getattr(a, "rename", None), "--rename")
    return read_dataset(a.data, fs=getattr(a, "fs", None), rename=rename)


def cmd_data(a) -> int:
    from ardflow.ardcore.data import read_columns

    if a.action == "check":
        ds = _read_data(a)
        info = {"rows": len(ds), "t0": float(ds.t[0]), "t1": float(ds.t[-1]),
                "columns": {k: {"nan": int(np.isnan(v).sum()), "min": float(np.nanmin(v)), "max": float(np.nanmax(v))}
                            for k, v in ds.columns.items()}}
        print(json.dumps(info, indent=2))
    else:  # convert
        cols = read_columns(a.data)
        from ardflow.ardcore.data import Dataset

        rename = _kv(a.rename, "--rename")
        for o, n in rename.items():
            cols[n] = cols.pop(o)
        t = cols.pop("t") if "t" in cols else np.arange(len(next(iter(cols.values())))) / (a.fs or 1.0)
        ds = Dataset(t, cols, {"source": str(a.data)})
        ds.to_csv(a.out)
        print(f"wrote {a.out} ({len(ds)} rows, columns t, {', '.join(cols)})")
    return 0


def cmd_models(a) -> int:
    from ardflow.ardcore.library import BUILTINS, builtin

    if a.name:
        print(_load_model(a.name).model_dump_json(indent=2))
    else:
        for n in BUILTINS:
            s = builtin(n)
            print(f"{n:26s} {s.description}")
    return 0


# the examples folder: beside the source folders in a checkout, package data (ardflow/examples) in a wheel
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def cmd_example(a) -> int:
    """List the example study specs, or write one out to start your own study from."""
    names = sorted(p.stem for p in EXAMPLES.glob("*.json"))
    if not a.name:
        for n in names:
            desc = json.loads((EXAMPLES / f"{n}.json").read_text()).get("description", "")
            print(f"{n:22s} {desc[:90]}")
        return 0
    if a.name not in names:
        raise SystemExit(f"error: no example {a.name!r} (examples: {', '.join(names)})")
    text = (EXAMPLES / f"{a.name}.json").read_text()
    if a.out:
        Path(a.out).write_text(text)
        print(f"wrote {a.out}")
    else:
        print(text)
    return 0


def cmd_demo(a) -> int:
    """The main job: the paper's Section 3.6 study (M1, M2, M3 with ARD) on an embedded LocalCluster."""
    from ardflow.ardcore.study import load_spec
    from ardflow.workers.graph import prepare_store
    from ardflow.workers.store import StudyStore

    spec_path = EXAMPLES / "sec36.json"
    spec = load_spec(spec_path)
    if a.full:
        spec = full_settings(spec)
    out = Path(a.out)
    store = StudyStore(out)
    t0 = time.perf_counter()
    status = store.meta.get("status") if store.exists() else None
    same = status is not None and store.meta.get("spec") == spec.model_dump(mode="json")
    if same and status == "done":
        print(f"[demo] already done: {out.resolve()} (delete it to run again)", flush=True)
    elif same:
        print(f"[demo] continuing the study in {out.resolve()}", flush=True)
        _run_on_dask(a, store)
    else:
        if status is not None:
            import shutil

            # a run of other settings (demo vs --full, an edited example) is kept, not overwritten
            old = out.with_name(out.name + ".previous")
            shutil.rmtree(old, ignore_errors=True)
            out.rename(old)
            print(f"[demo] {out} held a study with other settings; moved it to {old}", flush=True)
        print(f"[demo] Section 3.6 study ({spec_path.name}{', paper scale' if a.full else ', demo scale'}): "
              "M1, M2, M3 with ARD priors on a3..a6, on an embedded Dask cluster", flush=True)
        store = prepare_store(spec, out, base=spec_path.parent)
        _run_on_dask(a, store)
    summary = json.loads(store.read_text("summary.json"))
    _print_table(summary)
    from .paper import check_label, reference_checks

    print("\n[demo] checks against the paper (issue 'Main job'):")
    for c in reference_checks(summary, spec.true_values):
        print(f"  [{check_label(c)}] {c['check']}: {c['detail']}"
              + (f"\n      documented difference: {c['documented']}" if c.get("documented") else ""))
    print(f"\n[demo] store (zarr):  {out.resolve()}")
    print(f"[demo] summary:       {(out / 'summary.json').resolve()}")
    print(f"[demo] report:        {(out / 'report' / 'report.html').resolve()}")
    print(f"[demo] wall time:     {time.perf_counter() - t0:.0f} s")
    return 0


class _Cluster:
    """A client on an existing scheduler, or an embedded LocalCluster (workers = cores)."""

    def __init__(self, scheduler: str | None, workers: int | None):
        self.scheduler, self.workers = scheduler, workers

    def __enter__(self):
        import os

        from distributed import Client, LocalCluster

        if self.scheduler:
            self.cluster = None
            self.client = Client(self.scheduler)
        else:
            n = self.workers or os.cpu_count() or 1
            # the dashboard has no authentication: loopback only
            self.cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                        dashboard_address="127.0.0.1:8787", silence_logs=40)
            self.client = Client(self.cluster)
            # compute yields to the driver, the API and the scheduler on a shared machine
            self.client.run(os.nice, 10)
        print(f"[ardflow] Dask dashboard: {self.client.dashboard_link}", flush=True)
        return self.client

    def __exit__(self, *exc):
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()


def _run_on_dask(a, store) -> dict:
    import contextlib

    from ardflow.workers.graph import run_study

    with _Cluster(a.scheduler, a.workers) as client:
        ctx = contextlib.nullcontext()
        if a.performance_report:
            from distributed import performance_report

            ctx = performance_report(filename=a.performance_report)
        max_trials = store.meta.get("spec", {}).get("maximiser", {}).get("max_trials", 60)
        with ctx, LiveProgress(max_trials) as live:
            summary = run_study(client, store, progress=live)
    if not store.remote:
        from .html_report import write_report

        print(f"[ardflow] report: {write_report(store).resolve()}", flush=True)
    return summary


def cmd_select(a) -> int:
    from ardflow.ardcore.study import load_spec, select

    spec = load_spec(a.spec)
    if a.full:
        spec = full_settings(spec)
    out = Path(a.out)
    t0 = time.perf_counter()
    base = Path(a.spec).resolve().parent
    if a.executor == "dask":
        from ardflow.workers.graph import prepare_store
        from ardflow.workers.store import StudyStore

        existing = StudyStore(a.out)
        if existing.exists() and existing.meta.get("status") not in (None, "created"):
            from ardflow.ardcore.errors import SpecError

            raise SpecError(f"{a.out} already holds a study (status {existing.meta.get('status')!r}); "
                            f"continue it with 'ardflow resume {a.out}' or choose another --out")
        store = prepare_store(spec, a.out, base=base)
        print(f"[ardflow] study {store.meta['study_id']} -> {store}", flush=True)
        summary = _run_on_dask(a, store)
        _print_table(summary)
        print(f"\nsummary: {store}/summary.json  ({time.perf_counter() - t0:.1f} s)")
        return 0
    elif a.executor == "serial":
        with LiveProgress(spec.maximiser.max_trials) as live:
            summary = select(spec, out=out, progress=live, base=base)
    else:
        from concurrent.futures import ProcessPoolExecutor

        from ardflow.ardcore.mcmc import executor_map

        with ProcessPoolExecutor(max_workers=a.workers) as ex, LiveProgress(spec.maximiser.max_trials) as live:
            summary = select(spec, out=out, progress=live, map_fn=executor_map(ex), base=base)
    _print_table(summary)
    print(f"\nsummary: {(out / 'summary.json').resolve()}  ({time.perf_counter() - t0:.1f} s)")
    return 0


def cmd_resume(a) -> int:
    from ardflow.ardcore.errors import SpecError
    from ardflow.workers.store import StudyStore

    store = StudyStore(a.store)
    if not store.exists() or "spec" not in store.meta:
        raise SpecError(f"{a.store}: not an ardflow study store")
    if store.meta.get("status") == "done":
        print(f"[ardflow] study already finished: {store}/summary.json")
        return 0
    if (Path(a.store) / "CANCELLED").exists():
        raise SpecError(f"{a.store}: the study was cancelled; it is not resumed")
    t0 = time.perf_counter()
    print(f"[ardflow] resuming study {store.meta['study_id']} in {store}", flush=True)
    summary = _run_on_dask(a, store)
    _print_table(summary)
    print(f"\nsummary: {store}/summary.json  ({time.perf_counter() - t0:.1f} s)")
    return 0


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

    from ardflow.ardcore.errors import SpecError

    import uvicorn

    from .app import Settings, create_app

    root = Path(a.root)
    root.mkdir(parents=True, exist_ok=True)
    token = a.token or os.environ.get("ARDFLOW_TOKEN")
    loopback = _is_loopback(a.host)
    if a.insecure_no_auth and not loopback:
        raise SpecError(f"--insecure-no-auth is only allowed on a loopback address, not {a.host}")
    if token is None and not a.insecure_no_auth:
        # a token always, unless asked otherwise on loopback: any local process or web page could talk to us
        tf = root / "token"
        token = tf.read_text().strip() if tf.exists() else secrets.token_urlsafe(24)
        tf.write_text(token)
        os.chmod(tf, 0o600)
        print(f"[ardflow] API token required (X-API-Token or Bearer); it is in {tf} "
              f"(export ARDFLOW_TOKEN=$(cat {tf}))", flush=True)
    # a page in the user's browser may not reach a loopback service under another name (DNS rebinding)
    hosts = ["127.0.0.1", "localhost", "[::1]", "::1"] if loopback else None
    # the API's event loop gets the GIL back every 1 ms (not 5) from the threads that parse submissions
    sys.setswitchinterval(0.001)
    with _Cluster(a.scheduler, a.workers) as client:
        tokens = json.loads(Path(a.tokens_file).read_text()) if a.tokens_file else None
        app = create_app(Settings(root=root, token=token, tokens=tokens, max_body_mb=a.max_body_mb,
                                  max_running=a.max_running, allowed_hosts=hosts), client)
        print(f"[ardflow] API on http://{a.host}:{a.port}/v1 (OpenAPI: /docs), registry {root.resolve()}", flush=True)
        try:
            uvicorn.run(app, host=a.host, port=a.port, log_level="warning")
        finally:
            app.state.runner.stop()
    return 0


def _client(a):
    import os

    from .client import Client

    token = a.token or os.environ.get("ARDFLOW_TOKEN")
    local = Path("runs/service/token")  # what `ardflow serve` generates with its default --root
    if token is None and local.exists():
        token = local.read_text().strip()
    return Client(a.url, token=token)


def cmd_submit(a) -> int:
    from .client import APIError

    with _client(a) as c:
        try:
            sid = c.submit(a.spec, csv=a.csv)
            print(sid, flush=True)
            if a.wait:
                c.wait(sid)
                _print_table(c.summary(sid))
        except APIError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    return 0


def cmd_status(a) -> int:
    from .client import APIError

    with _client(a) as c:
        try:
            print(json.dumps(c.status(a.id) if a.id else c.studies(), indent=2))
        except APIError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
    return 0


def cmd_fetch(a) -> int:
    from .client import APIError

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


def full_settings(spec):
    """The paper-scale sampler settings (method.md section 6): the engine's defaults."""
    from ardflow.ardcore.mcmc import SamplerConfig

    keys = ("n_chains", "round_size", "n_stationary", "n_proposal")
    return spec.model_copy(update={"sampler": spec.sampler.model_copy(
        update={k: getattr(SamplerConfig, k) for k in keys})})


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="ardflow", description="Bayesian model selection for stochastic dynamical systems")
    sub = p.add_subparsers(dest="cmd", required=True)

    s = sub.add_parser("simulate", help="simulate the reference data set or any model to CSV (+ JSON sidecar)")
    s.add_argument("model", help="'reference' (the paper's pipeline), a built-in model name, or a model JSON file")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", required=True)
    s.add_argument("--param", action="append", metavar="NAME=VALUE", help="parameter value (models other than reference)")
    s.add_argument("--n", type=int, default=5000, help="number of samples")
    s.add_argument("--dt", type=float, default=0.1, help="sampling interval")
    s.add_argument("--nsub", type=int, default=100, help="Euler-Maruyama steps per sample")
    s.add_argument("--input-std", type=float, default=1.0, help="std of the random input of forced models")
    s.set_defaults(fn=cmd_simulate)

    s = sub.add_parser("loglik", help="EKF log-likelihood of a model on a data set")
    s.add_argument("data")
    s.add_argument("--model", required=True)
    s.add_argument("--param", action="append", metavar="NAME=VALUE")
    s.add_argument("--substeps", type=int, default=None)
    s.add_argument("--fs", type=float, default=None, help="sampling frequency when the file has no 't' column")
    s.add_argument("--rename", action="append", metavar="OLD=NEW")
    s.set_defaults(fn=cmd_loglik)

    s = sub.add_parser("data", help="check or convert a data file (CSV, NPZ, MAT)")
    s.add_argument("action", choices=["check", "convert"])
    s.add_argument("data")
    s.add_argument("--fs", type=float, default=None)
    s.add_argument("--rename", action="append", metavar="OLD=NEW")
    s.add_argument("--out", default=None, help="CSV to write (convert)")
    s.set_defaults(fn=cmd_data)

    s = sub.add_parser("select", help="run a model-selection study (JSON spec); the zarr store and "
                                      "summary.json go to --out")
    s.add_argument("spec")
    s.add_argument("--out", required=True, help="study store directory (zarr) with summary.json")
    s.add_argument("--executor", choices=["dask", "processes", "serial"], default="dask",
                   help="dask (default: embedded LocalCluster or --scheduler), a local process pool, or serial")
    s.add_argument("--scheduler", default=None, help="address of an existing Dask scheduler")
    s.add_argument("--workers", type=int, default=None, help="embedded cluster / pool size (default: cores)")
    s.add_argument("--performance-report", default=None, metavar="FILE.html", help="write Dask's performance report")
    s.add_argument("--full", action="store_true", help="paper-scale sampler settings")
    s.set_defaults(fn=cmd_select)

    s = sub.add_parser("resume", help="continue a study whose driver stopped")
    s.add_argument("store")
    s.add_argument("--scheduler", default=None)
    s.add_argument("--workers", type=int, default=None)
    s.add_argument("--performance-report", default=None, metavar="FILE.html")
    s.set_defaults(fn=cmd_resume)

    s = sub.add_parser("serve", help="run the REST API (embedded LocalCluster or --scheduler)")
    s.add_argument("--host", default="127.0.0.1")
    s.add_argument("--port", type=int, default=8000)
    s.add_argument("--root", default="runs/service", help="registry directory (studies and data sets)")
    s.add_argument("--token", default=None,
                   help="API token (default: $ARDFLOW_TOKEN, else generated into ROOT/token)")
    s.add_argument("--insecure-no-auth", action="store_true",
                   help="no token (loopback only: any local process can then submit studies)")
    s.add_argument("--max-running", type=int, default=2, help="study drivers at once; the others wait queued")
    s.add_argument("--tokens-file", default=None,
                   help='JSON {"owner": "token", ...}: one token per user, each limited separately')
    s.add_argument("--scheduler", default=None)
    s.add_argument("--workers", type=int, default=None)
    s.add_argument("--max-body-mb", type=float, default=20.0)
    s.set_defaults(fn=cmd_serve)

    for name, fn, hlp in (("submit", cmd_submit, "submit a study to a running service"),
                          ("status", cmd_status, "status of one study (or the list)"),
                          ("fetch", cmd_fetch, "download a finished study's summary, posteriors and figures")):
        s = sub.add_parser(name, help=hlp)
        if name == "submit":
            s.add_argument("spec")
            s.add_argument("--csv", default=None, help="upload this CSV as the study's data set")
            s.add_argument("--wait", action="store_true")
        elif name == "status":
            s.add_argument("id", nargs="?")
        else:
            s.add_argument("id")
            s.add_argument("--out", required=True)
        s.add_argument("--url", default="http://127.0.0.1:8000")
        s.add_argument("--token", default=None)
        s.set_defaults(fn=fn)

    s = sub.add_parser("diagnose", help="close the loop: find the residual of a fitted model, trace it to a "
                                        "missing effect, add it under ARD and report the error before and after")
    s.add_argument("spec", help="study spec (JSON) or a finished study store; one model (--model, default the "
                                "spec's only model or the study's best) is diagnosed")
    s.add_argument("--out", required=True, help="directory for diagnosis.json, diagnosis.html and figures")
    s.add_argument("--model", help="which candidate of the spec to diagnose")
    s.add_argument("--test-start", type=int, help="first row of the held-out record for the free run "
                                                  "(rows of the same file; default: the estimation data)")
    s.add_argument("--test-stop", type=int, help="end row of the held-out record")
    s.add_argument("--test-data", help="held-out record in its own file (same columns as the data)")
    s.add_argument("--test-rename", action="append", metavar="OLD=NEW",
                   help="renaming of the held-out file's columns (default: the spec's data.rename); e.g. "
                        "--test-rename uVal=u --test-rename yVal=y for a file that holds both records")
    s.add_argument("--top-k", type=int, default=3, help="candidates confirmed by evidence per round (default 3)")
    s.add_argument("--max-rounds", type=int, default=3, help="effects added one after another at most (default 3)")
    s.set_defaults(fn=cmd_diagnose)

    s = sub.add_parser("models", help="list the built-in models, or print one as JSON")
    s.add_argument("name", nargs="?")
    s.set_defaults(fn=cmd_models)

    s = sub.add_parser("example", help="list the example study specs, or write one out")
    s.add_argument("name", nargs="?")
    s.add_argument("--out", help="file to write (default: print it)")
    s.set_defaults(fn=cmd_example)

    s = sub.add_parser("demo", help="the main job: the Section 3.6 study on an embedded cluster, with its report")
    s.add_argument("--out", default="runs/demo")
    s.add_argument("--full", action="store_true", help="paper-scale sampler settings")
    s.add_argument("--workers", type=int, default=None)
    s.add_argument("--scheduler", default=None)
    s.add_argument("--performance-report", default=None, metavar="FILE.html")
    s.set_defaults(fn=cmd_demo)
    return p


def cmd_diagnose(a) -> int:
    """Close the loop on one model of a study spec or of a finished study store."""
    from ardflow.ardcore.data import read_dataset
    from ardflow.ardcore.diagnose import DiagnoseConfig, diagnose
    from ardflow.ardcore.errors import SpecError
    from ardflow.ardcore.study import StudySpec, load_spec

    from .diagnose_report import write_diagnosis

    src = Path(a.spec)
    if src.is_dir():
        from ardflow.workers.store import StudyStore

        store = StudyStore(src)
        if not store.exists():
            raise SpecError(f"{src} is a directory but not a study store")
        spec = StudySpec.model_validate(store.meta["spec"])
        data = store.load_data()
        base = None
        default = (store.meta.get("summary") or {}).get("best_model")
    else:
        store = None
        spec = load_spec(src)
        base = src.resolve().parent
        data = spec.data.load(base)
        default = None
    name = a.model or (default if len(spec.models) > 1 else None)
    if name:
        picked = [m for m in spec.models if m.label == name]
        if not picked:
            raise SpecError(f"--model {name!r}: not in the spec (models: {[m.label for m in spec.models]})")
        spec = spec.model_copy(update={"models": picked})
    elif len(spec.models) > 1:
        raise SpecError(f"the spec has {len(spec.models)} models: choose one with --model")
    test = None
    if a.test_data:
        d = spec.data
        rename = _kv(a.test_rename, "--test-rename") if a.test_rename else d.rename
        test = read_dataset(a.test_data, time=d.time, fs=d.fs, rename=rename, columns=d.columns)
    elif a.test_start is not None or a.test_stop is not None:
        if spec.data.path is None:
            raise SpecError("--test-start/--test-stop need a spec whose data come from a file (data.path)")
        # the same loader as the estimation data (slice, then the same decimation)
        test = spec.data.model_copy(update={"start": a.test_start, "stop": a.test_stop}).load(base)
    cfg = DiagnoseConfig(top_k=a.top_k, max_rounds=a.max_rounds)
    t0 = time.perf_counter()
    fit = None
    if store is not None:
        from ardflow.workers.graph import stored_fit

        fit = stored_fit(store, spec.models[0].label)  # the study's own fit: no refit
    rep = diagnose(spec, data, test_data=test, config=cfg, base=fit,
                   progress=lambda s: print(f"[diagnose] {s}", flush=True))
    path = write_diagnosis(rep, data.t, a.out, col=spec.models[0].model_spec().observed_columns[0])
    print(f"\n{rep['verdict']}")
    print(f"\nreport: {path} and {Path(a.out) / 'diagnosis.html'}  ({time.perf_counter() - t0:.1f} s)")
    return 0


def main(argv: list[str] | None = None) -> int:
    from pydantic import ValidationError

    from ardflow.ardcore.errors import ArdflowError

    args = build_parser().parse_args(argv)
    if args.cmd == "data" and args.action == "convert" and not args.out:
        print("error: data convert needs --out FILE.csv", file=sys.stderr)
        return 2
    try:
        return args.fn(args)
    except ArdflowError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except ValidationError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
