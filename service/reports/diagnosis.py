"""Writes a closed-loop diagnosis (:func:`ardcore.loop.diagnose.diagnose`) to a directory: JSON, PNG figures, HTML."""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

import numpy as np

from ardflow.ardcore.jsonio import number
from ardflow.ardcore.loop.verdict import Diagnosis
from ardflow.ardcore.loop.verdict import expected_words, state_words

from ardflow.service.reports.diagnosis_figures import plot_candidates, plot_free_run, plot_noise, plot_tests


def _num(x) -> str:
    """A number at 4 significant digits (blank when absent)."""
    if x is None:
        return ""
    return f"{x:.4g}" if isinstance(x, (int, float)) and not isinstance(x, bool) else html.escape(str(x))


def _parameter_cells(name: str, q: dict) -> str:
    """A parameter's cells in the page's tables: its name, posterior mean and 99 % interval (empty: no
    posterior)."""
    interval = f"[{_num(q.get('q005'))}, {_num(q.get('q995'))}]" if q else ""
    return f"<td>{html.escape(name)}</td><td>{_num(q.get('mean'))}</td><td>{interval}</td>"


# the error table's rows: (key in the report, what it is, its unit: "data" is the measured column's unit)
ERRORS = [("innovation_rms", "one-step prediction error (innovation RMS)", "data"),
          ("standardized_rms", "standardised innovation RMS (1 when the filter's variances are right)", ""),
          ("log_evidence", "ln Z", "nats"),
          ("free_run.rms_error", "free-run RMS error", "data"),
          ("free_run.relative_rms_error", "free-run RMS error / RMS of the data", ""),
          ("free_run.draws_rms_error", "free-run RMS error, median over posterior draws", "data"),
          ("free_run.band_coverage", "share of the data inside the 90 % posterior predictive band", "%"),
          ("free_run.band_diverged", "share of the band's draws that diverged", "%"),
          ("free_run.band_halfwidth_rms", "the 90 % band's half-width (RMS)", "data"),
          ("free_run.band_factor", "process-noise scale of the band (calibrated on held-out blocks of the estimation record)", ""),
          ("free_run.amplitude_error", "oscillation amplitude error (relative)", ""),
          ("free_run.frequency_error", "oscillation frequency error (relative)", ""),
          ("free_run.harmonic_error", "harmonic spectrum error (relative)", "")]


def _error_table(j: dict, unit: str) -> str:
    """Error before and after, each measure named with its unit."""
    def get(d, key):
        for k in key.split("."):
            d = (d or {}).get(k)
        return d

    rows = []
    for key, what, u in ERRORS:
        b, a = get(j["before"], key), get(j.get("after"), key)
        if b is None and a is None:
            continue
        if u == "%":
            b, a = (None if x is None else 100 * x for x in (b, a))
        u = unit if u == "data" else u
        fmt = (lambda x: "" if x is None else f"{x:.1f}") if u in ("nats", "%") else _num
        rows.append(f"<tr><td>{html.escape(what)}</td><td>{html.escape(u)}</td><td>{fmt(b)}</td>"
                    f"<td>{fmt(a) if j.get('after') else '(nothing added)'}</td></tr>")
    return ("<table><tr><th>measure</th><th>unit</th><th>before</th><th>after</th></tr>" + "".join(rows)
            + "</table>")


def _records_table(j: dict, unit: str) -> str:
    """Several records: each estimation record's innovation tests and each test record's free-run error,
    before and after (empty for one record of each)."""
    rows = []
    for where, key, what in (("estimation", "records", "standardised innovation RMS / Ljung-Box p"),
                             ("test", "free_run.records", f"free-run RMS error [{unit}]")):
        def each(d):
            for k in key.split("."):
                d = (d or {}).get(k)
            return {r["name"]: r for r in d or []}
        b, a = each(j["before"]), each(j.get("after"))
        for name in b:
            cell = (lambda r: "" if r is None else f"{r['rms']:.3g} / {r['ljung_box_p']:.2g}") if key == "records" \
                else (lambda r: "" if r is None else _num(r.get("rms_error")))
            rows.append(f"<tr><td>{where}: {html.escape(name)}</td><td>{html.escape(what)}</td><td>{cell(b[name])}</td>"
                        f"<td>{cell(a.get(name)) if j.get('after') else '(nothing added)'}</td></tr>")
    if not rows:
        return ""
    return ("<h3>Each record</h3><table><tr><th>record</th><th>measure</th><th>before</th><th>after</th></tr>"
            + "".join(rows) + "</table>")


def _tests_table(j: dict, col: str) -> str:
    """The whiteness, normality and spectral tests of the standardised innovations, before and after."""
    b = (j.get("tests_before") or {}).get(col) or {}
    a = (j.get("tests_after") or {}).get(col) or {}

    def peaks(t):
        p = t.get("spectral_peaks") or []
        if not p:
            return "none"
        return ", ".join(f"{x['f']:.4g}" + (f" (harmonic {x['harmonic']})" if x.get("harmonic") else "")
                         for x in p[:4]) + (f" and {len(p) - 4} more" if len(p) > 4 else "")

    rows = [("Ljung-Box Q", lambda t: f"{_num(t.get('ljung_box'))} (p = {t.get('ljung_box_p', float('nan')):.2g}, "
                                      f"{t.get('ljung_box_lags')} lags)"),
            ("autocorrelations outside the 95 % band", lambda t: f"{100 * t.get('acf_outside', 0):.0f} %"),
            ("Jarque-Bera (normality)", lambda t: f"{_num(t.get('jarque_bera'))} "
                                                  f"(p = {t.get('jarque_bera_p', float('nan')):.2g})"),
            ("skew / excess kurtosis", lambda t: f"{_num(t.get('skew'))} / {_num(t.get('excess_kurtosis'))}"),
            ("spectral peaks above the background (frequency)", peaks)]
    out = ["<table><tr><th>test of the innovations</th><th>before</th><th>after</th></tr>"]
    for what, fmt in rows:
        out.append(f"<tr><td>{html.escape(what)}</td><td>{html.escape(fmt(b)) if b else ''}</td>"
                   f"<td>{html.escape(fmt(a)) if a else '(nothing added)'}</td></tr>")
    out.append("</table><p class='note'>White innovations: Ljung-Box p above 0.01, about 5 % of the "
               "autocorrelations outside the band, no spectral peak.</p>")
    qb, qa = number((b or {}).get("ljung_box")), number((a or {}).get("ljung_box"))
    if a and np.isfinite(qb) and np.isfinite(qa) and qa > qb * (1 + 0.1):
        out.append(f"<p class='warn'>The innovations are less white after the loop than before (Ljung-Box Q "
                   f"{_num(qb)} -> {_num(qa)}). The loop judges a model by its free run on held-out data, not by "
                   "its one-step prediction; a better model can leave the filter less process noise to absorb "
                   "what it still lacks, and that shows here as structure in the innovations.</p>")
    return "".join(out)


def _shape_cell(r: dict) -> str:
    """A form's fitted shape (an exponent, a saturation, a knee) with its 99 % interval."""
    e = r.get("shape")
    if not e:
        return ""
    return (f"<br>{html.escape(e['name'])} = {_num(e['mean'])} [{_num(e.get('q005'))}, {_num(e.get('q995'))}]"
            " (99 %)")


def _fate(c: dict, added: set) -> str:
    """What became of a confirmed candidate, in words."""
    if (c["effect"], c["target"]) in added:
        return "added"
    if not c.get("kept_terms"):
        return "rejected: ARD pruned its terms"
    if not np.isfinite(number(c["log_bayes_factor"])):
        return "rejected: its re-selection gave no evidence that is a result"
    if number(c.get("adjusted_log_bayes_factor", c["log_bayes_factor"])) <= number(c.get("threshold", 0)):
        return f"rejected: ln BF below its threshold {c.get('threshold', 0):.1f} (3 + ln N)"
    if not (c.get("stability") or {}).get("stable", True):
        return "rejected: the two halves of the record disagree"
    return "not added: another candidate explained it better"


def _model_section(m: dict, unit: str, scales: dict) -> list[str]:
    """The one model the report stands for: its noise level and why, its free run and band, its parameters
    (``scales``: :func:`effect_scales`)."""
    if not m:
        return []
    fr = m.get("free_run") or {}
    f = m.get("noise_factor", 1.0)
    cover = (f"; {100 * fr['band_coverage']:.0f} % of the held-out data inside its 90 % band"
             + html.escape(expected_words(fr)) if isinstance(fr.get("band_coverage"), (int, float)) else "")
    if f == 1.0:
        how = ("the posterior as sampled (its mean, its draws), at the process noise the evidence fitted"
               + (f"; {html.escape(m['chosen_by'])}" if "the posterior" in str(m.get("chosen_by", "")) else
                  ": no smaller process noise free-ran both held-out ends of the estimation record better"))
    else:
        held = ", ".join(f"x{k}: {v:.4g}" for k, v in (m.get("held_out_rms") or {}).items())
        pm = (m.get("posterior_mean_free_run") or {}).get("rms_error")
        how = (f"the final structure at {_num(f)} x its posterior process noise "
               f"({html.escape(', '.join(m.get('noise_parameters', [])))}), the level whose free run was best on the "
               f"held-out last {m.get('held_out_samples')} samples of the estimation record ({html.escape(held)}), "
               "refitted on the whole record there, with the Laplace approximation of its posterior"
               + (f"; at the posterior mean the same structure free-runs at {_num(pm)} {unit}" if pm is not None
                  else ""))
    rows = "".join(_parameter_row(k, q, scales.get(k, 1.0)) for k, q in (m.get("parameters") or {}).items())
    return [f"<h3>The model reported</h3><p>One model: {how}. Its free-run RMS error is "
            f"{_num(fr.get('rms_error'))} {unit}{cover}.</p>",
            "<details><summary>Its parameters (in the model's units: an added effect's coefficient is on its "
            "term as the effect writes it)</summary><table><tr><th>parameter</th><th>mean</th><th>sd</th>"
            f"<th>99 % interval</th></tr>{rows}</table></details>"]


def _parameter_row(name: str, q: dict, scale: float) -> str:
    """One parameter of the reported model in the model's units (``scale``: what its fitted value, on a
    normalised term, is multiplied by); a parameter without spread was held, not estimated: 'held'."""
    v = {k: (q[k] * scale if isinstance(q.get(k), (int, float)) else q.get(k)) for k in ("mean", "q005", "q995")}
    sd = q.get("sd")
    if not sd:
        return f"<tr><td>{html.escape(name)}</td><td>{_num(v['mean'])}</td><td colspan='2'>held at this value</td></tr>"
    lo, hi = sorted((v["q005"], v["q995"])) if None not in (v["q005"], v["q995"]) else (v["q005"], v["q995"])
    return (f"<tr><td>{html.escape(name)}</td><td>{_num(v['mean'])}</td><td>{_num(abs(sd * scale))}</td>"
            f"<td>[{_num(lo)}, {_num(hi)}]</td></tr>")


def effect_scales(j: dict) -> dict:
    """Each added effect's coefficient -> the scale of its normalised term (the confirmations' ``scales``): the
    value in the model's units is the fitted one times it."""
    out = {}
    for r in j.get("rounds") or []:
        for c in r.get("confirmed") or []:
            out.update({k: float(v) for k, v in (c.get("scales") or {}).items() if isinstance(v, (int, float))})
    return out


def _round_table(r: dict, k: int = 8) -> str:
    """One round: every confirmed candidate (screened and confirmed ln BF, its fate, its coefficients with
    their 99 % intervals) and the best of the rest as screened."""
    adds = r.get("added") or []
    adds = adds if isinstance(adds, list) else [adds]
    added = {(a["effect"], a["target"]) for a in adds} | {(a["effect"], a["target"]) for a in r.get("added_with") or []}
    out = [f"<h3>Round {r['round']} (model {html.escape(str(r.get('model', '')))})</h3><table><tr><th>candidate</th>"
           "<th>equation</th><th>screened ln BF</th><th>confirmed ln BF</th><th>result</th><th>coefficient</th>"
           "<th>mean</th><th>99 % interval</th></tr>"]
    confirmed = sorted(r.get("confirmed") or [], key=lambda c: -np.nan_to_num(number(c["log_bayes_factor"]), nan=-np.inf))
    refused = {(x["effect"], x["target"]) for x in r.get("refused") or []}
    for c in confirmed:
        post = {**(c.get("posterior") or {}), **(c.get("shape") or {})} or {"": {}}
        for i, (name, q) in enumerate(post.items()):
            lead = (f"<td>{html.escape(c['effect'])}</td><td>{html.escape(c['target'])}</td>"
                    f"<td>{_num(c.get('screened_log_bayes_factor'))}</td><td>{_num(c['log_bayes_factor'])}</td>"
                    f"<td>{html.escape('supported by the evidence, not kept: its model free-runs no better held out' if (c['effect'], c['target']) in refused and (c['effect'], c['target']) not in added else _fate(c, added))}</td>"
                    if i == 0 else "<td></td>" * 5)
            out.append(f"<tr>{lead}{_parameter_cells(name, q)}</tr>")
    tried = {(c["effect"], c["target"]) for c in confirmed}
    rest = [c for c in r.get("candidates") or [] if (c["effect"], c["target"]) not in tried][:max(0, k - len(tried))]
    for c in rest:
        out.append(f"<tr><td>{html.escape(c['effect'])}</td><td>{html.escape(c['target'])}</td>"
                   f"<td>{_num(c.get('log_bayes_factor'))}</td><td></td><td>"
                   + ("screened only: below 3 nats" if number(c.get("log_bayes_factor", 0)) < 3
                      else "screened only: not among the best to confirm") +
                   "</td><td></td><td></td><td></td></tr>")
    if not confirmed and not rest:
        out.append("<tr><td colspan='8'>no candidate screened</td></tr>")
    out.append("</table>")
    for x in r.get("replaced") or []:
        if x.get("state"):
            out.append(f"<p>This round added a state: {html.escape(state_words(x))} (ln BF "
                       f"{_num(x['log_bayes_factor'])}).</p>")
            continue
        out.append(f"<p>This round replaced the declared {html.escape(x['parameter'])}*({html.escape(x['term'])}) "
                   f"by {html.escape(x['by'])} (ln BF {_num(x['log_bayes_factor'])}): of the moves the evidence "
                   "supported, the one taken by its free run on held-out data (see how the loop decided).</p>"
                   if x.get("shape") else
                   f"<p>The declared {html.escape(x['parameter'])}*({html.escape(x['term'])}) was dropped: "
                   f"{html.escape(x['by'])} replaces it (ln BF {_num(x['log_bayes_factor'])}).</p>")
    if r.get("verdict"):
        out.append(f"<p>{html.escape(r['verdict'])}</p>")
    return "".join(out)


def _held_out_section(j: dict) -> list[str]:
    """How the loop decided: each round's model and every move the evidence supported, judged by their free run
    on held-out blocks of the estimation record (the loop's one criterion), and which move was taken."""
    h = j.get("held_out")
    if not h or not h.get("free_run"):
        return []
    blocks = list(next((e for e in h["free_run"] if e), {}))
    if not blocks:
        return []

    def row(label, e, overall, taken=False):
        return (f"<tr><td>{html.escape(label)}</td>" + "".join(f"<td>{_num(e.get(b))}</td>" for b in blocks)
                + f"<td>{_num(overall)}</td><td>{'taken' if taken else ''}</td></tr>")

    rows = []
    for rnd in h.get("moves") or []:
        rows.append(row(f"round {rnd['round']}: the model {rnd['model']}", rnd["score"]["blocks"],
                        rnd["score"]["overall"]))
        rows += [row(f"  + {m['move']}", m.get("blocks", {}), m.get("overall"), m.get("taken")) for m in rnd["moves"]]
    rows.append(row("the model reported", h["free_run"][-1], h["overall"][-1]))
    return [f"<h3>How the loop decided</h3><p>Every model refitted with one block of the estimation record "
            f"({100 * h['share']:g} % of it) left out, then free-run over that block; {html.escape(h['rule'])}."
            "</p><table><tr><th>model</th>" + "".join(f"<th>{html.escape(b)}</th>" for b in blocks)
            + f"<th>all blocks</th><th></th></tr>{''.join(rows)}</table>"]


def _states_table(states: list[dict]) -> str:
    """The page's "States added": an added state as clearly as an added term, its equation, its time constant (a
    lag, a sensor) or frequency (a mode) and its parameters, each with its 99 % interval."""
    body = ["<h2>States added</h2><table><tr><th>state</th><th>kind</th><th>equation</th>"
            "<th>parameter</th><th>mean</th><th>99 % interval</th></tr>"]
    for st in states:
        rows = dict(st["parameters"])
        if st.get("frequency"):
            rows = {"frequency (cycles per time unit)": st["frequency"], **rows}
        if st.get("time_constant"):
            rows = {"time constant": st["time_constant"], **rows}
        for i, (name, q) in enumerate(rows.items()):
            lead = (f"<td>{html.escape(st['name'])}</td><td>{html.escape(st['kind'])}</td>"
                    f"<td>{html.escape(st['equation'])}</td>" if i == 0 else "<td></td>" * 3)
            body.append(f"<tr>{lead}{_parameter_cells(name, q)}</tr>")
    body.append("</table>")
    return "".join(body)


def write_diagnosis(diagnosis: Diagnosis, data_t: np.ndarray, out_dir: str | Path, col: str = "y",
                    label=str) -> Path:
    """Write ``diagnosis.json``, the figures and ``diagnosis.html`` into ``out_dir``; returns the JSON path.
    ``label(column)``: an axis label with its unit, as the spec declares them (:meth:`DataSpec.axis_label`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arrays, j = {**diagnosis.arrays, "column": col}, diagnosis.to_json()
    figs = {
        "tests.png": ("whiteness and spectrum of the innovations, before and after", plot_tests(arrays, col,
                                                                                                 out / "tests.png",
                                                                                                 label("t"))),
        "process_noise.png": ("process noise the filter had to inject, per state",
                              plot_noise(arrays, data_t, out / "process_noise.png", label("t"))),
        "candidates.png": ("candidate effects ranked", plot_candidates(diagnosis.report, out / "candidates.png")),
        "free_run.png": ("free run against the data", plot_free_run(arrays, out / "free_run.png", label)),
    }
    path = out / "diagnosis.json"
    path.write_text(json.dumps(j, indent=2))
    m = re.search(r"\[(.+)\]$", label(col))
    unit = m.group(1) if m else ""
    def fig(name: str) -> str:
        cap = figs[name][0]
        return (f"<figure><img src='{name}' alt='{html.escape(cap)}'><figcaption>{html.escape(cap)}"
                "</figcaption></figure>")

    body = [f"<h1>Diagnosis of {html.escape(str(j['model']))}</h1>",
            f"<p class='verdict'><b>Verdict.</b> {html.escape(j.get('headline') or j['verdict'])}</p>",
            f"<details><summary>The loop's account, step by step</summary><p>{html.escape(j['verdict'])}</p>"
            "</details>"]
    for note in j.get("input_hold") or []:  # the record, not the declaration, decided how inputs vary
        body.append(f"<p class='note'><b>Inputs.</b> {html.escape(note)}</p>")
    if j.get("added"):
        # one row per coefficient: the effect, its term, the coefficient's posterior mean and 99 % interval
        # the coefficient as its round confirmed it, in the model's units; the reported model's table below holds
        # the final fit's values of the same parameters (normalised terms, refitted beside later effects)
        body.append("<h2>Effects added</h2><p>Each coefficient as the round that added it confirmed it, in the "
                    "model's units; the final model's values, refitted beside everything added after it, are under "
                    "<i>The model reported</i> in the same units.</p>"
                    "<table><tr><th>effect</th><th>equation</th><th>character</th>"
                    "<th>ln BF</th><th>coefficient</th><th>mean when added</th><th>99 % interval</th></tr>")
        for a in j["added"]:
            post = {**a.get("posterior", {}), **a.get("shape", {})} or {"-": {}}
            for i, (name, q) in enumerate(post.items()):
                lead = (f"<td>{html.escape(a['effect'])}</td><td>{html.escape(a['target'])}</td>"
                        f"<td>{html.escape(a.get('character') or '')}</td><td>{_num(a['log_bayes_factor'])}</td>"
                        if i == 0 else "<td></td>" * 4)
                body.append(f"<tr>{lead}{_parameter_cells(name, q)}</tr>")
        body.append("</table>")
    if j.get("states"):
        body.append(_states_table(j["states"]))
    if any(not r.get("state") for r in j.get("replaced") or []):
        body.append("<h2>Declared terms replaced</h2><table><tr><th>declared term</th><th>equation</th>"
                    "<th>replaced by</th><th>ln BF of the replacement</th></tr>")
        body += [f"<tr><td>{html.escape(r['parameter'])}*({html.escape(r['term'])})</td><td>{r['target']}</td>"
                 f"<td>{html.escape(r['by'])}{_shape_cell(r)}</td><td>{_num(r['log_bayes_factor'])}</td></tr>"
                 for r in j["replaced"] if not r.get("state")]
        body.append("</table>")
    body.append("<h2>Each round: the candidates and what became of them</h2>")
    body += [_round_table(r) for r in j.get("rounds", [])]
    body += ["<h2>Error before and after</h2>", _error_table(j, unit), _records_table(j, unit), fig("free_run.png")]
    body += _held_out_section(j)
    body += _model_section(j.get("reported") or {}, unit, effect_scales(j))
    body += ["<h2>Residual tests before and after</h2>", _tests_table(j, col), fig("tests.png"),
             "<h2>Where the model needed help</h2>", fig("process_noise.png"), fig("candidates.png")]
    style = ("body{font-family:sans-serif;font-size:15px;max-width:1100px;margin:auto}img{max-width:100%}"
             "table{border-collapse:collapse;margin:.4em 0}td,th{border:1px solid #ccc;padding:2px 6px}"
             ".verdict{font-size:1.1em}.note{color:#555;font-size:.9em}")
    (out / "diagnosis.html").write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>diagnosis</title>"
                                        f"<style>{style}</style></head><body>{''.join(body)}</body></html>")
    return path
