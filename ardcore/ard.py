"""ARD evidence maximisation over psi = {alpha_i} (method.md section 7).

Start at alpha_i = ``alpha_start`` (nearly flat). Visit the ARD parameters from the last
declared to the first (the most complex term first, see ``MaximiserConfig.order``). For
each, a line search in log10 alpha: step up by ``step_decades`` while the evidence improves
by more than ``step_noise_k`` times the standard error of the difference, then try half steps
down to ``min_step_decades``. When a coordinate stops improving (or alpha passes its pruning
threshold), test the nested model without the term (alpha = inf): unless the term is worth
more than ``keep_nats`` plus the noise, it is pruned (fixed to 0) and the maximisation
continues over the rest. Later sweeps also step down and re-test pruned terms; sweeps repeat
until one changes nothing. Each trial warm-starts from the best state so far. Every trial is
recorded in the history.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .evidence import Evidence, chib_jeliazkov, laplace
from .mcmc import Map, SamplerConfig, SamplerResult, initial_scale, sample, serial_map
from .posterior import ModelPosterior
from .priors import ARD

INF = math.inf


@dataclass
class MaximiserConfig:
    """Evidence-maximisation settings.

    Attributes
    ----------
    alpha_start : float
        Initial alpha of every ARD parameter.
    step_decades, min_step_decades : float
        First and smallest line-search step in log10 alpha.
    noise_k : float
        The prune test keeps a term only when ln Z with it beats ln Z without it by more than
        noise_k * se of the difference (and ``min_gain``), plus ``keep_nats``; a pruned term
        is re-tested in a later sweep on the noise margin alone, then prune-tested again.
    step_noise_k : float
        The same multiple for a line-search step up in alpha (default 1, as the prune test).
        0 lets the point estimate decide, so a noisy baseline cannot stop a coordinate at its
        starting alpha; on the Sec 3.6 demo that walked unneeded terms up to large alpha one
        step at a time (demo 629 s instead of 394 s) without changing the pruning pattern.
    min_gain : float
        Smallest improvement in ln Z (nats) that counts as a line-search step.
    keep_nats : float
        A term survives its prune test only when ln Z with it beats ln Z without it
        by more than ``keep_nats + noise_k * se``: the lower 1-se bound of its log Bayes factor
        must pass 1 nat, where Kass and Raftery's "positive" evidence starts (2 ln B = 2).
        Below that the evidence for the term is "not worth more than a bare mention"; on the
        Sec 3.6 demo M3 kept theta^5 on a gain of 1.1 +- 0.4 nats without it.
    prune_alpha : float
        Default pruning threshold: past it, the term is tested for removal at once.
    prune_test : bool
        Test alpha = inf when a coordinate stops improving.
    max_trials : int
        Most evidence evaluations per model.
    max_sweeps : int
        Most passes over the ARD parameters.
    order : {"reverse", "declared"}
        Order in which the coordinates are visited. "reverse" (default) starts from the last
        declared ARD parameter: declare terms from the simplest up (a3 .. a6) and the most
        complex one is tested for removal first, while the simpler terms that can stand in for
        it are still free (backward elimination under the hierarchy principle). Visiting a3
        first on the Sec 3.6 study let theta^5 stand in for theta^3 in M1, and theta^4 theta'
        for theta^2 theta' in M3, so the wrong member of each pair was pruned.
    """

    alpha_start: float = 1e-10
    step_decades: float = 2.0
    min_step_decades: float = 1.0
    noise_k: float = 1.0
    step_noise_k: float = 1.0
    min_gain: float = 0.05
    keep_nats: float = 1.0
    prune_alpha: float = 1e12
    prune_test: bool = True
    max_trials: int = 60
    max_sweeps: int = 2
    order: str = "reverse"

    def __post_init__(self):
        if self.order not in ("reverse", "declared"):
            raise ValueError(f"maximiser order must be 'reverse' or 'declared', not {self.order!r}")


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

    def to_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "psi": {k: ("inf" if v == INF else v) for k, v in self.psi.items()},
            **self.evidence.to_dict(), "accepted": self.accepted, "action": self.action,
            "wall_s": self.wall_s, "posterior": self.posterior, "diagnostics": self.diagnostics,
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


def build_target(spec, essential: dict, psi: dict, data, substeps=None) -> ModelPosterior:
    """The posterior at psi: ARD priors N(0, 1/alpha), alpha = inf fixes the term to 0."""
    pruned = {k: 0.0 for k, a in psi.items() if a == INF}
    s = spec.with_fixed(**pruned) if pruned else spec
    priors = dict(essential)
    priors.update({k: ARD(alpha=a) for k, a in psi.items() if a != INF})
    return ModelPosterior(s, priors, data, substeps)


class EvidenceEvaluator:
    """Evidence at a given psi, by Chib-Jeliazkov (sampling) or Laplace."""

    def __init__(self, spec, essential, data, sampler: SamplerConfig, *, method: str = "chib-jeliazkov",
                 substeps=None, map_fn: Map = serial_map, progress=None, cancel=None,
                 final_posterior: str = "sample"):
        self.spec, self.essential, self.data = spec, essential, data
        self.sampler, self.method, self.substeps = sampler, method, substeps
        self.map_fn, self.progress, self.cancel = map_fn, progress, cancel
        # Laplace studies: "sample" draws the final posterior by MCMC, "laplace" takes the Gaussian N(MAP, H^-1)
        # that the evidence itself assumed (what a screen of many candidates can afford)
        self.final_posterior = final_posterior

    def __call__(self, psi: dict, seed: int, warm: SamplerResult | None, *, final: bool = False,
                 iteration: int | None = None):
        target = build_target(self.spec, self.essential, psi, self.data, self.substeps)
        if self.method == "laplace":
            x0 = _warm_point(target, warm) if warm is not None else self._cold_start(target, seed)
            ev, xmap, C = laplace(target, x0, initial_scale(target.prior) if warm is None else None,
                                  warm=warm is not None)
            res = None
            if final and self.final_posterior == "laplace":
                res = _laplace_state(target, xmap, C, ev, draws=4000, seed=seed)
            elif final:
                res = sample(target, self.sampler, seed=seed, map_fn=self.map_fn,
                             starts=_starts_around(xmap, C, self.sampler.n_chains, seed), progress=self.progress,
                             cancel=self.cancel)
            else:
                res = _laplace_state(target, xmap, C, ev)
            return target, ev, res
        res = sample(target, self.sampler, seed=seed, map_fn=self.map_fn, warm=warm,
                     progress=self.progress, cancel=self.cancel)
        ev = chib_jeliazkov(target, res, n_proposal=self.sampler.n_proposal, seed=seed + 7, map_fn=self.map_fn)
        ev.warnings = list(res.warnings) + ev.warnings
        return target, ev, res


    def _cold_start(self, target, seed: int) -> np.ndarray:
        """Best of local searches from the prior medians and n_chains - 1 dispersed prior points.

        One local search from the medians can stop in a poor local mode of a rugged likelihood;
        a Laplace evidence taken there would be wrong by many nats.
        """
        from .mcmc import initial_points

        scale = initial_scale(target.prior)
        pts = [_warm_point(target, None)]
        pts += list(initial_points(target.prior, max(self.sampler.n_chains - 1, 0), np.random.default_rng(seed)))
        tasks = [(target, np.asarray(p, dtype=float), scale, self.sampler.start_maxfev) for p in pts]
        found = self.map_fn(_local_mode_task, tasks, label="start")
        return max(found, key=lambda r: r[1])[0]


def _local_mode_task(args):
    from .mcmc import local_mode

    target, x0, scale, maxfev = args
    return local_mode(target, x0, scale, maxfev)


def _warm_point(target, warm) -> np.ndarray:
    if warm is None:
        return np.array([p.quantile(0.5) if p.kind != "ard" else 0.0 for p in target.prior.priors])
    idx = {n: i for i, n in enumerate(warm.names)}
    return np.array([warm.phi_star[idx[n]] if n in idx else 0.0 for n in target.names])


def _starts_around(x, C, n, seed):
    from .mcmc import safe_cholesky

    rng = np.random.default_rng(seed)
    L = safe_cholesky(C if np.all(np.isfinite(C)) else np.diag(np.maximum(np.abs(x) * 1e-2, 1e-6) ** 2))
    return np.array([x + 2.0 * L @ rng.standard_normal(x.size) for _ in range(n)])


def _laplace_state(target, xmap, C, ev, *, draws: int = 0, seed: int = 0) -> SamplerResult:
    """A SamplerResult carrying the MAP for warm starts of the next Laplace trial; with ``draws``, also
    that many draws of the Laplace posterior N(MAP, C) as one chain (their lp/ll are not evaluated: NaN)."""
    from .mcmc import ChainState, safe_cholesky

    lp, ll = target(xmap)
    st = ChainState(0, xmap.tolist(), lp, ll, np.random.PCG64(0).state, xmap.tolist(), lp, ll)
    d = xmap.size
    samples = np.zeros((0, 0, d))
    if draws:
        L = safe_cholesky(C) if np.all(np.isfinite(C)) else np.zeros((d, d))
        z = np.random.default_rng(seed).standard_normal((draws, d))
        samples = (xmap + z @ L.T)[None]
    nan = np.full(samples.shape[:2], np.nan)
    return SamplerResult(list(target.names), samples, nan, nan, xmap, lp, ll,
                         C, [st], np.ones(d), [], 0, True, 0.0, 0.0, 0)


def maximise(evaluate: EvidenceEvaluator, ard: dict[str, float | None], config: MaximiserConfig, *,
             seed: int, on_trial: Callable[[Trial], None] | None = None,
             warm: SamplerResult | None = None) -> MaximiserResult:
    """Maximise the evidence over the ARD hyper-parameters.

    Parameters
    ----------
    evaluate : EvidenceEvaluator
    ard : dict
        ARD parameter -> its pruning threshold (None: ``config.prune_alpha``).
    config : MaximiserConfig
    seed : int
    on_trial : callable, optional
        Called with every :class:`Trial` as soon as it is done.
    warm : SamplerResult, optional
        Warm start of the first trial (e.g. the fit of a nested model; parameters it lacks start at 0).
    """
    psi = {k: config.alpha_start for k in ard}
    thresholds = {k: (v if v is not None else config.prune_alpha) for k, v in ard.items()}
    visit = list(ard)[::-1] if config.order == "reverse" else list(ard)
    history: list[Trial] = []
    counter = [0]

    def run(trial_psi, warm, action):
        it = counter[0]
        counter[0] += 1
        t0 = time.perf_counter()
        target, ev, res = evaluate(trial_psi, seed + 1009 * it, warm, iteration=it)
        post = {}
        diag = {}
        if res is not None and res.samples.size:
            post = posterior_summary(res.names, res.samples.reshape(-1, len(res.names)))
            diag = {"rhat": dict(zip(res.names, map(float, res.rhat))), "burnin_rounds": res.burnin_rounds,
                    "converged": res.converged, "acceptance": res.acceptance,
                    "burnin_acceptance": res.burnin_acceptance, "n_evaluations": res.n_evaluations}
        if res is not None:
            post.setdefault("_map", dict(zip(res.names, map(float, res.phi_star))))
        tr = Trial(it, dict(trial_psi), ev, False, action, time.perf_counter() - t0, post, diag)
        history.append(tr)
        return tr, target, res

    best, best_target, best_res = run(psi, warm, "start")
    best.accepted = True
    if on_trial:
        on_trial(best)

    def better(tr: Trial, ref: Trial, k: float | None = None, margin: float = 0.0) -> bool:
        se = math.hypot(tr.evidence.log_evidence_se, ref.evidence.log_evidence_se)
        k = config.noise_k if k is None else k
        return tr.evidence.log_evidence - ref.evidence.log_evidence > max(k * se, config.min_gain) + margin

    def accept(tr, target, res):
        nonlocal best, best_target, best_res, psi
        tr.accepted = True
        best, best_target, best_res, psi = tr, target, res, dict(tr.psi)

    settled: dict[str, dict] = {}  # psi at which a coordinate's search last ended
    pruned_at: dict[str, float] = {}  # the finite alpha a term had when it was pruned
    changed = True
    sweeps = 0
    while changed and counter[0] < config.max_trials and sweeps < config.max_sweeps:
        changed = False
        sweeps += 1
        for k in visit:
            if psi[k] == INF and sweeps > 1 and k in pruned_at and settled.get(k) != psi \
                    and counter[0] < config.max_trials:
                # the other terms have moved since k was pruned: does k come back?
                a = pruned_at[k]
                tr, target, res = run(dict(psi, **{k: a}), best_res, f"{k}: re-test (alpha = {a:.3g})")
                if better(tr, best):  # the prune test that follows applies keep_nats
                    accept(tr, target, res)
                    changed = True
                    del pruned_at[k]
                if on_trial:
                    on_trial(tr)
            if psi[k] == INF or settled.get(k) == psi:
                settled[k] = dict(psi)
                continue
            moved = False
            # up first (toward the simpler model); in later sweeps, when up does not pay, down: a term the
            # other terms' changes made more useful may have been shrunk too far
            for direction in ((1,) if sweeps == 1 else (1, -1)):
                step = config.step_decades
                while step >= config.min_step_decades - 1e-12 and counter[0] < config.max_trials:
                    a = psi[k] * 10.0 ** (direction * step)
                    if a >= thresholds[k] or a < config.alpha_start * (1 - 1e-9):
                        break
                    trial = dict(psi, **{k: a})
                    tr, target, res = run(trial, best_res,
                                          f"{k}: log10 alpha {math.log10(psi[k]):.2f} -> {math.log10(a):.2f}")
                    if better(tr, best, config.step_noise_k):
                        accept(tr, target, res)
                        changed = moved = True
                    else:
                        step /= 2.0
                    if on_trial:
                        on_trial(tr)
                if moved:
                    break
            if config.prune_test and counter[0] < config.max_trials:
                trial = dict(psi, **{k: INF})
                tr, target, res = run(trial, best_res, f"{k}: prune test (alpha = inf)")
                # Occam: the nested model wins unless the term is worth more than the noise
                if not better(best, tr, margin=config.keep_nats):
                    pruned_at[k] = psi[k]
                    accept(tr, target, res)
                    changed = True
                if on_trial:
                    on_trial(tr)
            settled[k] = dict(psi)
    return MaximiserResult(psi, best, best_res, best_target, history)
