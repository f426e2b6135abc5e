"""A model that does not declare how its inputs vary between samples holds them when the record does."""

import numpy as np

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.selection.hold import held_share, with_hold, with_holds
from ardflow.ardcore.selection.spec import StudySpec


def _steps(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.uniform(0, 1, n // 20 + 1), 20)[:n]


def _study(model="forced_linear_oscillator") -> StudySpec:
    lognormal = {"kind": "lognormal", "median": 1.0, "cov": 100}
    return StudySpec.model_validate({"data": {"generator": "appendix_a"}, "evidence": "laplace", "models": [
        {"model": model, "priors": {p: lognormal for p in ("k", "c", "b", "sigma")}}]})


def _record(u: np.ndarray, y: np.ndarray | None = None) -> Dataset:
    t = np.arange(u.size) * 0.02
    return Dataset(t, {"u": u, "y": np.zeros(u.size) if y is None else y})


def test_the_share_of_held_steps():
    assert held_share(np.array([1.0, 1.0, 2.0, 2.0, 2.0])) == 0.75
    assert held_share(np.sin(np.arange(100.0))) == 0.0
    assert held_share(np.ones(10)) == 0.0  # a constant is neither


def test_a_stepped_input_is_held_and_a_sampled_signal_interpolated():
    spec = _study()
    stepped, _ = with_holds(spec, _record(_steps(500)))
    assert stepped.models[0].model_spec().input_hold == "zoh"
    noise, notes = with_holds(spec, _record(np.random.default_rng(1).standard_normal(500)))
    assert noise is spec and notes == [] and noise.models[0].model_spec().input_hold == "foh"


def test_a_declared_hold_is_the_users():
    ms = _study().models[0].model_spec().model_dump(mode="json")  # every field written out, input_hold included
    spec = _study(ms)
    same, notes = with_holds(spec, _record(_steps(500)))
    assert notes == [] and same.models[0].model_spec().input_hold == "foh"


def test_the_held_candidate_is_the_same_model_otherwise_and_survives_the_store():
    spec = _study()
    cand, (note,) = with_hold(spec.models[0], _record(_steps(500)))
    assert "zoh" in note and cand.label == spec.models[0].label
    a, b = spec.models[0].model_spec(), cand.model_spec()
    assert a.model_dump(exclude={"input_hold"}) == b.model_dump(exclude={"input_hold"})
    back = StudySpec.model_validate(spec.model_copy(update={"models": [cand]}).model_dump(mode="json"))
    assert back.models[0].model_spec().input_hold == "zoh"


def test_the_hold_decides_which_model_the_record_supports():
    """A record simulated with its input held: the held model's likelihood at the truth is higher than the
    interpolating one's (the ramps are a misfit at every step)."""
    spec = _study()
    truth = {"k": 16.0, "c": 0.4, "b": 8.0, "sigma": 0.05}
    u = _steps(2000, 3)
    held = with_hold(spec.models[0], _record(u))[0].model_spec()
    cm = compile_model(held)
    t = np.arange(u.size) * 0.02
    _, y = cm.simulate(truth, t, x0=np.zeros(2), inputs=u[:, None], nsub=20, noise=True,
                       rng=np.random.default_rng(4))
    gamma = float(np.ravel(cm.obs_std(truth))[0])
    data = _record(u, y[:, 0] + gamma * np.random.default_rng(5).standard_normal(u.size))
    ll_zoh = cm.filter(truth, data).loglik
    ll_foh = compile_model(spec.models[0].model_spec()).filter(truth, data).loglik
    assert ll_zoh > ll_foh + 10, (ll_zoh, ll_foh)

