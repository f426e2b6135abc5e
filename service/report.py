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
    fig.tight_layout()
    out = Path(out)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
