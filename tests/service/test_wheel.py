"""The built wheel, installed into a fresh venv outside the repository, is a working tool.

The fresh venv gets its third-party dependencies from this test environment's site-packages
(a directory of links that leaves out every ``ardflow`` entry, so only the wheel provides
ardflow), which keeps the test offline and fast; the wheel itself is installed by pip.
"""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
import sysconfig
import time
import venv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
SMALL = ROOT / "tests" / "workers" / "small_study.json"


@pytest.fixture(scope="module")
def fresh(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    # built from a copy of the sources: setuptools writes build/ and *.egg-info beside what it builds
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("ardcore", "workers", "service", "examples"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
                        "-w", str(tmp / "dist"), str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    # a packaging warning (a data folder absent from `packages`) is what `make demo` shows a new user first
    assert "warning" not in (r.stdout + r.stderr).lower(), (r.stdout + r.stderr)[-3000:]
    wheel = next((tmp / "dist").glob("ardflow-*.whl"))
    env_dir = tmp / "venv"
    venv.create(env_dir, with_pip=False)
    py = env_dir / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    deps = tmp / "deps"
    deps.mkdir()
    ours = ("ardflow", "__editable__", "_ardflow", "ardcore", "workers", "service", "tests")
    for entry in Path(sysconfig.get_paths()["purelib"]).iterdir():
        if not entry.name.lower().startswith(ours) and entry.suffix != ".pth":
            (deps / entry.name).symlink_to(entry)
    Path(purelib, "deps.pth").write_text(str(deps) + "\n")
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q", "--no-deps",
                        "--no-index", str(wheel)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    work = tmp / "elsewhere"
    work.mkdir()
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    env["PATH"] = f"{env_dir / 'bin'}:{env['PATH']}"
    return env_dir, work, env


def _run(fresh, *args, timeout=300):
    env_dir, work, env = fresh
    return subprocess.run(list(args), cwd=work, env=env, capture_output=True, text=True, timeout=timeout)


def test_wheel_installs_one_namespace(fresh):
    env_dir, _, _ = fresh
    py = str(env_dir / "bin" / "python")
    for generic in ("service", "workers", "ardcore"):
        r = _run(fresh, py, "-c", f"import {generic}")
        assert r.returncode != 0 and "ModuleNotFoundError" in r.stderr, (generic, r.stdout, r.stderr)
    r = _run(fresh, py, "-c", "import ardflow.service.commands.local as c, ardflow.workers.graph, ardflow.ardcore.likelihood.ekf;"
                              "print(c.__file__); print(c.EXAMPLES)")
    assert r.returncode == 0, r.stderr
    where, examples = r.stdout.split()
    assert where.startswith(str(env_dir)) and examples.startswith(str(env_dir)), r.stdout


def test_wheel_runs_a_study_and_starts_the_demo(fresh):
    env_dir, work, env = fresh
    ardflow = str(env_dir / "bin" / "ardflow")
    r = _run(fresh, ardflow, "example", "sec33", "--out", "sec33.json")
    assert r.returncode == 0 and (work / "sec33.json").read_text().startswith("{"), r.stderr
    r = _run(fresh, ardflow, "select", str(SMALL), "--out", "small", "--workers", "1", timeout=600)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert (work / "small" / "summary.json").exists() and (work / "small" / "report" / "report.html").exists()
    # the demo's spec and data generator come from the package: it starts and fills its store
    p = subprocess.Popen([ardflow, "demo", "--out", "demo", "--workers", "1"], cwd=work, env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        deadline = time.time() + 240
        seen = ""
        while time.time() < deadline and "burn-in round" not in seen and "] trial" not in seen:
            line = p.stdout.readline()
            if not line:
                break
            seen += line
        assert "Section 3.6 study (sec36.json" in seen, seen
        assert (work / "demo" / "zarr.json").exists(), seen
    finally:
        os.killpg(p.pid, signal.SIGKILL)
        p.wait()


def test_editable_install_is_quiet(fresh, tmp_path):
    """`make venv`'s editable install, with the Makefile's environment, prints no packaging warning."""
    env_dir, _, env = fresh
    src = env_dir.parent / "src"
    setting = re.search(r'^EDITABLE_ENV := PYTHONWARNINGS="([^"]+)"', (ROOT / "Makefile").read_text(), re.M)
    assert setting, "the Makefile no longer sets EDITABLE_ENV"
    target = tmp_path / "editable"
    venv.create(target, with_pip=False)
    py = target / "bin" / "python"
    purelib = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                             capture_output=True, text=True, check=True).stdout.strip()
    Path(purelib, "deps.pth").write_text(str(env_dir.parent / "deps") + "\n")  # setuptools for the build
    r = subprocess.run([sys.executable, "-m", "pip", "--python", str(py), "install", "-q",
                        "--no-deps", "--no-build-isolation", "-e", str(src)],
                       capture_output=True, text=True, timeout=300, env={**env, "PYTHONWARNINGS": setting.group(1)})
    assert r.returncode == 0, r.stderr[-3000:]
    assert "warning" not in (r.stdout + r.stderr).lower(), (r.stdout + r.stderr)[-3000:]
