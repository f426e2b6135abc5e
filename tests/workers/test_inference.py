"""A finished study as ArviZ data: az.summary, az.loo and az.compare run on it, and the pointwise
log-likelihood is exact (its terms sum to the likelihood the sampler stored for the same draw)."""

from __future__ import annotations

import numpy as np
import pytest
from distributed import Client, LocalCluster

from ardflow.ardcore.selection.spec import load_spec
from ardflow.workers.graph import prepare_store, run_study
from ardflow.workers.inference import InferenceGroups, inference_groups, to_inference_data

from .test_orchestration import SPEC

az = pytest.importorskip("arviz")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=":0") as cl, \
            Client(cl) as c:
        st = prepare_store(load_spec(SPEC), tmp_path_factory.mktemp("inf") / "st")
        run_study(c, st, poll_s=0.2)
    return st


def test_groups_and_arviz_functions(store):
    dt = to_inference_data(store, "quad")
    post = dt["posterior"]
    samples, lp, ll, names = store.read_samples("quad", int(store.group("r")["models/quad"].attrs["best_iteration"]))
    # the optimal nested model's free parameters: a2 is pruned on data that are linear in x
    assert set(post.data_vars) == set(names) == {"a0", "a1", "gamma"}
    assert post["a0"].dims == ("chain", "draw") and post.sizes["chain"] == 3
    np.testing.assert_array_equal(post["a1"].values, samples[..., names.index("a1")])
    np.testing.assert_array_equal(dt["sample_stats"]["lp"].values, lp)
    assert dt["observed_data"]["y"].dims == ("time",)
    assert 0 < dt.attrs["acceptance"] < 1 and dt.attrs["burnin_rounds"] >= 1 and dt.attrs["n_evaluations"] > 0
    s = az.summary(dt)
    assert {"a0", "a1", "gamma"} <= set(s.index) and "r_hat" in s.columns
    assert float(s.loc["a1", "mean"]) == pytest.approx(5.0, abs=0.5)  # Appendix A: y = 3 + 5 x + noise


def test_pointwise_log_likelihood_is_exact_and_loo_compare_run(store):
    g = inference_groups(store, "quad", log_likelihood=True, max_draws=60)
    pw = g.groups["log_likelihood"]["y"]
    total = g.groups["sample_stats"]["log_likelihood"]
    assert pw.shape[:2] == total.shape and pw.shape[0] * pw.shape[1] <= 60
    np.testing.assert_allclose(pw.sum(axis=2), total, rtol=1e-9, atol=1e-8)
    # the NPZ that crosses the REST API carries every group unchanged
    back = InferenceGroups.from_npz(g.to_npz())
    np.testing.assert_array_equal(back.groups["log_likelihood"]["y"], pw)
    assert back.attrs["model"] == "quad" and back.dims == g.dims
    dts = {m: to_inference_data(store, m, log_likelihood=True, max_draws=200) for m in ("quad", "cubic")}
    loo = az.loo(dts["quad"])
    assert np.isfinite(float(loo.elpd)) and float(loo.elpd) < 0
    cmp = az.compare(dts)
    assert set(cmp.index) == {"quad", "cubic"} and cmp["rank"].min() == 0


def test_unfinished_model_is_a_clear_error(store):
    with pytest.raises(LookupError, match="no model"):
        to_inference_data(store, "nope")


def test_psis_loo_takes_a_constant_observation_exactly(store):
    """An observation whose log density is the same for every draw is left out at no change: its elpd term
    is that density (ArviZ's Pareto fit refuses such a column)."""
    from ardflow.workers.inference import psis_loo

    g = inference_groups(store, "quad", log_likelihood=True, max_draws=120)
    pw = g.groups["log_likelihood"]["y"]
    pw[..., 0] = -1.2345  # as the first one-step density of a model whose initial state is not a parameter
    with pytest.raises(ValueError, match="tail values"):
        az.loo(g.to_datatree())
    r = psis_loo(g.to_datatree())
    assert r["n_constant"] == 1 and r["elpd_i"][0] == -1.2345
    rest = az.loo(g.to_datatree().isel(time=slice(1, None)))
    assert r["elpd_loo"] == pytest.approx(float(rest.elpd) - 1.2345, rel=1e-12)


def test_loo_command(store, capsys):
    from ardflow.service.cli import main

    assert main(["loo", str(store.path), "--draws", "60"]) == 0
    out = capsys.readouterr().out
    assert "elpd_loo" in out and "quad" in out and "cubic" in out
    assert main(["loo", str(store.path.parent)]) == 2  # not a study store: one error line
