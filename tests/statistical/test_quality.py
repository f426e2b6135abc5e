"""The sampler's unconstrained coordinates, its independence proposal and the stop on quality, against
exact answers (seeded tolerances) and ArviZ's own diagnostics."""

import math

import numpy as np
import pytest

from ardflow.ardcore.sampling.diagnostics import convergence
from ardflow.ardcore.evidence.estimators import chib_jeliazkov
from ardflow.ardcore.sampling.config import SamplerConfig
from ardflow.ardcore.sampling.driver import Runtime, Start, sample
from ardflow.ardcore.likelihood.posterior import FunctionTarget
from ardflow.ardcore.model.priors import JointPrior, LogNormal, Normal, Uniform
from ardflow.ardcore.sampling.transform import Unconstrained

from .targets import GaussianLoglik, correlated_cov


def _prior_mix(names, m, S):
    """Uniform priors 12 sd wide around m on even parameters, normal on odd ones: the uniform part's
    normaliser is exact (1 / width) and its logit coordinates are far from linear."""
    sd = np.sqrt(np.diag(S))
    pri = {}
    for i, n in enumerate(names):
        if i % 2 == 0:
            pri[n] = Uniform(low=float(m[i] - 6 * sd[i]), high=float(m[i] + 6 * sd[i]))
        else:
            pri[n] = Normal(mean=0.0, sd=3.0)
    return pri


def test_unconstrained_round_trip_and_jacobian():
    pri = JointPrior(["a", "b", "c"], {"a": LogNormal(median=0.2, cov=50), "b": Uniform(low=-2, high=0),
                                       "c": Normal(sd=1.0)})
    u = Unconstrained(pri.priors)
    x = np.array([0.37, -1.3, 4.0])
    assert np.allclose(u.from_free(u.to_free(x)), x, rtol=1e-12)
    # ln|dx/dz| against a finite difference of from_free, coordinate by coordinate
    z, h = u.to_free(x), 1e-6
    fd = [(u.from_free(z + h * e)[i] - u.from_free(z - h * e)[i]) / (2 * h) for i, e in enumerate(np.eye(3))]
    assert u.log_jacobian(x) == pytest.approx(float(np.sum(np.log(fd))), abs=1e-6)
    assert u.log_jacobian(np.array([0.37, 0.0, 4.0])) == -math.inf  # on the uniform's bound


def test_a_covariance_taken_beside_a_bound_is_no_wider_than_the_prior_in_z():
    """A start optimiser's mode on a uniform prior's bound (Sec 3.6 M3's A at 0): dx/dz -> 0 there, and the
    linearised step in z must not exceed the prior's own sd in z, or every proposal lands on the bound."""
    pri = JointPrior(["A", "B", "c"], {"A": Uniform(low=0.0, high=0.5), "B": LogNormal(median=0.3, cov=50),
                                       "c": Normal(sd=1.0)})
    u = Unconstrained(pri.priors)
    C = np.diag([0.01, 0.01, 0.04]) + 0.001
    Cz = u.cov_to_free(C, np.array([1e-9, 0.3, 0.0]))
    sd = np.sqrt(np.diag(Cz))
    assert sd[0] <= math.pi / math.sqrt(3) * (1 + 1e-12)
    assert sd[1] == pytest.approx(math.sqrt(0.011) / 0.3)  # inside, the linearisation stands
    assert sd[2] == pytest.approx(math.sqrt(0.041))
    np.linalg.cholesky(Cz)  # still a covariance


@pytest.mark.parametrize("d,seed", [(4, 0), (6, 3)])
def test_evidence_exact_in_unconstrained_coordinates_with_the_jump(d, seed):
    """Chib-Jeliazkov with the mixed proposal, in logit coordinates, on a Gaussian likelihood whose
    normaliser over the prior is known: ln Z = sum ln(1 / width) over the uniform parameters + ln N(m; 0,
    S_odd + 9 I) over the normal ones (the uniform ones integrate to ~1 inside +-6 sd)."""
    from scipy.stats import multivariate_normal as mvn

    S = np.diag(np.diag(correlated_cov(d, seed)))  # independent, so the two groups factorise
    m = np.random.default_rng(seed + 10).standard_normal(d)
    names = [f"p{i}" for i in range(d)]
    pri = _prior_mix(names, m, S)
    target = FunctionTarget(names, JointPrior(names, pri), GaussianLoglik(m, S))
    odd = [i for i in range(d) if i % 2]
    exact = sum(-math.log(pri[names[i]].high - pri[names[i]].low) for i in range(0, d, 2))
    exact += mvn(np.zeros(len(odd)), S[np.ix_(odd, odd)] + 9 * np.eye(len(odd))).logpdf(m[odd])
    cfg = SamplerConfig(n_chains=4, round_size=500, n_stationary=2000, n_proposal=2000)
    res = sample(target, cfg, seed=seed)
    assert res.jump is not None and res.quality_met
    ev = chib_jeliazkov(target, res, n_proposal=cfg.n_proposal, seed=seed + 1, proposal_se_ratio=0.5)
    assert abs(ev.log_evidence - exact) < 0.1
    assert abs(ev.log_evidence - exact) < 5 * ev.log_evidence_se + 0.03


def test_the_jump_mixes_a_correlated_posterior_faster_per_evaluation():
    """ESS per likelihood evaluation (ArviZ, min over parameters) with the independence proposal mixed in
    against the plain random walk, same target, same draws."""
    d = 8
    S = correlated_cov(d, 4)
    m = np.zeros(d)
    names = [f"p{i}" for i in range(d)]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=3.0) for n in names}), GaussianLoglik(m, S))
    out = {}
    for w in (0.0, 0.5):
        cfg = SamplerConfig(n_chains=4, round_size=500, n_stationary=1000, n_proposal=100, jump_weight=w,
                            min_ess=0.0, max_rhat=2.0)
        res = sample(target, cfg, seed=5)
        diag = convergence(names, res.samples)
        out[w] = min(min(v["ess_bulk"], v["ess_tail"]) for v in diag.values()) / res.samples[:, :, 0].size
    assert out[0.5] > 3 * out[0.0]


def test_stationary_draws_continue_to_the_quality_target_and_report_a_short_budget():
    d = 6
    S = correlated_cov(d, 2)
    names = [f"p{i}" for i in range(d)]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=3.0) for n in names}),
                            GaussianLoglik(np.zeros(d), S))
    # a plain random walk needs far more than 100 draws per chain for ESS 400
    cfg = SamplerConfig(n_chains=4, round_size=100, n_stationary=100, n_proposal=100, jump_weight=0.0,
                        max_stationary=20000)
    res = sample(target, cfg, seed=1)
    assert res.quality_met and res.samples.shape[1] > 100
    diag = convergence(names, res.samples)  # what a user computes from the draws
    assert diag == res.diagnostics
    assert all(v["r_hat"] <= 1.01 and v["ess_bulk"] >= 400 and v["ess_tail"] >= 400 for v in diag.values())
    short = sample(target, cfg.model_copy(update={"max_stationary": 200}), seed=1)
    assert not short.quality_met and short.samples.shape[1] == 200
    assert any("not converged" in w for w in short.warnings)


def test_the_result_carries_the_kernel_of_the_pass_it_kept():
    """Chains started far out with a burn-in too short to settle: the first stationary pass is redrawn
    with a proposal refitted to it, and the result must carry that proposal (Chib-Jeliazkov uses it)."""
    from ardflow.ardcore.events import Note
    from ardflow.ardcore.sampling.chains import serial_map

    d = 4
    S = correlated_cov(d, 1)
    m = np.random.default_rng(11).standard_normal(d)
    names = [f"p{i}" for i in range(d)]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=3.0) for n in names}), GaussianLoglik(m, S))
    starts = m + 30 * np.sqrt(np.diag(S)) * np.sign(np.random.default_rng(0).standard_normal((4, d)))
    used = []

    def recording_map(func, items, step=None):
        if step is not None and step.kind == "stationary":
            used.append((np.array(items[0][2]), items[0][6]))
        return serial_map(func, items, step)

    notes = []
    cfg = SamplerConfig(n_chains=4, round_size=20, min_burnin_rounds=2, max_burnin_rounds=2, n_stationary=500,
                        n_proposal=200, max_stationary=500)
    res = sample(target, cfg, seed=12, start=Start(points=starts),
                 runtime=Runtime(map_fn=recording_map, progress=notes.append))
    assert any(isinstance(e, Note) and "drawn again" in e.message for e in notes)
    cov, jump = used[-1]
    np.testing.assert_array_equal(res.proposal_cov, cov)
    assert res.jump == jump.to_dict()
    assert not np.allclose(used[0][0], cov)  # the redraw really used another proposal


def _exact_mix_target(d, seed):
    from scipy.stats import multivariate_normal as mvn

    S = np.diag(np.diag(correlated_cov(d, seed)))
    m = np.random.default_rng(seed + 10).standard_normal(d)
    names = [f"p{i}" for i in range(d)]
    pri = _prior_mix(names, m, S)
    odd = [i for i in range(d) if i % 2]
    exact = sum(-math.log(pri[names[i]].high - pri[names[i]].low) for i in range(0, d, 2))
    exact += mvn(np.zeros(len(odd)), S[np.ix_(odd, odd)] + 9 * np.eye(len(odd))).logpdf(m[odd])
    return FunctionTarget(names, JointPrior(names, pri), GaussianLoglik(m, S)), exact


def test_continued_chains_reach_the_target_and_keep_an_exact_evidence():
    """A search trial's judged draws (short of the target) continued (:func:`continuation`): the kernel is
    refitted to them, the new draws reach the target, only the new evaluations are counted, and
    Chib-Jeliazkov on the continued draws still gives the exact ln Z."""
    from ardflow.ardcore.sampling.driver import continuation, continued

    target, exact = _exact_mix_target(4, 2)
    cfg = SamplerConfig(n_chains=4, round_size=100, min_burnin_rounds=1, n_stationary=100, n_proposal=1000,
                        max_stationary=5000, min_ess=1000)
    first = sample(target, cfg.judged(), seed=4)
    assert not first.quality_met and first.samples.shape[1] == 100
    kept = first.samples.copy()
    res = continued(sample(target, cfg, seed=99, start=Start(resume=continuation(first))), first)
    np.testing.assert_array_equal(first.samples, kept)  # the search trial's result is left as it was
    assert res.quality_met and res.samples.shape[1] > 100
    assert res.burnin_acceptance == first.burnin_acceptance and res.burnin_rounds == first.burnin_rounds
    assert res.n_evaluations == res.samples.shape[0] * res.samples.shape[1]  # one evaluation per new draw
    ev = chib_jeliazkov(target, res, n_proposal=cfg.n_proposal, seed=5, proposal_se_ratio=0.5)
    assert abs(ev.log_evidence - exact) < 5 * ev.log_evidence_se + 0.03
    # the same chains again: the continuation is deterministic (its streams travel in the chain states)
    again = sample(target, cfg, seed=1, start=Start(resume=continuation(first)))
    np.testing.assert_array_equal(again.samples, res.samples)


def test_pooled_evidence_error_is_calibrated_and_steadier_than_the_chains_spread():
    """Four chains' estimates with a known error s, each with a batch-means error estimate (9 degrees of
    freedom): the pooled se is unbiased for s / 2 (in variance) and varies far less from run to run than the
    spread of the four alone; chains that disagree beyond their own errors get the spread."""
    from ardflow.ardcore.evidence.estimators import BATCHES, pooled_se

    rng = np.random.default_rng(0)
    s, nc, runs = 0.3, 4, 4000
    pooled, spread = [], []
    for _ in range(runs):
        v = rng.normal(0.0, s, nc)
        w = s * np.sqrt(rng.chisquare(BATCHES - 1, nc) / (BATCHES - 1))
        pooled.append(pooled_se(v, w))
        spread.append(np.std(v, ddof=1) / math.sqrt(nc))
    pooled, spread = np.array(pooled), np.array(spread)
    assert np.mean(pooled ** 2) == pytest.approx(s * s / nc, rel=0.05)
    assert np.std(pooled) / np.mean(pooled) < 0.6 * np.std(spread) / np.mean(spread)
    # chains in different modes: their own errors are tiny, the spread is the error
    v = np.array([0.0, 0.1, 2.0, 2.1])
    assert pooled_se(v, np.full(4, 0.01)) == pytest.approx(np.std(v, ddof=1) / 2)


def test_the_diagnostics_are_arviz_s_summary_to_rounding():
    """What the sampler stops on and reports is what ``az.summary(kind="diagnostics")`` gives a user for the
    same draws: autocorrelated, anticorrelated and tied chains, chains apart, a constant, one chain, chains of
    4 and of odd length."""
    import warnings

    import arviz as az

    from ardflow.ardcore.sampling.diagnostics import FIELDS

    rng = np.random.default_rng(7)
    for chains, draws, phi in ((4, 1000, 0.95), (8, 333, -0.6), (1, 50, 0.3), (2, 4, 0.0), (4, 4001, 0.999)):
        e = rng.standard_normal((chains, draws, 4))
        x = np.zeros_like(e)
        for t in range(draws):
            x[:, t] = (phi * x[:, t - 1] if t else 0.0) + e[:, t]
        x[..., 1] = np.round(x[..., 1])  # ties
        x[..., 2] = 3.0  # a parameter that never moved
        x[..., 3] += rng.normal(0.0, 0.5, (chains, 1))  # chains that sit apart
        names = list("abcd")
        got = convergence(names, x)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            table = az.summary(az.from_dict({"posterior": {f"p{i}": x[..., i] for i in range(4)}}),
                               kind="diagnostics", round_to="none")
        for i, n in enumerate(names):
            for f in FIELDS:
                want = float(table.loc[f"p{i}"][f])
                if math.isnan(want):
                    assert math.isnan(got[n][f]), (chains, draws, n, f)
                else:
                    assert got[n][f] == pytest.approx(want, rel=1e-10, abs=1e-300), (chains, draws, n, f)
