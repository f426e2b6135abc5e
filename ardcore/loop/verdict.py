"""What the closed loop returns and says about a model.

A :class:`Diagnosis` holds the JSON report (``to_json``), the arrays its figures are drawn from, and the
initial and final models as :class:`FittedModel` (what a free run on a further held-out record needs). The
loop's rounds are :class:`LoopRound` while it runs: the round's JSON record beside the effects it added. The
rest is the report's words: the character of an added term, the verdict when nothing is added, what was withheld
or replaced, the declared parameters that moved, and the report that holds them (:func:`report`, used by
:func:`ardcore.loop.diagnose.diagnose`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import sympy as sp

from ..data import Dataset
from ..effects.base import Effect, oscillator_pairs, with_columns
from ..jsonio import number, to_jsonable
from ..model.declaration import ModelSpec
from ..selection.fit import ModelFit


@dataclass(frozen=True)
class FittedModel:
    """A model as the loop fitted it: pruned terms fixed, its posterior mean, the effects added (whose input
    columns a record must be given before a free run) and its sub-steps."""

    spec: ModelSpec
    phi: dict
    effects: tuple[Effect, ...] = ()
    substeps: int | None = None

    def free_run(self, record: Dataset, **kw) -> dict:
        """:func:`ardcore.loop.freerun.free_run` of this model on ``record`` (the effects' columns added to it)."""
        from .freerun import free_run

        for e in self.effects:
            record = with_columns(record, e)
        return free_run(self.spec, self.phi, record, substeps=self.substeps, **kw)


@dataclass
class LoopRound:
    """One round of the loop: its JSON record (ranking, confirmations, what was added, the error after) and
    the effects it added, as effects (``effects``) and as what they must keep earning (``added``,
    :class:`ardcore.loop.checks.Added`)."""

    record: dict
    effects: list = field(default_factory=list)
    added: list = field(default_factory=list)


@dataclass(frozen=True)
class Diagnosis:
    """The closed loop's result.

    Attributes
    ----------
    report : dict
        What :meth:`to_json` writes: ``before``/``after`` tests and errors, ``rounds``, ``candidates``,
        ``confirmed``, ``added``, ``removed``, ``parameter_shifts``, ``verdict``, ``final_fit``, ``wall_s``.
    arrays : dict
        ``before``/``after``: residual tests with spectra, innovations, injected process noise, free run.
    initial, final : FittedModel
        The model as given (at its posterior mean) and the one model the loop reports (``report["reported"]``):
        the final structure at the process-noise level that free-runs best on the held-out end of the
        estimation record (:mod:`ardcore.loop.simulation_fit`), its posterior mean at that level.
    """

    report: dict
    arrays: dict
    initial: FittedModel
    final: FittedModel
    posterior: FittedModel | None = None
    """The final structure at its posterior mean (``final`` itself when the chosen noise factor is 1): what
    the reported model is compared with (``report["reported"]["posterior_mean_free_run"]``)."""

    @property
    def verdict(self) -> str:
        return self.report["verdict"]

    @property
    def added(self) -> list:
        """The effects added and kept (their JSON records)."""
        return self.report["added"]

    def to_json(self) -> dict:
        """The report as plain JSON values (pruned alphas as in :mod:`ardcore.jsonio`)."""
        return to_jsonable(self.report)


_ODD = ("cubic_stiffness", "quintic_stiffness", "saturation", "sine_stiffness")


def character(spec: ModelSpec, phi: dict, eff: Effect, best: dict) -> str | None:
    """'hardening' or 'softening' for an odd stiffness term (its sign against the linear restoring slope),
    stiffer or softer beyond the gap for a one-sided contact; even and asymmetric terms (x^2, x|x|, x^4) make
    the stiffness differ between the two sides instead."""
    if eff.kind != "stiffness" or len(eff.terms) != 1 or not best["posterior"]:
        return None
    contact = eff.name.startswith("contact_")
    if not eff.name.startswith(_ODD) and not contact:
        return "asymmetric (stiffer on one side)"
    pairs = oscillator_pairs(spec)
    if not pairs:
        return None
    x, v = pairs[0]
    sm = spec.sym
    i = spec.states.index(best["target"])
    xs = sp.Symbol(x, real=True)
    slope = sp.diff(sm.drift[i], xs).subs({p: phi[str(p)] for p in sm.params})
    slope = slope.subs({s: 0 for s in sm.states}).subs({u: 0 for u in sm.inputs})
    try:
        slope = float(slope)
    except TypeError:
        return None
    coef = next(iter(best["posterior"].values()))["mean"]
    if slope == 0 or coef == 0:
        return None
    same = np.sign(coef) == np.sign(slope)
    if contact:  # its term rises with slope 1 beyond the gap on either side: the coefficient adds to the slope
        return "a stop: stiffer beyond the gap" if same else "softer beyond the gap"
    return "hardening" if same else "softening"


def unexplained(res, ranked: list, confirmed: list, col: str, config) -> str:
    t = res.tests[col]
    white = t["ljung_box_p"] > 0.01
    parts = []
    if white and not t["spectrum"]["peaks"]:
        parts.append("the innovations are white (Ljung-Box p = %.3g) with no spectral peak: "
                     "no evidence of a missing effect" % t["ljung_box_p"])
    else:
        screened_out = ranked and not any(number(c["log_bayes_factor"]) > config.min_score for c in ranked)
        # every confirmed candidate rejected by the full evidence (not merely unstable): the same conclusion
        rejected = confirmed and not any(c.get("survives") or c.get("stability") for c in confirmed)
        if screened_out or rejected:
            # the conclusion first: a right model with coloured noise and a missed effect must not read alike
            parts.append("no effect of the library is supported by the evidence, so the model is adequate as far "
                         "as the library can tell; the correlation left in the innovations is NOT explained by any "
                         "effect in the library (it lies outside the library or in the noise model)")
        else:
            parts.append("the residual is NOT explained by any effect in the library")
        parts.append("Ljung-Box Q = %.1f (p = %.2g)" % (t["ljung_box"], t["ljung_box_p"]))
        if t["spectrum"]["peaks"]:
            parts.append("innovation spectral peaks at " + ", ".join(
                "%.4g%s" % (p["f"], f" (harmonic {p['harmonic']})" if p.get("harmonic") else "")
                for p in t["spectrum"]["peaks"][:5]))
        var = {s: float(np.nanvar(r)) for s, r in res.process_noise_rate.items()}
        if var:
            parts.append("injected process noise per state (variance of rate): " + ", ".join(
                f"{s} {v:.3g}" for s, v in var.items()))
        share = injected_share(res)
        if share:
            parts.append("the noise the filter injects is " + ", ".join(
                f"{100 * v:.2g} % of the rms rate of change of {s}" for s, v in share.items())
                + ("" if max(share.values()) > 0.1 else
                   " (small: the model's dynamics carry the data; what remains is small or outside the dynamics, "
                   "e.g. coloured measurement noise)"))
    unstable = [c for c in confirmed if c.get("stability") and not c["stability"]["stable"]]
    if unstable:
        parts.append("supported by evidence but NOT stable between the two halves of the record (a term "
                     "compensating for something that changes over time, not the missing effect): " + ", ".join(
                         f"{c['effect']} (ln BF {_nats(c['log_bayes_factor'])}, z = "
                         f"{max(c['stability']['z'].values()):.1f})" for c in unstable))
    rest = [c for c in confirmed if c not in unstable]
    if rest:
        parts.append("tested by evidence and rejected: " + ", ".join(
            f"{c['effect']} (" + (f"ln BF {_nats(c['log_bayes_factor'])}" if _finite(c["log_bayes_factor"])
                                  else "its fit gave no evidence that is a result") + ")" for c in rest))
    elif ranked and not confirmed:
        parts.append(f"no candidate's screened ln Bayes factor reaches {config.min_score:g} (best: "
                     f"{ranked[0]['effect']} on {ranked[0]['target']}, {_nats(ranked[0]['log_bayes_factor'])})")
    return "; ".join(parts)


def _finite(x) -> bool:
    """Whether a number of the JSON records (infinities written "inf"/"-inf") is finite."""
    return math.isfinite(number(x))


def _nats(x) -> str:
    """A ln Bayes factor of the JSON records at one decimal ("-inf" as it is)."""
    return f"{number(x):.1f}" if _finite(x) else str(x)


def injected_share(res) -> dict:
    """rms of the injected noise rate / rms rate of change of each dynamic state (how much the filter had to push)."""
    out = {}
    for s, r in res.process_noise_rate.items():
        if s not in res.states:
            continue
        rate = np.diff(res.smoothed[:, res.states.index(s)]) / res.dt
        d = float(np.sqrt(np.nanmean((rate - np.nanmean(rate)) ** 2)))
        if d > 0 and np.isfinite(d):
            out[s] = float(np.sqrt(np.nanmean(r ** 2))) / d
    return out


def headline(report: dict, col: str, unit: str = "") -> str:
    """The verdict in at most three short sentences that agree with the report's own tests: what was added
    (or replaced), the error before and after, and whether structure is left in the innovations."""
    u = f" {unit}" if unit else ""
    added, replaced = report.get("added") or [], report.get("replaced") or []
    before, after = report["before"], report.get("after") or report["before"]
    if added or replaced:
        swaps = [state_words(r) if r.get("state") else
                 f"the declared {r['parameter']}*({r['term']}) replaced by {r['by']}"
                 + (f" ({r['shape']['name']} = {r['shape']['mean']:.3g})" if r.get("shape") else "")
                 for r in replaced]
        what = ("Added " + ", ".join(f"{x['effect']} to the {x['target']} equation" for x in added)
                + (", with " + ", ".join(swaps) if swaps else "") if added else
                ("In the " + replaced[0]["target"] + " equation, " if len(replaced) == 1 and not replaced[0].get("state")
                 else "") + "; ".join(swaps))
        what = what[0].upper() + what[1:] + (f"; {_not_kept(report)}." if report.get("withheld") else ".")
        error = (f"Free-run RMS error {before['free_run']['rms_error']:.3g}{u} -> "
                 f"{after['free_run']['rms_error']:.3g}{u}; ln Z {before['log_evidence']:.1f} -> "
                 f"{after['log_evidence']:.1f}.")
    else:
        what = (f"Nothing was added: {_not_kept(report)}." if report.get("withheld") else
                "Nothing was screened (no round was run): the model as given." if not report.get("rounds", [0]) else
                "Nothing was added: no effect of the library is supported by the evidence.")
        # the reported model: the declared structure, at the noise level chosen for it
        reported = (report.get("reported") or {}).get("free_run") or before["free_run"]
        error = f"Free-run RMS error {reported['rms_error']:.3g}{u}."
    p = ((report.get("tests_after") or report.get("tests_before") or {}).get(col) or {}).get("ljung_box_p")
    if p is None:
        left = ""
    elif p < 0.01:
        left = (f" Structure remains in the innovations (Ljung-Box p = {p:.1g}) that no effect of the library "
                "explains.")
    else:
        left = f" The innovations left are white (Ljung-Box p = {p:.2f})."
        z = number((report.get("after") or before).get("standardized_rms"))
        lo, hi = INNOVATION_RMS_RANGE
        if math.isfinite(z) and not lo <= z <= hi:
            # white, but not of the size the filter expects: its noise model is wrong, the model is not adequate
            left = (f" The innovations left are white (Ljung-Box p = {p:.2f}) but their standardised RMS is {z:.2f} "
                    "(1 when the filter's variances are right): the declared noise does not match the data.")
        rel = ((report.get("reported") or {}).get("free_run") or after["free_run"]).get("relative_rms_error")
        if isinstance(rel, (int, float)) and rel > POOR_FREE_RUN:
            # white innovations say the filter predicts one step; its process noise may cover what is missing
            left = (f" The innovations are white (Ljung-Box p = {p:.2f}), but the free run misses {rel:.0%} of the "
                    "output's spread: the process noise covers what the model lacks.")
    if report.get("stopped_by") == "round_cap":
        n = report.get("max_rounds", 0)
        left += (f" The loop stopped at its cap of {n} round{'s' if n != 1 else ''}, not by its criterion: "
                 "run it with more (--max-rounds) to see whether a further move free-runs better.")
    return f"{what} {error}{left}"


INNOVATION_RMS_RANGE = (2 / 3, 1.5)
"""Standardised innovations whose RMS lies outside this range are reported (here and in a study's report): 1
when the filter's variances are right, far below when the declared noise is too large or the measurement noise
is coloured (pre-filtered), far above when it is too small."""

POOR_FREE_RUN = 0.2
"""A free run whose RMS error exceeds this share of the output's spread is not called adequate by the headline,
however white the innovations."""


def _not_kept(report: dict) -> str:
    """What the evidence supported but the reported model leaves out, in a clause."""
    names = [x["effect"] for x in report["withheld"]]
    return (", ".join(names) + (" was" if len(names) == 1 else " were") + " supported by the evidence but not kept "
            f"(on held-out data the model reported free-runs as well or better without {'it' if len(names) == 1 else 'them'})")


def withheld_words(withheld: list, first: dict) -> str:
    """Why effects the evidence supported are not in the model reported (:mod:`.criterion`)."""
    h = first["held_out"]
    return (", ".join(x["effect"] for x in withheld) + " not kept: the evidence supported "
            + ("it" if len(withheld) == 1 else "them") + ", but on held-out blocks of the estimation record the model "
            "reported free-runs as well or better without " + ("it" if len(withheld) == 1 else "them")
            + f" (RMS error {h['overall'][-1]:.4g})")


def latest_forms(replaced: list) -> list:
    """The laws replaced, each once in the form the final model holds (a law whose form changed again in a
    later round says which forms it took before, ``earlier``)."""
    latest: dict = {}
    for x in replaced:
        key = (x["parameter"], x["term"])
        if key in latest and x.get("form") and latest[key].get("form"):
            x = {**x, "earlier": [*latest[key].get("earlier", []), latest[key]["form"]]}
        latest[key] = x
    return list(latest.values())


def state_words(x: dict) -> str:
    """``a state added: lag_P' = b_P*(P - lag_P) + k_P*dtheta', time constant 5.9 (99 % 4.6 to 7.4)`` for a
    move that added a state (:mod:`.states`): its equation, its time constant or its parameters."""
    st = x["state"]
    tc = st.get("time_constant")
    if tc:
        what = f"time constant {tc['mean']:.3g} (99 % {tc['q005']:.3g} to {tc['q995']:.3g})"
    else:
        what = ", ".join(f"{n} = {q['mean']:.3g} (99 % {q['q005']:.3g} to {q['q995']:.3g})"
                         for n, q in st["parameters"].items())
    return f"a state added: {st['equation']}, {what}"


def shape_words(x: dict) -> str:
    """``, e_a = 1.49 +- 0.02`` for a law replaced by another form, else nothing."""
    e = x.get("shape")
    return f", {e['name']} = {e['mean']:.3g} +- {e['sd']:.2g}" if e else ""


SHIFT_Z = 3.0
"""A declared parameter that moves by more than this many posterior sd once the effects are in is reported."""


def parameter_shifts(before: dict, after: ModelFit) -> dict:
    """The model's own parameters that moved by more than ``SHIFT_Z`` posterior sd (the larger of the two fits')
    between the first fit and the final one: before the effects were added they stood in for them (a
    stiffness that took up part of a free-play), which a user reading the first fit alone would not know."""
    out = {}
    for k, m0 in before["mean"].items():
        if k not in after.mean:
            continue
        sd = max(float(before["sd"].get(k, 0.0)), float(after.sd.get(k, 0.0)))
        if sd > 0 and abs(after.mean[k] - m0) > SHIFT_Z * sd:
            out[k] = {"before": float(m0), "after": float(after.mean[k]), "z": abs(after.mean[k] - m0) / sd}
    return out


def expected_words(fr: dict) -> str:
    """`` (its own draws: 75-97 %)``: the coverage range the band's model expects (:func:`~.band.expected_coverage`),
    and the share of its draws that diverged."""
    e = fr.get("band_expected")
    words = f" (its own draws: {e[0]:.0%}-{e[2]:.0%})" if e else ""
    if fr.get("band_diverged"):
        words += f", {fr['band_diverged']:.0%} of its draws diverged"
    return words


def report(spec, data, test_data, first: dict, rounds: list, arrays: dict, held) -> dict:
    """The loop's JSON report of a study ``spec`` on ``data``: before/after (``first``, ``arrays``), the rounds
    (:class:`~.result.LoopRound`), what was added, removed and replaced, the verdict, for the model it ``held``
    (a :class:`~.confirm.Fit`)."""
    from ..effects.states import Lag
    from .replace import shape_summary
    from .states import state_summary

    row = held.row
    records = [x.record for r in rounds for x in r.added]
    rounds = [r.record for r in rounds]
    added = [a for a in records if not a.get("removed")]
    removed = [a for a in records if a.get("removed")]
    kept = rounds
    replaced = latest_forms([x for r in kept for x in r.get("replaced", [])])
    # what the evidence supported and the criterion refused, each once (its latest judgement), unless taken later
    taken = {(a["effect"], a["target"]) for a in records} | {(x["by"], "") for x in replaced}
    withheld = list({(x["effect"], x["target"]): x for r in rounds for x in r.get("refused", [])
                     if (x["effect"], x["target"]) not in taken}.values())
    final_spec = held.cand.model_spec()
    for x in replaced:  # a form's shape as the final model has it (later rounds refit it with what they add)
        if x.get("shape") and x["shape"]["name"] in row.mean:
            x["shape"] = shape_summary(row, x["shape"]["name"])
        if x.get("state") and x["state"]["name"] in final_spec.states:
            x["state"] = state_summary(row, Lag(x["term"], x["target"], x["state"]["kind"]), final_spec)
    out = {"model": spec.models[0].label, "final_model": held.cand.label,
           "data": data.meta.get("source"), "n": len(data), "n_test": len(test_data), **first,
           "rounds": rounds,
           "candidates": rounds[0]["candidates"] if rounds else [],
           "confirmed": rounds[0]["confirmed"] if rounds else [],
           "added": added,
           "after": [r for r in kept if r["added"] or r.get("replaced")][-1]["after"] if added or replaced else None,
           "removed": removed, "replaced": replaced, "withheld": withheld, "tests_after": None,
           "states": [x["state"] for x in replaced if x.get("state")],
           "final_fit": row.summary(("log_evidence", "log_evidence_se", "mean", "sd", "q005", "q995"))}
    col = spec.models[0].model_spec().observed_columns[0]
    unit = (data.meta.get("units") or {}).get(col, "")
    if not added and not replaced:
        out["verdict"] = (withheld_words(withheld, first) if withheld else
                          rounds[0].get("verdict", "nothing added") if rounds else "no rounds run")
        out["headline"] = headline(out, col, unit)
        return out
    a, b = out["after"], out["before"]
    out["tests_after"] = strip_tests(arrays["after"]["tests"])
    out["parameter_shifts"] = shifts = parameter_shifts(first["base_fit"], row)
    out["verdict"] = (("added " + ", then ".join(f"{x['effect']} ({x['target']} equation, ln BF "
                                                  f"{x['log_bayes_factor']:.1f}"
                                                  + (f", {x['character']}" if x.get("character") else "") + ")"
                                                  for x in added) if added else
                        "no effect added" if replaced else "nothing added")
                      + f"; innovation RMS {b['innovation_rms']:.4g} -> {a['innovation_rms']:.4g}; free-run RMS "
                      f"error {b['free_run']['rms_error']:.4g} -> {a['free_run']['rms_error']:.4g}; ln Z "
                      f"{b['log_evidence']:.2f} -> {a['log_evidence']:.2f}"
                      + "".join((f"; {state_words(x)}" if x.get("state") else
                                 f"; the declared term {x['parameter']}*({x['term']}) of the {x['target']} "
                                 f"equation is replaced by {x['by']}" + shape_words(x))
                                + f" (ln BF {x['log_bayes_factor']:.1f})" for x in replaced)
                      + "".join(f"; {x['effect']} dropped again in round {x['removed']} (worth "
                                f"{x['log_bayes_factor_after']:.1f} nats beside the later effects)" for x in removed)
                      + "".join(f"; {k} moved {v['before']:.4g} -> {v['after']:.4g} ({v['z']:.0f} sd): it had "
                                f"absorbed part of what was missing" for k, v in shifts.items())
                      + (f"; then: {rounds[-1]['verdict']}" if rounds[-1].get("verdict") else "")
                      + (f"; {withheld_words(withheld, first)}" if withheld else ""))
    out["headline"] = headline(out, col, unit)
    return out


def strip_tests(tests: dict) -> dict:
    """JSON part of the tests (the spectrum arrays go to the figures)."""
    out = {}
    for c, t in tests.items():
        d = {k: v for k, v in t.items() if k not in ("spectrum", "acf")}
        d["acf"] = [float(x) for x in t["acf"]]
        d["spectral_peaks"] = t["spectrum"]["peaks"]
        out[c] = d
    return out
