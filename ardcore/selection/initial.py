"""An initial-state prior that agrees with the record.

A model declares its initial state in absolute units (the library's oscillators: y ~ N(0, 0.1^2),
v ~ N(0, 10^2); an undeclared state: N(0, 1)). A record in other units, or one that starts in mid
motion, contradicts that prior at its first sample; the filter then spends its first innovations
recovering, and their huge, parameter-dependent terms bend the fit. When (and only when) the first
samples contradict the declared prior by more than ``k`` standard deviations, the prior is re-centred
on the record: a directly observed state on its first observation, with the spread of the first samples
as its standard deviation; a state that is the observed state's derivative (``y' = v``) on the slope of
the first samples, with the spread of the sample-to-sample slopes. The declared standard deviation is
never narrowed. Declarations that depend on parameters are the model author's choice and kept.
"""

from __future__ import annotations

import numpy as np

from ..data import Dataset
from ..jsonio import number
from ..model.declaration import ModelSpec
from .spec import CandidateSpec

FIRST_SAMPLES = 50


def data_informed_initial(cand: CandidateSpec, data: Dataset, *, k: float = 3.0) -> tuple[CandidateSpec, list[str]]:
    """``cand`` with its initial-state prior re-centred on ``data`` where the two disagree, and what changed.

    Returns the candidate unchanged (and no notes) when its declared prior already covers the record's start.
    """
    model, notes = recentred(cand.resolved(), data, k=k)
    return (cand.model_copy(update={"model": model}), notes) if notes else (cand, [])


def recentred(ms: ModelSpec, data: Dataset, *, k: float = 3.0) -> tuple[ModelSpec, list[str]]:
    """The model with its initial-state prior re-centred on the start of ``data`` (see the module), and notes."""
    mean, std = dict(ms.initial_mean), dict(ms.initial_std)
    notes: list[str] = []
    t = data.t[:FIRST_SAMPLES]
    for o in ms.observations:
        s = str(o.expr).strip()
        if s not in ms.states or o.column not in data.columns:
            continue
        y = data.columns[o.column][:FIRST_SAMPLES]
        ok = np.isfinite(y)
        if ok.sum() < 3:
            continue
        ty, yy = t[ok], y[ok]
        # a declaration that is an expression (of parameters) is not a number: the model author's choice, kept
        m0, s0 = number(mean.get(s, 0.0)), number(std.get(s, 1.0))
        if np.isfinite(m0) and np.isfinite(s0) and abs(yy[0] - m0) > k * s0:
            spread = float(np.std(yy)) or abs(float(yy[0]))
            mean[s], std[s] = float(yy[0]), max(s0, spread)
            notes.append(f"initial {s}: N({m0:g}, {s0:g}^2) declared, the record starts at {yy[0]:.4g}: "
                         f"N({mean[s]:.4g}, {std[s]:.3g}^2) used")
        d = str(ms.drift.get(s, "")).strip()
        if d in ms.states and d != s:
            slopes = np.diff(yy) / np.diff(ty)
            n5 = min(5, yy.size)
            v0 = float(np.polyfit(ty[:n5] - ty[0], yy[:n5], 1)[0])
            m1, s1 = number(mean.get(d, 0.0)), number(std.get(d, 1.0))
            spread = float(np.sqrt(np.mean(slopes ** 2)))
            if np.isfinite(m1) and np.isfinite(s1) and (abs(v0 - m1) > k * s1 or spread > k * s1):
                mean[d], std[d] = v0, max(s1, spread)
                notes.append(f"initial {d} (= d{s}/dt): N({m1:g}, {s1:g}^2) declared, the record's first slopes "
                             f"are {v0:.4g} +- {spread:.3g}: N({v0:.4g}, {std[d]:.3g}^2) used")
    if not notes:
        return ms, []
    return ms.model_copy(update={"initial_mean": mean, "initial_std": std}).revalidate(), notes
