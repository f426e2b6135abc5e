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
