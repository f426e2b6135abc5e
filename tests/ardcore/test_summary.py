"""The study summary as a typed, versioned value: what compare() makes is what summary.json holds and reads
back; a summary written by a newer ardflow is refused with a message, one written before versions reads."""

import json
import math
from pathlib import Path

import pytest

from ardflow.ardcore.errors import DataError
from ardflow.ardcore.selection.fit import ModelFit
from ardflow.ardcore.selection.spec import load_spec
from ardflow.ardcore.selection.study import compare
from ardflow.ardcore.selection.summary import SCHEMA, StudySummary

ROOT = Path(__file__).resolve().parents[2]


def _summary() -> StudySummary:
    spec = load_spec(ROOT / "examples" / "polynomial.json")
    fits = [ModelFit("A", 10.0, 0.1, 12.0, 2.0, "laplace", {"a3": math.inf, "a2": 1e-3}, ["a2"], ["a3"],
                     mean={"a2": 0.5}, sd={"a2": 0.1}),
            ModelFit("B", 8.0, 0.2, 11.0, 3.0, "laplace", {"a3": 1.0}, ["a3"], [], mean={"a3": 0.2}, sd={"a3": 0.3})]
    return compare(fits, spec, {"source": "test", "n": 10}, 1.5).with_study_id("s-1")


def test_the_summary_reads_back_as_written():
    s = _summary()
    js = json.loads(json.dumps(s.to_json()))  # through text, as the store keeps it
    assert js["schema"] == SCHEMA and js["best_model"] == "A" and js["models"][0]["psi_opt"]["a3"] == "inf"
    back = StudySummary.from_json(js)
    assert back == s
    # Eq. 7 with equal priors: P(A)/P(B) = exp(ln Z_A - ln Z_B)
    assert back.model("A").probability / back.model("B").probability == pytest.approx(math.exp(2.0))


def test_a_newer_summary_is_refused_and_an_unversioned_one_reads():
    js = _summary().to_json()
    with pytest.raises(DataError, match="newer ardflow"):
        StudySummary.from_json({**js, "schema": SCHEMA + 1})
    old = {k: v for k, v in js.items() if k != "schema"}
    assert StudySummary.from_json(old) == _summary()
