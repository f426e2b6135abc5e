"""Evidence estimators (docs/method.md sections 3-4).

Chib-Jeliazkov from the stationary fixed-proposal samples of each chain, at
phi* = the best point any chain has seen, with goodness of fit and expected
information gain by Eq. 13, and what every estimator reports (:class:`Evidence`);
Laplace at the MAP is :mod:`.laplace`. Everything in log space.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Generator

import numpy as np
from scipy.special import logsumexp

from ..sampling.proposal import Jump, MixedProposal
from ..sampling.chains import Batch, Map, SamplerError, Step, run, serial_map
from ..sampling.config import SamplerResult
from ..sampling.transform import free_coordinates


@dataclass
class ChainEvidence:
    log_evidence: float
    se: float                  # batch-means noise of this chain's estimate
    log_posterior_ordinate: float


@dataclass
class Evidence:
    """An evidence estimate with its decomposition.

    Attributes
    ----------
    log_evidence, log_evidence_se : float
        Mean over chains and its standard error.
    goodness_of_fit : float
        ln p(d | phi*) (Eq. 13).
    information_gain : float
        goodness_of_fit - log_evidence.
    per_chain : list of ChainEvidence
    method : str
    warnings : list of str
    """

    log_evidence: float
    log_evidence_se: float
    goodness_of_fit: float
    information_gain: float
    method: str
    per_chain: list = field(default_factory=list)
    warnings: list = field(default_factory=list)
    n_evaluations: int = 0
    """Likelihood evaluations the estimate itself made (Chib-Jeliazkov: the proposal draws)."""

    def to_dict(self) -> dict:
        return {
            "log_evidence": self.log_evidence, "log_evidence_se": self.log_evidence_se,
            "goodness_of_fit": self.goodness_of_fit, "information_gain": self.information_gain,
            "method": self.method, "warnings": list(self.warnings),
            "per_chain": [c.__dict__ for c in self.per_chain], "n_evaluations": self.n_evaluations,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "Evidence":
        """The estimate :meth:`to_dict` wrote."""
        return cls(d["log_evidence"], d["log_evidence_se"], d["goodness_of_fit"], d["information_gain"],
                   d["method"], [ChainEvidence(**c) for c in d["per_chain"]], list(d["warnings"]),
                   d.get("n_evaluations", 0))


BATCHES = 10
"""Batches of a chain's terms for their batch-means error."""


def _batch_se(log_terms: np.ndarray, batches: int = BATCHES) -> float:
    """Standard error of ln(mean(exp(terms))) by batch means and the delta method."""
    n = log_terms.size
    b = max(2, min(batches, n // 10))
    parts = np.array_split(log_terms, b)
    lm = np.array([logsumexp(p) - math.log(p.size) for p in parts])
    total = logsumexp(lm) - math.log(b)
    rel = np.exp(lm - total)
    return float(np.std(rel, ddof=1) / math.sqrt(b))


DOMINANT = 0.9
"""A batch that carries more than this share of a mean's weight makes its batch-means error meaningless."""

DOMINATED = "one batch of draws carries the Chib-Jeliazkov mean"
"""The warning of an evidence whose estimate rests on one batch of draws (:func:`dominated`)."""


def dominated(log_terms: np.ndarray, batches: int = BATCHES) -> bool:
    """Whether one batch carries more than :data:`DOMINANT` of ln(mean(exp(terms))): the estimate is then as good
    as a handful of draws, and the delta method's error saturates at 1 nat whatever the truth (a placeholder,
    not an error bar)."""
    n = log_terms.size
    b = max(2, min(batches, n // 10))
    if n < 2 or not np.isfinite(log_terms).any():
        return False
    lm = np.array([logsumexp(p) - math.log(p.size) for p in np.array_split(log_terms, b)])
    rel = np.exp(lm - (logsumexp(lm) - math.log(b)))
    return bool(rel.max() > DOMINANT * b)


def pooled_se(values: np.ndarray, within: np.ndarray, batches: int = BATCHES) -> float:
    """Standard error of the mean of the per-chain estimates ``values``, whose own errors (batch means,
    ``within``) are known.

    The spread between a few chains alone is a poor estimate of their error (with 4 chains it has 3
    degrees of freedom: the reported se would be off by 40 % from seed to seed); each chain's batch means
    add ``batches - 1`` more. The two variance estimates of one chain's value are pooled by their degrees of
    freedom, unless the spread between the chains exceeds what their own errors allow (an F test at 1 %:
    batches too short for the autocorrelation, or chains in different modes); then the spread alone is
    the error.
    """
    nc = values.size
    if nc < 2:
        return float(within[0]) if within.size else math.inf
    between = float(np.var(values, ddof=1))
    inside = float(np.mean(within ** 2))
    k_b, k_w = nc - 1, nc * (batches - 1)
    from scipy.stats import f as f_dist  # here: scipy.stats costs every worker half a second at its start

    if not inside > 0 or between / inside > f_dist.ppf(0.99, k_b, k_w):
        return math.sqrt(between / nc)
    return math.sqrt((k_b * between + k_w * inside) / (k_b + k_w) / nc)


PROPOSAL_BLOCK = 250  # denominator draws between two looks at its Monte Carlo error


def _iid_log_mean_se(log_terms: np.ndarray) -> float:
    """Standard error of ln(mean(exp(terms))) for independent terms (delta method); inf when all are zero."""
    w = np.exp(log_terms - np.max(log_terms)) if np.isfinite(log_terms).any() else np.zeros(1)
    m = w.mean()
    return float(w.std(ddof=1) / m / math.sqrt(w.size)) if m > 0 and w.size > 1 else math.inf


COLLAPSED = "the posterior has collapsed"
"""The warning of a posterior far narrower than its own density says (:func:`collapse_drops`)."""

COLLAPSE_NATS = 2.0
"""The least drop of the log posterior 3 marginal sd either side of its mode that a Gaussian posterior cannot
show: there it is 4.5 nats times (marginal / conditional sd)^2 >= 4.5 (a Student t with 3 degrees of freedom
4.6); below 2 the reported sd is at least 1.5 times too small. A likelihood spiked at its mode (a kink the
optimiser sat on) falls by the spike's height whatever the distance, so a spike under 2 nats is caught too."""


def collapse_drops(target, center: np.ndarray, lp_center: float, sd: np.ndarray) -> list[float]:
    """Per parameter, how far the log posterior falls 3 ``sd`` (the draws' marginal sd) from ``center`` (the
    mode), on the side where it falls further (a bound or a skew on one side does not hide the other): 4.5 nats
    or more for a posterior the draws describe (:data:`COLLAPSE_NATS`). Chains that never left a tiny
    neighbourhood (a proposal far too small, a likelihood with kinks at the scale of their steps) report a
    spread the posterior's own density contradicts: it has barely changed that far out."""
    out = []
    for i in range(center.size):
        if not (np.isfinite(sd[i]) and sd[i] > 0):
            out.append(0.0)
            continue
        drops = []
        for sign in (1.0, -1.0):
            x = np.array(center, dtype=float)
            x[i] += sign * 3.0 * sd[i]
            v = target(x).log_posterior
            drops.append(lp_center - v if np.isfinite(v) else math.inf)
        out.append(float(max(drops)))
    return out


def collapsed(names, drops) -> list[tuple]:
    """``(name, drop)`` of the parameters whose drop (:func:`collapse_drops`) is below :data:`COLLAPSE_NATS`."""
    return [(n, d) for n, d in zip(names, drops) if d < COLLAPSE_NATS]


def collapse_warning(names, drops, why: str) -> list[str]:
    """The :data:`COLLAPSED` warning for the parameters :func:`collapsed` names (none when every one falls as a
    Gaussian must)."""
    narrow = collapsed(names, drops)
    if not narrow:
        return []
    return [f"{COLLAPSED}: 3 sd from its mode the log posterior falls by only "
            + ", ".join(f"{d:.2g} nats for {n}" for n, d in narrow[:5])
            + f" (at least 4.5 for a posterior that wide): {why}, so its intervals and this evidence are no result"]


def _cj_chain(args):
    target, samples, lp, phi_star, lp_star, cov, J, se_ratio, seed, *rest = args
    probe = rest[1] if len(rest) > 1 else None
    # the chains moved in unconstrained coordinates z with the fixed proposal q (the random walk N(z, cov),
    # mixed with the independence proposal ``jump`` when there is one; :mod:`.transform`, :class:`Jump`):
    # the ordinate is taken there, with the target's density in z (times |dx/dz|), and mapped back below
    q = MixedProposal(cov, Jump.from_dict(rest[0]) if rest else None)
    free = free_coordinates(target)
    zs, z_star = free.to_free(samples), free.to_free(phi_star)
    lpz = lp + free.log_jacobian(samples)
    jac_star = float(free.log_jacobian(phi_star))
    lpz_star = lp_star + jac_star
    # numerator: (1/M) sum_g alpha(z_g, z*) q(z* | z_g)
    log_q_to = q.log_q(z_star[None, :], zs)
    log_alpha = np.minimum(0.0, lpz_star - lpz + q.log_q(zs, z_star[None, :]) - log_q_to)
    num_terms = log_alpha + log_q_to
    log_num = logsumexp(num_terms) - math.log(samples.shape[0])
    num_se = _batch_se(num_terms)
    # denominator: (1/J) sum_j alpha(z*, z_j), z_j ~ q(. | z*). Its draws are independent, so a few
    # hundred usually pin it far below the numerator's error (autocorrelated draws): stop once its error is
    # under se_ratio of the numerator's, at most J draws
    rng = np.random.default_rng(seed)
    den_terms: list = []
    while len(den_terms) < J:
        for _ in range(min(PROPOSAL_BLOCK, J - len(den_terms))):
            zj = q.draw(rng, z_star)
            y = free.from_free(zj)
            lpj = target(y).log_posterior
            if lpj > -math.inf:
                lpj = lpj + free.log_jacobian(y)
            den_terms.append(min(0.0, lpj - lpz_star + q.log_ratio(zj, z_star)) if lpj > -math.inf else -math.inf)
        if se_ratio > 0 and _iid_log_mean_se(np.asarray(den_terms)) <= se_ratio * num_se:
            break
    den = np.asarray(den_terms)
    log_den = logsumexp(den) - math.log(den.size)
    se = math.sqrt(num_se ** 2 + _batch_se(den) ** 2)
    # ln p(x*|d) = ln p(z*|d) - ln|dx/dz|(x*)
    drops = collapse_drops(target, np.asarray(phi_star, float), lp_star, probe) if probe is not None else None
    return log_num - log_den - jac_star, se, den.size, dominated(num_terms) or dominated(den), drops


def chib_jeliazkov(target, res: SamplerResult, *, n_proposal: int, seed: int,
                   map_fn: Map = serial_map, proposal_se_ratio: float = 0.0) -> Evidence:
    """Chib-Jeliazkov evidence per chain at phi* (Eq. 10-12); mean and standard error over chains: the
    per-chain ordinates of :func:`iter_chib_jeliazkov` on ``map_fn``."""
    return run(iter_chib_jeliazkov(target, res, n_proposal=n_proposal, seed=seed,
                                   proposal_se_ratio=proposal_se_ratio), map_fn)


def iter_chib_jeliazkov(target, res: SamplerResult, *, n_proposal: int, seed: int,
                        proposal_se_ratio: float = 0.0) -> Generator[Batch, list, Evidence]:
    """Chib-Jeliazkov evidence per chain at phi* (Eq. 10-12) as a generator: each chain's ordinate is one
    task of the :class:`~ardcore.sampling.chains.Batch` it yields.

    Parameters
    ----------
    n_proposal : int
        J, the most proposal draws at phi* per chain (the denominator).
    proposal_se_ratio : float
        Stop a chain's denominator draws (in blocks of 250) once their Monte Carlo error is below this
        fraction of the numerator's; 0 always draws ``n_proposal``.

    Raises
    ------
    ValueError
        If a prior is improper (flat, or ARD with alpha = 0): the evidence is undefined.
    """
    if not target.prior.proper:
        bad = [n for n, p in zip(target.prior.names, target.prior.priors) if not p.proper]
        raise ValueError(f"evidence needs proper priors; improper: {bad}")
    nc = res.samples.shape[0]
    seeds = np.random.SeedSequence(seed).generate_state(nc)
    # Z = int L pi <= max L: a chain whose estimate exceeds it never reached phi*'s mode (its draws
    # put no proposal density at phi*), so its posterior ordinate is meaningless
    bound = max(float(res.ll_star), float(np.nanmax(res.ll)) if np.isfinite(res.ll).any() else -math.inf)
    warnings = []
    phi_star, lp_star, ll_star = res.phi_star, res.lp_star, float(res.ll_star)
    n_eval = 0
    # the draws' marginal spread, probed once (by the first chain's task) against the posterior's density
    sd = res.samples.reshape(-1, res.samples.shape[-1]).std(axis=0)
    for attempt in range(2):
        tasks = [(target, res.samples[c], res.lp[c], phi_star, lp_star, res.proposal_cov, n_proposal,
                  proposal_se_ratio, int(seeds[c]), res.jump, sd if c == 0 else None) for c in range(nc)]
        out = yield Batch(_cj_chain, tasks, Step("cj"))
        n_eval += sum(o[2] for o in out)
        per = [ChainEvidence(lp_star - o[0], o[1], o[0]) for o in out]
        valid = [p for p in per if math.isfinite(p.log_evidence) and p.log_evidence <= bound]
        if valid or attempt == 1 or not np.isfinite(res.lp).any():
            break
        # phi* sits where no stationary draw goes: take the best stationary draw instead
        c, i = np.unravel_index(np.nanargmax(res.lp), res.lp.shape)
        warnings.append(f"no chain's stationary draws reached phi* (ln post {lp_star:.2f}); the evidence is "
                        f"taken at the best stationary draw (ln post {res.lp[c, i]:.2f}); burn-in did not settle")
        phi_star, lp_star, ll_star = res.samples[c, i], float(res.lp[c, i]), float(res.ll[c, i])
    if len(valid) < nc:
        bad = [i for i, p in enumerate(per) if p not in valid]
        warnings.append(f"chains {bad} gave impossible ln evidence estimates (above the largest ln L seen, "
                        f"{bound:.2f}): they never reached phi*'s mode and were left out")
    if not valid:
        raise SamplerError("Chib-Jeliazkov: no chain reached the mode of phi* (every estimate exceeds max ln L); "
                           "the sampler did not converge")
    if any(o[3] for o, p in zip(out, per) if p in valid):
        warnings.append(f"{DOMINATED} in a chain: its se is no error bar, and the estimate no result")
    drops = out[0][4] if len(out[0]) > 4 and out[0][4] is not None else []
    warnings += collapse_warning(target.names, drops, "the chains never left a small neighbourhood")
    vals = np.array([p.log_evidence for p in valid])
    per, nc = valid, len(valid)
    mean = float(vals.mean())
    se = pooled_se(vals, np.array([p.se for p in per]))
    if nc > 1:
        noise = np.array([max(p.se, 1e-3) for p in per])
        stat = float(np.sum(((vals - mean) / noise) ** 2))
        from scipy.stats import chi2

        if stat > chi2.ppf(0.999, nc - 1) and np.ptp(vals) > 0.5:
            warnings.append(f"per-chain ln evidence estimates disagree beyond their noise "
                            f"(spread {np.ptp(vals):.2f} nats: {np.round(vals, 2).tolist()}); "
                            "chains may sit in different modes")
    gof = ll_star
    return Evidence(mean, se, gof, gof - mean, "chib-jeliazkov", per, warnings, n_evaluations=n_eval)
