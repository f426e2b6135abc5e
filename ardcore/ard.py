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
from typing import Callable, Literal

import numpy as np
from pydantic import BaseModel, Field

from .evaluate import (  # noqa: F401
    EvidenceEvaluator,
    _laplace_state,
    _local_mode_task,
    _starts_around,
    _warm_point,
    build_target,
)
from .evidence import Evidence
from .jsonio import encode_alpha
from .mcmc import SamplerResult
from .posterior import ModelPosterior
from .reweight import resample_states, reweight, weighted_summary
from .sampling import SETTINGS

INF = math.inf


class MaximiserConfig(BaseModel):
    """Evidence-maximisation settings, with their bounds: the study spec's ``maximiser`` section is this model.

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
    reweight : bool
        Line-search steps are first estimated by reweighting the draws of the last sampled trial
        (:mod:`ardcore.reweight`: the step changes only the ARD prior, so no likelihood is evaluated);
        a real trial (MCMC + Chib-Jeliazkov) runs only when that estimate is unreliable, for every
        prune test and re-test, and at the accepted optimum. Studies with Laplace evidence draw
        nothing to reweight.
    reweight_min_ess : float
        Smallest Kish effective sample size of the weights, as a share of the draws, for a reweighted
        step. Below about a quarter the new posterior's bulk sits where the old one has few draws and
        the estimate rests on a handful of them (its batch-means se is then itself unreliable).
    reweight_max_se : float
        Largest Monte Carlo se (nats, batch means) of a reweighted step; 0.2 is below the Chib-Jeliazkov
        se of a sampled trial in the reference studies, so a reweighted step is never the noisier one.
    reweight_min_step : float
        Smallest step (decades) tried by reweighting when a full step cannot be reweighted (see
        :func:`maximise`); such smaller steps cost no likelihood evaluation.
    """

    model_config = SETTINGS
    alpha_start: float = Field(1e-10, gt=0)
    step_decades: float = Field(2.0, gt=0, le=10)
    min_step_decades: float = Field(1.0, gt=0, le=10)
    noise_k: float = Field(1.0, ge=0, le=10)
    step_noise_k: float = Field(1.0, ge=0, le=10)
    min_gain: float = Field(0.05, ge=0, le=100)
    keep_nats: float = Field(1.0, ge=0, le=100)
    prune_alpha: float = Field(1e12, gt=0)
    prune_test: bool = True
    max_trials: int = Field(60, ge=1, le=1000)
    max_sweeps: int = Field(2, ge=1, le=100)
    order: Literal["reverse", "declared"] = Field(
        "reverse", description="visit the ARD parameters from the last declared (default) or the first")
    reweight: bool = True
    reweight_min_ess: float = Field(0.25, gt=0, le=1)
    reweight_max_se: float = Field(0.2, gt=0, le=100)
    reweight_min_step: float = Field(0.25, gt=0, le=10)


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

    @property
    def sampled(self) -> bool:
        return self.reweighted_from is None

    def to_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "psi": {k: encode_alpha(v) for k, v in self.psi.items()},
            **self.evidence.to_dict(), "accepted": self.accepted, "action": self.action,
            "wall_s": self.wall_s, "posterior": self.posterior, "diagnostics": self.diagnostics,
            "sampled": self.sampled, "reweighted_from": self.reweighted_from, "reweight_se": self.reweight_se,
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
    counter = [0]   # iteration ids (sampled and reweighted trials)
    n_sampled = [0]  # sampled trials: what max_trials limits

    def run(trial_psi, warm, action):
        it = counter[0]
        counter[0] += 1
        n_sampled[0] += 1
        t0 = time.perf_counter()
        target, ev, res = evaluate(trial_psi, seed + 1009 * it, warm, iteration=it)
        post = {}
        diag = {}
        if res is not None and res.samples.size:
            post = posterior_summary(res.names, res.samples.reshape(-1, len(res.names)))
            diag = {"rhat": dict(zip(res.names, map(float, res.rhat))), "burnin_rounds": res.burnin_rounds,
                    "converged": res.converged, "acceptance": res.acceptance,
                    "burnin_acceptance": res.burnin_acceptance,
                    # every likelihood evaluation of the trial: start, burn-in, stationary draws, CJ proposals
                    "n_evaluations": int(res.n_evaluations) + int(ev.n_evaluations)}
        if res is not None:
            post.setdefault("_map", dict(zip(res.names, map(float, res.phi_star))))
        tr = Trial(it, dict(trial_psi), ev, False, action, time.perf_counter() - t0, post, diag)
        history.append(tr)
        return tr, target, res

    best, best_target, best_res = run(psi, warm, "start")
    best.accepted = True
    base = (best, best_res)  # the sampled trial whose draws reweighted trials come from
    if on_trial:
        on_trial(best)

    def reweighted(trial_psi, action):
        """(trial, warm state) reweighted from the base trial's draws, or (None, weights or None) when that is
        not reliable (or does not apply)."""
        btr, bres = base
        if not config.reweight or bres is None or not bres.samples.size:
            return None, None
        rw = reweight(bres.names, bres.samples, btr.psi, trial_psi)
        if rw is None or not rw.reliable(config.reweight_min_ess, config.reweight_max_se):
            return None, rw
        it = counter[0]
        counter[0] += 1
        be = btr.evidence
        lz = be.log_evidence + rw.log_ratio
        ev = Evidence(lz, math.hypot(be.log_evidence_se, rw.se), be.goodness_of_fit, be.goodness_of_fit - lz,
                      "reweighted", warnings=[])
        tr = Trial(it, dict(trial_psi), ev, False, action + " (reweighted)", 0.0,
                   weighted_summary(bres.names, bres.samples, rw.weights),
                   {"ess": rw.ess, "n_draws": rw.n, "n_evaluations": 0}, reweighted_from=btr.iteration,
                   reweight_se=rw.se)
        history.append(tr)
        return tr, resample_states(bres, rw.weights, seed + 1009 * it)

    def label(k, a):
        return f"{k}: log10 alpha {math.log10(psi[k]):.2f} -> {math.log10(a):.2f}"

    def step(k, stp, direction):
        """One line-search step of ``stp`` decades: (trial, target, state), or None when the step is known to
        be worse without sampling it.

        Reweighted when that is reliable. When it is not, smaller steps in the same direction are
        reweighted (down to ``reweight_min_step`` decades): ln Z is unimodal in log alpha, so a reliable
        smaller step that is worse means the full step is worse too (None), and one that is better is
        taken instead. Only when no smaller step can be reweighted is the step sampled, its chains
        starting at draws resampled with the weights.
        """
        a = psi[k] * 10.0 ** (direction * stp)
        tr, state = reweighted(dict(psi, **{k: a}), label(k, a))
        if tr is not None:
            return tr, None, state
        rw = state
        sub = stp / 2.0
        while sub >= config.reweight_min_step - 1e-12:
            b = psi[k] * 10.0 ** (direction * sub)
            t2, st2 = reweighted(dict(psi, **{k: b}), label(k, b))
            if t2 is not None:
                if better(t2, best, config.step_noise_k):
                    return t2, None, st2
                if on_trial:
                    on_trial(t2)
                return None
            sub /= 2.0
        bres = base[1]
        # resampled starts need distinct draws to resample: with a few heavy weights the chains would all
        # start at one point, so then they continue from where the best trial's chains are
        spread = rw is not None and rw.ess >= 10 * len(bres.states)
        warm = resample_states(bres, rw.weights, seed + 1009 * counter[0]) if spread else best_res
        return run(dict(psi, **{k: a}), warm, label(k, a))

    def diff_se(a: Trial, b: Trial) -> float:
        """se of ln Z(a) - ln Z(b): a reweighted trial shares its base's estimate, so only the reweighting's
        own error separates them."""
        if a.reweighted_from is not None and a.reweighted_from == b.iteration:
            return a.reweight_se
        if b.reweighted_from is not None and b.reweighted_from == a.iteration:
            return b.reweight_se
        if a.reweighted_from is not None and a.reweighted_from == b.reweighted_from:
            return math.hypot(a.reweight_se, b.reweight_se)
        return math.hypot(a.evidence.log_evidence_se, b.evidence.log_evidence_se)

    def better(tr: Trial, ref: Trial, k: float | None = None, margin: float = 0.0) -> bool:
        k = config.noise_k if k is None else k
        return tr.evidence.log_evidence - ref.evidence.log_evidence > max(k * diff_se(tr, ref), config.min_gain) + margin

    def accept(tr, target, res):
        nonlocal best, best_target, best_res, psi, base
        tr.accepted = True
        best, best_target, best_res, psi = tr, target, res, dict(tr.psi)
        if tr.sampled:
            base = (tr, res)

    def settle():
        """The accepted optimum is sampled (never left as a reweighted estimate). A prune test in between
        compares its sampled alpha = inf trial with the reweighted estimate, whose se carries both the base
        trial's and the reweighting's error."""
        if best.sampled:
            return
        tr, target, res = run(dict(psi), best_res, "optimum: sampled at the line-search optimum")
        accept(tr, target, res)
        if on_trial:
            on_trial(tr)

    settled: dict[str, dict] = {}  # psi at which a coordinate's search last ended
    pruned_at: dict[str, float] = {}  # the finite alpha a term had when it was pruned
    changed = True
    sweeps = 0
    while changed and n_sampled[0] < config.max_trials and sweeps < config.max_sweeps:
        changed = False
        sweeps += 1
        for k in visit:
            if psi[k] == INF and sweeps > 1 and k in pruned_at and settled.get(k) != psi \
                    and n_sampled[0] < config.max_trials:
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
                stp = config.step_decades
                while stp >= config.min_step_decades - 1e-12 and n_sampled[0] < config.max_trials:
                    a = psi[k] * 10.0 ** (direction * stp)
                    if a >= thresholds[k] or a < config.alpha_start * (1 - 1e-9):
                        break
                    out = step(k, stp, direction)
                    if out is None:
                        break  # a reweighted smaller step was worse: so is this one
                    tr, target, res = out
                    if better(tr, best, config.step_noise_k):
                        accept(tr, target, res)
                        changed = moved = True
                    else:
                        stp /= 2.0
                    if on_trial:
                        on_trial(tr)
                if moved:
                    break
            if config.prune_test and n_sampled[0] < config.max_trials:
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
    settle()
    return MaximiserResult(psi, best, best_res, best_target, history)
