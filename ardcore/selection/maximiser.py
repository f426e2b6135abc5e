"""ARD evidence maximisation over psi = {alpha_i} (docs/method.md section 6).

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
from typing import Callable, Generator

from .config import MaximiserConfig
from ..evidence.evaluate import (
    EvidenceEvaluator,
)
from ..evidence.estimators import Evidence
from ..sampling.chains import run
from ..sampling.config import SamplerResult
from ..evidence.reweight import resample_states, reweight, weighted_summary
from ..sampling.transform import free_coordinates
from .trial import INF, MaximiserResult, Trial, TrialRequest, diff_se, posterior_summary


def maximise(evaluate: EvidenceEvaluator, ard: dict[str, float | None], config: MaximiserConfig, *,
             seed: int, on_trial: Callable[[Trial], None] | None = None,
             warm: SamplerResult | None = None) -> MaximiserResult:
    """Maximise the evidence over the ARD hyper-parameters: :class:`Maximiser` driven by ``evaluate``.

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
    return run(iter_maximise(_immediate(evaluate), ard, config, seed=seed, on_trial=on_trial, warm=warm,
                             budget=getattr(evaluate, "stationary_budget", 0)))


def iter_maximise(trial, ard: dict[str, float | None], config: MaximiserConfig, *, seed: int,
                  on_trial: Callable[[Trial], None] | None = None, warm: SamplerResult | None = None,
                  budget: int = 0) -> Generator:
    """:func:`maximise` as a generator: :class:`Maximiser` driven by ``trial``, a generator function with the
    arguments of :meth:`EvidenceEvaluator.trial` (whatever its trials yield, this yields: the chain tasks
    they wait for); returns the :class:`MaximiserResult`. ``budget``: the stationary draws per chain the
    reported trial may continue to (0, a closed-form evidence: nothing is continued)."""
    m = Maximiser(ard, config, seed=seed, warm=warm, on_trial=on_trial, budget=budget)
    while (req := m.next()) is not None:
        t0 = time.perf_counter()
        more = {"extend": True} if req.extend else {"bound": True} if req.bound else {}
        target, ev, res = yield from trial(req.psi, req.seed, req.warm, iteration=req.iteration, **more)
        m.observe(req, target, ev, res, time.perf_counter() - t0)
    return m.result()


def _immediate(evaluate):
    """A callable evaluator as a trial generator that waits for nothing."""
    def trial(*args, **kw):
        return evaluate(*args, **kw)
        yield  # unreachable: makes this a generator function
    return trial


class Maximiser:
    """The ARD evidence maximisation (module docstring) as a sans-IO state machine.

    :meth:`next` returns the next :class:`TrialRequest` (None when done); the caller evaluates it and
    hands the outcome to :meth:`observe`. Reweighted steps need no likelihood and are decided inside.
    Internally the plan is a generator: each place that needs a sampled trial yields its request.
    """

    def __init__(self, ard: dict[str, float | None], config: MaximiserConfig, *, seed: int,
                 warm: SamplerResult | None = None, on_trial: Callable[[Trial], None] | None = None,
                 budget: int = 0):
        self.config, self.seed, self.on_trial, self._warm = config, seed, on_trial, warm
        self.budget = budget  # stationary draws per chain the reported trial's chains may continue to
        self.psi = {k: config.alpha_start for k in ard}
        self.thresholds = {k: (v if v is not None else config.prune_alpha) for k, v in ard.items()}
        self.visit = list(ard)[::-1] if config.order == "reverse" else list(ard)
        self.history: list[Trial] = []
        self.n_sampled = 0  # what max_trials limits
        self._iteration = 0  # ids of sampled and reweighted trials
        self.best: Trial | None = None
        self.best_target = self.best_res = None
        self.base = None  # (trial, result): the sampled trial whose draws reweighted trials come from
        self.settled: dict[str, dict] = {}  # psi at which a coordinate's search last ended
        self.pruned_at: dict[str, float] = {}  # the finite alpha a term had when it was pruned
        self._plan_gen = self._plan()
        self._reply = None
        self._carried = None  # a prune bound that decided nothing, recorded with the trial sampled after it
        self._started = False

    # -- the interface
    def next(self) -> TrialRequest | None:
        """The next trial to sample, or None when the maximisation is over."""
        try:
            if not self._started:
                self._started = True
                return next(self._plan_gen)
            reply, self._reply = self._reply, None
            return self._plan_gen.send(reply)
        except StopIteration:
            return None

    def observe(self, request: TrialRequest, target, evidence: Evidence | None, res: SamplerResult | None,
                wall_s: float) -> Trial | None:
        """Record the outcome of ``request`` (a bound is recorded by the prune test that asked for it)."""
        if request.bound:
            self._reply = (evidence, wall_s)
            return None
        post, diag = {}, {}
        if res is not None and res.samples.size:
            post = posterior_summary(res.names, res.samples.reshape(-1, len(res.names)))
            diag = {"rhat": dict(zip(res.names, map(float, res.rhat))), "burnin_rounds": res.burnin_rounds,
                    "converged": res.converged, "acceptance": res.acceptance,
                    "burnin_acceptance": res.burnin_acceptance,
                    # every likelihood evaluation of the trial: start, burn-in, stationary draws, CJ proposals
                    "n_evaluations": int(res.n_evaluations) + int(evidence.n_evaluations)}
        if self._carried:  # a bound that decided nothing: its searches are this trial's cost
            diag["bound"] = self._carried
            diag["n_evaluations"] = diag.get("n_evaluations", 0) + self._carried["n_evaluations"]
            self._carried = None
        if res is not None:
            post.setdefault("_map", dict(zip(res.names, map(float, res.phi_star))))
        tr = Trial(request.iteration, dict(request.psi), evidence, False, request.action, wall_s, post, diag)
        self.history.append(tr)
        self._reply = (tr, target, res)
        return tr

    def result(self) -> MaximiserResult:
        return MaximiserResult(self.psi, self.best, self.best_res, self.best_target, self.history)

    # -- the plan
    def _plan(self):
        cfg = self.config
        tr, target, res = yield from self._sample(self.psi, self._warm, "start")
        tr.accepted = True
        self.best, self.best_target, self.best_res = tr, target, res
        self.base = (tr, res)
        self._notify(tr)
        changed, sweeps = True, 0
        while changed and self.n_sampled < cfg.max_trials and sweeps < cfg.max_sweeps:
            changed = False
            sweeps += 1
            for k in self.visit:
                changed = (yield from self._coordinate(k, sweeps)) or changed
        yield from self._settle()
        yield from self._refine()

    def _coordinate(self, k: str, sweeps: int):
        """One coordinate of a sweep: re-test it if pruned, else its line search and prune test."""
        cfg, changed = self.config, False
        if self.psi[k] == INF and sweeps > 1 and k in self.pruned_at and self.settled.get(k) != self.psi \
                and self.n_sampled < cfg.max_trials:
            changed = yield from self._retest(k)
        if self.psi[k] == INF or self.settled.get(k) == self.psi:
            self.settled[k] = dict(self.psi)
            return changed
        changed = (yield from self._line_search(k, sweeps)) or changed
        if cfg.prune_test and self.n_sampled < cfg.max_trials:
            changed = (yield from self._prune_test(k)) or changed
        self.settled[k] = dict(self.psi)
        return changed

    def _line_search(self, k: str, sweeps: int):
        """Up first (toward the simpler model); in later sweeps, when up does not pay, down: a term the other
        terms' changes made more useful may have been shrunk too far. True when alpha moved."""
        cfg, moved = self.config, False
        for direction in ((1,) if sweeps == 1 else (1, -1)):
            stp = cfg.step_decades
            while stp >= cfg.min_step_decades - 1e-12 and self.n_sampled < cfg.max_trials:
                a = self.psi[k] * 10.0 ** (direction * stp)
                if a >= self.thresholds[k] or a < cfg.alpha_start * (1 - 1e-9):
                    break
                out = yield from self._step(k, stp, direction)
                if out is None:
                    break  # a reweighted smaller step was worse: so is this one
                tr, target, res = out
                if self._better(tr, self.best, cfg.step_noise_k):
                    self._accept(tr, target, res)
                    moved = True
                else:
                    stp /= 2.0
                self._notify(tr)
            if moved:
                break
        return moved

    def _step(self, k: str, stp: float, direction: int):
        """One line-search step of ``stp`` decades: (trial, target, state), or None when the step is known to
        be worse without sampling it.

        Reweighted when that is reliable. When it is not, smaller steps in the same direction are
        reweighted (down to ``reweight_min_step`` decades): ln Z is unimodal in log alpha, so a reliable
        smaller step that is worse means the full step is worse too (None), and one that is better is
        taken instead. Only when no smaller step can be reweighted is the step sampled, its chains
        starting at draws resampled with the weights.
        """
        cfg = self.config
        a = self.psi[k] * 10.0 ** (direction * stp)
        tr, state = self._reweighted(dict(self.psi, **{k: a}), self._label(k, a))
        if tr is not None:
            return tr, None, state
        rw = state
        sub = stp / 2.0
        while sub >= cfg.reweight_min_step - 1e-12:
            b = self.psi[k] * 10.0 ** (direction * sub)
            t2, st2 = self._reweighted(dict(self.psi, **{k: b}), self._label(k, b))
            if t2 is not None:
                if self._better(t2, self.best, cfg.step_noise_k):
                    return t2, None, st2
                self._notify(t2)
                return None
            sub /= 2.0
        bres = self.base[1]
        # resampled starts need distinct draws to resample: with a few heavy weights the chains would all
        # start at one point, so then they continue from where the best trial's chains are
        spread = rw is not None and rw.ess >= 10 * len(bres.states)
        warm = (resample_states(bres, rw.weights, self.seed + 1009 * self._iteration,
                                free_coordinates(self.best_target, bres.names)) if spread else self.best_res)
        return (yield from self._sample(dict(self.psi, **{k: a}), warm, self._label(k, a)))

    def _prune_test(self, k: str):
        """Occam: the nested model (alpha = inf) wins unless the term is worth more than the noise. A nested
        model whose likelihood's maximum falls short of the current ln Z by more than that loses without being
        sampled (:meth:`_bounded`)."""
        psi, action = dict(self.psi, **{k: INF}), f"{k}: prune test (alpha = inf)"
        if (yield from self._bounded(k, psi, action)):
            return False
        tr, target, res = yield from self._sample(psi, self.best_res, action)
        # an evidence that is not a number decides nothing: the term stays (a NaN is never "no better")
        pruned = math.isfinite(tr.evidence.log_evidence) and not self._better(self.best, tr,
                                                                              margin=self.config.keep_nats)
        if pruned:
            self.pruned_at[k] = self.psi[k]
            self._accept(tr, target, res)
        self._notify(tr)
        return pruned

    def _bounded(self, k: str, psi: dict, action: str):
        """True when k's prune test (``psi``, ``action``) is decided by the upper bound of the nested model's ln Z
        (:attr:`MaximiserConfig.prune_bound`): below the current ln Z by more than the test's margin, the
        term stays, and the bound is the test's record in the history (it takes the iteration, the seed and
        the place in ``max_trials`` the sampled test would have: every trial after it is the same). Tried
        only for a term whose posterior mean is ``prune_bound_z`` sd or more from 0."""
        cfg, post = self.config, (self.best.posterior or {}).get(k)
        # a Laplace prune test is itself a search: a bound would cost what it saves
        if not (cfg.prune_bound and self.best.evidence.method != "laplace" and post and post.get("sd", 0) > 0
                and abs(post["mean"]) >= cfg.prune_bound_z * post["sd"]):
            return False
        it = self._iteration
        ev, wall = yield TrialRequest(it, psi, self.best_res, action, self.seed + 1009 * it, bound=True)
        if ev is None:
            return False
        need = max(cfg.noise_k * self.best.evidence.log_evidence_se, cfg.min_gain) + cfg.keep_nats
        if not self.best.evidence.log_evidence - ev.log_evidence > need:
            self._carried = {"log_likelihood_max": ev.log_evidence, "n_evaluations": int(ev.n_evaluations),
                             "decided": False}
            return False
        self._iteration += 1
        self.n_sampled += 1
        tr = Trial(it, psi, ev, False, f"{action}: decided by the likelihood bound", wall, {},
                   {"n_evaluations": int(ev.n_evaluations)}, bound=True)
        self.history.append(tr)
        self._notify(tr)
        return True

    def _retest(self, k: str):
        """The other terms have moved since k was pruned: does k come back? (The prune test that follows
        applies keep_nats.)"""
        a = self.pruned_at[k]
        tr, target, res = yield from self._sample(dict(self.psi, **{k: a}), self.best_res,
                                                  f"{k}: re-test (alpha = {a:.3g})")
        back = self._better(tr, self.best)
        if back:
            self._accept(tr, target, res)
            del self.pruned_at[k]
        self._notify(tr)
        return back

    def _settle(self):
        """The accepted optimum is sampled (never left as a reweighted estimate). A prune test in between
        compares its sampled alpha = inf trial with the reweighted estimate, whose se carries both the base
        trial's and the reweighting's error."""
        if self.best.sampled:
            return
        tr, target, res = yield from self._sample(dict(self.psi), self.best_res,
                                                  "optimum: sampled at the line-search optimum")
        self._accept(tr, target, res)
        self._notify(tr)

    def _refine(self):
        """The search trials' draws are judged, not continued (:meth:`SamplerConfig.judged`): the reported
        posterior is the optimum's chains continued to the quality target, and its evidence is taken again
        from all their draws. (Not counted against ``max_trials``: it is the same trial, drawn longer.)"""
        res = self.best_res
        if (res is None or res.quality_met or not res.samples.size or res.adaptation is None
                or res.samples.shape[1] >= self.budget):
            return
        tr, target, res = yield from self._sample(dict(self.psi), res, "optimum: chains continued to the quality "
                                                  "target", extend=True)
        self._accept(tr, target, res)
        self._notify(tr)

    # -- helpers
    def _sample(self, psi: dict, warm, action: str, extend: bool = False):
        it = self._iteration
        self._iteration += 1
        self.n_sampled += not extend
        return (yield TrialRequest(it, dict(psi), warm, action, self.seed + 1009 * it, extend))

    def _reweighted(self, trial_psi: dict, action: str):
        """(trial, warm state) reweighted from the base trial's draws, or (None, weights or None) when that is
        not reliable (or does not apply)."""
        cfg = self.config
        btr, bres = self.base
        if not cfg.reweight or bres is None or not bres.samples.size:
            return None, None
        rw = reweight(bres.names, bres.samples, btr.psi, trial_psi)
        if rw is None or not rw.reliable(cfg.reweight_min_ess, cfg.reweight_max_se):
            return None, rw
        it = self._iteration
        self._iteration += 1
        be = btr.evidence
        lz = be.log_evidence + rw.log_ratio
        ev = Evidence(lz, math.hypot(be.log_evidence_se, rw.se), be.goodness_of_fit, be.goodness_of_fit - lz,
                      "reweighted", warnings=[])
        tr = Trial(it, dict(trial_psi), ev, False, action + " (reweighted)", 0.0,
                   weighted_summary(bres.names, bres.samples, rw.weights),
                   {"ess": rw.ess, "n_draws": rw.n, "n_evaluations": 0}, reweighted_from=btr.iteration,
                   reweight_se=rw.se)
        self.history.append(tr)
        return tr, resample_states(bres, rw.weights, self.seed + 1009 * it,
                                   free_coordinates(self.best_target, bres.names))

    def _label(self, k: str, a: float) -> str:
        return f"{k}: log10 alpha {math.log10(self.psi[k]):.2f} -> {math.log10(a):.2f}"

    def _better(self, tr: Trial, ref: Trial, k: float | None = None, margin: float = 0.0) -> bool:
        k = self.config.noise_k if k is None else k
        return (tr.evidence.log_evidence - ref.evidence.log_evidence
                > max(k * diff_se(tr, ref), self.config.min_gain) + margin)

    def _accept(self, tr: Trial, target, res) -> None:
        tr.accepted = True
        self.best, self.best_target, self.best_res, self.psi = tr, target, res, dict(tr.psi)
        if tr.sampled:
            self.base = (tr, res)

    def _notify(self, tr: Trial) -> None:
        if self.on_trial:
            self.on_trial(tr)
