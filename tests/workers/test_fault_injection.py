"""Random kills of a study's driver: every resumed study ends with the uninterrupted summary, and no torn
file is left behind (slow: 20 kills at seeded random points)."""

import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ardflow.ardcore.selection.spec import load_spec
from ardflow.ardcore.selection.study import select

SPEC = Path(__file__).with_name("small_study.json")
ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.slow


def _json_files_whole(store: Path) -> list[str]:
    """Every JSON document of the store that does not parse (zarr metadata, attributes, progress lines)."""
    torn = []
    for p in store.rglob("*.json"):
        try:
            json.loads(p.read_text())
        except (ValueError, UnicodeDecodeError):
            torn.append(str(p.relative_to(store)))
    for p in store.rglob("*.jsonl"):
        for i, line in enumerate(p.read_text().splitlines()):
            try:
                json.loads(line)
            except ValueError:
                torn.append(f"{p.relative_to(store)}:{i + 1}")
    return torn


def test_driver_killed_at_random_points_resumes_to_the_same_summary(tmp_path):
    ref = {r["name"]: r for r in select(load_spec(SPEC))["models"]}
    rng = random.Random(2026)
    env = dict(os.environ)
    kills = 0

    def start(out: Path) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "ardflow.service.cli", "select", str(SPEC), "--out", str(out),
                                 "--executor", "serial"], cwd=ROOT, env=env, stdout=subprocess.DEVNULL,
                                stderr=subprocess.DEVNULL, start_new_session=True)

    # the kills land over the run's own length on this machine (a faster sampler must not make them miss)
    t0 = time.perf_counter()
    assert start(tmp_path / "whole").wait(timeout=600) == 0
    whole = time.perf_counter() - t0
    for trial in range(20):
        out = tmp_path / f"st{trial}"
        p = start(out)
        time.sleep(rng.uniform(0.15, 0.9) * whole)  # the start-up, the store's creation or any trial
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            kills += 1
        p.wait()
        if not (out / "zarr.json").exists():
            continue  # killed before the store existed: nothing to resume
        r = subprocess.run([sys.executable, "-m", "ardflow.service.cli", "resume", str(out), "--workers", "1"],
                           cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, (trial, r.stdout[-2000:], r.stderr[-2000:])
        got = {m["name"]: m for m in json.loads((out / "summary.json").read_text())["models"]}
        for k, m in got.items():
            assert m["log_evidence"] == pytest.approx(ref[k]["log_evidence"], abs=1e-9), (trial, k)
            assert m["psi_opt"] == ref[k]["psi_opt"] and m["mean"] == pytest.approx(ref[k]["mean"], abs=1e-12)
        assert not _json_files_whole(out), (trial, _json_files_whole(out))
    assert kills >= 15  # most kills landed while the study ran
