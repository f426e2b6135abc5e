"""Built-in model library.

Every entry is an ordinary declarative :class:`~ardcore.model.declaration.ModelSpec`;
users can copy one as JSON and edit it. The aeroelastic models (Euler sub-steps, as the paper's study was run and the
reference data are simulated) follow
``docs/worked-example.md`` (Eq. 15-18, Table 6); the candidate
terms e1..e6 of the paper are the parameters ``a1..a6`` here.
"""

from __future__ import annotations

import math

from ..errors import ModelError, did_you_mean
from .declaration import ModelSpec

# Structural constants of Eq. 15 (printed values, U = 8.50 m/s) and c6 (a_h = -0.628).
AERO_CONSTANTS = {
    "c1": -6.875e-05, "c2": -2.038e-02, "c3": 3.819e-02, "c4": -7.275e-03, "c5": 1.824e-01,
    "c6": math.pi * (0.25 - 0.628**2) / 2.0,
}
AERO_GAMMA_EKF = 1e-3
"""Declared measurement-noise std of the EKF on the reference data (Decision)."""

AERO_TRUE = {"B": 0.2, "a1": -1.25, "a2": -1.0, "a3": 100.0, "a4": -500.0, "a5": 0.0, "a6": 0.0,
             "sigma": 2e-3}
"""True parameters of the data-generating model (Eq. 16)."""

_F = "c1*sign(dtheta) + c2*theta + c3*CM + c4*dtheta + c5*theta**3"
_P = "a1*theta + a2*dtheta + a3*theta**3 + a4*theta**2*dtheta + a5*theta**5 + a6*theta**4*dtheta"
_INIT_STD = {"theta": 0.01, "dtheta": 0.01, "CM": 0.01}
_OBS_THETA = [{"column": "y", "expr": "theta", "noise_std": "gamma"}]


def aero_m1() -> ModelSpec:
    """M1, quasi-steady: CM = P + sigma xi, state [theta, dtheta]."""
    return ModelSpec(
        name="M1", description="Quasi-steady aerodynamics (worked-example.md, Eq. 17)",
        states=["theta", "dtheta"],
        derived={"P": _P},
        drift={"theta": "dtheta",
               "dtheta": "c1*sign(dtheta) + c2*theta + c4*dtheta + c5*theta**3 + c3*P"},
        diffusion={"dtheta": "c3*sigma"},
        observations=_OBS_THETA,
        parameters=["a1", "a2", "a3", "a4", "a5", "a6", "sigma"],
        constants={**{k: AERO_CONSTANTS[k] for k in ("c1", "c2", "c3", "c4", "c5")}, "gamma": AERO_GAMMA_EKF},
        initial_std={"theta": 0.01, "dtheta": 0.01}, integrator="euler", kinks="exact",
    )


def aero_m2() -> ModelSpec:
    """M2, first-order Wagner: the data-generating form with the full polynomial P."""
    return ModelSpec(
        name="M2", description="First-order Wagner unsteady aerodynamics (Eq. 16 with Eq. 18's P)",
        states=["theta", "dtheta", "CM"],
        derived={"F": _F, "P": _P},
        drift={"theta": "dtheta", "dtheta": "F", "CM": "B*(P - CM) + c6*F"},
        diffusion={"CM": "sigma"},
        observations=_OBS_THETA,
        parameters=["B", "a1", "a2", "a3", "a4", "a5", "a6", "sigma"],
        constants={**AERO_CONSTANTS, "gamma": AERO_GAMMA_EKF},
        initial_std=_INIT_STD, integrator="euler", kinks="exact",
    )


def aero_true() -> ModelSpec:
    """The data-generating model (Sec. 3.3): M2 with a5 = a6 = 0."""
    s = aero_m2().with_fixed(a5=0.0, a6=0.0)
    return s.model_copy(update={"name": "M2true", "description": "Data-generating model (Eq. 16)"})


def aero_m3() -> ModelSpec:
    """M3, second-order Wagner, state [theta, dtheta, CM, w] with w = CM' - c6 theta''."""
    return ModelSpec(
        name="M3", description="Second-order Wagner unsteady aerodynamics (Table 6)",
        states=["theta", "dtheta", "CM", "w"],
        derived={"F": _F, "P": _P,
                 "c7": "(0.5 + A)*B1 + (1 - A)*B2",
                 "kw": "2*c6*c7 + kappa - c6*(B1 + B2)"},
        drift={"theta": "dtheta", "dtheta": "F", "CM": "w + c6*F",
               "w": "-(B1 + B2)*w - B1*B2*CM + B1*B2*P + kw*F"},
        diffusion={"w": "B1*B2*sigma"},
        observations=_OBS_THETA,
        parameters=["A", "B1", "B2", "a1", "a2", "a3", "a4", "a5", "a6", "sigma"],
        constants={**AERO_CONSTANTS, "kappa": 0.5, "gamma": AERO_GAMMA_EKF},
        initial_std={**_INIT_STD, "w": 0.01}, integrator="euler", kinks="exact",
    )


def polynomial() -> ModelSpec:
    """Appendix A: y = a0 + a1 x + ... + a4 x^4 + eps (x a known input column; no dynamics)."""
    return ModelSpec(
        name="polynomial", description="Polynomial regression (Appendix A); x is a data column",
        states=["z"], drift={"z": 0.0}, inputs=["x"],
        observations=[{"column": "y", "expr": "a0 + a1*x + a2*x**2 + a3*x**3 + a4*x**4", "noise_std": "gamma"}],
        parameters=["a0", "a1", "a2", "a3", "a4", "gamma"],
        initial_std={"z": 0.0}, substeps=1, integrator="euler",
    )


def linear_gaussian() -> ModelSpec:
    """Two-state linear SDE observed in noise, for exactness tests against a Kalman filter."""
    return ModelSpec(
        name="linear_gaussian", description="dx = A x dt + diag(q) dW, y = x1 + N(0, r^2)",
        states=["x1", "x2"],
        drift={"x1": "a11*x1 + a12*x2", "x2": "a21*x1 + a22*x2"},
        diffusion={"x1": "q1", "x2": "q2"},
        observations=[{"column": "y", "expr": "x1", "noise_std": "r"}],
        parameters=["a11", "a12", "a21", "a22", "q1", "q2", "r"],
        initial_mean={"x1": "m1"}, initial_std={"x1": 1.0, "x2": 1.0},
        constants={"m1": 0.5},
    )


def linear_oscillator() -> ModelSpec:
    """Free linear damped oscillator y'' = -k y - c y' (+ noise): the pendulum's starting model."""
    return ModelSpec(
        name="linear_oscillator", description="y'' = -k y - c y' + sigma xi",
        states=["y", "v"], drift={"y": "v", "v": "-k*y - c*v"}, diffusion={"v": "sigma"},
        observations=[{"column": "y", "expr": "y", "noise_std": "gamma"}],
        parameters=["k", "c", "sigma"], constants={"gamma": 1e-4},
        initial_std={"y": 1.0, "v": 1.0},
    )


def forced_linear_oscillator() -> ModelSpec:
    """Linear forced oscillator y'' = -k y - c y' + b u: Silverbox's starting model."""
    return ModelSpec(
        name="forced_linear_oscillator", description="y'' = -k y - c y' + b u + sigma xi",
        states=["y", "v"], inputs=["u"],
        drift={"y": "v", "v": "-k*y - c*v + b*u"}, diffusion={"v": "sigma"},
        observations=[{"column": "y", "expr": "y", "noise_std": "gamma"}],
        parameters=["k", "c", "b", "sigma"], constants={"gamma": 1e-4},
        initial_std={"y": 0.1, "v": 10.0},
    )


def duffing() -> ModelSpec:
    """Forced Duffing oscillator y'' = -k y - c y' - k3 y^3 + b u (Silverbox's physics)."""
    s = forced_linear_oscillator()
    return s.model_copy(update={
        "name": "duffing", "description": "y'' = -k y - c y' - k3 y^3 + b u + sigma xi",
        "drift": {"y": "v", "v": "-k*y - c*v - k3*y**3 + b*u"},
        "parameters": ["k", "c", "k3", "b", "sigma"]}).revalidate()


def pendulum() -> ModelSpec:
    """Pendulum theta'' = -w2 sin(theta) - c theta' (+ noise)."""
    return linear_oscillator().model_copy(update={
        "name": "pendulum", "description": "theta'' = -w2 sin(theta) - c theta' + sigma xi",
        "drift": {"y": "v", "v": "-w2*sin(y) - c*v"}, "parameters": ["w2", "c", "sigma"]}).revalidate()


BUILTINS = {
    "M1": aero_m1, "M2": aero_m2, "M3": aero_m3, "M2true": aero_true,
    "polynomial": polynomial, "linear_gaussian": linear_gaussian,
    "linear_oscillator": linear_oscillator, "forced_linear_oscillator": forced_linear_oscillator,
    "duffing": duffing, "pendulum": pendulum,
}


def builtin(name: str) -> ModelSpec:
    """A built-in model by name (see :data:`BUILTINS`)."""
    try:
        return BUILTINS[name]()
    except KeyError:
        raise ModelError(f"unknown built-in model {name!r}{did_you_mean(name, BUILTINS)} "
                         f"(known: {', '.join(BUILTINS)})") from None
