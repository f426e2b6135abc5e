"""A mistyped name (model, example, spec key) is answered with the closest valid one."""

import json
import types
from pathlib import Path

import pytest

from ardflow.ardcore.errors import ModelError, SpecError, did_you_mean
from ardflow.ardcore.model.library import builtin
from ardflow.ardcore.selection.spec import load_spec


def test_did_you_mean_only_when_close():
    assert did_you_mean("n_stationry", ["n_stationary", "n_chains"]) == " (did you mean 'n_stationary'?)"
    assert did_you_mean("zzz", ["n_stationary", "n_chains"]) == ""


def test_unknown_builtin_model_suggests_the_closest():
    with pytest.raises(ModelError, match="did you mean 'linear_oscillator'"):
        builtin("linear_osciliator")


def test_mistyped_spec_key_suggests_the_field(tmp_path):
    spec = json.loads((Path(__file__).resolve().parents[2] / "examples" / "sec33.json").read_text())
    spec["sampler"] = {**spec.get("sampler", {}), "n_stationry": 100}
    p = tmp_path / "s.json"
    p.write_text(json.dumps(spec))
    with pytest.raises(SpecError, match=r"sampler\.n_stationry: .*did you mean 'n_stationary'"):
        load_spec(p)


def test_unknown_example_suggests_the_closest():
    from ardflow.service.commands.local import cmd_example

    with pytest.raises(SystemExit, match="did you mean 'sec33'"):
        cmd_example(types.SimpleNamespace(name="sec333", out=None))
