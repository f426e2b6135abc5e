"""A study's result, typed: the comparison of the optimal nested models (Eq. 7) and every model's fit.

:func:`ardcore.selection.study.compare` makes a :class:`StudySummary`; its JSON (:meth:`StudySummary.to_json`)
is ``summary.json``, which the store, the service and the reports read back with
:meth:`StudySummary.from_json`. The JSON carries a schema version: a summary written by a newer ardflow is
refused with a message instead of being misread, and one written before versions existed reads as version 1.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from ..errors import DataError
from ..jsonio import to_jsonable
from .fit import ModelFit

SCHEMA = 1
"""The version of ``summary.json`` this ardflow writes and the newest it reads."""


@dataclass(frozen=True)
class ComparedModel:
    """One candidate at its evidence optimum and its posterior probability among the candidates, P(M|d) by
    Eq. 7, with the probability's standard deviation from the evidence's Monte Carlo error."""

    fit: ModelFit
    probability: float
    probability_sd: float
    refused: str | None = None
    """Why the fit is no result (:meth:`ModelFit.degenerate`): it takes no part in the comparison (probability
    0), and the reason is reported instead."""

    def to_json(self) -> dict:
        return {**self.fit.to_json(), "probability": self.probability, "probability_sd": self.probability_sd,
                "refused": self.refused}


@dataclass(frozen=True)
class StudySummary:
    """The result of a model-selection study.

    Attributes
    ----------
    study : str
        The spec's name.
    data : dict
        The data set's ``source`` and length ``n`` (:func:`~.study.data_meta`), and ``input_hold`` when the
        record decided how the models take their inputs between samples.
    models : tuple of ComparedModel
        Every candidate, in the spec's order.
    best_model : str
        The candidate with the largest evidence.
    seed : int
    wall_s : float
    spec : dict
        The study spec as JSON.
    study_id : str or None
        The store's study id (None for an in-memory run).
    """

    study: str
    data: dict
    models: tuple
    best_model: str
    seed: int
    wall_s: float
    spec: dict
    study_id: str | None = None

    def model(self, name: str) -> ComparedModel:
        """The candidate called ``name`` (KeyError when there is none)."""
        for m in self.models:
            if m.fit.name == name:
                return m
        raise KeyError(name)

    def with_study_id(self, study_id: str | None) -> "StudySummary":
        return replace(self, study_id=study_id)

    def to_json(self) -> dict:
        """``summary.json``: the schema version, the study, the data, one row per model (its
        :meth:`ModelFit.to_json` with its probability), the best model, the seed, the wall time, the spec."""
        return to_jsonable({"schema": SCHEMA, "study": self.study, "data": self.data,
                            "models": [m.to_json() for m in self.models], "best_model": self.best_model,
                            "seed": self.seed, "wall_s": self.wall_s, "spec": self.spec,
                            "study_id": self.study_id})

    @classmethod
    def from_json(cls, d: dict) -> "StudySummary":
        """The summary :meth:`to_json` wrote (a summary without a version is version 1).

        Raises
        ------
        DataError
            When the summary was written by a newer ardflow (a schema this one does not know).
        """
        schema = int(d.get("schema", 1))
        if schema > SCHEMA:
            raise DataError(f"this summary.json has schema version {schema}, written by a newer ardflow; this "
                            f"one reads versions up to {SCHEMA}: upgrade ardflow to read it")
        models = tuple(ComparedModel(ModelFit.from_json(r), r.get("probability"), r.get("probability_sd"),
                                     r.get("refused")) for r in d["models"])
        return cls(d["study"], dict(d.get("data") or {}), models, d["best_model"], int(d.get("seed", 0)),
                   float(d.get("wall_s", 0.0)), dict(d.get("spec") or {}), d.get("study_id"))
