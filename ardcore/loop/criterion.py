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
  when the evidence supports it *and* it free-runs better held out: the blocks' typical relative change (the
  mean of their log error ratios, :func:`change`) better by more than :data:`FREE_RUN_TOLERANCE`, the loudest
  block (where a stand-in must extrapolate) no worse (:func:`improves`);
* a move that **removes** (an earlier effect a later one made redundant, a declared term an effect replaced)
  is taken when the evidence prefers the smaller model and it free-runs no worse held out
  (:func:`no_worse`);
* of several moves that improve, one that another free-runs better on every block is out, a noise level is out
  beside a move of the dynamics, the survivors together are out unless they free-run better than each alone;
  between the rest the blocks disagree and the evidence picks (:func:`pick`);
* a measurement-noise level changes what the filter trusts, not the dynamics: it must free-run no worse;
* a state the model lacks (a lag, a store, a hysteresis) that the criterion would take displaces the terms'
  move only when it free-runs better on every block, else the terms, the cheaper change, go first
  (:func:`contest`);
* the loop **stops** when no move the evidence supports improves the score.

The evidence proposes, the held-out free run decides: a stand-in that the evidence supports but that
extrapolates badly is never taken, so nothing needs to be withdrawn at the end. The round's moves are made by
:func:`_moves` (each survivor of the confirmations alone, the survivors fitted together when the evidence
prefers them so, the declared laws in another form) and :func:`decide` takes one; what the evidence supported
and the criterion refused is recorded in the round, every round's judgement in ``report["held_out"]``
(:func:`held_out_record`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..errors import FitError
from .checks import joint_fit, split_stability
from .config import DiagnoseConfig, LoopContext
from .confirm import Fit
from .freerun import fitted
from .verdict import LoopRound
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


FLOOR = 0.05
"""A block error below this share of the current model's largest counts as that share: a ratio between two
near-perfect blocks (a limit cycle's amplitude right to 0.1 %) is noise, not a gain."""


def change(new: Score, cur: Score) -> float:
    """The mean over the blocks of ln(new error / current error), each error floored at :data:`FLOOR` x the
    current model's largest: the typical relative change of the free run held out, every block weighing alike
    whatever its scale (an RMS over the blocks lets the block with the largest error, a start whose unseen
    state the filter has had 50 samples to find, outweigh the two others)."""
    floor = FLOOR * max(cur.errors.values())
    return float(np.mean([math.log(max(new.errors[b], floor) / max(cur.errors[b], floor)) for b in cur.errors]))


def improves(new: Score, cur: Score, tol: float = FREE_RUN_TOLERANCE) -> bool:
    """Whether ``new`` free-runs better than ``cur`` held out: the blocks' typical relative change
    (:func:`change`) better by more than ``tol``, and the loudest block no worse by more than ``tol``. The loudest
    stretch is where a stand-in fitted to smaller motions must extrapolate, and what extrapolates badly is
    worse there first; any other single block does not veto, its error carrying the noise of what happened in
    it (a limit cycle's amplitude wanders with the process noise; a record's start, what the filter finds of an
    unmeasured state in 50 samples). A model without a score never improves; any finite score improves on a
    model without one (a current model that diverges everywhere)."""
    if not new.errors or not math.isfinite(new.overall):
        return False
    if not cur.errors or not math.isfinite(cur.overall):
        return True
    if set(new.errors) != set(cur.errors):  # scored on other blocks: the totals alone compare
        return new.overall * (1 + tol) < cur.overall
    loud = new.errors.get(LOUDEST, 0.0) <= cur.errors.get(LOUDEST, math.inf) * (1 + tol)
    return loud and change(new, cur) < -math.log1p(tol)


LOUDEST = "loudest"
"""The held-out block a move may not make worse (:data:`~.simulation_fit.HELD_OUT_BLOCKS`)."""


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
        self._pending: dict[int, tuple] = {}  # id(row) -> (row, Future): scores started by :meth:`prefetch`

    def _task(self, f) -> tuple:
        fspec, phi = fitted(f.cand, f.row)
        return fspec, phi, f.data, f.cand.substeps, self.settings

    def prefetch(self, fits: list) -> None:
        """Start scoring ``fits`` on the pool now, for :meth:`scores` to collect: the round's moves are scored while
        this process fits the survivors together. Nothing is started on a pool that runs tasks in this process."""
        submit = getattr(self.mapper, "submit", None)
        if submit is None:
            return
        for f in fits:
            if id(f.row) not in self._kept and id(f.row) not in self._pending:
                self._pending[id(f.row)] = (f.row, submit(held_out_task, self._task(f)))

    def scores(self, fits: list) -> list[Score]:
        """The held-out score of each :class:`~.confirm.Fit` (its structure with pruned terms fixed, refitted
        from its posterior mean)."""
        todo = list({id(f.row): f for f in fits if id(f.row) not in self._kept}.values())
        fresh = [f for f in todo if id(f.row) not in self._pending]
        computed = dict(zip(map(id, (f.row for f in fresh)),
                            self.mapper(held_out_task, [self._task(f) for f in fresh]) if fresh else []))
        for f in todo:
            got = computed[id(f.row)] if id(f.row) in computed else self._pending.pop(id(f.row))[1].result()
            if isinstance(got, HeldOut):
                errs = {b: (float(e) if math.isfinite(e) else INF) for b, e in got.errors.items()}
                self._kept[id(f.row)] = (f.row, Score(errs, got))
            else:  # too short to hold a block out (None), or the refit failed (its message)
                self._kept[id(f.row)] = (f.row, Score({}, None, got))
        return [self._kept[id(f.row)][1] for f in fits]

    def score(self, fit) -> Score:
        """:meth:`scores` of one fit."""
        return self.scores([fit])[0]

    def refuses_removal(self, current, smaller) -> str | None:
        """Why the loop may not drop a term from ``current`` (a fit) although the evidence prefers ``smaller``
        (the fit without it), or None: the smaller model free-runs worse held out (:func:`no_worse`)."""
        now, without = self.scores([current, smaller])
        if no_worse(without, now):
            return None
        return f"without it the model free-runs worse held out ({describe(without)} against {describe(now)})"

    def alternative(self, current, fits: list, names: list[str] | None = None) -> tuple[int, list[Score]]:
        """Which of ``fits``, alternatives for one change of ``current`` (a declared law in each of its forms, all
        supported by the evidence), the held-out free run prefers, and their scores: :func:`pick` among those
        that improve on ``current``; when none does, the one whose blocks change least for the worse
        (:func:`change`), for the criterion to judge beside the round's other moves. The forms of a law are often
        within a few nats of each other where the law is wrong, and which of them the evidence ranks first
        then turns on a fit's last digits (on the real tanks a knee or a power law of the upper outflow). With
        ``names`` (one per fit) each score is said."""
        got = self.scores([current] + list(fits))
        cur, alts = got[0], got[1:]
        k = pick(cur, alts, [False] * len(fits), [f.row.log_evidence for f in fits])
        if k is None:
            finite = [i for i, s in enumerate(alts) if s.errors and math.isfinite(s.overall)]
            k = (min(finite, key=lambda i: change(alts[i], cur)) if finite and cur.errors and math.isfinite(cur.overall)
                 else max(range(len(fits)), key=lambda i: fits[i].row.log_evidence))
        for i, (name, sc) in enumerate(zip(names or (), alts)):
            self.say(f"  held out: {name}: {describe(sc)}" + (" (taken)" if i == k else ""))
        return k, alts

    def choose(self, current, moves: list) -> tuple[int | None, list[Score]]:
        """Which of ``moves`` (:class:`Move` each, supported by the evidence) the loop takes over ``current`` (a
        fit), and every move's score (:func:`pick` on their held-out scores)."""
        if not moves:
            return None, []
        got = self.scores([current] + [m.fit for m in moves])
        parts = [[j for j, o in enumerate(moves) if j != i and m.holds(o)] for i, m in enumerate(moves)]
        return pick(got[0], got[1:], [m.nuisance for m in moves], [m.fit.row.log_evidence for m in moves],
                    parts), got[1:]


def pick(cur: Score, scores: list[Score], nuisance: list[bool], log_evidence: list[float],
         parts: list[list[int]] | None = None) -> int | None:
    """The move the held-out scores take over the current model's ``cur``, or None.

    A move qualifies when it :func:`improves` on the current model, a nuisance (a measurement-noise level, which
    changes what the filter trusts and not the dynamics) when it is :func:`no_worse`. Of those that qualify:

    * one that another free-runs better on every block (:func:`dominates`) is out;
    * a nuisance is out when a move of the dynamics qualifies: the one free-runs better, the other only no worse,
      and the evidence cannot weigh them (it judges one-step prediction, where a noise level gains hundreds of
      nats; it goes in next round if it still free-runs no worse);
    * a move that holds another qualifying one (``parts[i]``: the survivors fitted together hold each alone) is
      out unless it :func:`improves` on it: what it adds must free-run better, as every addition must.

    Between the rest the blocks disagree and the evidence decides (the highest ln Z, its Occam factor charging
    each its parameters). On a record too short to hold a block out, the move with the highest evidence."""
    ok = list(range(len(scores)))
    if cur.errors or cur.failed is not None:  # else too short to hold a block out: the evidence alone decides
        ok = [i for i in ok if (no_worse if nuisance[i] else improves)(scores[i], cur)]
    front = [i for i in ok if not any(dominates(scores[j], scores[i]) for j in ok if j != i)]
    if any(not nuisance[i] for i in front):
        front = [i for i in front if not nuisance[i]]
    if parts is not None:
        front = [i for i in front if all(improves(scores[i], scores[j]) for j in parts[i] if j in ok)]
    if not front:
        return None
    return max(front, key=lambda i: log_evidence[i])


def dominates(a: Score, b: Score, tol: float = FREE_RUN_TOLERANCE) -> bool:
    """Whether ``a`` free-runs better than ``b`` on every held-out block, by more than ``tol`` on each."""
    return bool(a.errors) and set(a.errors) == set(b.errors) and all(
        a.errors[k] * (1 + tol) < b.errors[k] for k in a.errors)


def describe(score: Score) -> str:
    """``start 0.12, end 0.31, loudest 0.40`` (or why there is no score)."""
    if not score.errors:
        return f"no held-out score ({score.failed or 'the record is too short to hold a block out'})"
    return ", ".join(f"{b} {e:.4g}" for b, e in score.errors.items())


# --------------------------------------------------------------------------- the round's move


def stable(ctx: LoopContext, survivors: list) -> list:
    """The survivors whose coefficients agree over the two halves of the record (:func:`split_stability`; a
    noise level is not checked: it is a nuisance that may drift over a record)."""
    config = ctx.config
    if config.split_z is None:
        return survivors
    for c in survivors:
        if c.fitted_effect.where != "noise":
            c.stability = split_stability(ctx.spec, c, config, ctx.say, ctx.mapper)
            c.survives = c.stability["stable"]
    return [c for c in survivors if (c.stability or {}).get("stable", True) and c.survives]


@dataclass
class Move:
    """A change of the model the evidence supports, for the criterion to judge: ``kind`` "add" (the
    confirmations ``chosen``, fitted together in ``fit`` when more than one) or "replace" (declared laws in
    another form, ``fit``); ``name`` says what it is."""

    kind: str
    fit: Fit
    name: str
    chosen: list = field(default_factory=list)

    def holds(self, other: "Move") -> bool:
        """Whether this move adds everything ``other`` adds and more (the survivors together hold each alone)."""
        mine = {id(c) for c in self.chosen}
        return bool(other.chosen) and len(mine) > len(other.chosen) and all(id(c) in mine for c in other.chosen)

    @property
    def nuisance(self) -> bool:
        """A measurement-noise level: it changes what the filter trusts, not the dynamics, so it must free-run
        no worse held out rather than better; unless it was confirmed unscreened (``forced``, a quiet
        channel): the screen did not propose it, so it must free-run better as every addition must."""
        return self.kind == "add" and all(c.fitted_effect.where == "noise" and not c.forced for c in self.chosen)


def _moves(ctx: LoopContext, held: Fit, swap, survivors: list) -> list[Move]:
    """The round's moves: the declared laws in another form, each survivor alone and, when the evidence prefers
    them together by more than ``min_log_bf``, the survivors fitted together."""
    config, say = ctx.config, ctx.say
    moves = []
    if swap is not None:
        moves.append(Move("replace", swap[0], " and ".join(x["by"] for x in swap[1])))
    for c in survivors:
        moves.append(Move("add", c.fit, f"{c.effect} -> {c.target}", [c]))
    if config.joint and len([c for c in survivors if c.fitted_effect.where != "noise"]) > 1:
        # the survivors were screened as distinct: fitted together under ARD, which prunes any that the others
        # make redundant; a move when it beats the best single effect by more than min_log_bf
        try:
            j = joint_fit(ctx, held, survivors)
        except (FitError, ValueError, np.linalg.LinAlgError) as e:
            say(f"  the survivors together could not be fitted ({type(e).__name__})")
        else:
            if j.row.log_evidence > survivors[0].log_evidence + config.min_log_bf and j.row.degenerate() is None:
                moves.append(Move("add", j, " with ".join(c.effect for c in survivors), list(survivors)))
    return moves


def decide(ctx: LoopContext, crit: Criterion, held: Fit, swap, survivors: list, deferred: list,
            rnd: LoopRound) -> tuple[Move | None, dict]:
    """The move the loop takes this round, by the one criterion (:mod:`.criterion`), or None (the loop stops),
    and the round's record of what was judged.

    A measurement-noise level off by more than 2x goes in alone when it free-runs no worse held out (the noise
    rule: every other candidate was screened against a filter that took the misfit for process noise); if it
    does not, the candidates deferred behind it are judged now. Otherwise every move the evidence supports
    (:func:`_moves`) is scored held out and :meth:`Criterion.choose` takes one or none."""
    say, rec = ctx.say, rnd.record
    cur = crit.score(held)
    judged = {"round": rec["round"], "model": held.cand.label, "score": cur.to_json(), "moves": []}
    if deferred:
        noise = _moves(ctx, held, None, survivors[:1])
        k, (s,) = crit.choose(held, noise[:1])
        judged["moves"].append({"move": noise[0].name, "kind": "add", **s.to_json(), "taken": k == 0})
        if k == 0:
            say(f"  held out: {noise[0].name} free-runs no worse ({describe(s)} against {describe(cur)}): it goes in "
                "first")
            return noise[0], judged
        say(f"  held out: {noise[0].name} free-runs worse ({describe(s)} against {describe(cur)}): not added; "
            + ", ".join(c.effect for c in deferred) + " judged now")
        refuse(rec, noise[0], s)
        survivors = stable(ctx, deferred)
    # the single moves are scored on the pool while this process fits the survivors together (_moves)
    crit.prefetch([held] + ([swap[0]] if swap is not None else []) + [c.fit for c in survivors])
    moves = _moves(ctx, held, swap, survivors)
    if not moves:
        return None, judged
    k, scores = crit.choose(held, moves)
    say(f"  held out: the model: {describe(cur)}")
    for i, (m, s) in enumerate(zip(moves, scores)):
        judged["moves"].append({"move": m.name, "kind": m.kind, **s.to_json(), "taken": i == k})
        say(f"  held out: {m.name}: {describe(s)}" + (" (taken)" if i == k else ""))
        if i != k:
            refuse(rec, m, s)
    if k is None:
        say(f"  nothing the evidence supports free-runs better held out than the model ({describe(cur)})")
        rec["verdict"] = (rec.get("verdict") or "") + ("; " if rec.get("verdict") else "") + (
            "supported by the evidence but free-running no better on held-out blocks of the estimation record "
            "(each left out of a refit): " + ", ".join(m.name for m in moves))
    return (moves[k] if k is not None else None), judged


def contest(ctx: LoopContext, crit: Criterion, held: Fit, terms: tuple, states, rnd: LoopRound,
            judged: dict) -> tuple[Move | None, object]:
    """The round's move and its swap once the states have competed with the terms' move: ``terms`` is
    ``(move, swap)``, the move :func:`decide` took from the terms (or None) and the declared laws in another form
    it may be.

    ``states`` yields the state moves in order (each a ``swap`` tuple, fitted on demand); each is judged by
    :func:`decide` and the first the criterion would take competes: it displaces the terms' move only when it
    free-runs better on every held-out block (:func:`dominates`), else the terms go first, as they are the
    cheaper change. The loser is recorded as refused. A state the criterion refuses does not hide the next."""
    move, swap = terms
    for extra in states:
        found, more = decide(ctx, crit, held, extra, [], [], rnd)
        judged["moves"] += more["moves"]
        if found is None:
            continue
        state_wins = move is None or dominates(crit.score(found.fit), crit.score(move.fit))
        if move is not None:
            loser = move if state_wins else found
            ctx.say(f"  held out: {found.name if state_wins else move.name} is taken over {loser.name}")
            for j in judged["moves"]:
                if j["move"] == loser.name:
                    j["taken"] = False
            refuse(rnd.record, loser, crit.score(loser.fit))
        return (found, extra) if state_wins else (move, swap)
    return move, swap


def refuse(rec: dict, move: Move, score) -> None:
    """Record in the round that ``move``, which the evidence supports, was not taken by the criterion."""
    for c in move.chosen or [None]:
        rec.setdefault("refused", []).append(
            {"effect": c.effect if c is not None else move.name, "target": c.target if c is not None else "",
             "kind": move.kind, "round": rec["round"],
             "log_bayes_factor": c.log_bayes_factor if c is not None else None, "held_out": score.to_json()})


def held_out_record(config: DiagnoseConfig, judged: list[dict], final) -> dict:
    """``report["held_out"]``: each round's model judged on held-out blocks, the moves of each round, and the
    blocks of the model reported (its band is calibrated on them)."""
    models = [j["score"]["blocks"] for j in judged]
    overall = [j["score"]["overall"] for j in judged]
    if not models or final.to_json()["blocks"] != models[-1]:  # the model reported, unless the last round's
        models.append(final.to_json()["blocks"])
        overall.append(final.overall)
    return {"share": config.simulation_held_out, "free_run": models, "overall": overall, "kept": len(models) - 1,
            "moves": judged,
            "rule": f"a move is taken when the evidence supports it and its model free-runs the held-out blocks "
                    f"better (their mean log error ratio by more than {100 * FREE_RUN_TOLERANCE:g} %, the loudest no "
                    "worse); of "
                    "several, the one with the highest evidence among those no other free-runs better on every block; "
                    "the loop stops when no move does",
            "blocks": {b: list(v) for b, v in final.held.blocks.items()} if final.held else None}
