"""Peer baselines for the closed-loop benchmark, on the same data and splits as the loop.

Free-run (simulation) RMS error on a test record, the benchmark convention: the first
``init`` samples of the test record may be used to initialise (here: as the lagged
outputs a NARX model needs), the error is taken from sample ``init`` on.

* ``arx``: linear ARX by least squares (orders as the Silverbox literature uses them).
* ``narx``: polynomial NARX by least squares: linear lags of y and u and the
  polynomial terms in y of degree 2 and 3 a Duffing-type circuit needs, then a
  simulation-error refit of the same coefficients (Gauss-Newton on the free run of a
  part of the estimation record, as is customary for NARX models used in simulation).
* ``pysindy`` / ``sysidentpy``: when installed (``pip install -e '.[bench]'``), each
  configured as its documentation advises for a forced system.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit
from scipy import optimize


def _lagged(y: np.ndarray, u: np.ndarray, na: int, nb: int, k0: int) -> tuple[np.ndarray, np.ndarray]:
    """Linear regressors y(k-1..k-na), u(k..k-nb) for k >= k0."""
    n = y.size
    ks = np.arange(k0, n)
    cols = [y[ks - i] for i in range(1, na + 1)] + [u[ks - j] for j in range(0, nb + 1)]
    return np.column_stack(cols), y[ks]


def _narx_features(ylags: np.ndarray, ulags: np.ndarray) -> np.ndarray:
    """[1, y lags, u lags, y1^2, y1 y2, y2^2, y1^3, y1^2 y2, y1 y2^2, y2^3] per row."""
    y1, y2 = ylags[:, 0], ylags[:, 1]
    return np.column_stack([np.ones(len(y1)), ylags, ulags, y1 * y1, y1 * y2, y2 * y2,
                            y1 ** 3, y1 * y1 * y2, y1 * y2 * y2, y2 ** 3])


NA, NB = 3, 3


@njit(cache=True)
def _simulate_narx(theta, y0, u, na, nb):
    """Free run of the NARX (and ARX when the polynomial part is zero) from the first lags of y0."""
    n = u.size
    y = np.empty(n)
    k0 = max(na, nb)
    y[:k0] = y0[:k0]
    for k in range(k0, n):
        y1, y2 = y[k - 1], y[k - 2]
        v = theta[0]
        for i in range(na):
            v += theta[1 + i] * y[k - 1 - i]
        for j in range(nb + 1):
            v += theta[1 + na + j] * u[k - j]
        b = 1 + na + nb + 1
        v += (theta[b] * y1 * y1 + theta[b + 1] * y1 * y2 + theta[b + 2] * y2 * y2 + theta[b + 3] * y1 ** 3
              + theta[b + 4] * y1 * y1 * y2 + theta[b + 5] * y1 * y2 * y2 + theta[b + 6] * y2 ** 3)
        if not math.isfinite(v) or abs(v) > 1e6:
            y[k:] = np.nan
            return y
        y[k] = v
    return y


def fit_narx(y: np.ndarray, u: np.ndarray, *, polynomial: bool = True, refit_samples: int = 20000) -> np.ndarray:
    """Least squares (one-step), then for the NARX a simulation-error refit on part of the record."""
    k0 = max(NA, NB)
    L, target = _lagged(y, u, NA, NB, k0)
    F = _narx_features(L[:, :NA], L[:, NA:])
    if not polynomial:
        F = F[:, :1 + NA + NB + 1]
    s = np.linalg.norm(F, axis=0)
    s[s == 0] = 1
    th, *_ = np.linalg.lstsq(F / s, target, rcond=None)
    th = th / s
    full = np.zeros(1 + NA + NB + 1 + 7)
    full[:th.size] = th
    if not polynomial:
        return full
    m = min(refit_samples, y.size)
    ys, us = y[:m], u[:m]

    def resid(p):
        sim = _simulate_narx(p * full_scale, ys, us, NA, NB)
        r = sim[k0:] - ys[k0:]
        return np.where(np.isfinite(r), r, 1.0)

    full_scale = np.where(full != 0, np.abs(full), 1.0)
    r = optimize.least_squares(resid, full / full_scale, method="lm", max_nfev=200 * full.size)
    cand = r.x * full_scale
    # keep the refit only when it simulates better on the estimation part it was fitted on
    e0 = np.sqrt(np.nanmean(resid(full / full_scale) ** 2))
    e1 = np.sqrt(np.nanmean(resid(r.x) ** 2))
    return cand if e1 < e0 else full


def free_run_rms(theta: np.ndarray, y: np.ndarray, u: np.ndarray, init: int = 50) -> float:
    sim = _simulate_narx(theta, y, u, NA, NB)
    e = sim[init:] - y[init:]
    return float(np.sqrt(np.mean(e ** 2))) if np.all(np.isfinite(e)) else float("inf")


def pysindy_free_run(y_est, u_est, tests: dict, fs: float, init: int = 50) -> dict | None:
    """PySINDy on (y, dy/dt) with the input as control, cubic polynomial library, STLSQ (its documented
    defaults for a forced oscillator); free run by its own ``simulate`` from the state at sample ``init``."""
    try:
        import pysindy as ps
    except ImportError:
        return None
    dt = 1.0 / fs
    x = np.column_stack([y_est, np.gradient(y_est, dt)])
    model = ps.SINDy(feature_library=ps.PolynomialLibrary(degree=3), optimizer=ps.STLSQ(threshold=1e-3))
    model.fit(x, t=dt, u=u_est[:, None])
    out = {}
    for name, (yt, ut) in tests.items():
        xt = np.column_stack([yt, np.gradient(yt, dt)])
        t = np.arange(yt.size - init) * dt
        try:
            sim = model.simulate(xt[init], t, u=ut[init:, None], integrator="odeint")
            e = sim[:, 0] - yt[init:init + sim.shape[0]]
            out[name] = float(np.sqrt(np.mean(e ** 2))) if sim.shape[0] == t.size else float("inf")
        except Exception:  # a diverging simulation is a result, not a crash of the bench
            out[name] = float("inf")
    return out


def sysidentpy_free_run(y_est, u_est, tests: dict, init: int = 50) -> dict | None:
    """SysIdentPy FROLS polynomial NARX (degree 3, lags 3, 13 terms, as its Silverbox example), free run
    with ``steps_ahead=None`` from the first lags of each test record."""
    try:
        from sysidentpy.basis_function import Polynomial
        from sysidentpy.model_structure_selection import FROLS
    except ImportError:
        return None
    model = FROLS(order_selection=False, n_terms=13, ylag=3, xlag=3, basis_function=Polynomial(degree=3))
    model.fit(X=u_est[:, None], y=y_est[:, None])
    out = {}
    for name, (yt, ut) in tests.items():
        try:
            yh = model.predict(X=ut[:, None], y=yt[:init, None], steps_ahead=None).ravel()
            e = yh[init:] - yt[init:yh.size]
            out[name] = float(np.sqrt(np.mean(e ** 2))) if np.all(np.isfinite(e)) else float("inf")
        except Exception:
            out[name] = float("inf")
    return out
