"""Every family of the effect library planted in a forced oscillator and found by the closed loop (slow).

The truth is y'' = -k y - c y' + b u + (effect) + sigma xi, y measured with noise 2e-3, u a band-limited
random input; the proposed model lacks the effect. Each effect is sized to cost roughly 100-800 nats
(the loop's reported ln BF is printed). The loop (Laplace evidence, one round) must add the planted
family to the planted target and, when it adds the planted family itself, its coefficient's 99 % interval
must hold the truth; a shaped effect's shape must be within 25 % of the truth (or, loosely identified,
inside its fitted 99 % interval). On clean data (3 seeds) nothing is added.
"""

import pytest

from ardflow.ardcore.loop.config import DiagnoseConfig
from ardflow.ardcore.loop.diagnose import diagnose
from ardflow.ardcore.effects.base import Effect, augment
from ardflow.ardcore.selection.spec import StudySpec

from ..forced_oscillator import base_spec, forced_data

pytestmark = [pytest.mark.slow, pytest.mark.timeout(1800)]

def make_data(seed, effect=None, target="v", value=0.0):
    if effect is None:
        return forced_data(seed)
    truth, names = augment(base_spec(), effect, target)
    return forced_data(seed, truth, {nm: value for nm in names}, effect.columns_for)


def study(seed=2):
    return StudySpec.model_validate({
        "name": "families", "data": {"generator": "appendix_a"}, "evidence": "laplace",
        "models": [{"model": base_spec().model_dump(mode="json"),
                    "priors": {"k": {"kind": "lognormal", "median": 15.0, "cov": 100},
                               "c": {"kind": "lognormal", "median": 0.3, "cov": 200},
                               "b": {"kind": "lognormal", "median": 5.0, "cov": 200},
                               "sigma": {"kind": "lognormal", "median": 0.3, "cov": 200}}}],
        "sampler": {"n_stationary": 200, "n_proposal": 200, "round_size": 100, "start_maxfev": 600},
        "seed": seed})


def fp(delta):
    return f"0.5*(y - {delta}*sign(y))*(1 + sign(abs(y) - {delta}))"


def planted(name, kind, expr, code, value, *truth, **kw):
    """(planted effect, target, coefficient, accepted kinds or names, true shape or None) of one family; the
    target is the acceleration ``v`` unless the effect acts on the observation (then ``y``). ``truth``: the
    accepted kinds or names (default: the effect's name) and the true shape, when they are given."""
    accepted, shape = (*truth, None, None)[:2]
    eff = Effect(name, kind, expr if isinstance(expr, tuple) else (expr,), code=code, **kw)
    return eff, "y" if kw.get("where") == "observation" else "v", value, accepted or {name}, shape


FAMILIES = {
    "odd stiffness": planted("cubic_stiffness(y)", "stiffness", "y**3", "s3y", -1.2),
    "even stiffness": planted("quadratic_stiffness(y)", "stiffness", "y**2", "s2y", -0.7),
    "asymmetric stiffness": planted("asymmetric_stiffness(y)", "stiffness", "y*abs(y)", "say", -2.2),
    "cubic damping": planted("cubic_damping(v)", "damping", "v**3", "d3v", -0.12),
    "quadratic damping": planted("quadratic_damping(v)", "damping", "v*abs(v)", "dqv", -0.3),
    # a smooth sign over 0.05: the library's dry friction and Stribeck (whose peak may decay beyond the data) are
    # both this family
    "dry friction": planted("dry_friction(v)", "friction", "tanh(v/0.05)", "fdv", -1.0, {"friction"}),
    # a saturating stiffness is a free-play with a rounded corner: at this size and noise the evidence of the two
    # differs by a fraction of a nat either way, and the loop confirms both and names the better (see rival_nats)
    "free-play": planted("free_play(y)", "free-play", fp(0.3), "fpwy", -6.0, {"free-play", "saturation"}, 0.3),
    "saturation": planted("saturation(y)", "stiffness", "y - 0.3*tanh(y/0.3)", "sty", 8.0,
                          {"saturation", "free-play"}, 0.3),
    # a pendulum-like restoring force, -8 y - 8 sin(y): the data reach |y/L| ~ 3, where its higher orders tell
    # it from a cubic (with L = 1.5 the cubic alone has the higher evidence)
    # (written in the library's normalisation, 6 L^2 (y - L sin(y/L)) at L = 1: 8 (y - sin y) is 1.333 of it)
    "sine stiffness": planted("sine_stiffness(y)", "stiffness", "6*(y - sin(y))", "sny", 8.0 / 6.0,
                              {"sine_stiffness"}, 1.0),
    # a stop that the mass meets above y = 0.6 (std of y ~0.9): one-sided, so no symmetric family stands in
    "contact": planted("contact_above(y)", "stiffness", "0.5*(y - 0.6)*(1 + sign(y - 0.6))", "cay", -8.0,
                       {"contact_above"}, 0.6),
    "periodic forcing": planted("forcing(f=1.37)", "forcing", ("forcing0_sin", "forcing0_cos"), "fo0", 0.5,
                                {"forcing"}, 1.37, frequency=1.37),
    "input nonlinearity": planted("input_cubic(u)", "input", "u**3", "u3u", 0.35),
    "input-state cross": planted("input_cross(u*y)", "input", "u*y", "uuy", 1.5),
    # a small lead of the input (u(t + tau) ~ u + tau du/dt, tau = 0.01 of the 0.02 sampling interval x b = 5)
    "input rate": planted("input_rate(u)", "input", "d_u_dt", "uru", 0.05, rate_of="u"),
    "offset": planted("offset", "offset", "1", "off", 0.8),
    # in a linear model a sensor bias and a constant force are the same data: either is the right answer
    "sensor bias": planted("sensor_bias", "measurement", "1", "mb", 0.05, {"sensor_bias", "offset"},
                           where="observation"),
    "feedthrough": planted("feedthrough(u)", "measurement", "u", "mfu", 0.002, where="observation"),
    "sensor nonlinearity": planted("sensor_cubic(y)", "measurement", "(y)**3", "m3y", 0.015, where="observation"),
}


def _matches(added: dict, accepted: set) -> bool:
    base = added["effect"].split("(")[0]
    return added["effect"] in accepted or added["kind"] in accepted or base in accepted


def _shape(name: str) -> float | None:
    inside = name[name.index("(") + 1:-1] if "(" in name else ""
    for part in inside.split(","):
        if "=" in part:
            return float(part.split("=")[1])
    return None


def _found_first(case: str, planted_effect: tuple, seed: int, targets: tuple = ("v",)) -> dict:
    """Run the loop (one round) on data with the planted effect; the first effect added must be of the
    planted family, on its target (or one of ``targets``), with its shape within 25 %. Returns its record."""
    eff, target, value, accepted, shape = planted_effect
    rep = diagnose(study(), make_data(seed, eff, target, value),
                   config=DiagnoseConfig(max_rounds=1, band_draws=0)).to_json()
    added = rep["added"]
    print(f"\n[{case}] {eff.name} = {value} on {target}: added "
          + "; ".join(f"{a['effect']} -> {a['target']} (ln BF {a['log_bayes_factor']:.1f}) {a['posterior']}"
                      for a in added))
    assert added, rep["verdict"]
    first = added[0]
    assert _matches(first, accepted) and first["target"] in (target, *targets), (first["effect"], first["target"])
    if shape is not None and _shape(first["effect"]) is not None:
        # found: its screened shape within 25 % of the truth, or (a shape the data pin down only loosely, as a
        # narrow free-play's width) the fitted shape's 99 % interval holds the truth and its sd is under half of it
        fitted = list((first.get("shape") or {}).values())
        near = abs(_shape(first["effect"]) - shape) < 0.25 * shape
        held = bool(fitted) and fitted[0]["q005"] < shape < fitted[0]["q995"] and fitted[0]["sd"] < 0.5 * shape
        assert near or held, (first["effect"], fitted)
    return first


def _true_model_interval(eff, target, value, seed) -> tuple[float, float]:
    """Laplace posterior mean and sd of the planted coefficient in the *true* model on the same record: what
    no method can beat on this noise realisation."""
    import numpy as np

    from ardflow.ardcore.effects.base import with_columns
    from ardflow.ardcore.evidence.laplace import laplace
    from ardflow.ardcore.likelihood.posterior import ModelPosterior
    from ardflow.ardcore.model.priors import Normal

    from ..forced_oscillator import TRUE

    truth, names = augment(base_spec(), eff, target)
    # the loop's own priors on the model's parameters, a broad one on the planted coefficient
    priors = {**study().models[0].priors, names[0]: Normal(mean=0.0, sd=100.0 * abs(value))}
    tg = ModelPosterior(truth, priors, with_columns(make_data(seed, eff, target, value), eff))
    _, xmap, C = laplace(tg, np.array([TRUE.get(p, value) for p in tg.prior.names]))
    i = tg.prior.names.index(names[0])
    return float(xmap[i]), float(np.sqrt(C[i, i]))


@pytest.mark.parametrize("family", list(FAMILIES))
def test_planted_family_is_found(family):
    eff, target, value, accepted, shape = FAMILIES[family]
    first = _found_first(family, FAMILIES[family], 1)
    if first["effect"].split("(")[0] == eff.name.split("(")[0]:
        # the planted family itself (shaped ones too: their corners are rounded, their shapes fitted), its
        # coefficient's 99 % interval holds the truth; or, where this record's noise puts even the true
        # model's own 99 % interval off the truth (1 % of records: the input rate on seed 1, z = 3.0, where
        # 24 seeds show its posterior calibrated), the loop's estimate agrees with the true model's
        for post in first["posterior"].values():
            if not post["q005"] < value < post["q995"] and len(eff.terms) == 1 and not eff.shape:
                m, sd = _true_model_interval(eff, target, value, 1)
                assert abs(m - value) > 2.576 * sd and abs(post["mean"] - m) < 2 * max(sd, post["sd"]), \
                    (value, post, m, sd)
                continue
            assert post["q005"] < value < post["q995"], (value, post)


# Other sizes (x0.35 and x2.5 of the coefficient above), shapes and frequencies, on another noise realisation:
# a loop that finds an effect only at the size its test used has not found it. Left out: a saturation and a
# sine stiffness at x2.5 (-16 y + 20 (...) is an unstable truth; its record diverges and the loop refuses it,
# see test_a_record_no_parameter_can_fit_is_refused_with_its_reason). What the data cannot tell apart at the
# weak size is accepted: an offset force and a sensor bias (a static shift of y either way), a sine stiffness
# and another odd stiffness (its higher orders are then below the noise).
OTHER_SIZES = {f"{fam} x{m}": (eff, tgt, val * m, acc | ({"sensor_bias"} if fam == "offset" and m < 1 else set())
                                | ({"stiffness"} if fam == "sine stiffness" and m < 1 else set()), shp)
               for fam, (eff, tgt, val, acc, shp) in FAMILIES.items() for m in (0.35, 2.5)
               if not (m > 1 and fam in ("saturation", "sine stiffness"))}
OTHER_SIZES.update({
    "free-play width 0.15": planted("free_play(y)", "free-play", fp(0.15), "fpwy", -6.0, {"free-play", "saturation"},
                                    0.15),
    "saturation level 0.6": planted("saturation(y)", "stiffness", "y - 0.6*tanh(y/0.6)", "sty", 8.0,
                                    {"saturation", "free-play"}, 0.6),
    "contact below at 1.2": planted("contact_below(y)", "stiffness", "-0.5*(-y - 1.2)*(1 + sign(-y - 1.2))", "cby",
                                    -8.0, {"contact_below"}, 1.2),
    "dry friction over 0.15": planted("dry_friction(v)", "friction", "tanh(v/0.15)", "fdv", -1.0, {"friction"}),
    # by the resonance (0.64): the innovations' peak there is the oscillation's own; a driven model screens it
    "periodic forcing at 0.61": planted("forcing(f=0.61)", "forcing", ("forcing0_sin", "forcing0_cos"), "fo0", 0.5,
                                        {"forcing"}, 0.61, frequency=0.61),
    "periodic forcing at 2.9": planted("forcing(f=2.9)", "forcing", ("forcing0_sin", "forcing0_cos"), "fo0", 0.5,
                                       {"forcing"}, 2.9, frequency=2.9),
})


@pytest.mark.parametrize("case", list(OTHER_SIZES))
def test_family_is_found_at_other_sizes_and_shapes(case):
    """The family is added first, to its target (seed 4; the coefficient's interval is checked above)."""
    _found_first(case, OTHER_SIZES[case], 4, targets=("v", "y"))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_nothing_is_added_to_the_forced_oscillator_without_an_effect(seed):
    rep = diagnose(study(seed), make_data(seed), config=DiagnoseConfig(max_rounds=1, band_draws=0)).to_json()
    print(f"\n[forced clean seed {seed}] {rep['verdict']}")
    assert rep["added"] == [], rep["verdict"]


def test_van_der_pol_limit_cycle_from_a_linear_model():
    """A self-excited oscillator the library was not written for: van der Pol, y'' = mu (1 - y^2) y' - w2 y,
    offered as a linear oscillator with free (negative) damping. The loop must add the cross term y^2 v with
    -mu inside its 99 % interval, and the limit cycle's amplitude and frequency must come out within 5 %."""
    import numpy as np

    from ardflow.ardcore.data import Dataset
    from ardflow.ardcore.model.declaration import ModelSpec
    from ardflow.ardcore.likelihood.simulate import simulate_model

    truth = ModelSpec(name="vdp", states=["y", "v"], drift={"y": "v", "v": "mu*(1 - y**2)*v - w2*y"},
                      diffusion={"v": "s"}, observations=[{"column": "y", "expr": "y", "noise_std": "g"}],
                      parameters=["mu", "w2", "s"], constants={"g": 0.01}, initial_std={"y": 1.0, "v": 1.0})
    t = np.arange(4000) * 0.02
    y = simulate_model(truth, {"mu": 0.8, "w2": 9.0, "s": 0.2}, t, 3, x0=[0.5, 0.0]).columns["y"]
    model = truth.model_copy(update={"name": "lin", "drift": {"y": "v", "v": "c*v - w2*y"},
                                     "parameters": ["c", "w2", "s"]}).revalidate()
    st = StudySpec.model_validate({
        "name": "vdp", "data": {"generator": "appendix_a"}, "evidence": "laplace",
        "models": [{"model": model.model_dump(mode="json"),
                    "priors": {"c": {"kind": "normal", "mean": 0, "sd": 5},
                               "w2": {"kind": "lognormal", "median": 8, "cov": 100},
                               "s": {"kind": "lognormal", "median": 0.3, "cov": 200}}}],
        "sampler": {"n_stationary": 200, "n_proposal": 200, "round_size": 100, "start_maxfev": 600}, "seed": 1})
    est, test = Dataset(t[:2000], {"y": y[:2000]}, {}), Dataset(t[2000:] - t[2000], {"y": y[2000:]}, {})
    rep = diagnose(st, est, test_data=test, config=DiagnoseConfig(max_rounds=2, band_draws=0)).to_json()
    print(f"\n[van der Pol] {rep['verdict']}")
    assert [a["effect"] for a in rep["added"]] == ["cross(y^2*v)"], rep["verdict"]
    post = rep["added"][0]["posterior"]["k_c21y_v"]
    assert post["q005"] < -0.8 < post["q995"], post
    fr = rep["after"]["free_run"]
    assert abs(fr["amplitude_error"]) < 0.05 and abs(fr["frequency_error"]) < 0.05, fr


def test_input_rate_posterior_is_calibrated_over_seeds():
    """The input rate's coefficient in the true model: over 16 records the spread of (estimate - truth) / sd
    is that of a standard normal (a likelihood that mistook the rough rate column would be overconfident)."""
    import numpy as np

    eff, target, value, _, _ = FAMILIES["input rate"]
    z = []
    for seed in range(9, 25):
        m, sd = _true_model_interval(eff, target, value, seed)
        z.append((m - value) / sd)
    z = np.array(z)
    print(f"\n[input rate calibration] z mean {z.mean():.2f}, sd {z.std(ddof=1):.2f}")
    assert abs(z.mean()) < 0.8 and 0.5 < z.std(ddof=1) < 1.5, np.round(z, 2)
