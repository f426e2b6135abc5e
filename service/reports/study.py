"""The study report: one self-contained HTML page with PNG figures beside it (no network assets)."""

from __future__ import annotations

import html
import math
from pathlib import Path

import numpy as np

from ardflow.ardcore.loop.verdict import INNOVATION_RMS_RANGE
from ardflow.ardcore.sampling.diagnostics import Quality

from ardflow.service.reports.paper import FIG15_M2OPT_BOUNDS, TABLE10, TABLE10_OFFSET
from ardflow.service.reports.plots import (
    TAU_SECONDS, Labels, drawn_alone, plot_ard_bounds, plot_data_and_psd, plot_evidence_history, plot_joint,
    plot_marginals, plot_model_probabilities, plot_prediction,
)

_CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #bbb;padding:4px 8px;text-align:right}
th{background:#eee}td.l,th.l{text-align:left}img{max-width:100%;border:1px solid #ddd;margin:.5em 0}
.warn{color:#a40}"""


def _fmt(x, nd=3):
    if isinstance(x, str):
        return html.escape(x)
    if x is None:
        return "-"
    if isinstance(x, float):
        if not math.isfinite(x):
            return "not a number" if x != x else ("infinite" if x > 0 else "minus infinite")
        return f"{x:.{nd}f}" if abs(x) < 1e5 else f"{x:.{nd}e}"
    return html.escape(str(x))


def write_report(store, out: str | Path | None = None, submit=None) -> Path:
    """Write ``report.html`` and its figures for a finished study; returns the HTML path.

    Parameters
    ----------
    store : workers.store.StudyStore
    out : path, optional
        Directory for the report (default: ``STORE/report`` for a local store).
    submit : callable, optional
        ``submit(fn, *args, **kwargs)`` returning a future (``.result()``), as a Dask client's: where the
        figures are drawn, side by side, in processes that can write to ``out``. Default: here, one after
        another.
    """
    from ardflow.ardcore.selection.spec import StudySpec

    typed = store.read_summary()
    if typed is None:
        raise LookupError("the study has no summary yet")
    summary = typed.to_json()
    out = Path(out) if out is not None else Path(store.path) / "report"
    out.mkdir(parents=True, exist_ok=True)
    spec = StudySpec.model_validate(store.meta["spec"])
    reference = spec.naming.generator == "reference"
    best = summary["best_model"]
    it, _ = store.model_result(best)
    samples, _, _, names = store.finished_samples(best, it)
    truth, ref_bounds = _truth(spec, best)
    data = store.load_data()
    col = "y" if "y" in data.columns else next(iter(data.columns))
    # the figures are drawn where ``submit`` runs them (a study's own workers, side by side) while this process
    # filters the best model for its innovations; the prediction's figures follow them
    submit = submit or _Done
    drawn = _submitted(_report_figures(store, spec, summary, (names, samples), out, data, col), submit)
    try:
        innovations = _best_innovations(spec, summary, data, col)
    except Exception as exc:  # noqa: BLE001 - a check that cannot be computed must not cost the report
        innovations = exc
    # on the page they come after the data's figure and the models' probabilities
    drawn[2:2] = _submitted(_prediction_figures(spec, best, out, (data, col), innovations), submit)
    figs = [_drawn(cap, f, job) for cap, f, job in drawn]
    table10 = _comparison_table(summary)
    post_table = _posterior_table(names, samples, truth, ref_bounds)
    paper = _paper_section(summary, spec) if reference and {r["name"] for r in summary["models"]} <= set(TABLE10) \
        else ""
    warns = [f"<li>{html.escape(r['name'])}: {html.escape(w)}</li>" for r in summary["models"] for w in r["warnings"]]
    warns += [f"<li class=warn>{html.escape(best)}: {html.escape(w)}</li>"
              for w in self_checks(names, samples, truth, innovations, COLOURED if reference else "")]
    body = [f"<h1>ardflow study {html.escape(spec.name)}</h1>",
            f"<p>{html.escape(spec.description)}</p>",
            f"<p>Data: {html.escape(str(summary['data'].get('source')))}, {summary['data'].get('n')} points. "
            f"Best model: <b>{html.escape(best)}</b>. Wall time {summary['wall_s']:.0f} s.</p>",
            # the record, not the declaration, decided how inputs vary between samples (ardcore/selection/hold.py)
            *(f"<p class='note'><b>Inputs.</b> {html.escape(n)}</p>"
              for n in summary["data"].get("input_hold", [])),
            _records_table(data, innovations, col, best),
            "<h2>Model comparison</h2>", table10,
            f"<h2>Posterior of {html.escape(best)}</h2>", post_table, _convergence_table(summary), paper,
            "<h2>Warnings</h2><ul>" + ("".join(warns) or "<li>none</li>") + "</ul>",
            "<h2>Figures</h2>"]
    for cap, f in figs:
        if not f:
            body.append(f"<p class=warn>{html.escape(cap)}</p>")
            continue
        body.append(f"<figure><img src='{f}' alt='{html.escape(cap)}'><figcaption>{html.escape(cap)}</figcaption>"
                    "</figure>")
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>ardflow: {html.escape(spec.name)}</title>"
            f"<style>{_CSS}</style></head><body>{''.join(body)}</body></html>")
    path = out / "report.html"
    path.write_text(page)
    return path


def _records_table(data, innovations, col: str, best: str) -> str:
    """A study of several records: each record's source, length, and how the best model's one-step prediction
    fits it (its RMS error in the data's units, the standardised innovations' RMS); empty for one record."""
    if data.n_records < 2:
        return ""
    rows = []
    for name, info, sl in zip(data.record_names(), data.record_info(), data.record_slices()):
        fit = "", ""
        if not isinstance(innovations, Exception):
            e, v = innovations[0][sl], innovations[1][sl]
            ok = np.isfinite(e) & np.isfinite(v)
            fit = (f"{np.sqrt(np.mean(e[ok] ** 2)):.4g}", f"{np.sqrt(np.mean(e[ok] ** 2 / v[ok])):.2f}") if ok.any() \
                else ("", "")
        rows.append(f"<tr><td>{html.escape(name)}</td><td>{html.escape(str(info.get('source')))}</td>"
                    f"<td>{sl.stop - sl.start}</td><td>{fit[0]}</td><td>{fit[1]}</td></tr>")
    return (f"<h2>Records</h2><p>Each record is filtered from its own initial state; the parameters are shared."
            f"</p><table><tr><th>record</th><th>source</th><th>points</th><th>{html.escape(best)}: one-step RMS "
            f"error of {html.escape(col)}</th><th>standardised innovation RMS</th></tr>{''.join(rows)}</table>")


def _truth(spec, best: str) -> tuple[dict, dict | None]:
    """The true values a generated data set declares, and the paper's 99 % bounds for its own model M2."""
    reference = spec.naming.generator == "reference"
    return dict(spec.true_values), (FIG15_M2OPT_BOUNDS if (reference and best == "M2") else None)


COLOURED = ("expected on the reference data: its measurement noise is low-pass filtered, so it is coloured and "
            "smaller than the white noise the EKF declares; see docs/worked-example.md, the measurement pipeline")
"""Why the reference problem's standardised innovations are far below 1 (said beside that warning)."""


def self_checks(names: list, samples: np.ndarray, truth: dict, innovations, why: str = "") -> list[str]:
    """What the report's own checks say is wrong with the best model: a true value the data were generated with
    outside its 99 % posterior bounds, standardised innovations whose RMS is outside
    :data:`INNOVATION_RMS_RANGE` (``innovations``: ``(innovations, variances)``, or why they could not be
    computed); ``why``: a known reason for the latter, said with it."""
    out = []
    for i, n in enumerate(names):
        tv = truth.get(n)
        if tv is None:
            continue
        lo, hi = np.quantile(samples[..., i].ravel(), [0.005, 0.995])
        if not lo <= tv <= hi:
            out.append(f"the true {n} = {tv:g} is outside its 99 % posterior bounds [{lo:.4g}, {hi:.4g}]: the "
                       "model, its priors or its declared noise (the measurement noise std) do not match the data")
    if isinstance(innovations, Exception):
        out.append(f"the innovations could not be computed ({type(innovations).__name__}: {innovations})")
        return out
    innov, var = innovations
    z = innov / np.sqrt(var)
    z = z[np.isfinite(z)]
    rms = float(np.sqrt(np.mean(z ** 2))) if z.size else math.nan
    lo, hi = INNOVATION_RMS_RANGE
    if not lo <= rms <= hi:
        out.append(f"the standardised innovations have RMS {rms:.2f} (1 when the filter's variances are right): "
                   "the declared measurement noise, or the model, does not match the data" + (f" ({why})" if why else ""))
    return out


class _Done:
    """A figure drawn here: its result, or the error drawing it raised, on ``.result()``."""

    def __init__(self, fn, *args, **kw):
        try:
            self.value, self.error = fn(*args, **kw), None
        except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not cost the report
            self.value, self.error = None, exc

    def result(self):
        if self.error is not None:
            raise self.error
        return self.value


def _submitted(entries: list[tuple], submit) -> list[tuple]:
    """Each figure entry (``(caption, file, function, args, kwargs)``; no function: nothing to draw) as
    ``(caption, file, job)``, its function handed to ``submit`` to draw while no other of its process does."""
    return [(cap, f, submit(drawn_alone, fn, *args, **kw) if fn is not None else None)
            for cap, f, fn, args, kw in entries]


def _drawn(cap: str, f: str, job) -> tuple[str, str]:
    """The figure's caption and file once its ``job`` is done; no file, and a caption that says why, when it
    could not be drawn."""
    if job is None:
        return cap, ""
    try:
        job.result()
        return cap, f
    except Exception as exc:  # noqa: BLE001 - a figure that cannot be drawn must not cost the report
        return f"({cap}: could not be drawn, {type(exc).__name__}: {exc})", ""


def _labels(spec, col: str) -> Labels:
    """A figure's names and units as the spec declares them (data.units, data.labels)."""
    seconds = spec.naming.units.get("t") == "s"
    return Labels(f"{spec.name}: {spec.naming.axis_label(col)}", spec.naming.axis_label("t"),
                  spec.naming.axis_label(col), "Hz" if seconds else "cycles per time unit")


def _report_figures(store, spec, summary, draws: tuple, out: Path, data, col: str) -> list[tuple]:
    """The report's figures but the prediction's (:func:`_prediction_figures`), each ``(caption, file, function,
    args, kwargs)``: the function draws the file in ``out``. ``draws``: the best model's parameter names and
    posterior samples; ``data``: the study's data (read once, by :func:`write_report`), ``col`` its measured
    channel. The paper's figure numbers are cited only for the paper's own problem."""
    reference = spec.naming.generator == "reference"
    cite = (lambda figs: f" ({figs})") if reference else (lambda figs: "")
    best = summary["best_model"]
    names, samples = draws
    truth, ref_bounds = _truth(spec, best)
    figs: list[tuple] = [
        ("Data and its power spectral density" + cite("Figs. 2-3"), "data_psd.png", plot_data_and_psd,
         (data.t, data.columns[col], out / "data_psd.png"),
         {"labels": _labels(spec, col), "cutoff": 0.2295 if reference else None,
          "tau_seconds": TAU_SECONDS if reference else None}),
        ("Posterior probability of each candidate model (Eq. 7), with its ln evidence", "probabilities.png",
         plot_model_probabilities, (summary["models"], out / "probabilities.png"), {})]
    histories = store.histories([r["name"] for r in summary["models"]])
    figs.append(("ln evidence, goodness of fit and information gain per maximisation trial" + cite("Figs. 8, 11-14"),
                 "evidence.png", plot_evidence_history, (histories, out / "evidence.png"), {}))
    for cand in spec.models:
        ard = cand.ard_names
        if ard and histories.get(cand.label):
            f = f"ard_{cand.label}.png"
            figs.append((f"{cand.label}: prior and posterior 99 % bounds of the ARD parameters per trial" + cite("Fig. 9"),
                         f, plot_ard_bounds, (histories[cand.label], ard, out / f), {}))
    figs.append((f"{best} (optimal nested model): marginal posteriors, 99 % bounds, true values" + cite("Fig. 15"),
                 "marginals.png", plot_marginals, (names, samples, out / "marginals.png", truth, ref_bounds), {}))
    figs.append((f"{best}: joint posteriors" + cite("Fig. 16"), "joint.png", plot_joint,
                 (names, samples, out / "joint.png", truth), {}))
    return figs


def _prediction_figures(spec, best: str, out: Path, record: tuple, innovations) -> list[tuple]:
    """The data against the best model's one-step prediction, one figure per record, as
    :func:`_report_figures`' entries; ``record``: the study's data and its measured channel, ``innovations``:
    the best model's innovations and their variances, or why there are none (the entry then draws nothing and
    its caption says why)."""
    data, col = record
    several = data.n_records > 1
    figs = []
    for r, (rec, rows) in enumerate(zip(data.record_names(), data.record_slices())):
        f = f"prediction_{r}.png" if several else "prediction.png"
        name = f" on {rec}" if several else ""
        if isinstance(innovations, Exception):
            figs.append((f"(the prediction of {best}{name} could not be drawn: {type(innovations).__name__})", "",
                         None, (), {}))
            continue
        figs.append((f"Data against {best}'s one-step prediction{name}, and the standardised residuals", f,
                     plot_prediction, (data.record(r).t, data.columns[col][rows], *(a[rows] for a in innovations),
                                       out / f), {"model": best + name, "labels": _labels(spec, col)}))
    return figs


def _best_innovations(spec, summary: dict, data, col: str) -> tuple:
    """The best model's innovations on ``col`` and their variances at its posterior mean (the EKF)."""
    from ardflow.ardcore.likelihood.ekf import compile_model
    from ardflow.ardcore.loop.freerun import fitted_spec
    from ardflow.ardcore.selection.fit import ModelFit

    best = summary["best_model"]
    cand = next(c for c in spec.models if c.label == best)
    fit = ModelFit.from_json(next(r for r in summary["models"] if r["name"] == best))
    fspec = fitted_spec(cand, fit)
    res = compile_model(fspec).filter(fit.point(fspec.free_parameters), data, cand.substeps)
    j = fspec.observed_columns.index(col)
    return res.innovations[:, j], res.innovation_var[:, j]


def _psi(psi: dict) -> str:
    """psi_opt as a reader wants it: 'a3 1e-04, a5 pruned'."""
    from ardflow.ardcore.jsonio import is_pruned

    return ", ".join(f"{k} {'pruned' if is_pruned(v) else f'{float(v):.0e}'}" for k, v in psi.items()) or "-"


def _comparison_table(summary: dict) -> str:
    """The model comparison (the paper's Table 10 analogue)."""
    rows = []
    for r in summary["models"]:
        rows.append("<tr>" + "".join([
            f"<td class=l>{html.escape(r['name'])}</td>",
            f"<td>{_fmt(r['goodness_of_fit'])}</td>", f"<td>{_fmt(r['information_gain'])}</td>",
            f"<td>{_fmt(r['log_evidence'])} &plusmn; {_fmt(r['log_evidence_se'])}</td>",
            (f"<td class=warn title='{html.escape(r['refused'], quote=True)}'>refused</td>" if r.get("refused")
             else f"<td>{_fmt(r['probability'], 4)}</td>"),
            f"<td class=l>{', '.join(r['kept']) or '-'}</td>", f"<td class=l>{', '.join(r['pruned']) or '-'}</td>",
            f"<td class=l>{html.escape(_psi(r['psi_opt']))}</td>"]) + "</tr>")
    why = "".join(f"<p class=warn>{html.escape(r['name'])} is refused, no result: {html.escape(r['refused'])}</p>"
                  for r in summary["models"] if r.get("refused"))
    return ("<table><tr><th class=l>model</th><th>GoF</th><th>EIG</th><th>ln evidence</th><th>P(M|d)</th>"
            "<th class=l>kept</th><th class=l>pruned</th><th class=l>psi_opt</th></tr>" + "".join(rows) + "</table>"
            + why)


def _flag(bad: bool, text: str) -> str:
    return f"<b class=warn>{text}</b>" if bad else text


def _convergence_table(summary: dict) -> str:
    """Every model's reported draws judged by ArviZ (rank-normalised split R-hat, bulk and tail ESS, MCSE
    of the mean), the values outside the target marked (an undefined one, JSON null, counts as outside)."""
    q = Quality()
    rows = []
    for r in summary["models"]:
        diag = r.get("diagnostics") or {}
        state = "converged" if r.get("converged") else "<b class=warn>not converged</b>"
        for i, (n, d) in enumerate(diag.items()):
            ok = {k: v is not None and math.isfinite(v) and (v <= q.max_rhat if k == "r_hat" else v >= q.min_ess)
                  for k, v in ((k, d.get(k)) for k in ("r_hat", "ess_bulk", "ess_tail"))}
            rows.append("<tr>" + (f"<td class=l rowspan={len(diag)}>{html.escape(r['name'])}<br>{state}</td>"
                                  if i == 0 else "")
                        + f"<td class=l>{html.escape(n)}</td>"
                        f"<td>{_flag(not ok['r_hat'], _fmt(d.get('r_hat'), 4))}</td>"
                        f"<td>{_flag(not ok['ess_bulk'], _fmt(d.get('ess_bulk'), 0))}</td>"
                        f"<td>{_flag(not ok['ess_tail'], _fmt(d.get('ess_tail'), 0))}</td>"
                        f"<td>{_fmt(d.get('mcse_mean') if d.get('mcse_mean') is None else f'{d['mcse_mean']:.2g}')}"
                        "</td></tr>")
    if not rows:
        return ""
    return (f"<h2>Convergence (ArviZ)</h2><p>Each model's reported draws, as <code>az.summary</code> judges them; "
            f"the target is R-hat &le; {q.max_rhat:g} and bulk and tail ESS &ge; {q.min_ess:g} for every "
            "parameter (Vehtari et al. 2021). The intervals and the evidence rest on these draws.</p>"
            "<table><tr><th class=l>model</th><th class=l>parameter</th><th>R-hat</th><th>bulk ESS</th>"
            "<th>tail ESS</th><th>MCSE mean</th></tr>" + "".join(rows) + "</table>")


def _posterior_table(names, samples, truth: dict, ref_bounds) -> str:
    """The best model's posterior: mean, sd, 99 % bounds; the true value and whether it is inside when the data
    were generated, the paper's bounds for the paper's own models (columns shown only when they hold something)."""
    known = [n for n in names if truth.get(n) is not None]
    paper = [n for n in names if ref_bounds and ref_bounds.get(n) is not None]
    post_rows = []
    for i, n in enumerate(names):
        x = samples[..., i].ravel()
        lo, hi = np.quantile(x, [0.005, 0.995])
        tv = truth.get(n)
        inside = "" if tv is None else ("yes" if lo <= tv <= hi else "<b class=warn>no</b>")
        pb = ref_bounds.get(n) if ref_bounds else None
        post_rows.append(f"<tr><td class=l>{n}</td><td>{_fmt(float(x.mean()), 4)}</td><td>{_fmt(float(x.std()), 4)}"
                         f"</td><td>[{_fmt(float(lo), 4)}, {_fmt(float(hi), 4)}]</td>"
                         + (f"<td>{_fmt(tv, 4)}</td><td>{inside}</td>" if known else "")
                         + (f"<td>{'-' if pb is None else f'[{pb[0]:g}, {pb[1]:g}]'}</td>" if paper else "")
                         + "</tr>")
    return ("<table><tr><th class=l>parameter</th><th>mean</th><th>sd</th><th>99 % bounds</th>"
            + ("<th>true</th><th>true inside</th>" if known else "") + ("<th>paper 99 %</th>" if paper else "")
            + "</tr>" + "".join(post_rows) + "</table>")


def _paper_section(summary: dict, spec) -> str:
    """This run against the paper's Table 10, and the reference checks."""
    prow = []
    best_here = max(r["log_evidence"] for r in summary["models"])
    best_paper = max(TABLE10[r["name"]]["log_evidence"] for r in summary["models"])
    for r in summary["models"]:
        p = TABLE10[r["name"]]
        prow.append(
            f"<tr><td class=l>{r['name']}</td><td>{_fmt(p['log_evidence'] + TABLE10_OFFSET, 2)}</td>"
            f"<td>{_fmt(r['log_evidence'], 2)}</td><td>{_fmt(p['log_evidence'] - best_paper, 2)}</td>"
            f"<td>{_fmt(r['log_evidence'] - best_here, 2)}</td>"
            f"<td>{_fmt(p['goodness_of_fit'] + TABLE10_OFFSET, 2)}</td>"
            f"<td>{_fmt(r['goodness_of_fit'], 2)}</td><td>{_fmt(p['information_gain'], 2)}</td>"
            f"<td>{_fmt(r['information_gain'], 2)}</td><td>{_fmt(p['probability'], 3)}</td>"
            f"<td>{_fmt(r['probability'], 3)}</td><td class=l>{', '.join(p['pruned'])}</td>"
            f"<td class=l>{', '.join(r['pruned']) or '-'}</td></tr>")
    paper = ("<h2>This run against the paper (Table 10)</h2><p>Absolute values depend on the noise realisation "
             "and the filter; compare the ranking, the pruning pattern, the decomposition trends and the "
             "parameter recovery (&Delta; ln Z: against the best model of the same run).</p><table><tr>"
             "<th class=l>model</th><th>ln Z paper</th><th>ln Z here</th>"
             "<th>&Delta; ln Z paper</th><th>&Delta; ln Z here</th>"
             "<th>GoF paper</th><th>GoF here</th><th>EIG paper</th><th>EIG here</th><th>P paper</th>"
             "<th>P here</th><th class=l>pruned paper</th><th class=l>pruned here</th></tr>" + "".join(prow)
             + "</table>")
    from ardflow.service.reports.paper import check_label, reference_checks

    checks = reference_checks(summary, spec.true_values)
    paper += ("<h3>Checks</h3><table><tr><th class=l>check</th><th>result</th><th class=l>detail</th></tr>"
              + "".join(f"<tr><td class=l>{html.escape(c['check'])}</td><td>{check_label(c)}"
                        f"</td><td class=l>{html.escape(c['detail'])}"
                        + (f"<br><i>documented difference: {html.escape(c['documented'])}</i>"
                           if c.get("documented") else "") + "</td></tr>" for c in checks) + "</table>")
    return paper
