"""Baselines for the EKF benchmark on M2 (reference problem).

``ekf_m2_numpy``: the filter as a filterpy user would write it, numpy matrices
per sub-step. ``ekf_m2_handwritten``: the same filter as a hand-written scalar
numba kernel. Both must agree with the generated kernel (checked by the bench).
"""

import math

import numpy as np
from numba import njit

from ardflow.ardcore.model.library import AERO_CONSTANTS

C1, C2, C3, C4, C5, C6 = (AERO_CONSTANTS[k] for k in ("c1", "c2", "c3", "c4", "c5", "c6"))


def ekf_m2_numpy(p, t, y, nsub, gamma, init_std=0.01):
    B, a1, a2, a3, a4, a5, a6, sigma = p
    x = np.zeros(3)
    P = np.eye(3) * init_std**2
    H = np.array([[1.0, 0.0, 0.0]])
    R = np.array([[gamma**2]])
    ll = 0.0
    for k in range(len(t)):
        if k:
            dt = (t[k] - t[k - 1]) / nsub
            Q = np.diag([0.0, 0.0, sigma**2 * dt])
            for _ in range(nsub):
                th, dth, cm = x
                F = C1 * np.sign(dth) + C2 * th + C3 * cm + C4 * dth + C5 * th**3
                Pp = a1 * th + a2 * dth + a3 * th**3 + a4 * th**2 * dth + a5 * th**5 + a6 * th**4 * dth
                f = np.array([dth, F, B * (Pp - cm) + C6 * F])
                dF = np.array([C2 + 3 * C5 * th**2, C4, C3])
                dP = np.array([a1 + 3 * a3 * th**2 + 2 * a4 * th * dth + 5 * a5 * th**4 + 4 * a6 * th**3 * dth,
                               a2 + a4 * th**2 + a6 * th**4, 0.0])
                J = np.vstack([[0.0, 1.0, 0.0], dF, B * dP + C6 * dF + np.array([0.0, 0.0, -B])])
                A = np.eye(3) + J * dt
                P = A @ P @ A.T + Q
                x = x + f * dt
        S = H @ P @ H.T + R
        e = y[k] - (H @ x)[0]
        K = P @ H.T @ np.linalg.inv(S)
        x = x + (K * e).ravel()
        P = P - K @ S @ K.T
        ll += -0.5 * (math.log(2 * math.pi * S[0, 0]) + e * e / S[0, 0])
    return ll


@njit(cache=True, nogil=True)
def ekf_m2_handwritten(p, t, y, nsub, gamma, init_std):
    B, a1, a2, a3, a4, a5, a6, sigma = p[0], p[1], p[2], p[3], p[4], p[5], p[6], p[7]
    x0 = 0.0
    x1 = 0.0
    x2 = 0.0
    v = init_std * init_std
    P00, P01, P02, P11, P12, P22 = v, 0.0, 0.0, v, 0.0, v
    R = gamma * gamma
    s2 = sigma * sigma
    ll = 0.0
    for k in range(t.shape[0]):
        if k > 0:
            dt = (t[k] - t[k - 1]) / nsub
            for _ in range(nsub):
                th2 = x0 * x0
                th3 = th2 * x0
                th4 = th2 * th2
                sg = 1.0 if x1 > 0 else (-1.0 if x1 < 0 else 0.0)
                F = C1 * sg + C2 * x0 + C3 * x2 + C4 * x1 + C5 * th3
                Pp = a1 * x0 + a2 * x1 + a3 * th3 + a4 * th2 * x1 + a5 * th4 * x0 + a6 * th4 * x1
                dF0 = C2 + 3.0 * C5 * th2
                j20 = B * (a1 + 3.0 * a3 * th2 + 2.0 * a4 * x0 * x1 + 5.0 * a5 * th4 + 4.0 * a6 * th3 * x1) + C6 * dF0
                j21 = B * (a2 + a4 * th2 + a6 * th4) + C6 * C4
                j22 = C6 * C3 - B
                # M = A P with A = I + J dt
                M00 = P00 + dt * P01
                M01 = P01 + dt * P11
                M02 = P02 + dt * P12
                M10 = P01 + dt * (dF0 * P00 + C4 * P01 + C3 * P02)
                M11 = P11 + dt * (dF0 * P01 + C4 * P11 + C3 * P12)
                M12 = P12 + dt * (dF0 * P02 + C4 * P12 + C3 * P22)
                M20 = P02 + dt * (j20 * P00 + j21 * P01 + j22 * P02)
                M21 = P12 + dt * (j20 * P01 + j21 * P11 + j22 * P12)
                M22 = P22 + dt * (j20 * P02 + j21 * P12 + j22 * P22)
                # P = M A^T + Q dt
                P00 = M00 + dt * M01
                P01 = M01 + dt * (dF0 * M00 + C4 * M01 + C3 * M02)
                P02 = M02 + dt * (j20 * M00 + j21 * M01 + j22 * M02)
                P11 = M11 + dt * (dF0 * M10 + C4 * M11 + C3 * M12)
                P12 = M12 + dt * (j20 * M10 + j21 * M11 + j22 * M12)
                P22 = M22 + dt * (j20 * M20 + j21 * M21 + j22 * M22) + s2 * dt
                x0, x1, x2 = x0 + dt * x1, x1 + dt * F, x2 + dt * (B * (Pp - x2) + C6 * F)
        S = P00 + R
        e = y[k] - x0
        x0 += P00 / S * e
        x1 += P01 / S * e
        x2 += P02 / S * e
        k0, k1, k2 = P00, P01, P02
        P00 -= k0 * k0 / S
        P01 -= k0 * k1 / S
        P02 -= k0 * k2 / S
        P11 -= k1 * k1 / S
        P12 -= k1 * k2 / S
        P22 -= k2 * k2 / S
        ll -= 0.5 * (math.log(2 * math.pi * S) + e * e / S)
    return ll
