"""What makes the state families cheap on a long record, each against the exact thing it replaces: a search on the
record's first samples, a screen on the move's own kernel with the current model's values held, and a fit from the
prior whose start searches run on the pool before it."""

import numpy as np
import pytest

from ardflow.ardcore.data import join_records
from ardflow.ardcore.likelihood.posterior import ModelPosterior
from ardflow.ardcore.model.priors import JointPrior


@pytest.fixture(scope="module")
def record():
    from tests.bench.validation import RECORDS

    rec = RECORDS["sensor_lag"](n=6000)  # 3,000 estimation samples
    return rec, rec.spec.models[0]


def _posterior(cand, data):
    return ModelPosterior(cand.model_spec(), dict(cand.priors), data, cand.substeps)


def _median(target):
    return np.array([p.quantile(0.5) for p in target.prior.priors])


def test_a_window_is_the_posterior_of_the_record_s_first_samples(record):
    """A window of n samples evaluates what a posterior built on the first n samples evaluates, to the bit; no
    window, one longer than the record, or a record of several experiments leaves the posterior as it is."""
    rec, cand = record
    full = _posterior(cand, rec.est)
    x = _median(full)
    w = full.window(1000)
    assert len(w.data) == 1000 and len(full.data) == len(rec.est)  # the original keeps its record
    assert w(x) == _posterior(cand, rec.est.slice(0, 1000))(x)
    assert w(x) != full(x)
    assert full.window(None) is full and full.window(len(rec.est)) is full
    two = _posterior(cand, join_records([rec.est.slice(0, 1500), rec.est.slice(1500, None)]))
    assert two.window(1000) is two


def test_a_held_target_is_the_move_with_the_current_values_fixed_in_it(record):
    """The screen's target (the move's own kernel, the current model's parameters held at given values) is the
    posterior of the model with those values fixed in its spec, over the others alone: the same prior and, to
    rounding, the same likelihood."""
    from ardflow.ardcore.screening.states import Conditional

    rec, cand = record
    names = cand.model_spec().free_parameters
    known = {n: p.quantile(0.5) * 1.1 for n, p in zip(names, _posterior(cand, rec.est).prior.priors)}
    new = [names[0], names[2]]
    for n in new:
        known.pop(n)
    held = Conditional(cand, known, new).target(rec.est)
    fixed = cand.model_copy(update={"priors": {n: cand.priors[n] for n in new}, "fixed": {**cand.fixed, **known}})
    ref = _posterior(fixed, rec.est)
    assert held.names == ref.names == new
    assert isinstance(held.prior, JointPrior)
    for x in (_median(ref), _median(ref) * 0.8):
        (lp, ll), (lp_ref, ll_ref) = held(x), ref(x)
        assert ll == pytest.approx(ll_ref, rel=1e-10, abs=1e-8) and lp - ll == pytest.approx(lp_ref - ll_ref)
    assert held.window(500).full.data.t.size == 500 and held.full.data.t.size == len(rec.est)


def test_a_move_on_a_model_that_fixed_a_term_is_screened_with_that_term_fixed(record):
    """A term an earlier round dropped (fixed at 0, its prior still declared) is neither held nor sampled: the
    move is screened on the model as it stands, as the loop's later rounds need."""
    from ardflow.ardcore.screening.states import conditional

    rec, cand = record
    names = cand.model_spec().free_parameters
    dropped = cand.model_copy(update={"fixed": {**cand.fixed, names[1]: 0.0}})
    known = {n: 1.0 for n in names[2:]}
    c = conditional(dropped, known)
    assert c is not None and c.new == [names[0]] and set(c.known) == set(names[2:])
    target = c.target(rec.est)
    x = np.array([1.0])
    ref = _posterior(dropped.model_copy(update={"priors": {names[0]: cand.priors[names[0]]},
                                                  "fixed": {**dropped.fixed, **known}}), rec.est)
    assert target(x).log_likelihood == pytest.approx(ref(x).log_likelihood, rel=1e-10)
    assert conditional(cand, {n: 1.0 for n in names}) is None  # nothing new to sample


def test_a_fit_from_the_prior_with_its_searches_on_a_window_reaches_the_same_evidence(record):
    """A Laplace fit from the prior whose start searches read 1,000 of the record's 3,000 samples ends where the
    one whose searches read all of them ends: its Newton steps and its evidence read the whole record."""
    from ardflow.ardcore.selection.study import run_candidate

    rec, cand = record
    whole, _ = run_candidate(cand, rec.est, rec.spec, 0, final_posterior="laplace")
    spec = rec.spec.model_copy(update={"sampler": rec.spec.sampler.model_copy(update={"search_window": 1000})})
    windowed, _ = run_candidate(cand, rec.est, spec, 0, final_posterior="laplace")
    assert windowed.log_evidence == pytest.approx(whole.log_evidence, abs=1e-3)
    for n, v in whole.map.items():
        assert windowed.map[n] == pytest.approx(v, rel=1e-4, abs=1e-6 * whole.sd[n]), n


def test_fits_whose_start_searches_ran_on_the_pool_first_are_the_fits(record):
    """:func:`fit_all` on a real two-process pool (a fit from the prior and a warm one) gives what each fit run
    whole in one process gives, to the bit; a fit whose first batch differs from the results handed to it is an
    error, never a fit from someone else's searches."""
    from ardflow.ardcore.loop.confirm import Answered, fit_all, fit_task, pool_mapper

    rec, cand = record
    data = rec.est.slice(0, 1500)
    cold = (cand, data, rec.spec, None, "laplace")
    row, mr = fit_task(cold)
    warm = (cand, data, rec.spec, mr.sampler, "laplace")
    alone = [fit_task(t) for t in (warm, cold)]
    mapper, close = pool_mapper(2)
    try:
        pooled = fit_all(mapper, [warm, cold])
    finally:
        close()
    for (a, _), (b, _) in zip(alone, pooled):
        assert a.log_evidence == b.log_evidence and a.map == b.map and a.sd == b.sd
    with pytest.raises(RuntimeError, match="first batch"):
        Answered([1, 2])(abs, [1, 2, 3])
    assert Answered([7])(abs, [-1]) == [7] and Answered(None)(abs, [-1]) == [1]


def test_newton_steps_with_a_window_s_curvature_reach_the_record_s_mode_on_fewer_record_evaluations(record):
    """Laplace's Newton steps with the curvature of the record's first 1,000 samples scaled to its 3,000
    (:func:`record_curvature`) end at the evidence and the mode the steps with the record's own Hessians end at,
    from a warm start and from a search, and read the whole record fewer times from the search (with 4
    parameters a Hessian costs 2.3 gradients: from a warm start they read it no more often; the saving grows with
    the parameters' count, ``make bench --only loop``'s loop_silverbox_s)."""
    from ardflow.ardcore.evidence.laplace import laplace, record_curvature
    from ardflow.ardcore.sampling.starts import initial_scale

    rec, cand = record
    reads: dict[int, int] = {}

    class Counted(ModelPosterior):
        def __call__(self, x):
            reads[len(self.data)] = reads.get(len(self.data), 0) + 1
            return super().__call__(x)

    full = Counted(cand.model_spec(), dict(cand.priors), rec.est, cand.substeps)
    n = len(rec.est)
    assert record_curvature(full, full) is None and record_curvature(full, full.window(n)) is None
    ref, x_ref, C_ref = laplace(full, _median(full), initial_scale(full.prior))
    start = x_ref + 0.5 * np.sqrt(np.diag(C_ref))  # half an sd off in every coordinate: a warm start
    for warm, x0 in ((False, _median(full)), (True, start)):
        reads.clear()
        plain, x_plain, _ = laplace(full, x0, initial_scale(full.prior), warm=warm)
        whole = reads.pop(n)
        windowed, x_win, C = laplace(full, x0, initial_scale(full.prior), warm=warm, search=full.window(1000))
        assert reads[1000] > 0 and reads[n] <= (whole if warm else 0.75 * whole), (warm, reads, whole)
        assert windowed.log_evidence == pytest.approx(plain.log_evidence, abs=1e-3)
        np.testing.assert_allclose(x_win, x_plain, atol=1e-2 * np.sqrt(np.diag(C)).min())
