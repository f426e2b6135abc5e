"""Evidence estimators against exact answers (seeded tolerances)."""

import math

import numpy as np
import pytest
from scipy.stats import multivariate_normal as mvn

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.evidence.estimators import chib_jeliazkov
from ardflow.ardcore.evidence.laplace import laplace
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.sampling.config import SamplerConfig
from ardflow.ardcore.sampling.driver import Runtime, Start, sample
from ardflow.ardcore.likelihood.posterior import FunctionTarget, ModelPosterior
from ardflow.ardcore.model.priors import JointPrior, Normal

from .targets import LINEAR_SYSTEM, GaussianLoglik, augmented_kalman, correlated_cov, linear_gaussian_spec

CFG = SamplerConfig(n_chains=4, round_size=500, n_stationary=5000, n_proposal=5000)


@pytest.mark.parametrize("d,seed", [(6, 0), (8, 1)])
def test_correlated_gaussian_known_normaliser(d, seed):
    S = correlated_cov(d, seed)
    m = np.random.default_rng(seed + 10).standard_normal(d)
    tau = 3.0
    names = [f"p{i}" for i in range(d)]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=tau) for n in names}), GaussianLoglik(m, S))
    exact = mvn(np.zeros(d), S + tau**2 * np.eye(d)).logpdf(m)
    res = sample(target, CFG, seed=seed)
    ev = chib_jeliazkov(target, res, n_proposal=CFG.n_proposal, seed=seed + 1)
    assert abs(ev.log_evidence - exact) < 0.15
    assert abs(ev.log_evidence - exact) < 5 * ev.log_evidence_se + 0.05
    lap, xmap, C = laplace(target, res.phi_star)
    assert lap.log_evidence == pytest.approx(exact, abs=1e-6)
    # the posterior itself is right: mean and sd against the conjugate answer
    P = np.linalg.inv(np.linalg.inv(S) + np.eye(d) / tau**2)
    mu = P @ np.linalg.inv(S) @ m
    flat = res.samples.reshape(-1, d)
    assert np.all(np.abs(flat.mean(0) - mu) < 0.1 * np.sqrt(np.diag(P)) + 0.01)
    assert np.allclose(flat.std(0), np.sqrt(np.diag(P)), rtol=0.1)


@pytest.mark.parametrize("d,seed", [(6, 0), (8, 1)])
def test_denominator_stops_early_without_losing_the_normaliser(d, seed):
    """proposal_se_ratio: the independent denominator draws stop once their error is half the numerator's;
    the estimate stays on the exact ln Z at a fraction of J, and ratio 0 draws all J."""
    S = correlated_cov(d, seed)
    m = np.random.default_rng(seed + 10).standard_normal(d)
    names = [f"p{i}" for i in range(d)]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=3.0) for n in names}), GaussianLoglik(m, S))
    exact = mvn(np.zeros(d), S + 9.0 * np.eye(d)).logpdf(m)
    # the plain random walk's autocorrelated numerator, which the early stop was designed against
    res = sample(target, CFG.model_copy(update={"jump_weight": 0.0, "min_ess": 0.0}), seed=seed)
    full = chib_jeliazkov(target, res, n_proposal=CFG.n_proposal, seed=seed + 1)
    early = chib_jeliazkov(target, res, n_proposal=CFG.n_proposal, seed=seed + 1, proposal_se_ratio=0.5)
    assert full.n_evaluations == CFG.n_chains * CFG.n_proposal
    assert early.n_evaluations <= CFG.n_chains * CFG.n_proposal // 2
    assert abs(early.log_evidence - exact) < 0.15
    assert early.log_evidence_se < 1.5 * full.log_evidence_se + 0.02


def regression_setup(seed=3, n=60, known_gamma=0.3):
    spec = builtin("polynomial").with_fixed(a3=0.0, a4=0.0, gamma=known_gamma)
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 2, n)
    y = 1.0 + 2.0 * x - 0.5 * x**2 + known_gamma * rng.standard_normal(n)
    data = Dataset(np.arange(n, dtype=float), {"x": x, "y": y})
    prior_sd = {"a0": 2.0, "a1": 3.0, "a2": 1.5}
    priors = {k: Normal(mean=0.0, sd=v) for k, v in prior_sd.items()}
    X = np.column_stack([np.ones(n), x, x**2])
    S0 = np.diag([v**2 for v in prior_sd.values()])
    exact = mvn(np.zeros(n), known_gamma**2 * np.eye(n) + X @ S0 @ X.T).logpdf(y)
    return ModelPosterior(spec, priors, data), exact


def test_conjugate_regression_laplace_exact_and_cj():
    target, exact = regression_setup()
    lap, xmap, C = laplace(target, np.zeros(3), np.ones(3))
    assert lap.log_evidence == pytest.approx(exact, rel=1e-8)
    res = sample(target, CFG, seed=5)
    ev = chib_jeliazkov(target, res, n_proposal=CFG.n_proposal, seed=6)
    assert abs(ev.log_evidence - exact) < 0.1
    assert ev.goodness_of_fit - ev.log_evidence == pytest.approx(ev.information_gain)


def test_linear_gaussian_state_space_cj_within_015_nats():
    spec = linear_gaussian_spec()
    n = 200
    t = np.arange(n) * 0.1
    rng = np.random.default_rng(11)
    u = np.sin(0.9 * t) + 0.5 * rng.standard_normal(n)
    from ardflow.ardcore.likelihood.simulate import simulate_model

    ds = simulate_model(spec, {"b1": 1.5, "b2": -0.4, "c": 0.3}, t, seed=12, nsub=20, inputs={"u": u})
    prior_mean, prior_sd = np.array([0.0, 0.0, 0.0]), np.array([2.0, 1.0, 1.0])
    priors = {k: Normal(mean=m, sd=s) for k, m, s in zip(["b1", "b2", "c"], prior_mean, prior_sd)}
    target = ModelPosterior(spec, priors, ds)
    exact = augmented_kalman([ds], LINEAR_SYSTEM, prior_mean, prior_sd)
    lap, _, _ = laplace(target, np.zeros(3), np.ones(3))
    assert lap.log_evidence == pytest.approx(exact, abs=1e-5)
    res = sample(target, CFG, seed=13)
    ev = chib_jeliazkov(target, res, n_proposal=CFG.n_proposal, seed=14)
    assert abs(ev.log_evidence - exact) < 0.15


def test_chains_in_different_modes_raise_a_warning():
    """Chains stuck in different modes give per-chain estimates that disagree: it must be reported."""
    from ardflow.ardcore.sampling.chains import ChainState, run_round
    from ardflow.ardcore.sampling.config import SamplerResult
    from ardflow.ardcore.sampling.adaptation import rhat

    from .targets import TwoModes

    names = ["p0", "p1"]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=100.0) for n in names}), TwoModes())
    cov = np.eye(2) * 2.38**2 / 2
    S, LP, LL, states = [], [], [], []
    for c, x0 in enumerate([[0.0, 0.0], [40.0, 0.0], [0.0, 0.0], [40.0, 0.0]]):
        lp, ll = target(np.array(x0))
        st = ChainState(c, x0, lp, ll, np.random.PCG64(c).state, x0, lp, ll)
        r = run_round(target, st, cov, 4000, adaptive=False)
        S.append(r.samples), LP.append(r.lp), LL.append(r.ll), states.append(r.state)
    best = max(states, key=lambda q: q.best_lp)
    res = SamplerResult(names, np.stack(S), np.stack(LP), np.stack(LL), np.array(best.best_x), best.best_lp,
                        best.best_ll, cov, states, rhat(S), [], 0, False, 0.3, 0.3, 0)
    ev = chib_jeliazkov(target, res, n_proposal=4000, seed=3)
    # the chains in the far mode put no proposal density at phi*: their estimates exceed max ln L
    assert any("impossible" in w for w in ev.warnings), ev.warnings
    assert len(ev.per_chain) == 2 and ev.log_evidence < best.best_ll
    # the same construction with all chains in one mode raises nothing
    res1 = SamplerResult(names, np.stack([S[0], S[2]]), np.stack([LP[0], LP[2]]), np.stack([LL[0], LL[2]]),
                         np.array(best.best_x), best.best_lp, best.best_ll, cov, states[:1], rhat(S), [], 0, True,
                         0.3, 0.3, 0)
    assert not chib_jeliazkov(target, res1, n_proposal=4000, seed=3).warnings


def test_sampler_crosses_modes_with_pooled_covariance():
    """INCA pools the between-chain spread, so chains started in two modes still mix (and R-hat says so)."""
    from .targets import TwoModes

    names = ["p0", "p1"]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=100.0) for n in names}), TwoModes(sep=12.0))
    starts = np.array([[0.0, 0.0], [12.0, 0.0], [0.0, 0.0], [12.0, 0.0]])
    cfg = SamplerConfig(n_chains=4, round_size=500, max_burnin_rounds=40, n_stationary=4000, n_proposal=2000)
    res = sample(target, cfg, seed=2, start=Start(points=starts))
    frac = (res.samples[:, :, 0] > 6).mean()
    assert 0.1 < frac < 0.3  # true mass of the second mode: 0.2


def test_chain_stuck_in_a_minor_mode_is_moved_and_evidence_is_exact():
    """A chain started in a mode with e^-30 of the mass is moved to the main one during burn-in."""
    from .targets import TwoModes

    names = ["p0", "p1"]
    w = 1 - math.exp(-30.0)
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=100.0) for n in names}), TwoModes(sep=40.0, w=w))
    exact = -math.log(2 * math.pi * (1e4 + 1)) + math.log(w)  # the minor mode adds e^-30 of the mass
    starts = np.array([[0.0, 0.0], [40.0, 0.0], [0.3, 0.0], [0.0, 0.3]])
    cfg = SamplerConfig(n_chains=4, round_size=500, max_burnin_rounds=12, n_stationary=4000, n_proposal=4000)
    notes = []
    res = sample(target, cfg, seed=5, start=Start(points=starts),
                 runtime=Runtime(progress=lambda p: notes.append(getattr(p, "message", None))))
    assert "burn-in round 1: chains [1]" in " ".join(filter(None, notes)), notes
    assert res.converged and not res.warnings, res.warnings
    assert (res.samples[:, :, 0] > 20).mean() == 0.0
    ev = chib_jeliazkov(target, res, n_proposal=cfg.n_proposal, seed=6)
    assert abs(ev.log_evidence - exact) < 0.15 and not ev.warnings, (ev.log_evidence, exact, ev.warnings)


def test_warm_laplace_reaches_the_cold_mode_of_a_skewed_posterior():
    """laplace(warm=True): Newton steps from a point several sd off, reusing a Hessian across steps (chord
    steps), end at the mode that the cold path (Nelder-Mead then Newton) finds on a non-Gaussian posterior,
    with the same ln Z; and on a Gaussian it is exact."""
    d = 5
    S = correlated_cov(d, 3)
    m = np.random.default_rng(13).standard_normal(d)
    names = [f"p{i}" for i in range(d)]
    prior = JointPrior(names, {n: Normal(sd=3.0) for n in names})
    gauss = FunctionTarget(names, prior, GaussianLoglik(m, S))
    exact = mvn(np.zeros(d), S + 9.0 * np.eye(d)).logpdf(m)
    sd = np.sqrt(np.diag(S))
    lap, _, _ = laplace(gauss, m + 3 * sd, warm=True)
    assert lap.log_evidence == pytest.approx(exact, abs=1e-6)

    class Skewed(GaussianLoglik):
        def __call__(self, x):
            z = np.asarray(x) - m
            return super().__call__(x) - 20 * np.sum(z ** 3) - 200 * np.sum(z ** 4)
    skew = FunctionTarget(names, prior, Skewed(m, S))
    cold, xc, Cc = laplace(skew, np.zeros(d), np.ones(d))
    warm, xw, Cw = laplace(skew, xc + 2 * np.sqrt(np.diag(Cc)), warm=True)
    assert np.allclose(xw, xc, atol=1e-3 * np.sqrt(np.diag(Cc)).min())
    assert warm.log_evidence == pytest.approx(cold.log_evidence, abs=1e-3)


def test_fd_derivatives_exact_on_a_quadratic_and_second_order_otherwise():
    """The d^2 + d + 1 point rule: f, gradient and Hessian exact on a correlated quadratic (up to rounding),
    and on a smooth non-quadratic the Hessian's error falls ~4x when the steps halve (second order)."""
    from ardflow.ardcore.sampling.starts import fd_derivatives

    d = 6
    A = np.linalg.inv(correlated_cov(d, 5))
    b = np.random.default_rng(5).standard_normal(d)
    x = np.random.default_rng(6).standard_normal(d)
    f0, g, H = fd_derivatives(lambda v: 0.5 * v @ A @ v - b @ v + 2.0, x, np.full(d, 0.1))
    assert f0 == pytest.approx(0.5 * x @ A @ x - b @ x + 2.0, rel=1e-12)
    assert np.allclose(g, A @ x - b, atol=1e-9) and np.allclose(H, A, atol=1e-8)

    def f(v):
        return float(np.sum(np.exp(0.3 * v)) + (v[0] * v[1]) ** 2 + np.sin(v[2] * v[3]))

    def exact(v):
        H = np.diag(0.09 * np.exp(0.3 * v))
        H[0, 0] += 2 * v[1] ** 2
        H[1, 1] += 2 * v[0] ** 2
        H[0, 1] = H[1, 0] = 4 * v[0] * v[1]
        s, c = np.sin(v[2] * v[3]), np.cos(v[2] * v[3])
        H[2, 2] += -s * v[3] ** 2
        H[3, 3] += -s * v[2] ** 2
        H[2, 3] = H[3, 2] = c - s * v[2] * v[3]
        return H

    errs = [np.abs(fd_derivatives(f, x, np.full(d, h))[2] - exact(x)).max() for h in (0.02, 0.01)]
    assert errs[1] < 0.3 * errs[0] and errs[1] < 1e-3


def test_a_mean_carried_by_one_batch_is_recognised():
    """The batch-means error of ln mean(exp(terms)): on well-mixed terms it matches the spread of repeated
    estimates; when one term carries the mean (a Chib-Jeliazkov ratio where one draw dominates) the delta
    method gives 1 nat whatever the truth, and the estimate is recognised as resting on one batch (the loop
    then takes it as no result)."""
    import numpy as np

    from ardflow.ardcore.evidence.estimators import _batch_se, dominated

    rng = np.random.default_rng(0)
    draws = [rng.normal(0.0, 0.5, 2000) for _ in range(200)]
    est = [np.log(np.mean(np.exp(d))) for d in draws]
    se = np.median([_batch_se(d) for d in draws])
    assert 0.6 * np.std(est) < se < 1.6 * np.std(est), (se, np.std(est))
    assert not any(dominated(d) for d in draws[:20])
    spiky = rng.normal(0.0, 0.5, 2000)
    spiky[1234] = 40.0
    assert dominated(spiky) and abs(_batch_se(spiky) - 1.0) < 1e-6


def _chains_from(target, start, cov, n=3000, chains=4):
    """Random-walk chains all started at ``start`` with the fixed proposal ``cov``, as a SamplerResult."""
    from ardflow.ardcore.sampling.adaptation import rhat
    from ardflow.ardcore.sampling.chains import ChainState, run_round
    from ardflow.ardcore.sampling.config import SamplerResult

    S, LP, LL, states = [], [], [], []
    for c in range(chains):
        lp, ll = target(np.array(start))
        st = ChainState(c, list(start), lp, ll, np.random.PCG64(c).state, list(start), lp, ll)
        r = run_round(target, st, cov, n, adaptive=False)
        S.append(r.samples), LP.append(r.lp), LL.append(r.ll), states.append(r.state)
    best = max(states, key=lambda q: q.best_lp)
    return SamplerResult(target.names, np.stack(S), np.stack(LP), np.stack(LL), np.array(best.best_x), best.best_lp,
                         best.best_ll, cov, states, rhat(S), [], 0, True, 0.3, 0.3, 0)


def test_collapsed_chains_are_caught_and_are_no_result():
    """Chains started at one point with a proposal far too small never leave a tiny neighbourhood: their spread
    is 10^4 times narrower than the posterior's. The evidence says so and the fit is no result; chains that
    describe the posterior raise nothing."""
    from ardflow.ardcore.evidence.estimators import COLLAPSED
    from ardflow.ardcore.selection.fit import ModelFit

    names = ["p0", "p1", "p2"]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=10.0) for n in names}),
                            GaussianLoglik(np.zeros(3), np.eye(3)))
    stuck = _chains_from(target, [0.3, -0.2, 0.1], np.eye(3) * 1e-10)
    assert stuck.samples.reshape(-1, 3).std(0).max() < 1e-3
    ev = chib_jeliazkov(target, stuck, n_proposal=1000, seed=3)
    bad = [w for w in ev.warnings if COLLAPSED in w]
    assert bad and all(n in bad[0] for n in names), ev.warnings
    fit = ModelFit(name="m", log_evidence=ev.log_evidence, log_evidence_se=max(ev.log_evidence_se, 0.1),
                   goodness_of_fit=0.0, information_gain=0.0, evidence_method="chib-jeliazkov",
                   sd={n: 1e-5 for n in names}, warnings=list(ev.warnings))
    assert fit.degenerate() and COLLAPSED in fit.degenerate()
    healthy = _chains_from(target, [0.3, -0.2, 0.1], np.eye(3) * 2.38 ** 2 / 3, n=6000)
    ev = chib_jeliazkov(target, healthy, n_proposal=1000, seed=3)
    assert not [w for w in ev.warnings if COLLAPSED in w], ev.warnings


class _Stairs:
    """A Gaussian log-likelihood with steps of up to ``eps`` nats as x0 crosses a grid ``step`` wide, far finer
    than the posterior: a likelihood rough at the scale of a finite-difference Hessian's steps, as a filter's is
    where sub-steps cross a kink."""

    def __init__(self, m, S, eps, step):
        self.g, self.eps, self.step = GaussianLoglik(m, S), eps, step

    def __call__(self, x):
        return self.g(x) + self.eps * ((math.floor(x[0] / self.step) * 7919) % 13) / 13


@pytest.mark.parametrize("frac", [0.003, 0.01, 0.03])
def test_laplace_on_a_likelihood_rough_at_its_steps_takes_the_posterior_s_own_curvature(frac):
    """Steps of 0.05 nats in the likelihood give a finite-difference curvature of any size and sign at the
    Hessian's steps (before, 22 of 24 such fits were 'collapsed' or 'not positive definite', no result, off by
    3-12 nats); over the posterior's width the curvature is the Gaussian's, and so is the evidence (within the
    roughness and the mode's uncertainty along it: 0.25 nats; 0.1 measured)."""
    d = 3
    for seed in range(8):
        S = correlated_cov(d, seed)
        m = np.random.default_rng(seed + 10).standard_normal(d) * 0.1
        names = [f"p{i}" for i in range(d)]
        target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=3.0) for n in names}),
                                _Stairs(m, S, 0.05, frac * math.sqrt(S[0, 0])))
        exact = mvn(np.zeros(d), S + 9 * np.eye(d)).logpdf(m)
        lap, _, C = laplace(target, np.zeros(d), np.ones(d))
        assert lap.warnings == [] and abs(lap.log_evidence - exact) < 0.25, (seed, lap.log_evidence - exact)
        P = np.linalg.inv(np.linalg.inv(S) + np.eye(d) / 9)
        assert np.allclose(np.sqrt(np.diag(C)), np.sqrt(np.diag(P)), rtol=0.25), (np.diag(C), np.diag(P))
