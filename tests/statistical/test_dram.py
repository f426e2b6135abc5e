"""DRAM leaves the target invariant; pooled adaptation (INCA) shortens burn-in."""

import json
import math

import numpy as np
import pytest
from scipy import stats

from ardflow.ardcore.sampling.chains import ChainState, run_round
from ardflow.ardcore.sampling.config import SamplerConfig
from ardflow.ardcore.sampling.adaptation import rhat
from ardflow.ardcore.sampling.driver import Runtime, Start, sample
from ardflow.ardcore.likelihood.posterior import FunctionTarget
from ardflow.ardcore.model.priors import JointPrior, Normal

from .targets import GaussianLoglik, correlated_cov


def gaussian_target(d=3, seed=0):
    S = correlated_cov(d, seed, scale=1.0)
    names = [f"p{i}" for i in range(d)]
    # a very wide prior: the posterior is N(m, ~S)
    m = np.arange(d, dtype=float)
    t = FunctionTarget(names, JointPrior(names, {n: Normal(sd=1e4) for n in names}), GaussianLoglik(m, S))
    return t, m, S


def fresh_state(target, x, seed):
    lp, ll = target(x)
    return ChainState(0, list(x), lp, ll, np.random.PCG64(seed).state, list(x), lp, ll)


@pytest.mark.parametrize("dr", [True, False])
def test_invariance_with_fixed_proposal(dr):
    target, m, S = gaussian_target()
    # a deliberately poor proposal (too wide) so that delayed rejection is exercised often
    cov = 9.0 * np.eye(3)
    st = fresh_state(target, m, 1)
    out = []
    n_dr = 0
    for _ in range(40):
        r = run_round(target, st, cov, 1000, adaptive=dr, dr_scale=0.2)
        st = r.state
        out.append(r.samples)
        n_dr += r.dr_accepted
    X = np.concatenate(out)
    if dr:
        assert n_dr > 1000
    else:
        assert n_dr == 0
    thin = X[::100]  # roughly independent draws for the KS test
    for i in range(3):
        sd = math.sqrt(S[i, i])
        assert abs(X[:, i].mean() - m[i]) < 0.1 * sd
        assert X[:, i].std() == pytest.approx(sd, rel=0.08)
        assert stats.kstest(thin[:, i], stats.norm(m[i], sd).cdf).pvalue > 1e-3
    C = np.cov(X.T)
    assert np.allclose(C, S, atol=0.12 * np.max(np.diag(S)))


def test_chain_state_serialises_and_resumes_exactly():
    target, m, S = gaussian_target()
    st = fresh_state(target, m, 7)
    cov = np.eye(3)
    a = run_round(target, st, cov, 200, adaptive=True)
    b1 = run_round(target, a.state, cov, 300, adaptive=True)
    restored = ChainState.from_dict(json.loads(json.dumps(a.state.to_dict())))
    b2 = run_round(target, restored, cov, 300, adaptive=True)
    assert np.array_equal(b1.samples, b2.samples)


def test_rhat_detects_separated_chains():
    rng = np.random.default_rng(0)
    same = [rng.standard_normal((1000, 2)) for _ in range(4)]
    apart = [rng.standard_normal((1000, 2)) + 3 * c for c in range(4)]
    assert np.all(rhat(same) < 1.02)
    assert np.all(rhat(apart) > 2)


def burnin_rounds(inca, seed, d=10):
    S = correlated_cov(d, 3, scale=1.0)
    names = [f"p{i}" for i in range(d)]
    # prior sd 10: the initial proposal (0.1 prior sd) is isotropic and of the right size, the shape is wrong
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=10.0) for n in names}), GaussianLoglik(np.zeros(d), S))
    rng = np.random.default_rng(seed)
    starts = 3 * rng.standard_normal((4, d))
    # the random walk's own adaptation is what is compared: no independence proposal, no stop on quality
    cfg = SamplerConfig(n_chains=4, round_size=100, min_burnin_rounds=2, max_burnin_rounds=200, n_stationary=50,
                        n_proposal=50, inca=inca, jump_weight=0.0, min_ess=0.0, max_rhat=2.0)
    return sample(target, cfg, seed=seed, start=Start(points=starts)).burnin_rounds


def test_pooled_adaptation_shortens_burnin():
    # 10-d correlated Gaussian, 4 chains, rounds of 100: measured 10.4 vs 22.7 rounds (seeds 0-9)
    seeds = range(8)
    pooled = [burnin_rounds(True, s) for s in seeds]
    alone = [burnin_rounds(False, s) for s in seeds]
    print("burn-in rounds, INCA:", pooled, "independent:", alone)
    assert np.mean(pooled) < 0.75 * np.mean(alone)


def test_sampler_rounds_as_events_and_resume_from_one():
    """iter_sample yields one typed event per burn-in round and per stationary task, each carrying the state to
    resume from; driven by hand it gives sample()'s result, and resuming from a stationary task's checkpoint
    (with the draws so far) gives the same draws as the run that was not interrupted."""
    from ardflow.ardcore.sampling.driver import STATIONARY_ROUNDS, RoundEvent, Start, iter_sample

    target, _, _ = gaussian_target()
    cfg = SamplerConfig(n_chains=3, round_size=50, min_burnin_rounds=2, max_burnin_rounds=30, n_stationary=300,
                        n_proposal=50, start_maxfev=200, min_ess=0.0, max_rhat=2.0)
    gen = iter_sample(target, cfg, seed=4)
    events = []
    while True:
        try:
            events.append(next(gen))
        except StopIteration as done:
            res = done.value
            break
    assert all(isinstance(e, RoundEvent) for e in events)
    stages = [e.stage for e in events]
    assert stages[0] == "burnin" and events[0].round == 0 and stages[-1] == "stationary"
    assert stages == sorted(stages)  # burn-in rounds, then stationary rounds
    # a stationary task carries up to STATIONARY_ROUNDS rounds: 300 draws in tasks of 200 and 100
    tasks = -(-cfg.n_stationary // (STATIONARY_ROUNDS * cfg.round_size))
    assert tasks == 2 and stages.count("stationary") == tasks and stages.count("burnin") == res.burnin_rounds + 1
    evals = [e.checkpoint["counters"][2] for e in events]
    assert evals == sorted(evals) and evals[-1] == res.n_evaluations
    json.dumps(events[-2].checkpoint)  # JSON-able
    again = sample(target, cfg, seed=4)
    np.testing.assert_array_equal(again.samples, res.samples)
    mid = dict(events[-2].checkpoint, samples=res.samples, lp=res.lp, ll=res.ll)  # after the first stationary task
    resumed = sample(target, cfg, seed=4, start=Start(resume=mid))
    np.testing.assert_array_equal(resumed.samples, res.samples)
    assert resumed.n_evaluations == res.n_evaluations


def far_start_run(restarts: int, notes: list | None = None):
    """Chains started 30 sd out with two short burn-in rounds: the first stationary draws still disagree."""
    target, m, S = gaussian_target(d=2, seed=1)
    starts = m + 30 * np.sqrt(np.diag(S)) * np.sign(np.random.default_rng(0).standard_normal((4, 2)))
    # the plain random walk, judged at the old threshold and not continued: the redraw alone is tested
    cfg = SamplerConfig(n_chains=4, round_size=20, min_burnin_rounds=2, max_burnin_rounds=2, n_stationary=100,
                        n_proposal=50, stationary_restarts=restarts, jump_weight=0.0, max_stationary=100,
                        min_ess=0.0, max_rhat=1.1)
    progress = (lambda e: notes.append(e)) if notes is not None else None
    res = sample(target, cfg, seed=12, start=Start(points=starts), runtime=Runtime(progress=progress))
    return res, target, m, S, cfg, starts


def test_stationary_draws_that_fail_rhat_are_drawn_again():
    """Burn-in ends on a loose R-hat over a few rounds; the stationary draws themselves must pass
    rhat_threshold, or they count as burn-in and are drawn again from where the chains are."""
    from ardflow.ardcore.events import Note

    once, *_ = far_start_run(0)
    assert np.max(once.rhat) > 1.1 and any("R-hat" in w for w in once.warnings)
    notes = []
    res, target, m, S, cfg, starts = far_start_run(6, notes)
    redraws = [e for e in notes if isinstance(e, Note) and "drawn again" in e.message]
    assert redraws and np.max(res.rhat) < 1.1 and not any("R-hat" in w for w in res.warnings)
    flat = res.samples.reshape(-1, 2)
    assert np.all(np.abs(flat.mean(0) - m) < 6 * np.sqrt(np.diag(S) * 20 / flat.shape[0]))  # tau ~ 20
    # every evaluation is counted: redrawn passes included
    assert res.n_evaluations >= cfg.n_chains * cfg.n_stationary * (len(redraws) + 1)
    # resuming inside a redrawn pass gives the same draws
    from ardflow.ardcore.sampling.driver import Start, iter_sample

    gen = iter_sample(target, cfg, seed=12, start=Start(points=starts))
    cks = []
    while True:
        try:
            cks.append(next(gen).checkpoint)
        except StopIteration:
            break
    # (a checkpoint of the last pass: the draws it holds so far are the first slots of the final draws)
    mid = [c for c in cks if c["stage"] == "stationary" and c["pass"] == len(redraws) and 0 < c["done"] < 100][0]
    resumed = sample(target, cfg, seed=12, start=Start(resume=dict(mid, samples=res.samples, lp=res.lp, ll=res.ll)))
    np.testing.assert_array_equal(resumed.samples, res.samples)


class _Counting:
    """A target that counts its calls (the sampler's own evaluation count is checked against it)."""

    def __init__(self, target):
        self.target, self.names, self.prior, self.calls = target, target.names, target.prior, 0

    def __call__(self, x):
        self.calls += 1
        return self.target(x)


@pytest.mark.parametrize("dr_scale", [0.1, 0.0])
def test_evaluation_count_is_every_likelihood_call(dr_scale):
    """n_evaluations counts what the chains really evaluate: the second stage of delayed rejection only when it
    is on (with dr_scale = 0 a rejected proposal costs nothing more)."""
    target, m, S = gaussian_target()
    counted = _Counting(target)
    cfg = SamplerConfig(n_chains=3, round_size=100, min_burnin_rounds=2, max_burnin_rounds=4, n_stationary=200,
                        n_proposal=50, start_maxfev=200, dr_scale=dr_scale)
    res = sample(counted, cfg, seed=3, start=Start(points=np.array([m, m + 0.1, m - 0.1])))
    assert res.n_evaluations == counted.calls
