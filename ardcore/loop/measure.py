"""What the loop measures of a model each round (:mod:`ardcore.loop.diagnose`): its residuals on the estimation
records, its free run with a band on the test records, and the errors the report states before and after (each
record's own where there are several)."""

from __future__ import annotations

import numpy as np

from .config import LoopContext
from .confirm import Fit
from .freerun import Band, free_run, posterior_draws
from .residuals import Residuals, residuals
from ..selection.fit import ModelFit


def measure(ctx: LoopContext, held: Fit, fspec, phi, test, rnd: int) -> tuple[Residuals, dict, dict]:
    """The fitted model's residuals on the estimation data, its free run (with a band) on the test record
    and the errors reported for both; ``fspec, phi``: the held model with its pruned terms fixed, at its
    posterior mean."""
    config = ctx.config
    res = residuals(fspec, phi, held.data, config, substeps=held.cand.substeps)
    fr = free_run(fspec, phi, test, init_samples=config.init_samples, substeps=held.cand.substeps,
                  band=Band(posterior_draws(held.mr, fspec, config.band_draws, seed=rnd), seed=rnd))
    return res, fr, errors(res, fr, held.row, ctx.column)


def errors(res: Residuals, fr: dict, row: ModelFit, col: str) -> dict:
    t = res.tests[col]
    keep = ("rms_error", "relative_rms_error", "frequency_error", "amplitude_error", "harmonic_error",
            "band_coverage", "band_halfwidth_rms", "draws_rms_error", "n_draws", "band_factor", "band_calibration")
    # the first innovations carry the initial-state uncertainty, not the model's error
    skip = min(10, max(0, res.raw_innovations.shape[0] // 10))
    out = {"innovation_rms": float(np.sqrt(np.nanmean(res.raw_innovations[skip:, 0] ** 2))),
           # what the model had to be pushed by (smoothed process noise, per unit time), per dynamic state
           "injected_noise_rms": {s: float(np.sqrt(np.nanmean(r ** 2))) for s, r in res.process_noise_rate.items()},
           "standardized_rms": t["rms"], "ljung_box": t["ljung_box"], "ljung_box_p": t["ljung_box_p"],
           "free_run": {k: fr[k] for k in keep if k in fr},
           "log_evidence": row.log_evidence, "log_evidence_se": row.log_evidence_se}
    if res.records:  # several estimation records: each one's innovation tests
        out["records"] = [dict(r) for r in res.records]
    if fr.get("records"):  # several test records: each one's free run
        out["free_run"]["records"] = fr["records"]
    return out


def strip_tests(tests: dict) -> dict:
    """JSON part of the tests (the spectrum arrays go to the figures)."""
    out = {}
    for c, t in tests.items():
        d = {k: v for k, v in t.items() if k not in ("spectrum", "acf")}
        d["acf"] = [float(x) for x in t["acf"]]
        d["spectral_peaks"] = t["spectrum"]["peaks"]
        out[c] = d
    return out


def figure_arrays(res: Residuals, fr: dict) -> dict:
    return {"tests": res.tests, "innovations": res.innovations, "process_noise_rate": res.process_noise_rate,
            "free_run": fr}
