"""A model for simulation: the loop's final structure fitted at the process-noise level that free-runs best.

The evidence and the posterior are the EKF's: parameters that predict the next sample given the filtered
state. When the model still lacks something, the fitted process noise stands in for it (the filter corrects
the state at every sample), and the parameters that set the long-horizon behaviour of a lightly damped
system (its damping terms, the height of its resonance) are weakly pinned and pulled by the misfit: on
Silverbox the evidence adds quadratic or cubic damping by thousands of nats, yet the posterior mean then
free-runs worse than without it. At a smaller process noise the filter trusts the model over more samples
and the likelihood weighs multi-step predictions; at zero it becomes the output-error (free-run) fit.

So the model the loop reports is the final structure at the process-noise level that free-runs best: its
noise parameters scaled by a factor chosen on held-out data (fit on the first part of the estimation record
by maximum likelihood at each factor, free run on the rest; factor 1 is the posterior's own noise and wins
unless another is better by ``min_gain``), then refitted on the whole record at that factor, with the
Laplace approximation of its posterior there (the likelihood's curvature; on these records the priors are
negligible beside it). This is a predictive choice, not an evidence one: model selection is unchanged.

Here too: the held-out blocks the loop's criterion scores models on (:func:`held_out_free_runs`, the error of
a free run on one: :func:`held_out_error`), and the one model the loop reports (:func:`reported_model`: its
noise level, its free run on the test record with the band calibrated out of sample on those blocks).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from scipy.optimize import minimize

from ..data import Dataset
from ..errors import FitError
from ..likelihood.ekf import compile_model
from ..sampling.chains import serial_map
from .config import LoopContext
from .freerun import Band, free_run, moved_draws, noise_parameters, posterior_draws
from .verdict import FittedModel, expected_words
from ..sampling.starts import fd_derivatives
from ..model.declaration import ModelSpec

if TYPE_CHECKING:  # the loop's fits; confirm.py does not need this module
    from .confirm import Fit


@dataclass
class SimulationFit:
    """The chosen noise factor, the parameters fitted at it (the noise parameters at ``factor`` x the
    posterior's) and the held-out free-run error of each factor at the record's end and start."""

    factor: float
    phi: dict
    noise_parameters: list
    held_out_rms: dict = field(default_factory=dict)
    fit_samples: int = 0
    held_out_samples: int = 0
    held_out_start: dict = field(default_factory=dict)
    """The free-run error on the record's first ``held_out_samples``, fitted on the rest, of factor 1 and the
    factor the end chose (empty when the end chose factor 1)."""

    def to_json(self) -> dict:
        return {"noise_factor": self.factor, "noise_parameters": self.noise_parameters,
                "held_out_rms": {f"{k:g}": v for k, v in self.held_out_rms.items()},
                "held_out_start_rms": {f"{k:g}": v for k, v in self.held_out_start.items()},
                "fit_samples": self.fit_samples, "held_out_samples": self.held_out_samples,
                "chosen_by": "held-out free runs at the start and the end of the estimation record, each fitted on the "
                             "rest (a predictive choice, not the evidence)"}

    def draws(self, posterior: list[dict], mean: dict) -> list[dict]:
        """The reported model's parameter draws: the posterior's draws (``posterior``, with their ``mean``)
        moved to this fit's parameters, each keeping its offset from the mean and its own process noise.

        The location is this predictive fit's; the spread is the evidence's posterior, the uncertainty the
        data leave in the parameters (a fit at a smaller noise than the data show would claim intervals as
        much too narrow as its noise is small). A predictive band made from them has the posterior's
        process noise at scale 1 (:func:`~ardcore.loop.freerun.calibrated_out_of_sample` calibrates it).
        """
        return moved_draws(posterior, mean, self.phi, self.noise_parameters)

    def parameters(self, posterior: dict) -> dict:
        """Per parameter: this fit's value as the mean and the posterior's sd and 99 % interval moved with it
        (``posterior``: parameter -> {mean, sd, q005, q995}); the noise parameters at their held values."""
        out = {}
        for p, v in self.phi.items():
            q = posterior.get(p, {})
            if p in self.noise_parameters or not q:
                out[p] = {"mean": float(v), "sd": 0.0, "q005": float(v), "q995": float(v)}
                continue
            m = float(v) - q["mean"]
            out[p] = {"mean": float(v), "sd": q["sd"], "q005": q["q005"] + m, "q995": q["q995"] + m}
        return out


def _whitening(lik, phi: dict, names: list[str]) -> np.ndarray:
    """A square root of the likelihood's curvature inverse at ``phi`` (finite differences, |eigenvalues|):
    Silverbox's parameters differ by many orders of magnitude and are tightly correlated, so a search in their
    own units takes ~1,300 evaluations per fit and stops early; in these coordinates ~300."""
    x = np.array([phi[p] for p in names])

    def nll(v):
        r = -lik({**phi, **dict(zip(names, map(float, v)))})
        return r if np.isfinite(r) else 1e300

    h = 1e-5 * np.where(x != 0, np.abs(x), 1.0)
    _, _, H = fd_derivatives(nll, x, h)
    if not np.all(np.isfinite(H)):
        return np.diag(np.where(x != 0, np.abs(x), 1.0))
    # the curvature spans ~16 orders of magnitude in the parameters' units: scale its diagonal to 1 first
    dg = np.abs(np.diag(H))
    D = np.where(dg > 0, 1 / np.sqrt(np.where(dg > 0, dg, 1.0)), np.abs(h) * 1e5)
    w, V = np.linalg.eigh(0.5 * (H + H.T) * np.outer(D, D))
    w = np.maximum(np.abs(w), 1e-12 * max(np.max(np.abs(w)), 1e-300))
    return D[:, None] * V / np.sqrt(w)


def _fit(lik, phi: dict, noise: list, factor: float, names: list, maxfun: int, L: np.ndarray) -> dict:
    """Maximum likelihood (``lik``: a bound likelihood) of ``names`` from ``phi``, the rest held; the noise
    parameters at ``factor`` x their value in ``phi``. The search runs in coordinates whitened by ``L``
    (:func:`_whitening`), where a unit step is about one standard deviation."""
    phi = {**phi, **{p: phi[p] * factor for p in noise}}
    x0 = np.array([phi[p] for p in names])

    def nll(z):
        v = lik({**phi, **dict(zip(names, map(float, x0 + L @ z)))})
        return -v if np.isfinite(v) else 1e300

    z0 = np.zeros(len(names))
    sol = minimize(nll, z0, method="L-BFGS-B", options={"maxfun": maxfun, "eps": 1e-3})
    out = dict(phi)
    if np.isfinite(sol.fun) and sol.fun < nll(z0):
        out.update(dict(zip(names, map(float, x0 + L @ sol.x))))
    return out


@dataclass(frozen=True)
class SimulationSettings:
    """How a simulation fit chooses its process-noise factor: the ``factors`` tried (largest first), the
    ``held_out`` share of the estimation record they are judged on, the ``min_gain`` by which the best must
    beat the posterior's own noise, the ``init_samples`` a free run starts after, and each fit's
    ``maxfun``."""

    factors: tuple = (0.3, 0.1, 0.03)
    held_out: float = 0.3
    min_gain: float = 0.05
    init_samples: int = 50
    maxfun: int = 3000


def _fit_task(args) -> dict:
    """:func:`_fit` of ``(spec, data, substeps, phi, noise, factor, names, maxfun, L)``, the likelihood bound where it
    runs: a picklable unit of work for a pool."""
    spec, data, substeps, phi, noise, factor, names, maxfun, L = args
    return _fit(compile_model(spec).bind(data, substeps), phi, noise, factor, names, maxfun, L)


def simulation_fit(spec: ModelSpec, phi: dict, data: Dataset, *, substeps: int | None = None,
                   settings: SimulationSettings = SimulationSettings(), mapper=serial_map) -> SimulationFit | None:
    """Choose the process-noise factor for simulation on held-out data (see module docstring).

    The factors are fitted in turn from the largest, each from the previous one's parameters (a
    continuation: at a small noise the likelihood far from its maximum is rugged, and the path through the
    larger factors stays near it), in coordinates whitened once by the curvature at ``phi``.

    Parameters
    ----------
    spec, phi : the fitted model and its posterior mean.
    data : Dataset
        The estimation record (with any columns the model's effects need).
    substeps : int, optional
        The fit's sub-steps.
    settings : SimulationSettings
        The factors of the noise parameters tried besides 1, the share of the record (at its end) the free
        runs are scored on, the relative reduction of that error a factor needs over factor 1.
    mapper : callable, optional
        ``mapper(fn, tasks)``: where the two contenders' fits without the record's start run (the loop's pool;
        default :func:`~ardcore.sampling.chains.serial_map`, here).

    Returns
    -------
    SimulationFit or None
        None when the model has no noise parameter that scales its process noise, or the record is too
        short to hold part of it out.
    """
    factors, held_out, min_gain = settings.factors, settings.held_out, settings.min_gain
    init_samples, maxfun = settings.init_samples, settings.maxfun
    noise = noise_parameters(spec)
    n = len(data)
    n_fit = int(round(n * (1 - held_out)))
    if not noise or not factors or n_fit < 4 * init_samples or n - n_fit < 4 * init_samples:
        return None
    names = [p for p in spec.free_parameters if p not in noise]
    model = compile_model(spec)
    # two held-out blocks: the record's end and its start, each free-run from the filter at its first samples
    # by a fit to the rest; a factor is chosen only when it free-runs better in both (what helps where the
    # record ends, a decay's small amplitudes, need not carry to the rest of the record or beyond it)
    lik = model.bind(data.slice(0, n_fit), substeps)
    L = _whitening(lik, phi, names)
    fitted, start = {}, dict(phi)
    for f in sorted({1.0, *factors}, reverse=True):
        q = _fit(lik, start, noise, f, names, maxfun, L)
        fitted[f] = q
        start = {**q, **{p: phi[p] for p in noise}}  # the next factor scales phi's noise, not this one's
    rms = _held_out_rms(spec, fitted, data.slice(n_fit, None), init_samples, substeps)
    best = min(rms, key=rms.get)
    if best == 1.0 or not rms[best] < (1 - min_gain) * rms[1.0]:
        return SimulationFit(1.0, dict(phi), noise, rms, n_fit, n - n_fit)
    # the start block only for the two contenders, each fitted from its end-block fit (near its optimum)
    tasks = [(spec, data.slice(n - n_fit, None), substeps, {**fitted[f], **{p: phi[p] for p in noise}}, noise, f,
              names, maxfun, L) for f in (1.0, best)]
    other = dict(zip((1.0, best), mapper(_fit_task, tasks)))
    start_rms = _held_out_rms(spec, other, data.slice(0, n - n_fit), init_samples, substeps)
    if not start_rms[best] < (1 - min_gain) * start_rms[1.0]:
        return SimulationFit(1.0, dict(phi), noise, rms, n_fit, n - n_fit, held_out_start=start_rms)
    # the whole record at the chosen factor, from the held-out fit (its noise parameters back at 1 x phi's)
    q = refit(spec, {**fitted[best], **{p: phi[p] for p in noise}}, data, best, substeps=substeps,
              maxfun=maxfun, whitening=L)
    return SimulationFit(best, q, noise, rms, n_fit, n - n_fit, start_rms)


HELD_OUT_BLOCKS = ("start", "end", "loudest")
"""The blocks of the estimation record a structure is judged on (:func:`held_out_free_runs`): its start, its end
and the stretch where the output is largest (where a stand-in fitted on smaller motions must extrapolate)."""


def held_out_blocks(data: Dataset, column: str, share: float) -> dict[str, tuple[int, int]]:
    """``(first, stop)`` of each of :data:`HELD_OUT_BLOCKS`: ``share`` of the record at its start, at its end, and
    where the output's power about its mean over that many samples is largest."""
    n = len(data)
    m = int(round(n * share))
    y = np.nan_to_num(data.columns[column] - np.nanmean(data.columns[column]))
    recs = data.record_slices()
    # several records: each block lies inside one (a free run starts within a record and never crosses into the
    # next experiment), no longer than the shortest record
    m = min([m] + [sl.stop - sl.start for sl in recs])
    best, k = -np.inf, 0
    for sl in recs:
        # each window's sum by a running sum (a convolution with m ones costs n m: seconds on a 65k record)
        c = np.concatenate([[0.0], np.cumsum(y[sl] ** 2)])
        power = c[m:] - c[:-m]
        j = int(np.argmax(power))
        if power[j] > best:
            best, k = power[j], sl.start + j
    return {"start": (0, m), "end": (n - m, n), "loudest": (k, k + m)}


@dataclass(frozen=True)
class HeldOut:
    """A structure judged on held-out blocks (:func:`held_out_free_runs`): per block its ``(first, stop)`` in the
    record, the parameters fitted without it and the free-run RMS error on it."""

    blocks: dict
    fits: dict
    errors: dict

    def refits(self, *names: str) -> tuple:
        """``(first, stop, parameters)`` of each block (of those ``names``, default all): what a band is
        calibrated on out of sample (:class:`~.freerun.Band`). A stretch two blocks share (the loudest is the
        record's start or end) is given once: its band would be simulated twice for the same answer (the
        calibration weighs a sample that overlapping blocks hold by one over their number)."""
        spans = {}
        for b in names or self.blocks:
            spans.setdefault(self.blocks[b], (*self.blocks[b], self.fits[b]))
        return tuple(spans.values())


def held_out_free_runs(spec: ModelSpec, phi: dict, data: Dataset, *, substeps: int | None = None,
                       settings: SimulationSettings = SimulationSettings()) -> HeldOut | None:
    """The free-run error (:func:`held_out_error`) of the structure ``spec`` on each block of
    :func:`held_out_blocks` (each the ``settings.held_out`` share of ``data``), fitted on the rest of the record
    (maximum likelihood at the posterior's process noise from its mean ``phi``, the block's observations left
    out: the filter predicts across them) and free-run from the state that fit's filter holds at the block's
    start. How the model predicts where its parameters did not see the data, which an in-sample free run
    cannot say: a flexible stand-in bends to the record it was fitted on and extrapolates badly beyond the
    motions it saw. Infinite where the free run diverges; None when the record is too short to hold a block
    out."""
    n = len(data)
    m = int(round(n * settings.held_out))
    if m < 4 * settings.init_samples or n - m < 4 * settings.init_samples:
        return None
    noise = noise_parameters(spec)
    names = [p for p in spec.free_parameters if p not in noise]
    model = compile_model(spec)
    L = _whitening(model.bind(data, substeps), phi, names)  # one search metric for every block
    blocks = held_out_blocks(data, spec.observed_columns[0], settings.held_out)
    fits, errors = {}, {}
    for name, (a, b) in blocks.items():
        same = next((k for k, span in blocks.items() if span == (a, b) and k in fits), None)
        if same is not None:  # the loudest stretch is the record's start or end: that block's refit is this one's
            fits[name], errors[name] = fits[same], errors[same]
            continue
        cols = {k: (v.copy() if k in spec.observed_columns else v) for k, v in data.columns.items()}
        for o in spec.observed_columns:
            cols[o][a:b] = np.nan
        fits[name] = _fit(model.bind(data.with_columns(cols), substeps), phi, noise, 1.0, names,
                          settings.maxfun, L)
        # the block is free-run from the state the refit's filter holds after the record up to it (and the block's
        # first init_samples, as a test record is): a slow state no sensor sees (an upper tank's level) is then
        # known at the block's start, and the block scores the model, not its initial guess
        first = max(x for x in data.starts if x <= a)  # the block's record: its free run starts there
        errors[name] = _held_out_rms(spec, {1.0: fits[name]}, data.slice(first, b), a - first + settings.init_samples,
                                     substeps)[1.0]
    return HeldOut(blocks, fits, errors)


def held_out_task(args) -> HeldOut | str | None:
    """:func:`held_out_free_runs` of ``(spec, phi, data, substeps, settings)``, a picklable unit of work for the
    loop's process pool; a failed fit is returned as its message, not raised."""
    from ..errors import FitError

    spec, phi, data, substeps, settings = args
    try:
        return held_out_free_runs(spec, phi, data, substeps=substeps, settings=settings)
    except (FitError, ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        return f"{type(exc).__name__}: {exc}"


def _held_out_rms(spec: ModelSpec, fitted: dict, part: Dataset, init_samples: int, substeps) -> dict:
    """Each factor's free-run error on ``part`` (:func:`held_out_error`; infinite when it diverges)."""
    return {f: held_out_error(free_run(spec, q, part, init_samples=init_samples, substeps=substeps))
            for f, q in fitted.items()}


def held_out_error(fr: dict) -> float:
    """The error of a free run ``fr`` (:func:`~.freerun.free_run`) on a held-out block, in the output's units;
    infinite when it diverges.

    A driven model's free run follows its input, so its RMS error is the error. A model without inputs that
    oscillates (a self-excited limit cycle, a free oscillation) cannot keep its phase over a long block: a
    frequency right to a fraction of a per cent still drifts out of phase, and the RMS error then measures the
    drift, not the model. Its error is the oscillation's own, phase-free: the relative errors of its amplitude,
    frequency and mean, ``rms_data * hypot(amplitude, frequency, mean)`` (an oscillation right in all three
    scores 0, as it would with its phase)."""
    r = float(fr["rms_error"])
    if not np.isfinite(r):
        return float("inf")
    if "amplitude_error" not in fr or not fr.get("rms_data"):
        return r
    y, yh = fr["y"], fr["y_free"]
    mean = (float(np.nanmean(yh)) - float(np.nanmean(y))) / fr["rms_data"]
    e = float(fr["rms_data"] * np.sqrt(fr["amplitude_error"] ** 2 + fr["frequency_error"] ** 2 + mean ** 2))
    return min(e, r) if np.isfinite(e) else r


def refit(spec: ModelSpec, phi: dict, data: Dataset, factor: float, *, substeps: int | None = None,
          maxfun: int = 3000, whitening: np.ndarray | None = None) -> dict:
    """The structure ``spec`` fitted to ``data`` by maximum likelihood from ``phi`` with its process noise at
    ``factor`` x its value in ``phi`` (held). ``whitening``: the search's coordinates (:func:`_whitening`;
    default: taken at ``phi``)."""
    noise = noise_parameters(spec)
    names = [p for p in spec.free_parameters if p not in noise]
    lik = compile_model(spec).bind(data, substeps)
    return _fit(lik, phi, noise, factor, names, maxfun, _whitening(lik, phi, names) if whitening is None else whitening)


# --------------------------------------------------------------------------- the model the loop reports


def reported_model(ctx: LoopContext, final: FittedModel, held: Fit, test: Dataset, shown: tuple, seed: int,
                   blocks=None) -> tuple[dict, FittedModel]:
    """The one model the loop reports, and its record: the final structure at the process-noise level whose
    free run is best on the held-out end of the estimation record (:mod:`.simulation_fit`: factor 1, the
    posterior's own noise, unless another is better by its ``min_gain``).

    At factor 1 it is the posterior (its mean, its MCMC draws). At another factor it is the structure refitted
    at that noise, with the posterior's spread moved to it (:meth:`~.simulation_fit.SimulationFit.draws`), and
    the posterior mean's free run is kept beside it as ``posterior_mean_free_run``. Either way its free run on
    the test record is measured again with its band calibrated out of sample on ``blocks`` (the
    :class:`~.simulation_fit.HeldOut` blocks of the estimation record, each left out of a refit), and replaces
    the measure ``shown`` stood for: ``(its JSON record, its figure's arrays)``, the last kept round's
    ``after`` (or the first measure when no round is kept). ``seed``: of the band's draws.
    """
    config, say = ctx.config, ctx.say
    rec = {"structure": held.cand.label, "noise_factor": 1.0,
           "parameters": {k: {q: getattr(held.row, q)[k] for q in ("mean", "sd", "q005", "q995")}
                          for k in held.row.mean}}
    measure, figure = shown
    measured = measure["free_run"]
    keep = ("rms_error", "relative_rms_error", "band_coverage", "band_expected", "band_diverged",
            "band_halfwidth_rms", "band_factor", "band_calibration", "n")
    rec["free_run"] = {k: measured[k] for k in keep if k in measured}
    sim, model = None, final
    if not config.simulation_factors:
        rec["chosen_by"] = "the posterior (no other noise level tried)"
    else:
        say("reported model: process-noise factors " + ", ".join(f"{f:g}" for f in config.simulation_factors)
            + " judged on held-out data")
        try:
            sim = simulation_fit(final.spec, final.phi, held.data, substeps=final.substeps,
                                 settings=SimulationSettings(factors=tuple(config.simulation_factors),
                                                             held_out=config.simulation_held_out,
                                                             init_samples=config.init_samples), mapper=ctx.mapper)
        except (FitError, ValueError, np.linalg.LinAlgError) as e:  # the posterior's own result stands
            rec["chosen_by"] = f"the posterior (the other noise levels failed: {type(e).__name__}: {e})"
        else:
            rec.update(sim.to_json() if sim else {"chosen_by": "the posterior (too short to hold part out)"})
    draws = posterior_draws(held.mr, final.spec, config.band_draws, seed=seed)
    if sim is not None and sim.factor != 1.0:
        model = FittedModel(final.spec, sim.phi, final.effects, final.substeps)
        draws = sim.draws(draws, final.phi)
        rec.update(parameters=sim.parameters(rec["parameters"]), posterior_mean_free_run=dict(rec["free_run"]))
    elif blocks is None:  # the posterior, its band as the loop measured it
        say("reported model: the posterior (no smaller process noise free-runs both held-out ends better)")
        return rec, final
    fr = free_run(model.spec, model.phi, test, init_samples=config.init_samples, substeps=model.substeps,
                  band=Band(draws, calibration=held.data, seed=seed, refits=blocks.refits() if blocks else (),
                            mapper=ctx.mapper))
    rec["free_run"] = {k: fr[k] for k in keep if k in fr}
    measure["free_run"] = {**{k: v for k, v in fr.items() if k in measured},
                           "band_calibration": fr.get("band_calibration"), "noise_factor": model_factor(sim)}
    figure["free_run"] = fr
    band = (f", its 90 % band (process noise x {fr['band_factor']:g}, calibrated on held-out blocks) holds "
            f"{fr['band_coverage']:.0%}{expected_words(fr)}" if "band_coverage" in fr else "")
    say(f"reported model: the structure at {model_factor(sim):g} x its posterior process noise; free-run RMS "
        f"error {fr['rms_error']:.4g} (posterior mean {measured['rms_error']:.4g}){band}")
    return rec, model


def model_factor(sim) -> float:
    """The process-noise factor of the reported model (1: the posterior's own)."""
    return 1.0 if sim is None else float(sim.factor)
