"""Closing the loop on synthetic reference data with undeclared effects, on clean data, and on real data (slow).

`make test-slow` runs these; each prints the figures the closing note quotes.
"""

import json
from pathlib import Path

import numpy as np
import pytest

from ardflow.ardcore.data import load_pendulum, load_silverbox
from ardflow.ardcore.loop.config import DiagnoseConfig
from ardflow.ardcore.loop.diagnose import diagnose
from ardflow.ardcore.effects.base import Effect, augment
from ardflow.ardcore.model.library import AERO_TRUE, aero_true
from ardflow.ardcore.likelihood.simulate import simulate_reference
from ardflow.ardcore.selection.spec import StudySpec, load_spec
from tests.pendulum_standin import pendulum_folder

pytestmark = [pytest.mark.slow, pytest.mark.timeout(3600)]
ROOT = Path(__file__).resolve().parents[2]

# M2's optimal nested structure (the data-generating form) with essential priors: the proposed model
M2_PRIORS = {"B": {"kind": "lognormal", "median": 0.2, "cov": 50}, "a1": {"kind": "uniform", "low": -2, "high": 0},
             "a2": {"kind": "uniform", "low": -2, "high": 0}, "a3": {"kind": "uniform", "low": -250, "high": 250},
             "a4": {"kind": "uniform", "low": -1000, "high": 0},
             "sigma": {"kind": "lognormal", "median": 0.002, "cov": 50}}


def m2_spec(seed):
    return StudySpec.model_validate({
        "name": "loop", "data": {"generator": "reference", "seed": seed},
        "models": [{"model": "M2true", "priors": M2_PRIORS}],
        "sampler": {"start_maxfev": 1500, "round_size": 250, "n_stationary": 1000, "n_proposal": 1000},
        "maximiser": {"step_decades": 2, "min_step_decades": 2, "max_sweeps": 1}, "seed": seed})


EFFECTS = {  # kind -> (effect as the library names it, target, value)
    "odd stiffness": (Effect("quintic_stiffness(theta)", "stiffness", ("theta**5",), code="s5theta"), "CM", 8000.0),
    "even stiffness": (Effect("quadratic_stiffness(theta)", "stiffness", ("theta**2",), code="s2theta"), "CM", 0.5),
    "damping": (Effect("cubic_damping(dtheta)", "damping", ("dtheta**3",), code="d3dtheta"), "CM", -3000.0),
}


def lco_error(fr):
    """Self-excited oscillation: amplitude and frequency errors, not phase."""
    return float(np.hypot(fr["amplitude_error"], fr["frequency_error"]))


@pytest.mark.parametrize("kind", list(EFFECTS))
def test_undeclared_effect_is_found_added_and_the_error_falls(kind):
    eff, target, value = EFFECTS[kind]
    spec, names = augment(aero_true(), eff, target)
    data = simulate_reference(3, true_params={names[0]: value}, spec=spec)
    rep = diagnose(m2_spec(3), data, config=DiagnoseConfig(top_k=3, max_rounds=1))
    j = rep.to_json()
    first = j["rounds"][0]["ranking"][0]  # evidence-confirmed first, then the regression order
    b, a = j["before"], j["after"]
    a = a or {"log_evidence": float("nan"), "innovation_rms": float("nan"),
              "free_run": {"amplitude_error": float("nan"), "frequency_error": float("nan"), "rms_error": float("nan")}}
    print(f"\n[{kind}] {eff.name} on {target} = {value}: ranked first {first['effect']} -> {first['target']}; "
          f"added {[x['effect'] for x in j['added']]}; posterior {j['added'][0]['posterior'] if j['added'] else None}; "
          f"confirmed {[(c['effect'], round(c['log_bayes_factor'], 2), c.get('stability', {}).get('z')) for c in j['rounds'][0]['confirmed']]}; "
          f"ln Z {b['log_evidence']:.2f} -> {a['log_evidence']:.2f}; LCO error {lco_error(b['free_run']):.4f} -> "
          f"{lco_error(a['free_run']):.4f}; free-run RMS {b['free_run']['rms_error']:.4g} -> "
          f"{a['free_run']['rms_error']:.4g}; innovation RMS {b['innovation_rms']:.4g} -> {a['innovation_rms']:.4g}; "
          f"injected noise RMS {b['injected_noise_rms']} -> {a.get('injected_noise_rms')}; "
          f"harmonic error {b['free_run'].get('harmonic_error')} -> {a['free_run'].get('harmonic_error')}")
    assert (first["effect"], first["target"]) == (eff.name, target)
    assert j["added"] and j["added"][0]["effect"] == eff.name  # ARD kept it
    post = next(iter(j["added"][0]["posterior"].values()))
    assert post["q005"] < value < post["q995"]
    assert a["log_evidence"] > b["log_evidence"] + 5
    # the error that must fall: the process noise the model had to inject into the state the effect acts on
    assert a["injected_noise_rms"][target] < 0.8 * b["injected_noise_rms"][target]


@pytest.mark.parametrize("seed", [1, 2, 4])
def test_nothing_is_added_without_an_undeclared_effect(seed):
    rep = diagnose(m2_spec(seed), simulate_reference(seed), config=DiagnoseConfig(top_k=2, max_rounds=1)).to_json()
    print(f"\n[clean seed {seed}] {rep['verdict']}")
    assert rep["added"] == []
    assert rep["replaced"] == []  # no law in another form and no state (a lag, a sensor, a hysteresis) either


def test_a_measurement_noise_declared_far_too_small_is_raised_and_nothing_else_added():
    """A clean forced oscillator whose user declares its sensor 25 times quieter than it is (0.002 against 0.05).
    The filter then explains the sensor's noise by process noise, and the fit free-runs about five times worse
    than the model with the right noise. The score of the noise level at the declared value is ~0 (its share of
    the innovations' variance vanishes there), so the loop must confirm it anyway: it raises the noise, its
    factor's 99 % interval holding 25, adds nothing else (no forcing, mode or actuator standing in for it), and
    the reported model free-runs within 5 % of the same structure declared with the right noise."""
    from tests.bench import validation as V

    rng = np.random.default_rng(34)
    u = V._noise_input(rng, 4000)
    truth = V._truth("-k*y - c*v + b*u", ["k", "c", "b", "sigma"], 0.05)
    data = V._simulate(truth, {"k": 16.0, "c": 0.4, "b": 8.0, "sigma": 0.6}, np.arange(4000) * 0.02, u, 34, 2)
    est, test = data.slice(0, 2400), data.slice(2400, None)
    right = diagnose(V._oscillator_study("right", V._linear_oscillator(0.05), V.OSC_PRIORS), est, test_data=test,
                     config=DiagnoseConfig(max_rounds=0)).to_json()
    rep = diagnose(V._oscillator_study("quiet", V._linear_oscillator(2e-3), V.OSC_PRIORS), est,
                   test_data=test).to_json()
    fr, floor = rep["reported"]["free_run"]["rms_error"], right["before"]["free_run"]["rms_error"]
    k = {q: rep["final_fit"][q]["k_mny_y"] for q in ("q005", "q995")}
    print(f"\n[quiet sensor] {rep['verdict']}\n  free run {rep['before']['free_run']['rms_error']:.4g} -> {fr:.4g}"
          f" (declared right: {floor:.4g}); noise factor 99 % {np.exp(k['q005']):.3g}-{np.exp(k['q995']):.3g}")
    assert [a["effect"] for a in rep["added"]] == ["measurement_noise(y)"], rep["verdict"]
    assert rep["replaced"] == [], rep["verdict"]
    assert np.exp(k["q005"]) < 25.0 < np.exp(k["q995"])
    assert fr <= 1.05 * floor


def _sensor_mode_record():
    """The reference problem whose sensor also picks up a lightly damped, noise-driven mode at 0.15 cycles/tau
    (y = theta + z): a resonance of the measurement, not of the dynamics."""
    base = aero_true()
    w, zeta = 2 * np.pi * 0.15, 0.02
    spec = base.model_copy(update={
        "name": "M2mode", "states": list(base.states) + ["z", "zd"],
        "drift": {**base.drift, "z": "zd", "zd": f"-{w * w:.6g}*z - {2 * zeta * w:.6g}*zd"},
        "diffusion": {**base.diffusion, "zd": "0.00036"},
        "observations": [{"column": "y", "expr": "theta + z", "noise_std": "gamma"}],
        "initial_std": {**base.initial_std, "z": 0.0, "zd": 0.0}}).revalidate()
    return simulate_reference(3, spec=spec)


def test_effect_outside_the_library_is_reported_unexplained():
    """The sensor's noise-driven mode against the term families alone (the state families off): nothing among
    them is a random narrow-band process, so the loop must not add a term, and must say where the residual lies
    (the innovation peak at the mode's frequency)."""
    rep = diagnose(m2_spec(3), _sensor_mode_record(), config=DiagnoseConfig(top_k=3, max_rounds=1,
                                                                            states=False)).to_json()
    print(f"\n[outside the library] {rep['verdict']}")
    assert rep["added"] == [], rep["verdict"]
    assert "NOT explained" in rep["verdict"]
    peaks = [p["f"] for p in rep["tests_before"]["y"]["spectral_peaks"]]
    assert any(abs(f - 0.15) < 0.015 for f in peaks), peaks


def test_a_resonance_the_sensor_picks_up_is_a_pickup_not_a_mode_of_the_structure():
    """The same record with the state families: the innovations' line at 0.15 cycles/tau is offered as a pickup
    (a vibration the measurement reads and the dynamics never see) beside a second mode of the structure, which
    imitates it by coupling a resonance into the dynamics (before the pickup it was taken: a mode with a mass
    ratio of 0.76, the declared aerodynamics moved by 3-10 sd to make room for it). The evidence takes the pickup,
    at the planted frequency, and nothing else; the declared model's parameters, which had absorbed the resonance
    (B 0.89 against the truth's 0.2), come back to the truth within their 99 % intervals, and the free run improves
    (the filter no longer takes the resonance for the wing's motion)."""
    rep = diagnose(m2_spec(3), _sensor_mode_record(), config=DiagnoseConfig(top_k=3, max_rounds=1)).to_json()
    print(f"\n[sensor resonance] {rep['verdict']}")
    states = [x["state"] for x in rep["replaced"] if x.get("state")]
    assert [s["kind"] for s in states] == ["pickup"], rep["verdict"]
    f = states[0]["frequency"]
    assert f["q005"] < 0.15 < f["q995"], f
    assert rep["added"] == [], rep["verdict"]
    fit = rep["final_fit"]
    truth = {k: AERO_TRUE[k] for k in ("B", "a1", "a2", "a3", "a4", "sigma")}
    assert all(fit["q005"][k] < v < fit["q995"][k] for k, v in truth.items()), {
        k: (fit["q005"][k], fit["q995"][k]) for k in truth}
    assert rep["after"]["free_run"]["rms_error"] < 0.5 * rep["before"]["free_run"]["rms_error"]


def test_pendulum_sine_stiffness_and_held_out_free_run(tmp_path, monkeypatch):
    # the real record when $ARDFLOW_DATA holds it, else the synthetic stand-in with the same physics
    monkeypatch.setenv("ARDFLOW_DATA", str(pendulum_folder(tmp_path)))
    spec = load_spec(ROOT / "examples" / "pendulum_diagnose.json")
    base = ROOT / "examples"
    data = spec.data.load(base)
    full = load_pendulum()
    test = full.slice(40000, None)
    test = type(test)(test.t[::20].copy(), {"y": test.columns["y"][::20].copy()}, test.meta)
    rep = diagnose(spec, data, test_data=test, config=DiagnoseConfig(top_k=3, max_rounds=2))
    j = rep.to_json()
    print("\n[pendulum] " + j["verdict"])
    print(json.dumps({"before": j["before"]["free_run"], "after": j["after"]["free_run"],
                      "added": j["added"]}, indent=1))
    # a pendulum's restoring force is sin(theta): the sine stiffness, softening, its period L near 1 rad
    sine = [x for x in j["added"] if x["effect"].startswith("sine_stiffness(y")]
    assert sine and sine[0]["character"] == "softening", j["verdict"]
    L = next(iter(sine[0]["shape"].values()))
    assert L["q005"] < 1.0 < L["q995"], L
    # the declared encoder noise (1e-4) is too small: the loop estimates it, and the process noise that had
    # absorbed the misfit (and spoilt the free run) falls
    assert any(x["effect"] == "measurement_noise(y)" for x in j["added"]), j["verdict"]
    assert j["after"]["free_run"]["rms_error"] < 0.2 * j["before"]["free_run"]["rms_error"]
    assert j["after"]["free_run"]["rms_error"] < 0.04  # issue 11's target (a 3-term FROLS reaches 0.041)


def test_silverbox_hardening_cubic_on_the_test_segment():
    spec = load_spec(ROOT / "examples" / "silverbox_diagnose.json")
    data = spec.data.load(ROOT / "examples")
    full = load_silverbox()
    test = full.slice(105712, 127400)
    rep = diagnose(spec, data, test_data=test, config=DiagnoseConfig(top_k=3, max_rounds=3))
    j = rep.to_json()
    print("\n[silverbox] " + j["verdict"])
    print(json.dumps({"before": j["before"]["free_run"], "after": j["after"]["free_run"],
                      "added": j["added"]}, indent=1))
    # the customary second test record: the arrow (rows 100-40575), free run of the final model

    arrow = full.slice(100, 40575)
    arrow_err = {"initial": rep.initial.free_run(arrow)["rms_error"], "final": rep.final.free_run(arrow)["rms_error"]}
    print(f"[silverbox] arrow test segment: free-run RMS error {arrow_err['initial']:.4g} -> "
          f"{arrow_err['final']:.4g} V")
    stiff = [x for x in j["added"] if x["kind"] == "stiffness" and x["character"]]
    assert stiff and stiff[0]["character"] == "hardening"
    assert any(x["effect"] == "cubic_stiffness(y)" for x in j["added"]), j["verdict"]
    # both customary test segments (first-order hold and RK4: the model is no longer limited by a half-sample
    # input delay); the measured input feeds through to the measured output
    assert any(x["effect"] == "feedthrough(u)" for x in j["added"]), j["verdict"]
    assert j["after"]["free_run"]["rms_error"] < 0.1 * j["before"]["free_run"]["rms_error"]
    assert arrow_err["final"] < 0.1 * arrow_err["initial"]
    assert j["after"]["free_run"]["rms_error"] < 1e-3 and arrow_err["final"] < 1e-3
