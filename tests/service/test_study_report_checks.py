"""The study report warns when its own checks fail: a true value outside its 99 % bounds, innovations whose
standardised RMS is far from 1."""

from __future__ import annotations

import re

import numpy as np

from ardflow.service.reports.study import INNOVATION_RMS_RANGE, self_checks


def test_true_value_outside_bounds_and_miscalibrated_innovations_are_warned():
    rng = np.random.default_rng(0)
    samples = rng.normal(size=(4, 2000, 2))  # two parameters, each N(0, 1): 99 % bounds about +-2.6
    white = (rng.normal(size=5000), np.ones(5000))
    assert self_checks(["a", "b"], samples, {"a": 0.5, "b": -1.0}, white) == []
    w = self_checks(["a", "b"], samples, {"a": 0.5, "b": 4.0}, white)
    assert len(w) == 1 and w[0].startswith("the true b = 4 is outside")
    # the filter's variances four times too large: standardised RMS 0.5, outside the range
    assert INNOVATION_RMS_RANGE[0] > 0.5
    rms = float(np.sqrt(np.mean(white[0] ** 2)))
    for scale in (4.0, 0.25):
        w = self_checks(["a"], samples[..., :1], {}, (white[0], scale * white[1]))
        assert len(w) == 1 and float(re.search(r"RMS ([0-9.]+) ", w[0]).group(1)) == round(rms / np.sqrt(scale), 2)
    w = self_checks(["a"], samples[..., :1], {}, ValueError("no filter"))
    assert w == ["the innovations could not be computed (ValueError: no filter)"]
