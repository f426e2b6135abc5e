"""The screen of a state move (:mod:`ardcore.loop.states`): its own parameters fitted with the current model held.

A full fit of a state move searches every parameter from the prior, a Nelder-Mead walk in all of them. The
screen fits only the move's own parameters (one to three) with the current model's held at its MAP: a few loose
searches polished by Newton steps. Its Laplace evidence against the current model's likelihood at that MAP is a
conditional ln Bayes factor, which orders the moves and drops those that fit no better even where their state is
best placed; its MAP is where the full fit starts.
"""

from __future__ import annotations

import copy
from typing import NamedTuple

import numpy as np

from ..likelihood.posterior import Target
from ..model.priors import JointPrior
from ..selection.spec import CandidateSpec


class Conditional(NamedTuple):
    """A state move's candidate with the current model's parameters held at ``known`` (its MAP): its ``new``
    parameters are the only ones sampled. The move's own kernel evaluates it, the one its full fits use next;
    holding the values in the spec instead would compile a kernel for each round's MAP."""

    cand: CandidateSpec
    known: dict
    new: list

    def target(self, data):
        """The posterior of the ``new`` parameters on ``data`` (:class:`Held`)."""
        from ..likelihood.posterior import ModelPosterior

        c = self.cand
        return Held(ModelPosterior(c.model_spec(), dict(c.priors), data, c.substeps), self.known, self.new)


class Held(Target):
    """``full`` (a target) over ``new`` alone, every other parameter held at its value in ``known``; the prior is
    ``full``'s on the ``new`` parameters."""

    def __init__(self, full, known: dict, new: list):
        self.full, self.names = full, list(new)
        self.prior = JointPrior(self.names, {n: full.prior.priors[full.names.index(n)] for n in new})
        self._x = np.array([float(known[n]) if n not in new else np.nan for n in full.names])
        self._at = np.array([full.names.index(n) for n in new], dtype=int)

    def loglik(self, x: np.ndarray) -> float:
        z = self._x.copy()
        z[self._at] = x
        return self.full.loglik(z)

    def window(self, n: int | None) -> "Held":
        out = copy.copy(self)
        out.full = self.full.window(n)
        return out


def conditional(cand: CandidateSpec, known: dict) -> Conditional | None:
    """``cand`` with every free parameter ``known`` names (the current model's MAP) held there and the new state's
    own, the free parameters it does not name, sampled alone (:class:`Conditional`); None when the move has none or
    when it selects terms by ARD (a lag). A parameter ``cand`` fixes (a term dropped earlier, 0) stays fixed."""
    free = cand.model_spec().free_parameters
    new = [n for n in free if n not in known]
    if cand.ard or not new:
        return None
    return Conditional(cand, {n: float(known[n]) for n in free if n not in new}, new)


SCREEN_STARTS = 4
"""Searches per state move in the screen: from the new parameters' prior medians and from dispersed prior points
(a mode's frequency or a Bouc-Wen shape has local optima a single search can stop in)."""
SCREEN_TOLERANCE = 0.01
"""Where a screen's search stops (nats, and prior scales in the parameters): Newton steps take it to the mode."""
SCREEN_MAXFEV = 300
"""Likelihood evaluations one screen search may take."""


def _screen_search(args) -> tuple[np.ndarray, float]:
    """One loose Nelder-Mead search of a screen (a picklable unit of work): ``(conditional, data, x0, window)``,
    on the record's first ``window`` samples."""
    from ..sampling.starts import initial_scale, local_mode

    c, data, x0, window = args
    target = c.target(data).window(window)
    return local_mode(target, x0, initial_scale(target.prior), SCREEN_MAXFEV, xatol=SCREEN_TOLERANCE,
                      fatol=SCREEN_TOLERANCE, passes=1)


def _screen_evidence(args) -> tuple[float, dict]:
    """A screen's Laplace evidence and MAP from its best search's point ``x0`` (Newton steps on the whole record,
    with the curvature of its first ``window`` samples until the record's mode): ``(conditional, data, x0,
    window)``."""
    from ..evidence.laplace import laplace
    from ..sampling.starts import initial_scale

    c, data, x0, window = args
    target = c.target(data)
    ev, x, _ = laplace(target, x0, initial_scale(target.prior), warm=True, search=target.window(window))
    return ev.log_evidence, dict(zip(target.names, map(float, x)))


def screen(ctx, cands: list[Conditional], data, seed: int, window: int | None = None) -> list[tuple[float, dict]]:
    """Each of ``cands`` (from :func:`conditional`) screened: its Laplace evidence and MAP from the best of
    :data:`SCREEN_STARTS` loose Nelder-Mead searches (all of them one batch on the loop's pool ``ctx.mapper``, on
    the record's first ``window`` samples: they only place the Newton steps) polished by Newton steps on the
    whole record."""
    from ..sampling.starts import initial_points

    rng = np.random.default_rng(seed)
    starts = []
    for c in cands:
        prior = JointPrior(c.new, {n: c.cand.priors[n] for n in c.new})
        median = [p.quantile(0.5) if p.kind != "ard" else 0.0 for p in prior.priors]
        starts.append([np.asarray(median, float), *initial_points(prior, SCREEN_STARTS - 1, rng)])
    found = ctx.mapper(_screen_search, [(c, data, x, window) for c, xs in zip(cands, starts) for x in xs])
    best = [max(found[k * SCREEN_STARTS:(k + 1) * SCREEN_STARTS], key=lambda r: r[1])[0] for k in range(len(cands))]
    return ctx.mapper(_screen_evidence, [(c, data, x, window) for c, x in zip(cands, best)])
