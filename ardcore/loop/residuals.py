"""The residuals of a fitted model (docs/method.md section 8, step 2) and their tests.

The residuals: standardised EKF innovations, and the process noise the filter had to inject per dynamic state,
from an RTS smoother on the model with a small diagnostic noise (its level fitted by maximum likelihood) on
every dynamic state. Their tests: whiteness, normality, spectral peaks, dominant frequency, harmonics
(``config`` arguments need ``max_lag``, ``ljung_box_lags`` and ``peak_p``, a
:class:`~ardcore.loop.config.DiagnoseConfig`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, signal, stats

from ..data import Dataset
from ..effects.base import dynamic_states, short_name
from ..likelihood.ekf import compile_model
from .config import DiagnoseConfig
from ..model.declaration import ModelSpec


def acf(x: np.ndarray, max_lag: int) -> np.ndarray:
    """Sample autocorrelation at lags 0..max_lag (NaN ignored)."""
    x = x[np.isfinite(x)]
    x = x - x.mean()
    d = float(x @ x)
    return np.array([float(x[: x.size - k] @ x[k:]) / d if d > 0 else 0.0 for k in range(max_lag + 1)])


def spectral_peaks(x: np.ndarray, fs: float, p: float, *, nperseg: int | None = None) -> dict:
    """Welch spectrum and the bins significantly above a running-median background."""
    x = x[np.isfinite(x)]
    nperseg = nperseg or int(min(x.size, max(256, 2 ** int(np.log2(max(x.size // 8, 2))))))
    f, P = signal.welch(x, fs=fs, nperseg=nperseg)
    k = max(5, (P.size // 20) | 1)
    bg = np.array([np.median(P[max(0, i - k):i + k + 1]) for i in range(P.size)])
    n_avg = max(1, 2 * x.size // nperseg - 1)
    # a Welch bin ~ background * chi2(2 n_avg) / (2 n_avg); the median of that is ~ (1 - 2/(9*2n))^3
    med = (1 - 2 / (9 * 2 * n_avg)) ** 3
    thr = stats.chi2.ppf(1 - p, 2 * n_avg) / (2 * n_avg) / med
    ratio = P / np.maximum(bg, 1e-300)
    idx = [i for i in range(1, P.size - 1) if ratio[i] > thr and P[i] >= P[i - 1] and P[i] >= P[i + 1]]
    peaks = sorted(({"f": float(f[i]), "power_ratio": float(ratio[i])} for i in idx),
                   key=lambda d: -d["power_ratio"])
    return {"f": f, "psd": P, "background": bg, "threshold": float(thr), "peaks": peaks[:10],
            "resolution": float(fs / nperseg)}


def _label_harmonics(peaks: list[dict], fundamental: float | None) -> None:
    """Mark each peak that is a harmonic of ``fundamental`` with its order (``peak["harmonic"]``)."""
    for pk in peaks:
        if fundamental:
            m = pk["f"] / fundamental
            pk["harmonic"] = int(round(m)) if abs(m - round(m)) < 0.08 and round(m) >= 1 else None


def noise_peaks(rate: np.ndarray, fs: float, p: float, fundamental: float | None) -> dict:
    """Spectral peaks of the process noise the filter injected into one state (``rate``, its drift per unit
    time), over two Welch segments. A missing forcing shows there whole: the innovations are what the filter
    could not follow, and it follows a slow forcing by that noise, so a line far below the record's own
    oscillation is faint in them; and a segment as long as half the record resolves a line a few cycles long."""
    x = rate[np.isfinite(rate)]
    sp_ = spectral_peaks(x, fs, p, nperseg=max(min(256, x.size), x.size // 2))
    _label_harmonics(sp_["peaks"], fundamental)
    return sp_


def residual_tests(e: np.ndarray, fs: float, config, *, fundamental: float | None = None) -> dict:
    """Whiteness, normality and spectral peaks of one standardised innovation series."""
    x = e[np.isfinite(e)]
    n = x.size
    r = acf(x, config.max_lag)
    band = 1.96 / math.sqrt(n)
    h = config.ljung_box_lags
    q = float(n * (n + 2) * np.sum(r[1:h + 1] ** 2 / (n - np.arange(1, h + 1))))
    jb = stats.jarque_bera(x)
    sp_ = spectral_peaks(x, fs, config.peak_p)
    _label_harmonics(sp_["peaks"], fundamental)
    return {
        "n": n, "rms": float(np.sqrt(np.mean(x ** 2))), "mean": float(x.mean()),
        "acf": r, "acf_band": band, "acf_outside": float(np.mean(np.abs(r[1:]) > band)),
        "ljung_box": q, "ljung_box_lags": h, "ljung_box_p": float(stats.chi2.sf(q, h)),
        "jarque_bera": float(jb.statistic), "jarque_bera_p": float(jb.pvalue),
        "skew": float(stats.skew(x)), "excess_kurtosis": float(stats.kurtosis(x)),
        "spectrum": sp_,
    }


def dominant_frequency(y: np.ndarray, fs: float) -> float:
    """Frequency of the largest spectral peak (cycles per time unit)."""
    y = y[np.isfinite(y)]
    y = y - y.mean()
    f, P = signal.periodogram(y * np.hanning(y.size), fs=fs)
    i = int(np.argmax(P[1:])) + 1
    if 1 < i < P.size - 1:  # parabolic interpolation on log power
        a, b, c = np.log(P[i - 1:i + 2] + 1e-300)
        i = i + 0.5 * (a - c) / (a - 2 * b + c) if (a - 2 * b + c) != 0 else i
    return float(i * fs / y.size)


def harmonics(y: np.ndarray, fs: float, f0: float, n: int = 7, floor: float | None = None) -> tuple[np.ndarray, float]:
    """Amplitudes of the first ``n`` harmonics of ``f0``, clipped below at ``floor``
    (default: 10 x the median spectral amplitude of ``y``, its noise floor); returns them and the floor."""
    y = y[np.isfinite(y)] - np.nanmean(y)
    w = np.hanning(y.size)
    A = np.abs(np.fft.rfft(y * w)) * 2 / w.sum()
    f = np.fft.rfftfreq(y.size, 1 / fs)
    floor = 10 * float(np.median(A)) if floor is None else floor
    out = np.full(n, floor)
    for k in range(1, n + 1):
        sel = np.abs(f - k * f0) <= max(2 * (f[1] - f[0]), 0.01 * k * f0)
        if sel.any():
            out[k - 1] = max(float(A[sel].max()), floor)
    return out, floor



@dataclass
class Residuals:
    """The residuals of a fitted model on one data set (see module docstring)."""

    innovations: np.ndarray          # standardised, (n, m)
    raw_innovations: np.ndarray      # (n, m)
    smoothed: np.ndarray             # (n, n_x)
    process_noise_rate: dict         # state -> (n-1,) injected drift w_k / dt
    noise_std: dict                  # state -> fitted diagnostic noise std (or the model's own)
    tests: dict                      # per observation channel
    loglik: float
    states: tuple = ()               # names of the smoothed columns
    dt: float = 1.0                  # median sample interval
    records: tuple = ()              # several records: each one's name and its first channel's tests
    noise_spectra: dict = field(default_factory=dict)  # state -> noise_peaks of its injected process noise


def _diagnostic_spec(spec: ModelSpec, states: list[str]) -> tuple[ModelSpec, list[str]]:
    """``spec`` with a noise parameter on every listed state that has none."""
    add = [s for s in states if not spec.diffusion.get(s)]
    names = [short_name(f"q_diag_{s}") for s in add]
    if not add:
        return spec, []
    diff = dict(spec.diffusion)
    diff.update({s: n for s, n in zip(add, names)})
    new = spec.model_copy(update={"name": short_name(f"{spec.name}_diag"), "diffusion": diff,
                                  "parameters": list(spec.parameters) + names})
    return new.revalidate(), names


def residuals(spec: ModelSpec, phi: dict, data: Dataset, config: DiagnoseConfig, *,
              substeps: int | None = None) -> Residuals:
    """Residuals of ``spec`` at parameter values ``phi`` (dict over its free parameters)."""
    cm = compile_model(spec)
    fr = cm.filter(phi, data, substeps)
    fs = 1.0 / float(np.median(np.diff(data.t)))
    e = fr.standardized
    fund = dominant_frequency(data.columns[spec.observed_columns[0]], fs)
    tests = {c: residual_tests(e[:, j], fs, config, fundamental=fund) for j, c in enumerate(spec.observed_columns)}
    records = ()
    if data.n_records > 1:  # each experiment's own whiteness: one record's structure is not averaged away
        records = tuple({"name": name, **{k: v for k, v in residual_tests(e[sl, 0], fs, config).items()
                                          if k in ("n", "rms", "ljung_box", "ljung_box_p")}}
                        for name, sl in zip(data.record_names(), data.record_slices()))
    dyn = dynamic_states(spec)
    dspec, qnames = _diagnostic_spec(spec, dyn)
    dcm = compile_model(dspec)
    scale = np.nanstd(fr.filtered, axis=0)
    q0 = {}
    if qnames:
        lik = dcm.bind(data, substeps)
        idx = [spec.states.index(n[len("q_diag_"):]) for n in qnames]
        # the injected noise is at most of the order of the state's rate of change
        hi = np.log10(np.maximum(scale[idx] * fs, 1e-12))
        lo = hi - 8

        def nll(z):
            z = np.clip(z, lo, hi)
            v = lik({**phi, **{n: 10.0 ** zi for n, zi in zip(qnames, z)}})
            return -v if np.isfinite(v) else 1e300

        best = min((optimize.minimize(nll, np.full(len(qnames), s), method="Nelder-Mead",
                                      options={"xatol": 0.05, "fatol": 0.05, "maxfev": 400})
                    for s in (lo + 2, hi - 3)), key=lambda r: r.fun)
        q0 = {n: float(10.0 ** np.clip(best.x, lo, hi)[i]) for i, n in enumerate(qnames)}
    _, sm = dcm.smooth({**phi, **q0}, data, substeps)
    dt = np.diff(data.t)
    rates = {s: sm.process_noise[1:, spec.states.index(s)] / dt for s in dyn}
    noise_std = {s: q0.get(f"q_diag_{s}") for s in dyn}
    spectra = {s: noise_peaks(r, fs, config.peak_p, fund) for s, r in rates.items() if np.isfinite(r).sum() > 16}
    return Residuals(e, fr.innovations, sm.smoothed, rates, noise_std, tests, fr.loglik, tuple(spec.states),
                     float(np.median(dt)), records, spectra)
