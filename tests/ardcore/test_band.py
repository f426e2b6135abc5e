"""The free run's 90 % posterior predictive band (ardcore.loop.freerun): its bounds, the coverage its own model
expects, and draws that diverge."""

import numpy as np
import pytest

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.likelihood.simulate import simulate_model
from ardflow.ardcore.loop.band import band_level, band_of, diverged, expected_coverage, typical_level
from ardflow.ardcore.loop.freerun import Band, _predictive, _scaled, calibrated_out_of_sample, free_run
from ardflow.ardcore.model.declaration import ModelSpec
from ardflow.ardcore.selection.initial import recentred


def test_the_band_of_many_draws_is_their_5_and_95_percent_quantiles():
    ys = np.random.default_rng(0).standard_normal((4000, 300))
    lo, hi = band_of(ys)
    assert np.mean(lo) == pytest.approx(-1.645, abs=0.02) and np.mean(hi) == pytest.approx(1.645, abs=0.02)
    assert np.allclose(lo, -1.645, atol=0.15) and np.allclose(hi, 1.645, atol=0.15)


def test_a_band_of_few_draws_holds_a_new_draw_90_percent_of_the_time():
    """The loop's bands are made of 40 posterior draws (``band_draws``): their 5 % and 95 % quantiles hold a new
    draw of the same model only 86 % of the time (it falls outside the k-th smallest of n with probability
    k / (n + 1)). At the band's levels (:func:`band_level`) it is 90 %, whatever the number of draws."""
    rng = np.random.default_rng(4)
    for n in (20, 40, 100):
        ys, new = rng.standard_normal((n, 40000)), rng.standard_normal(40000)
        lo, hi = band_of(ys)
        assert np.mean((new >= lo) & (new <= hi)) == pytest.approx(0.9, abs=0.006), n
    plain = np.quantile(ys[:40], [0.05, 0.95], axis=0)
    assert np.mean((new >= plain[0]) & (new <= plain[1])) < 0.87  # what the sample quantiles give


def test_a_diverged_draw_counts_beyond_the_band_not_dropped():
    """Ten of 100 draws diverge half-way: from there more than 5 % are beyond either bound, so both bounds are
    infinite (dropping them would leave a finite band that claims 90 % of a model that diverges); before it the
    band is the finite draws'."""
    ys = np.random.default_rng(1).standard_normal((100, 40))
    ys[:10, 20:] = np.nan
    ys[:10, 30:] = np.inf
    lo, hi = band_of(ys)
    assert np.all(np.isfinite(lo[:20])) and np.all(np.isfinite(hi[:20]))
    assert np.all(lo[20:] == -np.inf) and np.all(hi[20:] == np.inf)
    assert diverged(ys) == pytest.approx(0.1)
    # three of 100: fewer than 5 %, the bounds stay finite
    ys[3:10] = np.random.default_rng(2).standard_normal((7, 40))
    lo, hi = band_of(ys)
    assert np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))


def test_the_expected_coverage_of_independent_draws_is_90_percent():
    """Each draw inside the band of the others: for independent samples (white errors) about 90 % with little
    spread; for slow errors (a random walk: few independent stretches) a range from under half to all of the
    record about a median of 90 % (the band is set for a typical record), which is why one record's coverage can
    sit well outside 80-97 % under a right model."""
    rng = np.random.default_rng(3)
    white = expected_coverage(rng.standard_normal((400, 500)))
    assert white[1] == pytest.approx(0.9, abs=0.01) and white[2] - white[0] < 0.06
    slow = expected_coverage(np.cumsum(rng.standard_normal((400, 500)), axis=1))
    assert slow[0] < 0.6 and slow[2] > 0.97 and slow[1] == pytest.approx(0.9, abs=0.02)


def test_the_typical_level_is_the_pointwise_one_for_independent_draws():
    """Where each sample's error is independent of the next, a draw's share inside the band is its pointwise
    coverage, so the level a typical record needs is :func:`band_level`'s."""
    rng = np.random.default_rng(5)
    for n in (20, 40, 100):
        q = typical_level(rng.standard_normal((n, 20000)))
        assert q == pytest.approx(band_level(n), abs=0.004), n


@pytest.mark.parametrize("kind", ["random_walk", "dephasing"])
def test_a_typical_record_of_slow_errors_has_90_percent_of_its_points_inside(kind):
    """A pointwise band of slow errors (a random walk; an oscillation whose draws drift out of phase by their
    frequencies) holds 90 % of the draws at each time but far more of a typical record's points: a few draws far
    off widen it. At :func:`typical_level` new records of the same model have a median of 90 % of their points
    inside (over 20 sets of 40 draws, as the loop's bands are made)."""
    rng = np.random.default_rng(6)
    t = np.arange(2000) * 0.01

    def draws(n):
        if kind == "random_walk":
            return np.cumsum(rng.standard_normal((n, 500)), axis=1)
        w = 2 * np.pi * np.exp(0.03 * rng.standard_normal((n, 1)))
        return np.sin(w * t) + 0.02 * rng.standard_normal((n, t.size))

    pointwise, typical = [], []
    for _ in range(20):
        ys, new = draws(40), draws(200)
        for level, got in ((band_level(40), pointwise), (typical_level(ys), typical)):
            lo, hi = band_of(ys, level)
            got.append(np.median([np.mean((y >= lo) & (y <= hi)) for y in new]))
    if kind == "random_walk":  # the dephasing draws' shares are less skewed: their pointwise band holds ~92 %
        assert np.mean(pointwise) > 0.94
    assert np.mean(typical) == pytest.approx(0.9, abs=0.02)


def _bistable() -> ModelSpec:
    """x' = -x + a x^3: stable about 0 within |x| < 1/sqrt(a), beyond it the state diverges; a process noise
    sigma kicks it over that edge at a rate that grows steeply with sigma."""
    return ModelSpec(name="bistable_band", states=["x"], inputs=[], drift={"x": "-x + a*x**3"},
                     diffusion={"x": "sigma"}, observations=[{"column": "y", "expr": "x", "noise_std": "0.002"}],
                     parameters=["a", "sigma"], initial_std={"x": 0.1})


def test_the_band_never_takes_a_noise_scale_at_which_its_draws_diverge():
    """The data (a linear Ornstein-Uhlenbeck process, noise 0.35) move more than the model's draws (noise 0.05):
    on short blocks of the estimation record its band needs a process-noise scale of several times to hold
    90 %. Over the test record, 25 times longer, that scale kicks many draws over the model's edge and they
    diverge: the band steps its scale down until at most 5 % do, and stays finite."""
    spec = _bistable()
    truth = spec.model_copy(update={"name": "ou_band", "drift": {"x": "-x"}, "parameters": ["sigma"]}).revalidate()
    dt = 0.02
    est = simulate_model(truth, {"sigma": 0.35}, np.arange(3000) * dt, 4, x0=[0.0])
    test = simulate_model(truth, {"sigma": 0.35}, np.arange(5000) * dt, 5, x0=[0.0])
    est, test = (Dataset(d.t, {"y": d.columns["y"]}, {}) for d in (est, test))
    rng = np.random.default_rng(6)
    draws = [{"a": float(1.0 + 0.02 * rng.standard_normal()), "sigma": 0.05} for _ in range(40)]
    phi = {"a": 1.0, "sigma": 0.05}
    band = Band(draws, calibration=est, seed=7, refits=((0, 200, phi), (1400, 1600, phi), (2800, 3000, phi)))
    calibrated, record = calibrated_out_of_sample(spec, phi, band, 50, None)
    assert calibrated > 2.0, record
    pspec = recentred(spec, test)[0]
    fr = free_run(spec, phi, test, band=band)
    ys = _predictive(pspec, _scaled(draws, ["sigma"], calibrated), test, fr["start"], None, band.seed)
    assert diverged(ys) > 0.05  # at the blocks' scale the long test record's draws diverge
    assert fr["band_factor"] < calibrated and fr["band_diverged"] <= 0.05
    assert np.all(np.isfinite(fr["band"][0])) and np.all(np.isfinite(fr["band"][1]))
    assert 0.0 <= fr["band_expected"][0] <= fr["band_expected"][1] <= fr["band_expected"][2] <= 1.0


def test_the_true_model_s_band_holds_90_percent_of_its_records_on_average():
    """The band simulates what the simulator does: on records of a lightly damped, noise-driven oscillator, the
    band of the true model at its true values holds 90 % of the records' points on average, though one record's
    coverage may sit far from it (a slow error holds few independent stretches: the validation set's
    ``sensor_lag`` test half is held 71 % by its own truth's band)."""
    spec = ModelSpec(name="band_oscillator", states=["y", "v"], inputs=["u"], drift={"y": "v", "v": "-k*y - c*v + b*u"},
                     diffusion={"v": "sigma"}, observations=[{"column": "y", "expr": "y", "noise_std": "0.002"}],
                     parameters=["k", "c", "b", "sigma"], initial_std={"y": 0.1, "v": 0.1}, substeps=10)
    phi = {"k": 16.0, "c": 0.4, "b": 8.0, "sigma": 0.3}
    t = np.arange(1500) * 0.02
    cover = []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        u = np.convolve(rng.standard_normal(t.size + 16), np.ones(8) / np.sqrt(8), mode="same")[8:-8]
        d = simulate_model(spec, phi, t, seed, inputs={"u": u}, x0=[0.0, 0.0])
        data = Dataset(d.t, {"y": d.columns["y"], "u": u}, {})
        cover.append(free_run(spec, phi, data, band=Band(draws=[phi] * 40, seed=seed))["band_coverage"])
    assert np.mean(cover) == pytest.approx(0.9, abs=0.03), cover
    assert max(cover) - min(cover) > 0.05  # one record's coverage is no measure of the band
