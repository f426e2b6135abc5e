"""Peer baselines for the closed-loop benchmark, on the same data and splits as the loop.

Free-run (simulation) RMS error on a test record, the benchmark convention: the first
``init`` samples of the test record may be used to initialise (here: as the lagged
outputs a NARX model needs), the error is taken from sample ``init`` on.

* ``arx``: linear ARX by least squares (orders as the Silverbox literature uses them).
* ``narx``: polynomial NARX by least squares: linear lags of y and u and the
  polynomial terms in y of degree 2 and 3 a Duffing-type circuit needs, then a
  simulation-error refit of the same coefficients (Gauss-Newton on the free run of a
  part of the estimation record, as is customary for NARX models used in simulation).
* ``pysindy`` / ``sysidentpy``: when installed (``pip install -e '.[bench]'``): PySINDy's
  discrete-time SINDy and SysIdentPy's FROLS/AOLS polynomial NARX, their settings chosen on
  a validation part of the estimation record.
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


@njit(cache=True)
def _poly_map(coef, powers, x0, c):
    """Free run of a polynomial map x_{k+1} = coef @ prod(z_k ** powers), z_k = (x_k, c_k)."""
    n, nx = c.shape[0], x0.size
    out = np.empty((n, nx))
    x = x0.copy()
    out[0] = x
    for k in range(1, n):
        z = np.concatenate((x, c[k - 1]))
        th = np.ones(powers.shape[0])
        for j in range(powers.shape[0]):
            for i in range(z.size):
                for _ in range(powers[j, i]):
                    th[j] *= z[i]
        x = coef @ th
        if not np.all(np.isfinite(x)) or np.max(np.abs(x)) > 1e6:
            out[k:] = np.nan
            return out
        out[k] = x
    return out


def pysindy_free_run(y_est, u_est, tests: dict, init: int = 50) -> dict | None:
    """PySINDy's discrete-time SINDy (``DiscreteSINDy``) on the state (y_k, y_{k-1}) with (u_k, u_{k-1}) as
    control, a cubic polynomial library and STLSQ, the threshold chosen by free run on the last 20 % of the
    estimation record (continuous-time SINDy needs the second derivative of a measured signal, which
    free-ran at 55-300 mV here); free run of the identified map from the first ``init`` samples."""
    try:
        import pysindy as ps
    except ImportError:
        return None

    def st(y, u):
        return np.column_stack([y[1:], y[:-1]]), np.column_stack([u[1:], u[:-1]])

    def fit(th, y, u):
        x, c = st(y, u)
        m = ps.DiscreteSINDy(feature_library=ps.PolynomialLibrary(degree=3), optimizer=ps.STLSQ(threshold=th))
        m.fit(x, t=1, u=c)
        return m

    def run(m, y, u):
        x, c = st(y, u)
        coef = np.ascontiguousarray(m.coefficients(), dtype=float)
        powers = np.ascontiguousarray(m.feature_library.powers_, dtype=np.int64)
        sim = _poly_map(coef, powers, x[init - 1].astype(float), np.ascontiguousarray(c[init - 1:], dtype=float))
        e = sim[:, 0] - x[init - 1:, 0]
        return float(np.sqrt(np.mean(e[1:] ** 2))) if np.all(np.isfinite(e)) else float("inf")

    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cut = int(0.8 * y_est.size)
        best = min((run(fit(th, y_est[:cut], u_est[:cut]), y_est[cut:], u_est[cut:]), th)
                   for th in (1e-5, 1e-4, 1e-3, 1e-2))
        model = fit(best[1], y_est, u_est)
    return {name: run(model, yt, ut) for name, (yt, ut) in tests.items()}


def sysidentpy_free_run(y_est, u_est, tests: dict, init: int = 50) -> dict | None:
    """SysIdentPy polynomial NARX (degree 3, lags 3): FROLS with 13 terms and AOLS (k = 13, L = 1), the one
    that free-runs better on the last 20 % of the estimation record is refitted on all of it; free run
    (``steps_ahead=None``) from the first ``init`` samples of each test record."""
    try:
        from sysidentpy.basis_function import Polynomial
        from sysidentpy.model_structure_selection import AOLS, FROLS
    except ImportError:
        return None
    import warnings

    def make(kind):
        if kind == "frols":
            return FROLS(order_selection=False, n_terms=13, ylag=3, xlag=3, basis_function=Polynomial(degree=3))
        return AOLS(ylag=3, xlag=3, k=13, L=1, basis_function=Polynomial(degree=3))

    def run(model, yt, ut):
        try:
            yh = model.predict(X=ut[:, None], y=yt[:init, None], steps_ahead=None).ravel()
            e = yh[init:] - yt[init:yh.size]
            return float(np.sqrt(np.mean(e ** 2))) if np.all(np.isfinite(e)) else float("inf")
        except Exception:  # a diverging free run is a result, not a crash of the bench
            return float("inf")

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        cut = int(0.8 * y_est.size)
        scores = []
        for kind in ("frols", "aols"):
            m = make(kind)
            m.fit(X=u_est[:cut, None], y=y_est[:cut, None])
            scores.append((run(m, y_est[cut:], u_est[cut:]), kind))
        model = make(min(scores)[1])
        model.fit(X=u_est[:, None], y=y_est[:, None])
    return {name: run(model, yt, ut) for name, (yt, ut) in tests.items()}
