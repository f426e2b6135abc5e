"""``make bench``: measured figures written to ``.bench/results.json``.

Keys (a contract; see README): ekf_m2_ms, ekf_numpy_ms, ekf_speedup, ekf_handwritten_ms,
ekf_vs_handwritten, ekf_compile_first_call_s, ekf_cached_first_call_s, ekf_m2_substep_table.
Existing keys written by other benchmarks are kept.

``--tiny`` runs every group's code at a tiny size (the smoke test in ``make test``: a group that no longer
runs fails there, not at the next ``make bench``); its figures measure nothing and go to ``--out`` only.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("NUMBA_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[2]

import numpy as np  # noqa: E402


TINY_SAMPLER = {"n_chains": 2, "round_size": 50, "min_burnin_rounds": 1, "max_burnin_rounds": 2,
                "n_stationary": 100, "max_stationary": 100, "n_proposal": 100, "start_maxfev": 100}
"""Sampler settings of ``--tiny`` runs: every stage runs, none long."""

TINY_MAXIMISER = {"step_decades": 4, "min_step_decades": 4, "max_sweeps": 1, "max_trials": 2}


def _tiny_spec(spec, **sampler):
    """``spec`` (a StudySpec) at the tiny settings."""
    return spec.model_copy(update={"sampler": spec.sampler.model_copy(update={**TINY_SAMPLER, **sampler}),
                                   "maximiser": spec.maximiser.model_copy(update=TINY_MAXIMISER)})


def _median_ms(fn, repeats: int, number: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        for _ in range(number):
            fn()
        times.append((time.perf_counter() - t0) / number)
    return statistics.median(times) * 1e3


_FIRST_CALL = """
import time, json, sys
t0 = time.perf_counter()
from ardflow.ardcore.likelihood.simulate import simulate_reference
from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.model.library import builtin, AERO_TRUE
ds = simulate_reference(1)
t1 = time.perf_counter()
cm = compile_model(builtin("M2"))
ll = cm.loglik([AERO_TRUE[k] for k in cm.param_names], ds)
print(json.dumps({"first_call_s": time.perf_counter() - t1}))
"""


def first_call_seconds(cache: str) -> float:
    env = dict(os.environ, ARDFLOW_CACHE_DIR=cache)
    r = subprocess.run([sys.executable, "-c", _FIRST_CALL], capture_output=True, text=True, env=env, check=True)
    return json.loads(r.stdout.strip().splitlines()[-1])["first_call_s"]


def bench_ekf(tiny: bool = False) -> dict:
    from ardflow.ardcore.likelihood.ekf import compile_model
    from ardflow.ardcore.model.library import AERO_GAMMA_EKF, AERO_TRUE, builtin
    from ardflow.ardcore.likelihood.simulate import simulate_reference
    from tests.bench.baselines import ekf_m2_handwritten, ekf_m2_numpy

    ds = simulate_reference(1)
    cm = compile_model(builtin("M2"))
    p = np.array([AERO_TRUE[k] for k in cm.param_names])
    lik = cm.bind(ds, substeps=10)
    t, y = ds.t, ds.columns["y"]
    ll_gen = lik(p)
    ll_hand = ekf_m2_handwritten(p, t, y, 10, AERO_GAMMA_EKF, 0.01)
    ll_np = ekf_m2_numpy(p, t, y, 10, AERO_GAMMA_EKF)
    assert abs(ll_gen - ll_hand) < 1e-6 * abs(ll_gen), (ll_gen, ll_hand)
    assert abs(ll_gen - ll_np) < 1e-6 * abs(ll_gen), (ll_gen, ll_np)
    rep, num = (1, 2) if tiny else (15, 20)
    subs = (1, 2) if tiny else (1, 2, 5, 10, 20, 50, 100, 200)
    gen_ms = _median_ms(lambda: lik(p), repeats=rep, number=num)
    hand_ms = _median_ms(lambda: ekf_m2_handwritten(p, t, y, 10, AERO_GAMMA_EKF, 0.01), repeats=rep, number=num)
    np_ms = _median_ms(lambda: ekf_m2_numpy(p, t, y, 10, AERO_GAMMA_EKF), repeats=1 if tiny else 3, number=1)
    table = {str(n): cm.loglik(p, ds, substeps=n) for n in subs}
    # the same model with RK4 sub-steps (the default scheme of a new model), and the cost per sub-step
    rk = compile_model(builtin("M2").model_copy(update={"integrator": "rk4"}).revalidate())
    table_rk4 = {str(n): rk.loglik(p, ds, substeps=n) for n in subs}
    rk_lik = rk.bind(ds, substeps=2)
    rk4_ms = _median_ms(lambda: rk_lik(p), repeats=rep, number=num)
    sb = silverbox_substep_table(tiny)
    with tempfile.TemporaryDirectory() as cache:
        cold = first_call_seconds(cache)
        warm = first_call_seconds(cache)
    return {
        "ekf_m2_ms": gen_ms,
        "ekf_numpy_ms": np_ms,
        "ekf_speedup": np_ms / gen_ms,
        "ekf_handwritten_ms": hand_ms,
        "ekf_vs_handwritten": gen_ms / hand_ms,
        "ekf_compile_first_call_s": cold,
        "ekf_cached_first_call_s": warm,
        "ekf_m2_loglik": ll_gen,
        "ekf_m2_substep_table": table,
        "ekf_m2_rk4_substep_table": table_rk4,
        "ekf_m2_rk4_2sub_ms": rk4_ms,
        **sb,
    }


def bench_records(tiny: bool = False, k: int = 4) -> dict:
    """A study of ``k`` equal records: one likelihood evaluation of the joined records (one kernel call) against
    ``k`` single-record evaluations (M2 on ``k`` seeds of the reference data), in the same run."""
    from ardflow.ardcore.data import join_records
    from ardflow.ardcore.likelihood.ekf import compile_model
    from ardflow.ardcore.likelihood.simulate import simulate_reference
    from ardflow.ardcore.model.library import AERO_TRUE, builtin

    recs = [simulate_reference(s) for s in range(1, k + 1)]
    if tiny:
        recs = [r.slice(0, 500) for r in recs]
    cm = compile_model(builtin("M2"))
    p = np.array([AERO_TRUE[n] for n in cm.param_names])
    singles = [cm.bind(r, substeps=10) for r in recs]
    joined = cm.bind(join_records(recs), substeps=10)
    assert abs(joined(p) - sum(f(p) for f in singles)) < 1e-8 * abs(joined(p))
    rep, num = (1, 2) if tiny else (15, 10)
    one = _median_ms(lambda: [f(p) for f in singles], repeats=rep, number=num)
    all_ = _median_ms(lambda: joined(p), repeats=rep, number=num)
    return {"records_k": k, "records_single_ms": one, "records_joined_ms": all_,
            "records_cost_ratio": all_ / one}


def silverbox_substep_table(tiny: bool = False) -> dict:
    """Sub-step convergence on Silverbox: ln L on the estimation segment and the multisine free-run error of a
    Duffing model with input feedthrough (parameters fitted once by the loop, rounded), per scheme and hold."""
    from ardflow.ardcore.data import SILVERBOX_SPLITS, load_silverbox
    from ardflow.ardcore.likelihood.ekf import compile_model
    from ardflow.ardcore.model.declaration import ModelSpec

    d = load_silverbox()
    est, test = d.slice(*SILVERBOX_SPLITS["estimation"]), d.slice(*SILVERBOX_SPLITS["test_multisine"])
    phi = {"k": 1.845e5, "c": 41.94, "b": 1.941e5, "sigma": 1.986, "gamma": 1.261e-4, "k3": 7.228e5, "off": 997.8,
           "e": -0.03706}
    out = {}
    schemes = (("euler", "zoh"), ("euler", "foh"), ("rk4", "zoh"), ("rk4", "foh"))
    if tiny:
        est, test, schemes = est.slice(0, 500), test.slice(0, 300), schemes[:1]
    for integ, hold in schemes:
        spec = ModelSpec(name="sb", states=["y", "v"], inputs=["u"], diffusion={"v": "sigma"},
                         drift={"y": "v", "v": "-k*y - c*v - k3*y**3 - off + b*u"},
                         observations=[{"column": "y", "expr": "y + e*u", "noise_std": "gamma"}],
                         parameters=list(phi), initial_std={"y": 0.1, "v": 10.0}, integrator=integ, input_hold=hold)
        cm = compile_model(spec)
        row = {}
        for n in (1, 2) if tiny else (1, 2, 5, 20, 100):
            x0 = cm.filter(phi, test.slice(0, 51), n).filtered[-1]
            rest = test.slice(50, None)
            _, H = cm.simulate(phi, rest.t, x0=x0, inputs=rest.columns["u"][:, None], nsub=n, noise=False)
            row[str(n)] = {"loglik": cm.loglik(phi, est, n),
                           "free_run_mv": 1e3 * float(np.sqrt(np.mean((H[:, 0] - rest.columns["y"]) ** 2)))}
        out[f"ekf_silverbox_{integ}_{hold}_substep_table"] = row
    return out


def _m2_target(psi):
    from ardflow.ardcore.evidence.evaluate import build_target
    from ardflow.ardcore.likelihood.simulate import simulate_reference
    from ardflow.ardcore.selection.spec import load_spec

    spec = load_spec(Path(__file__).resolve().parents[2] / "examples" / "sec35.json")
    cand = spec.models[0]
    return build_target(cand.model_spec(), dict(cand.priors), psi, simulate_reference(1))


def bench_engine(tiny: bool = False) -> dict:
    """Evidence noise over independent seeds, and single-core sampler throughput (M2, reference data)."""
    from concurrent.futures import ProcessPoolExecutor

    from ardflow.ardcore.evidence.estimators import chib_jeliazkov
    from ardflow.ardcore.sampling.chains import ChainState, executor_map, run_round
    from ardflow.ardcore.sampling.config import SamplerConfig
    from ardflow.ardcore.sampling.driver import Runtime, sample

    psi = {"a3": 1e-4, "a4": 1e-5, "a5": float("inf"), "a6": float("inf")}  # the paper's psi_opt
    target = _m2_target(psi)
    cfg = SamplerConfig(**TINY_SAMPLER) if tiny else SamplerConfig()
    vals, ses, walls = [], [], []
    with ProcessPoolExecutor(2) as ex:
        mf = executor_map(ex)
        for seed in range(2 if tiny else 5):
            t0 = time.perf_counter()
            res = sample(target, cfg, seed=1000 + seed, runtime=Runtime(map_fn=mf))
            ev = chib_jeliazkov(target, res, n_proposal=cfg.n_proposal, seed=2000 + seed, map_fn=mf)
            walls.append(time.perf_counter() - t0)
            vals.append(ev.log_evidence)
            ses.append(ev.log_evidence_se)
            print(f"  seed {seed}: ln Z = {ev.log_evidence:.3f} +- {ev.log_evidence_se:.3f} ({walls[-1]:.1f} s)", flush=True)
    # single-core throughput: one chain, stationary (one evaluation per sample)
    x = np.array(res.phi_star)
    lp, ll = target(x)
    st = ChainState(0, x.tolist(), lp, ll, np.random.PCG64(0).state, x.tolist(), lp, ll)
    t0 = time.perf_counter()
    r = run_round(target, st, res.proposal_cov, 100 if tiny else 3000, adaptive=False)
    rate = r.samples.shape[0] / (time.perf_counter() - t0)
    return {
        "sampler_step_us": _sampler_step_us(target, res, 200 if tiny else 20_000),
        "evidence_sd_nats": float(np.std(vals, ddof=1)),
        "evidence_values": vals,
        "evidence_se_mean": float(np.mean(ses)),
        "evidence_wall_s_mean": float(np.mean(walls)),
        "mcmc_samples_per_s": rate,
    }


def _sampler_step_us(target, res, n: int) -> float:
    """The sampler's own time per step, in microseconds: a stationary round (the random walk mixed with the
    independence proposal, as the stationary stage draws) on ``target``'s prior with a likelihood that costs
    nothing, so what is timed is the proposal, its densities, the coordinates' map and the prior."""
    from ardflow.ardcore.likelihood.posterior import FunctionTarget
    from ardflow.ardcore.sampling.chains import ChainState, run_round
    from ardflow.ardcore.sampling.proposal import Jump
    from ardflow.ardcore.sampling.transform import free_coordinates

    costless = FunctionTarget(target.names, target.prior, lambda x: 0.0)
    x = np.array(res.phi_star)
    lp, ll = costless(x)
    st = ChainState(0, x.tolist(), lp, ll, np.random.PCG64(0).state, x.tolist(), lp, ll)
    cov = np.asarray(res.proposal_cov, float)  # in the chain's coordinates, as the sampler keeps it
    jump = Jump(free_coordinates(target).to_free(x), 4.0 * cov, 0.5, 5.0)
    t0 = time.perf_counter()
    run_round(costless, st, cov, n, adaptive=False, jump=jump)
    return (time.perf_counter() - t0) / n * 1e6


def _dir_mb(path) -> float:
    return sum(f.stat().st_size for f in Path(path).rglob("*") if f.is_file()) / 1e6


def bench_dask(tiny: bool = False) -> dict:
    """Scaling of chain throughput with workers, orchestration overhead, store size (M2, reference data)."""
    from concurrent.futures import ProcessPoolExecutor

    from ardflow.ardcore.evidence.evaluate import EvidenceEvaluator, EvidenceSettings
    from ardflow.ardcore.sampling.config import SamplerConfig
    from ardflow.ardcore.sampling.chains import executor_map
    from ardflow.ardcore.sampling.driver import Runtime, sample
    from ardflow.ardcore.likelihood.simulate import simulate_reference
    from ardflow.ardcore.selection.spec import load_spec
    from ardflow.workers.cluster import ClusterClient
    from ardflow.workers.tasks import DaskMap
    from ardflow.workers.graph import StoredEvaluator, TrialSite
    from ardflow.workers.store import StudyStore

    psi = {"a3": 1e-4, "a4": 1e-5, "a5": float("inf"), "a6": float("inf")}
    target = _m2_target(psi)
    cfg = SamplerConfig(**{**TINY_SAMPLER, "n_chains": 4}) if tiny else \
        SamplerConfig(n_chains=4, round_size=500, n_stationary=3000, n_proposal=2000)
    rates = {}
    for nw in (1, 2):
        with ClusterClient(None, nw) as c:  # the cluster a study starts (its workers configured as they run there)
            sample(target, SamplerConfig(n_chains=4, round_size=50, n_stationary=50, n_proposal=50,
                                         min_burnin_rounds=1, max_burnin_rounds=1, max_stationary=50),
                   seed=0, runtime=Runtime(map_fn=DaskMap(c, f"warm{nw}")))
            t0 = time.perf_counter()
            res = sample(target, cfg, seed=1, runtime=Runtime(map_fn=DaskMap(c, f"scale{nw}")))
            n_chain_samples = cfg.n_chains * (res.burnin_rounds * cfg.round_size + res.samples.shape[1])
            rates[nw] = n_chain_samples / (time.perf_counter() - t0)
        print(f"  {nw} worker(s): {rates[nw]:.0f} samples/s", flush=True)

    spec = load_spec(Path(__file__).resolve().parents[2] / "examples" / "sec35.json")
    cand = spec.models[0]
    data = simulate_reference(1)
    import tempfile

    # the same trial (seed 12) in a plain process pool and through Dask and the store, in turns (a shared
    # machine's speed drifts between runs): each one's median of ``repeats``
    repeats = 1 if tiny else 3
    t_in, t_dask = [], []
    with ProcessPoolExecutor(2) as ex, tempfile.TemporaryDirectory() as d, ClusterClient(None, 2) as c:
        ev = EvidenceEvaluator(cand.model_spec(), dict(cand.priors), data, EvidenceSettings(cfg),
                               runtime=Runtime(map_fn=executor_map(ex)))
        store = StudyStore.create(Path(d) / "st", spec.model_dump(mode="json"), data)
        se = StoredEvaluator(cand.model_spec(), dict(cand.priors), data, EvidenceSettings(cfg),
                             site=TrialSite(c, store, "bench", "M2"))
        ev(psi, 11, None)  # warm the pool and the workers
        se(psi, 11, None, iteration=0)
        for k in range(repeats):
            t0 = time.perf_counter()
            ev(psi, 12, None)
            t_in.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            _, _, res = se(psi, 12, None, iteration=k + 1)  # a new trial of the store each time
            t_dask.append(time.perf_counter() - t0)
        mb = _dir_mb(Path(d) / "st" / "models" / "M2" / "trials" / "001")
        n_samples = res.samples.shape[0] * res.samples.shape[1]
    t_in, t_dask = float(np.median(t_in)), float(np.median(t_dask))
    print(f"  in-process {t_in:.1f} s, orchestrated {t_dask:.1f} s", flush=True)
    return {
        "dask_samples_per_s_1w": rates[1],
        "dask_samples_per_s_2w": rates[2],
        "dask_scaling_2w": rates[2] / rates[1],
        "dask_overhead": t_dask / t_in - 1.0,
        "dask_trial_wall_s": t_dask,
        "inprocess_trial_wall_s": t_in,
        "store_mb_per_1e6_samples": mb / n_samples * 1e6,
    }


def bench_api(tiny: bool = False) -> dict:
    """The service under load (real ``ardflow serve`` over HTTP, 2 drivers at most): 50 concurrent
    submissions of the Sec 3.3 study by three users and a large data-set upload (500,000 rows) while 20
    clients poll the studies' status.

    Keys: api_status_p95_ms / _p99_ms / _p50_ms (status latency under that load), api_upload_s, api_requests, api_errors (answers
    other than 200/202 to valid requests), api_rss_mb (largest resident memory of the API process),
    api_max_drivers (most studies ``running`` at once, as the status reports them), api_max_running (the
    setting), api_queued_seen (most studies ``queued`` at once).
    """
    import asyncio
    import json as _json
    import signal
    import tempfile

    import httpx

    token, max_running = "bench-token", 2
    n_submit, n_clients, n_polls = (2, 2, 3) if tiny else (50, 20, 40)
    # three users submit (each under the per-token limit of 20); the admin's token polls every study
    users = {f"user{i}": f"bench-user-{i}" for i in range(3)}
    root = Path(tempfile.mkdtemp())
    p, base = _serve(root, {"admin": token, **users}, "--max-running", str(max_running))
    h = {"X-API-Token": token}

    def rss_mb() -> float:
        try:
            for line in Path(f"/proc/{p.pid}/status").read_text().splitlines():
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024
        except OSError:
            pass
        return float("nan")

    try:
        spec = _json.loads((Path(__file__).resolve().parents[2] / "examples" / "sec33.json").read_text())
        ids: list[str] = []
        lat: list[float] = []
        errors: list = []
        peak = {"running": 0, "queued": 0, "rss": rss_mb()}

        async def submit(c, i):
            who = list(users.values())[i % len(users)]
            r = await c.post(f"{base}/studies", json=dict(spec, seed=100 + i), headers={"X-API-Token": who})
            if r.status_code != 202:
                errors.append(("submit", r.status_code, r.text[:200]))
            else:
                ids.append(r.json()["id"])

        async def poll(c, n):
            while not ids:
                if sum(e[0] == "submit" for e in errors) >= n_submit:
                    return  # every submission refused: nothing to poll (the errors are reported)
                await asyncio.sleep(0.05)
            k = 0
            while k < n or "upload_s" not in peak:  # status is measured while the upload is parsed
                k += 1
                t0 = time.perf_counter()
                r = await c.get(f"{base}/studies/{ids[len(lat) % len(ids)]}")
                lat.append((time.perf_counter() - t0) * 1e3)
                if r.status_code != 200:
                    errors.append(("status", r.status_code))
                await asyncio.sleep(0.02)

        async def watch(c, stop):
            while not stop.is_set():
                r = await c.get(f"{base}/studies")
                if r.status_code == 200:
                    st = [x["status"] for x in r.json()]
                    peak["running"] = max(peak["running"], st.count("running"))
                    peak["queued"] = max(peak["queued"], st.count("queued"))
                peak["rss"] = max(peak["rss"], rss_mb())
                await asyncio.sleep(0.25)

        rows = 2000 if tiny else 500_000
        csv = ("t,y\n" + "".join(f"{i * 0.01:.2f},{math.sin(i * 0.01):.6f}\n" for i in range(rows))).encode()

        async def upload(c):
            t0 = time.perf_counter()
            r = await c.post(f"{base}/datasets", content=csv, headers={"Content-Type": "text/csv"})
            peak["upload_s"] = time.perf_counter() - t0
            if r.status_code != 201:
                errors.append(("upload", r.status_code, r.text[:200]))

        async def main():
            stop = asyncio.Event()
            async with httpx.AsyncClient(headers=h, timeout=120) as c:
                w = asyncio.create_task(watch(c, stop))
                await asyncio.gather(upload(c), *(submit(c, i) for i in range(n_submit)),
                                     *(poll(c, n_polls) for _ in range(n_clients)))
                await asyncio.sleep(1 if tiny else 5)
                stop.set()
                await w

        asyncio.run(main())
        for sid in ids:
            httpx.post(f"{base}/studies/{sid}/cancel", headers=h, json={})
    finally:
        os.killpg(p.pid, signal.SIGKILL)
    return {"api_status_p95_ms": float(np.percentile(lat, 95)) if lat else float("nan"),
            "api_status_p99_ms": float(np.percentile(lat, 99)) if lat else float("nan"),
            "api_upload_s": peak.get("upload_s", float("nan")),
            "api_status_p50_ms": float(np.percentile(lat, 50)) if lat else float("nan"),
            "api_requests": len(lat), "api_errors": len(errors), "api_error_samples": errors[:5],
            "api_rss_mb": peak["rss"], "api_max_drivers": peak["running"], "api_max_running": max_running,
            "api_queued_seen": peak["queued"], "api_submitted": len(ids)}


def _serve(root: Path, tokens: dict, *args: str) -> tuple[subprocess.Popen, str]:
    """``ardflow serve`` on ``root`` with ``tokens`` (owner -> token) and ``args``, in its own session; returns
    the process and its API's base URL once it answers (the caller kills its process group)."""
    import socket

    import httpx

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    tokens_file = root.parent / f"{root.name}-tokens.json"
    tokens_file.write_text(json.dumps(tokens))
    p = subprocess.Popen([sys.executable, "-m", "ardflow.service.cli", "serve", "--port", str(port), "--root", str(root),
                          "--tokens-file", str(tokens_file), *args],
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    base = f"http://127.0.0.1:{port}/v1"
    for _ in range(600):
        try:
            if httpx.get(f"{base}/health", timeout=1).status_code == 200:
                break
        except httpx.HTTPError:
            time.sleep(0.2)
    return p, base


def bench_listing(tiny: bool = False) -> dict:
    """``GET /v1/studies`` with 1,000 finished studies in the registry (real ``ardflow serve`` over HTTP): a user
    who owns 10 of them, and the admin who sees every one (the first page, 200), each listing 200 times in a row.

    Keys: api_listing_studies (the registry's size), api_listing_user_p50_ms / _p99_ms, api_listing_admin_p50_ms /
    _p99_ms. The registry is written directly (each study a registry entry and a store that says done), the way
    a long-running service's registry looks; the service is started on it as after a restart.
    """
    import signal
    import tempfile

    import httpx

    from ardflow.workers.store import StudyStore

    n, n_mine, n_req = (40, 4, 20) if tiny else (1000, 10, 200)
    root = Path(tempfile.mkdtemp())
    tokens = {"admin": "bench-admin", "mine": "bench-mine", "other": "bench-other"}
    for i in range(n):
        sid = f"listed-{i:08x}"
        d = root / "studies" / sid
        d.mkdir(parents=True)
        (d / "meta.json").write_text(json.dumps({"id": sid, "name": "listed", "created": 1.7e9 + i,
                                                 "owner": "mine" if i % (n // n_mine) == 0 else "other"}))
        StudyStore(d / "store").update_meta(study_id=sid, status="done")
    p, base = _serve(root, tokens, "--workers", "1")
    out = {"api_listing_studies": n}
    try:
        for who in ("user", "admin"):
            h = {"X-API-Token": tokens["mine" if who == "user" else "admin"]}
            with httpx.Client(headers=h, timeout=60) as c:
                got = c.get(f"{base}/studies").json()
                assert len(got) == (n_mine if who == "user" else min(n, 200)), len(got)
                lat = []
                for _ in range(n_req):
                    t0 = time.perf_counter()
                    c.get(f"{base}/studies").raise_for_status()
                    lat.append((time.perf_counter() - t0) * 1e3)
            out[f"api_listing_{who}_p50_ms"] = float(np.percentile(lat, 50))
            out[f"api_listing_{who}_p99_ms"] = float(np.percentile(lat, 99))
    finally:
        os.killpg(p.pid, signal.SIGKILL)
    return out


def _study(args: list[str], out: Path) -> dict:
    """Run an ardflow command that writes a Section 3.6 study to ``out`` (fresh); wall time and results."""
    import shutil

    from ardflow.service.reports.paper import reference_checks

    shutil.rmtree(out, ignore_errors=True)
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "ardflow.service.cli", *args, "--out", str(out)], check=True,
                   stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    s = json.loads((out / "summary.json").read_text())
    eff = study_efficiency(out, wall)
    spec = json.loads((ROOT / "examples" / "sec36.json").read_text())
    return {"wall_s": wall,
            "evidence_se": {r["name"]: r["log_evidence_se"] for r in s["models"]},
            "log_evidence": {r["name"]: r["log_evidence"] for r in s["models"]},
            "probability": {r["name"]: r["probability"] for r in s["models"]},
            "pruned": {r["name"]: r["pruned"] for r in s["models"]},
            "trials": {r["name"]: r["iterations"] for r in s["models"]},
            "sampled_trials": {r["name"]: r.get("sampled_trials") for r in s["models"]},
            # every likelihood evaluation: start optimisation, burn-in, stationary draws, Chib-Jeliazkov proposals
            "evaluations": sum(int(r.get("n_evaluations", 0)) for r in s["models"]),
            "checks": {c["check"]: c["passed"] for c in reference_checks(s, spec["true_values"])},
            # the table the worked example prints (README, generated)
            "table": [{k: r.get(k) for k in ("name", "log_evidence", "log_evidence_se", "goodness_of_fit",
                                             "information_gain", "probability", "kept", "pruned")}
                      for r in s["models"]],
            "efficiency": eff["efficiency"], "likelihood_s": eff["likelihood_s"], "efficiency_models": eff["per_model"],
            **_store_convergence(out)}


def study_efficiency(out: Path, wall: float, cores: int | None = None) -> dict:
    """The share of the hardware a finished study spent in likelihoods: (sum over models of its evaluations x that
    model's single-core likelihood time on the study's data) / (cores x wall). The likelihood time is the median of
    repeated calls of the candidate's full model (its ARD terms at their posterior means or 0), measured here on
    one core; 1 means the study did nothing but evaluate likelihoods on every core."""
    from ardflow.ardcore.likelihood.ekf import compile_model
    from ardflow.ardcore.selection.spec import StudySpec
    from ardflow.workers.store import StudyStore

    store = StudyStore(next(p.parent for p in out.rglob("zarr.json") if (p.parent / "models").is_dir()))
    spec = StudySpec.model_validate(store.meta["spec"])
    data = store.load_data()
    summary = json.loads((out / "summary.json").read_text())
    work, per_model = 0.0, {}
    for r in summary["models"]:
        cand = next(c for c in spec.models if c.label == r["name"])
        ms = cand.model_spec()
        lik = compile_model(ms).bind(data, cand.substeps)
        phi = np.array([float((r.get("mean") or {}).get(p, (r.get("map") or {}).get(p, 0.0))) for p in ms.free_parameters])
        lik(phi)
        ms_each = _median_ms(lambda: lik(phi), repeats=7, number=10)
        per_model[r["name"]] = {"evaluations": int(r.get("n_evaluations", 0)), "likelihood_ms": ms_each}
        work += int(r.get("n_evaluations", 0)) * ms_each / 1e3
    cores = cores or os.cpu_count() or 1
    return {"efficiency": work / (cores * wall), "likelihood_s": work, "per_model": per_model}


def _store_convergence(out: Path) -> dict:
    """Every model's reported draws read from the zarr store with zarr itself and judged by ArviZ's
    ``az.summary`` (not the project's own diagnostics): the worst R-hat and the smallest bulk or tail ESS."""
    import arviz as az
    import zarr

    stores = [p for p in out.rglob("zarr.json") if (p.parent / "models").is_dir()]
    if not stores:
        return {}
    g = zarr.open_group(str(stores[0].parent), mode="r")
    rhat, ess = {}, {}
    for name, mg in g["models"].groups():
        it = mg.attrs.get("best_iteration")
        if it is None:
            continue
        tg = mg[f"trials/{int(it):03d}"]
        x = np.asarray(tg["samples"][:])
        names = [str(v) for v in tg["param"][:]]
        t = az.summary(az.from_dict({"posterior": {f"p{i}": x[..., i] for i in range(len(names))}}),
                       kind="diagnostics", round_to="none")
        rhat[name] = float(t["r_hat"].max())
        ess[name] = float(min(t["ess_bulk"].min(), t["ess_tail"].min()))
    return {"max_rhat": max(rhat.values()), "min_ess": min(ess.values()),
            "max_rhat_per_model": rhat, "min_ess_per_model": ess}


def bench_posterior(tiny: bool = False, seeds: int = 10, models: tuple = ("M2", "M3"), full: bool = False) -> dict:
    """The sampler on Sec 3.6's M2 and M3 at their optimal psi, demo settings, ``seeds`` seeds: the reported
    ln Z standard error against the seed-to-seed sd (``evidence_se_ratio``: mean se / sd of the model furthest
    from 1, which is honest; per model beside it), and
    ArviZ's ESS per likelihood evaluation with the independence proposal against the plain random walk.
    With ``full`` the paper-scale settings (``--full``), keys ``posterior_full_*`` and
    ``evidence_se_ratio_full``, no random-walk comparison."""
    from concurrent.futures import ProcessPoolExecutor

    from ardflow.ardcore.sampling.diagnostics import convergence
    from ardflow.ardcore.evidence.evaluate import build_target
    from ardflow.ardcore.evidence.estimators import chib_jeliazkov
    from ardflow.ardcore.sampling.chains import executor_map
    from ardflow.ardcore.sampling.driver import Runtime, sample
    from ardflow.ardcore.selection.spec import StudySpec

    spec = StudySpec.model_validate(json.loads((ROOT / "examples" / "sec36.json").read_text()))
    if full:
        from ardflow.service.commands.study import full_settings

        spec = full_settings(spec)
    if tiny:
        spec, seeds, models = _tiny_spec(spec), 2, ("M2",)
    pre, post = ("posterior_full_", "_full") if full else ("posterior_", "")
    data = spec.data.load()
    psi = {"a3": 1e-4, "a4": 1e-5, "a5": math.inf, "a6": math.inf}
    out: dict = {}
    ratios = []
    with ProcessPoolExecutor(2) as ex:
        mf = executor_map(ex)
        for label in models:
            cand = next(c for c in spec.models if c.label == label)
            target = build_target(cand.model_spec(), dict(cand.priors), psi, data, cand.substeps)
            lz, se, epe = [], [], []
            for seed in range(seeds):
                res = sample(target, spec.sampler, seed=100 + seed, runtime=Runtime(map_fn=mf))
                ev = chib_jeliazkov(target, res, n_proposal=spec.sampler.n_proposal, seed=seed + 7, map_fn=mf,
                                    proposal_se_ratio=spec.sampler.proposal_se_ratio)
                lz.append(ev.log_evidence)
                se.append(ev.log_evidence_se)
                d = convergence(list(res.names), res.samples)
                epe.append(min(min(v["ess_bulk"], v["ess_tail"]) for v in d.values()) / res.n_evaluations)
            sd = float(np.std(lz, ddof=1))
            out[f"{pre}{label}_lnz"] = lz
            out[f"{pre}{label}_lnz_sd"] = sd
            out[f"{pre}{label}_se_mean"] = float(np.mean(se))
            out[f"{pre}{label}_ess_per_evaluation"] = float(np.mean(epe))
            ratios.append(float(np.mean(se)) / sd if sd > 0 else math.nan)
            if full:
                continue
            # the same target with the plain random walk of method.md (jump_weight 0), one seed
            rw = sample(target, spec.sampler.model_copy(update={"jump_weight": 0.0, "max_stationary": None}),
                        seed=100, runtime=Runtime(map_fn=mf))
            d = convergence(list(rw.names), rw.samples)
            out[f"posterior_{label}_ess_per_evaluation_random_walk"] = (
                min(min(v["ess_bulk"], v["ess_tail"]) for v in d.values()) / rw.n_evaluations)
    # the headline is the model whose reported error is furthest from its seed spread (either way)
    out[f"evidence_se_ratio{post}"] = max(ratios, key=lambda r: abs(math.log(r)) if r > 0 else math.inf)
    out[f"evidence_se_ratio{post}_per_model"] = dict(zip(models, ratios))
    return out


def bench_posterior_full(tiny: bool = False) -> dict:
    """:func:`bench_posterior` at the paper-scale settings (8 seeds)."""
    return bench_posterior(tiny, seeds=8, full=True)


def bench_study(tiny: bool = False) -> dict:
    """`make demo`'s study and the paper-scale one (`--full`), end to end on the embedded cluster."""
    if tiny:
        from ardflow.ardcore.selection.spec import load_spec

        spec = _tiny_spec(load_spec(ROOT / "examples" / "sec36.json"))
        path = Path(tempfile.mkdtemp()) / "sec36_tiny.json"
        path.write_text(spec.model_dump_json())
        demo = _study(["select", str(path), "--workers", "2"], path.parent / "study")
        full = dict(demo)
    else:
        demo = _study(["demo"], ROOT / ".bench" / "study_demo")
        # the README's picture is the demo report's evidence figure, as this run drew it
        import shutil

        (ROOT / "docs" / "img").mkdir(exist_ok=True)
        shutil.copyfile(ROOT / ".bench" / "study_demo" / "report" / "evidence.png", ROOT / "docs" / "img" / "evidence.png")
        full = _study(["select", str(ROOT / "examples" / "sec36.json"), "--full"], ROOT / ".bench" / "study_full")
    out = {"study_demo_s": demo.pop("wall_s"), "study_full_s": full.pop("wall_s")}
    out.update({f"study_demo_{k}": v for k, v in demo.items()})
    out.update({f"study_full_{k}": v for k, v in full.items()})
    return out


def _after_mv(rep, seg: dict) -> dict:
    """Free-run RMS errors (mV) on the Silverbox test segments of the one model the loop reports
    (``<segment>``) and of its structure at the posterior mean (``<segment>_posterior_mean``)."""
    out = {}
    for k in ("multisine", "arrow"):
        out[k] = 1e3 * rep.final.free_run(seg[f"test_{k}"])["rms_error"]
        out[f"{k}_posterior_mean"] = 1e3 * (rep.posterior or rep.final).free_run(seg[f"test_{k}"])["rms_error"]
    return out


def bench_loop(tiny: bool = False) -> dict:
    """The closed loop on the real records, and the peers on the same data and splits, in one run.

    Silverbox: fit on the estimation segment, free run on the multisine and arrow test segments (first 50
    samples initialise). Pendulum: fit 2-40 s, free run 40-120 s. Reference data: the loop on the 5000-point
    record (M2's data-generating form, one round). The pendulum is the real record when ``$ARDFLOW_DATA`` holds it,
    else the synthetic stand-in (``loop_pendulum_record`` says which). Keys: loop_silverbox_{multisine,arrow}_mv (after the loop: the one
    model it reports; ..._posterior_mean_mv its structure at the posterior mean; loop_silverbox_noise_factor, the
    process-noise factor of the reported model, ``ardcore.loop.simulation_fit``),
    ..._before_mv, loop_silverbox_s, loop_pendulum_rad (+ _before), loop_pendulum_s, loop_reference_s,
    loop_peer_{arx,narx,pysindy,sysidentpy}_{multisine,arrow}_mv, loop_peer_best_multisine_mv,
    loop_peer_best_arrow_mv, loop_peer_narx_pendulum_rad, loop_silverbox_added, loop_pendulum_added,
    loop_silverbox_samples and loop_silverbox_rounds (the record's length and the rounds run in loop_silverbox_s),
    loop_silverbox_multisine_band_coverage and loop_pendulum_band_coverage (the held-out data's share inside the
    final model's 90 % posterior predictive band), loop_silverbox_states_ratio (:func:`states_ratio` on that
    65k-sample record: what the state families cost beside a round's terms, at most 2; written when a round ran
    them).
    """
    from ardflow.ardcore.data import SILVERBOX_SPLITS, load_pendulum, load_silverbox
    from ardflow.ardcore.loop.config import DiagnoseConfig
    from ardflow.ardcore.loop.diagnose import diagnose
    from ardflow.ardcore.likelihood.simulate import simulate_reference
    from ardflow.ardcore.selection.spec import StudySpec, load_spec

    from . import peers

    from ardflow.ardcore.data import PENDULUM_RELPATH, external_path

    from ..pendulum_standin import pendulum_folder

    out: dict = {}
    full = load_silverbox()
    seg = {k: full.slice(*v) for k, v in SILVERBOX_SPLITS.items()}
    # --tiny: short records and the tiny sampler (the same code path, nothing measured)
    cut = (lambda d, n: d.slice(0, n)) if tiny else (lambda d, n: d)
    shrink = _tiny_spec if tiny else (lambda spec: spec)
    # --tiny: one round on Silverbox (every move's code runs), none on the pendulum and the reference data
    rounds, pendulum_rounds, reference_rounds = (1, 0, 0) if tiny else (3, 3, 1)
    if tiny:
        seg = {k: cut(v, 1500 if k == "estimation" else 800) for k, v in seg.items()}
    # -- peers, same data and split
    y, u = seg["estimation"].columns["y"], seg["estimation"].columns["u"]
    tests = {"multisine": (seg["test_multisine"].columns["y"], seg["test_multisine"].columns["u"]),
             "arrow": (seg["test_arrow"].columns["y"], seg["test_arrow"].columns["u"])}
    runs = peers.heads(tests.values())
    arx = peers.tuned_narx(y, u, degrees=(1,), runs=runs)
    narx = peers.tuned_narx(y, u, runs=runs)
    peer = {"arx": {k: arx.free_run_rms(*v) for k, v in tests.items()},
            "narx": {k: narx.free_run_rms(*v) for k, v in tests.items()}}
    for name, fn in (("pysindy", lambda: peers.pysindy_free_run(y, u, tests)),
                     ("sysidentpy", lambda: peers.sysidentpy_free_run(y, u, tests))):
        r = fn()
        if r is not None:
            peer[name] = r
    for name, r in peer.items():
        for k, v in r.items():
            out[f"loop_peer_{name}_{k}_mv"] = 1e3 * v
    out["loop_peer_best_multisine_mv"] = min(1e3 * r["multisine"] for r in peer.values())
    out["loop_peer_best_arrow_mv"] = min(1e3 * r["arrow"] for r in peer.values())
    # -- the loop on Silverbox
    spec = shrink(load_spec(ROOT / "examples" / "silverbox_diagnose.json"))
    t0 = time.perf_counter()
    # `ardflow diagnose`'s defaults: three rounds after the first, then the simulation fit
    est = cut(spec.data.load(ROOT / "examples"), 1500)
    rep = diagnose(spec, est, test_data=seg["test_multisine"],
                   config=DiagnoseConfig(max_rounds=rounds), progress=lambda m: print("  " + m, flush=True))
    out["loop_silverbox_s"] = time.perf_counter() - t0
    # the long-record contract: this many samples through this many rounds in loop_silverbox_s
    out["loop_silverbox_samples"] = len(est)
    out["loop_silverbox_rounds"] = len(rep.report["rounds"])
    if states_ratio(rep.report) is not None:  # a round that took a noise level alone runs no state family
        out["loop_silverbox_states_ratio"] = states_ratio(rep.report)
    out["loop_silverbox_multisine_before_mv"] = 1e3 * rep.report["before"]["free_run"]["rms_error"]
    out["loop_silverbox_arrow_before_mv"] = 1e3 * rep.initial.free_run(seg["test_arrow"])["rms_error"]
    out.update({f"loop_silverbox_{k}_mv": v for k, v in _after_mv(rep, seg).items()})
    out["loop_silverbox_noise_factor"] = rep.report["reported"]["noise_factor"]
    # the share of the held-out data inside the final model's 90 % posterior predictive band
    out["loop_silverbox_multisine_band_coverage"] = rep.report["reported"]["free_run"].get("band_coverage")
    out["loop_silverbox_added"] = [a["effect"] + " -> " + a["target"] for a in rep.added]
    # -- the pendulum
    # the real record when $ARDFLOW_DATA holds it (it is not shipped), else the synthetic stand-in
    out["loop_pendulum_record"] = "real" if external_path(PENDULUM_RELPATH) is not None else "stand-in"
    os.environ["ARDFLOW_DATA"] = str(pendulum_folder(Path(tempfile.mkdtemp(prefix="ardflow-pendulum-"))))
    pend = shrink(load_spec(ROOT / "examples" / "pendulum_diagnose.json"))
    pfull = load_pendulum()
    ptest = pfull.slice(40000, None)
    ptest = cut(type(ptest)(ptest.t[::20].copy(), {"y": ptest.columns["y"][::20].copy()}, ptest.meta), 800)
    t0 = time.perf_counter()
    pdata = cut(pend.data.load(ROOT / "examples"), 800)
    prep = diagnose(pend, pdata, test_data=ptest, config=DiagnoseConfig(max_rounds=pendulum_rounds),
                    progress=lambda m: print("  " + m, flush=True))
    out["loop_pendulum_s"] = time.perf_counter() - t0
    out["loop_pendulum_before_rad"] = prep.report["before"]["free_run"]["rms_error"]
    out["loop_pendulum_rad"] = prep.report["reported"]["free_run"]["rms_error"]
    out["loop_pendulum_posterior_mean_rad"] = (prep.posterior or prep.final).free_run(ptest)["rms_error"]
    out["loop_pendulum_noise_factor"] = prep.report["reported"]["noise_factor"]
    out["loop_pendulum_band_coverage"] = prep.report["reported"]["free_run"].get("band_coverage")
    out["loop_pendulum_added"] = [a["effect"] + " -> " + a["target"] for a in prep.added]
    py = pdata.columns["y"]
    pn = peers.tuned_narx(py, np.zeros_like(py), runs=peers.heads([(ptest.columns["y"], np.zeros(len(ptest)))]))
    out["loop_peer_narx_pendulum_rad"] = pn.free_run_rms(ptest.columns["y"], np.zeros(len(ptest)))
    # -- the loop on the 5000-point reference data (M2's data-generating form)
    ref = StudySpec.model_validate({
        "name": "loop", "data": {"generator": "reference", "seed": 3},
        "models": [{"model": "M2true", "priors": {
            "B": {"kind": "lognormal", "median": 0.2, "cov": 50}, "a1": {"kind": "uniform", "low": -2, "high": 0},
            "a2": {"kind": "uniform", "low": -2, "high": 0}, "a3": {"kind": "uniform", "low": -250, "high": 250},
            "a4": {"kind": "uniform", "low": -1000, "high": 0},
            "sigma": {"kind": "lognormal", "median": 0.002, "cov": 50}}}],
        "sampler": {"start_maxfev": 1500, "round_size": 250, "n_stationary": 1000, "n_proposal": 1000},
        "maximiser": {"step_decades": 2, "min_step_decades": 2, "max_sweeps": 1}, "seed": 3})
    ref = shrink(ref)
    if not tiny:
        _save_partial(out)
    t0 = time.perf_counter()
    try:
        rrep = diagnose(ref, cut(simulate_reference(3), 1000), config=DiagnoseConfig(max_rounds=reference_rounds),
                        progress=lambda m: print("  " + m, flush=True))
        out["loop_reference_s"] = time.perf_counter() - t0
        out["loop_reference_added"] = [a["effect"] + " -> " + a["target"] for a in rrep.added]
    except Exception as e:  # recorded, so the Silverbox and pendulum figures above are not lost
        out["loop_reference_error"] = f"{type(e).__name__}: {e}"
    return out


def bench_fresh(tiny: bool = False) -> dict:
    """``make demo`` on a clean clone of HEAD: venv, install, cold kernel cache, the study and its report.

    Key: fresh_demo_s (wall time of ``make demo`` in the clone), fresh_demo_evaluations.
    """
    import shutil
    import tempfile

    tmp = Path(tempfile.mkdtemp(prefix="ardflow-fresh-"))
    try:
        subprocess.run(["git", "clone", "-q", str(ROOT), str(tmp / "ardflow")], check=True)
        clone = tmp / "ardflow"
        env = {k: v for k, v in os.environ.items() if k not in ("VIRTUAL_ENV", "ARDFLOW_CACHE_DIR")}
        env["ARDFLOW_CACHE_DIR"] = str(tmp / "kernel-cache")  # cold: every kernel generated and compiled
        args = []
        if tiny:
            from ardflow.ardcore.selection.spec import load_spec

            (tmp / "tiny.json").write_text(_tiny_spec(load_spec(clone / "examples" / "sec36.json")).model_dump_json())
            args = [f"DEMO_ARGS=--spec {tmp / 'tiny.json'} --workers 2"]
        t0 = time.perf_counter()
        subprocess.run(["make", "demo", *args], cwd=clone, env=env, check=True, stdout=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        s = json.loads((clone / "runs" / "demo" / "summary.json").read_text())
        return {"fresh_demo_s": wall,
                "fresh_demo_evaluations": sum(int(r.get("n_evaluations", 0)) for r in s["models"])}
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


VERDICTS = ROOT / "tests" / "bench" / "verdicts.json"
"""The regression gate's recorded verdicts (:func:`bench_validation`): what the loop did on each validation record
when it was last measured. A change to the loop may improve a verdict, never worsen one."""


def _peers(rec) -> dict:
    """The peers' free-run RMS errors on ``rec``'s test record, each tuned as its users tune it
    (:mod:`tests.bench.peers`): a linear ARX and a polynomial NARX (orders, degree and terms chosen by free run
    on validation blocks of the estimation record, then a simulation-error refit), SysIdentPy and PySINDy."""
    from . import peers

    y = rec.est.columns["y"]
    u = rec.est.columns.get("u", np.zeros_like(y))
    yt = rec.test.columns["y"]
    ut = rec.test.columns.get("u", np.zeros_like(yt))
    runs = peers.heads([(yt, ut)])
    out = {"arx": peers.tuned_narx(y, u, degrees=(1,), runs=runs).free_run_rms(yt, ut),
           "narx": peers.tuned_narx(y, u, runs=runs).free_run_rms(yt, ut)}
    if "u" in rec.est.columns:  # the libraries' NARX and SINDy with a control input
        for p, fn in (("pysindy", peers.pysindy_free_run), ("sysidentpy", peers.sysidentpy_free_run)):
            got = fn(y, u, {"test": (yt, ut)})
            if got is not None:
                out[p] = got["test"]
    return out


def states_ratio(report: dict) -> float | None:
    """The state families' cost against the terms': the largest over a loop's rounds of the time the hysteresis,
    sensor and mode states took (their screen and the full fits it orders; run in every round that does not take
    a noise level alone) over the time the round's additions, laws and lags took (None: no round ran them)."""
    got = [r["states_s"] / r["terms_s"] for r in report.get("rounds", []) if r.get("states_s") and r.get("terms_s")]
    return max(got) if got else None


def bench_states(tiny: bool = False) -> dict:
    """What the state families cost on a long record: the loop on the validation set's sensor-lag record at
    10,000 estimation samples (its truth a linear oscillator read through a first-order sensor, its user model
    the plain oscillator), timed on a warm kernel cache (a first run fills it). Keys: ``states_10k_ratio``
    (:func:`states_ratio`: the hysteresis, sensor and mode states' time over the round's additions, laws and
    lags; issue target <= 2), ``states_10k_samples``,
    ``states_10k_s`` (the loop's wall time), ``states_10k_forms`` (the states it added) and
    ``states_10k_free_run`` (the reported model's free run on the test half)."""
    from ardflow.ardcore.loop.config import DiagnoseConfig
    from ardflow.ardcore.loop.diagnose import diagnose

    from .validation import RECORDS

    rec = RECORDS["sensor_lag"](n=800 if tiny else 20_000)
    # --tiny: the fit and the report only (no round runs the state families)
    args = ((_tiny_spec(rec.spec) if tiny else rec.spec), rec.est)
    kw = {"test_data": rec.test, "config": DiagnoseConfig(max_rounds=0) if tiny else DiagnoseConfig()}
    if not tiny:
        # the timed run reads every kernel from the cache: on a cold one the terms' rounds also compile their
        # candidates' kernels, and the ratio came out 2.0 against 4.7 warm
        diagnose(*args, **kw)
    t0 = time.perf_counter()
    rep = diagnose(*args, **kw, progress=lambda m: print("    " + m, flush=True))
    r = rep.report
    ratio = states_ratio(r)
    if ratio is None:  # no round ran the state families (--tiny runs none: its figures measure nothing)
        ratio = 0.0 if tiny else float("nan")
    return {"states_10k_ratio": ratio, "states_10k_samples": len(rec.est),
            "states_10k_s": time.perf_counter() - t0, "states_10k_forms": [x.get("form") for x in r["replaced"]],
            "states_10k_free_run": r["reported"]["free_run"]["rms_error"]}


def bench_bands(tiny: bool = False) -> dict:
    """What the band of each simulated validation record's own truth holds of its test record
    (:func:`validation.truth_band`: 40 draws at the true values, seed 0): the most a fitted model's band can be
    asked to hold there. Keys ``band_truth_<r>``, ``bands_records`` (how many were measured) and
    ``bands_truth_in_range`` (how many of them the truth's band holds 80-97 % of). No loop runs: a few seconds a
    record."""
    from .validation import RECORDS, band_held, truth_band

    out: dict = {}
    # --tiny: two kinds of record (a driven oscillator, the self-excited LCO), shortened
    names = ["none", "lco_none"] if tiny else list(RECORDS)
    for name in names:
        rec = RECORDS[name](n=800) if tiny else RECORDS[name]()
        c = truth_band(rec, 40)
        if c is not None:
            out[f"band_truth_{name}"] = c
            print(f"  [{name}] the truth's band holds {100 * c:.0f} % of the test record", flush=True)
    got = [v for k, v in out.items() if k.startswith("band_truth_")]
    out["bands_records"] = len(got)
    out["bands_truth_in_range"] = sum(map(band_held, got))
    return out


TINY_RECORDS = ("cascade", "duffing", "backlash", "heated_body", "none", "tanks_linear", "lco_gust")
"""The validation records a ``--tiny`` run fits, one of each kind (each fits a model of its own, compiled on a
first run): a simulated tank with laws, a driven oscillator, one with a kink (abs, sign), a heated body, a clean
record, the real tanks, a gate LCO with a gust input."""


def bench_validation(tiny: bool = False, records: list | None = None, seed: int | None = None) -> dict:
    """The loop on the validation set (:mod:`tests.bench.validation`): each record from its plain user model,
    and the peers on the same split, in one run; and the regression gate.

    Keys per record ``<r>``: ``loop_<r>_free_run`` (the reported model's free-run RMS error on the test
    record), ``loop_<r>_before`` (the user's model's), ``loop_<r>_band_coverage`` (the test data's share
    inside the reported model's 90 % band), ``loop_<r>_band_expected`` (the range its model expects),
    ``loop_<r>_s`` (the loop's wall time), ``loop_<r>_added`` and ``loop_<r>_replaced`` (what it did),
    ``loop_<r>_withheld`` (supported by the evidence, not taken by the held-out criterion), ``loop_<r>_verdict`` (``found``, ``nothing`` or ``other``: :func:`validation.verdict`),
    ``peer_<p>_<r>`` for the tuned linear ARX and polynomial NARX, SysIdentPy and PySINDy, ``peer_best_<r>`` the
    best of them; and the summary ``validation_loop_at_or_below_best_peer`` (records with an input where the
    loop's free run is at or below the best peer's; a self-excited LCO's free run loses its phase, so its
    records are graded by their verdict only), ``validation_records``, ``validation_check_records`` and
    ``validation_checks_at_or_below_best_peer``, ``validation_added_on_clean`` (effects added where the truth
    has none), ``validation_regressions`` (records whose verdict is worse than :data:`VERDICTS` holds: the gate;
    a full run fails when any is). Per record also ``loop_<r>_posterior_mean_free_run``,
    ``loop_<r>_noise_factor`` and ``loop_<r>_design``. With ``records`` (``--records``) the run is limited to those:
    it checks the gate on them and leaves the set's summary keys as the last full run wrote them. With ``seed``
    (``--seed``) every record's study runs at that seed instead of its own: how much a verdict owes to the
    loop's random numbers (its starts, its draws). Such a run is compared with the recorded verdicts
    (``validation_worse_at_seed``) but is no gate and records nothing.
    """
    from ardflow.ardcore.errors import ArdflowError
    from ardflow.ardcore.loop.config import DiagnoseConfig
    from ardflow.ardcore.loop.diagnose import diagnose

    from .validation import RECORDS, graded, verdict

    out: dict = {}
    recorded = json.loads(VERDICTS.read_text()) if VERDICTS.exists() else {}
    wins = clean_added = checks = checks_won = compared = 0
    regressions = []
    names = [n for n in RECORDS if not tiny or n in TINY_RECORDS]  # --tiny: one record of each kind
    if records is not None:
        names = [n for n in names if n in records]
    for name in names:
        make = RECORDS[name]
        rec = make(n=800) if tiny else make()
        spec = _tiny_spec(rec.spec) if tiny else rec.spec
        if seed is not None:
            spec = spec.model_copy(update={"seed": seed})
        print(f"  [{name}] {rec.physics}" + (f" (seed {seed})" if seed is not None else ""), flush=True)
        t0 = time.perf_counter()
        try:
            # --tiny: the fit, the measures and the reported model only (no round: the keys, not the figures)
            config = DiagnoseConfig(max_rounds=0) if tiny else DiagnoseConfig()
            rep = diagnose(spec, rec.est, test_data=rec.test, config=config,
                           progress=lambda m: print("    " + m, flush=True))
        except ArdflowError as exc:  # a record the loop fails on (or cannot start on) is a result, and a regression
            out[f"loop_{name}_s"] = time.perf_counter() - t0
            out[f"loop_{name}_error"] = str(exc)
            out[f"loop_{name}_verdict"] = "failed"
            if name in recorded:
                regressions.append(f"{name}: {recorded[name]} -> failed ({exc})")
            continue
        out[f"loop_{name}_s"] = time.perf_counter() - t0
        r = rep.report
        out[f"loop_{name}_free_run"] = r["reported"]["free_run"]["rms_error"]
        out[f"loop_{name}_before"] = r["before"]["free_run"]["rms_error"]
        out[f"loop_{name}_band_coverage"] = r["reported"]["free_run"].get("band_coverage")
        out[f"loop_{name}_band_expected"] = r["reported"]["free_run"].get("band_expected")
        # how the band's scale was chosen (the held-out blocks' coverage at each scale tried)
        out[f"loop_{name}_band_calibration"] = r["reported"]["free_run"].get("band_calibration")
        out[f"loop_{name}_band_factor"] = r["reported"]["free_run"].get("band_factor")
        out[f"loop_{name}_added"] = [a["effect"] + " -> " + a["target"] for a in rep.added]
        out[f"loop_{name}_replaced"] = [f"{x['state']['term']} -> {x['by']}" if x.get("state") else
                                        f"{x['parameter']}*({x['term']}) -> {x['by']}" for x in r["replaced"]]
        out[f"loop_{name}_forms"] = [x.get("form") for x in r["replaced"]]
        out[f"loop_{name}_states_ratio"] = states_ratio(r)
        out[f"loop_{name}_withheld"] = [a["effect"] + " -> " + a["target"] for a in r.get("withheld", [])]
        if rec.real:  # a measured record: no truth to find; its free run must stay as good as recorded
            out[f"loop_{name}_verdict"] = v = out[f"loop_{name}_free_run"]
            if isinstance(recorded.get(name), float) and v > 1.05 * recorded[name]:
                regressions.append(f"{name}: free run {recorded[name]:.4g} -> {v:.4g}")
        else:
            out[f"loop_{name}_verdict"] = v = verdict(rec, rep.added, r["replaced"], out[f"loop_{name}_before"],
                                                      out[f"loop_{name}_free_run"])
            if name in recorded and graded(rec, v) < graded(rec, recorded[name]):
                regressions.append(f"{name}: {recorded[name]} -> {v}")
        # the reported model beside its structure at the posterior mean (the same model at noise factor 1)
        out[f"loop_{name}_noise_factor"] = r["reported"].get("noise_factor", 1.0)
        out[f"loop_{name}_posterior_mean_free_run"] = (r["reported"].get("posterior_mean_free_run")
                                                       or r["reported"]["free_run"])["rms_error"]
        out[f"loop_{name}_design"] = rec.design
        if not rec.has_effect:
            clean_added += len(rep.added) + len(r["replaced"])
        if tiny and f"peer_best_{name}" not in CONTRACT["validation"]:
            continue  # --tiny: the peers on the records the contract names (the same code on the others)
        peer = _peers(rec)
        for p, val in peer.items():
            out[f"peer_{p}_{name}"] = val
        out[f"peer_best_{name}"] = min(peer.values())
        if "u" in rec.est.columns:
            won = out[f"loop_{name}_free_run"] <= out[f"peer_best_{name}"]
            compared += 1
            wins += won
            checks_won += won and not rec.design
            checks += not rec.design
        if not tiny:  # a smoke run never touches the measured figures
            _save_partial(out)
    if seed is not None:  # another seed: no gate, nothing recorded
        return {**out, "validation_seed": seed, "validation_worse_at_seed": regressions}
    if not tiny:
        # what this run found becomes the record, only where no verdict got worse (the gate stays as it was)
        if not regressions:
            VERDICTS.write_text(json.dumps({**recorded, **{n: out[f"loop_{n}_verdict"] for n in names}}, indent=1)
                                + "\n")
        else:
            print("  [gate] verdicts worse than recorded: " + "; ".join(regressions), flush=True)
    if records is not None:  # a subset: its records and the gate on them, not the set's summary
        return {**out, "validation_regressions": regressions}
    out["validation_records"] = len(names)
    out["validation_compared_records"] = compared
    out["validation_loop_at_or_below_best_peer"] = wins
    out["validation_check_records"] = checks
    out["validation_checks_at_or_below_best_peer"] = checks_won
    out["validation_added_on_clean"] = clean_added
    out["validation_regressions"] = regressions
    out["validation_regression_count"] = len(regressions)
    return out


def _save_partial(res: dict) -> None:
    """Merge figures measured so far into .bench/results.json (a long group must not lose them on a crash)."""
    path = ROOT / ".bench" / "results.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    old = json.loads(path.read_text()) if path.exists() else {}
    old.update(res)
    path.write_text(json.dumps(old, indent=2))


BENCHES = {"ekf": bench_ekf, "records": bench_records, "engine": bench_engine, "dask": bench_dask, "api": bench_api, "listing": bench_listing,
           "study": bench_study,
           "posterior": bench_posterior, "posterior_full": bench_posterior_full,
           "loop": bench_loop, "states": bench_states, "validation": bench_validation, "bands": bench_bands,
           "fresh": bench_fresh}


CONTRACT = {
    "ekf": ["ekf_m2_ms", "ekf_speedup", "ekf_vs_handwritten", "ekf_compile_first_call_s", "ekf_cached_first_call_s"],
    "records": ["records_cost_ratio"],
    "engine": ["evidence_sd_nats", "evidence_se_mean", "mcmc_samples_per_s", "sampler_step_us"],
    "dask": ["dask_samples_per_s_1w", "dask_samples_per_s_2w", "dask_scaling_2w", "dask_overhead",
             "store_mb_per_1e6_samples"],
    "api": ["api_status_p95_ms", "api_status_p99_ms", "api_upload_s", "api_errors", "api_rss_mb", "api_max_drivers"],
    "listing": ["api_listing_studies", "api_listing_user_p99_ms", "api_listing_admin_p99_ms"],
    "study": ["study_demo_s", "study_demo_evaluations", "study_demo_min_ess", "study_demo_max_rhat", "study_demo_efficiency",
              "study_full_s",
              "study_full_min_ess", "study_full_max_rhat"],
    "posterior": ["evidence_se_ratio", "posterior_M2_ess_per_evaluation",
                  "posterior_M2_ess_per_evaluation_random_walk"],
    "posterior_full": ["evidence_se_ratio_full", "posterior_full_M2_lnz_sd", "posterior_full_M2_se_mean"],
    "loop": ["loop_silverbox_multisine_mv", "loop_silverbox_arrow_mv", "loop_pendulum_rad",
             "loop_peer_best_multisine_mv", "loop_peer_pysindy_multisine_mv", "loop_peer_sysidentpy_multisine_mv",
             "loop_peer_narx_pendulum_rad"],
    "states": ["states_10k_ratio", "states_10k_samples", "states_10k_s"],
    "validation": ["validation_records", "validation_loop_at_or_below_best_peer", "validation_added_on_clean",
                   "validation_regression_count",
                   *[k.format(r) for r in ("cascade", "duffing", "backlash", "heated_body", "none")
                     for k in ("loop_{}_free_run", "peer_best_{}", "loop_{}_s")]],
    "fresh": ["fresh_demo_s", "fresh_demo_evaluations"],
    "bands": ["bands_records", "bands_truth_in_range", "band_truth_none"],
}
"""Keys each group must write (named in issues and the README: a contract); the smoke test checks them."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=None, help="default .bench/results.json (--tiny: .bench/tiny.json, so a smoke "
                                                "run never overwrites measured figures)")
    ap.add_argument("--only", nargs="*", choices=sorted(BENCHES), default=None)
    ap.add_argument("--tiny", action="store_true", help="every group at a tiny size: the smoke test (figures "
                                                        "meaningless)")
    ap.add_argument("--records", nargs="+", default=None, metavar="NAME",
                    help="the validation group on these records only (the gate on them; the set's summary is left "
                         "as the last full run wrote it)")
    ap.add_argument("--seed", type=int, default=None,
                    help="the validation group with every study at this seed (no gate, nothing recorded; needs --out)")
    a = ap.parse_args(argv)
    if a.seed is not None and (a.out is None or a.only != ["validation"]):
        ap.error("--seed runs the validation group alone (--only validation) and writes only to --out: a run at "
                 "another seed is no gate and publishes nothing")
    if a.records:
        from .validation import RECORDS

        unknown = sorted(set(a.records) - set(RECORDS))
        if unknown:
            ap.error(f"unknown validation records: {', '.join(unknown)} (known: {', '.join(RECORDS)})")
    out = Path(a.out or (".bench/tiny.json" if a.tiny else ".bench/results.json"))
    out.parent.mkdir(parents=True, exist_ok=True)
    res = json.loads(out.read_text()) if out.exists() else {}
    ran: dict = {}  # what this run measured (the file also holds earlier runs' keys)
    for name in a.only or BENCHES:
        print(f"[bench] {name} ...", flush=True)
        r = (bench_validation(tiny=a.tiny, records=a.records, seed=a.seed)
             if name == "validation" and (a.records or a.seed is not None) else BENCHES[name](tiny=a.tiny))
        res.update(r)
        ran.update(r)
        for k, v in r.items():
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                print(f"  {k:28s} {v:.4g}")
    res["machine"] = {"cpus": os.cpu_count(), "python": platform.python_version(), "platform": platform.platform(),
                      "date": time.strftime("%Y-%m-%d")}
    out.write_text(json.dumps(res, indent=2))
    print(f"[bench] wrote {out}")
    if ran.get("validation_regressions") and not a.tiny:
        print("[bench] FAILED: the regression gate (tests/bench/verdicts.json): " + "; ".join(
            ran["validation_regressions"]), file=sys.stderr)
        return 1
    if not a.tiny and a.out is None:
        # the measured headline figures, with their provenance, for the README and docs
        from .figures import FIGURES, publish, update_readme

        publish(ran, " ".join(
            ["python -m tests.bench.run"] + (["--only", *a.only] if a.only else [])
            + (["--records", *a.records] if a.records else [])), res["machine"])
        update_readme()
        print(f"[bench] wrote {FIGURES.relative_to(ROOT)} and the README's figures table")
    return 0


if __name__ == "__main__":
    sys.exit(main())
