"""Targets for the sampler: unnormalised log posteriors over named parameters.

A target is a picklable callable ``x -> Density(log_posterior, log_likelihood)``
(log_posterior = log prior + log likelihood, unnormalised) with ``names`` and
``prior`` (a :class:`~ardcore.model.priors.JointPrior`). Compiled kernels are not
pickled: a target rebuilds them on first use in whichever process runs it.
"""

from __future__ import annotations

import copy
import math
from typing import Callable, NamedTuple

import numpy as np

from ..data import Dataset
from .ekf import compile_model
from ..model.declaration import ModelSpec
from ..model.priors import JointPrior, Prior


class Density(NamedTuple):
    """A target's value at one point (unpacks as ``lp, ll``)."""

    log_posterior: float
    """ln prior + ln likelihood, unnormalised."""
    log_likelihood: float


_OUTSIDE = Density(-math.inf, -math.inf)


class Target:
    """What the sampler and the evidence need of a target: ``names``, ``prior`` and ``loglik(x)``; calling it
    gives (ln prior + ln likelihood, ln likelihood), both -inf outside the prior's support or where the
    likelihood is not finite (a :class:`Density`)."""

    names: list[str]
    prior: JointPrior

    def loglik(self, x: np.ndarray) -> float:
        raise NotImplementedError

    def window(self, n: int | None) -> "Target":
        """This target on its record's first ``n`` samples, the same prior: what a search that only places a
        start may read (itself here: a target without a record)."""
        return self

    def __call__(self, x) -> Density:
        lp = self.prior.logpdf(x)
        if lp == -math.inf:
            return _OUTSIDE
        ll = float(self.loglik(np.asarray(x, dtype=float)))
        if not math.isfinite(ll):
            return _OUTSIDE
        return Density(lp + ll, ll)


class ModelPosterior(Target):
    """p(phi | d, psi) up to its normaliser, for a declarative model and data.

    Parameters
    ----------
    spec : ModelSpec
        With pruned parameters already in ``spec.fixed``.
    priors : dict
        A prior for every free parameter (ARD priors included).
    data : Dataset
    substeps : int, optional
    """

    def __init__(self, spec: ModelSpec, priors: dict[str, Prior], data: Dataset, substeps: int | None = None):
        self.spec = spec
        self.names = spec.free_parameters
        self.prior = JointPrior(self.names, priors)
        self.data = data
        self.substeps = substeps or spec.substeps
        self._lik = None

    @property
    def likelihood(self):
        if self._lik is None:
            self._lik = compile_model(self.spec).bind(self.data, self.substeps)
        return self._lik

    def __getstate__(self):
        d = dict(self.__dict__)
        d["_lik"] = None
        return d

    def loglik(self, x: np.ndarray) -> float:
        return self.likelihood(x)

    def window(self, n: int | None) -> "ModelPosterior":
        """This posterior on the record's first ``n`` samples, the same prior (:class:`Target`); itself when
        ``n`` is None, when the record is no longer or when the data hold several records."""
        if n is None or self.data.n_records > 1 or len(self.data) <= n:
            return self
        out = copy.copy(self)
        out.data, out._lik = self.data.slice(0, n), None
        return out


class FunctionTarget(Target):
    """A target from plain functions (tests, non-ODE models).

    Parameters
    ----------
    names : list of str
    prior : JointPrior
    loglik : callable
        ``x -> ln p(d | x)``; must be picklable for process-based executors.
    """

    def __init__(self, names: list[str], prior: JointPrior, loglik: Callable[[np.ndarray], float]):
        self.names = list(names)
        self.prior = prior
        self.loglik = loglik
