"""What the ARD maximiser records and asks for (:mod:`.maximiser`): one evidence evaluation during the
maximisation (:class:`Trial`), the next one it asks its driver for (:class:`TrialRequest`), what it returns
(:class:`MaximiserResult`), and how two trials' ln Z are compared (:func:`diff_se`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from ..evidence.estimators import Evidence
from ..jsonio import encode_alpha
from ..likelihood.posterior import ModelPosterior
from ..sampling.config import SamplerResult

INF = math.inf


@dataclass
class Trial:
    """One evidence evaluation during maximisation."""

    iteration: int
    psi: dict
    evidence: Evidence
    accepted: bool
    action: str
    wall_s: float
    posterior: dict
    diagnostics: dict
    reweighted_from: int | None = None
    """Iteration of the sampled trial whose draws were reweighted (None: this trial was sampled)."""
    reweight_se: float = 0.0
    """Monte Carlo se of the reweighting alone (the difference to its base trial has only this error)."""
    bound: bool = False
    """The evidence is an upper bound (:attr:`MaximiserConfig.prune_bound`), no chain was sampled."""

    @property
    def sampled(self) -> bool:
        return self.reweighted_from is None and not self.bound

    def to_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "psi": {k: encode_alpha(v) for k, v in self.psi.items()},
            **self.evidence.to_dict(), "accepted": self.accepted, "action": self.action,
            "wall_s": self.wall_s, "posterior": self.posterior, "diagnostics": self.diagnostics,
            "sampled": self.sampled, "reweighted_from": self.reweighted_from, "reweight_se": self.reweight_se,
            "bound": self.bound,
        }


@dataclass
class MaximiserResult:
    psi_opt: dict
    best: Trial
    sampler: SamplerResult | None
    target: ModelPosterior
    history: list = field(default_factory=list)

    @property
    def kept(self) -> list:
        return [k for k, v in self.psi_opt.items() if v != INF]

    @property
    def pruned(self) -> list:
        return [k for k, v in self.psi_opt.items() if v == INF]


def posterior_summary(names, samples: np.ndarray) -> dict:
    """mean, sd and 0.5 / 99.5 % quantiles per parameter of pooled samples (n, d)."""
    q = np.quantile(samples, [0.005, 0.995], axis=0)
    return {n: {"mean": float(samples[:, i].mean()), "sd": float(samples[:, i].std(ddof=1)),
                "q005": float(q[0, i]), "q995": float(q[1, i])} for i, n in enumerate(names)}


@dataclass(frozen=True)
class TrialRequest:
    """What the maximiser asks for next: the evidence at ``psi`` by sampling (MCMC + Chib-Jeliazkov or
    Laplace), its chains warm-started from ``warm``; with ``extend``, the chains of ``warm`` (sampled at
    ``psi``) continued to the sampler's quality target instead (:func:`~ardcore.sampling.driver.continuation`);
    with ``bound``, no chains: an upper bound of ln Z at ``psi`` (:meth:`EvidenceEvaluator.likelihood_bound`)."""

    iteration: int
    psi: dict
    warm: SamplerResult | None
    action: str
    seed: int
    extend: bool = False
    bound: bool = False


def diff_se(a: Trial, b: Trial) -> float:
    """se of ln Z(a) - ln Z(b): a reweighted trial shares its base's estimate, so only the reweighting's own
    error separates them."""
    if a.reweighted_from is not None and a.reweighted_from == b.iteration:
        return a.reweight_se
    if b.reweighted_from is not None and b.reweighted_from == a.iteration:
        return b.reweight_se
    if a.reweighted_from is not None and a.reweighted_from == b.reweighted_from:
        return math.hypot(a.reweight_se, b.reweight_se)
    return math.hypot(a.evidence.log_evidence_se, b.evidence.log_evidence_se)
