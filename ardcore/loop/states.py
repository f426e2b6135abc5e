"""States the model lacks: a declared quantity or a state through a lag, a hysteresis, a sensor's or an actuator's
dynamics, a second store, a second mode, a relaxation, a vibration the sensor picks up.

The loop's other moves add or reshape terms in the equations of the states the user declared. Many real
omissions are a state of their own. Nine families are offered, each a full fit judged like a law replacement
(:mod:`.replace`): its ln Bayes factor against the current model must exceed ``config.min_log_bf`` plus ln of
the number of candidates tried and its fit must be a result, then the loop's held-out criterion judges it. The
hysteresis, the sensor, the actuator, the store, the mode, the pickup and the transfer lag are screened first
(:func:`screened_states`): only those that fit better with the current model held at its MAP are fitted in full
(:func:`_screened_picks`), a relaxation beside a mode (:data:`UNSCREENED`). A lag and a transfer lag (a state read
through a lag by another's equation) are offered every round, beside the laws, whose stand-ins would take them up
first; the others only when the loop would stop (the term families left structure they cannot take up).

The families and what each adds to a declaration are :mod:`ardcore.effects.states`. Priors: a lag's rate ``b``
lognormal at the record's dominant angular frequency, a tenth to ten times it at +-2 sd (a sensor's or an
actuator's once to a hundred times: it is faster than what it measures or drives); its ``k`` normal around 0
at the size that makes ``k s'`` as large as ``b D``; the law's coefficients keep their prior's width centred on
zero (a lag turns the law's phase, so a sign chosen for the quasi-steady reading no longer binds) and its ARD
terms are selected again.
A hysteresis' ``beta`` lognormal at the inverse of the displacement's spread, ``gamma`` normal around 0 at that
size, ``k`` normal around 0 at the size of the velocity equation's own drift over the displacement. A store's
``b`` as a lag's, its ``k`` normal around 0 at the size of its state's own drift over that state's spread (a
relaxation's as a store's, on the velocity). A mode's
``w`` lognormal over a tenth to ten times the record's dominant frequency, ``zeta`` lognormal from 0.5 % to 50 %,
``mu`` normal around 0 at 1 (an effect's coefficient, taken only when its 99 % interval excludes 0). A pickup is
offered only for a channel measuring an oscillator's position whose innovations hold a line that is not a
harmonic of the record's own oscillation (:func:`lines`): its ``w`` lognormal at that line, 0.8 to 1.25 times it
at +-2 sd, ``zeta`` as a mode's, the level ``s`` lognormal at the level that makes the vibration a tenth of the
measurement's spread (with ``zeta`` 5 %), 30 times less to 30 times more at +-2 sd. Though it changes what the
filter trusts and not the dynamics, it is taken, as any addition, only when it free-runs better held out: a
measurement filtered before it was sampled (the reference problem's anti-aliasing filter) holds coloured noise that
a pickup takes up by tens of nats, and there it free-runs worse.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import sympy as sp

from ..effects.base import declared_names, short_name
from ..effects.states import (EXCHANGES, READINGS, SECOND_ORDER, Lag, actuators, hystereses, lag_spec, lags, modes,
                              names_of, new_states, pickups, relaxations, sensors, stores, transfers)
from ..likelihood.ekf import compile_model
from ..model.declaration import ModelSpec
from ..model.expr import parse_expression
from ..model.priors import LogNormal, Normal, Uniform
from ..selection.spec import CandidateSpec
from .confirm import Fit, essential_from_row

RATE_SPAN = 10.0
"""A lag's rate prior spans the record's dominant angular frequency divided and multiplied by this at +-2 sd."""


def dominant_rate(y: np.ndarray, dt: float) -> float:
    """The angular frequency of the largest peak of ``y``'s periodogram (its mean removed); for a record with
    no peak above the lowest frequency, that lowest frequency (the record's own time scale)."""
    y = np.asarray(y, float)
    y = y[np.isfinite(y)] - np.nanmean(y)
    p = np.abs(np.fft.rfft(y * np.hanning(y.size))) ** 2
    f = np.fft.rfftfreq(y.size, dt)
    j = 1 + int(np.argmax(p[1:])) if p.size > 1 else 0
    return 2 * math.pi * float(f[max(j, 1)] if f.size > 1 else 1.0 / (dt * max(y.size, 1)))


def signal_values(spec: ModelSpec, phi: dict, text: str, states: np.ndarray, columns: dict) -> np.ndarray:
    """``text`` (an expression of ``spec``, derived quantities allowed) along the filtered ``states``."""
    names = declared_names(spec)
    e = parse_expression(text, names)
    derived = {sp.Symbol(d, real=True): parse_expression(t, names) for d, t in spec.derived.items()}
    for _ in range(len(derived) + 1):
        e = e.subs(derived)
    values = {**spec.constants, **spec.fixed, **phi}
    e = e.subs({sp.Symbol(n, real=True): v for n, v in values.items()})
    args = [sp.Symbol(n, real=True) for n in (*spec.states, *spec.inputs)]
    f = sp.lambdify(args, e, modules="numpy")
    out = f(*states.T, *[np.asarray(columns[u], float) for u in spec.inputs])
    return np.asarray(out, dtype=float) * np.ones(states.shape[0])


def _centred(prior):
    """A bounded uniform prior on one side of zero widened to both (a lag turns the law's phase)."""
    if isinstance(prior, Uniform) and (prior.low >= 0 or prior.high <= 0):
        m = max(abs(prior.low), abs(prior.high))
        return Uniform(low=-m, high=m)
    return prior


def _lognormal(median: float, span: float) -> LogNormal:
    """Lognormal at ``median`` whose +-2 sd of the log span ``median / span`` to ``median * span``."""
    return LogNormal.spanning(median, median / span, median * span)


class Along(NamedTuple):
    """The current model along the record, what every state move's priors are scaled from: its fitted spec and
    posterior mean, its filtered states, the record's dominant angular frequency and, per observed column, the
    angular frequency of its innovations' line (:func:`lines`)."""

    fspec: ModelSpec
    phi: dict
    states: np.ndarray
    rate: float
    lines: dict = {}


def along(current: Fit, lines: dict | None = None) -> Along:
    """:class:`Along` for the current model (one filter pass, shared by every move offered)."""
    from .freerun import fitted

    fspec, phi = fitted(current.cand, current.row)
    states = compile_model(fspec).filter(phi, current.data, current.cand.substeps).filtered
    y = np.asarray(current.data.columns[fspec.observed_columns[0]], float)
    t = np.asarray(current.data.t, float)
    return Along(fspec, phi, states, dominant_rate(y, float(np.median(np.diff(t)))), dict(lines or {}))


def lines(tests: dict) -> dict:
    """Per observed column of the residual ``tests`` (:func:`~.residuals.residual_tests` of each), the angular
    frequency of the strongest spectral peak of its innovations that is not a harmonic of the record's own
    oscillation: a line a pickup may be (:func:`~ardcore.effects.states.pickups`); columns without one are left
    out."""
    out = {}
    for col, t in tests.items():
        top = next((p for p in t["spectrum"]["peaks"] if not p.get("harmonic")), None)
        if top is not None and top["f"] > 0:
            out[col] = 2 * math.pi * float(top["f"])
    return out


def lag_candidate(current: Fit, lag: Lag, at: Along | None = None) -> CandidateSpec | None:
    """The current model with the state move ``lag`` (:func:`lag_spec`) as a candidate with its priors (module
    docstring), scaled from ``at`` (default: :func:`along` the current model); None when the record gives them
    no scale."""
    cand = current.cand
    at = at or along(current)
    fspec, phi, states, rate = at.fspec, at.phi, at.states, at.rate
    cols = current.data.columns
    target = lag.target if lag.kind not in READINGS else None
    d = signal_values(fspec, phi, lag.term, states, cols)
    acc = signal_values(fspec, phi, fspec.drift[target], states, cols) if target else d
    sd_d, sd_acc = float(np.nanstd(d)), float(np.nanstd(acc))
    if not all(np.isfinite(x) and x > 0 for x in (rate, sd_d, sd_acc)):
        return None
    ms = cand.model_spec()
    priors, fixed = essential_from_row(cand, current.row)
    new, ard = names_of(lag), []
    if lag.kind == "hysteresis":
        spec = lag_spec(ms, lag, (0.0, sd_d))
        _, k, beta, gamma = new
        priors[k] = Normal(mean=0.0, sd=sd_acc / sd_d)
        priors[beta] = _lognormal(1.0 / sd_d, RATE_SPAN)
        priors[gamma] = Normal(mean=0.0, sd=1.0 / sd_d)
    elif lag.kind == "mode":
        spec = lag_spec(ms, lag, (float(d[0]), sd_d))
        _, _, w, zeta, mu = new
        priors[w] = _lognormal(rate, RATE_SPAN)
        priors[zeta] = LogNormal.spanning(0.05, 0.005, 0.5)
        priors[mu] = Normal(mean=0.0, sd=1.0)
    elif lag.kind == "pickup":
        w0 = at.lines.get(lag.target)
        if w0 is None:
            return None
        p, dp, w, zeta, level = new
        sd_p = 0.1 * sd_d  # the vibration's stationary sd is s / sqrt(4 zeta w^3)
        spec = lag_spec(ms, lag, (0.0, sd_p, sd_p * w0))
        priors[w] = LogNormal.spanning(w0, w0 / 1.25, w0 * 1.25)
        priors[zeta] = LogNormal.spanning(0.05, 0.005, 0.5)
        priors[level] = _lognormal(sd_p * math.sqrt(4 * 0.05 * w0 ** 3), 30.0)
    elif lag.kind == "transfer":
        # the lagged state starts where the state it follows does; its rate is a lag's
        spec = lag_spec(ms, lag, (float(d[0]), sd_d))
        priors[new[1]] = _lognormal(rate, RATE_SPAN)
    elif lag.kind in EXCHANGES:
        # the store starts where its state does, as uncertain as that state's spread; its rate is a lag's, its
        # exchange as large as the state's own drift over its spread (a hysteresis' coupling)
        spec = lag_spec(ms, lag, (float(d[0]), sd_d))
        _, b, k = new
        priors[b] = _lognormal(rate, RATE_SPAN)
        priors[k] = Normal(mean=0.0, sd=sd_acc / sd_d)
    elif lag.kind in ("sensor", "actuator"):
        # a sensor starts at its first reading, an actuator at its first command
        y0 = float(np.asarray(cols[lag.target if lag.kind == "sensor" else lag.term], float)[0])
        spec = lag_spec(ms, lag, (y0 if np.isfinite(y0) else float(d[0]), 0.1 * sd_d))
        priors[new[1]] = _lognormal(10.0 * rate, RATE_SPAN)
    else:
        spec = lag_spec(ms, lag, (float(d[0]), sd_d))
        _, b, k = new
        # the law's own terms: their essential priors centred, their ARD selected again
        own = {str(x) for x in parse_expression(ms.derived[lag.term], declared_names(spec)).free_symbols}
        ard = [a for a in cand.ard_names if a in own]
        priors = {n: (_centred(p) if n in own else p) for n, p in priors.items() if n not in ard}
        fixed = {n: v for n, v in fixed.items() if n not in ard}
        priors[b] = _lognormal(rate, RATE_SPAN)
        priors[k] = Normal(mean=0.0, sd=rate * sd_d / sd_acc)
    return CandidateSpec(model=spec, name=spec.name, priors=priors, fixed=fixed, ard=ard, substeps=cand.substeps)


def _live(text: str, spec: ModelSpec | None) -> str:
    """``text`` with the parameters ``spec`` fixes at 0 taken out (a stand-in the backward check dropped after the
    state read it)."""
    zeros = {sp.Symbol(n, real=True): 0 for n, v in (spec.fixed if spec is not None else {}).items() if v == 0}
    if not zeros:
        return text
    return str(parse_expression(text, declared_names(spec)).subs(zeros)).replace("Abs(", "abs(")


def state_summary(row, lag: Lag, spec: ModelSpec | None = None) -> dict:
    """The added state as the report shows it, from a fit's summary row: its name, kind and equation, what it
    acts on, its parameters (mean, sd, 99 % interval) and, for a lag or a sensor, its time constant ``1/b``.
    With ``spec`` (the model it belongs to), terms that model fixes at 0 are left out of the equation."""
    from .replace import shape_summary

    new = names_of(lag)
    z = new[0]
    lag = lag._replace(term=_live(lag.term, spec))
    if lag.kind == "hysteresis":
        v = lag.target
        eq = f"{z}' = {v} - {new[2]}*|{v}|*{z} - {new[3]}*{v}*|{z}|, {new[1]}*{z} in the {v} equation"
    elif lag.kind == "sensor":
        eq = f"{z}' = {new[1]}*({lag.term} - {z}), the measurement {lag.target} reads {z}"
    elif lag.kind == "actuator":
        eq = f"{z}' = {new[1]}*({lag.term} - {z}), the dynamics read {z} for {lag.term}"
    elif lag.kind == "transfer":
        eq = f"{z}' = {new[1]}*({lag.term} - {z}), the {lag.target} equation reads {z} for {lag.term}"
    elif lag.kind in EXCHANGES:
        x = lag.term
        eq = f"{z}' = {new[1]}*({x} - {z}), {new[2]}*({z} - {x}) in the {x} equation"
    elif lag.kind == "mode":
        q, dq, w, zeta, mu = new
        x, v = lag.term, lag.target
        f = f"{w}^2*({q} - {x}) + 2*{zeta}*{w}*({dq} - {v})"
        eq = f"{q}' = {dq}, {dq}' = -({f}), {mu}*({f}) in the {v} equation"
    elif lag.kind == "pickup":
        p, dp, w, zeta, level = new
        eq = (f"{p}' = {dp}, {dp}' = -{w}^2*{p} - 2*{zeta}*{w}*{dp} + {level}*noise, the measurement {lag.target} "
              f"reads {lag.term} + {p}")
    else:
        eq = f"{z}' = {new[1]}*({lag.term} - {z}) + {new[2]}*{lag.target}'"
    states = new_states(lag)
    out = {"name": z, "kind": lag.kind, "term": lag.term, "target": lag.target, "equation": eq,
           "states": list(states), "parameters": {n: shape_summary(row, n) for n in new[len(states):] if n in row.mean}}
    if lag.kind in ("lag", "sensor", "actuator", "store", "relaxation", "transfer") and new[1] in row.mean:
        r = out["parameters"][new[1]]
        out["time_constant"] = {"mean": 1.0 / r["mean"], "q005": 1.0 / r["q995"], "q995": 1.0 / r["q005"]}
    if lag.kind in SECOND_ORDER and new[2] in row.mean:
        r = out["parameters"][new[2]]
        out["frequency"] = {k: r[k] / (2 * math.pi) for k in ("mean", "q005", "q995")}
    return out


COUPLING = {"hysteresis": 1, "store": 2, "relaxation": 2, "mode": 4}
"""The parameter (its place in :func:`names_of`) through which a state of fixed form acts on the model: its
coupling, an effect's coefficient whose 99 % interval must exclude 0."""


def screened_states(ctx, current: Fit, offered: list, tasks: list) -> list[tuple[int, tuple]] | None:
    """The full fits the screen orders: ``(index into offered, fit task)`` by conditional ln BF, best first, each
    warm-started where its screen peaked; None when a move cannot be screened (a lag, whose law's terms ARD selects
    again: every lag is fitted in full).

    The screen fits each move's own parameters with the current model's held at its MAP (a search in one to
    three dimensions, not in all of them, :func:`~ardcore.screening.states.screen`): its ln Bayes factor against
    the current model's likelihood at that MAP is a conditional one. A move whose conditional ln BF is not
    positive does not fit the data better even where the new state is best placed, and is not fitted in full; the
    others are fitted in full both from the screen's values and from the prior (:func:`_better_start`)."""
    from ..screening.states import conditional, screen
    from .confirm import warm_with

    known = dict(zip(current.mr.sampler.names, np.asarray(current.mr.sampler.phi_star, float)))
    screened = [i for i, m in enumerate(offered) if m.kind not in UNSCREENED]
    if not screened:
        return []
    reduced = [conditional(tasks[i][0], known) if offered[i].kind != "lag" else None for i in screened]
    if any(r is None for r in reduced):
        return None
    cond = screen(ctx, reduced, current.data, ctx.spec.seed, ctx.config.search_window)
    base = current.row.goodness_of_fit
    order = []
    for i, r, (log_z, at) in zip(screened, reduced, cond):
        gain, new, move = log_z - base, r.new, offered[i]
        if not np.isfinite(gain):  # never a NaN said as a figure: the screen found no evidence to weigh
            ctx.say(f"  screened: {_a(move.kind)} {_where(move)}: no finite conditional evidence (the likelihood or "
                    "its curvature is not finite where the state fits best beside the current model), not fitted "
                    "in full")
            continue
        ctx.say(f"  screened: {_a(move.kind)} {_where(move)}: conditional ln BF {gain:.1f}"
                + ("" if gain > 0 else ", not fitted in full"))
        if gain > 0:
            cand, data, spec, _, posterior = tasks[i]
            order.append((gain, i, (cand, data, spec, warm_with(current.mr.sampler, new, [at[n] for n in new]),
                                    posterior)))
    return [(i, task) for _, i, task in sorted(order, key=lambda x: -x[0])]


SAME_MODE_NATS = 0.1
"""Two full fits of one move whose Laplace evidences differ by less than this reached the same mode."""


def _better_start(fits: list) -> tuple:
    """Of a move's full fit from its screened values and its fit from the prior (the search every full fit
    makes), the one with the higher evidence, the prior's on a tie (:data:`SAME_MODE_NATS`). A start at the screen's
    values, the current model's parameters where they were, can stop in a nearby mode below the one the searches
    from the prior find (a sensor on M1 with a measurement noise: 10 nats below), or find one they miss (a sensor on
    the square-root tanks, where the prior's searches end at a curvature that is not positive definite)."""
    (warm, wm), (cold, cm) = fits
    # degenerate(): None for a result (a finite evidence with a real error and a posterior that moved)
    if warm.degenerate() is None and (cold.degenerate() is not None
                                      or warm.log_evidence > cold.log_evidence + SAME_MODE_NATS):
        return warm, wm
    return cold, cm


def _where(lag: Lag) -> str:
    """Where a state move acts, as the progress lines say it: ``(h1 -> h2)``; a sensor or a pickup by the channel it
    reads (``(y)``): its term is the measurement's whole expression, which after a few rounds holds every
    measurement effect's scaled terms."""
    return f"({lag.target})" if lag.kind in READINGS else f"({lag.term} -> {lag.target})"


def _a(kind: str) -> str:
    """``kind`` with its article, as the progress lines say it."""
    return ("an " if kind[0] in "aeiou" else "a ") + kind


def _refused(lag: Lag, row, gain: float, need: float) -> str | None:
    """Why the state move ``lag`` fitted as ``row`` does not qualify (it gains no more than ``need`` nats, its
    fit is no result, or a coupled state's coupling may be 0), None when it does."""
    if not gain > need:
        return f"the best state, {_a(lag.kind)} {_where(lag)}: ln BF {gain:.1f}, needs {need:.1f}"
    why = row.degenerate()
    if why is not None:
        return f"{_a(lag.kind)} {_where(lag)}: {why}"
    if lag.kind in COUPLING:
        # a Bouc-Wen state or a second mode acts on the model only through its coupling: one whose 99 % interval
        # holds 0 changes nothing the data pin down (its shape then fits the noise), as an effect ARD would prune
        name = names_of(lag)[COUPLING[lag.kind]]
        c = state_summary(row, lag)["parameters"].get(name)
        if c is None or not (c["q005"] > 0 or c["q995"] < 0):
            return f"{_a(lag.kind)} {_where(lag)}: its coupling {name}'s 99 % interval holds 0"
    return None


def _taken(ctx, current: Fit, lag: Lag, task: tuple, fit: tuple, gain: float, need: float):
    """``(fit, [record], ln BF)`` of the state move ``lag`` fitted as ``fit`` when it qualifies
    (:func:`_refused`), else None (said why)."""
    row, mr = fit
    why = _refused(lag, row, gain, need)
    if why is not None:
        ctx.say("  " + why)
        return None
    state = state_summary(row, lag)
    ctx.say(f"  a state: {state['equation']} (ln BF {gain:.1f})")
    record = {"parameter": "", "term": lag.term, "target": lag.target, "by": f"the state {state['name']}",
              "form": lag.kind, "log_bayes_factor": float(gain), "state": state}
    return Fit(task[0], row, mr, current.data), [record], float(gain)


SWAPPED = {"sensor": ("actuator",), "actuator": ("sensor",), "mode": ("relaxation", "pickup"), "pickup": ("mode",)}
"""Moves the screen, which holds the current model where it was, cannot order. The lag at a model's output and the
lag at its input, which its linear part cannot tell apart (a linear system read through a lag is the same system
driven through it: on the validation set's ``actuator`` record the actuator screened at 66 nats against the
sensor's 292 and beat it in full by 140); a second mode and a relaxation (a massless mode on a spring and damper
is a relaxation, :data:`UNSCREENED`); a second mode and a pickup (a resonance in the measurement, which a mode
coupled to the dynamics imitates: on the reference problem with a sensor mode the mode screened at 74.6 nats and
the pickup at 72.3). When the screen's best move is one of these, its rivals are fitted beside it and the evidence
chooses."""

UNSCREENED = ("relaxation",)
"""Moves the screen cannot weigh, fitted in full only beside their :data:`SWAPPED` rival, from the prior. A
relaxation's exchange ``-k v`` is a damping, which the current model's damping held at its MAP had taken up: on the
``viscoelastic`` record it screened at -0.7 and beat every other move in full (ln BF 83 against the mode's 78).
Screened with that damping released, it cost a 10,000-sample round's states 2.5 times its terms (bench
``states_10k_ratio``, limit 2); a second mode, a mass on the same spring and damper, screens where it helps."""


LAG_KINDS = ("lag", "transfer")
"""The state families offered every round beside the laws: a lag of what an equation already reads, which the
term families' stand-ins would otherwise take up first."""

STATE_KINDS = ("hysteresis", "sensor", "actuator", "store", "mode", "relaxation", "pickup")
"""The state families offered every round that does not take a noise level alone, competing with the terms' move
(``diagnose``: a state that free-runs better on every held-out block displaces it)."""


def _screened_picks(ctx, current: Fit, offered: list, tasks: list, order: list, need: float):
    """The moves :func:`state_moves` offers of the screened ones (``order``, :func:`screened_states`), one at a time,
    as the criterion refuses them.

    The screen's best is fitted in full from its screened values and from the prior (:func:`_better_start`),
    side by side with its swapped rivals (:data:`SWAPPED`: one that screened positive from its screened values, one
    not screened, :data:`UNSCREENED`, from the prior); of those that qualify (:func:`_refused`) the one with the
    higher evidence comes first, then the others that qualify. Then the rest are fitted in the screen's order,
    each from both starts, and each that qualifies comes next: a fit is paid for only once the moves before it
    were refused."""
    from .confirm import fit_all

    if not order:
        return
    base = current.row.log_evidence
    head = [order[0]]
    for kind in SWAPPED.get(offered[order[0][0]].kind, ()):
        if kind in UNSCREENED:  # a rival the screen cannot weigh, from the prior
            head += [(i, tasks[i]) for i, m in enumerate(offered) if m.kind == kind][:1]
        else:  # a screened one, from its screened values
            head += [o for o in order[1:] if offered[o[0]].kind == kind][:1]
    got = fit_all(ctx.mapper, [head[0][1], tasks[head[0][0]], *(task for _, task in head[1:])])
    fits = [_better_start(got[:2]), *got[2:]]
    gains = [f[0].log_evidence - base if np.isfinite(f[0].log_evidence) else -math.inf for f in fits]
    if len(head) > 1:
        ctx.say("  fitted in full: " + ", ".join(f"{_a(offered[i].kind)} ln BF {g:.1f}"
                                                 for (i, _), g in zip(head, gains)))
    ok = [j for j in range(len(head)) if _refused(offered[head[j][0]], fits[j][0], gains[j], need) is None]
    if not ok:
        _taken(ctx, current, offered[head[0][0]], head[0][1], fits[0], gains[0], need)  # says why not
    done = set()
    for j in sorted(ok, key=lambda j: -gains[j]):
        i, task = head[j]
        done.add(i)
        yield _taken(ctx, current, offered[i], task, fits[j], gains[j], need)
    rival = {i: f for (i, _), f in zip(head[1:], fits[1:])}  # fitted from its screened values already
    for i, task in order[1:]:
        if i in done:
            continue
        # the rival's fit from the prior now; the others' from both starts
        fit = _better_start([rival[i], *fit_all(ctx.mapper, [tasks[i]])] if i in rival
                            else fit_all(ctx.mapper, [task, tasks[i]]))
        got = _taken(ctx, current, offered[i], task, fit, fit[0].log_evidence - base, need)
        if got is not None:
            yield got


def best_state(ctx, current: Fit, kinds: tuple = ("lag",), lines: dict | None = None):
    """The state move of ``kinds`` (module docstring) worth most, as ``(fit, [record], ln BF)`` like
    :func:`~.replace.best_laws`, or None: the first of :func:`state_moves`."""
    return next(state_moves(ctx, current, kinds, lines), None)


def state_moves(ctx, current: Fit, kinds: tuple = ("lag",), lines: dict | None = None):
    """The state moves of ``kinds`` (module docstring) that qualify, each as ``(fit, [record], ln BF)`` like
    :func:`~.replace.best_laws`, the one worth most first; the next is fitted only when asked for (the criterion
    refused the one before: a refused state must not hide the next, as a pickup that gained hundreds of nats and
    free-ran worse hid a second thermal store).

    A move qualifies when its ln Bayes factor against the current model exceeds ``config.min_log_bf`` plus ln of
    the number offered and its fit is a result (:func:`_taken`). Lags are fitted side by side on the loop's pool
    (a full ARD re-selection each, the law's terms selected again) and the best is judged. The other states are
    screened first (:func:`screened_states`) and fitted in full in the screen's order, a sensor's and an
    actuator's lag side by side (:func:`_screened_picks`). A round that takes one offers the others again. The
    record is a replacement's with the state (:func:`state_summary`). ``lines``: per observed column, its
    innovations' line (:func:`lines`), where a pickup is offered."""
    from .confirm import fit_all

    config, say = ctx.config, ctx.say
    ms = current.cand.model_spec()
    offer = {"lag": lags, "hysteresis": hystereses, "sensor": sensors, "actuator": actuators, "store": stores,
             "relaxation": relaxations, "transfer": transfers, "mode": modes, "pickup": pickups}
    offered, tasks = [], []
    moves = [m for kind in kinds for m in offer[kind](ms) if m.kind != "pickup" or m.target in (lines or {})]
    rivals = {k for m in moves for k in SWAPPED.get(m.kind, ())}
    moves = [m for m in moves if m.kind not in UNSCREENED or m.kind in rivals]  # fitted only beside a rival
    at = along(current, lines) if moves else None
    # the screened families' searches from the prior read the record's first config.search_window samples (a
    # lag's fit re-selects a law's terms, like the laws beside it, and reads the whole record)
    windowed = ctx.spec.model_copy(update={"sampler": ctx.spec.sampler.model_copy(
        update={"search_window": config.search_window})})
    for lag in moves:
        cand = lag_candidate(current, lag, at)
        if cand is not None:
            offered.append(lag)
            tasks.append((cand, current.data, ctx.spec if lag.kind == "lag" else windowed, None, config.posterior))
    if not tasks:
        return
    say("  a state: " + ", ".join(f"{x.kind} {_where(x)}" for x in offered))
    need = config.min_log_bf + math.log(len(tasks))
    order = screened_states(ctx, current, offered, tasks)
    if order is not None:
        yield from _screened_picks(ctx, current, offered, tasks, order, need)
        return
    fits = fit_all(ctx.mapper, tasks)  # lags: fits from the prior, their start searches spread over the pool
    gain = np.array([row.log_evidence - current.row.log_evidence for row, _ in fits], dtype=float)
    if not np.isfinite(gain).any():
        return
    # the lags are judged against the laws by their best alone (its ln BF), so the best one is the only one offered
    k = int(np.nanargmax(np.where(np.isfinite(gain), gain, -np.inf)))
    got = _taken(ctx, current, offered[k], tasks[k], fits[k], float(gain[k]), need)
    if got is not None:
        yield got
