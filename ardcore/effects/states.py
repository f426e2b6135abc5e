"""The state families: what the loop adds when a model lacks a state, as changes to a declaration (the model
surgery; their priors, screen and choice are :mod:`ardcore.loop.states`).

**A lag**. A declared derived quantity ``D`` (a signal: it holds a state or an input) that enters one state's
equation and no observation or noise: that equation sees a new state instead::

    z' = b (D - z) + k s'        (s: the state whose equation D entered, s' its drift)

``b`` the lag's rate (1 / time constant), ``k`` the part of the state's own rate that feeds the lagged quantity
directly (the apparent mass of an unsteady moment: M2's ``c6 F``). A process noise declared on ``D`` (the
state's diffusion proportional to ``D``'s coefficient: M1's ``c3 sigma``) moves into the lag's equation. A
quantity already acting through a lag (a state ``s`` whose drift holds ``g (D - s)``, the rate ``g`` a
parameter: M2's ``B (P - CM)``) is not offered again.

**A hysteresis**. For an oscillator ``x' = v``, a Bouc-Wen state in the velocity's equation::

    v' = ... + k z,    z' = v - beta |v| z - gamma v |z|

(``z`` a displacement that saturates near ``1 / (beta + gamma)``).

**A sensor**. For a measured state, the sensor's own first-order dynamics: the measurement reads ``m``,
``m' = b (h - m)`` (``h`` the declared measurement expression).

**An actuator**. For an input ``u`` that drives the dynamics, the actuator's own first-order dynamics: every
drift equation reads ``a`` instead of ``u``, ``a' = b (u - a)`` (a valve, a motor, a heater that does not
follow its command at once).

**A second store**. For a first-order state ``x`` (a temperature, a level, a charge: not an oscillator's), a
second store exchanging with it (a second thermal mass, a tank or a capacitor it feeds and drains)::

    x' = ... + k (z - x),    z' = b (x - z)

(``b`` the store's rate, ``k`` the exchange's rate seen from ``x``).

**A relaxation**. For an oscillator ``x' = v``, a viscoelastic element (a Maxwell element: a spring and a damper
in series, a rubber mount, a lagged damping) acting on the velocity's equation, the same exchange as a store's::

    v' = ... + k (z - v),    z' = b (v - z)

(slow against ``b`` it is a damping ``-k v``, fast against it a stiffness ``k b x``: a damping and stiffness that
change with frequency).

**A transfer lag**. A first-order state ``s`` that another first-order state's equation ``t`` reads directly
reaches it through a lag: that equation reads ``z`` where it read ``s``, ``z' = b (s - z)`` (water falling from
one tank to the next through a pipe, heat crossing a wall).

**A second mode**. For an oscillator ``x' = v``, a mass on a spring and damper attached to it (a secondary
structure, a sloshing or a flexible part), two states ``q, dq``::

    q' = dq,   dq' = -f,   v' = ... + mu f,   f = w^2 (q - x) + 2 zeta w (dq - v)

(``w`` its angular frequency, ``zeta`` its damping ratio, ``mu`` the mass ratio that couples it back).

**A pickup**. For a measurement of an oscillator's position, a lightly damped vibration driven by noise that the
sensor reads on top of it (its mount's or a support's resonance, a sting's mode): coloured measurement noise, two
states ``p, dp`` the dynamics never see::

    y = h + p,   p' = dp,   dp' = -w^2 p - 2 zeta w dp + s xi

(``w`` its angular frequency, ``zeta`` its damping ratio, ``s`` the level of the noise that drives it).
"""

from __future__ import annotations

import re
from typing import NamedTuple

import sympy as sp

from .base import declared_names, oscillator_pairs, short_name, user_inputs
from ..model.declaration import ModelSpec
from ..model.expr import parse_expression


class Lag(NamedTuple):
    """A state move: ``kind`` "lag" (the derived quantity ``term`` of the ``target`` state's equation through a
    lag), "hysteresis" (a Bouc-Wen state of the oscillator whose position is ``term`` in the velocity ``target``'s
    equation), "sensor" (the measurement ``term`` of the observed column ``target`` read through a lag),
    "actuator" (the input ``term`` read through a lag by every drift equation, ``target`` the first state it
    drives), "store" (a second store exchanging with the first-order state ``term``, its equation ``target``),
    "relaxation" (a viscoelastic element exchanging with the velocity ``term`` in its own equation),
    "transfer" (the state ``term`` read through a lag by the equation of ``target``),
    "mode" (a second mode of the oscillator whose position is ``term``, coupled to its velocity
    ``target``) or "pickup" (a noise-driven vibration the measurement ``term`` of the observed column ``target``
    reads on top)."""

    term: str
    target: str
    kind: str = "lag"


def _uses(spec: ModelSpec) -> dict:
    """Derived quantity -> the names its expression holds, those of the derived quantities it uses included."""
    names, out = declared_names(spec), {}
    for d, text in spec.derived.items():
        sym = {str(s) for s in parse_expression(text, names).free_symbols}
        out[d] = sym.union(*(out[u] for u in sym if u in out))
    return out


def _mentions(spec: ModelSpec, text: str, term: str, uses: dict) -> bool:
    sym = {str(s) for s in parse_expression(text, declared_names(spec)).free_symbols}
    return term in sym or any(term in uses.get(u, ()) for u in sym)


def lags(spec: ModelSpec) -> list[Lag]:
    """The derived quantities a lag may be offered for (module docstring): in one state's drift, in no
    observation, diffusion or initial state, a signal (it holds a state or an input), not already acting through
    a lag."""
    uses, names, free = _uses(spec), declared_names(spec), set(spec.free_parameters)
    elsewhere = ([o.expr for o in spec.observations] + [o.noise_std for o in spec.observations]
                 + list(spec.diffusion.values()) + list(spec.initial_mean.values())
                 + list(spec.initial_std.values()))
    out = []
    signals = {*spec.states, *spec.inputs}
    for d in spec.derived:
        if not uses[d] & signals:
            continue  # a coefficient made of parameters, not a signal
        where = [s for s, text in spec.drift.items() if _mentions(spec, text, d, uses)]
        if len(where) != 1 or any(_mentions(spec, str(t), d, uses) for t in elsewhere):
            continue
        s = where[0]
        f = parse_expression(spec.drift[s], names)
        g = sp.diff(f, sp.Symbol(d, real=True))
        rates = {str(x) for x in g.free_symbols} & free
        if rates and not rates & {str(x) for x in (sp.diff(f, sp.Symbol(s, real=True)) + g).free_symbols}:
            continue  # the drift holds g (D - s): D already acts through a lag
        out.append(Lag(d, s))
    return out


def _oscillators(spec: ModelSpec) -> list[tuple[str, str]]:
    """The oscillators (position, velocity) of ``spec`` but those a second mode or a pickup added: a state of fixed
    form takes nothing more (a mode of a mode, or its hysteresis, is a basis expansion, not a missing effect)."""
    made = _made(spec)
    return [(x, v) for x, v in oscillator_pairs(spec) if x not in made]


def hystereses(spec: ModelSpec) -> list[Lag]:
    """A Bouc-Wen state for each oscillator (position, velocity) that has none yet."""
    return [Lag(x, v, "hysteresis") for x, v in _oscillators(spec) if names_of(Lag(x, v, "hysteresis"))[0]
            not in spec.states]


def modes(spec: ModelSpec) -> list[Lag]:
    """A second mode for each oscillator (position, velocity) that has none yet."""
    return [Lag(x, v, "mode") for x, v in _oscillators(spec) if names_of(Lag(x, v, "mode"))[0] not in spec.states]


def stores(spec: ModelSpec) -> list[Lag]:
    """A second store for each first-order state (none of an oscillator's, none a state family added: a store of
    a store is a basis expansion) that has none yet."""
    paired = {n for pair in oscillator_pairs(spec) for n in pair}
    made = _made(spec)
    return [Lag(x, x, "store") for x in spec.states if x not in paired and x not in made
            and names_of(Lag(x, x, "store"))[0] not in spec.states]


def transfers(spec: ModelSpec) -> list[Lag]:
    """A transfer lag for each first-order state that another first-order state's drift holds directly (a
    level in the next tank's inflow, a temperature in the next body's heat flow), neither state an oscillator's
    or one a family added, and not read through one yet. An oscillator's spring or damping read through a lag is
    no omitted state but another law, which its equation's terms take up."""
    names, made, out = declared_names(spec), _made(spec), []
    paired = {n for pair in oscillator_pairs(spec) for n in pair}
    first_order = [s for s in spec.states if s not in made and s not in paired]
    for t in first_order:
        sym = {str(x) for x in parse_expression(spec.drift[t], names).free_symbols}
        for s in first_order:
            if s != t and s in sym and names_of(Lag(s, t, "transfer"))[0] not in spec.states:
                out.append(Lag(s, t, "transfer"))
    return out


READINGS = ("sensor", "pickup")
"""The kinds that act on a measurement, not on a state's equation: their term is the observed channel's
expression, their target the channel."""

EXCHANGES = ("store", "relaxation")
"""The kinds that exchange with a state of the model, ``k (z - x)`` in its equation and ``z' = b (x - z)``: their
declaration, priors and report are one."""


def relaxations(spec: ModelSpec) -> list[Lag]:
    """A relaxation for each oscillator (position, velocity; none a mode added) that has none yet."""
    return [Lag(v, v, "relaxation") for _, v in _oscillators(spec)
            if names_of(Lag(v, v, "relaxation"))[0] not in spec.states]


def _made(spec: ModelSpec) -> set:
    """The states of ``spec`` a state family added (a lag, a sensor, a pickup, an actuator, a store, a relaxation,
    a hysteresis, a mode, a transfer lag), by their names."""
    moves = [Lag(d, d, "lag") for d in spec.derived]
    moves += [Lag(o.column, o.column, k) for o in spec.observations for k in READINGS]
    moves += [Lag(u, u, "actuator") for u in spec.inputs]
    moves += [Lag(x, x, k) for x in spec.states for k in ("store", "relaxation", "hysteresis", "mode")]
    moves += [Lag(x, t, "transfer") for x in spec.states for t in spec.states]
    return {n for m in moves for n in new_states(m)} & set(spec.states)


def sensors(spec: ModelSpec) -> list[Lag]:
    """A sensor state for each measurement of the states that is not read through one yet (what earlier rounds
    added to the measurement, a feedthrough standing in for the sensor's lag, is read through it too: the
    backward check then weighs it again)."""
    return _measured(spec, "sensor", set(spec.states))


def _measured(spec: ModelSpec, kind: str, of: set) -> list[Lag]:
    """A move of ``kind`` for each measurement of the states ``of`` that does not read its state yet."""
    names = declared_names(spec)
    out = []
    for o in spec.observations:
        sym = {str(x) for x in parse_expression(str(o.expr), names).free_symbols}
        if sym & of and names_of(Lag(str(o.expr), o.column, kind))[0] not in sym:
            out.append(Lag(str(o.expr), o.column, kind))
    return out


def pickups(spec: ModelSpec) -> list[Lag]:
    """A pickup for each measurement of an oscillator's position that reads none yet. A vibration is told from the
    dynamics by its line, where the record's own oscillation and its harmonics are not; on a first-order system
    a line in the innovations is as often a slow store or a forcing the model lacks (on the validation set's
    ``two_mass`` record a pickup gained 885 nats where a second thermal mass was missing)."""
    return _measured(spec, "pickup", {x for x, _ in _oscillators(spec)})


def actuators(spec: ModelSpec) -> list[Lag]:
    """An actuator state for each of the user's inputs (not a column the loop made: a forcing's sine, an input's
    rate) that drives a state's drift (directly or through a derived quantity) and is not read through one
    yet."""
    uses, out = _uses(spec), []
    for u in user_inputs(spec):
        where = [s for s, text in spec.drift.items() if _mentions(spec, text, u, uses)]
        if where and names_of(Lag(u, where[0], "actuator"))[0] not in spec.states:
            out.append(Lag(u, where[0], "actuator"))
    return out


def names_of(move: Lag) -> tuple[str, ...]:
    """The new state and its parameters, named after what they act on: a lag's (state, rate, feedthrough), a
    hysteresis' (state, coupling, beta, gamma), a sensor's or an actuator's (state, rate), a store's or a
    relaxation's (state, rate, exchange), a mode's (its two states, frequency, damping ratio, mass ratio)."""
    if move.kind == "hysteresis":
        x = move.term
        names = (f"hys_{x}", f"k_hys_{x}", f"beta_{x}", f"gamma_{x}")
    elif move.kind == "sensor":
        names = (f"sensor_{move.target}", f"b_sensor_{move.target}")
    elif move.kind == "actuator":
        names = (f"act_{move.term}", f"b_act_{move.term}")
    elif move.kind == "store":
        x = move.term
        names = (f"store_{x}", f"b_store_{x}", f"k_store_{x}")
    elif move.kind == "relaxation":
        v = move.term
        names = (f"rel_{v}", f"b_rel_{v}", f"k_rel_{v}")
    elif move.kind == "transfer":
        names = (f"tr_{move.term}_{move.target}", f"b_tr_{move.term}_{move.target}")
    elif move.kind == "mode":
        x = move.term
        names = (f"mode_{x}", f"dmode_{x}", f"w_mode_{x}", f"z_mode_{x}", f"mu_mode_{x}")
    elif move.kind == "pickup":
        y = move.target
        names = (f"pick_{y}", f"dpick_{y}", f"w_pick_{y}", f"z_pick_{y}", f"s_pick_{y}")
    else:
        names = (f"lag_{move.term}", f"b_{move.term}", f"k_{move.term}")
    # short enough that the loop's own names built on them (q_diag_<state>) stay within 32 characters
    return tuple(short_name(n, 24) for n in names)


def new_states(move: Lag) -> tuple[str, ...]:
    """The states ``move`` adds (:func:`names_of`'s first: two for a mode or a pickup, one otherwise); its
    parameters follow."""
    return names_of(move)[:2 if move.kind in SECOND_ORDER else 1]


SECOND_ORDER = ("mode", "pickup")
"""The kinds that add a position and its rate."""


def _words(text: str, old: str, new: str) -> str:
    return re.sub(rf"\b{re.escape(old)}\b", new, text)


def lag_spec(spec: ModelSpec, lag: Lag, start: tuple = (0.0, 1.0)) -> ModelSpec:
    """``spec`` with the state move ``lag`` (module docstring); ``start``: the new state's initial mean and
    standard deviation (and, for a pickup, its rate's)."""
    names = declared_names(spec)
    drift, derived, diffusion = dict(spec.drift), dict(spec.derived), dict(spec.diffusion)
    observations, new = list(spec.observations), names_of(lag)
    z = new[0]
    if lag.kind == "hysteresis":
        _, k, beta, gamma = new
        v = lag.target
        drift[v] = f"({drift[v]}) + {k}*{z}"
        drift[z] = f"{v} - {beta}*abs({v})*{z} - {gamma}*{v}*abs({z})"
    elif lag.kind == "sensor":
        _, b = new
        drift[z] = f"{b}*(({lag.term}) - {z})"
        observations = [o.model_copy(update={"expr": z}) if o.column == lag.target else o for o in observations]
    elif lag.kind == "actuator":
        _, b = new
        drift = {s: _words(text, lag.term, z) for s, text in drift.items()}
        derived = {d: _words(text, lag.term, z) for d, text in derived.items()}
        drift[z] = f"{b}*({lag.term} - {z})"
    elif lag.kind in EXCHANGES:
        _, b, k = new
        x = lag.term
        drift[x] = f"({drift[x]}) + {k}*({z} - {x})"
        drift[z] = f"{b}*({x} - {z})"
    elif lag.kind == "transfer":
        _, b = new
        drift[lag.target] = _words(drift[lag.target], lag.term, z)
        drift[z] = f"{b}*({lag.term} - {z})"
    elif lag.kind == "mode":
        q, dq, w, zeta, mu = new
        x, v = lag.term, lag.target
        force = f"({w}**2*({q} - {x}) + 2*{zeta}*{w}*({dq} - {v}))"
        drift[v] = f"({drift[v]}) + {mu}*{force}"
        drift[q] = dq
        drift[dq] = f"-{force}"
    elif lag.kind == "pickup":
        p, dp, w, zeta, level = new
        observations = [o.model_copy(update={"expr": f"({o.expr}) + {p}"}) if o.column == lag.target else o
                        for o in observations]
        drift[p] = dp
        drift[dp] = f"-{w}**2*{p} - 2*{zeta}*{w}*{dp}"
        diffusion[dp] = level
    else:
        _, b, k = new
        drift = {s: _words(text, lag.term, z) for s, text in drift.items()}
        derived = {d: (text if d == lag.term else _words(text, lag.term, z)) for d, text in derived.items()}
        noise = diffusion.get(lag.target)
        if noise is not None:
            # noise declared on the quantity (the state's diffusion its coefficient times a level) moves with it
            g = sp.diff(parse_expression(spec.drift[lag.target], names), sp.Symbol(lag.term, real=True))
            level = sp.simplify(parse_expression(str(noise), names) / g) if g != 0 else None
            if level is not None and not {str(x) for x in level.free_symbols} & {*spec.states, *spec.inputs}:
                diffusion.pop(lag.target)
                diffusion[z] = str(level)
        drift[z] = f"{b}*({lag.term} - {z}) + {k}*({drift[lag.target]})"
    states = list(new_states(lag))
    # a mode starts with the oscillator (q at x's start, dq at rest), as uncertain as the new state's start says;
    # a pickup about 0, its rate as uncertain as ``start`` says
    mean = {z: float(start[0])} if lag.kind not in SECOND_ORDER else {new[0]: float(start[0]), new[1]: 0.0}
    std = {n: float(start[1]) for n in states}
    if lag.kind == "pickup" and len(start) > 2:
        std[new[1]] = float(start[2])
    return spec.model_copy(update={
        "name": short_name(f"{spec.name}_{lag.kind[:3]}"), "states": list(spec.states) + states, "drift": drift,
        "derived": derived, "diffusion": diffusion, "observations": observations,
        "parameters": list(spec.parameters) + list(new[len(states):]),
        "initial_mean": {**spec.initial_mean, **mean}, "initial_std": {**spec.initial_std, **std}}).revalidate()
