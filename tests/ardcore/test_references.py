"""Powers about the level a declared law measures its state from (ardcore.effects.families.references)."""

import numpy as np
from scipy import optimize

from ardflow.ardcore.effects.families import candidate_effects, references
from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.likelihood.simulate import simulate_model
from ardflow.ardcore.model.declaration import ModelSpec
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.screening.screen import ScreenInput, screen_effects


def cooling(drift: str = "q*u - a*(T - 295)", **extra) -> ModelSpec:
    return ModelSpec.model_validate({
        "name": "cooling", "states": ["T"], "inputs": ["u", "Ta"], "drift": {"T": drift},
        "diffusion": {"T": "s"}, "observations": [{"column": "y", "expr": "T", "noise_std": "gamma"}],
        "constants": {"gamma": 0.1}, "parameters": ["a", "q", "s"], "initial_mean": {"T": 295.0},
        "initial_std": {"T": 1.0}, **extra})


def test_the_level_a_declared_law_measures_from_is_read_in_any_written_form():
    found = {d: references(cooling(d), "T") for d in (
        "q*u - a*(T - 295)", "q*u + a*(295 - T)", "q*u - 0.5*(T - 295)", "q*u - 0.5*T + 147.5",
        "q*u - a*(2*T - 590)", "q*u - a*(T + 20)", "q*u - a*(T - Ta)",
        "q*u - a*T", "2*u - 0.5*T", "q*u - a*T + 3")}
    assert found == {
        "q*u - a*(T - 295)": ["295"], "q*u + a*(295 - T)": ["295"], "q*u - 0.5*(T - 295)": ["295"],
        "q*u - 0.5*T + 147.5": ["295"], "q*u - a*(2*T - 590)": ["295"], "q*u - a*(T + 20)": ["-20"],
        "q*u - a*(T - Ta)": ["Ta"],  # an ambient the record carries
        # no level: a law through 0, an input's forcing, an offset beside a symbolic coefficient
        "q*u - a*T": [], "2*u - 0.5*T": [], "q*u - a*T + 3": []}
    # a derived quantity moves with the states: M2's moment lags P - CM, which is no level
    m2 = builtin("M2")
    assert all(references(m2, s) == [] for s in m2.states)


def test_the_powers_about_a_level_vanish_where_the_declared_law_does():
    names = {e.name: e for e in candidate_effects(cooling("q*u - a*(T + 20)"))}
    assert {"square(T+20)", "cube(T+20)", "power_law(T+20)"} <= set(names)
    assert names["square(T+20)"].terms == ("(T+20)**2",)
    # an oscillator's laws run through 0: its library is what it was
    lin = builtin("forced_linear_oscillator")
    assert not [e for e in candidate_effects(lin, scales={"y": 1.0}) if e.code.startswith("r")]
    # a spring to a drive, k*(u - y), or about a rest position, -k*(y - 0.3), in the velocity's equation: the
    # position's powers about it
    drive = lin.model_copy(update={"drift": {"y": "v", "v": "-c*v + k*(u - y)"}}).revalidate()
    rest = lin.model_copy(update={"drift": {"y": "v", "v": "-c*v - k*(y - 0.3) + b*u"}}).revalidate()
    assert references(drive, "y", "v") == ["u"] and references(rest, "y", "v") == ["0.3"]
    assert {"square(y-u)", "cube(y-u)"} <= {e.name for e in candidate_effects(drive, scales={"y": 1.0})}
    assert "cube(y-0.3)" in {e.name for e in candidate_effects(rest, scales={"y": 1.0})}
    # the loop passes the user's model: a level the loop's own terms hold (an overflow's h0) is not the user's
    grown = cooling("q*u - a*T + k*0.5*((T - 349) + sqrt((T - 349)**2 + 1))", parameters=["a", "q", "s", "k"])
    assert not [e for e in candidate_effects(grown, declared=cooling("q*u - a*T")) if "T-349" in e.name]


def test_the_screen_puts_radiation_about_the_ambient_above_the_stand_ins():
    """A body cooling to a 295 K ambient by convection and radiation, T^4 - 295^4: outside the library. The
    user declares Newton cooling; the square about the ambient is the radiation's leading term, and it screens
    above the library's powers of T itself (which vanish at 0 K) and its hinges."""
    rng = np.random.default_rng(3)
    n, dt = 3000, 5.0
    u = np.repeat(rng.uniform(0.0, 100.0, n), rng.integers(60, 300, n))[:n]
    truth = cooling("(u - 0.5*(T - 295) - 2.55e-9*(T**4 - 295**4))/500", input_hold="zoh")
    truth = truth.model_copy(update={"parameters": ["s"], "drift": {"T": truth.drift["T"]}}).revalidate()
    data = simulate_model(truth, {"s": 0.02}, np.arange(n) * dt, 5, inputs={"u": u, "Ta": np.full(n, 295.0)},
                          x0=[295.0])
    user = cooling(input_hold="zoh")
    lik = compile_model(user).bind(data)
    r = optimize.minimize(lambda z: -lik(np.exp(z)), np.log([1e-3, 2e-3, 0.02]), method="Nelder-Mead",
                          options={"maxfev": 2000, "xatol": 1e-4, "fatol": 1e-3})
    phi = dict(zip(["a", "q", "s"], np.exp(r.x)))
    T = data.columns["y"]
    levels = {"T": (float(T.min()), float(np.median(T)), float(T.max()))}
    ranked = screen_effects(ScreenInput(user, phi, data), candidate_effects(user, scales={"T": float(T.std())},
                                                                          levels=levels), ["T"], ["y"])
    assert "(T-295" in ranked[0].effect.name, [(c.effect.name, c.log_bayes_factor) for c in ranked[:5]]
    assert ranked[0].physical[0] < 0  # it cools
