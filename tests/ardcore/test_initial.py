"""The initial-state prior is re-centred on a record that contradicts it, and only then."""

import numpy as np
import pytest

from ardflow.ardcore.data import Dataset
from ardflow.ardcore.selection.initial import data_informed_initial, recentred
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.selection.spec import CandidateSpec


def _record(y0, v0, n=200, dt=0.01, w=3.0):
    t = np.arange(n) * dt
    y = y0 * np.cos(w * t) + v0 / w * np.sin(w * t)
    return Dataset(t, {"y": y, "u": np.zeros(n)})


def test_consistent_start_is_left_alone():
    ms = builtin("forced_linear_oscillator")  # y ~ N(0, 0.1^2), v ~ N(0, 10^2)
    out, notes = recentred(ms, _record(0.05, 1.0))
    assert notes == [] and out is ms


def test_start_far_from_the_declared_prior_is_recentred():
    ms = builtin("forced_linear_oscillator")
    out, notes = recentred(ms, _record(-50.0, 400.0))
    assert len(notes) == 2 and notes[0].startswith("initial y") and notes[1].startswith("initial v")
    assert float(out.initial_mean["y"]) == pytest.approx(-50.0)
    assert float(out.initial_std["y"]) >= 0.1  # never narrowed
    # the slope of the first samples: y' = v
    assert float(out.initial_mean["v"]) == pytest.approx(400.0, rel=0.05)
    assert float(out.initial_std["v"]) >= 10.0
    assert out.structure_hash() != ms.structure_hash()


def test_candidate_keeps_its_fixed_parameters_and_constants():
    cand = CandidateSpec(model="forced_linear_oscillator", constants={"gamma": 0.5}, fixed={"b": 0.0},
                         priors={"k": {"kind": "lognormal", "median": 9.0, "cov": 100},
                                 "c": {"kind": "lognormal", "median": 0.3, "cov": 100},
                                 "sigma": {"kind": "lognormal", "median": 0.3, "cov": 100}})
    new, notes = data_informed_initial(cand, _record(-50.0, 0.0))
    ms = new.model_spec()
    assert notes and "b" not in ms.free_parameters and float(ms.constants["gamma"]) == 0.5
    assert float(ms.initial_mean["y"]) == pytest.approx(-50.0)
