"""Candidate effects a model may lack, and how one is added to a model (docs/method.md section 8, step 3).

An effect is one or more terms, each an expression in the model's states and
inputs, that would be added (each with its own coefficient) to the drift of a
*target* state, to an observation (a sensor effect), to the noise level, or
between two states (a flow). The families the loop screens are built in
:mod:`ardcore.effects.families`; this module holds what an effect is and how it is added
to a model (:func:`augment`).

Shape parameters (a free-play width, a friction velocity, a forcing frequency) are
written ``{name}`` in the terms; :meth:`Effect.at` fixes them (the screen picks the
value that the evidence prefers, :mod:`ardcore.screening.screen`).

Shape parameters fitted with the coefficients (:meth:`Effect.with_shape_parameter`) are model
parameters under :func:`shape_prior`.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, replace

import numpy as np
import sympy as sp

from ..data import Dataset
from ..model.declaration import ModelSpec


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
    rate_of: str = ""
    """For an input's rate: the input column whose time derivative is the term's column (:meth:`columns_for`)."""
    degenerate: str = ""
    """The end of the shape range (``"low"``, ``"high"``) where the effect turns into a simpler family the
    model or the library has (a smooth sign as wide as the velocities is a viscous damping): a profile that
    climbs to it is confirmed at the screen's shape, since a fitted shape would walk along the ridge beyond."""

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

    def input_columns(self) -> list[str]:
        """Names of the extra input columns this effect needs (empty for most effects)."""
        return list(self.terms) if self.frequency is not None or self.rate_of else []

    def columns_for(self, t: np.ndarray, columns: dict | None = None) -> dict[str, np.ndarray]:
        """Extra input columns this effect needs on the time grid ``t`` (empty for most effects); an input's
        rate is computed from that input's column in ``columns`` (the record's own)."""
        if self.rate_of:
            if columns is None or self.rate_of not in columns:
                raise ValueError(f"effect {self.name!r} needs the input column {self.rate_of!r}")
            return {self.terms[0]: input_rate(t, columns[self.rate_of])}
        if self.frequency is None:
            return {}
        w = 2 * np.pi * self.frequency
        return {self.terms[0]: np.sin(w * t), self.terms[1]: np.cos(w * t)}


def input_rate(t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """du/dt at the samples: the derivative of the cubic spline through them (central differences lose
    8 % of a component at a tenth of the sampling rate; the spline's slope is exact to its fourth order)."""
    from scipy.interpolate import CubicSpline

    t, u = np.asarray(t, float), np.asarray(u, float)
    if t.size < 4:
        return np.gradient(u, t) if t.size > 1 else np.zeros_like(u)
    return CubicSpline(t, u)(t, 1)


RATE_COLUMN = "d_{}_dt"


def shape_prior(effect: Effect):
    """Prior of a shape parameter fitted with the effect (:meth:`Effect.with_shape_parameter`): lognormal
    with its median at the geometric middle of the library's range and that range within +-2 sd of ln(shape),
    so that the evidence pays for the shape as the screen's Occam factor does for its profile."""
    from ..model.priors import LogNormal

    _, lo, hi = effect.shape
    s = math.log(hi / lo) / 4.0
    return LogNormal(median=math.sqrt(lo * hi), cov=100.0 * math.sqrt(math.expm1(s * s)))


def shape_parameter_name(spec: ModelSpec, effect: Effect, target: str) -> str:
    """A name for ``effect``'s shape parameter on ``target`` not yet used in ``spec`` (e.g. ``L_sny_v``)."""
    return _unused(short_name(f"{effect.shape[0]}_{effect.code}_{target}"), _taken(spec))


def _taken(spec: ModelSpec) -> set:
    """Every name ``spec`` uses (parameters, constants, states, inputs)."""
    return set(spec.parameters) | set(spec.constants) | set(spec.states) | set(spec.inputs)


def _unused(base: str, taken: set) -> str:
    """``base``, or ``base_2``, ``base_3`` ... when taken (the same family added again: another width, another
    round)."""
    n, k = base, 2
    while n in taken:
        n, k = short_name(f"{base}_{k}"), k + 1
    return n


def with_columns(data: Dataset, eff: Effect) -> Dataset:
    """``data`` plus the input columns ``eff`` needs on its time grid."""
    cols = eff.columns_for(data.t, data.columns)
    return data.with_columns({**data.columns, **cols}) if cols else data


def user_inputs(spec: ModelSpec) -> list[str]:
    """The model's inputs without the columns the loop made (a periodic forcing's sine/cosine, an input's
    rate)."""
    made = r"forcing\d+_(sin|cos)|" + re.escape(RATE_COLUMN).replace(re.escape("{}"), ".+")
    return [u for u in spec.inputs if not re.fullmatch(made, u)]


def declared_names(spec: ModelSpec) -> set:
    """Every name ``spec`` declares: states, inputs, parameters, constants and derived quantities."""
    return {*spec.states, *spec.inputs, *spec.parameters, *spec.constants, *spec.derived}


def oscillator_pairs(spec: ModelSpec) -> list[tuple[str, str]]:
    """(x, v) pairs with dx/dt = v."""
    states = list(spec.states)
    return [(x, str(spec.drift[x]).strip()) for x in states if str(spec.drift[x]).strip() in states
            and str(spec.drift[x]).strip() != x]


def dynamic_states(spec: ModelSpec) -> list[str]:
    """States whose drift is not just another state (where an effect can enter)."""
    states = set(spec.states)
    return [s for s in spec.states if str(spec.drift[s]).strip() not in states]


def short_name(text: str, limit: int = 32) -> str:
    """``text`` as a name (letters, digits, underscore) of at most ``limit`` characters: cut, with a hash of the
    whole so that two long names stay distinct."""
    text = re.sub(r"[^0-9A-Za-z_]+", "", text)
    if len(text) <= limit:
        return text
    import hashlib

    return text[: limit - 7] + "_" + hashlib.sha1(text.encode()).hexdigest()[:6]


def coefficient_name(effect: Effect, term_index: int, target: str) -> str:
    """Parameter name of one term's coefficient, e.g. ``k_s3theta_CM`` (at most 32 characters)."""
    idx = "" if len(effect.terms) == 1 else str(term_index)
    return short_name(f"k_{effect.code}{idx}_{target}")


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
        taken = _taken(spec)
        names = []
        for i in range(len(effect.terms)):
            n = _unused(coefficient_name(effect, i, target), taken)
            taken.add(n)
            names.append(n)
    sc = scales or [None] * len(effect.terms)
    parts = [f"{n}*({term})" if c is None else f"{n}*({c if isinstance(c, str) else repr(float(c))}*({term}))"
             for n, term, c in zip(names, effect.terms, sc)]
    add = " + ".join(parts)
    shape = [effect.shape_parameter] if effect.shape_parameter and effect.shape_parameter not in spec.parameters else []
    update = {"name": short_name(f"{spec.name}_{effect.code}"), "parameters": list(spec.parameters) + names + shape,
              "inputs": list(spec.inputs) + [c for c in effect.input_columns() if c not in spec.inputs]}
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
    from ..model.expr import parse_expression

    names = list(spec.states) + list(spec.inputs)
    syms = [sp.Symbol(n, real=True) for n in names]
    out = []
    for e in exprs:
        ex = parse_expression(e, names, where="effect term")
        f = sp.lambdify(syms, ex, modules=[{"sign": np.sign}, "numpy"])
        out.append(f)
    return names, out
