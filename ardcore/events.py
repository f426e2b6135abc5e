"""Progress events of a running study: typed where they are made, JSON lines where they are stored.

The sampler reports :class:`BurninRound`, :class:`StationaryRound` and :class:`Note`; the maximiser
:class:`TrialDone`; a finished model :class:`ModelDone`. On their way out of a model's fit they are tagged
with the model as a :class:`ModelEvent`, which owns its JSON (one line of the store's progress log, with the
event's ``stage``: ``"burnin"``, ``"stationary"``, ``"note"``, ``"trial"``, ``"model_done"``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import ClassVar, Union, dataclass_transform

from .jsonio import number, to_jsonable


@dataclass_transform(frozen_default=True)
class _Event:
    """A progress event: a frozen dataclass with its ``stage`` (the name its JSON line carries)."""

    stage: ClassVar[str]

    def __init_subclass__(cls, *, stage: str, **kw):
        super().__init_subclass__(**kw)
        cls.stage = stage
        dataclass(frozen=True)(cls)


class Note(_Event, stage="note"):
    """Something a user should read (a chain moved out of a minor mode)."""

    message: str


class BurninRound(_Event, stage="burnin"):
    """A burn-in round committed: the split R-hat per parameter, the best ln posterior so far, acceptance."""

    round: int
    rhat: list
    best_lp: float
    acceptance: float

    @property
    def max_rhat(self) -> float:
        """The largest R-hat (NaN before there is one): burn-in ends when it falls below the threshold."""
        return max(self.rhat, default=math.nan)


class StationaryRound(_Event, stage="stationary"):
    """A stationary round: ``done`` of ``of`` draws per chain."""

    round: int
    done: int
    of: int
    acceptance: float


class TrialDone(_Event, stage="trial"):
    """An evidence trial of the maximiser: what it tried (``action``), at which psi, ln Z and its se (``bound``:
    ln Z is an upper bound, a prune test decided without sampling)."""

    iteration: int
    action: str
    psi: dict
    log_evidence: float
    log_evidence_se: float
    accepted: bool
    bound: bool = False


class ModelDone(_Event, stage="model_done"):
    """A model's evidence maximisation finished."""

    log_evidence: float


ProgressEvent = Union[Note, BurninRound, StationaryRound, TrialDone, ModelDone]
_BY_STAGE = {c.stage: c for c in (Note, BurninRound, StationaryRound, TrialDone, ModelDone)}


@dataclass(frozen=True)
class ModelEvent:
    """A progress event of one model's fit, and when it happened (seconds since the epoch, once stored)."""

    model: str
    event: ProgressEvent
    time: float | None = None

    @property
    def stage(self) -> str:
        return self.event.stage

    def to_json(self) -> dict:
        """One progress-log line: ``model``, ``time``, ``stage`` and the event's fields (non-finite numbers as
        in :mod:`ardcore.jsonio`)."""
        return to_jsonable({"time": self.time, "model": self.model, "stage": self.stage, **asdict(self.event)})

    @classmethod
    def from_json(cls, d: dict) -> ModelEvent | None:
        """The event of a progress-log line; None for a line of an unknown stage (a newer writer's)."""
        kind = _BY_STAGE.get(d.get("stage"))
        if kind is None:
            return None
        # a float field may arrive as an infinity or NaN in jsonio's string spelling; the annotations say which
        kw = {f.name: number(d.get(f.name)) if f.type == "float" else d.get(f.name) for f in fields(kind)}
        if "rhat" in kw:
            kw["rhat"] = [number(v) for v in kw["rhat"] or []]
        if "psi" in kw:
            kw["psi"] = {k: number(v) for k, v in (kw["psi"] or {}).items()}
        if "bound" in kw:
            kw["bound"] = bool(kw["bound"])  # absent from an older writer's lines
        t = d.get("time")
        return cls(str(d.get("model", "")), kind(**kw), float(t) if isinstance(t, (int, float)) else None)

