"""Every bench group runs: each at ``--tiny`` size in a subprocess, writing its contract keys as numbers (the
figures themselves measure nothing at this size)."""

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from .run import BENCHES, CONTRACT

ROOT = Path(__file__).resolve().parents[2]


def test_every_group_has_a_contract():
    assert set(CONTRACT) == set(BENCHES)


# `fresh` builds a venv and installs into it in a clean clone (as test_wheel does in the default suite): slow
@pytest.mark.parametrize("group", [pytest.param(g, marks=pytest.mark.slow) if g == "fresh" else g
                                   for g in sorted(BENCHES)])
def test_bench_group_runs_at_tiny_size(group, tmp_path):
    out = tmp_path / "results.json"
    r = subprocess.run([sys.executable, "-m", "tests.bench.run", "--tiny", "--only", group, "--out", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    res = json.loads(out.read_text())
    for key in CONTRACT[group]:
        assert key in res, f"{group}: {key} not written"
        assert isinstance(res[key], (int, float)) and not isinstance(res[key], bool), (key, res[key])
        assert math.isfinite(res[key]), (key, res[key])


def test_the_gate_grades_what_the_loop_did():
    """The regression gate's verdicts (tests.bench.validation): the planted family found beats nothing, which
    beats something else; on a clean record nothing is best; stand-ins that free-run the test better are as
    good as nothing only where the library cannot hold the truth; a simulated record is never graded as real."""
    import numpy as np

    from ardflow.ardcore.data import Dataset

    from .validation import _split, graded, verdict

    data = Dataset(np.arange(40.0), {"y": np.zeros(40)}, {})
    planted = _split("p", None, data, (True, False), "", ("cubic_stiffness", "form:power"))
    clean = _split("c", None, data, (False, False), "")
    hidden = _split("h", None, data, (True, False), "")
    assert not planted.real and planted.family == ("cubic_stiffness", "form:power")
    cubic, other = [{"effect": "cubic_stiffness(y)", "target": "v"}], [{"effect": "offset", "target": "v"}]
    assert verdict(planted, cubic, []) == "found" and verdict(planted, [], [{"form": "power"}]) == "found"
    assert verdict(planted, [], []) == "nothing" and verdict(planted, other, [], 1.0, 1.0) == "other"
    assert graded(planted, "found") > graded(planted, "nothing") > graded(planted, "other") > graded(planted, "failed")
    assert graded(clean, "nothing") > graded(clean, verdict(clean, other, [], 1.0, 0.5))
    assert verdict(hidden, other, [], 1.0, 0.5) == "stand-in" and graded(hidden, "stand-in") == graded(hidden, "nothing")
    assert graded(hidden, verdict(hidden, other, [], 1.0, 0.95)) < graded(hidden, "nothing")


def test_a_run_at_another_seed_is_no_gate_and_records_nothing(tmp_path):
    """``--seed`` runs the validation group with every study at that seed: it says how each record compares with
    what is recorded (``validation_worse_at_seed``) and never fails the gate, writes the verdicts or publishes; it
    is refused without ``--only validation`` and ``--out``."""
    from .run import VERDICTS, bench_validation, main

    with pytest.raises(SystemExit):
        main(["--only", "validation", "--tiny", "--records", "none", "--seed", "5"])  # no --out: it would publish
    with pytest.raises(SystemExit):
        main(["--only", "states", "--seed", "5", "--out", str(tmp_path / "x.json")])
    before = VERDICTS.read_text()
    got = bench_validation(tiny=True, records=["none"], seed=5)
    assert got["validation_seed"] == 5 and isinstance(got["validation_worse_at_seed"], list)
    assert "validation_regressions" not in got and "loop_none_verdict" in got
    assert VERDICTS.read_text() == before


def test_the_heated_body_s_truth_is_the_physics_its_record_is_made_of():
    """The band's truth for the heated body (a declared model) and the loop that makes its record
    (:func:`validation.heated_drift`) are written apart: their drifts agree wherever the record goes."""
    import numpy as np
    import sympy as sp

    from ardflow.ardcore.model.expr import parse_expression

    from .validation import _heated_truth, heated_drift

    spec, values = _heated_truth()
    names = {*spec.states, *spec.inputs, *spec.parameters, *spec.constants}
    f = sp.lambdify([sp.Symbol(n, real=True) for n in ("T", "u", *values)],
                    parse_expression(spec.drift["T"], names), modules="numpy")
    T, u = np.meshgrid(np.linspace(280.0, 420.0, 15), np.linspace(0.0, 100.0, 11))
    assert np.allclose(f(T, u, *values.values()), heated_drift(T, u), rtol=1e-12, atol=1e-15)
