"""Picklable test targets with exact answers."""

import math

import numpy as np


class GaussianLoglik:
    """ln N(m; x, S) as a function of x: with a N(0, tau^2 I) prior the evidence is N(m; 0, S + tau^2 I)."""

    def __init__(self, m, S):
        self.m = np.asarray(m, dtype=float)
        self.Si = np.linalg.inv(S)
        self.c = -0.5 * np.linalg.slogdet(2 * math.pi * np.asarray(S))[1]

    def __call__(self, x):
        d = x - self.m
        return self.c - 0.5 * d @ self.Si @ d


def correlated_cov(d, seed, scale=0.01):
    rng = np.random.default_rng(seed)
    A = rng.standard_normal((d, d))
    return (A @ A.T / d + 0.05 * np.eye(d)) * scale


class TwoModes:
    """Two far-apart Gaussian modes (sd ``sd``) of unequal mass: chains started in each never meet."""

    def __init__(self, sep=40.0, w=0.8, sd=1.0):
        self.sep, self.lw, self.lw2, self.sd = sep, math.log(w), math.log(1 - w), sd

    def __call__(self, x):
        z = x / self.sd
        a = self.lw - 0.5 * float(z @ z)
        y = z.copy()
        y[0] -= self.sep / self.sd
        b = self.lw2 - 0.5 * float(y @ y)
        return float(np.logaddexp(a, b)) - 0.5 * x.size * math.log(2 * math.pi) - x.size * math.log(self.sd)


def augmented_kalman(records, system, theta_mean, theta_sd, x_sd=1.0):
    """Exact ln p(d) of dx = (-a x + b1 u + b2) dt + q dW, y = x + c + N(0, r^2) (Euler sub-steps, inputs held):
    a Kalman filter on [x, b1, b2, c] with the parameters as static states (fixed where their sd is 0), through
    ``records`` (data sets with columns ``y``, ``u``) in turn. ``system`` is (a, q, r, nsub). At each record's
    start x is reset to its initial prior (``meta["initial_mean"]``/``["initial_std"]``, default 0 and ``x_sd``)
    and forgets its correlation with the parameters, which carry over."""
    a, q, r, nsub = system
    m = np.concatenate([[0.0], theta_mean])
    P = np.diag(np.concatenate([[x_sd**2], np.asarray(theta_sd, dtype=float) ** 2]))
    H = np.array([1.0, 0.0, 0.0, 1.0])
    ll = 0.0
    for ds in records:
        m[0] = ds.meta.get("initial_mean", {}).get("x", 0.0)
        P[0, :] = P[:, 0] = 0.0
        P[0, 0] = ds.meta.get("initial_std", {}).get("x", x_sd) ** 2
        t, y, u = ds.t, ds.columns["y"], ds.columns["u"]
        for k in range(len(t)):
            if k:
                h = (t[k] - t[k - 1]) / nsub
                F = np.eye(4)
                F[0, 0], F[0, 1], F[0, 2] = 1 - a * h, u[k - 1] * h, h
                Qm = np.zeros((4, 4))
                Qm[0, 0] = q**2 * h
                for _ in range(nsub):
                    m = F @ m
                    P = F @ P @ F.T + Qm
            S = H @ P @ H + r**2
            e = y[k] - H @ m
            K = P @ H / S
            m = m + K * e
            P = P - np.outer(K, K) * S
            ll += -0.5 * (math.log(2 * math.pi * S) + e * e / S)
    return ll


LINEAR_SYSTEM = (0.8, 0.3, 0.1, 5)
"""(a, q, r, nsub) of :func:`linear_gaussian_spec`: the decay rate, process and measurement noise, sub-steps."""


def linear_gaussian_spec():
    """dx = (-a x + b1 u + b2) dt + q dW, y = x + c + N(0, r^2) at :data:`LINEAR_SYSTEM`, discretised as
    :func:`augmented_kalman` is written for (Euler sub-steps, inputs held): its Kalman filter is exact."""
    from ardflow.ardcore.model.declaration import ModelSpec

    a, q, r, nsub = LINEAR_SYSTEM
    return ModelSpec(
        name="lin_param", states=["x"], inputs=["u"],
        drift={"x": "-a*x + b1*u + b2"}, diffusion={"x": "q"},
        observations=[{"column": "y", "expr": "x + c", "noise_std": "r"}],
        parameters=["b1", "b2", "c"], constants={"a": a, "q": q, "r": r},
        initial_std={"x": 1.0}, substeps=nsub, integrator="euler", input_hold="zoh")
