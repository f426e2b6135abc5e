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
