"""The free run (simulation) of a fitted model against a held-out record, with a posterior prediction band."""

from __future__ import annotations

import math
import warnings

from dataclasses import dataclass, field
from typing import Callable, NamedTuple

import numpy as np
import sympy as sp

from ..data import Dataset
from ..effects.base import user_inputs
from ..jsonio import is_pruned
from ..likelihood.ekf import compile_model
from ..selection.initial import recentred
from ..model.declaration import ModelSpec
from ..sampling.chains import serial_map
from ..selection.fit import ModelFit
from ..selection.spec import CandidateSpec
from .band import MAX_DIVERGED, band_of, diverged, expected_coverage, inside, typical_level
from .residuals import dominant_frequency, harmonics


def fitted_spec(cand: CandidateSpec, row: ModelFit) -> ModelSpec:
    """The candidate's model with the terms its optimal psi pruned fixed at 0."""
    spec = cand.model_spec()
    pruned = {k: 0.0 for k, v in row.psi_opt.items() if is_pruned(v)}
    return spec.with_fixed(**pruned) if pruned else spec


def fitted(cand: CandidateSpec, row: ModelFit) -> tuple[ModelSpec, dict]:
    """The candidate's model with pruned terms fixed at 0, and its posterior mean."""
    spec = fitted_spec(cand, row)
    return spec, row.point(spec.free_parameters)


BAND_FACTORS = (8.0, 5.66, 4.0, 2.83, 2.0, 1.41, 1.0, 0.71, 0.5, 0.35, 0.25, 0.1, 0.03, 0.0)
"""Scales of the process noise a band may be calibrated at (:func:`calibrated_out_of_sample`), largest first: above 1
for a model that still lacks something its posterior's noise does not cover."""


@dataclass(frozen=True)
class Band:
    """How a free run's 90 % posterior predictive band is made: the posterior ``draws`` (dicts over the free
    parameters), the ``seed`` of its random numbers and, to calibrate the process noise it simulates
    (:func:`calibrated_out_of_sample`), the estimation record (``calibration``) with blocks of it each left out
    of a refit of the structure (``refits``: ``(first, stop, the parameters fitted without it)``,
    :meth:`~.simulation_fit.HeldOut.refits`). Without them the band simulates the posterior's own noise."""

    draws: list
    calibration: Dataset | None = None
    seed: int = 0
    refits: tuple = ()
    mapper: Callable = field(default=serial_map, compare=False)
    """``mapper(fn, tasks)``: where the calibration's blocks are simulated (the loop's pool; default
    :func:`~ardcore.sampling.chains.serial_map`, here)."""


def free_run(spec: ModelSpec, phi: dict, data: Dataset, *, init_samples: int = 50,
             substeps: int | None = None, band: Band | None = None) -> dict:
    """Deterministic simulation of the fitted model against ``data``.

    The initial state is the filtered state after the first ``init_samples`` samples. For
    self-excited or free oscillations (no inputs) amplitude, frequency and spectrum are
    compared as well as the pointwise error, which a small frequency error dominates.
    With a ``band`` (:class:`Band`) the 90 % **posterior predictive** band: for each posterior draw
    the initial state is drawn from its filter's distribution after the first ``init_samples``
    samples, the model is simulated with its process noise and the measurement noise is added, so
    the band carries parameter, initial-state, process and measurement uncertainty together. The
    process noise the filter fitted also stands in for what the model lacks, which makes a band over
    a long horizon too wide or, where the record holds larger motions than those fitted, too narrow; with
    ``band.calibration`` and ``band.refits`` its scale is calibrated out of sample on blocks of the
    estimation record (:func:`calibrated_out_of_sample`, ``band_factor``), never on ``data``.
    ``band`` holds the pointwise bounds (:func:`band_of`), ``band_coverage`` the share of data inside
    it, ``draws_rms_error`` the median RMS error of the draws' deterministic free runs.
    """
    if data.n_records > 1:
        return _joined([free_run(spec, phi, data.slice(sl.start, sl.stop), init_samples=init_samples,
                                 substeps=substeps, band=band) for sl in data.record_slices()], data)
    # the initial filter starts from a prior that agrees with this record's start (a test record in mid motion)
    spec, _ = recentred(spec, data)
    out = _free_run_one(spec, phi, data, init_samples=init_samples, substeps=substeps)
    if band is None or not band.draws:
        return out
    sims = [_free_run_one(spec, d, data, init_samples=init_samples, substeps=substeps, full=False)
            for d in band.draws]
    factor, calibration = 1.0, None
    if band.calibration is not None and band.refits:
        factor, calibration = calibrated_out_of_sample(spec, phi, band, init_samples, substeps)
    noise = noise_parameters(spec)
    ys = _predictive(spec, _scaled(band.draws, noise, factor), data, out["start"], substeps, band.seed)
    # the calibration's blocks are shorter than a test record can be: where more than 5 % of the draws diverge
    # over its length the scale steps down (a band that holds the data by being infinite is no band). This reads
    # the record's inputs and start, as every free run does, never the outputs the band is judged on
    for f in sorted((x for x in BAND_FACTORS if x < factor), reverse=True):
        if diverged(ys) <= MAX_DIVERGED:
            break
        factor = f
        ys = _predictive(spec, _scaled(band.draws, noise, factor), data, out["start"], substeps, band.seed)
    if len(ys) >= 5:
        level = typical_level(ys)  # one sort of the draws for the band and the coverage its model expects
        lo, hi = band_of(ys, level)
        y = out["y"]
        ok = np.isfinite(y)
        wide = np.isfinite(hi - lo)
        out["band"] = (lo, hi)
        out["band_coverage"] = float(np.mean(inside(y[ok], lo[ok], hi[ok])))
        out["band_expected"] = expected_coverage(ys, level)
        out["band_diverged"] = diverged(ys)
        out["band_halfwidth_rms"] = float(np.sqrt(np.mean(((hi[wide] - lo[wide]) / 2) ** 2))) if wide.any() else math.inf
        out["draws_rms_error"] = float(np.median([r["rms_error"] for r in sims]))
        out["n_draws"] = int(len(ys))
        out["band_factor"] = factor
        if calibration is not None:
            out["band_calibration"] = calibration
    return out


def _joined(parts: list[dict], data: Dataset) -> dict:
    """The free runs of several records (each from its own start) as one: the series end to end, the errors
    and the band's coverage over every record's points, and each record's own under ``records``."""
    names = data.record_names()
    n = np.array([p["n"] for p in parts], dtype=float)
    w = n / n.sum()
    out = {"n": int(n.sum()), "start": parts[0]["start"],
           "starts": [int(sl.start + p["start"]) for sl, p in zip(data.record_slices(), parts)]}
    for k in ("t", "y", "y_free"):
        out[k] = np.concatenate([p[k] for p in parts])
    out["rms_error"] = float(np.sqrt(np.sum(w * np.array([p["rms_error"] for p in parts]) ** 2)))
    y = out["y"]
    out["rms_data"] = float(np.sqrt(np.nanmean((y - np.nanmean(y)) ** 2)))
    out["relative_rms_error"] = out["rms_error"] / out["rms_data"] if out["rms_data"] > 0 else float("nan")
    if all("band" in p for p in parts):
        out["band"] = tuple(np.concatenate([p["band"][i] for p in parts]) for i in (0, 1))
        out["band_coverage"] = float(np.sum(w * np.array([p["band_coverage"] for p in parts])))
        # each record's expected range, weighted like its coverage (an approximation of the joined range)
        out["band_expected"] = [float(x) for x in np.sum(w[:, None] * np.array([p["band_expected"] for p in parts]), 0)]
        out["band_diverged"] = max(p["band_diverged"] for p in parts)
        out["band_halfwidth_rms"] = float(np.sqrt(np.sum(w * np.array([p["band_halfwidth_rms"] for p in parts]) ** 2)))
        out["draws_rms_error"] = float(np.sum(w * np.array([p["draws_rms_error"] for p in parts])))
        out["n_draws"] = min(p["n_draws"] for p in parts)
        out["band_factor"] = parts[0]["band_factor"]
    out["records"] = [{"name": nm, **{k: v for k, v in p.items() if isinstance(v, (int, float, str))}}
                      for nm, p in zip(names, parts)]
    return out


def calibrated_out_of_sample(spec: ModelSpec, phi: dict, band: Band, init_samples: int,
                             substeps: int | None) -> tuple[float, dict | None]:
    """The process-noise scale of the band, calibrated on blocks the parameters did not see (``band.refits``):
    on each block the posterior draws, moved from the posterior mean ``phi`` to the fit without that block
    (:func:`moved_draws`, their spread widened as the refit saw less of the record), make the band from the
    block's start on.

    The posterior's own noise (scale 1) stands unless the blocks show it is wrong: their coverage at scale 1
    differs from 90 % by more than twice its standard error, counted over the blocks' independent stretches
    (:func:`independent_samples`: a slow error holds few). A correct model's blocks cover 90 % only on
    average, so a scale fitted to a few short blocks would move its band by their noise. Otherwise the
    coverage of the blocks together rises with the scale; the scale is where it reaches 90 %, interpolated
    between the two neighbouring :data:`BAND_FACTORS` (the largest when none reaches it: an honest band errs
    wide), and never one at which more than 5 % of a block's draws diverge (``diverges_at``: the largest below it
    stands). Returns it and the coverage at the factors tried."""
    noise = noise_parameters(spec)
    if not noise:
        return 1.0, None
    n = len(band.calibration)
    blocks, held = [], []
    for a, b, q in band.refits:
        part = band.calibration.slice(a, b)
        pspec, _ = recentred(spec, part)
        k0 = _start(pspec, part, init_samples)
        y = part.columns[spec.observed_columns[0]][k0:]
        spread = math.sqrt(n / max(n - (b - a), 1))  # the refit saw the rest of the record only
        blocks.append((pspec, part, k0, y, moved_draws(band.draws, phi, q, noise, spread)))
        held.append(a + k0 + np.flatnonzero(np.isfinite(y)))  # the record's samples the block is judged on
    # blocks may overlap (the loudest stretch runs into the record's end): a sample two blocks hold counts half in
    # each, so that no stretch of the record weighs double in the coverage or counts twice as independent
    times = np.bincount(np.concatenate(held), minlength=n) if held else np.zeros(n)
    parts = [_Block(*blk, 1.0 / times[i]) for blk, i in zip(blocks, held)]
    out = {"held_out_blocks": [[int(a), int(b)] for a, b, _ in band.refits], "out_of_sample": True}
    at_one = _blocks_inside(parts, noise, 1.0, substeps, band.seed + 1, band.mapper)
    if at_one is not None:
        c = _share_inside(at_one)
        se = math.sqrt(0.9 * 0.1 / max(sum(independent_samples(a) * float(np.mean(w)) for _, a, w in at_one if w.size),
                                       1.0))
        out.update({"coverage": {"1": c}, "coverage_se": se})
        if abs(c - 0.9) <= 2.0 * se:  # no evidence against the posterior's noise
            return 1.0, out
    cover: dict = {}
    chosen, below, ceiling = max(BAND_FACTORS), None, None
    for f in sorted(BAND_FACTORS):  # from the narrowest, until the band holds 90 %
        # scale 1 was run above, with the same draws and seed
        inside_f = at_one if f == 1.0 else _blocks_inside(parts, noise, f, substeps, band.seed + 1, band.mapper)
        if inside_f is None:
            # more than 5 % of a block's draws diverge at this scale: a band that holds the data by being
            # infinite is no band, so the largest scale below it stands
            ceiling = f
            chosen = below[0] if below is not None else min(BAND_FACTORS)
            break
        c = cover[f] = _share_inside(inside_f)
        if c >= 0.9:
            chosen = f if below is None else below[0] + (0.9 - below[1]) / (c - below[1]) * (f - below[0])
            break
        below = (f, c)
    if not cover:
        return 1.0, None
    out["coverage"] = {**{f"{f:g}": c for f, c in cover.items()}, **out.get("coverage", {})}
    if ceiling is not None:
        out["diverges_at"] = ceiling
    return float(chosen), out


def _predictive_task(args) -> np.ndarray:
    """:func:`_predictive` of ``(spec, draws, data, k0, substeps, seed)``: a picklable unit of work for a pool."""
    return _predictive(*args)


class _Block(NamedTuple):
    """A calibration block (:func:`calibrated_out_of_sample`): its model recentred on it, its data, the sample its
    band starts at, the outputs from there, the posterior draws moved to its refit, and the weight of each finite
    output (one over the blocks that hold it)."""

    spec: ModelSpec
    data: Dataset
    k0: int
    y: np.ndarray
    draws: list
    weight: np.ndarray


def _blocks_inside(parts: list, noise: list, factor: float, substeps, seed: int,
                   mapper: Callable = serial_map) -> list | None:
    """Per calibration block (:func:`calibrated_out_of_sample`'s ``parts``), where its data lie inside the band
    at process-noise ``factor`` (boolean series, its finite points), how far across it (the squared distance
    from its centre in half-widths) and each point's weight (one over the blocks that hold it); None when more
    than 5 % of a block's draws diverge. The blocks' draws are
    simulated by ``mapper`` (each block from its own seeded random numbers, so anywhere alike)."""
    tasks = [(p.spec, _scaled(p.draws, noise, factor), p.data, p.k0, substeps, seed) for p in parts]
    sims = mapper(_predictive_task, tasks)
    got = []
    for p, ys in zip(parts, sims):
        if len(ys) < 5 or diverged(ys) > MAX_DIVERGED:
            return None
        lo, hi = band_of(ys)
        y, ok = p.y, np.isfinite(p.y)
        # where the data lie across the band (inside within +-1): slower than its inside-outside series, as slow
        # as the error's envelope, so its independent stretches are the block's
        with np.errstate(invalid="ignore", divide="ignore"):
            across = (y[ok] - (lo[ok] + hi[ok]) / 2) / ((hi[ok] - lo[ok]) / 2)
        got.append((inside(y[ok], lo[ok], hi[ok]), np.nan_to_num(across ** 2, nan=0.0, posinf=1e6), p.weight))
    return got


def _share_inside(blocks: list) -> float:
    """The share of the calibration blocks' data inside their bands (:func:`_blocks_inside`), each point by its
    weight; 0 without any."""
    w = np.concatenate([w for *_, w in blocks]) if blocks else np.zeros(0)
    return float(np.sum(np.concatenate([x for x, _, _ in blocks]) * w) / np.sum(w)) if w.sum() > 0 else 0.0


def independent_samples(x: np.ndarray) -> float:
    """How many independent values a series ``x`` holds: its length over its integrated autocorrelation time
    (1 + 2 x the sum of its autocorrelations up to the first that is not positive)."""
    x = np.asarray(x, float)
    n = x.size
    if n < 3 or np.var(x) == 0:
        return float(n)
    d = x - x.mean()
    f = np.fft.rfft(d, 2 * n)
    acf = np.fft.irfft(f * np.conj(f))[:n] / (np.arange(n, 0, -1) * np.var(x))
    tau = 1.0
    for r in acf[1:n // 2]:
        if r <= 0:
            break
        tau += 2.0 * r
    return n / tau


def moved_draws(draws: list, mean: dict, point: dict, noise: list, spread: float = 1.0) -> list:
    """Posterior ``draws`` moved from their ``mean`` to another ``point`` (a fit without part of the record, a
    fit at another noise level): each keeps its offset from the mean, times ``spread`` (a fit to a share s of
    the record is 1/sqrt(s) times as uncertain), and its own ``noise`` parameters."""
    moved = [p for p in point if p not in noise and p in mean]
    return [{**d, **{p: point[p] + spread * (d[p] - mean[p]) for p in moved if p in d}} for d in draws]


def _scaled(draws: list, noise: list, factor: float) -> list:
    """The posterior draws with their process-noise parameters ``noise`` (:func:`noise_parameters`) scaled by
    ``factor``."""
    if factor == 1.0:
        return draws
    return [{k: (v * factor if k in noise else v) for k, v in d.items()} for d in draws]


def _predictive(spec: ModelSpec, draws: list, data: Dataset, k0: int, substeps: int | None,
                seed: int) -> np.ndarray:
    """Posterior predictive draws from sample ``k0`` on (:func:`_predictive_one`), stacked (draws x samples); a
    draw that diverged holds non-finite values from where it did (:func:`band_of` counts it)."""
    rng = np.random.default_rng(seed)
    return np.array([_predictive_one(spec, d, data, k0, substeps, rng) for d in draws])


def noise_parameters(spec: ModelSpec) -> list[str]:
    """Free parameters that scale the process noise: each diffusion expression is proportional to them
    (sigma, 2*sigma: scaling the parameter scales the noise). Empty when a diffusion term depends on a
    free parameter in another way (exp(s), s + 1), where scaling it would not scale the noise."""
    sm = spec.sym  # parsed, with constants, fixed values and derived quantities substituted
    out: list[str] = []
    for e in sm.diffusion:
        ps = [p for p in sm.params if p in e.free_symbols]
        if not ps:
            continue
        if len(ps) != 1 or sp.simplify(e - ps[0] * sp.diff(e, ps[0])) != 0:
            return []
        out += [str(p) for p in ps if str(p) not in out]
    return out


def _predictive_one(spec: ModelSpec, phi: dict, data: Dataset, k0: int, substeps: int | None,
                    rng: np.random.Generator) -> np.ndarray:
    """One draw of the posterior predictive from sample ``k0`` on: the initial state from the filter's
    N(mean, covariance) there, the model simulated with its process noise, the measurement noise added."""
    cm = compile_model(spec)
    fr = cm.filter(phi, data.slice(0, k0 + 1), substeps)
    m, P = fr.filtered[-1], fr.filtered_cov[-1]
    try:
        x0 = m + np.linalg.cholesky(0.5 * (P + P.T) + 1e-12 * np.eye(P.shape[0])) @ rng.standard_normal(m.size)
    except np.linalg.LinAlgError:
        x0 = m
    rest = data.slice(k0, None)
    U = np.column_stack([rest.columns[u] for u in spec.inputs]) if spec.inputs else None
    _, H = cm.simulate(phi, rest.t, x0=x0, inputs=U, nsub=substeps or spec.substeps, noise=True, rng=rng)
    std = np.asarray(cm.obs_std(phi), dtype=float).reshape(-1)
    return H[:, 0] + (std[0] if std.size else 0.0) * rng.standard_normal(H.shape[0])


def _start(spec: ModelSpec, data: Dataset, init_samples: int) -> int:
    """The sample a free run starts from: after ``init_samples`` samples of filtering, and for a model without
    inputs not before the record reaches half its largest amplitude."""
    k0 = min(max(1, init_samples), len(data) - 2)
    if not user_inputs(spec):
        # a self-excited oscillation may start at rest (friction-locked until noise breaks it): the free
        # run then starts at the first sample where the record reaches half its largest amplitude
        y = data.columns[spec.observed_columns[0]]
        a = np.abs(y - np.nanmedian(y))
        k0 = max(k0, int(np.argmax(a > 0.5 * np.nanmax(a))))
        k0 = min(k0, len(data) - 2)
    return k0


def _free_run_one(spec: ModelSpec, phi: dict, data: Dataset, *, init_samples: int = 50,
                  substeps: int | None = None, full: bool = True) -> dict:
    cm = compile_model(spec)
    col = spec.observed_columns[0]
    k0 = _start(spec, data, init_samples)
    fr = cm.filter(phi, data.slice(0, k0 + 1), substeps)
    x0 = fr.filtered[-1]
    rest = data.slice(k0, None)
    U = np.column_stack([rest.columns[u] for u in spec.inputs]) if spec.inputs else None
    # the same Euler sub-steps as the filter that fitted phi: the discretisation is part of the fitted model
    X, H = cm.simulate(phi, rest.t, x0=x0, inputs=U, nsub=substeps or spec.substeps, noise=False)
    y, yh = rest.columns[col], H[:, 0]
    err = yh - y
    fs = 1.0 / float(np.median(np.diff(rest.t)))
    with np.errstate(over="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a run that diverged everywhere: its error is NaN, said so
        rms = float(np.sqrt(np.nanmean(err ** 2)))
    out = {"n": int(y.size), "start": int(k0), "rms_error": rms,
           "rms_data": float(np.sqrt(np.nanmean((y - np.nanmean(y)) ** 2))),
           "t": rest.t, "y": y, "y_free": yh}
    out["relative_rms_error"] = out["rms_error"] / out["rms_data"] if out["rms_data"] > 0 else float("nan")
    # a self-excited or free oscillation (a forcing the loop found does not make it an input-driven system)
    if full and not user_inputs(spec) and np.all(np.isfinite(yh)):
        fd, fm = dominant_frequency(y, fs), dominant_frequency(yh, fs)
        hd, floor = harmonics(y, fs, fd)
        hm, _ = harmonics(yh, fs, fm, floor=floor)
        seen = (hd > floor) | (hm > floor)
        amp_d = float(np.sqrt(2) * np.std(y))
        amp_m = float(np.sqrt(2) * np.std(yh))
        out.update({"frequency_data": fd, "frequency_model": fm, "frequency_error": (fm - fd) / fd,
                    "amplitude_data": amp_d, "amplitude_model": amp_m, "amplitude_error": (amp_m - amp_d) / amp_d,
                    "harmonics_data": hd.tolist(), "harmonics_model": hm.tolist(),
                    "harmonic_error": float(np.sqrt(np.mean(np.log10(np.maximum(hm[seen], 1e-300) / hd[seen]) ** 2)))
                    if seen.any() else float("nan")})
    return out



def posterior_draws(mr, spec: ModelSpec, n: int, seed: int = 0) -> list[dict]:
    """Up to ``n`` posterior draws (dicts over the free parameters of ``spec``) from a fit's samples."""
    res = getattr(mr, "sampler", None)
    if not n or res is None or res.samples.size == 0:
        return []
    flat = res.samples.reshape(-1, res.samples.shape[-1])
    names = list(res.names)
    if any(p not in names for p in spec.free_parameters):
        return []
    idx = np.random.default_rng(seed).choice(flat.shape[0], size=min(n, flat.shape[0]), replace=False)
    return [{p: float(flat[i, names.index(p)]) for p in spec.free_parameters} for i in idx]
