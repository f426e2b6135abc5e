"""The lag move (a state the model lacks): which quantities it is offered for, and the model it builds."""

import numpy as np
import sympy as sp

from ardflow.ardcore.effects.states import Lag, lag_spec, lags
from ardflow.ardcore.loop.states import dominant_rate, signal_values
from ardflow.ardcore.model.declaration import ModelSpec, symbolic
from ardflow.ardcore.model.library import aero_m1, aero_m2


def test_a_quasi_steady_moment_is_offered_a_lag_and_a_lagged_one_is_not():
    assert lags(aero_m1()) == [Lag("P", "dtheta")]
    assert lags(aero_m2()) == []  # CM' = B (P - CM) + ...: P already acts through a lag


def test_the_lagged_quasi_steady_model_is_the_first_order_wagner_model():
    """M1 with its moment P through a lag is M2, the lag's rate M2's B and its feedthrough M2's c6 (the
    apparent mass), the noise declared on the moment moved into the lag's equation."""
    lagged = lag_spec(aero_m1(), Lag("P", "dtheta"))
    m2 = aero_m2()
    c6 = m2.constants["c6"]
    a = lagged.with_fixed(b_P=0.2, k_P=c6)
    b = m2.with_fixed(B=0.2)
    sa, sb = symbolic(a), symbolic(b)
    rename = {sp.Symbol("lag_P", real=True): sp.Symbol("CM", real=True)}
    assert [str(x) for x in sa.states] == ["theta", "dtheta", "lag_P"]
    for fa, fb in zip(sa.drift, sb.drift):
        assert sp.simplify(fa.subs(rename) - fb) == 0
    assert [sp.simplify(g.subs(rename) - h) for g, h in zip(sa.diffusion, sb.diffusion)] == [0, 0, 0]


def test_the_lag_rate_prior_is_centred_on_the_record_s_dominant_frequency():
    t = np.arange(5000) * 0.1
    y = np.sin(0.194 * t) + 0.1 * np.random.default_rng(0).standard_normal(t.size)
    assert abs(dominant_rate(y, 0.1) - 0.194) < 2 * np.pi / 500.0  # one bin of a 500-unit record


def test_a_derived_quantity_is_evaluated_along_the_states():
    m1 = aero_m1().with_fixed(a3=0.0, a5=0.0, a6=0.0)
    x = np.array([[0.1, 0.02], [-0.05, 0.01]])
    phi = {"a1": -1.2, "a2": 0.5, "a4": -400.0, "sigma": 0.002}
    got = signal_values(m1, phi, "P", x, {})
    want = -1.2 * x[:, 0] + 0.5 * x[:, 1] - 400.0 * x[:, 0] ** 2 * x[:, 1]
    np.testing.assert_allclose(got, want)


def test_an_added_state_reads_as_a_state_in_the_headline():
    """The headline names the state, its equation and its time constant with the interval (not 'the declared
    *(P) replaced')."""
    from ardflow.ardcore.loop.verdict import headline

    state = {"name": "lag_P", "kind": "lag", "term": "P", "target": "dtheta",
             "equation": "lag_P' = b_P*(P - lag_P) + k_P*dtheta'",
             "parameters": {"b_P": {"name": "b_P", "mean": 0.17, "sd": 0.02, "q005": 0.135, "q995": 0.218}},
             "time_constant": {"mean": 5.88, "q005": 4.59, "q995": 7.41}}
    fr = {"rms_error": 0.0175}
    report = {"added": [], "replaced": [{"parameter": "", "term": "P", "target": "dtheta", "by": "the state lag_P",
                                         "form": "lag", "log_bayes_factor": 70.5, "state": state}],
              "before": {"free_run": fr, "log_evidence": 26100.8},
              "after": {"free_run": {"rms_error": 0.011}, "log_evidence": 26171.3}, "rounds": [{}]}
    text = headline(report, "y")
    assert "A state added: lag_P' = b_P*(P - lag_P) + k_P*dtheta'" in text, text
    assert "time constant 5.88 (99 % 4.59 to 7.41)" in text, text
    assert "declared" not in text.split(".")[0], text


def test_a_hysteresis_and_a_sensor_are_offered_on_an_oscillator_and_built_as_declared():
    from ardflow.ardcore.model.library import builtin

    osc = builtin("forced_linear_oscillator")
    x, v = osc.states[:2]
    col = osc.observations[0].column
    offered = [*lags(osc)]
    from ardflow.ardcore.effects.states import hystereses, sensors

    assert lags(osc) == [] and hystereses(osc) == [Lag(x, v, "hysteresis")]
    assert sensors(osc) == [Lag(osc.observations[0].expr, col, "sensor")]
    h = lag_spec(osc, hystereses(osc)[0])
    z = h.states[-1]
    assert h.drift[z] == f"{v} - beta_{x}*abs({v})*{z} - gamma_{x}*{v}*abs({z})"
    assert f"k_hys_{x}*{z}" in h.drift[v] and h.parameters[-3:] == [f"k_hys_{x}", f"beta_{x}", f"gamma_{x}"]
    s = lag_spec(osc, sensors(osc)[0])
    m = s.states[-1]
    assert s.observations[0].expr == m and s.drift[m] == f"b_sensor_{col}*(({osc.observations[0].expr}) - {m})"
    # once read through a sensor and given a hysteresis, neither is offered again
    assert sensors(s) == [] and hystereses(h) == [] and offered == []


def test_an_actuator_reads_the_user_s_input_through_a_lag_and_is_offered_once():
    """The actuator built on the forced linear oscillator: every drift equation reads the new state where it read
    the input, the state follows the input at rate b; a column the loop made (an input's rate) is not offered,
    and an input read through an actuator is not offered again."""
    from ardflow.ardcore.effects.base import RATE_COLUMN
    from ardflow.ardcore.effects.states import actuators
    from ardflow.ardcore.model.library import builtin

    osc = builtin("forced_linear_oscillator")
    (u,), v = osc.inputs, osc.states[1]
    assert actuators(osc) == [Lag(u, v, "actuator")]
    a = lag_spec(osc, actuators(osc)[0], (0.2, 0.1))
    z = a.states[-1]
    assert (z, a.parameters[-1]) == (f"act_{u}", f"b_act_{u}") and a.drift[z] == f"b_act_{u}*({u} - {z})"
    assert a.initial_mean[z] == 0.2 and a.initial_std[z] == 0.1
    A, U = sp.Symbol(z, real=True), sp.Symbol(u, real=True)
    assert sp.simplify(symbolic(a).drift[1] - symbolic(osc).drift[1].subs(U, A)) == 0
    assert actuators(a) == []
    rate = RATE_COLUMN.format(u)
    made = osc.model_copy(update={"inputs": [u, rate], "parameters": [*osc.parameters, "k_rate"],
                                  "drift": {**osc.drift, v: f"{osc.drift[v]} + k_rate*{rate}"}}).revalidate()
    assert actuators(made) == [Lag(u, v, "actuator")]


def test_a_second_mode_is_a_mass_on_a_spring_and_damper_and_is_offered_once():
    """The mode built on the forced linear oscillator is the two-degree-of-freedom system it stands for: with the
    mass ratio mu, the oscillator's equation gains mu times the force its spring and damper pass to the mode,
    the mode's own equation loses that force; a mode is offered once, and neither a mode nor a hysteresis of the
    mode's own oscillator is offered after it."""
    from ardflow.ardcore.effects.states import hystereses, modes
    from ardflow.ardcore.model.library import builtin

    osc = builtin("forced_linear_oscillator")
    x, v = osc.states[:2]
    assert modes(osc) == [Lag(x, v, "mode")]
    m = lag_spec(osc, modes(osc)[0], (0.3, 0.5))
    q, dq = m.states[-2:]
    assert (q, dq) == (f"mode_{x}", f"dmode_{x}") and m.parameters[-3:] == [f"w_mode_{x}", f"z_mode_{x}", f"mu_mode_{x}"]
    assert m.initial_mean[q] == 0.3 and m.initial_mean[dq] == 0.0 and m.initial_std[dq] == 0.5
    sm = symbolic(m.with_fixed(**{f"w_mode_{x}": 9.0, f"z_mode_{x}": 0.03, f"mu_mode_{x}": 0.3}))
    X, V, Q, DQ = (sp.Symbol(n, real=True) for n in (x, v, q, dq))
    force = 81 * (Q - X) + 2 * 0.03 * 9 * (DQ - V)
    base = symbolic(osc).drift[1]
    assert sp.simplify(sm.drift[1] - base - 0.3 * force) == 0
    assert sm.drift[2] == DQ and sp.simplify(sm.drift[3] + force) == 0
    assert modes(m) == [] and hystereses(m) == [Lag(x, v, "hysteresis")]


def test_a_store_exchanges_with_a_first_order_state_and_is_offered_once():
    """The store built on Newton cooling is the two-mass system it stands for: the body's equation gains the
    exchange k (S - T), the store follows the body at rate b; it is offered for a first-order state only (not for
    an oscillator's), once, and not for a state a family added (a sensor's, its own)."""
    from ardflow.ardcore.effects.states import sensors, stores
    from ardflow.ardcore.model.library import builtin

    cool = ModelSpec(name="nc", states=["T"], inputs=["u"], drift={"T": "q*u - a*(T - 295)"}, diffusion={"T": "s"},
                     observations=[{"column": "y", "expr": "T", "noise_std": "gamma"}], constants={"gamma": 0.1},
                     parameters=["a", "q", "s"], initial_mean={"T": 295.0}, initial_std={"T": 5.0})
    assert stores(cool) == [Lag("T", "T", "store")] and stores(builtin("forced_linear_oscillator")) == []
    m = lag_spec(cool, stores(cool)[0], (296.0, 3.0))
    assert m.states == ["T", "store_T"] and m.parameters[-2:] == ["b_store_T", "k_store_T"]
    assert m.initial_mean["store_T"] == 296.0 and m.initial_std["store_T"] == 3.0
    sm = symbolic(m.with_fixed(b_store_T=0.001, k_store_T=0.003))
    T, S = sp.Symbol("T", real=True), sp.Symbol("store_T", real=True)
    assert sp.simplify(sm.drift[0] - symbolic(cool).drift[0] - 0.003 * (S - T)) == 0
    assert sp.simplify(sm.drift[1] - 0.001 * (T - S)) == 0
    assert stores(m) == []
    read = lag_spec(cool, sensors(cool)[0], (295.0, 0.1))
    assert stores(read) == [Lag("T", "T", "store")]


def test_a_transfer_lag_puts_a_lag_between_two_first_order_states_and_is_offered_once():
    """Two tanks in cascade with the upper one's level reaching the lower one's equation through a lag is the
    pipe between them: the lower equation reads the lagged level, which follows the upper one at rate b. It is
    offered for a first-order state that another first-order state's drift reads (not an oscillator's), once,
    and not for the state it added."""
    from ardflow.ardcore.effects.states import transfers
    from ardflow.ardcore.model.library import builtin

    tanks = ModelSpec(name="tanks", states=["h1", "h2"], inputs=["u"],
                      drift={"h1": "q*u - a*h1", "h2": "a*sqrt(h1) - c*h2"}, diffusion={"h1": "s", "h2": "s"},
                      observations=[{"column": "y", "expr": "h2", "noise_std": "gamma"}], constants={"gamma": 0.01},
                      parameters=["a", "c", "q", "s"], initial_mean={"h1": 1.0, "h2": 1.0},
                      initial_std={"h1": 0.1, "h2": 0.1})
    assert transfers(tanks) == [Lag("h1", "h2", "transfer")]
    assert transfers(builtin("forced_linear_oscillator")) == [] and transfers(aero_m2()) == []
    m = lag_spec(tanks, transfers(tanks)[0], (1.2, 0.3))
    assert m.states == ["h1", "h2", "tr_h1_h2"] and m.parameters[-1] == "b_tr_h1_h2"
    assert m.initial_mean["tr_h1_h2"] == 1.2 and m.initial_std["tr_h1_h2"] == 0.3
    sm, base = symbolic(m.with_fixed(b_tr_h1_h2=0.5)), symbolic(tanks)
    h1, z = sp.Symbol("h1", real=True), sp.Symbol("tr_h1_h2", real=True)
    assert sp.simplify(sm.drift[0] - base.drift[0]) == 0
    assert sp.simplify(sm.drift[1] - base.drift[1].subs(h1, z)) == 0
    assert sp.simplify(sm.drift[2] - 0.5 * (h1 - z)) == 0
    assert transfers(m) == []


def test_a_relaxation_exchanges_with_an_oscillator_s_velocity():
    """The relaxation built on a forced oscillator is a Maxwell element on its velocity: the velocity's equation
    gains k (z - v), z follows v at rate b; it is offered for an oscillator only (not for a first-order state),
    once."""
    from ardflow.ardcore.effects.states import relaxations
    from ardflow.ardcore.model.library import builtin

    osc = builtin("forced_linear_oscillator")
    assert relaxations(osc) == [Lag("v", "v", "relaxation")]
    m = lag_spec(osc, relaxations(osc)[0], (0.0, 0.5))
    assert m.states == ["y", "v", "rel_v"] and m.parameters[-2:] == ["b_rel_v", "k_rel_v"]
    sm = symbolic(m.with_fixed(b_rel_v=4.0, k_rel_v=1.5))
    V, Z = sp.Symbol("v", real=True), sp.Symbol("rel_v", real=True)
    assert sp.simplify(sm.drift[1] - symbolic(osc).drift[1] - 1.5 * (Z - V)) == 0
    assert sp.simplify(sm.drift[2] - 4.0 * (V - Z)) == 0
    assert relaxations(m) == []
    cool = ModelSpec(name="nc", states=["T"], inputs=["u"], drift={"T": "q*u - a*(T - 295)"}, diffusion={"T": "s"},
                     observations=[{"column": "y", "expr": "T", "noise_std": "gamma"}], constants={"gamma": 0.1},
                     parameters=["a", "q", "s"], initial_mean={"T": 295.0}, initial_std={"T": 5.0})
    assert relaxations(cool) == []


def test_a_pickup_is_a_noise_driven_vibration_the_sensor_reads_and_the_dynamics_never_see():
    """The pickup built on the forced linear oscillator: the measurement reads the declared expression plus the
    vibration, whose own second-order equation is driven by its noise level and by nothing of the model; no drift
    of the oscillator changes; it is offered once, and no state family takes the pickup for an oscillator (no
    mode, hysteresis or relaxation of it), and only an oscillator's measurement is offered one."""
    from ardflow.ardcore.effects.states import hystereses, modes, pickups, relaxations
    from ardflow.ardcore.model.library import builtin

    osc = builtin("forced_linear_oscillator")
    col = osc.observations[0].column
    assert pickups(osc) == [Lag(str(osc.observations[0].expr), col, "pickup")]
    m = lag_spec(osc, pickups(osc)[0], (0.0, 0.01, 0.09))
    p, dp = m.states[-2:]
    assert (p, dp) == (f"pick_{col}", f"dpick_{col}")
    assert m.parameters[-3:] == [f"w_pick_{col}", f"z_pick_{col}", f"s_pick_{col}"]
    assert m.initial_std[p] == 0.01 and m.initial_std[dp] == 0.09 and m.initial_mean[p] == 0.0
    sm = symbolic(m.with_fixed(**{f"w_pick_{col}": 9.0, f"z_pick_{col}": 0.03, f"s_pick_{col}": 0.2}))
    base = symbolic(osc)
    P, DP = (sp.Symbol(n, real=True) for n in (p, dp))
    assert all(sp.simplify(a - b) == 0 for a, b in zip(sm.drift[:2], base.drift))
    assert sm.drift[2] == DP and sp.simplify(sm.drift[3] + 81 * P + 2 * 0.03 * 9 * DP) == 0
    assert sp.simplify(sm.obs[0] - base.obs[0] - P) == 0
    assert sm.diffusion[3] == sp.Float(0.2) and all(sm.diffusion[i] == base.diffusion[i] for i in range(2))
    assert pickups(m) == [] and modes(m) == modes(osc) and hystereses(m) == hystereses(osc)
    assert relaxations(m) == relaxations(osc)
    # a first-order system's measurement is offered none: its line is as often a store or a forcing it lacks
    cool = ModelSpec(name="nc", states=["T"], inputs=["u"], drift={"T": "q*u - a*(T - 295)"}, diffusion={"T": "s"},
                     observations=[{"column": "y", "expr": "T", "noise_std": "gamma"}], constants={"gamma": 0.1},
                     parameters=["a", "q", "s"], initial_mean={"T": 295.0}, initial_std={"T": 5.0})
    assert pickups(cool) == []


def test_a_pickup_is_offered_at_the_innovations_line_that_is_no_harmonic():
    """:func:`lines` reads each channel's strongest innovation peak that is not a harmonic of the record's own
    oscillation (in rad per time unit); a channel with none is offered no pickup."""
    from ardflow.ardcore.loop.states import lines

    tests = {"y": {"spectrum": {"peaks": [{"f": 0.2, "harmonic": 1}, {"f": 0.15, "harmonic": None},
                                          {"f": 0.4, "harmonic": 2}]}},
             "z": {"spectrum": {"peaks": [{"f": 0.2, "harmonic": 1}]}}}
    assert lines(tests) == {"y": 2 * np.pi * 0.15}


def _screened(name: str):
    """The stop stage's screen of the state moves on a validation record's first 2,000 samples, from the user's
    linear oscillator fitted there: {kind: conditional ln BF}."""
    from types import SimpleNamespace

    from ardflow.ardcore.loop.confirm import Fit
    from ardflow.ardcore.screening.states import conditional, screen
    from ardflow.ardcore.effects.states import actuators, hystereses, modes, sensors, stores
    from ardflow.ardcore.loop.states import along, lag_candidate
    from ardflow.ardcore.selection.study import run_candidate
    from tests.bench.validation import RECORDS

    rec = RECORDS[name](n=2000)
    cand = rec.spec.models[0]
    row, mr = run_candidate(cand, rec.est, rec.spec, 0, final_posterior="laplace")
    cur = Fit(cand, row, mr, rec.est)
    at, ms = along(cur), cand.model_spec()
    moves = hystereses(ms) + sensors(ms) + actuators(ms) + stores(ms) + modes(ms)
    reduced = [conditional(lag_candidate(cur, m, at), dict(zip(mr.sampler.names, mr.sampler.phi_star)))
               for m in moves]
    # the screen searches only the new state's own parameters: the current model's are held at its MAP
    assert all(r.target(rec.est).names == r.new and set(r.new).isdisjoint(mr.sampler.names)
               and set(r.new) | set(r.known) == set(r.cand.priors) for r in reduced)
    ctx = SimpleNamespace(mapper=lambda fn, tasks: [fn(t) for t in tasks])
    got = screen(ctx, reduced, rec.est, 0)
    return {m.kind: log_z - row.goodness_of_fit for m, (log_z, _) in zip(moves, got)}, {
        m.kind: at for m, (_, at) in zip(moves, got)}


def test_the_screen_puts_a_planted_second_mode_first_near_its_frequency():
    """On a record whose truth has a second mode (9 rad/s, mass ratio 0.3), the mode's conditional ln BF is
    positive and the highest of the states, and its screened frequency is near the truth's: the full fit
    then starts there."""
    gain, at = _screened("second_mode")
    assert gain["mode"] > 0 and gain["mode"] == max(gain.values()), gain
    assert abs(at["mode"]["w_mode_y"] - 9.0) < 1.0, at["mode"]


def test_the_screen_gives_no_state_a_gain_on_a_clean_record():
    """On a record whose truth is the user's linear oscillator, no state move's conditional ln BF is positive:
    none is fitted in full."""
    gain, _ = _screened("none")
    assert all(g <= 0 for g in gain.values()), gain
