"""The one model the loop reports (docs/loop.md steps 5, 6 and 6b): which round's model, at which process-noise
level, with which band.

* :func:`held_out_choice`: each round's model refitted with a block of the estimation record left out and
  free-run over it (:func:`~.simulation_fit.held_out_free_runs`); a later round's model is kept only when it
  free-runs no worse on every block and better over them all. :func:`withhold` marks what the rounds after
  the kept one did as not kept.
* :func:`reported_model`: the kept structure at the process-noise level chosen on held-out data
  (:func:`~.simulation_fit.simulation_fit`), its free run on the test record with the band calibrated out of
  sample on the held-out blocks (:func:`~.freerun.calibrated_out_of_sample`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..data import Dataset
from ..errors import FitError
from ..model.declaration import ModelSpec
from .config import LoopContext
from .confirm import Fit
from .freerun import FREE_RUN_TOLERANCE, Band, free_run, posterior_draws
from .result import FittedModel, LoopRound
from .simulation_fit import HeldOut, SimulationSettings, held_out_task, simulation_fit

INF = math.inf


@dataclass(frozen=True)
class Snapshot:
    """The model the loop held at the start of a round (its fit, its structure with pruned terms fixed, its
    posterior mean) and the residual tests and free run measured on it."""

    held: Fit
    fspec: ModelSpec
    phi: dict
    arrays: dict


def held_out_choice(ctx: LoopContext, snapshots: list[Snapshot]) -> tuple[int, dict | None, object]:
    """Which round's model the loop reports, judged on held-out blocks of the estimation record
    (:func:`~.simulation_fit.held_out_free_runs`: the record's start, its end and its loudest stretch, each
    left out of a refit of the structure and free-run).

    From the declared model on, a later round's model is kept over the one kept so far only when it free-runs
    no worse on every block (within :data:`~.freerun.FREE_RUN_TOLERANCE`) and better over them all by more
    than that. Evidence and the in-sample never-worse check judge an effect on the data it was fitted to; a
    stand-in for what no library effect holds (a hidden hysteretic state) passes both and then extrapolates
    badly to motions larger than those it saw. Returns the index of the model kept (the last when the record
    is too short to hold a block out), the record of the choice and the kept model's
    :class:`~.simulation_fit.HeldOut` (its band is calibrated on those blocks), or None."""
    last = len(snapshots) - 1
    config = ctx.config
    settings = SimulationSettings(held_out=config.simulation_held_out, init_samples=config.init_samples)
    errs, held = [], []
    # side by side on the loop's pool: one model per task
    for e in ctx.mapper(held_out_task, [(s.fspec, s.phi, s.held.data, s.held.cand.substeps, settings)
                                        for s in snapshots]):
        if e is None:
            return last, None, None
        held.append(e if isinstance(e, HeldOut) else None)
        errs.append(e.errors if isinstance(e, HeldOut) else {})  # a failed refit ranks last

    def overall(e: dict) -> float:
        return float(np.sqrt(np.mean([v ** 2 for v in e.values()]))) if e else INF

    if last == 0:  # nothing to choose between: the blocks still calibrate the band
        return 0, None, held[0]
    keep, tol = 0, 1 + FREE_RUN_TOLERANCE
    for j in range(1, last + 1):
        e, k = errs[j], errs[keep]
        if e and (not k or all(e[b] <= k[b] * tol for b in e) and overall(e) * tol < overall(k)):
            keep = j
    ctx.say(f"held-out free runs (each block, {100 * config.simulation_held_out:g} % of the record, left out of a "
            "refit): " + "; ".join(f"round {i} " + ", ".join(f"{b} {v:.4g}" for b, v in e.items())
                                   for i, e in enumerate(errs))
            + ("" if keep == last else f"; the model of round {keep} is kept (what came after free-runs worse "
                                       f"on a block)"))
    return keep, {"share": config.simulation_held_out, "free_run": errs, "overall": [overall(e) for e in errs],
                  "kept": keep, "rule": f"a later round's model is kept when no block is worse by more than "
                                        f"{100 * FREE_RUN_TOLERANCE:g} % and all together are better by more",
                  "blocks": {b: list(v) for b, v in held[keep].blocks.items()} if held[keep] else None}, held[keep]


def withhold(rounds: list[LoopRound], keep: int) -> None:
    """Mark what rounds ``keep`` on added, replaced or dropped as not kept: the model of round ``keep`` is
    reported (:func:`held_out_choice`)."""
    for r in rounds[keep:]:
        r.record["withheld"] = True
        for x in r.added:
            x.record["withheld"] = True
    for r in rounds[:keep]:
        for x in r.added:
            if x.record.get("removed") is not None and x.record["removed"] >= keep:
                x.record.pop("removed")  # dropped in a round not kept: still in the model reported
                x.record.pop("log_bayes_factor_after", None)


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
    keep = ("rms_error", "relative_rms_error", "band_coverage", "band_halfwidth_rms", "band_factor", "n")
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
                                                             init_samples=config.init_samples))
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
                  band=Band(draws, calibration=held.data, seed=seed, refits=blocks.refits("end") if blocks else ()))
    rec["free_run"] = {k: fr[k] for k in keep if k in fr}
    measure["free_run"] = {**{k: v for k, v in fr.items() if k in measured},
                           "band_calibration": fr.get("band_calibration"), "noise_factor": model_factor(sim)}
    figure["free_run"] = fr
    band = (f", its 90 % band (process noise x {fr['band_factor']:g}, calibrated on held-out blocks) holds "
            f"{fr['band_coverage']:.0%}" if "band_coverage" in fr else "")
    say(f"reported model: the structure at {model_factor(sim):g} x its posterior process noise; free-run RMS "
        f"error {fr['rms_error']:.4g} (posterior mean {measured['rms_error']:.4g}){band}")
    return rec, model


def model_factor(sim) -> float:
    """The process-noise factor of the reported model (1: the posterior's own)."""
    return 1.0 if sim is None else float(sim.factor)
