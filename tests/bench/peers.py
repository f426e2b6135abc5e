"""Peer baselines for the closed-loop benchmark, on the same data and splits as the loop.

Free-run (simulation) RMS error on a test record, the benchmark convention: the first
``init`` samples of the test record may be used to initialise (here: as the lagged
outputs a NARX model needs), the error is taken from sample ``init`` on.

* ``arx`` and ``narx`` (:func:`tuned_narx`): a linear ARX and a polynomial NARX as their users tune them:
  orders, degree and terms (forward orthogonal least squares) chosen by free run on validation blocks of the
  estimation record, then a simulation-error refit (Levenberg-Marquardt on the free run, as is customary for
  NARX models used in simulation).
* ``pysindy`` / ``sysidentpy``: when installed (``pip install -e '.[bench]'``): PySINDy's
  discrete-time SINDy and SysIdentPy's FROLS/AOLS polynomial NARX, their settings chosen on
  a validation part of the estimation record, the record fed as it is or standardized
  (:func:`scaling_tuned`).
"""

from __future__ import annotations

import functools
import math

import numpy as np
from numba import njit
from scipy import optimize


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


def scaling_tuned(peer):
    """``peer(y_est, u_est, tests, init)`` (returning its errors on ``tests`` and its settings' error on its own
    validation part of the estimation record) fed the record as it is and standardized (the output and the input
    centred and scaled by the estimation record's mean and standard deviation), as a user tries both: the one
    whose settings free-run the validation part better, its errors in the record's units. On raw values a
    polynomial library's columns can differ in their sixth digit (a temperature near 300 K, cubed) and a
    sparsity threshold means nothing across scales: PySINDy fed the two-mass record raw diverged."""

    # the peer's name and docstring, not its annotations: the wrapper returns the errors alone (a dict)
    @functools.wraps(peer, assigned=("__module__", "__name__", "__qualname__", "__doc__"))
    def run(y_est, u_est, tests: dict, init: int = 50) -> dict | None:
        best = None
        for standard in (False, True):
            (my, sy), (mu, su) = (((float(np.mean(x)), float(np.std(x)) or 1.0) if standard else (0.0, 1.0))
                                  for x in (y_est, u_est))
            got = peer((y_est - my) / sy, (u_est - mu) / su,
                       {k: ((y - my) / sy, (u - mu) / su) for k, (y, u) in tests.items()}, init)
            if got is not None and (best is None or got[1] * sy < best[1]):
                best = ({k: v * sy for k, v in got[0].items()}, got[1] * sy)
        return None if best is None else best[0]
    return run


@scaling_tuned
def pysindy_free_run(y_est, u_est, tests: dict, init: int = 50) -> tuple[dict, float] | None:
    """PySINDy's discrete-time SINDy (``DiscreteSINDy``) on the state (y_k, y_{k-1}) with (u_k, u_{k-1}) as
    control, a cubic polynomial library (quadratic, then linear, when every threshold's cubic map blows up) and
    STLSQ, the threshold chosen by free run on the last 20 % of the estimation record (continuous-time SINDy
    needs the second derivative of a measured signal, which free-ran at 55-300 mV here); free run of the
    identified map from the first ``init`` samples, and the chosen threshold's error on that last 20 %
    (:func:`scaling_tuned`)."""
    try:
        import pysindy as ps
    except ImportError:
        return None

    def st(y, u):
        return np.column_stack([y[1:], y[:-1]]), np.column_stack([u[1:], u[:-1]])

    def fit(th, y, u, degree=3):
        x, c = st(y, u)
        m = ps.DiscreteSINDy(feature_library=ps.PolynomialLibrary(degree=degree), optimizer=ps.STLSQ(threshold=th))
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
        model = None
        # the cubic library first; when every threshold's map blows up, a user lowers the degree
        for degree in (3, 2, 1):
            ranked = sorted((run(fit(th, y_est[:cut], u_est[:cut], degree), y_est[cut:], u_est[cut:]), th)
                            for th in (1e-5, 1e-4, 1e-3, 1e-2))
            if model is None:  # the cubic's best on the validation part, should no degree stay bounded
                model, val = fit(ranked[0][1], y_est, u_est), ranked[0][0]
            # the best threshold whose map, fitted on the whole record, stays bounded there and on every test
            # record's inputs (a user re-chooses one that blows up; the test outputs only score it)
            bounded = next(((v, m) for v, th in ranked
                            if _bounded(run, m := fit(th, y_est, u_est, degree), [(y_est, u_est), *tests.values()])),
                           None)
            if bounded is not None:
                val, model = bounded
                break
    return {name: run(model, yt, ut) for name, (yt, ut) in tests.items()}, val


def _bounded(run, model, records) -> bool:
    """Whether ``run(model, y, u)`` (an RMS error, inf where the simulation left any sane range) is finite on each
    ``(y, u)`` of ``records``: the simulation reads only ``y``'s first samples and ``u``, so this is a check a
    user makes before any test output is seen."""
    return all(math.isfinite(run(model, y, u)) for y, u in records)


@scaling_tuned
def sysidentpy_free_run(y_est, u_est, tests: dict, init: int = 50) -> tuple[dict, float] | None:
    """SysIdentPy's polynomial NARX as its users tune it: FROLS (and AOLS) over lags 1-4, degree 2-3 and 5-20
    terms, each fitted on the first 80 % of the estimation record and free-run (``steps_ahead=None``) over the
    rest; the best that stays bounded there is refitted on all of it and free-run on each test record from its
    first ``init`` samples, and its error on that rest (:func:`scaling_tuned`)."""
    try:
        from sysidentpy.basis_function import Polynomial
        from sysidentpy.model_structure_selection import AOLS, FROLS
    except ImportError:
        return None
    import warnings

    def make(kind, lag, degree, n):
        if kind == "frols":
            return FROLS(order_selection=False, n_terms=n, ylag=lag, xlag=lag, basis_function=Polynomial(degree=degree))
        return AOLS(ylag=lag, xlag=lag, k=n, L=1, basis_function=Polynomial(degree=degree))

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
            for lag in (1, 2, 3, 4):
                for degree in (2, 3):
                    for n in (5, 8, 13, 20):
                        try:
                            m = make(kind, lag, degree, n)
                            m.fit(X=u_est[:cut, None], y=y_est[:cut, None])
                        except Exception:  # a grid point the library cannot fit is skipped, as a user would
                            continue
                        # scored on the validation block; one that diverges over the whole record is out
                        val = run(m, y_est[cut:], u_est[cut:])
                        scores.append((val if math.isfinite(run(m, y_est, u_est)) else math.inf, (kind, lag, degree, n)))
        model = None
        for val, cfg in sorted(scores, key=lambda s: s[0]):
            m = make(*cfg)
            m.fit(X=u_est[:, None], y=y_est[:, None])
            # refitted on the whole record, it must still stay bounded there and on the test records' inputs
            if _bounded(run, m, [(y_est, u_est), *tests.values()]):
                model = m
                break
        if model is None:
            return None
    return {name: run(model, yt, ut) for name, (yt, ut) in tests.items()}, val


# --------------------------------------------------------------------------- the NARX as its users tune it


@njit(cache=True)
def _simulate_terms(theta, powers, y0, u, na, nb):
    """Free run of a polynomial NARX y(k) = theta @ prod(z ** powers), z = [y(k-1..k-na), u(k..k-nb)], from
    the first max(na, nb) samples of ``y0``; NaN from where it leaves any sane range."""
    n = u.size
    y = np.empty(n)
    k0 = max(na, nb)
    y[:k0] = y0[:k0]
    z = np.empty(na + nb + 1)
    for k in range(k0, n):
        for i in range(na):
            z[i] = y[k - 1 - i]
        for j in range(nb + 1):
            z[na + j] = u[k - j]
        v = 0.0
        for t in range(powers.shape[0]):
            f = theta[t]
            for i in range(z.size):
                for _ in range(powers[t, i]):
                    f *= z[i]
            v += f
        if not math.isfinite(v) or abs(v) > 1e6:
            y[k:] = np.nan
            return y
        y[k] = v
    return y


def _powers(na: int, nb: int, degree: int) -> np.ndarray:
    """Exponents of every monomial of z = [y(k-1..k-na), u(k..k-nb)] up to ``degree``, the constant first."""
    import itertools

    m = na + nb + 1
    rows = [np.zeros(m, dtype=np.int64)]
    for d in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(range(m), d):
            r = np.zeros(m, dtype=np.int64)
            for i in combo:
                r[i] += 1
            rows.append(r)
    return np.array(rows)


def _forward_order(F: np.ndarray, target: np.ndarray, max_terms: int) -> list[int]:
    """Columns of ``F`` in the order forward orthogonal least squares picks them (largest error reduction ratio
    first, Billings' FROLS): the term selection of polynomial NARX users."""
    Q = F.astype(float).copy()  # orthogonalised in place as terms are picked
    picked: list[int] = []
    tt = float(target @ target)
    for _ in range(min(max_terms, F.shape[1])):
        nq = np.einsum("ij,ij->j", Q, Q)
        err = np.where(nq > 1e-12 * max(nq.max(), 1e-300), (Q.T @ target) ** 2 / np.where(nq > 0, nq, 1) / tt, -1)
        err[picked] = -1
        j = int(np.argmax(err))
        if err[j] <= 0:
            break
        picked.append(j)
        q = Q[:, j] / math.sqrt(nq[j])
        Q -= np.outer(q, q @ Q)
    return picked


class NARX:
    """A polynomial NARX (orders ``na``, ``nb``, ``degree``) fitted by least squares and refitted by simulation
    error; :meth:`free_run_rms` scores it as the bench does (the first ``init`` samples initialise)."""

    def __init__(self, na: int, nb: int, degree: int, terms: list | None = None):
        self.na, self.nb, self.degree = na, nb, degree
        p = _powers(na, nb, degree)
        self.powers = np.ascontiguousarray(p if terms is None else p[sorted(terms)])
        self.theta = np.zeros(self.powers.shape[0])

    def _features(self, y, u):
        k0 = max(self.na, self.nb)
        ks = np.arange(k0, y.size)
        z = np.column_stack([y[ks - i] for i in range(1, self.na + 1)] + [u[ks - j] for j in range(self.nb + 1)])
        return np.prod(z[:, None, :] ** self.powers[None, :, :], axis=2), y[ks]

    def fit(self, y, u, *, refit_samples: int = 20000, max_nfev: int = 60):
        """Least squares (one step ahead), then Levenberg-Marquardt on the free-run error of the first
        ``refit_samples`` samples, kept when it free-runs the estimation record better."""
        self.least_squares(y, u)
        m = min(refit_samples, y.size)
        ys, us, k0 = y[:m], u[:m], max(self.na, self.nb)
        scale = np.where(self.theta != 0, np.abs(self.theta), 1.0)

        def resid(p):
            r = _simulate_terms(p * scale, self.powers, ys, us, self.na, self.nb)[k0:] - ys[k0:]
            return np.where(np.isfinite(r), r, 10.0 * np.nanstd(ys))

        e0 = np.sqrt(np.mean(resid(self.theta / scale) ** 2))
        try:
            r = optimize.least_squares(resid, self.theta / scale, method="lm", max_nfev=max_nfev * self.theta.size)
            if np.sqrt(np.mean(resid(r.x) ** 2)) < e0:
                self.theta = r.x * scale
        except (ValueError, np.linalg.LinAlgError):
            pass
        return self

    def least_squares(self, y, u) -> "NARX":
        """This model fitted by least squares (one step ahead) to ``y``, ``u``."""
        G, target = self._features(y, u)
        s = np.linalg.norm(G, axis=0)
        s[s == 0] = 1
        th, *_ = np.linalg.lstsq(G / s, target, rcond=None)
        self.theta = th / s
        return self

    def bounded(self, y, u, starts: int = 16, runs: tuple = ()) -> bool:
        """Whether the free run stays finite over ``y``, ``u`` from each of ``starts`` points spread over it, and
        over each of ``runs`` (``(y_head, u)``: the first outputs and the inputs of a record it will be
        free-run on; no output beyond the head is read)."""
        n = y.size
        for k in range(0, n - max(self.na, self.nb) - 1, max(1, n // starts)):
            sim = _simulate_terms(self.theta, self.powers, y[k:], u[k:], self.na, self.nb)
            if not np.all(np.isfinite(sim)):
                return False
        return all(np.all(np.isfinite(_simulate_terms(self.theta, self.powers, yh, ur, self.na, self.nb)))
                   for yh, ur in runs)

    def free_run_rms(self, y, u, init: int = 50) -> float:
        sim = _simulate_terms(self.theta, self.powers, y, u, self.na, self.nb)
        e = sim[init:] - y[init:]
        return float(np.sqrt(np.mean(e ** 2))) if np.all(np.isfinite(e)) else float("inf")


def heads(tests, init: int = 50) -> tuple:
    """``(y_head, u)`` of each ``(y, u)`` test record: what a free run from its start reads (the first ``init``
    outputs and the inputs), for :func:`tuned_narx`'s ``runs``."""
    return tuple((y[:init], u) for y, u in tests)


VALIDATION = 0.2
"""The share of the estimation record in each of :func:`tuned_narx`'s two validation blocks (its end, its start)."""

FINALISTS = 3
"""The models :func:`tuned_narx` refits by simulation error and scores again."""


def tuned_narx(y: np.ndarray, u: np.ndarray, *, degrees=(1, 2, 3), orders=(1, 2, 3, 4),
               sizes=(2, 3, 4, 5, 6, 8, 10, 13, 16, 20), runs: tuple = ()) -> NARX:
    """A polynomial NARX as its users tune it, by free run on validation blocks: for every (na = nb + 1,
    degree) of the grid the terms are ranked by forward orthogonal least squares (Billings' FROLS), and every
    model of the first ``sizes`` terms is fitted by least squares without a block of :data:`VALIDATION` of the
    estimation record (its end, then its start) and free-run over it; the :data:`FINALISTS` with the lowest RMS
    over both blocks are refitted by simulation error and scored again; the winner is refitted so on the whole
    record. A model that diverges on a validation block is never chosen (the next one is), nor one whose free
    run blows up on the inputs it will be run on (``runs``: ``(y_head, u)`` of each test record, see
    :func:`heads`), which its user sees at once and re-chooses for. ``degrees=(1,)``: a linear ARX."""
    n = y.size
    m_ = int(VALIDATION * n)
    folds = [(slice(0, n - m_), slice(n - m_, n)), (slice(m_, n), slice(0, m_))]

    def score(make, refit=False):
        e = []
        for fit, val in folds:
            m = make()
            m = m.fit(y[fit], u[fit]) if refit else m.least_squares(y[fit], u[fit])
            e.append(m.free_run_rms(y[val], u[val]))
        return float(np.sqrt(np.mean(np.square(e))))

    first = []
    for d in degrees:
        for na in orders:
            nb = na - 1
            F, target = NARX(na, nb, d)._features(y[folds[0][0]], u[folds[0][0]])
            order = _forward_order(F, target, max(sizes))
            for k in sizes:
                if k > len(order):
                    break
                terms = tuple(order[:k])
                first.append((score(lambda: NARX(na, nb, d, list(terms))), (na, nb, d, terms)))
    ranked = sorted([f for f in first if math.isfinite(f[0])], key=lambda f: f[0]) or first
    second = [(score(lambda c=c: NARX(c[0], c[1], c[2], list(c[3])), refit=True), c) for _, c in ranked[:FINALISTS]]
    # the winner refitted on the whole record must stay bounded there from any start and on the test inputs
    # (a user re-chooses a model whose free run blows up): else the next one
    order = [c for _, c in sorted(second, key=lambda f: f[0])] + [c for _, c in ranked[FINALISTS:]]
    for na, nb, d, terms in order:
        m = NARX(na, nb, d, list(terms)).fit(y, u)
        if m.bounded(y, u, runs=runs):
            return m
    na, nb, d, terms = order[0]
    return NARX(na, nb, d, list(terms)).fit(y, u)
