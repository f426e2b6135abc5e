"""How a model takes its inputs between samples, from the record when the model does not say.

A model's inputs are known only at the samples; between them the integrator interpolates them linearly by
default (``input_hold: "foh"``), right for a sampled continuous signal (a multisine, a measured force). A
command from a digital controller or a stepped test (a heater's power, a pump's setting) is held between
samples instead, and interpolating it makes every step a ramp one sample long. A model fitted that way
misses by the same amount at every step, and the loop then finds a term that only offsets those misses (a
feedthrough of the input to the sensor, or the input's rate). So when a model does not declare its hold, and
each of its inputs that varies holds its value from one sample to the next in at least :data:`HELD_SHARE`
of its steps, the model holds them too (``"zoh"``). A sampled continuous signal repeats a value almost never,
so a record of one keeps the default.
"""

from __future__ import annotations

import numpy as np

from ..data import Dataset
from .spec import RECORD_INPUT, CandidateSpec, StudySpec

HELD_SHARE = 0.5
"""The least share of a signal's sample-to-sample steps that are exactly zero for it to count as held."""


def _steps(x: np.ndarray) -> np.ndarray:
    """The finite signal ``x``'s sample-to-sample steps."""
    x = np.asarray(x, dtype=float)
    return np.diff(x[np.isfinite(x)])


def held_share(x: np.ndarray) -> float:
    """The share of the finite signal ``x``'s sample-to-sample steps that are exactly zero (0 for a signal that
    never changes: a constant is neither held nor interpolated, both holds give it)."""
    d = _steps(x)
    return float(np.mean(d == 0)) if np.any(d != 0) else 0.0


def with_hold(cand: CandidateSpec, data: Dataset) -> tuple[CandidateSpec, list[str]]:
    """``cand`` holding its inputs between samples when its model does not declare ``input_hold`` and every
    input of ``data`` it reads that varies is held (:data:`HELD_SHARE`); the note saying so (none otherwise)."""
    ms = cand.resolved()
    if not ms.inputs or "input_hold" in ms.model_fields_set or any(i not in data.columns for i in ms.inputs):
        return cand, []
    # the record indicators (per-record parameters, :meth:`CandidateSpec.for_records`) are the study's, not data
    varying = {i: held_share(data.columns[i]) for i in ms.inputs
               if not i.startswith(RECORD_INPUT) and np.any(_steps(data.columns[i]) != 0)}
    if not varying or min(varying.values()) < HELD_SHARE:
        return cand, []
    shares = ", ".join(f"{i} {100 * s:.0f} %" for i, s in varying.items())
    note = (f"model {cand.label}: its inputs hold their values between samples (steps that are zero: {shares}), "
            "so the model holds them too (input_hold 'zoh' instead of the linear interpolation 'foh'); declare "
            "input_hold in the model to choose")
    model = ms.model_copy(update={"input_hold": "zoh"})
    return cand.model_copy(update={"model": model, "name": cand.label, "constants": {}}), [note]


def with_holds(spec: StudySpec, data: Dataset) -> tuple[StudySpec, list[str]]:
    """Every candidate of ``spec`` through :func:`with_hold` on the study's ``data``, and the notes."""
    got = [with_hold(c, data) for c in spec.models]
    notes = [n for _, ns in got for n in ns]
    return (spec.model_copy(update={"models": [c for c, _ in got]}) if notes else spec), notes
