"""Law replacement: a declared law replaced by the same law in another form.

Forward selection adds terms beside what the user declared; when the declared law itself is wrong (a linear
outflow where the flow goes over a weir, h^1.5, or through an orifice, h^0.5; a flow that saturates; a flow
that starts only above a crest) the added terms only approximate the right law around the recorded levels
and stack up. This move proposes, for every declared law ``p * T`` of a first-order state (a term linear in
a parameter of the user's, ``T`` in states only, ``p`` nowhere but in the drifts where ``T`` leaves or
enters), the model with ``p * F(T)`` in its place, for each form F (:data:`FORMS`) with its shape a new
parameter under a lognormal prior that holds the declared law at one end or in the middle:

* ``power``: ``|T|^e sign(T)``, e around 1 (an orifice 0.5, laminar 1, a weir 1.5, turbulent 2);
* ``saturation``: ``s tanh(T / s)``, a law that levels off beyond s (a pump, a valve at its stop);
* ``knee``: ``max(T - c, 0)`` with its corner rounded, a law that starts only above c (a crest, a
  threshold), for a term that stays positive (a level).

A declared **coupling** to an input (``k * (u - y)``: a load driven through a gear or a linkage, in any state's
drift, an oscillator's too) is offered in the forms of :data:`COUPLING_FORMS`, the first of them:

* ``dead_zone``: ``sign(T) max(|T| - d, 0)`` with its corners rounded, slack of half-width d (a backlash, a
  free-play in the drive).

Each is fitted like any candidate and judged by its evidence against the current model, with the same
multiplicity and never-worse checks as an addition; the loop takes it when it is worth more than the round's
best addition.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import sympy as sp

from ..effects.base import oscillator_pairs
from ..likelihood.ekf import compile_model
from ..model.declaration import ModelSpec, symbolic
from ..model.priors import LogNormal
from ..selection.spec import CandidateSpec
from .confirm import Fit, essential_from_row, fit_task, warm_with
from .freerun import fitted

POWER_RANGE = (0.25, 4.0)
"""The exponents the prior of ``e`` spans at +-2 sd (an orifice 0.5, laminar 1, a weir 1.5, turbulent 2)."""


class Law(NamedTuple):
    """A declared law ``parameter * term`` and the drifts it is written in (state -> +1 or -1, the term's sign
    there: a flow leaves one level and enters another), and the names of the :data:`FORMS` it is offered in."""

    parameter: str
    term: str
    drifts: dict
    forms: tuple = ("power", "saturation", "knee")


COUPLING_FORMS = ("dead_zone", "saturation", "power")
"""The forms of a coupling to an input (a drive through a gear or a linkage, ``k * (u - y)``): slack in it (a
backlash, a free-play), a limit on what it transmits (a slipping clutch), or a power law."""


def _settled(e: sp.Expr) -> sp.Expr:
    """``e`` with every number at 12 significant digits. A law's text holds its width as ``w**2``; once a model's
    equation has been printed and parsed again that square is one number, which may differ from the text's in
    its last bit, and sympy would keep both terms of a difference that is zero (the old shape left in the model
    while its parameter is gone)."""
    return e.xreplace({f: sp.Float(f"{float(f):.12g}") for f in e.atoms(sp.Float)})


def _text(e: sp.Expr) -> str:
    """A sympy expression in the model language (``abs``, not ``Abs``)."""
    return str(e).replace("Abs(", "abs(")


class LinearTerm(NamedTuple):
    """A free parameter of the user's that multiplies a term linearly wherever it appears: ``terms`` maps each
    drift it appears in (in the model's state order) to that term, ``names`` every symbol the terms use."""

    parameter: str
    terms: dict
    names: set


def linear_terms(spec: ModelSpec, new_parameters: set = frozenset()) -> list[LinearTerm]:
    """The parameters of the user's (not in ``new_parameters``) that appear in no diffusion, observation or
    initial state and linearly in every drift they appear in: fixing one to 0 removes exactly its terms. What
    law replacement (:func:`declared_laws`) and the drop move (:func:`~ardcore.loop.checks.declared_rivals`)
    start from."""
    sm = symbolic(spec)
    names = [str(x) for x in sm.states]
    elsewhere = [sp.sympify(e) for e in
                 list(sm.diffusion) + list(sm.obs) + list(sm.obs_std) + list(sm.init_mean) + list(sm.init_std)]
    out = []
    for p in sm.params:
        if str(p) in new_parameters or any(p in e.free_symbols for e in elsewhere):
            continue
        where = [j for j, f in enumerate(sm.drift) if p in f.free_symbols]
        terms = {names[j]: sp.diff(sm.drift[j], p) for j in where}
        if not terms or any(p in t.free_symbols for t in terms.values()):
            continue  # absent, or not linear in p (a derivative free of p means drift = p * term + rest)
        out.append(LinearTerm(str(p), terms, set().union(*({str(x) for x in t.free_symbols}
                                                           for t in terms.values()))))
    return out


def declared_laws(spec: ModelSpec, new_parameters: set = frozenset()) -> list[Law]:
    """The declared laws another form may replace (module docstring), the parameter in no diffusion,
    observation or initial state and linear wherever it appears:

    * a law of first-order states: its term in states only, none an oscillator's position or velocity (a
      spring or a damper is the loop's additions' business);
    * a **coupling** to an input: a term in one drift that holds both inputs and states (a drive through a
      gear, ``k * (u - y)``), offered in :data:`COUPLING_FORMS`; the additions act on a state or an input
      alone and cannot put slack between the two."""
    states = set(spec.states)
    osc = {s for pair in oscillator_pairs(spec) for s in pair}
    inputs = set(spec.inputs)
    out = []
    for lt in linear_terms(spec, new_parameters):
        used = lt.names & states
        if used and lt.names & inputs and len(lt.terms) == 1 and not lt.names - used - inputs:
            term, = lt.terms.values()
            lead = -term if term.could_extract_minus_sign() else term
            out.append(Law(lt.parameter, _text(lead), {s: 1 if sp.simplify(t - lead) == 0 else -1
                                                       for s, t in lt.terms.items()}, COUPLING_FORMS))
            continue
        if not used or lt.names & inputs or lt.names - used or used & osc or set(lt.terms) & osc:
            continue
        base = next(iter(lt.terms.values()))
        if any(sp.simplify(t - base) != 0 and sp.simplify(t + base) != 0 for t in lt.terms.values()):
            continue  # a different term in each drift: not one law
        lead = -base if base.could_extract_minus_sign() else base
        out.append(Law(lt.parameter, _text(lead), {s: 1 if sp.simplify(t - lead) == 0 else -1
                                                   for s, t in lt.terms.items()}))
    return out


class Form(NamedTuple):
    """One form a declared law may take: its name, the prefix of its shape parameter, ``text(T, shape)`` the
    law in the model language, and ``prior(values of T)`` the shape's prior (None: not for these values)."""

    name: str
    prefix: str
    text: object
    prior: object


def _power_prior(values: np.ndarray):
    lo, hi = POWER_RANGE
    return LogNormal.spanning(1.0, lo, hi)


def _saturation_prior(values: np.ndarray):
    """Saturation from a fifth of the term's largest size to five times it (far out: the declared law)."""
    top = float(np.nanmax(np.abs(values)))
    return LogNormal.spanning(top, 0.2 * top, 5.0 * top) if top > 0 else None


def _knee_prior(values: np.ndarray):
    """A knee inside the recorded values of a term that stays positive (a level): from 1 % of its median to
    its 95th percentile."""
    q05, q50, q95 = np.nanquantile(values, [0.05, 0.5, 0.95])
    if not (q05 > 0 and q95 > q50 > 0):
        return None
    return LogNormal.spanning(math.sqrt(0.01 * q50 * q95), 0.01 * q50, float(q95))


def _dead_zone_prior(values: np.ndarray):
    """A half-width of the slack from 1 % of the term's median size to its 95th percentile."""
    q50, q95 = np.nanquantile(np.abs(values), [0.5, 0.95])
    if not q95 > q50 > 0:
        return None
    return LogNormal.spanning(math.sqrt(0.01 * q50 * q95), 0.01 * q50, float(q95))


def _dead_zone_text(t: str, d: str, width: float) -> str:
    """``sign(T) max(|T| - d, 0)``, its corners rounded over ``width``: zero inside the slack, the declared law
    shifted by the slack outside it."""
    w = f"{width:.4g}"
    return (f"0.5*((({t}) - {d}) + sqrt((({t}) - {d})**2 + {w}**2)) "
            f"+ 0.5*((({t}) + {d}) - sqrt((({t}) + {d})**2 + {w}**2))")


def _knee_text(t: str, c: str, width: float) -> str:
    arg = f"({t}) - {c}"
    return f"0.5*(({arg}) + sqrt(({arg})**2 + {width:.4g}**2))"


FORMS = {
    "power": Form("power", "e", lambda t, e, v: f"abs({t})**{e}*sign({t})", _power_prior),
    "saturation": Form("saturation", "sat", lambda t, s_, v: f"{s_}*tanh(({t})/{s_})", _saturation_prior),
    # the corner rounded over 1 % of the recorded range, as the library's ramps (smooth for the EKF's slope)
    "knee": Form("knee", "knee", lambda t, c, v: _knee_text(t, c, 0.01 * float(np.nanmax(v) - np.nanmin(v))),
                 _knee_prior),
    "dead_zone": Form("dead_zone", "gap", lambda t, d, v: _dead_zone_text(
        t, d, 0.01 * float(np.nanmax(v) - np.nanmin(v))), _dead_zone_prior),
}
"""The forms a declared law is offered in (module docstring)."""


def law_spec(spec: ModelSpec, law: Law, form: Form, shape: str, values: np.ndarray) -> ModelSpec:
    """``spec`` with the law ``p * T`` written ``p * F(T)`` in each of its drifts, with the sign the term has
    there (``shape`` the form's new parameter); the declared term cancels exactly when the expression is
    parsed."""
    drift = dict(spec.drift)
    p, t = law.parameter, law.term
    law_text = form.text(t, shape, values)
    for state, sign in law.drifts.items():
        drift[state] = f"({drift[state]}) - {sign}*{p}*({t}) + {sign}*{p}*({law_text})"
    return spec.model_copy(update={"name": (spec.name + "_" + form.prefix)[:32], "drift": drift,
                                   "parameters": list(spec.parameters) + [shape]}).revalidate()


def term_values(current: Fit, law: Law) -> np.ndarray:
    """The declared term along the record: the filtered states at the posterior mean put into it."""
    fspec, phi = fitted(current.cand, current.row)
    fr = compile_model(fspec).filter(phi, current.data, current.cand.substeps)
    names = list(fspec.states) + list(fspec.inputs)
    f = sp.lambdify([sp.Symbol(n, real=True) for n in names], sp.sympify(law.term.replace("abs(", "Abs(")),
                    modules="numpy")
    cols = [current.data.columns[u] for u in fspec.inputs]
    return np.asarray(f(*fr.filtered.T, *cols), dtype=float) * np.ones(len(current.data))


def best_laws(ctx, current: Fit, new_parameters: set = frozenset(), replaced: list = (), crit=None):
    """The declared laws worth replacing, one after another, as ``(fit, records, ln BF)``, or None.

    :func:`best_law` on the current model, then again on the model it leaves, while one qualifies (two wrong
    laws of a cascade are each worth less alone than a stand-in that patches both, and more together). The
    caller weighs the total ln Bayes factor against the round's best addition. ``replaced``: the records of
    the laws replaced in earlier rounds, which may change form again (:func:`best_law`). ``crit``: the loop's
    :class:`~.criterion.Criterion`, which chooses between the forms that qualify (None: the evidence does)."""
    fit, records = current, []
    while (got := best_law(ctx, fit, new_parameters, [*replaced, *records], crit)) is not None:
        fit = got[0]
        records.append(got[1])
    if not records:
        return None
    return fit, records, float(fit.row.log_evidence - current.row.log_evidence)


def _reforms(current: Fit, replaced: list) -> list:
    """(law, its form now, its shape now, the law's text now) of every law an earlier round replaced and the
    model still holds in that form (the latest record of each law)."""
    params = set(current.cand.model_spec().parameters)
    out, seen = [], set()
    for x in reversed(replaced):
        key = (x.get("parameter"), x.get("term"))
        if key in seen or not x.get("law_text") or x.get("shape", {}).get("name") not in params:
            continue
        seen.add(key)
        out.append((Law(x["parameter"], x["term"], dict(x["drifts"]), tuple(x.get("forms", ()))),
                    FORMS[x["form"]], x["shape"]["name"], x["law_text"]))
    return out


def reform_spec(spec: ModelSpec, law: Law, now: tuple, form: Form, shape: str, values: np.ndarray) -> ModelSpec:
    """``spec`` with a law already replaced (``now``: its shape and its text in the model) written in another
    ``form`` (``shape`` its new parameter): the law's text cancels exactly when the expression is parsed, and
    the old shape leaves the parameters."""
    from ..model.expr import parse_expression

    old_shape, old_text = now
    drift = dict(spec.drift)
    names = {*spec.states, *spec.inputs, *spec.parameters, *spec.constants, *spec.derived, shape}
    p = parse_expression(law.parameter, names)
    old = _settled(parse_expression(old_text, names))
    new = parse_expression(form.text(law.term, shape, values), names)
    gone = sp.Symbol(old_shape)
    for state, sign in law.drifts.items():
        # in sympy, not as text: the old shape must be gone from the text the model is validated from
        e = _settled(parse_expression(drift[state], names)) - sign * p * old + sign * p * new
        if gone in e.free_symbols:
            raise ValueError(f"the law {law.parameter}*({law.term}) in its {old_shape} form is not in the "
                             f"{state} equation as recorded")
        drift[state] = _text(e)
    params = [q for q in spec.parameters if q != old_shape] + [shape]
    return spec.model_copy(update={"name": (spec.name + "_" + form.prefix)[:32], "drift": drift,
                                   "parameters": params}).revalidate()


def best_law(ctx, current: Fit, new_parameters: set = frozenset(), replaced: list = (), crit=None):
    """The declared law and form (module docstring) worth most, as ``(fit, record)``, or None.

    A law an earlier round replaced (``replaced``: their records) is offered in its other forms too: which
    form a wrong law takes first depends on what else the model lacks then (a pipe's square root looks like
    a saturation while the overflow it feeds is missing), and once that is in, the law may be worth more in
    another form.

    Every candidate is fitted side by side on the loop's pool; one qualifies when its ln Bayes factor against
    the current model exceeds ``config.min_log_bf`` plus ln of the number of candidates tried (their
    multiplicity, as for additions) and its fit is a result. Of several that qualify, ``crit`` (the loop's
    :class:`~.criterion.Criterion`) takes the one that free-runs best held out
    (:meth:`~.criterion.Criterion.alternative`; without it, the highest evidence); the criterion then judges it
    beside the round's additions (:mod:`.criterion`). The record says
    what was replaced (parameter, term, target, by, form, the shape's posterior, ln BF)."""

    spec, config, say, mapper = ctx.spec, ctx.config, ctx.say, ctx.mapper
    ms = current.cand.model_spec()
    priors, fixed = essential_from_row(current.cand, current.row)
    tasks, offered = [], []
    for w in declared_laws(ms, new_parameters):
        values = None
        for form in (FORMS[f] for f in w.forms):
            shape = f"{form.prefix}_{w.parameter}"[:32]
            if any(f"{f.prefix}_{w.parameter}"[:32] in ms.parameters for f in FORMS.values()):
                break  # a law already in another form is not offered again
            if values is None:
                values = term_values(current, w)
            prior = form.prior(values)
            if prior is None:
                continue
            pspec = law_spec(ms, w, form, shape, values)
            cand = CandidateSpec(model=pspec, name=pspec.name, priors={**priors, shape: prior}, fixed=fixed,
                                 substeps=current.cand.substeps)
            # started where the form is closest to the declared law (its prior's median)
            warm = warm_with(current.mr.sampler, [shape], [prior.median]) if current.mr.sampler is not None else None
            tasks.append((cand, current.data, spec, warm, config.posterior))
            offered.append((w, form, shape))
    for w, now_form, now_shape, now_text in _reforms(current, replaced):
        values = term_values(current, w)
        for form in (FORMS[f] for f in w.forms):
            shape = f"{form.prefix}_{w.parameter}"[:32]
            prior = form.prior(values)
            if form.name == now_form.name or prior is None or shape in ms.parameters:
                continue
            try:
                pspec = reform_spec(ms, w, (now_shape, now_text), form, shape, values)
            except ValueError as e:  # the model no longer holds the law as recorded: it keeps its form
                say(f"  {w.parameter}*({w.term}) is not offered as a {form.name} law: {e}")
                continue
            cpriors = {k: v for k, v in priors.items() if k != now_shape}
            cfixed = {k: v for k, v in fixed.items() if k != now_shape}
            cand = CandidateSpec(model=pspec, name=pspec.name, priors={**cpriors, shape: prior}, fixed=cfixed,
                                 substeps=current.cand.substeps)
            warm = warm_with(current.mr.sampler, [shape], [prior.median]) if current.mr.sampler is not None else None
            tasks.append((cand, current.data, spec, warm, config.posterior))
            offered.append((w, form, shape))
    if not tasks:
        return None
    fits = mapper(fit_task, tasks)
    gain = np.array([row.log_evidence - current.row.log_evidence for row, _ in fits], dtype=float)
    if not np.isfinite(gain).any():
        return None
    need = config.min_log_bf + math.log(len(tasks))
    why = [row.degenerate() for row, _ in fits]
    ok = [i for i in range(len(tasks)) if np.isfinite(gain[i]) and gain[i] > need and why[i] is None]
    if not ok:
        k = int(np.nanargmax(np.where(np.isfinite(gain), gain, -np.inf)))
        w, form, _ = offered[k]
        if gain[k] > need:
            say(f"  the declared {w.parameter}*({w.term}) stays: as a {form.name} law {why[k]}")
        else:
            say(f"  the declared {w.parameter}*({w.term}) is no worse than any other form (best: {form.name}, ln BF "
                f"{gain[k]:.1f}, needs {need:.1f})")
        return None
    k = ok[0]
    if len(ok) > 1:
        say("  the forms the evidence supports (ln BF): " + ", ".join(
            f"{offered[i][0].parameter} as {offered[i][1].name} {gain[i]:.1f}" for i in ok))
        if crit is not None:
            # the free run on held-out blocks, not a few nats of one-step evidence, says which form is the law
            j, _ = crit.alternative(current, [Fit(tasks[i][0], *fits[i], current.data) for i in ok],
                                    [f"{offered[i][0].parameter} as {offered[i][1].name}" for i in ok])
            k = ok[j]
        else:
            k = max(ok, key=lambda i: gain[i])
    (w, form, shape), (row, mr) = offered[k], fits[k]
    by = {"power": f"{w.parameter}*|{w.term}|^{shape}*sign({w.term})",
          "saturation": f"{w.parameter}*{shape}*tanh({w.term}/{shape})",
          "knee": f"{w.parameter}*max({w.term} - {shape}, 0)",
          "dead_zone": f"{w.parameter}*sign({w.term})*max(|{w.term}| - {shape}, 0)"}[form.name]
    fit = Fit(tasks[k][0], row, mr, current.data)
    say(f"  {w.parameter}*({w.term}) as a {form.name} law: {by}, {shape} = {row.mean[shape]:.3g} +- "
        f"{row.sd[shape]:.2g} (ln BF {gain[k]:.1f})")
    return fit, {"parameter": w.parameter, "term": w.term, "target": next(iter(w.drifts)), "by": by,
                 "form": form.name, "shape": shape_summary(row, shape), "log_bayes_factor": float(gain[k]),
                 "drifts": dict(w.drifts), "forms": list(w.forms),
                 "law_text": form.text(w.term, shape, term_values(current, w))}


def shape_summary(row, name: str) -> dict:
    """A form's shape parameter as a fit's summary row has it (mean, sd, 99 % interval)."""
    return {"name": name, "mean": float(row.mean[name]), "sd": float(row.sd[name]),
            "q005": float(row.q005[name]), "q995": float(row.q995[name])}
