"""A study prepared on a stepped record is stored holding its inputs (``ardcore.selection.hold``)."""

import numpy as np

from ardflow.ardcore.selection.spec import StudySpec
from ardflow.workers.graph import prepare_store
from ardflow.workers.store import StudyStore
from tests.ardcore.test_hold import _steps, _study


def test_the_store_keeps_the_hold_the_record_decided(tmp_path):
    """A study prepared on a stepped record is stored holding its inputs (the workers read the stored spec), and
    its metadata says the record decided it."""
    u = _steps(600)
    np.savetxt(tmp_path / "steps.csv", np.c_[u, np.sin(np.arange(u.size) / 10)], delimiter=",", header="u,y",
               comments="")
    raw = _study().model_dump(mode="json", exclude={"models"})
    lognormal = {"kind": "lognormal", "median": 1.0, "cov": 100}
    spec = StudySpec.model_validate({**raw, "data": {"path": str(tmp_path / "steps.csv"), "fs": 50.0},
                                     "models": [{"model": "forced_linear_oscillator",
                                                 "priors": {p: lognormal for p in ("k", "c", "b", "sigma")}}]})
    store = prepare_store(spec, tmp_path / "st")
    meta = StudyStore(store.path).meta
    assert "'zoh'" in meta["data"]["input_hold"][0]
    assert StudySpec.model_validate(meta["spec"]).models[0].model_spec().input_hold == "zoh"
