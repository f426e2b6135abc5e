"""Writes a closed-loop diagnosis (:func:`ardcore.loop.diagnose.diagnose`) to a directory: JSON, PNG figures, HTML."""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from ardflow.ardcore.loop.result import Diagnosis

from .report import pyplot, save_figure


def _plot_tests(arrays: dict, col: str, out: Path) -> Path:
    """Innovation autocorrelation with 95 % bands and innovation spectrum with its peaks, before/after."""
    plt = pyplot()
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 3.8))
    for label, style in (("before", "C3"), ("after", "C0")):
        if label not in arrays:
            continue
        t = arrays[label]["tests"][col]
        r = t["acf"]
        a1.plot(np.arange(r.size), r, "o-", ms=3, color=style, label=label)
        sp = t["spectrum"]
        a2.semilogy(sp["f"], sp["psd"], color=style, lw=0.8, label=label)
        for p in sp["peaks"]:
            a2.plot(p["f"], np.interp(p["f"], sp["f"], sp["psd"]), "v", color=style, ms=7)
    band = arrays["before"]["tests"][col]["acf_band"]
    a1.axhspan(-band, band, color="0.85", label="95 % band (white)")
    a1.set(xlabel="lag [samples]", ylabel="autocorrelation", title="standardised innovations: whiteness")
    a2.set(xlabel="frequency [cycles / time unit]", ylabel="PSD", title="innovation spectrum (peaks marked)")
    a1.legend(fontsize=8)
    a2.legend(fontsize=8)
    return save_figure(fig, out)


def _plot_noise(arrays: dict, t: np.ndarray, out: Path, time_label: str = "time") -> Path:
    """The smoothed process noise (drift the filter had to inject) per dynamic state, before/after."""
    plt = pyplot()
    states = list(arrays["before"]["process_noise_rate"])
    fig, axes = plt.subplots(len(states), 1, figsize=(11, 2.4 * len(states)), squeeze=False)
    for ax, s in zip(axes[:, 0], states):
        for label, style in (("before", "C3"), ("after", "C0")):
            if label in arrays and s in arrays[label]["process_noise_rate"]:
                ax.plot(t[1:], arrays[label]["process_noise_rate"][s], color=style, lw=0.5, label=label)
        ax.set(ylabel=f"injected d{s}/dt", title=f"smoothed process noise on {s}")
        ax.legend(fontsize=8, loc="upper right")
    axes[-1, 0].set_xlabel(time_label)
    return save_figure(fig, out)


def _plot_candidates(report: dict, out: Path, k: int = 12) -> Path:
    plt = pyplot()
    c = report["candidates"][:k][::-1]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(c) + 1.2))
    conf = {(x["effect"], x["target"]): x for x in report["confirmed"]}
    colors = ["C2" if conf.get((x["effect"], x["target"]), {}).get("survives") else
              ("C1" if (x["effect"], x["target"]) in conf else "0.6") for x in c]
    # screened ln BF spans nats to tens of thousands: a signed log scale keeps both ends readable
    v = np.array([x["log_bayes_factor"] for x in c])
    if not len(c):  # --max-rounds 0: nothing was screened
        ax.text(0.5, 0.5, "no candidates screened", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return save_figure(fig, out)
    ax.barh([f"{x['effect']} -> {x['target']}" for x in c], np.sign(v) * np.log10(1 + np.abs(v)), color=colors)
    ticks = [t for t in (-100, -10, 0, 3, 10, 100, 1000, 10000, 100000) if abs(t) <= max(10, np.abs(v).max() * 1.5)]
    ax.set_xticks(np.sign(ticks) * np.log10(1 + np.abs(ticks)), [str(t) for t in ticks])
    ax.axvline(np.log10(4), color="k", lw=0.6, ls=":")
    ax.set(xlabel="screened ln Bayes factor of adding the effect (dotted: 3 nats)",
           title="candidate effects (green: kept by evidence, orange: rejected by evidence)")
    return save_figure(fig, out)


def _plot_free_run(arrays: dict, out: Path, label=str) -> Path:
    """The free run before and after against the data, with its bands, and the spectra; ``label(column)`` is
    an axis label with its unit (:meth:`DataSpec.axis_label`)."""
    plt = pyplot()
    fr0 = arrays["before"]["free_run"]
    fig, (a1, a2) = plt.subplots(2, 1, figsize=(11, 6))
    t = fr0["t"]
    n = min(t.size, 4000)
    a1.plot(t[:n], fr0["y"][:n], "k", lw=0.8, label="data")
    a1.plot(t[:n], fr0["y_free"][:n], "C3", lw=0.8, label="free run, before")
    if "band" in fr0:
        a1.fill_between(t[:n], fr0["band"][0][:n], fr0["band"][1][:n], color="C3", alpha=0.15, lw=0,
                        label=f"90 % band of posterior draws, before ({100 * fr0['band_coverage']:.0f} % of data inside)")
    if "after" in arrays:
        fr1 = arrays["after"]["free_run"]
        if "band" in fr1:
            a1.fill_between(fr1["t"][:n], fr1["band"][0][:n], fr1["band"][1][:n], color="C0", alpha=0.2, lw=0,
                            label=f"90 % band, after ({100 * fr1['band_coverage']:.0f} % of data inside)")
        a1.plot(fr1["t"][:n], fr1["y_free"][:n], "C0", lw=0.8, label="free run, after")
    a1.set(xlabel=label("t"), ylabel=label(arrays.get("column", "y")),
           title="free-run simulation against the (held-out) data")
    a1.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    from scipy import signal

    fs = 1.0 / float(np.median(np.diff(t)))
    for y, lab, st in [(fr0["y"], "data", "k"), (fr0["y_free"], "before", "C3")] + (
            [(arrays["after"]["free_run"]["y_free"], "after", "C0")] if "after" in arrays else []):
        if np.all(np.isfinite(y)):
            f, P = signal.welch(y - np.mean(y), fs=fs, nperseg=min(y.size, 4096))
            a2.semilogy(f, P + 1e-300, st, lw=0.8, label=lab)
    a2.set(xlabel="frequency [Hz]" if label("t").endswith("[s]") else "frequency [cycles per time unit]",
           ylabel="PSD", title="spectra (compare these, not phase, for self-excited systems)")
    a2.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return save_figure(fig, out)


def write_diagnosis(diagnosis: Diagnosis, data_t: np.ndarray, out_dir: str | Path, col: str = "y",
                    label=str) -> Path:
    """Write ``diagnosis.json``, the figures and ``diagnosis.html`` into ``out_dir``; returns the JSON path.
    ``label(column)``: an axis label with its unit, as the spec declares them (:meth:`DataSpec.axis_label`)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    arrays, j = {**diagnosis.arrays, "column": col}, diagnosis.to_json()
    figs = {
        "tests.png": ("whiteness and spectrum of the innovations, before and after", _plot_tests(arrays, col,
                                                                                                 out / "tests.png")),
        "process_noise.png": ("process noise the filter had to inject, per state",
                              _plot_noise(arrays, data_t, out / "process_noise.png", label("t"))),
        "candidates.png": ("candidate effects ranked", _plot_candidates(diagnosis.report, out / "candidates.png")),
        "free_run.png": ("free run against the data", _plot_free_run(arrays, out / "free_run.png", label)),
    }
    path = out / "diagnosis.json"
    path.write_text(json.dumps(j, indent=2))
    rows = []
    for key in ("innovation_rms", "standardized_rms", "ljung_box", "log_evidence"):
        b = j["before"].get(key)
        a = (j.get("after") or {}).get(key)
        rows.append((key, b, a))
    for key, b in j["before"]["free_run"].items():
        rows.append((f"free run: {key}", b, ((j.get("after") or {}).get("free_run") or {}).get(key)))

    def f(x):
        return "" if x is None else (f"{x:.4g}" if isinstance(x, float) else html.escape(str(x)))

    body = [f"<h1>Diagnosis of {html.escape(str(j['model']))}</h1>",
            f"<p class='verdict'><b>Verdict.</b> {html.escape(j.get('headline') or j['verdict'])}</p>",
            f"<details><summary>The loop's account, step by step</summary><p>{html.escape(j['verdict'])}</p>"
            "</details>",
            "<h2>Error before and after</h2><table><tr><th>measure</th><th>before</th><th>after</th></tr>"]
    body += [f"<tr><td>{html.escape(k)}</td><td>{f(b)}</td><td>{f(a)}</td></tr>" for k, b, a in rows]
    body.append("</table>")
    sim = j.get("simulation") or {}
    if "factor" in sim:
        held = ", ".join(f"x{k}: {v:.4g}" for k, v in sim["held_out_rms"].items())
        body.append(f"<h2>Simulation fit</h2><p>The final structure fitted at {f(sim['factor'])} x its posterior "
                    f"process noise ({html.escape(', '.join(sim['noise_parameters']))}), the factor that free-ran "
                    f"best on the held-out last {sim['held_out_samples']} samples of the estimation record "
                    f"({html.escape(held)}): free-run RMS error {f(sim['free_run']['rms_error'])}. A predictive "
                    "choice for simulation, not the evidence's: the posterior, its intervals and the model "
                    "selection above are unchanged.</p>")
    if j.get("added"):
        # one row per coefficient: the effect, its term, the coefficient's posterior mean and 99 % interval
        body.append("<h2>Effects added</h2><table><tr><th>effect</th><th>equation</th><th>character</th>"
                    "<th>ln BF</th><th>coefficient</th><th>mean</th><th>99 % interval</th></tr>")
        for a in j["added"]:
            post = {**a.get("posterior", {}), **a.get("shape", {})} or {"-": {}}
            for i, (name, q) in enumerate(post.items()):
                lead = (f"<td>{html.escape(a['effect'])}</td><td>{html.escape(a['target'])}</td>"
                        f"<td>{html.escape(a.get('character') or '')}</td><td>{f(a['log_bayes_factor'])}</td>"
                        if i == 0 else "<td></td>" * 4)
                body.append(f"<tr>{lead}<td>{html.escape(name)}</td><td>{f(q.get('mean'))}</td>"
                            f"<td>[{f(q.get('q005'))}, {f(q.get('q995'))}]</td></tr>")
        body.append("</table>")
    if j.get("replaced"):
        body.append("<h2>Declared terms replaced</h2><table><tr><th>declared term</th><th>equation</th>"
                    "<th>replaced by</th><th>ln BF for the model without it</th></tr>")
        body += [f"<tr><td>{html.escape(r['parameter'])}*({html.escape(r['term'])})</td><td>{r['target']}</td>"
                 f"<td>{html.escape(r['by'])}</td><td>{f(r['log_bayes_factor'])}</td></tr>" for r in j["replaced"]]
        body.append("</table>")
    body.append("<h2>Candidates confirmed by evidence</h2><table><tr><th>effect</th><th>target</th>"
                "<th>ln BF</th><th>ARD keeps</th><th>survives</th></tr>")
    body += [f"<tr><td>{html.escape(c['effect'])}</td><td>{c['target']}</td><td>{f(c['log_bayes_factor'])}</td>"
             f"<td>{html.escape(', '.join(c['kept_terms']))}</td><td>{c['survives']}</td></tr>" for c in j["confirmed"]]
    body.append("</table>")
    for name, (cap, _) in figs.items():
        body.append(f"<figure><img src='{name}' alt='{html.escape(cap)}'><figcaption>{html.escape(cap)}"
                    "</figcaption></figure>")
    style = ("body{font-family:sans-serif;max-width:1100px;margin:auto}img{max-width:100%}"
             "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:2px 6px}")
    (out / "diagnosis.html").write_text(f"<!doctype html><html><head><meta charset='utf-8'><title>diagnosis</title>"
                                        f"<style>{style}</style></head><body>{''.join(body)}</body></html>")
    return path
