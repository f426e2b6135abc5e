"""Study specs: examples validate; bad specs are rejected with the field named."""

import json
import math
from pathlib import Path

import pytest
from pydantic import ValidationError

from ardflow.ardcore.errors import SpecError
from ardflow.ardcore.selection.spec import StudySpec, load_spec
from ardflow.ardcore.selection.study import model_probabilities

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.mark.parametrize("name", ["polynomial", "sec33", "sec34", "sec35", "sec36"])
def test_examples_validate(name):
    spec = load_spec(EXAMPLES / f"{name}.json")
    assert spec.models


def base():
    return json.loads((EXAMPLES / "sec35.json").read_text())


def mutate(fn):
    d = base()
    fn(d)
    return d


@pytest.mark.parametrize("change,field,msg", [
    (lambda d: d["models"][0]["priors"].update(a1={"kind": "uniform", "low": 0, "high": -2}),
     "models.0.priors.a1", "must be greater than low"),
    (lambda d: d["models"][0]["priors"].update(zz={"kind": "uniform", "low": 0, "high": 1}),
     "models.0", "'zz' is not a parameter"),
    (lambda d: d["models"][0]["ard"].append("a9"), "models.0", "'a9' is not a parameter"),
    (lambda d: d["models"][0]["priors"]["B"].update(cov=-5), "models.0.priors.B.lognormal.cov", "greater than 0"),
    (lambda d: d["models"][0]["priors"]["sigma"].update(median=math.inf), "models.0.priors.sigma.lognormal.median",
     "finite"),
    (lambda d: d["models"][0]["priors"].pop("B"), "models.0", "no prior for parameter 'B'"),
    (lambda d: d.update(sampler={"n_chains": 1}), "sampler.n_chains", "greater than or equal to 2"),
    (lambda d: d.update(bogus=1), "bogus", "Extra inputs"),
    (lambda d: d["data"].update(path="x.csv"), "data", "exactly one of"),
    (lambda d: d["models"][0].update(model="M9"), "models.0", "unknown built-in model 'M9'"),
    (lambda d: d["models"][0].update(constants={"zz": 1.0}), "models.0", "'zz' is not a constant (constants: ["),
    (lambda d: d["models"][0].update(constants={"gamma": math.inf}), "models.0.constants.gamma", "finite"),
    # a '$' puts the figures' text in math mode, where an unknown macro fails the report after the study ran
    (lambda d: d["data"].update(labels={"y": "$\\undefinedmacro{x}$"}), "data.labels.y", "should match pattern"),
    (lambda d: d["data"].update(units={"t": "$s$"}), "data.units.t", "should match pattern"),
])
def test_bad_specs_name_the_field(tmp_path, change, field, msg):
    p = tmp_path / "spec.json"
    p.write_text(json.dumps(mutate(change)).replace("Infinity", "1e999"))
    with pytest.raises(SpecError) as ei:
        load_spec(p)
    text = str(ei.value)
    assert field in text and msg in text, text


def test_nan_rejected_in_python_api():
    d = base()
    d["models"][0]["priors"]["B"]["median"] = float("nan")
    with pytest.raises(ValidationError):
        StudySpec.model_validate(d)


def test_model_probabilities():
    p, sd = model_probabilities([10.0, 10.0 + math.log(3)], [0.0, 0.0])
    assert p == pytest.approx([0.25, 0.75])
    assert sd == pytest.approx([0.0, 0.0], abs=1e-12)
    p, sd = model_probabilities([0.0, 0.0], [0.5, 0.5])
    assert 0.1 < sd[0] < 0.4
