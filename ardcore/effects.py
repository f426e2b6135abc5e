"""Library of candidate effects a model may lack (method.md section 9, step 3).

An effect is one or more terms, each an expression in the model's states and
inputs, that would be added (each with its own coefficient) to the drift of a
*target* state. The library is generic: it is built from the model's structure,
not from its names.

* A **displacement/velocity pair** (x, v) is a state x whose drift is exactly
  another state v. For each pair the library proposes stiffness terms (x^2,
  x|x|, x^3, x^5), damping terms (v^3, v|v| quadratic damping, sign(v) Coulomb
  friction, and smooth dry friction and Stribeck friction with their velocity
  scale), cross terms (x^2 v, x v^2), a free-play / dead zone of half-width
  delta (x reduced by delta towards 0 outside |x| < delta; delta a shape
  parameter), a saturating stiffness, a sine (pendulum) stiffness L sin(x/L)
  with its period L a shape parameter, and a constant offset.
* **Inputs** u: u, u^2, u^3, u x, u v.
* **Periodic forcing** at a frequency found in the residual spectrum: a sine
  and a cosine (supplied as extra input columns, since expressions have no
  time variable); the frequency is a shape parameter refined by the screen.
* **Any dynamic state** s (first-order, level/flow and coupled models as well as
  oscillators): s^2, s^3, s|s|, sqrt(|s|) (outflow through an orifice), saturation
  tanh(s/s0), linear coupling to every other state, and an offset.
* **Flows between coupled levels** (``where="flow"``): where one dynamic state drives another's drift,
  a flow law (sqrt, x|x|, saturating) that leaves the first and enters the second (the pipe between
  two tanks), with one coefficient when the model conserves the flow in its units, else one per side.
* **Measurement effects** (``where="observation"``, added to an observation's
  expression): a bias, a direct feedthrough of each input, and a quadratic/cubic
  sensor nonlinearity.
* Targets are the *dynamic* states: those whose drift is not just another state.

Shape parameters (a free-play width, a friction velocity, a forcing frequency) are
written ``{name}`` in the terms; :meth:`Effect.at` fixes them (the screen picks the
value that the evidence prefers, :mod:`ardcore.screen`).

Extend it by passing ``extra`` effects to :func:`candidate_effects`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace

import numpy as np
import sympy as sp

from .data import Dataset
from .model import ModelSpec


@dataclass(frozen=True)
class Effect:
    """A candidate effect.

    Attributes
    ----------
    name : str
        Identifier, e.g. ``cubic_stiffness(y)``.
    kind : str
        Family (stiffness, damping, friction, cross, free-play, offset, input, forcing).
    terms : tuple of str
        Expressions in states and inputs; each gets its own coefficient.
    description : str
    code : str
        Short tag used in parameter names (names are limited to 32 characters).
    frequency : float, optional
        For periodic forcing: the terms are the input columns ``<name>_sin`` and
        ``<name>_cos`` at this frequency (cycles per time unit), made by :meth:`columns_for`.
    """

    name: str
    kind: str
    terms: tuple
    description: str = ""
    frequency: float | None = None
    code: str = "e"
    where: str = "drift"
    shape: tuple = ()
    """``(name, low, high)``: a shape parameter written ``{name}`` in the terms, to be fixed by :meth:`at`."""
    between: tuple = ()
    """For ``where="flow"``: ``(source, receiver)``; the terms leave the source's drift and enter the receiver's
    (a conserved flow between two levels, as through the pipe joining two tanks)."""
    shape_parameter: str = ""
    """The model parameter the shape is written as (:meth:`with_shape_parameter`: fitted with the coefficients
    under its prior, :func:`shape_prior`, instead of fixed at the screen's profile maximum)."""

    def at(self, value: float) -> "Effect":
        """This effect with its shape parameter fixed to ``value`` (a forcing effect: its frequency)."""
        if not self.shape:
            return self
        name = self.shape[0]
        v = float(f"{value:.6g}")
        if name == "f":
            return replace(self, name=f"forcing(f={v:.6g})", description=f"periodic forcing at {v:.6g} cycles/unit",
                           frequency=v, shape=())
        terms = tuple(t.replace("{" + name + "}", repr(v)) for t in self.terms)
        base = self.name.split("(")[0]
        arg = self.name[len(base) + 1:-1]
        return replace(self, name=f"{base}({arg},{name}={v:.3g})", terms=terms, shape=(),
                       description=self.description.replace("{" + name + "}", f"{v:.3g}"))

    def with_shape_parameter(self, pname: str) -> "Effect":
        """This effect with its shape written as the model parameter ``pname`` (a forcing frequency stays a
        shape: its sine and cosine are input columns made before the fit)."""
        if not self.shape or self.shape[0] == "f":
            return self
        name = self.shape[0]
        return replace(self, terms=tuple(t.replace("{" + name + "}", pname) for t in self.terms), shape=(),
                       shape_parameter=pname, description=self.description.replace("{" + name + "}", pname))

    def columns_for(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """Extra input columns this effect needs on the time grid ``t`` (empty for most effects)."""
        if self.frequency is None:
            return {}
        w = 2 * np.pi * self.frequency
        return {self.terms[0]: np.sin(w * t), self.terms[1]: np.cos(w * t)}


def shape_prior(effect: Effect):
    """Prior of a shape parameter fitted with the effect (:meth:`Effect.with_shape_parameter`): lognormal
    with its median at the geometric middle of the library's range and that range within +-2 sd of ln(shape),
    so that the evidence pays for the shape as the screen's Occam factor does for its profile."""
    from .priors import LogNormal

    _, lo, hi = effect.shape
    s = math.log(hi / lo) / 4.0
    return LogNormal(median=math.sqrt(lo * hi), cov=100.0 * math.sqrt(math.expm1(s * s)))


def shape_parameter_name(spec: ModelSpec, effect: Effect, target: str) -> str:
    """A name for ``effect``'s shape parameter on ``target`` not yet used in ``spec`` (e.g. ``L_sny_v``)."""
    taken = set(spec.parameters) | set(spec.constants) | set(spec.states) | set(spec.inputs)
    base = _short(f"{effect.shape[0]}_{effect.code}_{target}")
    n, k = base, 2
    while n in taken:
        n, k = _short(f"{base}_{k}"), k + 1
    return n


def with_columns(data: Dataset, eff: Effect) -> Dataset:
    """``data`` plus the input columns ``eff`` needs on its time grid."""
    cols = eff.columns_for(data.t)
    return Dataset(data.t, {**data.columns, **cols}, dict(data.meta)) if cols else data


def user_inputs(spec: ModelSpec) -> list[str]:
    """The model's inputs without the sine/cosine columns of a periodic forcing the loop added."""
    return [u for u in spec.inputs if not re.fullmatch(r"forcing\d+_(sin|cos)", u)]


def oscillator_pairs(spec: ModelSpec) -> list[tuple[str, str]]:
    """(x, v) pairs with dx/dt = v."""
    states = list(spec.states)
    return [(x, str(spec.drift[x]).strip()) for x in states if str(spec.drift[x]).strip() in states
            and str(spec.drift[x]).strip() != x]


def dynamic_states(spec: ModelSpec) -> list[str]:
    """States whose drift is not just another state (where an effect can enter)."""
    states = set(spec.states)
    return [s for s in spec.states if str(spec.drift[s]).strip() not in states]


def candidate_effects(spec: ModelSpec, *, scales: dict[str, float] | None = None,
                      frequencies: list[float] = (), extra: list[Effect] = ()) -> list[Effect]:
    """The candidate effects for ``spec``.

    Parameters
    ----------
    spec : ModelSpec
    scales : dict, optional
        Typical magnitude (e.g. the std) of each state; sets the free-play widths.
    frequencies : list of float
        Forcing frequencies (cycles per time unit) found in the residual spectrum.
    extra : list of Effect
        User-supplied effects appended to the library.
    """
    scales = scales or {}
    out: list[Effect] = []
    # the user's inputs (columns of a periodic forcing the loop added are not inputs to build effects from)
    inputs = user_inputs(spec)
    for x, v in oscillator_pairs(spec):
        out += _oscillator_effects(x, v, scales, inputs)
    for u in inputs:
        out += [Effect(f"input({u})", "input", (u,), f"linear input {u}", code=f"u1{u}"),
                Effect(f"input_quadratic({u})", "input", (f"{u}**2",), f"quadratic input {u}^2", code=f"u2{u}"),
                Effect(f"input_cubic({u})", "input", (f"{u}**3",), f"cubic input {u}^3", code=f"u3{u}")]
    pair_v = {v for _, v in oscillator_pairs(spec)}
    for s_ in dynamic_states(spec):
        if s_ in pair_v:
            continue  # a velocity: the oscillator families above cover it
        out += _level_effects(s_, scales, inputs)
    out += flow_effects(spec, scales)
    used = set(spec.inputs)
    free_idx = (i for i in range(100) if f"forcing{i}_sin" not in used)  # columns of forcing already added stay
    for f in frequencies:
        i = next(free_idx)
        out.append(Effect(f"forcing(f={f:.4g})", "forcing", (f"forcing{i}_sin", f"forcing{i}_cos"),
                          f"periodic forcing at {f:.4g} cycles/unit", frequency=float(f),
                          code=f"fo{i}", shape=("f", 0.97 * f, 1.03 * f)))
    # measurement effects: added to an observation's expression
    out += _measurement_effects(spec, inputs)
    out += list(extra)
    # one offset per model is enough
    seen, uniq = set(), []
    for e in out:
        if e.name not in seen:
            seen.add(e.name)
            uniq.append(e)
    return uniq


def _oscillator_effects(x: str, v: str, scales: dict[str, float], inputs: list[str]) -> list[Effect]:
    """Stiffness, damping, friction, cross, free-play, saturation and input terms of a pair dx/dt = v."""
    out: list[Effect] = []
    out += [
        Effect(f"quadratic_stiffness({x})", "stiffness", (f"{x}**2",), f"even-order (asymmetric) stiffness {x}^2", code=f"s2{x}"),
        Effect(f"asymmetric_stiffness({x})", "stiffness", (f"{x}*abs({x})",), f"stiffness {x}|{x}|", code=f"sa{x}"),
        Effect(f"cubic_stiffness({x})", "stiffness", (f"{x}**3",), f"cubic stiffness {x}^3", code=f"s3{x}"),
        Effect(f"quintic_stiffness({x})", "stiffness", (f"{x}**5",), f"fifth-order stiffness {x}^5", code=f"s5{x}"),
        Effect(f"cubic_damping({v})", "damping", (f"{v}**3",), f"cubic damping {v}^3", code=f"d3{v}"),
        Effect(f"quadratic_damping({v})", "damping", (f"{v}*abs({v})",), f"quadratic damping {v}|{v}|", code=f"dq{v}"),
        Effect(f"coulomb_friction({v})", "friction", (f"sign({v})",), f"Coulomb friction sign({v})", code=f"fc{v}"),
        Effect(f"cross({x}^2*{v})", "cross", (f"{x}**2*{v}",), f"cross term {x}^2 {v}", code=f"c21{x}"),
        Effect(f"cross({x}*{v}^2)", "cross", (f"{x}*{v}**2",), f"cross term {x} {v}^2", code=f"c12{x}"),
        Effect("offset", "offset", ("1",), "constant offset", code="off"),
    ]
    out += [
        Effect(f"quartic_stiffness({x})", "stiffness", (f"{x}**4",), f"fourth-order stiffness {x}^4", code=f"s4{x}"),
    ]
    s = scales.get(x)
    if s and s > 0:
        # the width as a shape parameter, from 2 % to 150 % of the displacement's std
        out.append(Effect(f"free_play({x})", "free-play",
                          (f"0.5*({x} - {{delta}}*sign({x}))*(1 + sign(abs({x}) - {{delta}}))",),
                          f"dead zone of half-width {{delta}} in {x}", code=f"fpw{x}",
                          shape=("delta", 0.02 * s, 1.5 * s)))
        out.append(Effect(f"saturation({x})", "stiffness", (f"{x} - {{xs}}*tanh({x}/{{xs}})",),
                          f"stiffness that saturates beyond |{x}| ~ {{xs}}", code=f"st{x}",
                          shape=("xs", 0.2 * s, 1.5 * s)))
        # a restoring force periodic in x (a pendulum's gravity, a rotor in a periodic field): -k x becomes
        # -k L sin(x/L); its quintic and higher orders are tied to the cubic, so it extrapolates in amplitude
        out.append(Effect(f"sine_stiffness({x})", "stiffness", (f"{x} - {{L}}*sin({x}/{{L}})",),
                          f"restoring force periodic in {x}, L sin({x}/L) with L = {{L}}", code=f"sn{x}",
                          shape=("L", 0.3 * s, 3.0 * s)))
    sv = scales.get(v)
    if sv and sv > 0:
        # dry friction with a smooth sign (the EKF sees its slope) and Stribeck's decaying static peak
        out.append(Effect(f"dry_friction({v})", "friction", (f"tanh({v}/{{vs}})",),
                          "dry (Coulomb) friction, smooth sign over {vs}", code=f"fd{v}",
                          shape=("vs", 0.005 * sv, 0.3 * sv)))
        out.append(Effect(f"stribeck({v})", "friction", (f"tanh({v}/{0.01 * sv:.3g})*exp(-({v}/{{vs}})**2)",),
                          "Stribeck friction peak decaying over {vs}", code=f"fs{v}",
                          shape=("vs", 0.02 * sv, 1.0 * sv)))
    for u in inputs:
        out += [Effect(f"input_cross({u}*{x})", "input", (f"{u}*{x}",), f"input-state cross term {u} {x}", code=f"u{u}{x}"),
                Effect(f"input_cross({u}*{v})", "input", (f"{u}*{v}",), f"input-velocity cross term {u} {v}", code=f"u{u}{v}")]
    return out


def _level_effects(s_: str, scales: dict[str, float], inputs: list[str]) -> list[Effect]:
    """Terms of any dynamic state that is not a velocity: powers, an orifice outflow, saturation, offset and
    input cross terms (first-order, level/flow and coupled models)."""
    out: list[Effect] = []
    sc = scales.get(s_)
    out += [Effect(f"square({s_})", "state", (f"{s_}**2",), f"{s_}^2", code=f"q2{s_}"),
            Effect(f"cube({s_})", "state", (f"{s_}**3",), f"{s_}^3", code=f"q3{s_}"),
            Effect(f"signed_square({s_})", "state", (f"{s_}*abs({s_})",), f"{s_}|{s_}|", code=f"qa{s_}"),
            Effect(f"sqrt_outflow({s_})", "state", (f"sqrt(abs({s_}))*sign({s_})",),
                   f"outflow through an orifice, sqrt({s_})", code=f"qr{s_}"),
            Effect("offset", "offset", ("1",), "constant offset", code="off")]
    if sc and sc > 0:
        out.append(Effect(f"saturation({s_})", "state", (f"{s_} - {{xs}}*tanh({s_}/{{xs}})",),
                          f"{s_} saturating beyond ~{{xs}}", code=f"qs{s_}", shape=("xs", 0.2 * sc, 1.5 * sc)))
    for u in inputs:
        out += [Effect(f"input_cross({u}*{s_})", "input", (f"{u}*{s_}",), f"input-state cross term {u} {s_}",
                       code=f"u{u}{s_}")]
    return out


def _measurement_effects(spec: ModelSpec, inputs: list[str]) -> list[Effect]:
    """Effects on what is measured: a bias, input feedthrough, the noise level, sensor nonlinearities."""
    out: list[Effect] = []
    out.append(Effect("sensor_bias", "measurement", ("1",), "measurement bias", code="mb", where="observation"))
    for u in inputs:
        out.append(Effect(f"feedthrough({u})", "measurement", (u,), f"direct feedthrough of {u} to the measurement",
                          code=f"mf{u}", where="observation"))
    for o in spec.observations:
        # the declared measurement noise may be too small: then the filter explains the misfit by process noise,
        # and the fitted dynamics free-run poorly. exp(k) scales it; ARD on k (k = 0: as declared) decides.
        out.append(Effect(f"measurement_noise({o.column})", "noise", ("noise",),
                          f"measurement noise of {o.column} larger or smaller than declared (x exp(k))",
                          code=f"mn{o.column}", where="noise"))
    for o in spec.observations:
        e = str(o.expr).strip()
        if e not in spec.states:
            continue  # a sensor nonlinearity of a state-observing channel only (its terms may hold no parameters)
        out += [Effect(f"sensor_quadratic({o.column})", "measurement", (f"({e})**2",),
                       "quadratic sensor nonlinearity", code=f"m2{o.column}", where="observation"),
                Effect(f"sensor_cubic({o.column})", "measurement", (f"({e})**3",),
                       "cubic sensor nonlinearity", code=f"m3{o.column}", where="observation")]
    return out


def flow_effects(spec: ModelSpec, scales: dict[str, float]) -> list[Effect]:
    """Flows between coupled levels (tanks, compartments, thermal masses): for each dynamic state i whose
    value drives another one's drift j, a flow law f(x_i) that leaves i and enters j.

    When one parameter of the model already appears in both drifts (``-a*h1`` in one, ``a*h1`` in the other:
    the model conserves what flows, in its units) the flow has one coefficient; otherwise (levels of tanks
    of different cross-sections) it has one per side. An outflow added to i alone and an inflow to j alone
    would each be screened without the other, and neither would find the pipe between them."""
    pair_v = {v for _, v in oscillator_pairs(spec)}
    levels = [s_ for s_ in dynamic_states(spec) if s_ not in pair_v]
    sm = spec.sym
    params = set(sm.params)
    out = []
    for i in levels:
        xi = sp.Symbol(i, real=True)
        di = sm.drift[spec.states.index(i)]
        for j in levels:
            dj = sm.drift[spec.states.index(j)]
            if j == i or xi not in dj.free_symbols:
                continue
            one = bool(di.free_symbols & dj.free_symbols & params)
            laws = [("sqrt_flow", "fr", f"sqrt(abs({i}))*sign({i})", f"through an orifice, sqrt({i})", None),
                    ("square_flow", "fa", f"{i}*abs({i})", f"growing as {i}|{i}|", None)]
            sc = scales.get(i)
            if sc and sc > 0:
                laws.append(("saturating_flow", "fs", f"{{xs}}*tanh({i}/{{xs}})", "saturating beyond ~{xs}",
                             ("xs", 0.2 * sc, 1.5 * sc)))
            for name, code, term, what, shape in laws:
                out.append(Effect(f"{name}({i}->{j})", "flow", (term,) if one else (term, term),
                                  f"flow from {i} to {j} {what}", code=f"{code}{i}{j}", where="flow",
                                  between=(i, j), shape=shape or ()))
    return out


def _short(text: str, limit: int = 32) -> str:
    text = re.sub(r"[^0-9A-Za-z_]+", "", text)
    if len(text) <= limit:
        return text
    import hashlib

    return text[: limit - 7] + "_" + hashlib.sha1(text.encode()).hexdigest()[:6]


def coefficient_name(effect: Effect, term_index: int, target: str) -> str:
    """Parameter name of one term's coefficient, e.g. ``k_s3theta_CM`` (at most 32 characters)."""
    idx = "" if len(effect.terms) == 1 else str(term_index)
    return _short(f"k_{effect.code}{idx}_{target}")


def augment(spec: ModelSpec, effect: Effect, target: str, scales: list[float] | None = None,
            *, names: list[str] | None = None) -> tuple[ModelSpec, list[str]]:
    """``spec`` with ``effect`` added to ``target``; returns it and the new coefficient names.

    ``target`` is a state (the effect enters its drift) or, for ``effect.where == "observation"``, an
    observed column (the effect enters that observation's expression); for ``"noise"``, the observed
    column whose noise std is multiplied by ``exp(k)``. With ``scales`` each term is
    written ``k * (scale * term)``: the coefficient ``k`` is then dimensionless (1 = an effect as large
    as the target's own drift), so that priors, proposal steps and evidence do not depend on the
    term's units. Without, ``k`` is the physical coefficient.
    """
    if effect.shape and "{" in "".join(effect.terms):
        raise ValueError(f"effect {effect.name!r} has a free shape parameter {effect.shape[0]!r}: fix it with .at()")
    if names is None:
        taken = set(spec.parameters) | set(spec.constants) | set(spec.states) | set(spec.inputs)
        names = []
        for i in range(len(effect.terms)):
            n, k = coefficient_name(effect, i, target), 2
            while n in taken:  # the same family added again (another width, another round)
                n, k = _short(f"{coefficient_name(effect, i, target)}_{k}"), k + 1
            taken.add(n)
            names.append(n)
    sc = scales or [None] * len(effect.terms)
    parts = [f"{n}*({term})" if c is None else f"{n}*({c if isinstance(c, str) else repr(float(c))}*({term}))"
             for n, term, c in zip(names, effect.terms, sc)]
    add = " + ".join(parts)
    shape = [effect.shape_parameter] if effect.shape_parameter and effect.shape_parameter not in spec.parameters else []
    update = {"name": _short(f"{spec.name}_{effect.code}"), "parameters": list(spec.parameters) + names + shape,
              "inputs": list(spec.inputs) + [c for c in effect.columns_for(np.zeros(1)) if c not in spec.inputs]}
    if effect.where == "noise":
        if all(o.column != target for o in spec.observations):
            raise ValueError(f"{target!r} is not an observed column of {spec.name!r}")
        update["observations"] = [o.model_copy(update={"noise_std": f"({o.noise_std})*exp({names[0]})"})
                                  if o.column == target else o for o in spec.observations]
    elif effect.where == "observation":
        obs = [o.model_copy(update={"expr": f"({o.expr}) + {add}"}) if o.column == target else o
               for o in spec.observations]
        if all(o.column != target for o in spec.observations):
            raise ValueError(f"{target!r} is not an observed column of {spec.name!r}")
        update["observations"] = obs
    elif effect.where == "flow":
        src, dst = effect.between
        if target != src:
            raise ValueError(f"the flow {effect.name!r} leaves {src!r}, not {target!r}")
        drift = dict(spec.drift)
        # one coefficient: the same flow on both sides; two: one per side
        drift[src] = f"({drift[src]}) - ({parts[0]})"
        drift[dst] = f"({drift[dst]}) + {parts[-1]}"
        update["drift"] = drift
    else:
        drift = dict(spec.drift)
        drift[target] = f"({drift[target]}) + {add}"
        update["drift"] = drift
    return spec.model_copy(update=update).revalidate(), names


def feature_functions(spec: ModelSpec, exprs: list[str]):
    """Vectorised numpy callables of expressions in the model's states and inputs: f(states, inputs) -> array."""
    from .expr import parse_expression

    names = list(spec.states) + list(spec.inputs)
    syms = [sp.Symbol(n, real=True) for n in names]
    out = []
    for e in exprs:
        ex = parse_expression(e, names, where="effect term")
        f = sp.lambdify(syms, ex, modules=[{"sign": np.sign}, "numpy"])
        out.append(f)
    return names, out
