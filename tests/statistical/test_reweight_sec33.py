"""Reweighted trials of the Section 3.3 study against full Chib-Jeliazkov evaluations at the same psi (slow)."""

import math
from pathlib import Path

import numpy as np
import pytest

from ardflow.ardcore.evidence.evaluate import EvidenceEvaluator, EvidenceSettings
from ardflow.ardcore.selection.spec import load_spec
from ardflow.ardcore.selection.study import run_candidate

pytestmark = [pytest.mark.slow, pytest.mark.timeout(3600)]

ROOT = Path(__file__).resolve().parents[2]


def test_reweighted_evidence_matches_a_sampled_trial_at_the_same_psi():
    spec = load_spec(ROOT / "examples" / "sec33.json")
    spec = spec.model_copy(update={"sampler": spec.sampler.model_copy(
        update={"n_stationary": 1500, "n_proposal": 1500, "round_size": 250})})
    data = spec.data.load(ROOT / "examples")
    cand = spec.models[0]
    row, mr = run_candidate(cand, data, spec, 0)
    reweighted = [t for t in mr.history if not t.sampled]
    assert reweighted, [t.action for t in mr.history]
    assert mr.best.sampled and row.log_evidence == mr.best.evidence.log_evidence
    ev = EvidenceEvaluator(cand.model_spec(), dict(cand.priors), data, EvidenceSettings(spec.sampler),
                           substeps=cand.substeps)
    # the reweighted steps nearest the optimum (where the weights are least even) and the first one
    picks = sorted(reweighted, key=lambda t: -t.iteration)[:2] + [reweighted[0]]
    for t in picks:
        _, full, _ = ev(t.psi, seed=977 + t.iteration, warm=mr.sampler)
        se = math.hypot(t.evidence.log_evidence_se, full.log_evidence_se)
        print(f"\n{t.action}: reweighted {t.evidence.log_evidence:.3f} +- {t.evidence.log_evidence_se:.3f} "
              f"(ESS {t.diagnostics['ess']:.0f}), sampled {full.log_evidence:.3f} +- {full.log_evidence_se:.3f}")
        assert abs(t.evidence.log_evidence - full.log_evidence) < 2 * se + 0.05
    n_sampled = sum(t.sampled for t in mr.history)
    print(f"sampled {n_sampled} of {len(mr.history)} trials; {row.n_evaluations} likelihood evaluations")
    assert np.isfinite(row.n_evaluations) and row.n_evaluations > 0
