"""What the closed loop returns (:func:`ardcore.loop.diagnose.diagnose`), typed.

A :class:`Diagnosis` holds the JSON report (``to_json``), the arrays its figures are drawn from, and the
initial and final models as :class:`FittedModel` (what a free run on a further held-out record needs). The
loop's rounds are :class:`LoopRound` while it runs: the round's JSON record beside the effects it added.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..data import Dataset
from ..effects.base import Effect, with_columns
from ..jsonio import to_jsonable
from ..model.declaration import ModelSpec


@dataclass(frozen=True)
class FittedModel:
    """A model as the loop fitted it: pruned terms fixed, its posterior mean, the effects added (whose input
    columns a record must be given before a free run) and its sub-steps."""

    spec: ModelSpec
    phi: dict
    effects: tuple[Effect, ...] = ()
    substeps: int | None = None

    def free_run(self, record: Dataset, **kw) -> dict:
        """:func:`ardcore.loop.freerun.free_run` of this model on ``record`` (the effects' columns added to it)."""
        from .freerun import free_run

        for e in self.effects:
            record = with_columns(record, e)
        return free_run(self.spec, self.phi, record, substeps=self.substeps, **kw)


@dataclass
class LoopRound:
    """One round of the loop: its JSON record (ranking, confirmations, what was added, the error after) and
    the effects it added, as effects (``effects``) and as what they must keep earning (``added``,
    :class:`ardcore.loop.checks.Added`)."""

    record: dict
    effects: list = field(default_factory=list)
    added: list = field(default_factory=list)


@dataclass(frozen=True)
class Diagnosis:
    """The closed loop's result.

    Attributes
    ----------
    report : dict
        What :meth:`to_json` writes: ``before``/``after`` tests and errors, ``rounds``, ``candidates``,
        ``confirmed``, ``added``, ``removed``, ``parameter_shifts``, ``verdict``, ``final_fit``, ``wall_s``.
    arrays : dict
        ``before``/``after``: residual tests with spectra, innovations, injected process noise, free run.
    initial, final : FittedModel
        The model as given (at its posterior mean) and the one model the loop reports (``report["reported"]``):
        the final structure at the process-noise level that free-runs best on the held-out end of the
        estimation record (:mod:`ardcore.loop.simulation_fit`), its posterior mean at that level.
    """

    report: dict
    arrays: dict
    initial: FittedModel
    final: FittedModel
    posterior: FittedModel | None = None
    """The final structure at its posterior mean (``final`` itself when the chosen noise factor is 1): what
    the reported model is compared with (``report["reported"]["posterior_mean_free_run"]``)."""

    @property
    def verdict(self) -> str:
        return self.report["verdict"]

    @property
    def added(self) -> list:
        """The effects added and kept (their JSON records)."""
        return self.report["added"]

    def to_json(self) -> dict:
        """The report as plain JSON values (pruned alphas as in :mod:`ardcore.jsonio`)."""
        return to_jsonable(self.report)

