"""The INCA coordinator state machine (sans-IO): idempotent reports, checkpoint round trip."""

import json

import numpy as np

from ardflow.ardcore.sampling.adaptation import AdaptationPool, rhat
from ardflow.ardcore.sampling.chains import RoundStats


def halves_of(x):
    h = x.shape[0] // 2
    return RoundStats.of(x[:h]), RoundStats.of(x[h:])


def test_commit_waits_for_every_chain_and_is_idempotent():
    rng = np.random.default_rng(0)
    pool = AdaptationPool(3, 2, np.eye(2), min_rounds=1)
    rounds = [[rng.standard_normal((100, 2)) for _ in range(3)] for _ in range(4)]
    for r, per_chain in enumerate(rounds, start=1):
        for c, x in enumerate(per_chain):
            committed = pool.report(c, r, halves_of(x), (x[0].tolist(), -float(c), 0.0))
            assert committed == (c == 2)
            assert pool.report(c, r, halves_of(x), None) == (c == 2)  # a re-run task reports again
        assert pool.rounds == r
    # R-hat from statistics equals R-hat from the samples (latter half of rounds, split)
    keep = 4 - 4 // 2
    direct = rhat([np.concatenate([rounds[r][c] for r in range(4 - keep, 4)]) for c in range(3)])
    assert np.allclose(pool.rhat(), direct)
    # pooled covariance: 2.38^2/d times the sample covariance of the window
    allx = np.concatenate([rounds[r][c] for r in range(4 - keep, 4) for c in range(3)])
    assert np.allclose(pool.cov, 2.38**2 / 2 * np.cov(allx.T), rtol=1e-6)
    assert pool.best[1] == 0.0


def test_checkpoint_round_trip():
    rng = np.random.default_rng(1)
    pool = AdaptationPool(2, 3, np.eye(3), min_rounds=2)
    for r in (1, 2):
        for c in range(2):
            pool.report(c, r, halves_of(rng.standard_normal((50, 3))), None)
    back = AdaptationPool.from_dict(json.loads(json.dumps(pool.to_dict())))
    assert back.rounds == 2 and np.allclose(back.cov, pool.cov) and np.allclose(back.rhat(), pool.rhat())
    x = rng.standard_normal((50, 3))
    for p in (pool, back):
        p.report(0, 3, halves_of(x), None)
        p.report(1, 3, halves_of(x + 1), None)
    assert np.allclose(back.cov, pool.cov)


def test_sampler_resumes_exactly_from_any_checkpoint():
    import copy

    from ardflow.ardcore.sampling.config import SamplerConfig
    from ardflow.ardcore.sampling.driver import Runtime, Start, sample
    from ardflow.ardcore.likelihood.posterior import FunctionTarget
    from ardflow.ardcore.model.priors import JointPrior, Normal

    from .targets import GaussianLoglik, correlated_cov

    d = 3
    names = [f"p{i}" for i in range(d)]
    target = FunctionTarget(names, JointPrior(names, {n: Normal(sd=10.0) for n in names}),
                            GaussianLoglik(np.zeros(d), correlated_cov(d, 0, 1.0)))
    # stationary tasks of four 50-draw rounds: a checkpoint between the stage's two tasks
    cfg = SamplerConfig(n_chains=3, round_size=50, n_stationary=400, n_proposal=50)
    cks = []
    full = sample(target, cfg, seed=4,
                  runtime=Runtime(checkpoint=lambda ck: cks.append(copy.deepcopy(json.loads(json.dumps(ck))))))
    stages = [c["stage"] for c in cks]
    assert "burnin" in stages and "stationary" in stages
    first = stages.index("stationary")
    assert cks[first]["done"] < cks[first]["goal"]  # resumed mid-stage, not at its end
    # every checkpoint, the last burn-in round's too (whose resume once drew one burn-in round more)
    for k in range(len(cks)):
        ck = dict(cks[k])
        if ck["stage"] == "stationary":
            ck.update(samples=full.samples, lp=full.lp, ll=full.ll)  # what the store holds (only :done is used)
        again = sample(target, cfg, seed=4, start=Start(resume=ck))
        assert np.array_equal(again.samples, full.samples)
        assert again.lp_star == full.lp_star and again.burnin_rounds == full.burnin_rounds


def test_outlier_chain_is_dropped_from_the_pool_and_moved():
    rng = np.random.default_rng(0)
    stats = lambda mu: (RoundStats.of(mu + rng.standard_normal((50, 2))),  # noqa: E731
                        RoundStats.of(mu + rng.standard_normal((50, 2))))
    for nats, moved in ((10.0, {2: 1}), (0.0, {})):
        pool = AdaptationPool(3, 2, np.eye(2), outlier_nats=nats)
        levels = [-3.0, -2.5, -40.0]
        for c in range(3):
            pool.report(c, 1, stats(np.zeros(2) if c < 2 else np.full(2, 50.0)), ([0.0, 0.0], levels[c], 0.0,
                                                                                  levels[c]))
        assert pool.moved(1) == moved
        assert (len(pool.halves[2]) == 0) == bool(moved)
        # with the far chain dropped the pooled covariance is the within-mode one, not the between-mode spread
        assert (np.max(np.diag(pool.cov)) < 10) == bool(moved)
        assert AdaptationPool.from_dict(pool.to_dict()).moved(1) == moved
