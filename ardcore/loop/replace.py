"""Law replacement: a declared law of a first-order state replaced by the same law through a fitted power.

Forward selection adds terms beside what the user declared; when the declared law itself is wrong (a linear
outflow where the flow goes over a weir, h^1.5, or through an orifice, h^0.5; a linear exchange where a
reaction has another order) the added terms only approximate the right law around the recorded levels and
stack up. This move proposes, for every declared law ``p * T`` of a first-order state (a term linear in a
parameter of the user's, ``T`` in states only, ``p`` nowhere but in the drifts where ``T`` leaves or enters),
the model with ``p * |T|^e sign(T)`` in its place, the exponent ``e`` a new parameter under a lognormal prior
around 1 (the declared law itself). It is fitted like any candidate and judged by its evidence against the
current model, with the same multiplicity and never-worse checks as an addition.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import sympy as sp

from ..effects.base import oscillator_pairs
from ..model.declaration import ModelSpec, symbolic
from ..selection.spec import CandidateSpec
from .confirm import Fit, essential_from_row, fit_task, warm_with

POWER_RANGE = (0.25, 4.0)
"""The exponents the prior of ``e`` spans at +-2 sd (an orifice 0.5, laminar 1, a weir 1.5, turbulent 2)."""


class Law(NamedTuple):
    """A declared law ``parameter * term`` and the drifts it is written in (state -> the term there, signed as
    that drift has it: a flow leaves one level and enters another)."""

    parameter: str
    term: str
    drifts: dict


def _text(e: sp.Expr) -> str:
    """A sympy expression in the model language (``abs``, not ``Abs``)."""
    return str(e).replace("Abs(", "abs(")


def declared_laws(spec: ModelSpec, new_parameters: set = frozenset()) -> list[Law]:
    """The declared laws of first-order states a power may replace (module docstring): not an oscillator's
    position or velocity (a spring or a damper is the loop's additions' business), no input in the term, the
    parameter in no diffusion, observation or initial state, and linear wherever it appears."""
    sm = symbolic(spec)
    names = [str(x) for x in sm.states]
    osc = {s for pair in oscillator_pairs(spec) for s in pair}
    inputs = {str(u) for u in sm.inputs}
    elsewhere = [sp.sympify(e) for e in
                 list(sm.diffusion) + list(sm.obs) + list(sm.obs_std) + list(sm.init_mean) + list(sm.init_std)]
    out = []
    for p in sm.params:
        if str(p) in new_parameters or any(p in e.free_symbols for e in elsewhere):
            continue
        where = [j for j, f in enumerate(sm.drift) if p in f.free_symbols]
        terms = [sp.diff(sm.drift[j], p) for j in where]
        if not terms or any(p in t.free_symbols for t in terms):
            continue  # absent, or not linear in p
        used = set().union(*({str(x) for x in t.free_symbols} for t in terms))
        states = used & set(names)
        if not states or used & inputs or used - states or states & osc or any(names[j] in osc for j in where):
            continue
        base = terms[0]
        if any(sp.simplify(t - base) != 0 and sp.simplify(t + base) != 0 for t in terms):
            continue  # a different term in each drift: not one law
        lead = -base if base.could_extract_minus_sign() else base
        out.append(Law(str(p), _text(lead), {names[j]: _text(t) for j, t in zip(where, terms)}))
    return out


def power_law_spec(spec: ModelSpec, law: Law, exponent: str) -> ModelSpec:
    """``spec`` with the law ``p * T`` written ``p * |T|^e sign(T)`` in each of its drifts (``e`` the new
    parameter ``exponent``); the declared term cancels exactly when the expression is parsed."""
    drift = dict(spec.drift)
    p = law.parameter
    for state, t in law.drifts.items():
        # the term with its sign in this drift: the odd power keeps the sign
        drift[state] = f"({drift[state]}) - {p}*({t}) + {p}*(abs({t})**{exponent}*sign({t}))"
    return spec.model_copy(update={"name": (spec.name + "_pw")[:32], "drift": drift,
                                   "parameters": list(spec.parameters) + [exponent]}).revalidate()


def exponent_prior():
    """Lognormal around 1 with :data:`POWER_RANGE` at +-2 sd of ln e."""
    from ..model.priors import LogNormal

    lo, hi = POWER_RANGE
    s = math.log(hi / lo) / 4.0
    return LogNormal(median=1.0, cov=100.0 * math.sqrt(math.expm1(s * s)))


def best_power_law(spec, current: Fit, config, say, mapper, new_parameters: set = frozenset()):
    """The declared law (module docstring) whose fitted power is worth most, as ``(fit, record)``, or None.

    Every candidate law is fitted side by side on the loop's pool; the best qualifies when its ln Bayes
    factor against the current model exceeds ``config.min_log_bf`` plus ln of the number of laws tried (their
    multiplicity, as for additions) and its free run on the estimation record is no worse. The record says
    what was replaced (parameter, term, target, by, the exponent's posterior, ln BF); the caller weighs it
    against the round's additions (:func:`~ardcore.loop.diagnose.diagnose`)."""
    from .checks import free_run_rms, worse_than_before

    ms = current.cand.model_spec()
    laws = [w for w in declared_laws(ms, new_parameters) if f"e_{w.parameter}"[:32] not in ms.parameters]
    if not laws:
        return None
    priors, fixed = essential_from_row(current.cand, current.row)
    tasks = []
    for w in laws:
        e = f"e_{w.parameter}"[:32]
        pspec = power_law_spec(ms, w, e)
        cand = CandidateSpec(model=pspec, name=pspec.name, priors={**priors, e: exponent_prior()}, fixed=fixed,
                             substeps=current.cand.substeps)
        warm = warm_with(current.mr.sampler, [e], [1.0]) if current.mr.sampler is not None else None
        tasks.append((cand, current.data, spec, warm, config.posterior))
    fits = mapper(fit_task, tasks)
    gain = np.array([row.log_evidence - current.row.log_evidence for row, _ in fits], dtype=float)
    if not np.isfinite(gain).any():
        return None
    need = config.min_log_bf + math.log(len(tasks))
    k = int(np.nanargmax(np.where(np.isfinite(gain), gain, -np.inf)))
    w, (row, mr) = laws[k], fits[k]
    e = f"e_{w.parameter}"[:32]
    if not gain[k] > need:
        say(f"  the declared {w.parameter}*({w.term}) is no worse than its power law "
            f"(ln BF {gain[k]:.1f} at {e} = {row.mean.get(e, float('nan')):.3g}, needs {need:.1f})")
        return None
    fit = Fit(tasks[k][0], row, mr, current.data)
    why = worse_than_before(fit, free_run_rms(current, config), config)
    if why is not None:
        say(f"  the declared {w.parameter}*({w.term}) stays: with its power law {why}")
        return None
    by = f"{w.parameter}*|{w.term}|^{e}*sign({w.term})"
    say(f"  {w.parameter}*({w.term}) through a power: {by}, {e} = {row.mean[e]:.3g} +- {row.sd[e]:.2g} "
        f"(ln BF {gain[k]:.1f})")
    return fit, {"parameter": w.parameter, "term": w.term, "target": next(iter(w.drifts)), "by": by,
                 "exponent": exponent_summary(row, e), "log_bayes_factor": float(gain[k])}


def exponent_summary(row, name: str) -> dict:
    """The exponent's posterior in a fit's summary row (mean, sd, 99 % interval)."""
    return {"name": name, "mean": float(row.mean[name]), "sd": float(row.sd[name]),
            "q005": float(row.q005[name]), "q995": float(row.q995[name])}
