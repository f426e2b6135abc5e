"""Figures for reports (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

import math
import threading
from pathlib import Path
from typing import NamedTuple

import numpy as np
from ardflow.ardcore.jsonio import is_pruned

TAU_SECONDS = 0.156 / (2 * 8.5)
"""Seconds per non-dimensional time unit of the reference problem (c / 2U)."""


DRAWING = threading.Lock()
"""One figure at a time in a process: matplotlib's font cache and mathtext are not thread-safe."""


def drawn_alone(fn, *args, **kw):
    """``fn(*args, **kw)`` (a plot) while no other thread of this process draws."""
    with DRAWING:
        return fn(*args, **kw)


class _Figures:
    """What the figures need of pyplot (``subplots``) without its global state: each figure is its own
    ``matplotlib.figure.Figure``, so figures drawn at once in several threads of one process (a threaded Dask
    worker drawing a report) stay apart, and none is left open."""

    @staticmethod
    def subplots(*args, figsize=None, **kw):
        from matplotlib.figure import Figure

        fig = Figure(figsize=figsize)
        return fig, fig.subplots(*args, **kw)


def pyplot() -> _Figures:
    """The figure factory the plots draw with (:class:`_Figures`, rendered by Agg on save)."""
    return _Figures()


class Labels(NamedTuple):
    """A figure's names: its ``title``, the ``time`` axis, the measured channel ``y`` (with its unit) and the
    spectrum's ``frequency_unit`` (the defaults are the reference problem's)."""

    title: str = "Reference data"
    time: str = "non-dimensional time tau"
    y: str = "pitch angle theta [rad]"
    frequency_unit: str = "cycles per time unit"


def plot_data_and_psd(t: np.ndarray, y: np.ndarray, out: str | Path, *, labels: Labels = Labels(),
                      clean: np.ndarray | None = None, cutoff: float | None = None,
                      tau_seconds: float | None = TAU_SECONDS) -> Path:
    """The measured signal (paper Fig. 2) and its power spectral density (Fig. 3).

    Parameters
    ----------
    t, y : ndarray
        Sample times and the measured channel.
    out : path
        PNG file to write.
    clean : ndarray, optional
        Noise-free signal, drawn underneath.
    cutoff : float, optional
        Low-pass cut-off (cycles per time unit), marked on the spectrum.
    tau_seconds : float, optional
        When given, the spectrum's top axis is also labelled in Hz.
    labels : Labels
        The title, the axes' labels (with units) and the spectrum's frequency unit.
    """
    from scipy.signal import welch

    plt = pyplot()
    fs = 1.0 / float(np.median(np.diff(t)))
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(9, 7))
    if clean is not None:
        a0.plot(t, clean, color="0.7", lw=2.0, label="noise-free")
    a0.plot(t, y, lw=0.7, color="C0", label="measured")
    a0.set_xlabel(labels.time)
    a0.set_ylabel(labels.y)
    a0.set_title(labels.title)
    if clean is not None:
        a0.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=9)
    f, pxx = welch(y - np.mean(y), fs=fs, nperseg=min(len(y), 2048))
    a1.semilogy(f, pxx, color="C0")
    if cutoff:
        a1.axvline(cutoff, color="C3", ls="--", lw=1, label=f"low-pass cut-off {cutoff:g}")
        a1.legend(fontsize=8)
    a1.set_xlabel(f"frequency [{labels.frequency_unit}]")
    a1.set_ylabel("PSD")
    a1.set_xlim(0, min(fs / 2, 5 * cutoff) if cutoff else fs / 2)
    if tau_seconds:
        sec = a1.secondary_xaxis("top", functions=(lambda x: x / tau_seconds, lambda x: x * tau_seconds))
        sec.set_xlabel("frequency [Hz]")
    return save_figure(fig, out)


def save_figure(fig, out):
    """Save to a path (returned as Path) or a binary file object."""
    fig.tight_layout()
    if isinstance(out, (str, Path)):
        out = Path(out)
    fig.savefig(out, dpi=110, format="png")
    return out


def plot_evidence_history(histories: dict[str, list[dict]], out):
    """ln evidence, goodness of fit and information gain per maximisation trial (Figs. 8, 11-14)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for i, (model, hist) in enumerate(histories.items()):
        it = [h["iteration"] for h in hist]
        for ax, key, label in zip(axes, ("log_evidence", "goodness_of_fit", "information_gain"),
                                  ("ln evidence", "goodness of fit", "information gain")):
            # a bound has no information gain of its own (its goodness of fit is the likelihood's maximum)
            y = np.array([h.get(key, np.nan) if isinstance(h.get(key), (int, float))
                          and not (h.get("bound") and key == "information_gain") else np.nan for h in hist])
            ax.plot(it, y, "-", color=f"C{i}", lw=1, label=model)
            # sampled trials (MCMC + Chib-Jeliazkov) as dots, reweighted ones (no likelihood evaluated) as crosses,
            # prune tests decided by an upper bound of ln Z as triangles pointing down (the value is at most that)
            smp = np.array([h.get("sampled", True) for h in hist], dtype=bool)
            bnd = np.array([bool(h.get("bound")) for h in hist], dtype=bool)
            ax.plot(np.asarray(it)[smp], y[smp], "o", color=f"C{i}", ms=3)
            ax.plot(np.asarray(it)[~smp & ~bnd], y[~smp & ~bnd], "x", color=f"C{i}", ms=5)
            ax.plot(np.asarray(it)[bnd], y[bnd], "v", color=f"C{i}", ms=5)
            acc = [j for j, h in enumerate(hist) if h.get("accepted")]
            ax.plot([it[j] for j in acc], y[acc], "o", color=f"C{i}", ms=7, mfc="none")
            ax.set_xlabel("trial")
            ax.set_title(label)
    axes[0].legend(fontsize=8, title="dots: sampled, x: reweighted\nv: upper bound, open circles: accepted")
    return save_figure(fig, out)


def plot_ard_bounds(history: list[dict], ard: list[str], out):
    """Prior (+-2.576/sqrt(alpha)) and posterior 99 % bounds of each ARD parameter per trial (Fig. 9)."""
    plt = pyplot()
    n = max(1, len(ard))
    fig, axes = plt.subplots(1, n, figsize=(3.6 * n, 3.6), squeeze=False)
    for ax, name in zip(axes[0], ard):
        for h in history:
            it = h["iteration"]
            a = h["psi"].get(name)
            post = h.get("posterior", {}).get(name)
            if is_pruned(a):
                rejected = str(h.get("action", "")).startswith(f"{name}: prune test") and not h.get("accepted")
                ax.plot([it], [0.0], "x", color="C1" if rejected else "C3")
                continue
            half = 2.576 / np.sqrt(float(a))
            ax.plot([it, it], [-half, half], color="0.75", lw=6, solid_capstyle="butt")
            if post:
                ax.plot([it, it], [post["q005"], post["q995"]], color="C0" if h.get("accepted") else "C1", lw=2)
        ax.set_yscale("symlog", linthresh=1.0)
        ax.set_title(name)
        ax.set_xlabel("trial")
    axes[0][0].set_ylabel("99 % bounds")
    fig.suptitle("prior (grey), posterior (blue: accepted trial, orange: rejected); x: term removed "
                 "(orange: its prune test, rejected)", fontsize=9)
    return save_figure(fig, out)


def plot_marginals(names: list[str], samples: np.ndarray, out, true_values: dict | None = None,
                   reference_bounds: dict | None = None):
    """Marginal posteriors with 99 % bounds and the true values (Fig. 15)."""
    plt = pyplot()
    d = len(names)
    cols = min(3, d)
    rows = int(np.ceil(d / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(4 * cols, 3 * rows), squeeze=False)
    flat = samples.reshape(-1, d)
    for i, name in enumerate(names):
        ax = axes[i // cols][i % cols]
        x = flat[:, i]
        ax.hist(x, bins=60, density=True, color="C0", alpha=0.7)
        lo, hi = np.quantile(x, [0.005, 0.995])
        ax.axvspan(lo, hi, color="C0", alpha=0.1, label="99 % bounds")
        if true_values and name in true_values:
            ax.axvline(true_values[name], color="C3", lw=2, label="true")
        if reference_bounds and name in reference_bounds:
            rlo, rhi = reference_bounds[name]
            ax.axvline(rlo, color="k", ls=":", lw=1, label="paper 99 %")
            ax.axvline(rhi, color="k", ls=":", lw=1)
        ax.set_title(name)
    for j in range(d, rows * cols):
        axes[j // cols][j % cols].axis("off")
    axes[0][0].legend(fontsize=7)
    return save_figure(fig, out)


def plot_joint(names: list[str], samples: np.ndarray, out, true_values: dict | None = None, max_points: int = 3000):
    """Pairwise joint posteriors (Fig. 16), thinned."""
    plt = pyplot()
    d = len(names)
    flat = samples.reshape(-1, d)
    flat = flat[:: max(1, flat.shape[0] // max_points)]
    fig, axes = plt.subplots(d, d, figsize=(2.0 * d, 2.0 * d), squeeze=False)
    for i in range(d):
        for j in range(d):
            ax = axes[i][j]
            if j > i:
                ax.axis("off")
                continue
            if i == j:
                ax.hist(flat[:, i], bins=40, color="C0")
            else:
                ax.plot(flat[:, j], flat[:, i], ".", ms=1, alpha=0.3, color="C0")
                if true_values and names[i] in true_values and names[j] in true_values:
                    ax.plot(true_values[names[j]], true_values[names[i]], "+", color="C3", ms=10, mew=2)
            if i == d - 1:
                ax.set_xlabel(names[j], fontsize=8)
            if j == 0:
                ax.set_ylabel(names[i], fontsize=8)
            ax.tick_params(labelsize=6)
    return save_figure(fig, out)


def plot_prediction(t: np.ndarray, y: np.ndarray, innovations: np.ndarray, innovation_var: np.ndarray,
                    out: str | Path, *, model: str, labels: Labels) -> Path:
    """The data against the model's one-step prediction (the EKF forecast, with its 95 % band), and the
    standardised residuals below it (white noise of unit variance when the model carries the data)."""
    plt = pyplot()
    pred = y - innovations
    sd = np.sqrt(innovation_var)
    n = min(t.size, 3000)  # a readable stretch of the record
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(11, 6.5), sharex=True, gridspec_kw={"height_ratios": [2, 1]})
    a0.fill_between(t[:n], (pred - 1.96 * sd)[:n], (pred + 1.96 * sd)[:n], color="C1", alpha=0.25, lw=0,
                    label="95 % prediction band")
    a0.plot(t[:n], y[:n], "k.", ms=2, label="data")
    a0.plot(t[:n], pred[:n], "C1", lw=0.9, label=f"{model}: one-step prediction")
    a0.set(ylabel=labels.y, title=f"data against the prediction of {model} (posterior mean)")
    a0.legend(fontsize=9, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    z = innovations / sd
    a1.plot(t[:n], z[:n], "C0", lw=0.6)
    a1.axhspan(-1.96, 1.96, color="0.9", zorder=0)
    a1.set(xlabel=labels.time, ylabel="standardised residual", title="residuals (grey: 95 % of white noise)")
    return save_figure(fig, out)


def _number(x) -> bool:
    """A finite number (a missing value, JSON null, or a NaN is written as a word instead)."""
    return isinstance(x, (int, float)) and math.isfinite(x)


def plot_model_probabilities(rows: list[dict], out: str | Path) -> Path:
    """P(M|d) of each candidate, with its ln evidence and standard error written on its bar."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 0.6 + 0.55 * len(rows)))
    names = [r["name"] for r in rows]
    p = [float(r.get("probability") or 0.0) for r in rows]
    ax.barh(names, p, color=["C2" if v == max(p) else "C7" for v in p])
    for i, r in enumerate(rows):
        z, se = r.get("log_evidence"), r.get("log_evidence_se")
        words = ("refused: no result" if r.get("refused") or not _number(z)
                 else f"P = {p[i]:.3f}   ln Z = {z:.2f} ± " + (f"{se:.2f}" if _number(se) else "unknown"))
        ax.text(min(p[i], 0.62) + 0.01, i, words, va="center", fontsize=9)
    ax.set(xlim=(0, 1), xlabel="posterior model probability P(M|d) (equal prior odds)",
           title="which model the data support")
    ax.invert_yaxis()
    return save_figure(fig, out)
