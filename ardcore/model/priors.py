"""Prior distributions (docs/method.md section 1).

Essential parameters get proper priors (lognormal by median and COV %,
uniform by bounds, normal); ``flat`` is allowed for sampling but has no
normalising constant, so evidence computations refuse it. Questionable terms
get the ARD prior N(0, 1/alpha): alpha -> 0 is flat, alpha = inf switches the
term off (the parameter is fixed to 0 and leaves phi).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

_LN2PI = math.log(2 * math.pi)


class _PriorBase(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    @property
    def proper(self) -> bool:
        """Whether the density is normalised (evidence needs every prior proper)."""
        return True

    def logpdf(self, x: float) -> float:  # pragma: no cover - interface
        raise NotImplementedError

    def sample(self, rng: np.random.Generator, size=None):  # pragma: no cover - interface
        raise NotImplementedError

    def in_support(self, x: float) -> bool:
        return math.isfinite(self.logpdf(x))

    def quantile(self, p: float) -> float:  # pragma: no cover - interface
        raise NotImplementedError



class LogNormal(_PriorBase):
    """Lognormal with the given ``median`` and coefficient of variation ``cov`` in percent."""

    kind: Literal["lognormal"] = "lognormal"
    median: float = Field(gt=0)
    cov: float = Field(gt=0, le=10000, description="coefficient of variation, %")

    @classmethod
    def spanning(cls, median: float, lo: float, hi: float) -> "LogNormal":
        """Lognormal at ``median`` whose +-2 sd of the log span ``lo``..``hi`` (the wider side)."""
        s = max(math.log(hi / median), math.log(median / lo)) / 2.0
        return cls(median=median, cov=100.0 * math.sqrt(math.expm1(s * s)))

    @property
    def mu(self) -> float:
        return math.log(self.median)

    @property
    def s(self) -> float:
        return math.sqrt(math.log1p((self.cov / 100.0) ** 2))

    def logpdf(self, x: float) -> float:
        if not x > 0:
            return -math.inf
        z = (math.log(x) - self.mu) / self.s
        return -0.5 * z * z - math.log(x * self.s) - 0.5 * _LN2PI

    def sample(self, rng, size=None):
        return np.exp(self.mu + self.s * rng.standard_normal(size))

    def quantile(self, p: float) -> float:
        from scipy.special import ndtri

        return math.exp(self.mu + self.s * float(ndtri(p)))


class Uniform(_PriorBase):
    """Uniform on ``[low, high]``."""

    kind: Literal["uniform"] = "uniform"
    low: float
    high: float

    @model_validator(mode="after")
    def _order(self):
        if not self.high > self.low:
            raise ValueError(f"uniform prior: high ({self.high}) must be greater than low ({self.low})")
        return self

    def logpdf(self, x: float) -> float:
        if self.low <= x <= self.high:
            return -math.log(self.high - self.low)
        return -math.inf

    def sample(self, rng, size=None):
        return rng.uniform(self.low, self.high, size)

    def quantile(self, p: float) -> float:
        return self.low + p * (self.high - self.low)


class Normal(_PriorBase):
    """Normal with ``mean`` and standard deviation ``sd``."""

    kind: Literal["normal"] = "normal"
    mean: float = 0.0
    sd: float = Field(gt=0)

    def logpdf(self, x: float) -> float:
        z = (x - self.mean) / self.sd
        return -0.5 * z * z - math.log(self.sd) - 0.5 * _LN2PI

    def sample(self, rng, size=None):
        return self.mean + self.sd * rng.standard_normal(size)

    def quantile(self, p: float) -> float:
        from scipy.special import ndtri

        return self.mean + self.sd * float(ndtri(p))


class Flat(_PriorBase):
    """Improper flat prior (log-density 0). Not allowed where evidence is computed."""

    kind: Literal["flat"] = "flat"

    @property
    def proper(self) -> bool:
        return False

    def logpdf(self, x: float) -> float:
        return 0.0 if math.isfinite(x) else -math.inf

    def sample(self, rng, size=None):
        raise ValueError("a flat prior cannot be sampled")

    def quantile(self, p: float) -> float:
        raise ValueError("a flat prior has no quantiles")


def frozen_ard(alpha: float) -> Prior:
    """The ARD prior of a term at a fixed, finite alpha as an essential prior: N(0, 1/alpha), flat at 0 (what a
    refit with psi held at its optimum uses: the halves check, a joint fit, Savage-Dickey)."""
    a = float(alpha)
    return Normal(mean=0.0, sd=1.0 / math.sqrt(a)) if a > 0 else Flat()


class ARD(_PriorBase):
    """Automatic relevance determination prior N(0, 1/alpha), alpha in [0, inf].

    alpha = 0 is flat (improper); alpha = inf is the point mass at 0 (the term
    is switched off and the parameter is removed from phi by the caller).
    """

    kind: Literal["ard"] = "ard"
    alpha: float = Field(ge=0, allow_inf_nan=True)

    @model_validator(mode="after")
    def _alpha(self):
        if math.isnan(self.alpha):
            raise ValueError("alpha must not be NaN")
        return self

    @property
    def proper(self) -> bool:
        return 0 < self.alpha < math.inf

    @property
    def sd(self) -> float:
        return 1.0 / math.sqrt(self.alpha) if self.alpha > 0 else math.inf

    def logpdf(self, x: float) -> float:
        a = self.alpha
        if a == 0:
            return 0.0
        if a == math.inf:
            return 0.0 if x == 0 else -math.inf
        return 0.5 * (math.log(a) - _LN2PI) - 0.5 * a * x * x

    def sample(self, rng, size=None):
        if self.alpha == 0:
            raise ValueError("ARD prior with alpha = 0 cannot be sampled")
        if self.alpha == math.inf:
            return np.zeros(size) if size is not None else 0.0
        return self.sd * rng.standard_normal(size)

    def quantile(self, p: float) -> float:
        from scipy.special import ndtri

        return self.sd * float(ndtri(p)) if 0 < self.alpha < math.inf else 0.0


PriorSpec = Annotated[Union[LogNormal, Uniform, Normal, Flat], Field(discriminator="kind")]
"""An essential prior as written in a study spec, e.g. ``{"kind": "lognormal", "median": 0.2, "cov": 50}``."""

Prior = Union[LogNormal, Uniform, Normal, Flat, ARD]


class JointPrior:
    """Independent priors over named parameters (fast scalar log-density)."""

    def __init__(self, names: list[str], priors: dict[str, Prior]):
        missing = [n for n in names if n not in priors]
        if missing:
            raise ValueError(f"no prior for parameter {missing[0]!r}")
        self.names = list(names)
        self.priors = [priors[n] for n in names]

    @property
    def proper(self) -> bool:
        return all(p.proper for p in self.priors)

    def logpdf(self, x) -> float:
        s = 0.0
        for p, v in zip(self.priors, x):
            s += p.logpdf(float(v))
            if s == -math.inf:
                return s
        return s
