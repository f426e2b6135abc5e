"""The figures of a closed-loop diagnosis report (:mod:`service.reports.diagnosis`): the innovations' whiteness
and spectrum, the process noise the filter injected, the candidates ranked and the free run before and after."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ardflow.ardcore.jsonio import number
from ardflow.service.reports.plots import pyplot, save_figure


def frequency_label(time_label: str) -> str:
    """The frequency axis's label for a time axis labelled ``time_label`` (Hz when time is in seconds)."""
    return "frequency [Hz]" if time_label.endswith("[s]") else "frequency [cycles per time unit]"


def plot_tests(arrays: dict, col: str, out: Path, time_label: str = "time") -> Path:
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
    a2.set(xlabel=frequency_label(time_label), ylabel="PSD", title="innovation spectrum (peaks marked)")
    a1.legend(fontsize=8)
    a2.legend(fontsize=8)
    return save_figure(fig, out)


def plot_noise(arrays: dict, t: np.ndarray, out: Path, time_label: str = "time") -> Path:
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


def candidate_fates(report: dict, candidates: list) -> list[str]:
    """Per screened candidate: ``added`` (confirmed and in the model), ``confirmed`` (confirmed, not added) or
    ``screened`` (never confirmed). A confirmation names the effect as fitted (its shape refined), the screen as
    screened: they are matched by the latter."""
    conf = {(x.get("screened_effect", x["effect"]), x["target"]): x for x in report["confirmed"]}
    added = {(a["effect"], a["target"]) for a in report.get("added", [])}
    out = []
    for x in candidates:
        k = conf.get((x["effect"], x["target"]))
        out.append("screened" if k is None else "added" if (k["effect"], k["target"]) in added else "confirmed")
    return out


def plot_candidates(report: dict, out: Path, k: int = 12) -> Path:
    plt = pyplot()
    c = report["candidates"][:k][::-1]
    fig, ax = plt.subplots(figsize=(8, 0.35 * len(c) + 1.2))
    colors = [{"added": "C2", "confirmed": "C1", "screened": "0.6"}[f] for f in candidate_fates(report, c)]
    # screened ln BF spans nats to tens of thousands: a signed log scale keeps both ends readable
    v = np.array([number(x["log_bayes_factor"]) for x in c])
    v = np.where(np.isfinite(v), v, 0.0)  # a failed confirmation has no bar
    if not len(c):  # --max-rounds 0: nothing was screened
        ax.text(0.5, 0.5, "no candidates screened", ha="center", va="center", transform=ax.transAxes)
        ax.set_axis_off()
        return save_figure(fig, out)
    ax.barh([f"{x['effect']} -> {x['target']}" for x in c], np.sign(v) * np.log10(1 + np.abs(v)), color=colors)
    ticks = [t for t in (-100, -10, 0, 3, 10, 100, 1000, 10000, 100000) if abs(t) <= max(10, np.abs(v).max() * 1.5)]
    ax.set_xticks(np.sign(ticks) * np.log10(1 + np.abs(ticks)), [str(t) for t in ticks])
    ax.axvline(np.log10(4), color="k", lw=0.6, ls=":")
    ax.set(xlabel="screened ln Bayes factor of adding the effect (dotted: 3 nats)",
           title="candidate effects of round 0, as screened")
    from matplotlib.patches import Patch

    ax.legend(handles=[Patch(color="C2", label="confirmed and added"), Patch(color="C1", label="confirmed, not added"),
                       Patch(color="0.6", label="screened only")], fontsize=9, loc="upper left",
              bbox_to_anchor=(1.01, 1.0))
    return save_figure(fig, out)


ZOOM_SAMPLES = 600
"""How many samples of the test record the free-run figure shows in full (a few periods of a typical response)."""


def plot_free_run(arrays: dict, out: Path, label=str) -> Path:
    """The free run before and after: the error over the whole test record (where the improvement shows), a
    zoom on :data:`ZOOM_SAMPLES` samples with the data and the bands (where the loudest stretch of the data is,
    its span in the title), and the spectra; ``label(column)`` is an axis label with its unit
    (:meth:`DataSpec.axis_label`)."""
    plt = pyplot()
    fr0 = arrays["before"]["free_run"]
    fr1 = arrays["after"]["free_run"] if "after" in arrays else None
    runs = [(fr0, "before", "C3")] + ([(fr1, "after", "C0")] if fr1 is not None else [])
    fig, (a0, a1, a2) = plt.subplots(3, 1, figsize=(11, 9))
    t, y = fr0["t"], fr0["y"]
    ylab = label(arrays.get("column", "y"))
    for fr, name, st in runs:
        e = fr["y"] - fr["y_free"]
        a0.plot(fr["t"], e, st, lw=0.5, label=f"{name}: RMS {float(fr['rms_error']):.4g}")
    a0.set(xlabel=label("t"), ylabel=f"error: {ylab}", title=f"free-run error over the whole test record "
           f"({t.size:,} samples, {t[0]:.6g} to {t[-1]:.6g})")
    a0.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    n = min(t.size, ZOOM_SAMPLES)
    yc = np.nan_to_num(y - np.nanmean(y))
    k = int(np.argmax(np.convolve(yc ** 2, np.ones(n), mode="valid"))) if t.size > n else 0
    z = slice(k, k + n)
    a1.plot(t[z], y[z], "k", lw=0.9, label="data")
    for fr, name, st in runs:
        if "band" in fr:
            # a bound made infinite by diverged draws is drawn at the edge of the data's range
            edge = np.nanmax(np.abs(y[z] - np.nanmean(y[z]))) * 3 + np.abs(np.nanmean(y[z]))
            a1.fill_between(fr["t"][z], np.clip(fr["band"][0][z], -edge, edge), np.clip(fr["band"][1][z], -edge, edge),
                            color=st, alpha=0.15, lw=0,
                            label=f"90 % band, {name} ({100 * fr['band_coverage']:.0f} % of the record inside)")
        a1.plot(fr["t"][z], fr["y_free"][z], st, lw=0.8, label=f"free run, {name}")
    a1.set(xlabel=label("t"), ylabel=ylab,
           title=f"zoom: samples {k:,} to {k + n:,} of the test record (its loudest stretch)" if t.size > n
           else "the whole test record")
    a1.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    from scipy import signal

    fs = 1.0 / float(np.median(np.diff(t)))
    for yy, lab, st in [(y, "data", "k")] + [(fr["y_free"], name, st) for fr, name, st in runs]:
        if np.all(np.isfinite(yy)):
            f, P = signal.welch(yy - np.mean(yy), fs=fs, nperseg=min(yy.size, 4096))
            a2.semilogy(f, P + 1e-300, st, lw=0.8, label=lab)
    a2.set(xlabel=frequency_label(label("t")),
           ylabel="PSD", title="spectra (compare these, not phase, for self-excited systems)")
    a2.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    return save_figure(fig, out)
