"""The library of candidate effects (docs/method.md section 8, step 3): the families the loop screens.

It is built from the model's structure, not from its names (see :mod:`ardcore.effects.base` for what an
effect is and how one is added to a model):

* A **displacement/velocity pair** (x, v) is a state x whose drift is exactly
  another state v. For each pair the library proposes stiffness terms (x^2,
  x|x|, x^3, x^4, x^5), damping terms (v^3, v|v| quadratic damping, sign(v) Coulomb
  friction, and smooth dry friction and Stribeck friction with their velocity
  scale), cross terms (x^2 v, x v^2), a free-play / dead zone of half-width
  delta (x reduced by delta towards 0 outside |x| < delta; delta a shape
  parameter), a saturating stiffness, a sine (pendulum) stiffness L sin(x/L)
  with its period L a shape parameter, a one-sided contact stiffness max(x - g, 0) above or below a
  gap g (a stop, a bumper), and a constant offset.
* **Inputs** u: u, u^2, u^3, u x, u v, and the input's rate du/dt (a transfer-function zero: a small
  lead or lag of the input, e.g. a skew between the channels that sampled u and y, is u - tau du/dt).
* **Periodic forcing** at a frequency found in the residual spectrum: a sine
  and a cosine (supplied as extra input columns, since expressions have no
  time variable); the frequency is a shape parameter refined by the screen.
* **Any dynamic state** s (first-order, level/flow and coupled models as well as
  oscillators): s^2, s^3, s|s|, sqrt(|s|) (outflow through an orifice), saturation
  tanh(s/s0), an overflow max(s - h0, 0) that acts only above a level h0 (a tank's overflow, a
  relief valve; h0 a shape parameter between the state's median and maximum), linear coupling to
  every other state, and an offset.
* **Powers about a declared level**: where the user's drift measures a state from a level c (Newton cooling
  ``a*(T - 295)``, a set point, an ambient input; an oscillator's position in its velocity's equation, a rest
  position or a drive ``k*(u - x)``), (s - c)^2, (s - c)^3 and |s - c|^p sign(s - c), which vanish where the
  declared law does (radiation to the ambient, a valve about its set point, a coupling spring's hardening).
* **Flows between coupled levels** (``where="flow"``): where one dynamic state drives another's drift,
  a flow law (sqrt, x|x|, saturating, overflow above a level) that leaves the first and enters the
  second (the pipe between two tanks, what spills over from the upper one), with one coefficient when
  the model conserves the flow in its units, else one per side.
* **Measurement effects** (``where="observation"``, added to an observation's
  expression): a bias, a direct feedthrough of each input, and a quadratic/cubic
  sensor nonlinearity; and the measurement noise level (``where="noise"``).
* Targets are the *dynamic* states: those whose drift is not just another state.

Extend it by passing ``extra`` effects to :func:`candidate_effects`.
"""

from __future__ import annotations

import sympy as sp

from .base import RATE_COLUMN, Effect, declared_names, dynamic_states, oscillator_pairs, user_inputs
from ..model.declaration import ModelSpec
from ..model.expr import parse_expression


def candidate_effects(spec: ModelSpec, *, scales: dict[str, float] | None = None,
                      levels: dict[str, tuple[float, float, float]] | None = None,
                      frequencies: list = (), frequency_resolution: float = 0.0,
                      extra: list[Effect] = (), declared: ModelSpec | None = None) -> list[Effect]:
    """The candidate effects for ``spec``.

    Parameters
    ----------
    spec : ModelSpec
    scales : dict, optional
        Typical magnitude (e.g. the std) of each state; sets the free-play widths.
    levels : dict, optional
        (minimum, median, maximum) of each state over the record: an overflow's level is searched between
        the median and the maximum (proposed only where both are positive), a contact's gap out to the
        extreme on its side.
    frequencies : list of float or of (float, float)
        Forcing frequencies (cycles per time unit) found in a residual spectrum, each alone or with the
        width of its spectrum's bins.
    frequency_resolution : float
        Width of the spectrum's bins where a frequency comes alone: a peak locates its line only to about a
        bin, so each forcing's frequency is searched over at least +-1.5 bins around it (else +-3 %).
    extra : list of Effect
        User-supplied effects appended to the library.
    declared : ModelSpec, optional
        The model the user declared, whose drifts say the levels a state is measured from
        (:func:`references`; default ``spec``). The loop passes it: terms it added (an overflow above h0)
        hold levels of their own, which are not the user's.
    """
    scales = scales or {}
    declared = declared or spec
    out: list[Effect] = []
    # the user's inputs (columns of a periodic forcing the loop added are not inputs to build effects from)
    inputs = user_inputs(spec)
    for x, v in oscillator_pairs(spec):
        out += _oscillator_effects(x, v, scales, inputs, (levels or {}).get(x))
        # a spring about a rest position or a drive, -k*(x - x0) or k*(u - x) in the velocity's equation
        if v in declared.drift:
            out += _reference_effects(x, references(declared, x, v))
    for u in inputs:
        out += [Effect(f"input({u})", "input", (u,), f"linear input {u}", code=f"u1{u}"),
                Effect(f"input_quadratic({u})", "input", (f"{u}**2",), f"quadratic input {u}^2", code=f"u2{u}"),
                Effect(f"input_cubic({u})", "input", (f"{u}**3",), f"cubic input {u}^3", code=f"u3{u}"),
                # a zero of the transfer function; for a small lag or lead tau of the input (a skew between the
                # channels, an amplifier's bandwidth) u(t - tau) ~ u - tau du/dt
                Effect(f"input_rate({u})", "input", (RATE_COLUMN.format(u),), f"rate of input {u}, d{u}/dt (a zero; "
                       "a small lead or lag of the input)", code=f"ur{u}", rate_of=u)]
    pair_v = {v for _, v in oscillator_pairs(spec)}
    for s_ in dynamic_states(spec):
        if s_ in pair_v:
            continue  # a velocity: the oscillator families above cover it
        out += _level_effects(s_, scales, inputs, (levels or {}).get(s_))
        out += _reference_effects(s_, references(declared, s_) if s_ in declared.states else [])
    out += flow_effects(spec, scales, levels)
    used = set(spec.inputs)
    free_idx = (i for i in range(100) if f"forcing{i}_sin" not in used)  # columns of forcing already added stay
    for f in frequencies:
        f, resolution = f if isinstance(f, tuple) else (f, frequency_resolution)
        i = next(free_idx)
        w = min(max(0.03 * f, 1.5 * resolution), 0.5 * f)
        out.append(Effect(f"forcing(f={f:.4g})", "forcing", (f"forcing{i}_sin", f"forcing{i}_cos"),
                          f"periodic forcing at {f:.4g} cycles/unit", frequency=float(f),
                          code=f"fo{i}", shape=("f", f - w, f + w)))
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


def _oscillator_effects(x: str, v: str, scales: dict[str, float], inputs: list[str],
                        level: tuple[float, float, float] | None = None) -> list[Effect]:
    """Stiffness, damping, friction, cross, free-play, saturation, contact and input terms of a pair
    dx/dt = v."""
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
        # the width as a shape parameter, from 2 % to 150 % of the displacement's std; x - clip(x, -delta, delta)
        # as two ramps with rounded corners (see _ramp)
        lo, hi = 0.02 * s, 1.5 * s
        out.append(Effect(f"free_play({x})", "free-play",
                          (f"{_ramp(f'{x} - {{delta}}', lo, hi)} - {_ramp(f'-{x} - {{delta}}', lo, hi)}",),
                          f"dead zone of half-width {{delta}} in {x}", code=f"fpw{x}",
                          shape=("delta", lo, hi), degenerate="low"))  # no gap: a linear stiffness
        out.append(Effect(f"saturation({x})", "stiffness", (f"{x} - {{xs}}*tanh({x}/{{xs}})",),
                          f"stiffness that saturates beyond |{x}| ~ {{xs}}", code=f"st{x}",
                          shape=("xs", 0.2 * s, 1.5 * s), degenerate="high"))  # x^3 / 3 xs^2: a cubic
        # a restoring force periodic in x (a pendulum's gravity, a rotor in a periodic field): -k x becomes
        # -k L sin(x/L); its quintic and higher orders are tied to the cubic, so it extrapolates in amplitude.
        # Written as x^3 + O(x^5 / L^2) so that the coefficient is the cubic's and L only bends the higher
        # orders (with x - L sin(x/L) ~ x^3 / 6 L^2 the two trade off along a curved ridge)
        out.append(Effect(f"sine_stiffness({x})", "stiffness", (f"6*{{L}}**2*({x} - {{L}}*sin({x}/{{L}}))",),
                          f"restoring force periodic in {x}, L sin({x}/L) with L = {{L}}", code=f"sn{x}",
                          shape=("L", 0.3 * s, 3.0 * s), degenerate="high"))  # the cubic itself
        out += _contacts(x, s, level)
    sv = scales.get(v)
    if sv and sv > 0:
        # dry friction with a smooth sign (the EKF sees its slope) and Stribeck's decaying static peak
        out.append(Effect(f"dry_friction({v})", "friction", (f"tanh({v}/{{vs}})",),
                          "dry (Coulomb) friction, smooth sign over {vs}", code=f"fd{v}",
                          shape=("vs", 0.005 * sv, 0.3 * sv), degenerate="high"))  # v / vs: viscous damping
        out.append(Effect(f"stribeck({v})", "friction", (f"tanh({v}/{0.01 * sv:.3g})*exp(-({v}/{{vs}})**2)",),
                          "Stribeck friction peak decaying over {vs}", code=f"fs{v}",
                          shape=("vs", 0.02 * sv, 1.0 * sv), degenerate="high"))  # no decay: Coulomb
    for u in inputs:
        out += [Effect(f"input_cross({u}*{x})", "input", (f"{u}*{x}",), f"input-state cross term {u} {x}", code=f"u{u}{x}"),
                Effect(f"input_cross({u}*{v})", "input", (f"{u}*{v}",), f"input-velocity cross term {u} {v}", code=f"u{u}{v}")]
    return out


def _ramp(arg: str, lo: float, hi: float) -> str:
    """max(arg, 0) as a hyperbola whose corner is rounded over 1 % of the searched range [lo, hi], not max():
    the likelihood must be smooth in the threshold for the Laplace Hessian (a kink makes its finite
    differences, and so every sd, collapse) and the EKF's Jacobian must see the slope change."""
    w = 0.01 * (hi - lo)
    return f"0.5*(({arg}) + sqrt(({arg})**2 + {w:.4g}**2))"


def _overflow(s_: str, level: tuple[float, float, float] | None) -> tuple | None:
    """(term, shape) of a flow that starts above a level h0 of ``s_``, max(s_ - h0, 0), h0 between the
    state's median and maximum; None without a positive range (the shape is searched on a log scale)."""
    if not level or not (0 < level[1] < level[2]):
        return None
    return _ramp(f"{s_} - {{h0}}", level[1], level[2]), ("h0", float(level[1]), float(level[2]))


def _contacts(x: str, s: float, level: tuple[float, float, float] | None) -> list[Effect]:
    """One-sided stiffness beyond a gap g on either side of the rest position (a stop, a bumper, a contact
    that closes): max(x - g, 0) above, -max(-x - g, 0) below (a negative coefficient restores in both), g
    from 10 % of the std to the record's extreme on that side."""
    out = []
    if not level or not s > 0:
        return out
    lo = 0.1 * s
    for side, code, sign, arg, extreme in (("above", "ca", "", f"{x} - {{g}}", level[2]),
                                           ("below", "cb", "-", f"-{x} - {{g}}", -level[0])):
        if extreme > 1.2 * lo:
            out.append(Effect(f"contact_{side}({x})", "stiffness", (sign + _ramp(arg, lo, extreme),),
                              f"one-sided stiffness {side} a gap {{g}} in {x}", code=f"{code}{x}",
                              shape=("g", lo, float(extreme))))
    return out


def _level_effects(s_: str, scales: dict[str, float], inputs: list[str],
                   level: tuple[float, float, float] | None = None) -> list[Effect]:
    """Terms of any dynamic state that is not a velocity: powers, an orifice outflow, saturation, an overflow,
    offset and input cross terms (first-order, level/flow and coupled models)."""
    out: list[Effect] = []
    sc = scales.get(s_)
    out += [Effect(f"square({s_})", "state", (f"{s_}**2",), f"{s_}^2", code=f"q2{s_}"),
            Effect(f"cube({s_})", "state", (f"{s_}**3",), f"{s_}^3", code=f"q3{s_}"),
            Effect(f"signed_square({s_})", "state", (f"{s_}*abs({s_})",), f"{s_}|{s_}|", code=f"qa{s_}"),
            Effect(f"sqrt_outflow({s_})", "state", (f"sqrt(abs({s_}))*sign({s_})",),
                   f"outflow through an orifice, sqrt({s_})", code=f"qr{s_}"),
            Effect("offset", "offset", ("1",), "constant offset", code="off")]
    # a power law of the level with its exponent fitted: an orifice (1/2), laminar flow (1), a weir (3/2), a
    # turbulent pipe or a reaction order; sign-symmetric so that a level through zero stays smooth
    out.append(Effect(f"power_law({s_})", "state", (f"abs({s_})**{{p}}*sign({s_})",),
                      f"power law |{s_}|^p sign({s_}) with p = {{p}}", code=f"qp{s_}", shape=("p", 0.25, 3.0)))
    if sc and sc > 0:
        out.append(Effect(f"saturation({s_})", "state", (f"{s_} - {{xs}}*tanh({s_}/{{xs}})",),
                          f"{s_} saturating beyond ~{{xs}}", code=f"qs{s_}", shape=("xs", 0.2 * sc, 1.5 * sc),
                          degenerate="high"))  # a cube
    over = _overflow(s_, level)
    if over:
        out.append(Effect(f"overflow({s_})", "state", (over[0],), f"acts only above {s_} = {{h0}} (an overflow)",
                          code=f"qo{s_}", shape=over[1]))
    for u in inputs:
        out += [Effect(f"input_cross({u}*{s_})", "input", (f"{u}*{s_}",), f"input-state cross term {u} {s_}",
                       code=f"u{u}{s_}")]
    return out


def references(spec: ModelSpec, s_: str, equation: str | None = None) -> list[str]:
    """The levels the user's drift of ``equation`` (default ``s_``'s own; an oscillator's position in its
    velocity's) measures ``s_`` from: ``c`` wherever it holds ``s_ - c`` (times a
    number, any sign), ``c`` a nonzero number or one input, parameter or constant (an ambient temperature, a
    set point, a supply pressure; not a derived quantity, which may move with the states: M2's moment lags
    ``P - CM``). Newton cooling ``a*(T - 295)`` declares 295, and so does its expanded form
    ``q*u - 0.5*T + 147.5``."""
    names = declared_names(spec)
    s = sp.Symbol(s_, real=True)
    found = []
    for node in sp.preorder_traversal(parse_expression(spec.drift[equation or s_], names)):
        if not isinstance(node, sp.Add):
            continue
        with_s = [a for a in node.args if a.has(s)]
        others = [a for a in node.args if not a.has(s)]
        k = sp.simplify(sp.Add(*with_s) / s) if with_s else None
        if k is None or not k.is_number or k == 0:
            continue
        # alone beside s_, any constant or name; among other terms (a number distributed over the sum), the
        # numbers only: a forcing such as 2*u is not a level
        rest = others[0] if len(others) == 1 else sp.Add(*[a for a in others if a.is_number])
        if rest == 0:
            continue
        c = -rest / k
        if c.is_number:
            found.append(f"{float(c):.6g}")
        elif c.is_Symbol and str(c) in {*spec.inputs, *spec.parameters, *spec.constants}:
            found.append(str(c))
    return list(dict.fromkeys(found))


def _reference_effects(s_: str, refs: list[str]) -> list[Effect]:
    """Powers of ``s_`` about each level the user's drift measures it from (:func:`references`): where the
    declared law is linear in ``s_ - c``, its nonlinear completion is a series in ``s_ - c``, which vanishes
    where the declared law does. The library's powers of ``s_`` itself vanish at 0, far from such a level
    (radiation to an ambient at 295 K, T^4 - 295^4, is (T - 295) times a cubic in it; a square of T alone
    would move the body's equilibrium, and only with an offset beside it could it stand in)."""
    out = []
    for i, c in enumerate(refs):
        tag = f"{s_}+{c[1:]}" if c.startswith("-") else f"{s_}-{c}"
        d = f"({tag})"
        out += [Effect(f"square({tag})", "state", (f"{d}**2",), f"{d}^2", code=f"r2{i}{s_}"),
                Effect(f"cube({tag})", "state", (f"{d}**3",), f"{d}^3", code=f"r3{i}{s_}"),
                Effect(f"power_law({tag})", "state", (f"abs{d}**{{p}}*sign{d}",),
                       f"power law |{d}|^p sign{d} with p = {{p}}", code=f"rp{i}{s_}", shape=("p", 0.25, 3.0))]
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


def flow_effects(spec: ModelSpec, scales: dict[str, float],
                 levels: dict[str, tuple[float, float, float]] | None = None) -> list[Effect]:
    """Flows between coupled levels (tanks, compartments, thermal masses): for each dynamic state i whose
    value drives another one's drift j, a flow law f(x_i) that leaves i and enters j.

    When one parameter of the model already appears in both drifts (``-a*h1`` in one, ``a*h1`` in the other:
    the model conserves what flows, in its units) the flow has one coefficient; otherwise (levels of tanks
    of different cross-sections) it has one per side. An outflow added to i alone and an inflow to j alone
    would each be screened without the other, and neither would find the pipe between them."""
    pair_v = {v for _, v in oscillator_pairs(spec)}
    states = [s_ for s_ in dynamic_states(spec) if s_ not in pair_v]
    sm = spec.sym
    params = set(sm.params)
    out = []
    for i in states:
        xi = sp.Symbol(i, real=True)
        di = sm.drift[spec.states.index(i)]
        for j in states:
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
            over = _overflow(i, (levels or {}).get(i))
            if over:
                laws.append(("overflow_flow", "fo", over[0], "spilling over above {h0}", over[1]))
            for name, code, term, what, shape in laws:
                out.append(Effect(f"{name}({i}->{j})", "flow", (term,) if one else (term, term),
                                  f"flow from {i} to {j} {what}", code=f"{code}{i}{j}", where="flow",
                                  between=(i, j), shape=shape or ()))
    return out
