"""The screen of a state move (:mod:`ardcore.loop.states`): its own parameters fitted with the current model held.

A full fit of a state move searches every parameter from the prior, a Nelder-Mead walk in all of them. The
screen fits only the move's own parameters (one to three) with the current model's held at its MAP: a few loose
searches polished by Newton steps. Its Laplace evidence against the current model's likelihood at that MAP is a
conditional ln Bayes factor, which orders the moves and drops those that fit no better even where their state is
best placed; its MAP is where the full fit starts.
"""

from __future__ import annotations

import numpy as np

from ..selection.spec import CandidateSpec


def conditional(cand: CandidateSpec, known: dict) -> tuple[CandidateSpec, list[str]] | None:
    """``cand`` with every parameter ``known`` names (the current model's MAP) fixed there, the new state's own
    sampled alone, and the names of those new ones; None when the move has none, when it samples one ``known``
    does not name, or when it selects terms by ARD (a lag)."""
    new = [n for n in cand.priors if n not in known]
    if cand.ard or not new or any(n not in known for n in cand.priors if n not in new):
        return None
    fixed = {**cand.fixed, **{n: float(known[n]) for n in cand.priors if n not in new}}
    return cand.model_copy(update={"priors": {n: cand.priors[n] for n in new}, "fixed": fixed}), new


SCREEN_STARTS = 4
"""Searches per state move in the screen: from the new parameters' prior medians and from dispersed prior points
(a mode's frequency or a Bouc-Wen shape has local optima a single search can stop in)."""
SCREEN_TOLERANCE = 0.01
"""Where a screen's search stops (nats, and prior scales in the parameters): Newton steps take it to the mode."""
SCREEN_MAXFEV = 300
"""Likelihood evaluations one screen search may take."""


def _target(cand: CandidateSpec, data):
    from ..likelihood.posterior import ModelPosterior

    return ModelPosterior(cand.model_spec(), dict(cand.priors), data, cand.substeps)


def _screen_search(args) -> tuple[np.ndarray, float]:
    """One loose Nelder-Mead search of a screen (a picklable unit of work): ``(cand, data, x0)``."""
    from ..sampling.starts import initial_scale, local_mode

    cand, data, x0 = args
    target = _target(cand, data)
    return local_mode(target, x0, initial_scale(target.prior), SCREEN_MAXFEV, xatol=SCREEN_TOLERANCE,
                      fatol=SCREEN_TOLERANCE, passes=1)


def _screen_evidence(args) -> tuple[float, dict]:
    """A screen's Laplace evidence and MAP from its best search's point ``x0`` (Newton steps): ``(cand, data,
    x0)``."""
    from ..evidence.laplace import laplace
    from ..sampling.starts import initial_scale

    cand, data, x0 = args
    target = _target(cand, data)
    ev, x, _ = laplace(target, x0, initial_scale(target.prior), warm=True)
    return ev.log_evidence, dict(zip(target.names, map(float, x)))


def screen(ctx, cands: list[CandidateSpec], data, seed: int) -> list[tuple[float, dict]]:
    """Each of ``cands`` (from :func:`conditional`) screened: its Laplace evidence and MAP from the best of
    :data:`SCREEN_STARTS` loose Nelder-Mead searches (all of them one batch on the loop's pool) polished by
    Newton steps."""
    from ..model.priors import JointPrior
    from ..sampling.starts import initial_points

    rng = np.random.default_rng(seed)
    starts = []
    for c in cands:
        prior = JointPrior(c.model_spec().free_parameters, dict(c.priors))
        median = [p.quantile(0.5) if p.kind != "ard" else 0.0 for p in prior.priors]
        starts.append([np.asarray(median, float), *initial_points(prior, SCREEN_STARTS - 1, rng)])
    found = ctx.mapper(_screen_search, [(c, data, x) for c, xs in zip(cands, starts) for x in xs])
    best = [max(found[k * SCREEN_STARTS:(k + 1) * SCREEN_STARTS], key=lambda r: r[1])[0] for k in range(len(cands))]
    return ctx.mapper(_screen_evidence, [(c, data, x) for c, x in zip(cands, best)])
