"""Reweighting between ARD trials (ardcore.evidence.reweight) against exact evidence: a conjugate polynomial
regression, where ln Z at every psi is known in closed form."""

import math

import numpy as np
import pytest

from ardflow.ardcore.selection.maximiser import INF, maximise
from ardflow.ardcore.evidence.evaluate import EvidenceEvaluator, EvidenceSettings
from ardflow.ardcore.selection.config import MaximiserConfig
from ardflow.ardcore.data import Dataset
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.sampling.config import SamplerConfig
from ardflow.ardcore.model.priors import Normal
from ardflow.ardcore.evidence.reweight import reweight

GAMMA = 0.3
ESSENTIAL = {"a0": 2.0, "a1": 3.0}
ARD_TERMS = ["a2", "a3", "a4"]


def setup(seed=3, n=80):
    spec = builtin("polynomial").with_fixed(gamma=GAMMA)
    rng = np.random.default_rng(seed)
    x = np.linspace(0, 2, n)
    y = 1.0 + 2.0 * x - 0.5 * x ** 2 + GAMMA * rng.standard_normal(n)  # a3 = a4 = 0: ARD should prune them
    data = Dataset(np.arange(n, dtype=float), {"x": x, "y": y})
    X = np.column_stack([x ** k for k in range(5)])

    def exact(psi):
        keep = [0, 1] + [2 + i for i, k in enumerate(ARD_TERMS) if psi[k] != INF]
        var = [ESSENTIAL["a0"] ** 2, ESSENTIAL["a1"] ** 2] + [1 / psi[k] for k in ARD_TERMS if psi[k] != INF]
        Xk = X[:, keep]
        # ln N(y; 0, g^2 I + X S X') by the posterior identity (stable for the wide priors of small alpha)
        A = np.diag(1 / np.asarray(var)) + Xk.T @ Xk / GAMMA ** 2
        b = Xk.T @ y / GAMMA ** 2
        _, logdet_A = np.linalg.slogdet(A)
        return float(-0.5 * (n * math.log(2 * math.pi * GAMMA ** 2) + logdet_A + np.sum(np.log(var))
                             + y @ y / GAMMA ** 2 - b @ np.linalg.solve(A, b)))
    return spec, data, X, y, exact


def posterior_draws(X, y, psi, n, seed):
    """Exact posterior draws of (a0..a4) at psi (all terms on)."""
    prec = np.diag([1 / ESSENTIAL["a0"] ** 2, 1 / ESSENTIAL["a1"] ** 2] + [psi[k] for k in ARD_TERMS])
    P = np.linalg.inv(prec + X.T @ X / GAMMA ** 2)
    m = P @ X.T @ y / GAMMA ** 2
    return np.random.default_rng(seed).multivariate_normal(m, P, size=n)


@pytest.mark.parametrize("seed", [0, 1])
def test_reweighted_log_ratio_matches_the_exact_one(seed):
    _, _, X, y, exact = setup()
    psi = {"a2": 1e-4, "a3": 1e-4, "a4": 1e-4}
    draws = posterior_draws(X, y, psi, 4 * 2000, seed).reshape(4, 2000, 5)
    names = ["a0", "a1", "a2", "a3", "a4"]
    for new in ({"a4": 1e-2}, {"a4": 1.0, "a3": 1e-2}, {"a3": 10.0}, {"a2": 0.1}):
        to = dict(psi, **new)
        rw = reweight(names, draws, psi, to)
        truth = exact(to) - exact(psi)
        assert abs(rw.log_ratio - truth) < 4 * rw.se + 0.01, (new, rw, truth)
    # far steps spread the weights: the effective sample size falls with the step
    ess = [reweight(names, draws, psi, dict(psi, a3=a)).ess for a in (1e-2, 1.0, 1e2, 1e4)]
    assert all(a > b for a, b in zip(ess, ess[1:])), ess
    # reweighting does not apply to switching a term off, or from a flat prior
    assert reweight(names, draws, psi, dict(psi, a3=INF)) is None
    assert reweight(names, draws, dict(psi, a3=0.0), psi) is None


def test_maximiser_reweights_steps_and_every_reported_evidence_is_right():
    spec, data, _, _, exact = setup()
    cfg = SamplerConfig(n_chains=4, round_size=250, n_stationary=1500, n_proposal=1500, start_maxfev=400)
    essential = {k: Normal(mean=0.0, sd=v) for k, v in ESSENTIAL.items()}
    mcfg = MaximiserConfig(alpha_start=1e-6, step_decades=2, min_step_decades=2, max_sweeps=1)
    out = {}
    for rw in (True, False):
        ev = EvidenceEvaluator(spec, essential, data, EvidenceSettings(cfg))
        out[rw] = maximise(ev, {k: None for k in ARD_TERMS}, MaximiserConfig(**{**mcfg.__dict__, "reweight": rw}),
                           seed=11)
    on, off = out[True], out[False]
    assert on.psi_opt["a3"] == INF and on.psi_opt["a4"] == INF and on.psi_opt["a2"] != INF
    assert on.pruned == off.pruned
    sampled = [t for t in on.history if t.sampled]
    reweighted = [t for t in on.history if not t.sampled]
    assert reweighted and len(sampled) < len([t for t in off.history])
    assert on.best.sampled  # the optimum is always a sampled trial
    # every estimate the history reports is within 3 se of the exact ln Z (se: CJ's, and the reweighting's); a
    # prune test decided by the likelihood bound reports a bound: at or above the exact ln Z of the nested model,
    # and below the optimum's by more than the test's margin (the sampled test would have kept the term too)
    for t in on.history:
        if t.bound:
            assert exact(t.psi) <= t.evidence.log_evidence + 1e-6, (t.action, t.evidence.log_evidence, exact(t.psi))
            assert exact(on.psi_opt) - exact(t.psi) > mcfg.keep_nats, t.action
            continue
        assert abs(t.evidence.log_evidence - exact(t.psi)) < 3 * t.evidence.log_evidence_se + 0.15, \
            (t.action, t.evidence.log_evidence, exact(t.psi), t.evidence.log_evidence_se)
    print(f"\nsampled trials {len(sampled)} (+{len(reweighted)} reweighted) vs {len(off.history)} without reweighting")



def test_a_prune_test_the_likelihood_bound_decides_changes_nothing_else():
    """On the conjugate regression a2 is worth tens of nats: its prune test is decided by the bound on the nested
    model's ln Z, which is at or above the exact value. Every other trial is the one the fully sampled run makes
    (the same seeds, draws and estimates), the optimum and its evidence are identical, and the bound costs a
    fraction of the chains it replaced."""
    spec, data, _, _, exact = setup()
    cfg = SamplerConfig(n_chains=4, round_size=250, n_stationary=1000, n_proposal=1000, start_maxfev=400)
    essential = {k: Normal(mean=0.0, sd=v) for k, v in ESSENTIAL.items()}
    runs = {}
    for bound in (True, False):
        ev = EvidenceEvaluator(spec, essential, data, EvidenceSettings(cfg))
        runs[bound] = maximise(ev, {k: None for k in ARD_TERMS},
                               MaximiserConfig(alpha_start=1e-6, step_decades=2, min_step_decades=2, max_sweeps=1,
                                               prune_bound=bound), seed=11)
    on, off = runs[True], runs[False]
    decided = [t for t in on.history if t.bound]
    assert [t.action.split(":")[0] for t in decided] == ["a2"], [t.action for t in on.history]
    assert exact(decided[0].psi) <= decided[0].evidence.log_evidence
    assert on.psi_opt == off.psi_opt and on.best.evidence.log_evidence == off.best.evidence.log_evidence
    same = {t.iteration: t.evidence.log_evidence for t in on.history if not t.bound}
    assert same == {t.iteration: t.evidence.log_evidence for t in off.history if t.iteration in same}
    replaced = next(t for t in off.history if t.iteration == decided[0].iteration)
    assert replaced.evidence.log_evidence < on.best.evidence.log_evidence - 10  # the sampled test lost by far
    cost = decided[0].diagnostics["n_evaluations"]
    assert cost < 0.25 * replaced.diagnostics["n_evaluations"], (cost, replaced.diagnostics["n_evaluations"])


def test_prune_test_warm_start_is_the_exact_conditional():
    """A prune test fixes a term at 0; its posterior is the previous one conditioned there. On the conjugate
    regression both are Gaussian, so the warm start's proposal must be the nested posterior's covariance
    (scaled 2.38^2 / d) and the moved draws must be draws of the nested posterior."""
    from types import SimpleNamespace

    from ardflow.ardcore.evidence.evaluate import build_target
    from ardflow.ardcore.sampling.starts import initial_scale, warm_positions

    spec, data, X, y, _ = setup()
    psi = {"a2": 1e-2, "a3": 1e-2, "a4": 1e-2}
    names = ["a0", "a1", "a2", "a3", "a4"]
    prec = np.diag([1 / ESSENTIAL["a0"] ** 2, 1 / ESSENTIAL["a1"] ** 2] + [psi[k] for k in ARD_TERMS])
    P = np.linalg.inv(prec + X.T @ X / GAMMA ** 2)
    draws = posterior_draws(X, y, psi, 20000, seed=5)
    warm = SimpleNamespace(names=names, states=[SimpleNamespace(x=list(d)) for d in draws], phi_star=draws[0],
                           proposal_cov=(2.38 ** 2 / 5) * P)
    essential = {k: Normal(mean=0.0, sd=v) for k, v in ESSENTIAL.items()}
    target = build_target(spec, essential, dict(psi, a4=INF), data)
    assert target.names == names[:4]
    pos, _, cov = warm_positions(target, warm, initial_scale(target.prior))
    keep = slice(0, 4)
    nested_P = np.linalg.inv(prec[keep, keep] + X[:, keep].T @ X[:, keep] / GAMMA ** 2)
    nested_m = nested_P @ X[:, keep].T @ y / GAMMA ** 2
    np.testing.assert_allclose(cov, (2.38 ** 2 / 4) * nested_P, rtol=1e-8, atol=1e-14)
    pos = np.array(pos)
    se = np.sqrt(np.diag(nested_P) / pos.shape[0])
    assert np.all(np.abs(pos.mean(axis=0) - nested_m) < 5 * se)
    np.testing.assert_allclose(np.cov(pos.T), nested_P, rtol=0.1, atol=1e-12)
    # the marginal (what the warm start took before) is measurably off the nested posterior
    assert np.max(np.abs(draws[:, :4].mean(axis=0) - nested_m) / se) > 5
