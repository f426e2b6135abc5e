"""``ardflow`` commands that run studies and the closed loop: demo, select, resume, diagnose."""

from __future__ import annotations

import json
import time
from pathlib import Path

from ardflow.workers.cluster import ClusterClient

from ardflow.service.commands.local import EXAMPLES, parse_assignments
from ardflow.service.commands.progress import LiveProgress, print_table



CHECKS_TITLE = "checks against the paper (docs/worked-example.md)"
"""The heading of the demo's checks: the user's words, never the project's issue names."""

def full_settings(spec):
    """The paper-scale sampler settings (docs/method.md section 5): the engine's defaults."""
    from ardflow.ardcore.sampling.config import SamplerConfig

    keys = ("n_chains", "round_size", "n_stationary", "n_proposal")
    return spec.model_copy(update={"sampler": spec.sampler.model_copy(
        update={k: SamplerConfig.model_fields[k].default for k in keys})})


def _run_on_dask(a, store) -> dict:
    import contextlib
    import functools

    from ardflow.workers.graph import run_study

    with ClusterClient(a.scheduler, a.workers) as client:
        ctx = contextlib.nullcontext()
        if a.performance_report:
            from distributed import performance_report

            ctx = performance_report(filename=a.performance_report)
        max_trials = store.meta.get("spec", {}).get("maximiser", {}).get("max_trials", 60)
        with ctx, LiveProgress(max_trials) as live:
            summary = run_study(client, store, progress=live, done=store.remote)
        if not store.remote:
            # the study's workers draw the report's figures side by side (a remote store's report is the service's)
            _report_and_finish(store, functools.partial(client.submit, pure=False))
    return summary


def _report_and_finish(store, submit=None) -> None:
    """The report (its figures drawn where ``submit`` runs them), then the study's status ``done`` (the service
    reports done when all of it is written)."""
    from ardflow.service.reports.study import write_report

    print(f"[ardflow] report: {write_report(store, submit=submit).resolve()}", flush=True)
    store.update_meta(status="done")


def cmd_demo(a) -> int:
    """The main job: the paper's Section 3.6 study (M1, M2, M3 with ARD) on an embedded LocalCluster."""
    from ardflow.ardcore.selection.spec import load_spec
    from ardflow.workers.graph import prepare_store
    from ardflow.workers.store import StudyStore

    spec_path = Path(a.spec) if getattr(a, "spec", None) else EXAMPLES / "sec36.json"
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
    summary = store.read_summary().to_json()
    print_table(summary)
    from ardflow.service.reports.paper import check_label, reference_checks

    print(f"\n[demo] {CHECKS_TITLE}:")
    for c in reference_checks(summary, spec.true_values):
        print(f"  [{check_label(c)}] {c['check']}: {c['detail']}"
              + (f"\n      documented difference: {c['documented']}" if c.get("documented") else ""))
    print(f"\n[demo] store (zarr):  {out.resolve()}")
    print(f"[demo] summary:       {(out / 'summary.json').resolve()}")
    print(f"[demo] report:        {(out / 'report' / 'report.html').resolve()}")
    print(f"[demo] wall time:     {time.perf_counter() - t0:.0f} s")
    return 0


def cmd_select(a) -> int:
    """Run a study: chains on Dask (default) or on this machine; either way a zarr store with its report."""
    from ardflow.ardcore.selection.spec import load_spec
    from ardflow.workers.graph import prepare_store
    from ardflow.workers.store import StudyStore

    from ardflow.ardcore.selection.validation import check_study, parse_models

    spec = load_spec(a.spec)
    if a.full:
        spec = full_settings(spec)
    # every model becomes a kernel before anything is created: a typo is one line, not a worker's traceback
    # and a half-made store
    parse_models(spec)
    check_study(spec)
    t0 = time.perf_counter()
    base = Path(a.spec).resolve().parent

    existing = StudyStore(a.out)
    if existing.exists() and existing.meta.get("status") not in (None, "created"):
        from ardflow.ardcore.errors import SpecError

        raise SpecError(f"{a.out} already holds a study (status {existing.meta.get('status')!r}); "
                        + (f"continue it with 'ardflow resume {a.out}' or " if a.executor == "dask" else "")
                        + "choose another --out")
    store = prepare_store(spec, a.out, base=base)
    print(f"[ardflow] study {store.meta['study_id']} -> {store}", flush=True)
    if a.executor == "dask":
        summary = _run_on_dask(a, store)
    else:
        summary = _run_locally(a, store, spec)
    print_table(summary)
    print(f"\nsummary: {store}/summary.json  ({time.perf_counter() - t0:.1f} s)")
    return 0


def _run_locally(a, store, spec) -> dict:
    """The study serially or on a local process pool, into the same store layout and report as on Dask."""
    from concurrent.futures import ProcessPoolExecutor

    from ardflow.ardcore.sampling.chains import executor_map, serial_map
    from ardflow.workers.local import run_study_local

    with LiveProgress(spec.maximiser.max_trials) as live:
        if a.executor == "serial":
            summary = run_study_local(store, serial_map, progress=live, done=False)
        else:
            with ProcessPoolExecutor(max_workers=a.workers) as ex:
                summary = run_study_local(store, executor_map(ex), progress=live, done=False)
    _report_and_finish(store)
    return summary


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
    from ardflow.ardcore.selection.spec import StudySpec
    from ardflow.ardcore.selection.validation import check_study

    check_study(StudySpec.model_validate(store.meta["spec"]))  # a store made before specs were checked whole
    t0 = time.perf_counter()
    print(f"[ardflow] resuming study {store.meta['study_id']} in {store}", flush=True)
    summary = _run_on_dask(a, store)
    print_table(summary)
    print(f"\nsummary: {store}/summary.json  ({time.perf_counter() - t0:.1f} s)")
    return 0


def cmd_diagnose(a) -> int:
    """Close the loop on one model of a study spec or of a finished study store."""
    from ardflow.ardcore.data import read_dataset
    from ardflow.ardcore.loop.config import DiagnoseConfig
    from ardflow.ardcore.loop.diagnose import diagnose
    from ardflow.ardcore.errors import LoopFailed, SpecError
    from ardflow.ardcore.selection.spec import StudySpec, load_spec

    from ardflow.service.reports.diagnosis import write_diagnosis

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
        data = spec.load_data(base)
        default = None
    if a.seed is not None:
        spec = spec.model_copy(update={"seed": a.seed})
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
        d = spec.naming
        rename = parse_assignments(a.test_rename, "--test-rename") if a.test_rename else d.rename
        from ardflow.ardcore.data import join_records
        from ardflow.ardcore.selection.spec import uploaded_name

        files = a.test_data if isinstance(a.test_data, list) else [a.test_data]
        held = [read_dataset(f, time=d.time, fs=d.fs, rename=rename, columns=d.columns) for f in files]
        test = join_records(held, [uploaded_name(h) or Path(f).name for h, f in zip(held, files)])
    elif a.test_start is not None or a.test_stop is not None:
        if len(spec.records) > 1 or spec.naming.path is None:
            raise SpecError("--test-start/--test-stop need a spec whose data come from one file (data.path)")
        # the same loader as the estimation data (slice, then the same decimation)
        test = spec.naming.model_copy(update={"start": a.test_start, "stop": a.test_stop}).load(base)
    cfg = DiagnoseConfig(top_k=a.top_k, max_rounds=a.max_rounds)
    t0 = time.perf_counter()
    fit = None
    if store is not None:
        from ardflow.workers.graph import stored_fit

        fit = stored_fit(store, spec.models[0].label)  # the study's own fit: no refit
    try:
        rep = diagnose(spec, data, test_data=test, config=cfg, base=fit,
                       progress=lambda s: print(f"[diagnose] {s}", flush=True))
    except LoopFailed as exc:
        # never lose the work: what the loop had goes where the report would have gone, then the one-line error
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        tmp = out / "diagnosis.json.tmp"
        tmp.write_text(json.dumps(exc.partial, indent=1, allow_nan=False, default=str))
        tmp.replace(out / "diagnosis.json")
        # the folder is not named: the service passes its own paths, which its users must not see
        raise LoopFailed(f"{exc} to diagnosis.json in the --out folder", exc.partial) from None
    path = write_diagnosis(rep, data.t, a.out, col=spec.models[0].model_spec().observed_columns[0],
                           label=spec.naming.axis_label)
    print(f"\n{rep.report.get('headline', '')}\n\n{rep.verdict}")
    print(f"\nreport: {path} and {Path(a.out) / 'diagnosis.html'}  ({time.perf_counter() - t0:.1f} s)")
    return 0


def cmd_loo(a) -> int:
    """PSIS-LOO of every model of a finished study beside its log evidence (needs arviz)."""
    from ardflow.ardcore.errors import SpecError
    from ardflow.workers.store import StudyStore

    store = StudyStore(a.store)
    if not store.exists() or store.meta.get("status") != "done":
        raise SpecError(f"{a.store}: not a finished ardflow study store")
    try:
        import warnings

        from ardflow.workers.inference import loo_beside_evidence

        with warnings.catch_warnings():  # ArviZ warns about high Pareto k: the table counts them
            warnings.simplefilter("ignore", UserWarning)
            rows = loo_beside_evidence(store, max_draws=a.draws)
    except ImportError:
        raise SpecError("ardflow loo needs ArviZ: pip install arviz (or the 'arviz' extra)") from None
    print(f"{'model':<12s} {'ln Z':>12s} {'P(M|d)':>9s} {'elpd_loo':>12s} {'se':>6s} {'diff':>8s} {'diff se':>8s} "
          f"{'p_loo':>7s} {'k>0.7':>6s}")
    for r in rows:
        print(f"{r['model']:<12s} {r['log_evidence']:12.2f} {r['probability'] or 0:9.3g} {r['elpd_loo']:12.2f} "
              f"{r['elpd_se']:6.1f} {r['elpd_diff']:8.2f} {r['diff_se']:8.2f} {r['p_loo']:7.2f} {r['pareto_k_high']:6d}")
        for name, v in (r.get("elpd_records") or {}).items():
            print(f"{'':<12s} {'':>12s} {'':>9s} {v:12.2f}  on {name}")
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=2))
    return 0
