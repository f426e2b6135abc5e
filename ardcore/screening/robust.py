"""Evidence of a likelihood whose noise model is wrong in colour: the curvature (sandwich) adjustment.

The EKF likelihood takes its innovations as white. When they are not (a pipeline's low-pass filter, a
sensor's own dynamics) the score of a new term varies more than the likelihood's information says, and
the term looks better supported than it is. :func:`innovation_background` estimates the innovations'
actual spectrum, :func:`spectral_score_cov` the score's actual covariance from it (exactly, by Parseval),
and :func:`sandwich` adjusts the information and the score to it (used by :mod:`ardcore.screening.screen`).
"""

from __future__ import annotations

import numpy as np


def innovation_background(e: np.ndarray, *, median_bins: int = 9, segments: int = 8):
    """Spectral density of standardised innovations relative to white noise (1 = as the likelihood assumes),
    as a function of frequency in cycles per sample; None when it cannot be estimated.

    A Welch estimate (segments of about n/``segments`` samples, so bins of ~``segments``/n cycles per
    sample) smoothed by a running median over ``median_bins`` bins: a line (a missing forcing, 3-4 bins
    of a Hann window) does not count as noise, while colour that is narrow itself does (a pipeline's
    low-pass filter leaves the reference data's noise in a band of 0.023 cycles per sample, which
    segments of n/16 could not resolve). One observed channel only (several channels: None, the screen
    is not adjusted).
    """
    from scipy import signal

    e = np.asarray(e, float)
    if e.ndim == 2:
        if e.shape[1] != 1:
            return None
        e = e[:, 0]
    x = np.where(np.isfinite(e), e, 0.0)
    if np.isfinite(e).sum() < 64:
        return None
    nper = int(max(32, 2 ** int(np.log2(max(x.size // segments, 32)))))
    f, P = signal.welch(x, fs=1.0, nperseg=nper)
    P = P * np.where((f > 0) & (f < 0.5), 0.5, 1.0)  # one-sided density of unit white noise: 2 inside, 1 at the ends
    h = median_bins // 2
    bg = np.median(np.lib.stride_tricks.sliding_window_view(np.pad(P, h, mode="edge"), 2 * h + 1), axis=1)
    bg = bg / max(float(np.mean(np.isfinite(e) & (e != 0))), 1e-12)  # zeros for missing samples dilute the power
    return lambda fq: np.interp(fq, f, bg)


def spectral_score_cov(psi: np.ndarray, psd) -> np.ndarray:
    """Covariance of the score ``psi @ eps`` when the standardised innovations ``eps`` have the relative
    spectral density ``psd`` (the likelihood assumes 1: then the result is ``psi @ psi.T``).

    ``psi`` (rows: parameters, columns: samples) are the innovations' standardised sensitivities; by
    Parseval, ``Var(sum_t psi_t eps_t) = (1/n) sum_f psi_hat(f) S(f) psi_hat(f)^H``.
    """
    n = psi.shape[1]
    F = np.fft.rfft(psi, axis=1)
    fq = np.fft.rfftfreq(n)
    w = psd(fq) * np.where((fq > 0) & (fq < 0.5), 2.0, 1.0) / n
    V = np.real((F * w) @ np.conj(F).T)
    return 0.5 * (V + V.T)


def sandwich(H: np.ndarray, gb: np.ndarray, V: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Information and score of the likelihood adjusted to the score's actual variance ``V``.

    The EKF likelihood assumes white innovations; when they are not (coloured measurement noise, a
    filter in the data pipeline) the score varies more than its information says and every term looks
    more supported than it is. The curvature adjustment of a misspecified likelihood (Chandler and
    Bate 2007; Pauli, Racugno and Ventura 2011) replaces ``H`` by ``H V^-1 H`` and the score by
    ``H V^-1 g``, which keeps the estimate ``H^-1 g`` and gives it the sandwich variance
    ``H^-1 V H^-1``. Directions in which the score varies *less* than ``H`` says are left as they are:
    the screen never claims more evidence than the model's own likelihood.

    Returns the adjusted information and score, and the largest factor by which the likelihood
    understated the score's variance (1 for a correct likelihood).
    """
    w, U = np.linalg.eigh(H)
    keep = w > 1e-12 * max(float(w.max()), 1e-300)
    if not keep.any():
        return H, gb, 1.0
    M = U[:, keep] * np.sqrt(w[keep])                 # H = M M' on its range
    Minv = (U[:, keep] / np.sqrt(w[keep])).T
    A = Minv @ V @ Minv.T                             # V relative to H: identity for a correct likelihood
    c, Q = np.linalg.eigh(0.5 * (A + A.T))
    Ainv = (Q / np.maximum(c, 1.0)) @ Q.T
    Hs = M @ Ainv @ M.T
    gs = M @ Ainv @ (Minv @ gb)
    return 0.5 * (Hs + Hs.T), gs, float(max(np.max(c), 1.0))
