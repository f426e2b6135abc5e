"""Figures for reports (matplotlib, Agg backend, PNG files)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

TAU_SECONDS = 0.156 / (2 * 8.5)
"""Seconds per non-dimensional time unit of the reference problem (c / 2U)."""


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_data_and_psd(t: np.ndarray, y: np.ndarray, out: str | Path, *, clean: np.ndarray | None = None,
                      cutoff: float | None = None, title: str = "Reference data",
                      time_label: str = "non-dimensional time tau", tau_seconds: float | None = TAU_SECONDS) -> Path:
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
    """
    from scipy.signal import welch

    plt = _plt()
    fs = 1.0 / float(np.median(np.diff(t)))
    fig, (a0, a1) = plt.subplots(2, 1, figsize=(9, 7))
    if clean is not None:
        a0.plot(t, clean, color="0.7", lw=2.0, label="clean theta")
    a0.plot(t, y, lw=0.7, color="C0", label="measured (noisy, filtered)")
    a0.set_xlabel(time_label)
    a0.set_ylabel("pitch angle theta [rad]")
    a0.set_title(title)
    a0.legend(loc="upper left", fontsize=8)
    f, pxx = welch(y - np.mean(y), fs=fs, nperseg=min(len(y), 2048))
    a1.semilogy(f, pxx, color="C0")
    if cutoff:
        a1.axvline(cutoff, color="C3", ls="--", lw=1, label=f"low-pass cut-off {cutoff:g}")
        a1.legend(fontsize=8)
    a1.set_xlabel("frequency [cycles per time unit]")
    a1.set_ylabel("PSD")
    a1.set_xlim(0, min(fs / 2, 5 * cutoff) if cutoff else fs / 2)
    if tau_seconds:
        sec = a1.secondary_xaxis("top", functions=(lambda x: x / tau_seconds, lambda x: x * tau_seconds))
        sec.set_xlabel("frequency [Hz]")
    return _save(fig, out)


def _save(fig, out):
    """Save to a path (returned as Path) or a binary file object."""
    plt = _plt()
    fig.tight_layout()
    if isinstance(out, (str, Path)):
        out = Path(out)
    fig.savefig(out, dpi=110, format="png")
    plt.close(fig)
    return out


def plot_evidence_history(histories: dict[str, list[dict]], out):
    """ln evidence, goodness of fit and information gain per maximisation trial (Figs. 8, 11-14)."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for i, (model, hist) in enumerate(histories.items()):
        it = [h["iteration"] for h in hist]
        for ax, key, label in zip(axes, ("log_evidence", "goodness_of_fit", "information_gain"),
                                  ("ln evidence", "goodness of fit", "information gain")):
            y = np.array([h.get(key, np.nan) if isinstance(h.get(key), (int, float)) else np.nan for h in hist])
            ax.plot(it, y, "o-", color=f"C{i}", ms=3, lw=1, label=model)
            acc = [j for j, h in enumerate(hist) if h.get("accepted")]
            ax.plot([it[j] for j in acc], y[acc], "o", color=f"C{i}", ms=7, mfc="none")
            ax.set_xlabel("trial")
            ax.set_title(label)
    axes[0].legend(fontsize=8, title="open circles: accepted")
    return _save(fig, out)
