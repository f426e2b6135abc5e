"""Several records in one study: the summed likelihood, the evidence and what a pair of records identifies,
against exact answers (linear-Gaussian models, where the Kalman filter is exact)."""

from pathlib import Path

import numpy as np
import pytest

from ardflow.ardcore.data import Dataset, join_records
from ardflow.ardcore.evidence.estimators import chib_jeliazkov
from ardflow.ardcore.evidence.laplace import laplace
from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.likelihood.posterior import ModelPosterior
from ardflow.ardcore.likelihood.simulate import simulate_model
from ardflow.ardcore.model.declaration import ModelSpec
from ardflow.ardcore.model.priors import Normal
from ardflow.ardcore.sampling.config import SamplerConfig
from ardflow.ardcore.sampling.driver import sample

from .targets import LINEAR_SYSTEM, augmented_kalman, linear_gaussian_spec

SPEC = linear_gaussian_spec()
TRUE = {"b1": 1.5, "b2": -0.4, "c": 0.3}
PRIOR_MEAN, PRIOR_SD = np.zeros(3), np.array([2.0, 1.0, 1.0])


def two_records():
    """Two experiments of one system: different lengths, sample intervals and inputs; the second starts
    from a declared initial state (x = 2 +- 0.5), the first from the model's (0 +- 1)."""
    out = []
    for seed, n, dt, w, x0 in ((11, 150, 0.1, 0.9, 0.0), (21, 120, 0.05, 2.3, 2.0)):
        t = 3.0 + np.arange(n) * dt
        rng = np.random.default_rng(seed)
        u = np.sin(w * t) + 0.5 * rng.standard_normal(n)
        out.append(simulate_model(SPEC, TRUE, t, seed=seed + 1, nsub=20, inputs={"u": u}, x0=[x0]))
    out[1].meta.update(initial_mean={"x": 2.0}, initial_std={"x": 0.5})
    return out


def kalman_records(records, theta_mean, theta_sd):
    """Exact ln p(d) of :data:`SPEC` on ``records`` (:func:`targets.augmented_kalman`)."""
    return augmented_kalman(records, LINEAR_SYSTEM, theta_mean, theta_sd)


def test_joined_records_restart_the_filter_and_sum_exactly():
    recs = two_records()
    joined = join_records(recs, ["first", "second"])
    assert joined.starts == (0, 150) and len(joined) == 270 and np.all(np.diff(joined.t) > 0)
    theta = np.array([TRUE[k] for k in ("b1", "b2", "c")])
    cm = compile_model(SPEC)
    each = [cm.loglik(theta, r) for r in recs]
    both = cm.loglik(theta, joined)
    assert both == pytest.approx(sum(each), abs=1e-9)
    assert both == pytest.approx(kalman_records(recs, theta, np.zeros(3)), abs=1e-8)
    # what the loop does to a data set (an effect's input columns, a block's observations hidden) keeps its records
    from ardflow.ardcore.effects.base import with_columns
    from ardflow.ardcore.effects.families import candidate_effects

    forcing = next(e for e in candidate_effects(SPEC, frequencies=[0.5]) if e.columns_for(joined.t, joined.columns))
    assert with_columns(joined, forcing).starts == joined.starts
    # the second record's declared initial state matters: without it the sum changes
    plain = join_records([recs[0], Dataset(recs[1].t, recs[1].columns, {"source": "x"})])
    assert abs(cm.loglik(theta, plain) - both) > 1.0
    # concatenating the records as one (what users did before) is a different, wrong likelihood
    glued = Dataset(joined.t, joined.columns, {"source": "glued"})
    assert abs(cm.loglik(theta, glued) - both) > 1.0
    # each record comes back on its own time axis with its own initial state
    back = joined.record(1)
    assert np.allclose(back.t, recs[1].t) and back.meta["initial_mean"] == {"x": 2.0}
    assert cm.loglik(theta, back) == pytest.approx(each[1], abs=1e-9)
    # the smoother does not smooth across the records' boundary
    from ardflow.ardcore.likelihood.ekf import rts_smooth

    fr = cm.bind(joined).trace(theta)
    sm = rts_smooth(fr)
    assert np.isfinite(sm.smoothed).all() and fr.starts == (0, 150)
    one = rts_smooth(cm.bind(recs[0]).trace(theta))
    assert np.allclose(sm.smoothed[:150], one.smoothed, atol=1e-10)


def test_joint_evidence_of_two_records_is_the_exact_marginal_likelihood():
    recs = two_records()
    joined = join_records(recs)
    priors = {k: Normal(mean=m, sd=s) for k, m, s in zip(["b1", "b2", "c"], PRIOR_MEAN, PRIOR_SD)}
    target = ModelPosterior(SPEC, priors, joined)
    exact = kalman_records(recs, PRIOR_MEAN, PRIOR_SD)
    lap, _, _ = laplace(target, np.zeros(3), np.ones(3))
    assert lap.log_evidence == pytest.approx(exact, abs=1e-5)
    cfg = SamplerConfig(n_chains=4, round_size=500, n_stationary=3000, n_proposal=3000)
    res = sample(target, cfg, seed=31)
    ev = chib_jeliazkov(target, res, n_proposal=cfg.n_proposal, seed=32)
    assert abs(ev.log_evidence - exact) < max(0.15, 4 * ev.log_evidence_se), (ev.log_evidence, exact)


GAIN = ModelSpec(
    name="gain_by_speed", states=["x"], inputs=["u", "V"],
    drift={"x": "-a*x + (k0 + k1*V)*u"}, diffusion={"x": "q"},
    observations=[{"column": "y", "expr": "x", "noise_std": "r"}],
    parameters=["k0", "k1"], constants={"a": 1.0, "q": 0.05, "r": 0.05},
    initial_std={"x": 0.1}, substeps=4, integrator="euler", input_hold="zoh")


def test_two_conditions_identify_what_neither_does_alone():
    """A gain k0 + k1 V measured at two airspeeds V: each record fixes one combination, the pair fixes both.
    The pair's posterior precision is the sum of the records' minus the prior's (the model is linear-Gaussian
    in k0, k1, so this is exact, and Laplace is the posterior)."""
    from ardflow.ardcore.selection.spec import DataSpec

    t = np.arange(400) * 0.05
    rng = np.random.default_rng(5)
    u = np.sin(1.3 * t) + 0.3 * rng.standard_normal(t.size)
    recs = []
    for V, seed in ((1.0, 6), (3.0, 7)):
        ds = simulate_model(GAIN, {"k0": 0.5, "k1": 0.4}, t, seed=seed, nsub=8,
                            inputs={"u": u, "V": np.full(t.size, V)})
        recs.append(ds)
    priors = {"k0": Normal(mean=0.0, sd=3.0), "k1": Normal(mean=0.0, sd=3.0)}
    prior_prec = np.diag([1 / 9.0, 1 / 9.0])

    def cov(data):
        _, _, c = laplace(ModelPosterior(GAIN, priors, data), np.array([0.3, 0.3]), np.array([0.1, 0.1]))
        return c

    ca, cb, cab = cov(recs[0]), cov(recs[1]), cov(join_records(recs))
    predicted = np.linalg.inv(np.linalg.inv(ca) + np.linalg.inv(cb) - prior_prec)
    sd = lambda c: np.sqrt(np.diag(c))  # noqa: E731
    # alone, k1 is barely narrower than its prior (sd 3): one record sees only k0 + V k1
    assert sd(ca)[1] > 0.5 and sd(cb)[1] > 0.5
    assert sd(cab)[1] < 0.05 * min(sd(ca)[1], sd(cb)[1])
    assert sd(cab) == pytest.approx(sd(predicted), rel=0.02)
    # the airspeed reaches the model as a record constant of the data spec (an input column of that name)
    spec = DataSpec(generator="appendix_a", constants={"V": 2.5}, initial_mean={"x": 1.0})
    loaded = spec.load()
    assert np.all(loaded.columns["V"] == 2.5) and loaded.meta["initial_mean"] == {"x": 1.0}


@pytest.mark.slow
def test_diagnose_two_records_and_a_held_out_one(tmp_path):
    """`ardflow diagnose` on a study of two records (a Duffing oscillator swept at two amplitudes, the user's
    model linear) with two further records held out: the cubic stiffness is found on the pair, the held-out
    records' free-run errors fall, and the report shows each record."""
    import json

    from ardflow.service.cli import main
    from tests.bench.validation import OSC_PRIORS, SAMPLER, _linear_oscillator, _noise_input, _simulate, _truth

    truth = _truth("-k*y - c*v - k3*y**3 + b*u", ["k", "c", "k3", "b", "sigma"], 2e-3)
    values = {"k": 16.0, "c": 0.4, "k3": 4.0, "b": 8.0, "sigma": 0.3}
    files = []
    for i, (amp, seed) in enumerate(((1.0, 1), (1.8, 2), (1.4, 3), (0.8, 4))):
        t = np.arange(1500) * 0.02
        u = amp * np.sin(2 * np.pi * np.cumsum(0.3 + 0.9 * t / t[-1]) * 0.02) if i < 2 \
            else amp * _noise_input(np.random.default_rng(seed), t.size)
        files.append(tmp_path / f"run{i}.csv")
        _simulate(truth, values, t, u, seed, 2).to_csv(files[-1])
    spec = {"name": "duffing_records", "evidence": "laplace", "sampler": SAMPLER, "seed": 2,
            "data": [{"path": str(files[0]), "name": "sweep at 1.0"}, {"path": str(files[1]), "name": "sweep at 1.8"}],
            "models": [{"model": _linear_oscillator(2e-3), "priors": OSC_PRIORS}]}
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    out = tmp_path / "diag"
    assert main(["diagnose", str(tmp_path / "spec.json"), "--test-data", str(files[2]), "--test-data", str(files[3]),
                 "--out", str(out), "--max-rounds", "2"]) == 0
    rep = json.loads((out / "diagnosis.json").read_text())
    assert "cubic_stiffness" in {a["effect"].split("(")[0] for a in rep["added"]}, rep["added"]
    before, after = rep["before"]["free_run"]["rms_error"], rep["after"]["free_run"]["rms_error"]
    assert after < 0.2 * before, (before, after)
    # each record: the estimation records' innovation tests, the test records' free runs
    assert [r["name"] for r in rep["after"]["records"]] == ["sweep at 1.0", "sweep at 1.8"]
    runs = rep["after"]["free_run"]["records"]
    assert [r["name"] for r in runs] == ["run2.csv", "run3.csv"]
    assert all(r["rms_error"] < 0.3 * b["rms_error"] for r, b in zip(runs, rep["before"]["free_run"]["records"]))
    assert "<h3>Each record</h3>" in (out / "diagnosis.html").read_text()


def test_a_per_record_parameter_is_one_per_record_and_its_evidence_exact():
    """An offset that differs between two records (``per_record``): it becomes one parameter per record, each
    with the offset's prior; the Laplace evidence is the exact marginal likelihood of the linear-Gaussian model
    y = a0 + a1 x + offset_r + noise, and each record's offset is recovered."""
    from scipy.stats import multivariate_normal as mvn

    from ardflow.ardcore.selection.spec import StudySpec

    gamma, sd = 0.3, {"a0": 3.0, "a1": 3.0, "off": 1.0}
    study = StudySpec.model_validate({
        "name": "offsets", "evidence": "laplace",
        "data": [{"generator": "appendix_a", "seed": 1, "name": "one"}, {"generator": "appendix_a", "seed": 2}],
        "models": [{"model": {"name": "line", "states": ["z"], "drift": {"z": "0*z"}, "inputs": ["x"],
                              "observations": [{"column": "y", "expr": "a0 + a1*x + off", "noise_std": str(gamma)}],
                              "parameters": ["a0", "a1", "off"]},
                    "priors": {k: {"kind": "normal", "mean": 0.0, "sd": v} for k, v in sd.items()},
                    "per_record": ["off"]}]})
    cand = study.models[0]
    assert cand.model_spec().free_parameters == ["a0", "a1", "off_0", "off_1"]
    # validating the stored spec again changes nothing
    again = StudySpec.model_validate(study.model_dump(mode="json")).models[0]
    assert again.model_spec().free_parameters == cand.model_spec().free_parameters
    data = study.load_data()
    shift = np.where(np.arange(len(data)) < data.starts[1], 1.0, -1.0)  # the records' offsets: +1 and -1
    data.columns["y"] = data.columns["y"] + shift
    X = np.column_stack([np.ones(len(data)), data.columns["x"], data.columns["record_0"], data.columns["record_1"]])
    S0 = np.diag([sd["a0"] ** 2, sd["a1"] ** 2, sd["off"] ** 2, sd["off"] ** 2])
    exact = mvn(np.zeros(len(data)), gamma**2 * np.eye(len(data)) + X @ S0 @ X.T).logpdf(data.columns["y"])
    priors = {k: Normal(mean=0.0, sd=sd[k.split("_")[0]]) for k in cand.model_spec().free_parameters}
    lap, mode, _ = laplace(ModelPosterior(cand.model_spec(), priors, data), np.zeros(4), np.ones(4))
    assert lap.log_evidence == pytest.approx(exact, abs=1e-5)
    assert mode[2] - mode[3] == pytest.approx(2.0, abs=0.25)
    # a further experiment takes the records' mean offset
    held = study.held_out(Dataset(np.arange(20.0), {"x": np.linspace(0, 2, 20), "y": np.zeros(20)}))
    assert np.all(held.columns["record_0"] == 0.5) and np.all(held.columns["record_1"] == 0.5)


def test_the_store_keeps_the_records_and_reads_stores_written_before_them(tmp_path):
    import zarr

    from ardflow.workers.store import StudyStore

    recs = two_records()
    joined = join_records(recs, ["first", "second"])
    store = StudyStore.create(tmp_path / "st", {"name": "x"}, joined)
    back = store.load_data()
    assert back.starts == (0, 150) and [r["name"] for r in back.meta["records"]] == ["first", "second"]
    assert back.meta["records"][1]["initial_mean"] == {"x": 2.0}
    theta = np.array([TRUE[k] for k in ("b1", "b2", "c")])
    assert compile_model(SPEC).loglik(theta, back) == pytest.approx(compile_model(SPEC).loglik(theta, joined), abs=1e-9)
    # a store written before records existed has no record attributes: one record
    old = StudyStore.create(tmp_path / "old", {"name": "x"}, recs[0])
    g = zarr.open_group(str(tmp_path / "old" / "data"), mode="a")
    g.attrs.clear()
    assert old.load_data().starts == (0,) and len(old.load_data()) == 150


def test_the_tanks_example_is_two_real_records():
    from ardflow.ardcore.selection.spec import load_spec

    root = Path(__file__).resolve().parents[2]
    spec = load_spec(root / "examples" / "tanks_records.json")
    data = spec.load_data(root / "examples")
    assert data.starts == (0, 1024) and [r["name"] for r in data.meta["records"]] == ["estimation", "validation"]
    spec.check_data(data)
