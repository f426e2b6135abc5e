"""The sampler's coordinates: every parameter mapped to the whole real line.

A random-walk proposal on a bounded or positive parameter wastes its steps: near a bound half of them
leave the support, and a scale parameter whose posterior is skewed (a lag rate, a noise level) has no
single good step. The chains therefore move in unconstrained coordinates z (Stan's choice): the log of a
parameter with a lognormal prior, the logit of its position within a uniform prior's bounds, the
parameter itself otherwise (normal, ARD and flat priors). The target in z is the posterior times the
Jacobian |dx/dz|; draws, phi* and every reported number stay in the natural coordinates x. Only the
proposal covariance (the INCA pool, a warm start's first step) lives in z, and the Chib-Jeliazkov
ordinate is taken in z and mapped back (ln p(x*|d) = ln p(z*|d) - ln|dx/dz|(x*)).
"""

from __future__ import annotations

import math

import numpy as np

_IDENTITY, _LOG, _LOGIT = 0, 1, 2
_EDGE = 1e-12  # a start exactly on a uniform prior's bound is moved this far inside (its logit is infinite)


class Unconstrained:
    """The map between a joint prior's natural coordinates x and the sampler's unconstrained z.

    Parameters
    ----------
    priors : sequence of Prior or None
        One per parameter, deciding its map: lognormal -> log, uniform -> logit of the bounds, anything
        else (None included) -> identity.
    """

    def __init__(self, priors):
        kinds, lo, hi, width = [], [], [], []
        for p in priors:
            kind = getattr(p, "kind", "")
            # width: the prior's own sd in z (lognormal: its s; uniform: the standard logistic's pi / sqrt 3)
            if kind == "lognormal":
                kinds.append(_LOG), lo.append(0.0), hi.append(math.inf), width.append(p.s)
            elif kind == "uniform":
                kinds.append(_LOGIT), lo.append(float(p.low)), hi.append(float(p.high))
                width.append(math.pi / math.sqrt(3.0))
            else:
                kinds.append(_IDENTITY), lo.append(-math.inf), hi.append(math.inf), width.append(math.inf)
        self.prior_sd = np.array(width)
        self.kind = np.array(kinds, dtype=int)
        self.lo, self.hi = np.array(lo), np.array(hi)
        self._log, self._logit = self.kind == _LOG, self.kind == _LOGIT
        self.width = np.where(self._logit, self.hi - self.lo, 1.0)
        self.identity = not (self._log.any() or self._logit.any())
        # the uniform priors' bounds and log widths, taken out once (the Jacobian is read at every step)
        m = self._logit
        self._lo_m, self._hi_m, self._w_m, self._lnw_m = self.lo[m], self.hi[m], self.width[m], np.log(self.width[m])

    def to_free(self, x: np.ndarray) -> np.ndarray:
        """z of points x (the last axis is the parameter)."""
        x = np.asarray(x, dtype=float)
        if self.identity:
            return x.copy()
        z = x.copy()
        with np.errstate(divide="ignore", invalid="ignore"):
            lg = self._log
            z[..., lg] = np.log(x[..., lg])
            u = np.clip((x[..., self._logit] - self.lo[self._logit]) / self.width[self._logit], _EDGE, 1 - _EDGE)
            z[..., self._logit] = np.log(u) - np.log1p(-u)
        return z

    def from_free(self, z: np.ndarray) -> np.ndarray:
        """x of points z."""
        z = np.asarray(z, dtype=float)
        if self.identity:
            return z.copy()
        x = z.copy()
        x[..., self._log] = np.exp(z[..., self._log])
        m = self._logit
        x[..., m] = self._lo_m + self._w_m * _expit(z[..., m])
        return x

    def log_jacobian(self, x: np.ndarray) -> np.ndarray | float:
        """ln |dx/dz| at points x (summed over parameters); -inf on a uniform prior's bound."""
        x = np.asarray(x, dtype=float)
        if self.identity:
            return np.zeros(x.shape[:-1]) if x.ndim > 1 else 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            lg = np.log(x[..., self._log]).sum(axis=-1)
            xm = x[..., self._logit]
            lt = (np.log(xm - self._lo_m) + np.log(self._hi_m - xm) - self._lnw_m).sum(axis=-1)
        out = lg + lt
        return np.where(np.isnan(out), -np.inf, out) if np.ndim(out) else (float(out) if out == out else -math.inf)

    def slope(self, x: np.ndarray) -> np.ndarray:
        """dx/dz per parameter at the point x (what a covariance in x is divided by to be one in z)."""
        x = np.asarray(x, dtype=float)
        s = np.ones(x.shape)
        s[self._log] = x[self._log]
        m = self._logit
        s[m] = (x[m] - self.lo[m]) * (self.hi[m] - x[m]) / self.width[m]
        return np.where(np.isfinite(s) & (s > 0), s, 1.0)

    def cov_to_free(self, cov: np.ndarray, x: np.ndarray) -> np.ndarray:
        """A covariance in x at the point x, linearised into z (D^-1 C D^-1 with D = diag(dx/dz))."""
        if self.identity:
            return np.asarray(cov, dtype=float)
        s = self.slope(x)
        C = np.asarray(cov, dtype=float) / np.outer(s, s)
        # near a uniform prior's bound dx/dz -> 0 and the linearised sd in z explodes: no step wider than
        # the prior itself in z (every proposal would land on the bound and be refused)
        sd = np.sqrt(np.clip(np.diag(C), 0.0, None))
        shrink = np.where(sd > self.prior_sd, self.prior_sd / np.where(sd > 0, sd, 1.0), 1.0)
        return C * np.outer(shrink, shrink)


def _expit(z: np.ndarray) -> np.ndarray:
    from scipy.special import expit

    return expit(z)


def free_coordinates(target, names: list[str] | None = None) -> Unconstrained:
    """The unconstrained coordinates of ``target``'s parameters (its ``prior``; identity without one), or of
    ``names`` in that order (a name the target lacks, such as a term pruned since, maps to itself)."""
    prior = getattr(target, "prior", None)
    if names is None:
        return Unconstrained(list(prior.priors) if prior is not None else [None] * len(target.names))
    by_name = dict(zip(prior.names, prior.priors)) if prior is not None else {}
    return Unconstrained([by_name.get(n) for n in names])
