"""The generated EKF against an independent Kalman filter on linear-Gaussian models."""

import numpy as np
import pytest
from scipy.linalg import expm

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.likelihood.simulate import simulate_model

PARAMS = {"a11": -0.1, "a12": 1.0, "a21": -1.0, "a22": -0.2, "q1": 0.05, "q2": 0.2, "r": 0.1}


def system(p):
    A = np.array([[p["a11"], p["a12"]], [p["a21"], p["a22"]]])
    GG = np.diag([p["q1"] ** 2, p["q2"] ** 2])
    H = np.array([[1.0, 0.0]])
    return A, GG, H


def kalman(t, y, p, transition, x0, P0):
    """Plain textbook Kalman filter; `transition(dt)` gives (F, Q) of one interval."""
    A, GG, H = system(p)
    R = p["r"] ** 2
    x, P = x0.copy(), P0.copy()
    ll = 0.0
    for k in range(len(t)):
        if k:
            F, Q = transition(t[k] - t[k - 1])
            x, P = F @ x, F @ P @ F.T + Q
        if np.isnan(y[k]):
            continue
        S = (H @ P @ H.T).item() + R
        e = y[k] - (H @ x).item()
        K = (P @ H.T / S).ravel()
        x = x + K * e
        P = P - np.outer(K, K) * S
        ll += -0.5 * (np.log(2 * np.pi * S) + e * e / S)
    return ll


def step_matrix(A, h, scheme):
    """One sub-step's transition: I + A h (Euler); the RK4 map of a linear system, I + Ah + ... + (Ah)^4/24."""
    if scheme == "euler":
        return np.eye(len(A)) + A * h
    Ah = A * h
    return np.eye(len(A)) + Ah + Ah @ Ah / 2 + Ah @ Ah @ Ah / 6 + Ah @ Ah @ Ah @ Ah / 24


def spec_with(name, scheme, hold="foh"):
    return builtin(name).model_copy(update={"integrator": scheme, "input_hold": hold}).revalidate()


def euler_transition(p, nsub, scheme="euler"):
    A, GG, _ = system(p)

    def tr(dt):
        h = dt / nsub
        Fh = step_matrix(A, h, scheme)
        F, Q = np.eye(2), np.zeros((2, 2))
        for _ in range(nsub):
            F, Q = Fh @ F, Fh @ Q @ Fh.T + GG * h
        return F, Q
    return tr


def exact_transition(p):
    A, GG, _ = system(p)

    def tr(dt):
        # Van Loan: exact discretisation of dx = A x dt + G dW
        n = 2
        M = np.zeros((2 * n, 2 * n))
        M[:n, :n], M[:n, n:], M[n:, n:] = -A, GG, A.T
        E = expm(M * dt)
        F = E[n:, n:].T
        return F, F @ E[:n, n:]
    return tr


@pytest.fixture(scope="module")
def data():
    t = np.arange(400) * 0.1
    return simulate_model("linear_gaussian", PARAMS, t, seed=3, nsub=50)


def init():
    return np.array([0.5, 0.0]), np.eye(2)


@pytest.mark.parametrize("scheme", ["euler", "rk4"])
@pytest.mark.parametrize("nsub", [1, 3, 10])
def test_equals_exact_kalman_filter_of_the_same_discretisation(data, nsub, scheme):
    cm = compile_model(spec_with("linear_gaussian", scheme))
    ll = cm.loglik(PARAMS, data, substeps=nsub)
    ref = kalman(data.t, data.columns["y"], PARAMS, euler_transition(PARAMS, nsub, scheme), *init())
    assert ll == pytest.approx(ref, rel=1e-8)


def test_irregular_sampling_and_missing_observations(data):
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.02, 0.3, 300))
    y = simulate_model("linear_gaussian", PARAMS, t, seed=4, nsub=20).columns["y"].copy()
    y[rng.choice(300, 40, replace=False)] = np.nan
    ds = Dataset(t, {"y": y})
    for scheme in ("euler", "rk4"):
        cm = compile_model(spec_with("linear_gaussian", scheme))
        for nsub in (1, 7):
            ref = kalman(t, y, PARAMS, euler_transition(PARAMS, nsub, scheme), *init())
            assert cm.loglik(PARAMS, ds, substeps=nsub) == pytest.approx(ref, rel=1e-8)
    cm = compile_model(builtin("linear_gaussian"))
    # a missing observation is not an update: the filter result differs from dropping nothing
    r = cm.filter(PARAMS, ds, substeps=7)
    assert np.isnan(r.innovations[np.isnan(y), 0]).all()
    assert np.isfinite(r.innovations[~np.isnan(y), 0]).all()


def test_converges_to_exact_discretisation(data):
    cm = compile_model(spec_with("linear_gaussian", "euler"))
    exact = kalman(data.t, data.columns["y"], PARAMS, exact_transition(PARAMS), *init())
    errs = [abs(cm.loglik(PARAMS, data, substeps=n) - exact) for n in (1, 10, 100, 1000)]
    assert all(b < a for a, b in zip(errs, errs[1:]))
    # Euler is first order: ten times the sub-steps, about a tenth of the error
    assert errs[3] < 0.2 * errs[2] < 0.04 * errs[1]
    assert errs[3] / abs(exact) < 1e-5
    # RK4's mean map is fourth order; the process noise (G G^T dt per sub-step) stays first order, so the
    # likelihood converges at first order too, but from far closer: 1 RK4 sub-step beats 10 Euler ones
    rk = compile_model(spec_with("linear_gaussian", "rk4"))
    errs4 = [abs(rk.loglik(PARAMS, data, substeps=n) - exact) for n in (1, 10, 100)]
    assert all(b < a for a, b in zip(errs4, errs4[1:]))
    assert errs4[1] < errs[1] and errs4[2] < errs[2]


@pytest.mark.parametrize("scheme,hold", [("euler", "zoh"), ("euler", "foh"), ("rk4", "zoh"), ("rk4", "foh")])
def test_known_input_between_samples(scheme, hold):
    spec = spec_with("forced_linear_oscillator", scheme, hold)
    p = {"k": 4.0, "c": 0.4, "b": 2.0, "sigma": 0.1}
    t = np.arange(300) * 0.05
    u = np.sin(0.7 * t) + 0.3 * np.cos(2.3 * t)
    ds = simulate_model(spec, p, t, seed=1, nsub=10, inputs={"u": u})
    cm = compile_model(spec)
    nsub = 4
    A = np.array([[0, 1], [-p["k"], -p["c"]]])
    Bv = np.array([0, p["b"]])
    GG = np.diag([0, p["sigma"] ** 2])
    R = 1e-4 ** 2
    x, P = np.zeros(2), np.diag([0.1 ** 2, 10.0 ** 2])
    ll = 0.0
    y = ds.columns["y"]

    def uin(k, frac):  # the input at a fraction of the interval (k-1, k]
        return u[k - 1] + (u[k] - u[k - 1]) * frac if hold == "foh" else u[k - 1]

    def f(x, uu):
        return A @ x + Bv * uu

    for k in range(len(t)):
        if k:
            h = (t[k] - t[k - 1]) / nsub
            for s in range(nsub):
                Fh = step_matrix(A, h, scheme)
                if scheme == "euler":
                    x = x + h * f(x, uin(k, s / nsub))
                else:
                    u0, um, u1 = uin(k, s / nsub), uin(k, (s + 0.5) / nsub), uin(k, (s + 1) / nsub)
                    k1 = f(x, u0)
                    k2 = f(x + h / 2 * k1, um)
                    k3 = f(x + h / 2 * k2, um)
                    k4 = f(x + h * k3, u1)
                    x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
                P = Fh @ P @ Fh.T + GG * h
        S = P[0, 0] + R
        e = y[k] - x[0]
        K = P[:, 0] / S
        x, P = x + K * e, P - np.outer(K, K) * S
        ll += -0.5 * (np.log(2 * np.pi * S) + e * e / S)
    assert cm.loglik(p, ds, substeps=nsub) == pytest.approx(ll, rel=1e-8)


def test_filter_outputs_are_consistent(data):
    cm = compile_model(builtin("linear_gaussian"))
    r = cm.filter(PARAMS, data)
    assert r.loglik == pytest.approx(cm.loglik(PARAMS, data))
    z = r.standardized[:, 0]
    # at the true parameters, standardised innovations are ~ N(0, 1)
    assert abs(z.mean()) < 0.15 and 0.85 < z.std() < 1.15
    assert r.filtered.shape == (len(data), 2) and r.filtered_cov.shape == (len(data), 2, 2)
    assert np.allclose(r.filtered_cov, np.transpose(r.filtered_cov, (0, 2, 1)))


def test_wrong_parameter_vector_is_rejected(data):
    from ardflow.ardcore.errors import ModelError

    cm = compile_model(builtin("linear_gaussian"))
    with pytest.raises(ModelError, match="expected 7 parameters"):
        cm.loglik([1.0, 2.0], data)
    with pytest.raises(ModelError, match="no value for parameter 'r'"):
        cm.loglik({k: v for k, v in PARAMS.items() if k != "r"}, data)


def test_free_run_is_fourth_order_with_interpolated_inputs():
    """The deterministic simulation (free run) with RK4 and first-order hold converges at fourth order to the
    exact solution for an input that is piecewise linear between samples; Euler and zero-order hold do not."""
    from scipy.integrate import solve_ivp

    p = {"k": 40.0, "c": 0.5, "b": 3.0, "sigma": 0.1}
    t = np.arange(200) * 0.05
    u = np.random.default_rng(0).standard_normal(t.size)
    A = np.array([[0.0, 1.0], [-p["k"], -p["c"]]])
    sol = solve_ivp(lambda s, x: A @ x + np.array([0.0, p["b"] * np.interp(s, t, u)]), (t[0], t[-1]), [0.1, 0.0],
                    t_eval=t, rtol=1e-12, atol=1e-12, max_step=0.005)
    exact = sol.y[0]

    def err(scheme, hold, nsub):
        cm = compile_model(spec_with("forced_linear_oscillator", scheme, hold))
        X, _ = cm.simulate(p, t, x0=[0.1, 0.0], inputs=u[:, None], nsub=nsub, noise=False)
        return float(np.max(np.abs(X[:, 0] - exact)))

    e2, e4 = err("rk4", "foh", 2), err("rk4", "foh", 4)
    assert e4 < e2 / 12          # fourth order: 16x for twice the sub-steps
    assert e4 < 1e-5 * np.max(np.abs(exact)) * 100
    assert err("rk4", "zoh", 4) > 100 * e4      # held inputs: a half-sample delay no sub-step removes
    assert err("euler", "foh", 4) > 100 * e4
