"""The study on real Dask clusters and a real zarr store."""

import functools
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from distributed import Client, LocalCluster, get_task_stream

from ardflow.ardcore.selection.spec import load_spec
from ardflow.ardcore.selection.study import select
from ardflow.workers.graph import cancel_study, prepare_store, read_progress, run_study
from ardflow.workers.store import StudyStore

from ..browser import load_page

SPEC = Path(__file__).with_name("small_study.json")
ROOT = Path(__file__).resolve().parents[2]


def rows(summary):
    return {r["name"]: r for r in summary["models"]}


@pytest.fixture(scope="module")
def reference_summary():
    return select(load_spec(SPEC))


@pytest.fixture
def thread_cluster():
    # one per test (about 1 s each): a module-wide thread cluster used again after the tests that start, disrupt
    # and close clusters of their own in this process hung with idle workers (fsspec store, locally, and the
    # reference study, twice in fresh-clone CI), and took every later test with it
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cl, \
            Client(cl) as c:
        yield c


def test_orchestrated_equals_in_process(tmp_path, thread_cluster, reference_summary):
    store = prepare_store(load_spec(SPEC), tmp_path / "st")
    with get_task_stream(thread_cluster) as ts:
        s = run_study(thread_cluster, store, poll_s=0.2)
    a, b = rows(s), rows(reference_summary)
    for k in a:
        assert a[k]["log_evidence"] == pytest.approx(b[k]["log_evidence"], abs=1e-9)
        assert a[k]["pruned"] == b[k]["pruned"] and a[k]["psi_opt"] == b[k]["psi_opt"]
    keys = {t["key"] if isinstance(t["key"], str) else str(t["key"]) for t in ts.data}
    sid = store.meta["study_id"]
    assert f"burnin-{sid}-quad-it000-r001-c0" in keys
    assert f"compare-{sid}" in keys
    assert json.loads((tmp_path / "st" / "summary.json").read_text())["best_model"] == s["best_model"]
    hist = json.loads((tmp_path / "st" / "history.json").read_text())
    assert len(hist["quad"]) == a["quad"]["iterations"]
    # a sampled trial's chains ran as tasks; a reweighted one ran none
    for h in hist["cubic"][1:]:
        key = f"stationary-{sid}-cubic-it{h['iteration']:03d}-d000000-c2"
        assert (key in keys) == h["sampled"], (h["action"], h["sampled"])
    assert store.meta["status"] == "done"


def test_store_opens_with_xarray_named_dims(tmp_path, thread_cluster):
    xr = pytest.importorskip("xarray")
    store = prepare_store(load_spec(SPEC), tmp_path / "st")
    run_study(thread_cluster, store, poll_s=0.2)
    ds = xr.open_zarr(store.path, group="models/quad/trials/000", consolidated=False)
    assert ds["samples"].dims == ("chain", "draw", "param")
    assert list(ds["param"].values) == ["a0", "a1", "a2", "gamma"]
    assert np.isfinite(ds["samples"].values).all()
    data = xr.open_zarr(store.path, group="data", consolidated=False)
    assert data["y"].dims == ("time",) and data.sizes["time"] == 100


def test_cancel_takes_effect(tmp_path, thread_cluster):
    from ardflow.ardcore.sampling.driver import Cancelled

    store = prepare_store(load_spec(SPEC), tmp_path / "st")
    sid = store.meta["study_id"]
    import threading

    def cancel_soon():
        offsets = {}
        while not any(e.stage == "burnin" for e in read_progress(store, offsets)):
            time.sleep(0.05)
        cancel_study(thread_cluster, sid)

    th = threading.Thread(target=cancel_soon)
    th.start()
    with pytest.raises(Cancelled):
        run_study(thread_cluster, store, poll_s=0.1)
    th.join()
    assert store.meta["status"] == "cancelled"
    from distributed import Event

    Event(f"cancel-{sid}", client=thread_cluster).clear()


def _completes_despite(tmp_path, reference_summary, disrupt, processes: bool) -> None:
    """Run the reference study on its own LocalCluster, calling ``disrupt(client)`` once, when a trial is past
    its first iteration: the study completes with the undisturbed run's evidence and pruning."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=processes, dashboard_address=":0") as cl, \
            Client(cl) as c:
        store = prepare_store(load_spec(SPEC), tmp_path / "st")
        done = []

        def progress(ev):
            if not done and ev.stage == "trial" and ev.event.iteration >= 1:
                done.append(disrupt(c))

        s = run_study(c, store, progress=progress, poll_s=0.1)
    assert done
    a, b = rows(s), rows(reference_summary)
    for k in a:
        assert abs(a[k]["log_evidence"] - b[k]["log_evidence"]) < 5 * max(b[k]["log_evidence_se"], 0.05)
        assert a[k]["pruned"] == b[k]["pruned"]


def test_dropped_scheduler_connection_study_completes(tmp_path, reference_summary):
    """The client's stream to the scheduler is cut mid-study: it reconnects and every lost task is resubmitted."""

    def drop(c):
        c.loop.add_callback(c.scheduler_comm.comm.abort)
        return time.time()

    _completes_despite(tmp_path, reference_summary, drop, processes=False)


def test_lost_worker_process_study_completes(tmp_path, reference_summary):
    """A real process-based cluster: kill a worker process mid-study; the nanny restarts it."""

    def kill(c):
        victim = sorted(c.run(os.getpid).values())[0]
        os.kill(victim, signal.SIGKILL)
        return victim

    _completes_despite(tmp_path, reference_summary, kill, processes=True)


def test_killed_driver_resumes(tmp_path, reference_summary):
    out = tmp_path / "st"
    env = dict(os.environ)
    p = subprocess.Popen([sys.executable, "-m", "ardflow.service.cli", "select", str(SPEC), "--out", str(out),
                          "--workers", "2"], cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                         start_new_session=True)
    store = StudyStore(out)
    offsets = {}
    deadline = time.time() + 240
    trials = 0
    while time.time() < deadline and trials < 3:
        time.sleep(0.2)
        if store.exists() and store.meta.get("study_id"):
            trials += sum(1 for e in read_progress(store, offsets) if e.stage == "trial")
    os.killpg(p.pid, signal.SIGKILL)  # the driver and its embedded cluster
    p.wait()
    assert trials >= 3 and not (out / "summary.json").exists()
    r = subprocess.run([sys.executable, "-m", "ardflow.service.cli", "resume", str(out), "--workers", "2"], cwd=ROOT,
                       env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    s = json.loads((out / "summary.json").read_text())
    a, b = rows(s), rows(reference_summary)
    for k in a:
        # same seeds: finished trials are read back, the trial in flight continues from its checkpoint
        assert a[k]["log_evidence"] == pytest.approx(b[k]["log_evidence"], abs=1e-9)
        assert a[k]["pruned"] == b[k]["pruned"]


def test_coordinator_actor_restored_after_its_worker_dies():
    from ardflow.ardcore.sampling.adaptation import AdaptationPool
    from ardflow.ardcore.sampling.chains import RoundStats
    from ardflow.workers.coordinator import ActorPool

    rng = np.random.default_rng(0)

    def halves():
        x = rng.standard_normal((50, 2))
        return RoundStats.of(x[:25]), RoundStats.of(x[25:])

    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, \
            Client(cl) as c:
        pool = ActorPool(c, AdaptationPool(2, 2, np.eye(2)).to_dict(), "restore-test")
        for ch in range(2):
            pool.report(ch, 1, halves(), None)
        assert pool.rounds == 1
        holder = list(c.who_has(pool._future)[pool._future.key])[0]
        pid = c.run(os.getpid, workers=[holder])[holder]
        os.kill(pid, signal.SIGKILL)
        time.sleep(0.5)
        for ch in range(2):
            pool.report(ch, 2, halves(), None)
        assert pool.rounds == 2 and pool.restarts >= 1
        assert np.all(np.isfinite(pool.rhat()))
        pool.close()


@pytest.mark.timeout(300)
def test_reference_study_store_named_dims(tmp_path):
    # on process workers, as users run it
    xr = pytest.importorskip("xarray")
    spec = load_spec(ROOT / "examples" / "sec33.json").model_copy(update={
        "sampler": load_spec(SPEC).sampler.model_copy(update={"n_chains": 2, "n_stationary": 200, "n_proposal": 100}),
        "maximiser": load_spec(SPEC).maximiser.model_copy(update={"max_trials": 1, "prune_test": False}),
    })
    store = prepare_store(spec, tmp_path / "ref")
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, \
            Client(cl) as c:
        s = run_study(c, store, poll_s=0.2)
    assert s["models"][0]["name"] == "M2true"
    ds = xr.open_zarr(store.path, group="models/M2true/trials/000", consolidated=False)
    assert dict(ds.sizes) == {"chain": 2, "draw": 200, "param": 6}
    assert ds["log_likelihood"].dims == ("chain", "draw")
    assert list(ds["param"].values) == ["B", "a1", "a2", "a3", "a4", "sigma"]
    data = xr.open_zarr(store.path, group="data", consolidated=False)
    assert data.sizes["time"] == 5000


def test_fsspec_url_store(thread_cluster, reference_summary):
    """Any fsspec URL works as the store (memory:// is shared by the threads of this process)."""
    store = prepare_store(load_spec(SPEC), "memory://ardflow-test/st")
    s = run_study(thread_cluster, store, poll_s=0.2)
    assert StudyStore("memory://ardflow-test/st").meta["status"] == "done"
    assert json.loads(store.read_text("summary.json"))["best_model"] == s["best_model"]
    a, b = rows(s), rows(reference_summary)
    for k in a:
        assert a[k]["log_evidence"] == pytest.approx(b[k]["log_evidence"], abs=1e-9)
    samples, lp, ll, names = store.read_samples("quad", 0)
    assert samples.shape == (3, 400, 4) and np.isfinite(samples).all()
    assert store.read_checkpoint("quad", 0)["stage"] == "stationary"


def test_report_for_any_study(tmp_path, thread_cluster):
    import re

    from ardflow.service.reports.study import write_report

    spec = load_spec(SPEC).model_copy(update={"true_values": {"a0": 3.0, "a1": 5.0, "gamma": 0.3}})
    store = prepare_store(spec, tmp_path / "st")
    run_study(thread_cluster, store, poll_s=0.2)
    page = write_report(store)
    text = page.read_text()
    imgs = re.findall(r"<img src='([^']+)'", text)
    assert len(imgs) >= 6 and all((page.parent / f).stat().st_size > 1000 for f in imgs)
    assert "http" not in text  # no network assets
    assert "Model comparison" in text and "true inside" in text
    assert "Fig." not in text and "issue" not in text.lower()  # the paper's figures and the project's issues are not the user's
    shown = load_page(page)  # headless Chromium, network cut off
    assert len(shown["images"]) == len(imgs)
    assert all(i["complete"] and i["width"] > 100 for i in shown["images"]), shown["images"]
    assert not shown["blocked"] and not shown["failed"] and not shown["errors"], shown
    # the figures drawn on the study's workers, side by side (two threads of one process here): the same page
    # and the same pictures
    there = write_report(store, tmp_path / "on_workers", submit=functools.partial(thread_cluster.submit, pure=False))
    assert there.read_text() == text
    for f in imgs:
        assert (there.parent / f).read_bytes() == (page.parent / f).read_bytes(), f


class _SlowTarget:
    names = ["x"]

    def __call__(self, x):
        time.sleep(0.05)
        return 0.0, 0.0


def _calls_for(target, seconds):
    t0 = time.monotonic()
    while time.monotonic() - t0 < seconds:
        target([0.0])
    return "finished"


def test_task_wall_clock_limit_is_the_backstop(thread_cluster):
    """A task whose likelihood calls go on past ``max_task_s`` (as the worker timed the task) fails with a
    message naming the limit; within the limit it finishes."""
    from ardflow.ardcore.sampling.chains import SamplerError
    from ardflow.workers.tasks import StoppableTarget

    t = StoppableTarget(_SlowTarget(), "no-such-study", max_task_s=1.0)
    t.check_s = 0.1
    fut = thread_cluster.submit(_calls_for, t, 4.0, pure=False)
    with pytest.raises(SamplerError, match="ran longer than its limit of 1 s"):
        fut.result(timeout=30)
    assert thread_cluster.submit(_calls_for, t, 0.5, pure=False).result(timeout=30) == "finished"


def test_redrawn_stationary_passes_write_the_store_and_never_share_a_task_key(tmp_path, thread_cluster):
    """A stationary stage drawn again (its R-hat failed) on Dask: every pass's tasks have their own keys (a
    later pass never gets an earlier pass's cached result) and the store holds the final draws."""
    from ardflow.ardcore.sampling.driver import STATIONARY_ROUNDS, Runtime, Start, sample
    from ardflow.workers.tasks import DaskMap

    from ..statistical.test_dram import far_start_run

    local, target, _, _, cfg, starts = far_start_run(6)
    store = StudyStore.create(tmp_path / "st", {})
    store.create_trial("m", 0, list(target.names), cfg.n_chains, cfg.n_stationary, cfg.round_size, {})
    with get_task_stream(thread_cluster) as ts:
        res = sample(target, cfg, seed=12, start=Start(points=starts),
                     runtime=Runtime(map_fn=DaskMap(thread_cluster, "redraw", store, "m", 0)))
    np.testing.assert_array_equal(res.samples, local.samples)  # the same draws as in-process
    samples, lp, ll, _ = store.read_samples("m", 0)
    np.testing.assert_array_equal(samples, res.samples)
    np.testing.assert_allclose(ll, res.ll)
    keys = [str(t["key"]) for t in ts.data if str(t["key"]).startswith("stationary-redraw")]
    per_pass = -(-cfg.n_stationary // (STATIONARY_ROUNDS * cfg.round_size))  # tasks per chain in one pass
    assert len(keys) == len(set(keys)) > cfg.n_chains * per_pass  # more than one pass, no key twice


def test_a_continued_trial_stopped_mid_extension_resumes_to_the_same_numbers(tmp_path, thread_cluster):
    """The reported trial's chains continued past the judged draws (a quality target the search trials do
    not reach): stopped between two of its extension's rounds, the driver resumes from the checkpoint and
    the draws in the store, and ends with the numbers of an uninterrupted in-process run."""
    from ardflow.ardcore.events import Note
    from functools import partial

    from ardflow.ardcore.selection.study import CandidateHooks
    from ardflow.workers.graph import StoredEvaluator, TrialSite, fit_model

    raw = json.loads(SPEC.read_text())
    raw["models"] = raw["models"][:1]
    raw["sampler"].update(max_stationary=1200, min_ess=3000)
    spec = load_spec_dict(raw, tmp_path)
    ref = rows(select(spec))["quad"]
    store = prepare_store(spec, tmp_path / "st")
    data, sid = store.load_data(), store.meta["study_id"]

    class Stop(Exception):
        pass

    factory = partial(StoredEvaluator, site=TrialSite(thread_cluster, store, sid, "quad"))

    def stop_in_extension(ev):
        if isinstance(ev.event, Note) and "continuing to" in ev.event.message:
            raise Stop

    with pytest.raises(Stop):
        fit_model(store, spec, data, 0, CandidateHooks(progress=stop_in_extension, evaluator_factory=factory))
    it = max(int(k) for k in store.group("r")["models/quad/trials"].group_keys())
    ck = store.read_checkpoint("quad", it)
    assert ck["stage"] == "stationary" and store.trial_record("quad", it) is None  # stopped inside it
    row = fit_model(store, spec, data, 0, CandidateHooks(progress=lambda ev: None, evaluator_factory=factory))
    assert row.log_evidence == pytest.approx(ref["log_evidence"], abs=1e-9)
    assert row.diagnostics == ref["diagnostics"]
    samples, _, _, _ = store.read_samples("quad", it)
    assert samples.shape[1] == 1200 and not np.isnan(samples).any()


def load_spec_dict(raw: dict, tmp_path):
    p = tmp_path / "spec.json"
    p.write_text(json.dumps(raw))
    return load_spec(p)


@pytest.mark.parametrize("workers", [1, 2])
def test_same_seed_same_numbers_on_any_worker_count(tmp_path, workers, reference_summary):
    """Worker processes (not threads), one or two: the study's numbers are the in-process ones, bit for bit,
    and the reported draws in the store are what ArviZ judges in the summary."""
    import arviz as az

    store = prepare_store(load_spec(SPEC), tmp_path / "st")
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=":0") as cl, \
            Client(cl) as c:
        s = run_study(c, store, poll_s=0.2)
    a, b = rows(s), rows(reference_summary)
    for k in a:
        assert a[k]["log_evidence"] == b[k]["log_evidence"] and a[k]["mean"] == b[k]["mean"]
        it = store.group("r")[f"models/{k}"].attrs["best_iteration"]
        x, _, _, names = store.read_samples(k, it)
        t = az.summary(az.from_dict({"posterior": {n: x[..., i] for i, n in enumerate(names)}}),
                       kind="diagnostics", round_to="none")
        assert {n: float(t.loc[n, "r_hat"]) for n in names} == pytest.approx(
            {n: v["r_hat"] for n, v in a[k]["diagnostics"].items()}, rel=1e-12)


def test_prune_tests_decided_by_bounds_on_dask_are_the_in_process_ones(tmp_path, thread_cluster):
    """A line y = a0 + a1 x with ARD on both: each prune test is decided by the likelihood bound, a few searches
    on the cluster each. Every bound of the Dask run is the in-process one (a later bound's searches never get
    an earlier one's results), and so is every other trial."""
    from ardflow.ardcore.selection.spec import StudySpec

    d = json.loads(SPEC.read_text())
    d["models"] = [{"model": "polynomial", "name": "line", "fixed": {"a2": 0.0, "a3": 0.0, "a4": 0.0},
                    "priors": {"gamma": d["models"][0]["priors"]["gamma"]}, "ard": ["a0", "a1"]}]
    spec = StudySpec.model_validate(d)
    local = select(spec)["_history"]["line"]
    store = prepare_store(spec, tmp_path / "st")
    run_study(thread_cluster, store, poll_s=0.2)
    remote = json.loads((tmp_path / "st" / "history.json").read_text())["line"]
    bounds = {h["iteration"]: h["log_evidence"] for h in local if h.get("bound")}
    assert {h["action"].split(":")[0] for h in local if h.get("bound")} == {"a0", "a1"}
    assert len(set(bounds.values())) == 2  # a0's nested model and a1's: two maxima
    assert [(h["iteration"], h["log_evidence"], h.get("bound")) for h in remote] == \
        [(h["iteration"], h["log_evidence"], h.get("bound")) for h in local]
