"""A finished study as ArviZ data: az.summary, az.loo and az.compare run on it, and the pointwise
log-likelihood is exact (its terms sum to the likelihood the sampler stored for the same draw)."""

from __future__ import annotations

import numpy as np
import pytest
from distributed import Client, LocalCluster

from ardflow.ardcore.study import load_spec
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
