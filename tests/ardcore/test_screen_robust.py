"""The screen's adjustment to coloured innovations (ardcore.screening.screen: innovation_background, spectral_score_cov)."""

import numpy as np
import pytest
from scipy import linalg, optimize, signal

from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.effects.base import Effect
from ardflow.ardcore.effects.families import candidate_effects
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.screening.robust import innovation_background, spectral_score_cov
from ardflow.ardcore.screening.screen import ScreenInput, screen_effects
from ardflow.ardcore.likelihood.simulate import simulate_model

from ..forced_oscillator import base_spec, forced_data


def test_score_covariance_under_coloured_noise_is_exact():
    """Var(psi @ eps) for an MA(1) noise eps_t = (z_t + b z_t-1) / sqrt(1 + b^2): the spectral formula against
    the exact Toeplitz covariance."""
    rng = np.random.default_rng(0)
    n, b = 4000, 0.8
    t = np.arange(n)
    psi = np.vstack([np.sin(2 * np.pi * 0.013 * t), np.cos(2 * np.pi * 0.013 * t), rng.standard_normal(n),
                     np.sin(2 * np.pi * 0.31 * t) * np.exp(-t / 3000)])
    r = np.zeros(n)
    r[0], r[1] = 1.0, b / (1 + b * b)
    exact = psi @ linalg.toeplitz(r) @ psi.T

    def psd(f):
        return np.abs(1 + b * np.exp(-2j * np.pi * f)) ** 2 / (1 + b * b)
    V = spectral_score_cov(psi, psd)
    assert np.allclose(V, exact, rtol=0.02, atol=0.02 * np.abs(exact).max())
    # a white spectrum gives the likelihood's own information
    assert np.allclose(spectral_score_cov(psi, lambda f: np.ones_like(f)), psi @ psi.T, rtol=1e-10)


@pytest.mark.parametrize("seed", [1, 2])
def test_innovation_background_is_one_for_white_noise_and_follows_colour(seed):
    rng = np.random.default_rng(seed)
    z = rng.standard_normal(20000)
    bg = innovation_background(z)
    f = np.linspace(0.01, 0.49, 50)
    assert np.all(np.abs(bg(f) - 1) < 0.3) and abs(np.mean(bg(f)) - 1) < 0.05
    b = 0.8
    x = (z[1:] + b * z[:-1]) / np.sqrt(1 + b * b)
    truth = np.abs(1 + b * np.exp(-2j * np.pi * f)) ** 2 / (1 + b * b)
    assert np.all(np.abs(innovation_background(x)(f) - truth) < 0.25 * truth + 0.05)
    # a narrow line is not noise: the running median steps over it
    line = x + 0.15 * np.sin(2 * np.pi * 0.2 * np.arange(x.size))
    plain = innovation_background(x)(0.2)
    # the line is 5-6x the noise in its own bins; it lifts the median by an order statistic or two at most
    assert innovation_background(line)(0.2) < 1.5 * plain


def _fit(spec, data, x0):
    lik = compile_model(spec).bind(data)
    r = optimize.minimize(lambda z: -lik(np.exp(z)), np.log(x0), method="Nelder-Mead",
                          options={"maxfev": 4000, "xatol": 1e-6, "fatol": 1e-6})
    return dict(zip(spec.free_parameters, np.exp(r.x)))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_coloured_measurement_noise_does_not_pass_for_a_forcing(seed):
    """A correct oscillator model whose sensor noise was low-pass filtered (as a data pipeline does): the
    likelihood takes the noise as white, so a sine at a frequency where the noise is stronger than it
    assumes looks supported. Adjusted to the innovations' spectrum, it is not; unadjusted, it is
    (the test can fail both ways)."""
    rng = np.random.default_rng(seed)
    t = np.arange(6000) * 0.02
    spec = builtin("linear_oscillator").model_copy(update={"constants": {"gamma": 2e-3}}).revalidate()
    data = simulate_model(spec, {"k": 16.0, "c": 0.3, "sigma": 0.5}, t, seed, x0=[0.5, 0.0])
    # the sensor's noise (white, sd 0.01) through a zero-phase low-pass: far above the declared 2e-3 below 5 Hz
    noise = signal.sosfiltfilt(signal.butter(4, 5.0, fs=50.0, output="sos"), 0.02 * rng.standard_normal(t.size))
    data = type(data)(data.t, {"y": data.columns["y"] + noise}, data.meta)
    phi = _fit(spec, data, [16.0, 0.3, 0.5])
    y = data.columns["y"]
    # a forcing at the strongest innovation-spectrum bin between the resonance and the filter's cut-off
    e = compile_model(spec).filter(phi, data).standardized[:, 0]
    f, P = signal.periodogram(np.nan_to_num(e), fs=50.0)
    band = (f > 1.5) & (f < 4.5)
    f0 = float(f[band][np.argmax(P[band])])
    eff = Effect(f"forcing(f={f0:.4g})", "forcing", ("forcing0_sin", "forcing0_cos"), frequency=f0, code="fo0")
    scales = {"y": float(np.std(y)), "v": float(np.std(np.diff(y)) / 0.02)}
    plain = screen_effects(ScreenInput(spec, phi, data, robust=False), [eff], ["v"], ["y"])
    adjusted = screen_effects(ScreenInput(spec, phi, data), [eff] + candidate_effects(spec, scales=scales),
                              ["v"], ["y"])
    lbf = {(c.effect.name, c.target): c.log_bayes_factor for c in adjusted}
    assert plain[0].log_bayes_factor > 3, plain[0].log_bayes_factor  # the white-noise likelihood is fooled
    # below the loop's min_score (3 nats: not sent to the ARD re-selection), and far below the unadjusted value
    assert lbf[(eff.name, "v")] < min(3.0, plain[0].log_bayes_factor - 2), (lbf[(eff.name, "v")], plain[0])
    # nothing in the dynamics either (the noise level may be flagged: it *is* larger than declared)
    dyn = {k: v for k, v in lbf.items() if not k[0].startswith("measurement_noise")}
    assert max(dyn.values()) < 3, sorted(dyn.items(), key=lambda kv: -kv[1])[:3]


def _forced(seed, truth=None, params=None, columns=None):
    """Forced oscillator data, the base model and its fit (see tests/forced_oscillator.py)."""
    data = forced_data(seed, truth, params, columns)
    base = base_spec()
    return base, data, _fit(base, data, [16.0, 0.4, 8.0, 0.3])


def _forcing_candidate(f):
    return Effect(f"forcing(f={f})", "forcing", ("forcing0_sin", "forcing0_cos"), frequency=f, code="fo0",
                  shape=("f", 0.97 * f, 1.03 * f))


def test_a_forcing_is_coherent_and_a_noise_driven_mode_is_not():
    """A sinusoid of fixed amplitude and phase keeps its coefficients over the record; a lightly damped mode
    driven by noise (a narrow-band random process, narrower than the spectrum's bins) does not, and is not
    taken for a forcing however large its spectral peak."""
    from ardflow.ardcore.effects.base import augment

    forcing = Effect("forcing(f=1.37)", "forcing", ("forcing0_sin", "forcing0_cos"), frequency=1.37, code="fo0")

    truth, _ = augment(base_spec(), forcing, "v")
    spec, data, phi = _forced(1, truth, {"k_fo00_v": 0.5, "k_fo01_v": 0.5}, forcing.columns_for)
    got = screen_effects(ScreenInput(spec, phi, data), [_forcing_candidate(1.37)], ["v"], ["y"])[0]
    assert got.log_bayes_factor > 30 and got.coherence_p > 0.01, (got.log_bayes_factor, got.coherence_p)

    w, zeta = 2 * np.pi * 1.7, 0.02

    base = base_spec()
    mode = base.model_copy(update={
        "name": "mode", "states": ["y", "v", "z", "zd"],
        "drift": {**base.drift, "z": "zd", "zd": f"-{w * w:.6g}*z - {2 * zeta * w:.6g}*zd"},
        "diffusion": {**base.diffusion, "zd": "3.0"},
        "observations": [{"column": "y", "expr": "y + z", "noise_std": "gamma"}],
        "initial_std": {"y": 0.1, "v": 10.0, "z": 0.0, "zd": 0.0}}).revalidate()
    for seed in (1, 2):
        spec, data, phi = _forced(seed, mode)
        plain = screen_effects(ScreenInput(spec, phi, data, robust=False), [_forcing_candidate(1.7)], ["v"], ["y"])[0]
        got = screen_effects(ScreenInput(spec, phi, data), [_forcing_candidate(1.7)], ["v"], ["y"])[0]
        assert plain.log_bayes_factor > 30  # the white-noise likelihood takes the mode's peak for a forcing
        assert got.coherence_p < 1e-3 and got.log_bayes_factor <= 0, (got.coherence_p, got.log_bayes_factor)


def test_forward_selection_scores_jointly_and_finds_what_the_first_leaves():
    """distinct_candidates: the joint score from the screen's stored sensitivities reproduces each marginal
    ln BF exactly (no conditioning), a candidate conditioned on itself is worth nothing, and with a cubic and
    an even (y^2) stiffness planted together both are picked, the second by its conditional evidence."""
    from ardflow.ardcore.effects.base import augment
    from ardflow.ardcore.screening.screen import conditional_log_bayes_factor, distinct_candidates

    lib = {e.name: e for e in candidate_effects(base_spec())}
    truth, _ = augment(base_spec(), lib["cubic_stiffness(y)"], "v")
    truth, _ = augment(truth, lib["quadratic_stiffness(y)"], "v")
    spec, data, phi = _forced(3, truth, {"k_s3y_v": -40.0, "k_s2y_v": 12.0})
    scales = {"y": float(np.std(data.columns["y"])), "v": float(np.std(np.diff(data.columns["y"])) / 0.02)}
    effects = [e for e in candidate_effects(spec, scales=scales) if not e.shape]
    got = screen_effects(ScreenInput(spec, phi, data), effects, ["v"], ["y"])
    for c in got[:8]:
        assert conditional_log_bayes_factor(c, []) == pytest.approx(c.log_bayes_factor, rel=1e-9, abs=1e-9)
        assert conditional_log_bayes_factor(c, [c]) < 1.0
    picked = distinct_candidates(ScreenInput(spec, phi, data), got, 3, 3.0)
    names = [p.effect.name for p in picked]
    assert names[0] == got[0].effect.name
    assert {"cubic_stiffness(y)", "quadratic_stiffness(y)"} <= set(names), [(c.effect.name, c.log_bayes_factor,
                                                                            c.conditional_log_bayes_factor)
                                                                           for c in got[:8]]
    second = next(p for p in picked[1:] if p.effect.name in ("cubic_stiffness(y)", "quadratic_stiffness(y)"))
    assert second.conditional_log_bayes_factor > 3.0


def test_what_a_refused_pick_explained_is_proposed_next():
    """The loop's next proposals (:func:`~ardflow.ardcore.loop.confirm.hidden`): with a cubic stiffness
    planted, the forward selection picks it and sets aside the stiffnesses it explains. Once the picks are out
    (refused), those set aside are what the evidence proposes next: a second forward selection among them picks
    the best of them by its own evidence, none marked as explained by the refused picks."""
    from types import SimpleNamespace

    from ardflow.ardcore.effects.base import augment
    from ardflow.ardcore.loop.confirm import Screening, hidden
    from ardflow.ardcore.screening.screen import distinct_candidates

    lib = {e.name: e for e in candidate_effects(base_spec())}
    truth, _ = augment(base_spec(), lib["cubic_stiffness(y)"], "v")
    spec, data, phi = _forced(3, truth, {"k_s3y_v": -40.0})
    scales = {"y": float(np.std(data.columns["y"])), "v": float(np.std(np.diff(data.columns["y"])) / 0.02)}
    effects = [e for e in candidate_effects(spec, scales=scales) if not e.shape]
    inp = ScreenInput(spec, phi, data)
    got = screen_effects(inp, effects, ["v"], ["y"])
    picked = distinct_candidates(inp, got, 3, 3.0)
    assert picked[0].effect.name == "cubic_stiffness(y)"
    rest = hidden(Screening(inp, got), [SimpleNamespace(screened=p) for p in picked])
    assert rest and not set(map(id, rest)) & set(map(id, picked))
    assert all("cubic_stiffness(y)" in c.conditional_on for c in rest)
    assert max(c.log_bayes_factor for c in rest) > 3.0  # explained by the cubic, supported on its own
    again = distinct_candidates(inp, rest, 3, 3.0)
    assert again and again[0] is max(rest, key=lambda c: c.log_bayes_factor)
    assert all(getattr(c, "conditional_on", None) is None or "cubic_stiffness(y)" not in c.conditional_on
               for c in rest)


def test_a_model_that_has_the_input_rate_screens_it_again_without_error():
    """A later round screens the library on a model that holds an input's rate already: its column is one of
    the model's inputs (it used to be appended a second time, and building the term's function failed)."""
    from ardflow.ardcore.effects.base import augment, with_columns

    rate = next(e for e in candidate_effects(base_spec()) if e.name == "input_rate(u)")
    truth, names = augment(base_spec(), rate, "v")
    data = with_columns(forced_data(3, truth, {names[0]: 0.05}, rate.columns_for), rate)
    phi = {**_fit(base_spec(), data, [16.0, 0.4, 8.0, 0.3]), names[0]: 0.05}
    got = screen_effects(ScreenInput(truth, phi, data), [rate], ["v"], ["y"])
    assert len(got) == 1 and np.isfinite(got[0].log_bayes_factor)
    # the rate is in the model at its true value: another one is worth nothing
    assert got[0].log_bayes_factor < 3
