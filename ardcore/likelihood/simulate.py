"""Synthetic data: the reference measurement pipeline and generic simulation.

The reference pipeline is fixed by ``docs/worked-example.md``
(Section 3.2 and its Decisions): Euler-Maruyama with dtau = 1e-3 from rest,
theta sampled every 0.1, N(0, gamma^2) measurement noise, a 4th-order
zero-phase Butterworth low-pass at 0.2295 cycles per tau, and n_d = 5000
points starting just before the LCO onset.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
from scipy.signal import butter, find_peaks, sosfiltfilt

from ..data import Dataset
from .ekf import compile_model
from ..errors import SpecError
from ..model.library import AERO_TRUE, aero_true, builtin
from ..model.declaration import ModelSpec


@dataclass(frozen=True)
class ReferencePipeline:
    """Settings of the synthetic measurement pipeline (all documented defaults)."""

    dtau: float = 1e-3
    """Euler-Maruyama step."""
    dtau_obs: float = 0.1
    """Sampling interval of theta."""
    gamma: float = 2e-3
    """Measurement-noise std added before filtering."""
    cutoff: float = 0.2295
    """Butterworth cut-off, cycles per tau (25 Hz at U = 8.5 m/s)."""
    order: int = 4
    """Butterworth order (applied forward and backward: zero phase)."""
    n_d: int = 5000
    """Points kept."""
    tau_max: float = 1200.0
    """Simulated duration (extended automatically when the onset is late)."""
    onset_fraction: float = 0.1
    """The onset is the first sample whose envelope exceeds this fraction of the LCO amplitude."""
    lead_periods: float = 2.0
    """The record starts this many LCO periods before the onset."""


def lowpass(y: np.ndarray, fs: float, cutoff: float, order: int = 4) -> np.ndarray:
    """Zero-phase Butterworth low-pass (forward-backward)."""
    sos = butter(order, cutoff, btype="low", fs=fs, output="sos")
    return sosfiltfilt(sos, y)


def lco_stats(t: np.ndarray, y: np.ndarray) -> dict:
    """Amplitude, period and their modulation of a steady oscillation.

    Amplitudes are the positive peaks, periods the spacing of upward zero
    crossings (linearly interpolated). Modulation is the coefficient of
    variation (std / mean) over cycles.

    Returns
    -------
    dict
        ``amplitude``, ``period``, ``amplitude_modulation``, ``period_modulation``,
        ``n_cycles``.
    """
    dtm = float(np.median(np.diff(t)))
    pk, _ = find_peaks(y, distance=max(1, int(10.0 / dtm)))
    amps = y[pk]
    amps = amps[amps > 0.5 * np.max(amps)] if amps.size else amps
    s = np.sign(y)
    idx = np.flatnonzero((s[:-1] < 0) & (s[1:] >= 0))
    tc = t[idx] - y[idx] * (t[idx + 1] - t[idx]) / (y[idx + 1] - y[idx])
    per = np.diff(tc)
    per = per[per > 0.5 * np.median(per)] if per.size else per
    if amps.size < 3 or per.size < 3:
        return {"amplitude": float("nan"), "period": float("nan"), "amplitude_modulation": float("nan"),
                "period_modulation": float("nan"), "n_cycles": int(per.size)}
    return {
        "amplitude": float(np.mean(amps)),
        "period": float(np.mean(per)),
        "amplitude_modulation": float(np.std(amps) / np.mean(amps)),
        "period_modulation": float(np.std(per) / np.mean(per)),
        "n_cycles": int(per.size),
    }


def _onset_index(yf: np.ndarray, period_samples: int, fraction: float) -> tuple[int, float]:
    env = np.abs(yf)
    # LCO amplitude from the last third of the record
    tail = env[2 * env.size // 3:]
    amp = float(np.max(tail)) if tail.size else 0.0
    above = np.flatnonzero(env > fraction * amp)
    if amp <= 0 or above.size == 0:
        return -1, amp
    return int(above[0]), amp


def simulate_reference(seed: int, pipeline: ReferencePipeline | None = None,
                       true_params: dict | None = None, spec: ModelSpec | None = None, inputs=None) -> Dataset:
    """The reference data set of the paper's Section 3.2.

    Parameters
    ----------
    seed : int
        Seeds both the process noise and the measurement noise
        (``numpy.random.default_rng(seed)``). Same seed, same data.
    pipeline : ReferencePipeline, optional
    true_params : dict, optional
        Overrides of :data:`~ardcore.model.library.AERO_TRUE` (and values of any parameter ``spec`` adds).
    spec : ModelSpec, optional
        A variant of the data-generating model (e.g. with an effect the candidates do not
        declare); default :func:`~ardcore.model.library.aero_true`.
    inputs : callable, optional
        ``inputs(t)``: the columns of a variant with inputs (a periodic gust) on the simulation's time grid;
        they drive the truth and are not part of the data set (the models fitted to it do not know them).

    Returns
    -------
    Dataset
        Columns ``y`` (filtered, noisy theta); ``meta`` records the model, the
        true parameters, the seed, the pipeline, the onset and the clean theta.
    """
    pl = pipeline or ReferencePipeline()
    params = dict(AERO_TRUE, **(true_params or {}))
    spec = spec or aero_true()
    cm = compile_model(spec)
    phi = {k: params[k] for k in cm.param_names}
    nsub = int(round(pl.dtau_obs / pl.dtau))
    if abs(nsub * pl.dtau - pl.dtau_obs) > 1e-12:
        raise SpecError("dtau_obs must be a whole multiple of dtau")
    rng = np.random.default_rng(seed)
    tau_max = pl.tau_max
    fs = 1.0 / pl.dtau_obs
    for _attempt in range(6):
        n = int(round(tau_max / pl.dtau_obs)) + 1
        t = np.arange(n) * pl.dtau_obs
        rng = np.random.default_rng(seed)
        U = None
        if spec.inputs:
            cols = inputs(t) if inputs is not None else {}
            missing = [c for c in spec.inputs if c not in cols]
            if missing:
                raise SpecError(f"model {spec.name!r} needs input column {missing[0]!r}: pass inputs=")
            U = np.column_stack([np.asarray(cols[c], dtype=float) for c in spec.inputs])
        X, H = cm.simulate(phi, t, x0=np.zeros(len(spec.states)), inputs=U, nsub=nsub, rng=rng)
        theta = H[:, 0]
        noisy = theta + pl.gamma * rng.standard_normal(n)
        yf = lowpass(noisy, fs, pl.cutoff, pl.order)
        period_samples = int(round(32.4 / pl.dtau_obs))
        onset, amp = _onset_index(yf, period_samples, pl.onset_fraction)
        start = max(0, onset - int(round(pl.lead_periods * period_samples)))
        if onset >= 0 and amp > 10 * pl.gamma and start + pl.n_d <= n and onset < n // 2:
            break
        tau_max *= 2
    else:
        raise SpecError(f"no LCO onset found within tau = {tau_max / 2:g} (seed {seed})")
    sl = slice(start, start + pl.n_d)
    tt = np.round(t[sl] - t[start], 10)
    meta = {
        "source": f"simulate_reference(seed={seed})",
        "model": spec.model_dump(mode="json"),
        "true_params": params,
        "seed": seed,
        "pipeline": asdict(pl),
        "onset_tau": float(t[onset]),
        "start_tau": float(t[start]),
    }
    ds = Dataset(tt, {"y": yf[sl]}, meta)
    ds.meta["theta_clean"] = theta[sl]
    return ds


def simulate_model(name_or_spec, params: dict, t: np.ndarray, seed: int, *, nsub: int = 10,
                   inputs: dict[str, np.ndarray] | None = None, x0=None) -> Dataset:
    """Simulate any model at sample times ``t`` and add its measurement noise.

    Parameters
    ----------
    name_or_spec : str or ModelSpec
    params : dict
        Values of the free parameters.
    t : ndarray
    seed : int
    nsub : int
        Euler-Maruyama steps per sample interval.
    inputs : dict, optional
        Input columns (copied into the data set).
    """
    spec = builtin(name_or_spec) if isinstance(name_or_spec, str) else name_or_spec
    cm = compile_model(spec)
    rng = np.random.default_rng(seed)
    U = None
    if spec.inputs:
        missing = [c for c in spec.inputs if c not in (inputs or {})]
        if missing:
            raise SpecError(f"model {spec.name!r} needs input column {missing[0]!r}")
        U = np.column_stack([np.asarray(inputs[c], dtype=float) for c in spec.inputs])
    X, H = cm.simulate(params, t, x0=x0, inputs=U, nsub=nsub, rng=rng)
    cols = {}
    std = cm.obs_std(params)
    for j, c in enumerate(spec.observed_columns):
        cols[c] = H[:, j] + std[j] * rng.standard_normal(t.size)
    for c in spec.inputs:
        cols[c] = np.asarray(inputs[c], dtype=float)
    meta = {"source": f"simulate({spec.name}, seed={seed})", "model": spec.model_dump(mode="json"),
            "true_params": dict(params), "seed": seed, "pipeline": {"nsub": nsub}}
    return Dataset(np.asarray(t, dtype=float), cols, meta)
