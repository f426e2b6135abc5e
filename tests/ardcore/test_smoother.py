"""The RTS smoother on a linear-Gaussian model against the exact conditional mean of the joint Gaussian."""

import numpy as np
import pytest

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.likelihood.ekf import compile_model
from ardflow.ardcore.model.library import builtin

from .test_ekf_exact import PARAMS, euler_transition


@pytest.mark.parametrize("scheme", ["euler", "rk4"])
def test_smoother_equals_batch_conditional_mean(scheme):
    rng = np.random.default_rng(4)
    n, nsub = 40, 3
    t = np.cumsum(np.r_[0.0, rng.uniform(0.05, 0.3, n - 1)])  # irregular sampling
    y = rng.standard_normal(n) * 0.5
    y[[7, 8, 21]] = np.nan  # missing observations
    cm = compile_model(builtin("linear_gaussian").model_copy(update={"substeps": nsub, "integrator": scheme}))
    fr, sm = cm.smooth(PARAMS, Dataset(t, {"y": y}))

    # joint prior of the stacked states X = (x_0, ..., x_{n-1}) under the same discretisation
    tr = euler_transition(PARAMS, nsub, scheme)
    m0, P0 = cm.initial(PARAMS)
    Fs, Qs = [np.eye(2)], [P0]
    for k in range(1, n):
        F, Q = tr(t[k] - t[k - 1])
        Fs.append(F)
        Qs.append(Q)
    # X = L (x_0, w_1, ..., w_{n-1}), L lower block-triangular with products of the transitions
    L = np.zeros((2 * n, 2 * n))
    for i in range(n):
        L[2 * i:2 * i + 2, 2 * i:2 * i + 2] = np.eye(2)
        for j in range(i - 1, -1, -1):
            L[2 * i:2 * i + 2, 2 * j:2 * j + 2] = Fs[i] @ L[2 * (i - 1):2 * i, 2 * j:2 * j + 2]
    D = np.zeros((2 * n, 2 * n))
    for i in range(n):
        D[2 * i:2 * i + 2, 2 * i:2 * i + 2] = Qs[i]
    mean = L @ np.r_[m0, np.zeros(2 * (n - 1))]
    cov = L @ D @ L.T
    obs = np.flatnonzero(~np.isnan(y))
    H = np.zeros((obs.size, 2 * n))
    H[np.arange(obs.size), 2 * obs] = 1.0
    S = H @ cov @ H.T + PARAMS["r"] ** 2 * np.eye(obs.size)
    K = cov @ H.T @ np.linalg.inv(S)
    post = mean + K @ (y[obs] - H @ mean)
    post_cov = cov - K @ H @ cov
    xs = post.reshape(n, 2)
    np.testing.assert_allclose(sm.smoothed, xs, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(sm.smoothed_cov[:, 0, 0], np.diag(post_cov)[0::2], rtol=1e-6, atol=1e-12)
    w = np.array([xs[k] - Fs[k] @ xs[k - 1] for k in range(1, n)])
    np.testing.assert_allclose(sm.process_noise[1:], w, rtol=1e-6, atol=1e-9)
    # the trace kernel gives the same filter as the likelihood kernel
    assert fr.loglik == cm.loglik(PARAMS, Dataset(t, {"y": y}))
    assert np.allclose(fr.transition[1], Fs[1])
