"""Declarative stochastic state-space models.

A model is data: states, drift expressions, which states receive process noise
(and its diffusion coefficient), observations with their noise, known constants,
known inputs (data columns, interpolated between samples), named parameters, and
optionally parameters fixed to a value (a pruned term is fixed to 0)::

    du = F(u, phi, f) dt + diag(g(u, phi, f)) dW,     y_k = h(u(t_k), phi) + eps_k

:func:`symbolic` turns a :class:`ModelSpec` into sympy expressions (drift,
exact Jacobian, diffusion, observation); :mod:`ardcore.model.codegen` compiles them.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from dataclasses import dataclass
from functools import cached_property
from typing import Annotated, Literal, Union

import sympy as sp
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from ..errors import ModelError
from .expr import CONSTANTS, FUNCTIONS, expanded_size, parse_expression

NAME_PATTERN = r"^[A-Za-z][A-Za-z0-9_]{0,31}$"
_NAME_RE = re.compile(NAME_PATTERN)
RESERVED = set(FUNCTIONS) | set(CONSTANTS) | {"t", "dt"}

Name = Annotated[str, Field(pattern=NAME_PATTERN)]
ExprLike = Union[Annotated[str, Field(min_length=1, max_length=2000)], float]


class Observation(BaseModel):
    """One measured channel: data ``column`` = ``expr`` + N(0, ``noise_std``^2)."""

    model_config = ConfigDict(extra="forbid")
    column: Name
    expr: ExprLike
    noise_std: ExprLike = Field(description="Measurement-noise standard deviation: a number or "
                                            "an expression over parameters and constants.")


class ModelSpec(BaseModel):
    """A declarative stochastic state-space model.

    Attributes
    ----------
    name : str
        Identifier (letters, digits, underscore).
    states : list of str
        State names, in order.
    derived : dict
        Named intermediate expressions, evaluated in order (each may use the
        ones before it); they are substituted symbolically.
    drift : dict
        ``state -> expression`` for ``du/dt``; every state needs one.
    diffusion : dict
        ``state -> expression`` for the diffusion coefficient of the states
        that receive process noise (independent Wiener processes). Over a step
        ``dt`` a state gains variance ``g^2 dt``.
    observations : list of Observation
        The measured channels.
    parameters : list of str
        Named parameters phi, in order.
    constants : dict
        Known constants (baked into the compiled kernel).
    inputs : list of str
        Known inputs: data columns, interpolated between samples (see ``input_hold``).
    initial_mean, initial_std : dict
        Initial state mean and standard deviation (numbers or expressions over
        parameters and constants); missing states default to 0 and 1.
    fixed : dict
        Parameters fixed to a value (removed from phi).
    substeps : int
        EKF sub-steps per observation interval.
    integrator : {"rk4", "euler"}
        Scheme of a sub-step. ``"rk4"`` (default): classical Runge-Kutta for the mean and its
        exact tangent map for the covariance (``P <- Phi P Phi^T + G G^T dt``), fourth order, so a
        few sub-steps are enough. ``"euler"``: ``Phi = I + J dt`` (first order; the paper's
        aeroelastic models keep it so that their reference data and results are unchanged).
    input_hold : {"foh", "zoh"}
        How inputs vary between samples. ``"foh"`` (the default): linearly interpolated (first-order
        hold). ``"zoh"``: held at the previous sample, which delays them by half a sample. Undeclared, a
        study and a diagnosis take it from the record (:mod:`ardcore.selection.hold`).
    kinks : {"smooth", "exact"}
        How the filter treats ``abs``, ``sign``, ``max`` and ``min`` of the states. ``"smooth"`` (default):
        their expectation over the filter's own spread of the argument (:mod:`ardcore.model.kinks`), so the
        log-likelihood is smooth at the posterior's scale. ``"exact"``: as written, with d sign/dx = 0 (the
        paper's models keep it so that their reference results are unchanged). Simulations use the exact
        model either way.
    """

    model_config = ConfigDict(extra="forbid")

    name: Name
    description: str = Field("", max_length=4000)
    states: list[Name] = Field(min_length=1, max_length=12)
    derived: dict[Name, ExprLike] = Field(default_factory=dict, max_length=64)
    drift: dict[Name, ExprLike]
    diffusion: dict[Name, ExprLike] = Field(default_factory=dict)
    observations: list[Observation] = Field(min_length=1, max_length=8)
    parameters: list[Name] = Field(default_factory=list, max_length=64)
    constants: dict[Name, float] = Field(default_factory=dict, max_length=128)
    inputs: list[Name] = Field(default_factory=list, max_length=24)
    initial_mean: dict[Name, ExprLike] = Field(default_factory=dict)
    initial_std: dict[Name, ExprLike] = Field(default_factory=dict)
    fixed: dict[Name, float] = Field(default_factory=dict)
    substeps: int = Field(10, ge=1, le=10000)
    integrator: Literal["rk4", "euler"] = "rk4"
    input_hold: Literal["foh", "zoh"] = "foh"
    kinks: Literal["smooth", "exact"] = "smooth"

    @field_validator("constants", "fixed")
    @classmethod
    def _finite(cls, v: dict[str, float]) -> dict[str, float]:
        for k, x in v.items():
            if not math.isfinite(x):
                raise ValueError(f"{k!r} must be a finite number")
        return v

    @model_validator(mode="after")
    def _check_names(self) -> "ModelSpec":
        groups = {
            "states": self.states, "parameters": self.parameters,
            "constants": list(self.constants), "inputs": self.inputs, "derived": list(self.derived),
        }
        seen: dict[str, str] = {}
        for group, names in groups.items():
            for n in names:
                if n in RESERVED:
                    raise ValueError(f"{group}: name {n!r} is reserved")
                if n in seen:
                    raise ValueError(f"name {n!r} is declared twice ({seen[n]} and {group})")
                seen[n] = group
        for key, d in (("drift", self.drift), ("diffusion", self.diffusion),
                       ("initial_mean", self.initial_mean), ("initial_std", self.initial_std)):
            unknown = [s for s in d if s not in self.states]
            if unknown:
                raise ValueError(f"{key}: {unknown[0]!r} is not a state (states: {self.states})")
        missing = [s for s in self.states if s not in self.drift]
        if missing:
            raise ValueError(f"drift: no equation for state {missing[0]!r}")
        bad = [p for p in self.fixed if p not in self.parameters]
        if bad:
            raise ValueError(f"fixed: {bad[0]!r} is not a parameter (parameters: {self.parameters})")
        cols = [o.column for o in self.observations]
        if len(set(cols)) != len(cols):
            raise ValueError("observations: a column is observed twice")
        clash = set(cols) & set(self.inputs)
        if clash:
            raise ValueError(f"column {sorted(clash)[0]!r} is both an observation and an input")
        return self

    # -- convenience ---------------------------------------------------------
    @property
    def free_parameters(self) -> list[str]:
        """Parameters that are not fixed, in declaration order."""
        return [p for p in self.parameters if p not in self.fixed]

    @property
    def observed_columns(self) -> list[str]:
        return [o.column for o in self.observations]

    def with_fixed(self, **values: float) -> "ModelSpec":
        """A copy with more parameters fixed (e.g. ``with_fixed(a5=0.0)``)."""
        fixed = dict(self.fixed)
        fixed.update({k: float(v) for k, v in values.items()})
        return self.model_copy(update={"fixed": fixed}).revalidate()

    def with_constants(self, **values: float) -> "ModelSpec":
        """A copy with some constants changed."""
        c = dict(self.constants)
        for k, v in values.items():
            if k not in c:
                raise ModelError(f"{self.name}: {k!r} is not a constant (constants: {sorted(c)})")
            c[k] = float(v)
        return self.model_copy(update={"constants": c}).revalidate()

    def revalidate(self) -> "ModelSpec":
        return type(self).model_validate(self.model_dump())

    def model_copy(self, *, update=None, deep: bool = False) -> "ModelSpec":
        """pydantic's copy without the cached symbolic model: a copy with another drift or other inputs must
        not compile the original's (its kernel would be cached under the copy's structure hash)."""
        new = super().model_copy(update=update, deep=deep)
        new.__dict__.pop("sym", None)
        return new

    def structure_hash(self) -> str:
        """Hash of everything that determines the compiled kernel."""
        d = self.model_dump(exclude={"name", "description", "substeps"})
        blob = json.dumps(d, sort_keys=True, default=str)
        return hashlib.sha256(blob.encode()).hexdigest()[:20]

    @cached_property
    def sym(self) -> "SymbolicModel":
        return symbolic(self)


def sign_derivative_zero(e: sp.Expr) -> sp.Expr:
    # Decision (docs/method.md section 2): d sign(x)/dx = 0 in Jacobians.
    return e.replace(lambda a: isinstance(a, sp.DiracDelta), lambda a: sp.S.Zero)


@dataclass(frozen=True)
class SymbolicModel:
    """Sympy form of a model with derived quantities, constants and fixed values substituted.

    Attributes
    ----------
    states, params, inputs : tuple of sympy.Symbol
        ``params`` are the free parameters only.
    drift : tuple of sympy.Expr
        F(u, phi, f), one per state.
    jacobian : sympy.Matrix
        dF/du, exact, with d sign/dx = 0.
    diffusion : tuple of sympy.Expr
        Diffusion coefficient per state (0 where no noise).
    obs : tuple of sympy.Expr
        h_j(u, phi, f), one per observation.
    obs_jacobian : sympy.Matrix
        dh/du.
    obs_std : tuple of sympy.Expr
        Measurement-noise std per observation.
    init_mean, init_std : tuple of sympy.Expr
    """

    states: tuple
    params: tuple
    inputs: tuple
    drift: tuple
    jacobian: sp.Matrix
    diffusion: tuple
    obs: tuple
    obs_jacobian: sp.Matrix
    obs_std: tuple
    init_mean: tuple
    init_std: tuple


@dataclass(frozen=True)
class ParsedModel:
    """Every expression of a model parsed (bounded, :mod:`ardcore.model.expr`), with derived quantities, constants
    and fixed values substituted; not yet differentiated. ``drift`` is as written (not expanded)."""

    states: tuple
    inputs: tuple
    drift: tuple
    diffusion: tuple
    obs: tuple
    obs_std: tuple
    init_mean: tuple
    init_std: tuple


def parse_model(spec: ModelSpec) -> ParsedModel:
    """Parse every expression of ``spec``: cheap and bounded (sizes, depths, exponents, constants and derived
    chains written out are capped), so it is also the submit-time check of a model.

    Raises
    ------
    ModelError
        Naming the model and the field of any bad expression, or a
        measurement-noise / initial-std expression that depends on the state.
    """
    S = lambda n: sp.Symbol(n, real=True)  # noqa: E731
    states = [S(n) for n in spec.states]
    inputs = [S(n) for n in spec.inputs]
    subs: dict[sp.Symbol, sp.Expr] = {S(k): sp.Float(v) for k, v in spec.constants.items()}
    subs.update({S(k): sp.Float(v) for k, v in spec.fixed.items()})
    base = set(spec.states) | set(spec.parameters) | set(spec.constants) | set(spec.inputs)

    def parse(src, where, extra=()):
        e = parse_expression(src, base | set(extra), where=f"model {spec.name!r}, {where}")
        return e.xreplace(subs)

    known: list[str] = []
    sizes: dict[str, int] = {}
    for k, src in spec.derived.items():
        sizes[k] = expanded_size(src, sizes, where=f"model {spec.name!r}, derived[{k!r}]")
        subs[S(k)] = parse(src, f"derived[{k!r}]", known)
        known.append(k)
    for where, src in ([(f"drift[{n!r}]", spec.drift[n]) for n in spec.states]
                       + [(f"diffusion[{n!r}]", v) for n, v in spec.diffusion.items()]
                       + [(f"observations[{j}].expr", o.expr) for j, o in enumerate(spec.observations)]
                       + [(f"observations[{j}].noise_std", o.noise_std) for j, o in enumerate(spec.observations)]):
        expanded_size(src, sizes, where=f"model {spec.name!r}, {where}")
    dnames = list(spec.derived)
    drift = [parse(spec.drift[n], f"drift[{n!r}]", dnames) for n in spec.states]
    diffusion = [parse(spec.diffusion[n], f"diffusion[{n!r}]", dnames) if n in spec.diffusion else sp.S.Zero
                 for n in spec.states]
    obs = [parse(o.expr, f"observations[{j}].expr", dnames) for j, o in enumerate(spec.observations)]
    obs_std = [parse(o.noise_std, f"observations[{j}].noise_std", dnames) for j, o in enumerate(spec.observations)]
    init_mean = [parse(spec.initial_mean.get(n, 0.0), f"initial_mean[{n!r}]") for n in spec.states]
    init_std = [parse(spec.initial_std.get(n, 1.0), f"initial_std[{n!r}]") for n in spec.states]
    sset = set(states)
    for j, e in enumerate(obs_std):
        if e.free_symbols & (sset | set(inputs)):
            raise ModelError(f"model {spec.name!r}: observations[{j}].noise_std must not depend on states or inputs")
    for n, e in zip(spec.states, init_mean + init_std):
        if e.free_symbols & (sset | set(inputs)):
            raise ModelError(f"model {spec.name!r}: initial mean/std of {n!r} must not depend on states or inputs")
    return ParsedModel(tuple(states), tuple(inputs), tuple(drift), tuple(diffusion), tuple(obs), tuple(obs_std),
                       tuple(init_mean), tuple(init_std))


def symbolic(spec: ModelSpec) -> SymbolicModel:
    """Parse (:func:`parse_model`) and differentiate a model.

    Raises
    ------
    ModelError
        As :func:`parse_model`.
    """
    pm = parse_model(spec)
    drift = [sp.expand(f, deep=False) for f in pm.drift]
    J = sp.Matrix([[sign_derivative_zero(sp.diff(f, x)) for x in pm.states] for f in drift])
    H = sp.Matrix([[sign_derivative_zero(sp.diff(h, x)) for x in pm.states] for h in pm.obs])
    params = [sp.Symbol(p, real=True) for p in spec.free_parameters]
    return SymbolicModel(pm.states, tuple(params), pm.inputs, tuple(drift), J, pm.diffusion, pm.obs, H,
                         pm.obs_std, pm.init_mean, pm.init_std)
