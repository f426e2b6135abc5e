"""The forced oscillator the loop's tests plant effects in: y'' = -16 y - 0.4 y' + 8 u + sigma xi, y measured
with noise 2e-3, u a band-limited random input (shared by the screen's unit tests and the family tests)."""

import numpy as np

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.likelihood.simulate import simulate_model

TRUE = {"k": 16.0, "c": 0.4, "b": 8.0, "sigma": 0.3}


def base_spec():
    return builtin("forced_linear_oscillator").model_copy(update={"constants": {"gamma": 2e-3}}).revalidate()


def forced_data(seed, truth=None, params=None, columns=None, n=4000, dt=0.02) -> Dataset:
    """Data of ``truth`` (default: the base model) at TRUE updated by ``params``; ``columns(t, {"u": u})`` gives extra
    input columns the truth needs (a forcing's sine and cosine, an input's rate), which the data set does not
    carry."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    u = np.convolve(rng.standard_normal(n + 20), np.ones(8) / np.sqrt(8), mode="same")[:n]
    truth = truth or base_spec()
    inputs = {"u": u, **(columns(t, {"u": u}) if columns else {})}
    d = simulate_model(truth, {**TRUE, **(params or {})}, t, seed, inputs=inputs, x0=[0.0] * len(truth.states))
    return Dataset(d.t, {"y": d.columns["y"], "u": u}, d.meta)
