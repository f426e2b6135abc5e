"""The evidence at one psi: the posterior target with ARD priors N(0, 1/alpha) (alpha = inf fixes a term to
0), its chains' starts (cold, or warm from the previous trial), and Chib-Jeliazkov or Laplace."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Generator

import numpy as np

from .estimators import Evidence, iter_chib_jeliazkov
from .laplace import laplace
from ..sampling.chains import Batch, Step, run
from ..sampling.config import SamplerConfig, SamplerResult
from ..sampling.driver import Runtime, Start, continuation, continued, sample_batches
from ..sampling.starts import initial_scale
from ..sampling.starts import new_parameter_start
from ..likelihood.posterior import Density, ModelPosterior
from ..model.priors import ARD
from ..sampling.transform import free_coordinates

INF = math.inf


def build_target(spec, essential: dict, psi: dict, data, substeps=None) -> ModelPosterior:
    """The posterior at psi: ARD priors N(0, 1/alpha), alpha = inf fixes the term to 0."""
    pruned = {k: 0.0 for k, a in psi.items() if a == INF}
    s = spec.with_fixed(**pruned) if pruned else spec
    priors = dict(essential)
    priors.update({k: ARD(alpha=a) for k, a in psi.items() if a != INF})
    return ModelPosterior(s, priors, data, substeps)


@dataclass(frozen=True)
class EvidenceSettings:
    """How the evidence is computed: the ``sampler`` settings, the ``method`` (``"chib-jeliazkov"`` from
    MCMC draws or ``"laplace"``) and, for Laplace studies, the ``final_posterior``: ``"sample"`` draws the
    reported posterior by MCMC, ``"laplace"`` takes the Gaussian N(MAP, H^-1) the evidence itself assumed
    (what a screen of many candidates can afford)."""

    sampler: SamplerConfig
    method: str = "chib-jeliazkov"
    final_posterior: str = "sample"


class EvidenceEvaluator:
    """Evidence at a given psi, by Chib-Jeliazkov (sampling) or Laplace.

    Parameters
    ----------
    spec : ModelSpec
    essential : dict
        The essential parameters' priors.
    data : Dataset
    settings : EvidenceSettings
    substeps : int, optional
        Integration sub-steps (default: the model's).
    runtime : Runtime
        How the chains run and report (:class:`~ardcore.sampling.driver.Runtime`; its checkpoint and pool
        factory belong to orchestrators).
    """

    def __init__(self, spec, essential, data, settings: EvidenceSettings, *, substeps=None,
                 runtime: Runtime = Runtime()):
        self.spec, self.essential, self.data = spec, essential, data
        self.sampler, self.method, self.substeps = settings.sampler, settings.method, substeps
        self.final_posterior = settings.final_posterior
        self.runtime = runtime

    # read from the runtime, the one place they are set (an orchestrator replaces the runtime's map)
    map_fn = property(lambda self: self.runtime.map_fn)
    progress = property(lambda self: self.runtime.progress)
    cancel = property(lambda self: self.runtime.cancel)

    def config(self, extend: bool) -> SamplerConfig:
        """The sampler settings of a trial: the judged M draws for a search trial, the full budget for the
        reported trial's continued chains."""
        return self.sampler if extend else self.sampler.judged()

    @property
    def stationary_budget(self) -> int:
        """Stationary draws per chain the reported trial's chains may continue to (0: Laplace, no chains)."""
        return 0 if self.method == "laplace" else self.sampler.stationary_budget

    def __call__(self, psi: dict, seed: int, warm: SamplerResult | None, *, final: bool = False,
                 iteration: int | None = None, extend: bool = False, bound: bool = False):
        """(target, evidence, sampler result) at ``psi``: :meth:`trial` with its chain tasks on the runtime's
        map."""
        return run(self.trial(psi, seed, warm, final=final, iteration=iteration, extend=extend, bound=bound),
                   self.map_fn)

    def trial(self, psi: dict, seed: int, warm: SamplerResult | None, *, final: bool = False,
              iteration: int | None = None, extend: bool = False, bound: bool = False) -> Generator:
        """The trial at ``psi`` as a generator of the chain tasks it waits for (each a
        :class:`~ardcore.sampling.chains.Batch`; :func:`~ardcore.sampling.chains.run` drives it) returning
        (target, evidence, sampler result): chains warm-started from ``warm`` drawing the judged M per chain
        (:meth:`SamplerConfig.judged`), or with ``extend`` the chains of ``warm`` continued to the quality
        target (:func:`~ardcore.sampling.driver.continuation`). With ``bound``, no chain: an upper bound of
        ln Z at ``psi`` (:meth:`likelihood_bound`; evidence None where there is none to take: a Laplace
        evidence, no draws to start from). ``iteration`` numbers the trial for orchestrators that keep it."""
        target = build_target(self.spec, self.essential, psi, self.data, self.substeps)
        if bound:
            if self.method == "laplace" or warm is None or not warm.states:
                return target, None, None
            return target, (yield from self.likelihood_bound(target, warm)), None
        if self.method == "laplace":
            # the searches only place the start: on a long record they may read its first samples alone
            search = target.window(self.sampler.search_window)
            x0 = warm_point(target, warm) if warm is not None else (yield from self._cold_start(search, seed))
            ev, xmap, C = laplace(target, x0, initial_scale(target.prior) if warm is None else None,
                                  warm=warm is not None, search=search)
            res = None
            if final and self.final_posterior == "laplace":
                res = _laplace_state(target, xmap, C, ev, draws=LAPLACE_DRAWS, seed=seed)
            elif final:
                res = yield from sample_batches(
                    target, self.sampler, seed=seed,
                    start=Start(points=_starts_around(xmap, C, self.sampler.n_chains, seed)), runtime=self.runtime)
            else:
                # draws of N(MAP, H^-1), which the Laplace evidence assumes: the maximiser reweights them for
                # its line-search steps (only the ARD prior changes) instead of another Newton fit
                res = _laplace_state(target, xmap, C, ev, draws=LAPLACE_DRAWS, seed=seed)
            return target, ev, res
        if extend:
            res = yield from sample_batches(target, self.config(extend), seed=seed,
                                            start=Start(resume=continuation(warm)), runtime=self.runtime)
            res = continued(res, warm)
        else:
            res = yield from sample_batches(target, self.config(extend), seed=seed, start=Start(warm=warm),
                                            runtime=self.runtime)
        ev = yield from iter_chib_jeliazkov(target, res, n_proposal=self.sampler.n_proposal, seed=seed + 7,
                                            proposal_se_ratio=self.sampler.proposal_se_ratio)
        ev.warnings = list(res.warnings) + ev.warnings
        return target, ev, res

    def likelihood_bound(self, target, warm: SamplerResult) -> Generator:
        """An upper bound of ln Z of ``target``: the prior integrates to one, so Z = E_prior[L] <= max L. The
        maximum of the log likelihood over the prior's support is searched from the best point of each chain of
        ``warm`` (another model's: a parameter ``target`` fixes is dropped, one it adds starts at its prior's
        centre), in coordinates scaled by ``warm``'s posterior spread, half the start budget each (a
        generator: the searches are one batch). A search can stop short of the maximum, so the bound is the
        largest maximum found plus its gap to the next largest (the room the searches may have left; one
        search stuck far below does not widen it). Returns an :class:`Evidence` whose ``log_evidence`` is the
        bound (``method`` "likelihood bound", se 0, ``goodness_of_fit`` the largest maximum found)."""
        pts = [_projected(target, warm, np.asarray(s.best_x, float)) for s in warm.states]
        scale = _warm_scale(target, warm)
        tasks = [(target, x, scale, max(self.sampler.start_maxfev // 2, 20)) for x in pts]
        found = yield Batch(_max_likelihood_task, tasks, Step("start"))
        lls = sorted((ll for _, ll, _ in found), reverse=True)
        top, gap = lls[0], (lls[0] - lls[1] if len(lls) > 1 else 0.0)
        return Evidence(top + gap, 0.0, top, 0.0, "likelihood bound", n_evaluations=sum(n for *_, n in found))

    def _cold_start(self, target, seed: int) -> Generator:
        """Best of local searches from the prior medians and n_chains - 1 dispersed prior points (a generator:
        the searches are one batch).

        One local search from the medians can stop in a poor local mode of a rugged likelihood;
        a Laplace evidence taken there would be wrong by many nats.
        """
        from ..sampling.starts import initial_points

        scale = initial_scale(target.prior)
        pts = [warm_point(target, None)]
        pts += list(initial_points(target.prior, max(self.sampler.n_chains - 1, 0), np.random.default_rng(seed)))
        tasks = [(target, np.asarray(p, dtype=float), scale, self.sampler.start_maxfev) for p in pts]
        found = yield Batch(_local_mode_task, tasks, Step("start"))
        return max(found, key=lambda r: r[1])[0]


def _local_mode_task(args):
    from ..sampling.starts import local_mode

    target, x0, scale, maxfev = args
    return local_mode(target, x0, scale, maxfev)


class _LikelihoodOnly:
    """A target whose density is its likelihood over the prior's support (what a search for max L climbs)."""

    def __init__(self, target):
        self.target = target

    def __call__(self, x):
        d = self.target(x)
        return Density(d.log_likelihood if d.log_posterior > -math.inf else -math.inf, d.log_likelihood)


def _max_likelihood_task(args):
    """(point, its log likelihood, evaluations) of a likelihood maximisation over the prior's support."""
    from ..sampling.starts import Counted, local_mode

    target, x0, scale, maxfev = args
    counted = Counted(target)
    x, ll = local_mode(_LikelihoodOnly(counted), x0, scale, maxfev, xatol=1e-4, fatol=1e-3)
    return x, ll, counted.calls


def _projected(target, warm: SamplerResult, x: np.ndarray) -> np.ndarray:
    """A point ``x`` of ``warm``'s parameters as one of ``target``'s (see :func:`warm_point`)."""
    idx = {n: i for i, n in enumerate(warm.names)}
    return np.array([x[idx[n]] if n in idx else new_parameter_start(p)
                     for n, p in zip(target.names, target.prior.priors)])


def _warm_scale(target, warm: SamplerResult) -> np.ndarray:
    """Per parameter of ``target``, the posterior sd in ``warm``'s draws where it has one, else the prior's
    initial scale."""
    prior = initial_scale(target.prior)
    if not warm.samples.size:
        return prior
    sd = np.std(warm.samples.reshape(-1, warm.samples.shape[-1]), axis=0)
    idx = {n: i for i, n in enumerate(warm.names)}
    return np.array([sd[idx[n]] if n in idx and sd[idx[n]] > 0 else prior[j] for j, n in enumerate(target.names)])


def warm_point(target, warm) -> np.ndarray:
    if warm is None:
        return np.array([p.quantile(0.5) if p.kind != "ard" else 0.0 for p in target.prior.priors])
    return _projected(target, warm, np.asarray(warm.phi_star, float))


def _starts_around(x, C, n, seed):
    from ..sampling.proposal import safe_cholesky

    rng = np.random.default_rng(seed)
    L = safe_cholesky(C if np.all(np.isfinite(C)) else np.diag(np.maximum(np.abs(x) * 1e-2, 1e-6) ** 2))
    return np.array([x + 2.0 * L @ rng.standard_normal(x.size) for _ in range(n)])


LAPLACE_DRAWS = 4000
"""Draws of the Laplace posterior a Laplace trial carries (no likelihood evaluations: Gaussian draws)."""


def _laplace_state(target, xmap, C, ev, *, draws: int = 0, seed: int = 0) -> SamplerResult:
    """A SamplerResult carrying the MAP for warm starts of the next Laplace trial; with ``draws``, also
    that many draws of the Laplace posterior N(MAP, C) as one chain (their lp/ll are not evaluated: NaN)."""
    from ..sampling.chains import ChainState
    from ..sampling.proposal import safe_cholesky

    lp, ll = target(xmap)
    st = ChainState(0, xmap.tolist(), lp, ll, np.random.PCG64(0).state, xmap.tolist(), lp, ll)
    d = xmap.size
    samples = np.zeros((0, 0, d))
    if draws:
        L = safe_cholesky(C) if np.all(np.isfinite(C)) else np.zeros((d, d))
        z = np.random.default_rng(seed).standard_normal((draws, d))
        samples = (xmap + z @ L.T)[None]
    nan = np.full(samples.shape[:2], np.nan)
    # a proposal covariance is in the sampler's unconstrained coordinates (:mod:`.transform`)
    Cz = free_coordinates(target).cov_to_free(C, xmap) if np.all(np.isfinite(C)) else C
    return SamplerResult(list(target.names), samples, nan, nan, xmap, lp, ll,
                         Cz, [st], np.ones(d), [], 0, True, 0.0, 0.0, 0)


