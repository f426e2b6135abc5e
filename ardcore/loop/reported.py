"""The one model the loop reports (docs/loop.md steps 5 and 6): the loop's final structure (every move of which
its criterion took, :mod:`.criterion`) at the process-noise level chosen on held-out data
(:func:`~.simulation_fit.simulation_fit`), its free run on the test record with the band calibrated out of
sample on the criterion's held-out blocks (:func:`~.freerun.calibrated_out_of_sample`).
"""

from __future__ import annotations

import math

import numpy as np

from ..data import Dataset
from ..errors import FitError
from .config import LoopContext
from .confirm import Fit
from .freerun import Band, free_run, posterior_draws
from .result import FittedModel
from .simulation_fit import SimulationSettings, simulation_fit

INF = math.inf


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
