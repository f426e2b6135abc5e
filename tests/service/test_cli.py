"""The command line, run as a user runs it (a subprocess)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest


ROOT = Path(__file__).resolve().parents[2]


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "ardflow.service.cli", *args], capture_output=True, text=True,
                          cwd=cwd, env=dict(os.environ), timeout=300)


def test_simulate_reference_is_reproducible(tmp_path):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    for p in (a, b):
        r = run("simulate", "reference", "--seed", "3", "--out", str(p))
        assert r.returncode == 0, r.stderr
    assert a.read_bytes() == b.read_bytes()
    assert a.read_text().splitlines()[0] == "t,y"
    side = json.loads(a.with_suffix(".json").read_text())
    assert side["seed"] == 3 and side["true_params"]["a3"] == 100.0
    assert side["pipeline"]["n_d"] == 5000 and side["model"]["name"] == "M2true"
    r = run("loglik", str(a), "--model", "M2true", *[f"--param={k}={side['true_params'][k]}"
                                                     for k in ["B", "a1", "a2", "a3", "a4", "sigma"]])
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["loglik"] > 2.5e4


def test_simulate_other_model_with_input(tmp_path):
    out = tmp_path / "duff.csv"
    r = run("simulate", "duffing", "--seed", "1", "--out", str(out), "--n", "200", "--dt", "0.05",
            "--nsub", "10", "--param", "k=4", "--param", "c=0.3", "--param", "k3=1",
            "--param", "b=1", "--param", "sigma=0.1")
    assert r.returncode == 0, r.stderr
    assert out.read_text().splitlines()[0] == "t,y,u"


@pytest.mark.parametrize("args,msg", [
    (["simulate", "nonsense", "--out", "x.csv"], "unknown model 'nonsense'"),
    (["simulate", "pendulum", "--out", "x.csv", "--param", "w2=1"], "no value for 'c'"),
    (["simulate", "pendulum", "--out", "x.csv", "--param", "w2=abc"], "is not a number"),
    (["loglik", "missing.csv", "--model", "M2"], "no such file"),
    (["data", "check", "empty.csv"], "empty file"),
    (["loglik", "cut.npz", "--model", "M2"], "cannot read NPZ file"),
    (["loglik", "ok.csv", "--model", "big.json"], "nested too deeply"),
    (["data", "check", "long.csv"], "not a CSV table"),
    (["status", "--url", "http://127.0.0.1:9"], "cannot reach the ardflow service at http://127.0.0.1:9"),
    (["submit", "ok.json", "--url", "http://127.0.0.1:9"], "Start one with `ardflow serve`"),
])
def test_errors_are_one_line_without_traceback(tmp_path, args, msg):
    (tmp_path / "empty.csv").write_text("")
    (tmp_path / "ok.csv").write_text("t,y\n" + "".join(f"{i},{i % 3}\n" for i in range(20)))
    (tmp_path / "ok.json").write_text((ROOT / "examples" / "sec33.json").read_text())
    (tmp_path / "long.csv").write_text("t,y\n0," + "9" * 140_000 + "\n")
    import io

    buf = io.BytesIO()
    np.savez(buf, t=np.arange(100.0), y=np.ones(100))
    (tmp_path / "cut.npz").write_bytes(buf.getvalue()[:300])  # a truncated download
    big = {"name": "big", "states": ["x"], "drift": {"x": "+".join(["x"] * 1000)},
           "observations": [{"column": "y", "expr": "x", "noise_std": "0.1"}]}
    (tmp_path / "big.json").write_text(json.dumps(big))
    r = run(*args, cwd=tmp_path)
    assert r.returncode == 2
    assert msg in r.stderr and "Traceback" not in r.stderr


def test_a_typo_in_a_model_is_one_line_and_creates_nothing(tmp_path):
    spec = json.loads((ROOT / "examples" / "sec33.json").read_text())
    m = json.loads(run("models", "M2", cwd=tmp_path).stdout)
    m["drift"]["CM"] += " + zeta*theta"  # a symbol the model does not declare
    spec["models"][0].update(model=m, fixed={"a5": 0.0, "a6": 0.0})
    (tmp_path / "typo.json").write_text(json.dumps(spec))
    r = run("select", "typo.json", "--out", "st", cwd=tmp_path)
    assert r.returncode == 2 and "unknown name 'zeta'" in r.stderr, r.stderr
    assert len((r.stdout + r.stderr).strip().splitlines()) == 1 and "Traceback" not in r.stderr
    assert not (tmp_path / "st").exists()


def _oscillator_spec(path: str) -> dict:
    """A quick Laplace study of the linear oscillator on the record at ``path``."""
    return {"name": "osc", "data": {"path": path}, "evidence": "laplace",
            "models": [{"model": "linear_oscillator",
                        "priors": {"k": {"kind": "lognormal", "median": 15.0, "cov": 50},
                                   "c": {"kind": "lognormal", "median": 0.1, "cov": 200},
                                   "sigma": {"kind": "lognormal", "median": 0.05, "cov": 200}}}],
            "sampler": {"n_stationary": 200, "n_proposal": 200, "round_size": 100, "start_maxfev": 600}}


def test_diagnose_held_out_file_with_its_own_column_names(tmp_path):
    """A held-out file whose columns are named differently (yVal) is renamed by --test-rename."""
    import numpy as np

    from ardflow.ardcore.likelihood.simulate import simulate_model

    t = np.arange(1200) * 0.02
    d = simulate_model("linear_oscillator", {"k": 16.0, "c": 0.1, "sigma": 0.05}, t, 4, x0=[1.0, 0.0])
    y = d.columns["y"]
    (tmp_path / "est.csv").write_text("t,y\n" + "\n".join(f"{float(a)!r},{float(b)!r}" for a, b in zip(t[:800], y[:800])))
    (tmp_path / "val.csv").write_text("t,yVal\n" + "\n".join(f"{float(a)!r},{float(b)!r}" for a, b in zip(t[800:], y[800:])))
    (tmp_path / "spec.json").write_text(json.dumps(_oscillator_spec("est.csv")))
    r = run("diagnose", "spec.json", "--out", "out", "--test-data", "val.csv", "--max-rounds", "0", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "val.csv" in r.stderr, r.stderr
    r = run("diagnose", "spec.json", "--out", "out", "--test-data", "val.csv", "--test-rename", "yVal=y",
            "--max-rounds", "0", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rep = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert rep["n_test"] == 400


def test_diagnose_at_another_seed_says_which_it_ran(tmp_path):
    """``--seed`` runs the loop's random numbers at another seed than the spec's, and the diagnosis says which
    seed it ran at (with and without it)."""
    import numpy as np

    from ardflow.ardcore.likelihood.simulate import simulate_model
    from ardflow.ardcore.selection.spec import StudySpec

    t = np.arange(900) * 0.02
    d = simulate_model("linear_oscillator", {"k": 16.0, "c": 0.1, "sigma": 0.05}, t, 4, x0=[1.0, 0.0])
    (tmp_path / "est.csv").write_text("t,y\n" + "\n".join(f"{float(a)!r},{float(b)!r}"
                                                          for a, b in zip(t, d.columns["y"])))
    spec = _oscillator_spec("est.csv")
    (tmp_path / "spec.json").write_text(json.dumps(spec))
    for extra, seed in (([], StudySpec.model_validate(spec).seed), (["--seed", "7"], 7)):
        r = run("diagnose", "spec.json", "--out", "out", "--max-rounds", "0", *extra, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        assert json.loads((tmp_path / "out" / "diagnosis.json").read_text())["seed"] == seed


def test_live_progress_bars_and_plain_lines(capsys):
    """On an interactive terminal each model gets a bar that advances per trial and completes at model_done;
    in logs and CI the same events are plain lines."""
    from ardflow.ardcore.events import ModelEvent
    from ardflow.service.commands.progress import LiveProgress

    lines = [{"model": "M1", "stage": "burnin", "round": 1, "rhat": [1.5, "inf"], "best_lp": 1.0, "acceptance": 0.3},
              {"model": "M1", "stage": "trial", "iteration": 0, "action": "start", "log_evidence": 10.0,
               "log_evidence_se": 0.1, "accepted": True},
              {"model": "M2", "stage": "trial", "iteration": 0, "action": "start", "log_evidence": 12.0,
               "log_evidence_se": 0.1, "accepted": True},
              {"model": "M1", "stage": "trial", "iteration": 1, "action": "a3: log10 alpha -10 -> -8",
               "log_evidence": 11.0, "log_evidence_se": 0.1, "accepted": True},
              {"model": "M1", "stage": "model_done", "log_evidence": 11.0}]
    events = [ModelEvent.from_json(x) for x in lines]  # as read back from a store's progress log
    with LiveProgress(20, live=True) as live:
        for ev in events:
            live(ev)
        tasks = {t.fields["model"]: t for t in live._progress.tasks}
        assert tasks["M1"].completed == tasks["M1"].total == 20 and "11.000" in tasks["M1"].fields["status"]
        assert tasks["M2"].completed == 1 and "best ln Z 12.00" in tasks["M2"].fields["status"]
    with LiveProgress(20, live=False) as plain:
        for ev in events:
            plain(ev)
    out = capsys.readouterr().out
    assert "[M1] trial   1  a3: log10 alpha -10 -> -8" in out and "[M1] done: ln Z = 11.000" in out


def test_settings_are_listed_from_their_one_declaration():
    """`ardflow settings` prints every field the spec accepts, with the default and bounds the spec enforces."""
    from ardflow.ardcore.selection.config import MaximiserConfig
    from ardflow.ardcore.sampling.config import SamplerConfig
    from ardflow.ardcore.selection.spec import StudySpec

    r = run("settings")
    assert r.returncode == 0, r.stderr
    lines = {ln.split()[0]: ln for ln in r.stdout.splitlines() if ln.startswith("  ")}
    for model in (SamplerConfig, MaximiserConfig):
        for name in model.model_fields:
            assert name in lines, name
    assert "n_chains" in lines and ">= 2" in lines["n_chains"] and " 4 " in lines["n_chains"]
    # the bound printed is the bound the study spec enforces
    with pytest.raises(ValueError, match="n_chains"):
        StudySpec.model_validate({"name": "x", "data": {"generator": "appendix_a"}, "models": [],
                                  "sampler": {"n_chains": 1}})
    assert "reweight_min_ess" in lines and "<= 1" in lines["reweight_min_ess"]


def test_serial_and_dask_executors_write_the_same_store_and_report(tmp_path):
    """`select --executor serial` and `--executor dask` (embedded cluster): one store layout, one report, and
    (same seeds) the same numbers."""
    from pathlib import Path

    spec = Path(__file__).resolve().parents[1] / "workers" / "small_study.json"
    trees, reports, summaries = [], [], []
    for ex in ("serial", "dask"):
        out = tmp_path / ex
        r = run("select", str(spec), "--out", str(out), "--executor", ex, "--workers", "2")
        assert r.returncode == 0, r.stderr
        trees.append(sorted(str(p.relative_to(out)) for p in out.rglob("*")
                            if p.is_file() and "checkpoints" not in p.parts))  # checkpoints: Dask's resume only
        reports.append("\n".join(ln for ln in (out / "report" / "report.html").read_text().split("><")
                                 if "Wall time" not in ln))
        s = json.loads((out / "summary.json").read_text())
        summaries.append([(m["name"], m["log_evidence"], m["kept"], m["pruned"]) for m in s["models"]])
    assert trees[0] == trees[1]
    assert any(t.startswith("models/quad/trials/") for t in trees[0]), trees[0][:10]
    assert reports[0] == reports[1]
    assert summaries[0] == summaries[1]


def test_full_settings_are_the_engines_defaults():
    """`--full` (select, demo) sets the paper-scale sampler sizes: the defaults of the one declaration."""
    from ardflow.ardcore.sampling.config import SamplerConfig
    from ardflow.ardcore.selection.spec import load_spec
    from ardflow.service.commands.study import full_settings
    from ardflow.service.commands.local import EXAMPLES

    demo = load_spec(EXAMPLES / "sec36.json")
    full = full_settings(demo)
    assert (full.sampler.n_chains, full.sampler.round_size, full.sampler.n_stationary, full.sampler.n_proposal) \
        == (4, 500, 5000, 5000) == tuple(SamplerConfig.model_fields[k].default
                                         for k in ("n_chains", "round_size", "n_stationary", "n_proposal"))
    assert full.sampler.min_burnin_rounds == demo.sampler.min_burnin_rounds  # the rest as the spec says


@pytest.mark.parametrize("error", [RuntimeError, AttributeError])
def test_a_diagnosis_that_fails_after_its_fit_writes_what_it_had(tmp_path, monkeypatch, capsys, error):
    """A loop that fails after its first fit (here the trace raises inside the first round, with a numerical
    error or with a defect's) loses nothing: the CLI writes the measures, the rounds so far and the last model
    held to diagnosis.json with the reason, and says so in one line with a non-zero status."""
    from ardflow.ardcore.likelihood.simulate import simulate_model
    from ardflow.ardcore.loop import diagnose as loop
    from ardflow.service.cli import main

    t = np.arange(900) * 0.02
    d = simulate_model("linear_oscillator", {"k": 16.0, "c": 0.1, "sigma": 0.05}, t, 4, x0=[1.0, 0.0])
    (tmp_path / "est.csv").write_text("t,y\n" + "\n".join(f"{float(a)!r},{float(b)!r}"
                                                          for a, b in zip(t, d.columns["y"])))
    (tmp_path / "spec.json").write_text(json.dumps(_oscillator_spec(str(tmp_path / "est.csv"))))

    def broken(*a, **k):
        raise error("the trace broke")

    monkeypatch.setattr(loop, "trace_and_confirm", broken)
    rc = main(["diagnose", str(tmp_path / "spec.json"), "--out", str(tmp_path / "out"), "--max-rounds", "1"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "the trace broke" in err[0] and "diagnosis.json" in err[0], err
    rep = json.loads((tmp_path / "out" / "diagnosis.json").read_text())
    assert rep["status"] == "failed" and f"{error.__name__}: the trace broke" in rep["reason"]
    assert rep["before"]["free_run"]["rms_error"] > 0 and rep["last_fit"]["mean"]["k"] > 0
    assert rep["model"] == "linear_oscillator" and rep["rounds"] == []
