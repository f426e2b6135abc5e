"""The loop's one criterion (docs/loop.md, "How the loop decides"): the free run on data the fit did not see.

The evidence and the innovations are the EKF's: they judge one-step predictions from a filtered state. On a
real record where the model is far off, the fitted process noise absorbs the model error, the innovations
look white and the evidence prefers what helps one-step prediction, while the free run, which is what a user
judges a model by, stays poor or gets worse. So every move of the loop (add an effect, replace a declared
law, drop a term, stop) is decided here, by one number computed in one place:

* a model's **held-out score** is the free-run RMS error on each of three blocks of the estimation record
  (its start, its end and its loudest stretch, each :data:`~.simulation_fit.HELD_OUT_BLOCKS` share), each
  from a refit of the structure with that block's observations left out
  (:func:`~.simulation_fit.held_out_free_runs`); a diverging free run scores infinity;
* a move that **adds** (an effect, a law in another form, the survivors of a round together) is taken only
  when the evidence supports it *and* it free-runs better held out: all blocks together better by more than
  :data:`FREE_RUN_TOLERANCE` (:func:`improves`);
* a move that **removes** (an earlier effect a later one made redundant, a declared term an effect replaced)
  is taken when the evidence prefers the smaller model and it free-runs no worse held out
  (:func:`no_worse`);
* of several moves that improve, the evidence picks (:meth:`Criterion.choose`): the criterion says whether a
  move is worth taking, the evidence which;
* a measurement-noise level changes what the filter trusts, not the dynamics: it must free-run no worse;
* the loop **stops** when no move the evidence supports improves the score.

The evidence proposes, the held-out free run decides: a stand-in that the evidence supports but that
extrapolates badly is never taken, so nothing needs to be withdrawn at the end.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .freerun import fitted
from .simulation_fit import HeldOut, SimulationSettings, held_out_task

INF = math.inf

FREE_RUN_TOLERANCE = 0.01
"""Relative change of a held-out free-run error that counts as none: a measurement-noise level or a term the data
barely pin moves a refit, and with it the free run, by less than this."""


@dataclass(frozen=True)
class Score:
    """A model's held-out score: per block its free-run RMS error (``errors``) and the refits behind them
    (``held``, None when the record is too short to hold a block out or every refit failed; ``failed`` says
    why)."""

    errors: dict
    held: HeldOut | None = None
    failed: str | None = None

    @property
    def overall(self) -> float:
        """The RMS over the blocks of their errors (infinite when any block diverged or nothing was scored)."""
        v = list(self.errors.values())
        return float(np.sqrt(np.mean(np.square(v)))) if v else INF

    def to_json(self) -> dict:
        out = {"blocks": {b: float(e) for b, e in self.errors.items()}, "overall": self.overall}
        if self.failed:
            out["failed"] = self.failed
        return out


def improves(new: Score, cur: Score, tol: float = FREE_RUN_TOLERANCE) -> bool:
    """Whether ``new`` free-runs better than ``cur`` held out: all blocks together (the RMS of their errors)
    better by more than ``tol`` (relative). One block alone does not veto: a block's error carries the noise
    of what happened in it (a limit cycle's amplitude wanders with the process noise), and the blocks together
    are the criterion. A model without a score never improves; any finite score improves on a model without
    one (a current model that diverges everywhere)."""
    if not new.errors or not math.isfinite(new.overall):
        return False
    if not cur.errors or not math.isfinite(cur.overall):
        return True
    return new.overall * (1 + tol) < cur.overall


def no_worse(new: Score, cur: Score, tol: float = FREE_RUN_TOLERANCE) -> bool:
    """Whether ``new`` (a smaller model) free-runs held out no worse than ``cur``: all blocks together within
    ``tol``. Without a score for the current model the smaller model's evidence alone decides."""
    if not cur.errors or not math.isfinite(cur.overall):
        return True
    return math.isfinite(new.overall) and new.overall <= cur.overall * (1 + tol)


class Criterion:
    """Held-out scores of the loop's models, computed side by side on the loop's pool and kept per fit (a model
    is scored once however many moves it is compared in).

    Parameters
    ----------
    config : DiagnoseConfig
        ``simulation_held_out`` (the share of each block) and ``init_samples`` (a free run's start).
    mapper : callable
        ``mapper(fn, tasks)``: the loop's pool.
    say : callable
        The progress line.
    """

    def __init__(self, config, mapper, say):
        self.settings = SimulationSettings(held_out=config.simulation_held_out, init_samples=config.init_samples)
        self.mapper, self.say = mapper, say
        self._kept: dict[int, tuple] = {}  # id(row) -> (row, score): the row is held so its id stays its own

    def scores(self, fits: list) -> list[Score]:
        """The held-out score of each :class:`~.confirm.Fit` (its structure with pruned terms fixed, refitted
        from its posterior mean)."""
        todo = [f for f in fits if id(f.row) not in self._kept]
        tasks = []
        for f in todo:
            fspec, phi = fitted(f.cand, f.row)
            tasks.append((fspec, phi, f.data, f.cand.substeps, self.settings))
        for f, got in zip(todo, self.mapper(held_out_task, tasks) if tasks else []):
            if isinstance(got, HeldOut):
                errs = {b: (float(e) if math.isfinite(e) else INF) for b, e in got.errors.items()}
                self._kept[id(f.row)] = (f.row, Score(errs, got))
            else:  # too short to hold a block out (None), or the refit failed (its message)
                self._kept[id(f.row)] = (f.row, Score({}, None, got))
        return [self._kept[id(f.row)][1] for f in fits]

    def score(self, fit) -> Score:
        """:meth:`scores` of one fit."""
        return self.scores([fit])[0]

    def choose(self, current, moves: list) -> tuple[int | None, list[Score]]:
        """Which of ``moves`` (``(fit, nuisance)`` each, supported by the evidence) the loop takes over
        ``current`` (a fit), and every move's score. A move qualifies when it :func:`improves` on the current
        model, a nuisance (a measurement-noise level, which changes what the filter trusts and not the
        dynamics) when it is :func:`no_worse`; of those that qualify the evidence picks (the highest ln Z: the
        criterion says whether a move is worth taking, the evidence which of several, its Occam factor charging
        each its parameters). None when none qualifies; on a record too short to hold a block out, the move
        with the highest evidence."""
        if not moves:
            return None, []
        got = self.scores([current] + [m[0] for m in moves])
        cur, sc = got[0], got[1:]
        ok = list(range(len(moves)))
        if cur.errors or cur.failed is not None:  # else too short to hold a block out: the evidence alone decides
            ok = [i for i, (s, m) in enumerate(zip(sc, moves)) if (no_worse if m[1] else improves)(s, cur)]
        if not ok:
            return None, sc
        return max(ok, key=lambda i: moves[i][0].row.log_evidence), sc


def describe(score: Score) -> str:
    """``start 0.12, end 0.31, loudest 0.40`` (or why there is no score)."""
    if not score.errors:
        return f"no held-out score ({score.failed or 'the record is too short to hold a block out'})"
    return ", ".join(f"{b} {e:.4g}" for b, e in score.errors.items())
