"""Library of candidate effects a model may lack (method.md section 9, step 3).

An effect is one or more terms, each an expression in the model's states and
inputs, that would be added (each with its own coefficient) to the drift of a
*target* state. The library is generic: it is built from the model's structure,
not from its names.

* A **displacement/velocity pair** (x, v) is a state x whose drift is exactly
  another state v. For each pair the library proposes stiffness terms (x^2,
  x|x|, x^3, x^5), damping terms (v^3, v|v| quadratic damping, sign(v) Coulomb
  friction), cross terms (x^2 v, x v^2), a free-play / dead zone of width
  delta (x reduced by delta towards 0 outside |x| < delta, several widths)
  and a constant offset.
* **Inputs** u: u, u^2, u^3, u x, u v.
* **Periodic forcing** at a frequency found in the residual spectrum: a sine
  and a cosine (supplied as extra input columns, since expressions have no
  time variable).
* Targets are the *dynamic* states: those whose drift is not just another state.

Extend it by passing ``extra`` effects to :func:`candidate_effects`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import sympy as sp

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

    def columns_for(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """Extra input columns this effect needs on the time grid ``t`` (empty for most effects)."""
        if self.frequency is None:
            return {}
        w = 2 * np.pi * self.frequency
        return {self.terms[0]: np.sin(w * t), self.terms[1]: np.cos(w * t)}


def oscillator_pairs(spec: ModelSpec) -> list[tuple[str, str]]:
    """(x, v) pairs with dx/dt = v."""
    states = list(spec.states)
    return [(x, spec.drift[x].strip()) for x in states if spec.drift[x].strip() in states
            and spec.drift[x].strip() != x]


def dynamic_states(spec: ModelSpec) -> list[str]:
    """States whose drift is not just another state (where an effect can enter)."""
    states = set(spec.states)
    return [s for s in spec.states if spec.drift[s].strip() not in states]


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
    for x, v in oscillator_pairs(spec):
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
        s = scales.get(x)
        if s and s > 0:
            for j, frac in enumerate((0.1, 0.25, 0.5)):
                d = float(f"{frac * s:.3g}")
                out.append(Effect(f"free_play({x},delta={d:g})", "free-play",
                                  (f"0.5*({x} - {d!r}*sign({x}))*(1 + sign(abs({x}) - {d!r}))",),
                                  f"dead zone of half-width {d:g} in {x}", code=f"fp{j}{x}"))
        for u in spec.inputs:
            out += [Effect(f"input_cross({u}*{x})", "input", (f"{u}*{x}",), f"input-state cross term {u} {x}", code=f"u{u}{x}"),
                    Effect(f"input_cross({u}*{v})", "input", (f"{u}*{v}",), f"input-velocity cross term {u} {v}", code=f"u{u}{v}")]
    for u in spec.inputs:
        out += [Effect(f"input({u})", "input", (u,), f"linear input {u}", code=f"u1{u}"),
                Effect(f"input_quadratic({u})", "input", (f"{u}**2",), f"quadratic input {u}^2", code=f"u2{u}"),
                Effect(f"input_cubic({u})", "input", (f"{u}**3",), f"cubic input {u}^3", code=f"u3{u}")]
    for i, f in enumerate(frequencies):
        out.append(Effect(f"forcing(f={f:.4g})", "forcing", (f"forcing{i}_sin", f"forcing{i}_cos"),
                          f"periodic forcing at {f:.4g} cycles/unit", frequency=float(f),
                          code=f"fo{i}"))
    out += list(extra)
    # one offset per model is enough
    seen, uniq = set(), []
    for e in out:
        if e.name not in seen:
            seen.add(e.name)
            uniq.append(e)
    return uniq


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


def augment(spec: ModelSpec, effect: Effect, target: str) -> tuple[ModelSpec, list[str]]:
    """``spec`` with ``effect`` added to the drift of ``target``; returns it and the new coefficient names."""
    names = [coefficient_name(effect, i, target) for i in range(len(effect.terms))]
    add = " + ".join(f"{n}*({term})" for n, term in zip(names, effect.terms))
    drift = dict(spec.drift)
    drift[target] = f"({drift[target]}) + {add}"
    inputs = list(spec.inputs) + [c for c in effect.columns_for(np.zeros(1)) if c not in spec.inputs]
    new = spec.model_copy(update={"name": _short(f"{spec.name}_{effect.code}"), "drift": drift,
                                  "parameters": list(spec.parameters) + names, "inputs": inputs})
    return new.revalidate(), names


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
