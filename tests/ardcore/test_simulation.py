"""The simulation fit (ardcore.loop.simulation_fit): which parameters scale the process noise, and a model that lacks
a damping term free-runs better at the noise level chosen on held-out data than at its posterior mean."""

import numpy as np

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.evidence.estimators import laplace
from ardflow.ardcore.model.declaration import ModelSpec
from ardflow.ardcore.likelihood.posterior import ModelPosterior
from ardflow.ardcore.model.priors import LogNormal
from ardflow.ardcore.likelihood.simulate import simulate_model
from ardflow.ardcore.loop.freerun import noise_parameters
from ardflow.ardcore.loop.simulation_fit import simulation_fit
from ardflow.ardcore.loop.freerun import free_run


def _osc(drift_v: str, params: list, diffusion: str = "sigma") -> ModelSpec:
    return ModelSpec(name=f"sim_{abs(hash((drift_v, diffusion))) % 10**6}", states=["y", "v"], inputs=["u"],
                     drift={"y": "v", "v": drift_v}, diffusion={"v": diffusion},
                     observations=[{"column": "y", "expr": "y", "noise_std": "0.002"}],
                     parameters=params, initial_std={"y": 0.5, "v": 2.0})


def test_noise_parameters_are_those_the_diffusion_is_proportional_to():
    assert noise_parameters(_osc("-k*y", ["k", "sigma"])) == ["sigma"]
    assert noise_parameters(_osc("-k*y", ["k", "sigma"], "2*sigma")) == ["sigma"]
    assert noise_parameters(_osc("-k*y", ["k", "s"], "exp(s)")) == []
    assert noise_parameters(_osc("-k*y", ["k"], "0.3")) == []


def _record(truth, seed, params, n=3000, dt=0.02):
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    u = np.convolve(rng.standard_normal(n + 20), np.ones(8) / np.sqrt(8), mode="same")[:n]
    d = simulate_model(truth, params, t, seed, inputs={"u": u}, x0=[0.0, 0.0])
    return Dataset(t, {"y": d.columns["y"], "u": u}, {})


def _fitted_linear_model(truth, params):
    """The linear forced oscillator fitted (posterior mode) to a record of ``truth``, and a fresh record."""
    model = _osc("-k*y - c*v + b*u", ["k", "c", "b", "sigma"])
    est, fresh = _record(truth, 1, params), _record(truth, 2, params)
    priors = {"k": LogNormal(median=15.0, cov=100), "c": LogNormal(median=0.3, cov=300),
              "b": LogNormal(median=5.0, cov=200), "sigma": LogNormal(median=0.3, cov=300)}
    target = ModelPosterior(model, priors, est)
    _, xmap, _ = laplace(target, np.array([15.0, 0.3, 5.0, 0.3]))
    return model, dict(zip(target.prior.names, map(float, xmap))), est, fresh


def test_a_model_lacking_its_damping_free_runs_better_at_the_chosen_noise_level():
    """The truth has an amplitude-dependent damping q y^2 v and little process noise (0.02); the model has
    only viscous damping. Its posterior fit lets process noise (0.49) take up the misfit; the simulation
    fit must choose a smaller noise factor and free-run a fresh record better than the posterior mean."""
    truth = _osc("-k*y - c*v - q*y**2*v + b*u", ["k", "c", "b", "q", "sigma"])
    model, phi, est, fresh = _fitted_linear_model(truth, {"k": 16.0, "c": 0.05, "b": 8.0, "q": 1.0, "sigma": 0.02})
    sim = simulation_fit(model, phi, est)
    assert sim is not None and set(sim.held_out_rms) == {1.0, 0.3, 0.1, 0.03}
    assert sim.factor < 1.0, sim.held_out_rms
    assert sim.held_out_rms[sim.factor] == min(sim.held_out_rms.values())
    assert abs(sim.phi["sigma"] - sim.factor * phi["sigma"]) < 1e-12
    posterior_rms = free_run(model, phi, fresh)["rms_error"]
    simulation_rms = free_run(model, sim.phi, fresh)["rms_error"]
    print(f"\nposterior mean {posterior_rms:.4g}, simulation fit x{sim.factor:g} {simulation_rms:.4g}; "
          f"held out {sim.held_out_rms}")
    assert simulation_rms < 0.95 * posterior_rms


def test_the_posterior_noise_is_kept_when_a_smaller_one_free_runs_worse():
    """A missing cubic stiffness: at smaller process noise the fit free-runs the held-out part worse, so the
    simulation fit keeps the posterior mean as it is."""
    truth = _osc("-k*y - c*v - q*y**3 + b*u", ["k", "c", "b", "q", "sigma"])
    model, phi, est, _ = _fitted_linear_model(truth, {"k": 16.0, "c": 0.2, "b": 8.0, "q": 3.0, "sigma": 0.02})
    sim = simulation_fit(model, phi, est)
    assert sim.factor == 1.0 and sim.phi == phi, sim.held_out_rms
    assert min(sim.held_out_rms[f] for f in (0.3, 0.1, 0.03)) > sim.held_out_rms[1.0]
