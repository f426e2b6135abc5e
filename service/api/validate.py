"""Submit-time checks of a study: its models compiled in a child process with limits, its cost estimated."""

from __future__ import annotations

import json
import subprocess
import sys
import threading

from ardflow.ardcore.selection.spec import StudySpec

_checked: set[str] = set()
_lock = threading.Lock()
_slots = threading.BoundedSemaphore(2)  # child compilers at once: a burst of submissions cannot fork dozens


class Rejected(Exception):
    """A study that must not run: ``status`` (422 or 413) and a message naming the field."""

    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status = status


def check_models(spec: StudySpec, *, timeout_s: float = 30.0, memory_mb: int = 2048) -> None:
    """Parse, differentiate and generate every model's kernel (:mod:`ardcore.selection.validation`) in a child process
    with a wall-clock and an address-space limit; a model seen before (same structure) is not re-checked.

    Raises
    ------
    Rejected
        422 with the checker's message, or naming the limit the model ran into.
    """
    from ardflow.ardcore.selection.validation import parse_models
    from ardflow.ardcore.errors import ArdflowError

    try:
        parse_models(spec)  # bounded and cheap: most bad models are answered here, at once
    except ArdflowError as exc:
        raise Rejected(422, str(exc)) from None
    keys = [c.model_spec().structure_hash() for c in spec.models]
    with _slots:
        with _lock:
            if all(k in _checked for k in keys):  # also when a concurrent submission of the same models just did
                return
        _check_in_child(spec, keys, timeout_s, memory_mb)


def _check_in_child(spec: StudySpec, keys: list[str], timeout_s: float, memory_mb: int) -> None:
    try:
        # the child sets its own memory limit (preexec_fn is not safe in a threaded server)
        r = subprocess.run(["nice", "-n", "5", sys.executable, "-m", "ardflow.ardcore.selection.validation", "--memory-mb", str(memory_mb)],
                           input=json.dumps(spec.model_dump(mode="json")), capture_output=True, text=True,
                           timeout=timeout_s)
    except subprocess.TimeoutExpired:
        raise Rejected(422, f"models: compiling the models took longer than {timeout_s:g} s; "
                            "simplify the expressions (derived chains, powers, nesting)") from None
    if r.returncode == 2:
        raise Rejected(422, (r.stderr.strip().splitlines() or ["invalid model"])[0])
    if r.returncode != 0:
        tail = r.stderr.strip().splitlines()
        why = "it ran out of memory" if any("MemoryError" in t for t in tail) else f"exit {r.returncode}"
        raise Rejected(422, f"models: the models could not be compiled within {memory_mb} MB / "
                            f"{timeout_s:g} s ({why}); simplify the expressions")
    with _lock:
        _checked.update(keys)


def estimate_evaluations(spec: StudySpec) -> float:
    """An upper estimate of a study's likelihood evaluations: every model runs ``max_trials`` search trials,
    each with its start optimisation, every burn-in round (with delayed rejection: up to two per proposal),
    M stationary draws (each redraw of an unsettled stage is M more) and the Chib-Jeliazkov proposal draws;
    then its optimum's chains continue up to the budget (``max_stationary``) and take the proposal draws
    again."""
    s, m = spec.sampler, spec.maximiser
    per_trial = (s.n_chains * (s.start_maxfev + 2 * s.max_burnin_rounds * s.round_size
                                + (1 + s.stationary_restarts) * s.n_stationary)
                 + s.n_proposal * s.n_chains)
    refine = s.n_chains * (s.stationary_budget + s.stationary_restarts * s.n_stationary + s.n_proposal)
    return float(len(spec.models) * (m.max_trials * per_trial + refine))


def check_budget(spec: StudySpec, n_rows: int, budget: float) -> dict:
    """Reject a study whose estimated cost (evaluations x data rows x sub-steps) exceeds ``budget``.

    Returns the estimate; raises :class:`Rejected` (413) with it.
    """
    ev = estimate_evaluations(spec)
    # a likelihood costs a filter step per sub-step per row
    sub = max((c.substeps or c.model_spec().substeps) for c in spec.models)
    cost = ev * max(1, n_rows) * sub
    est = {"evaluations": ev, "rows": n_rows, "substeps": sub, "cost": cost, "budget": budget}
    if cost > budget:
        raise Rejected(413, f"study too large for this service: about {ev:.3g} likelihood evaluations x "
                            f"{n_rows} rows x {sub} sub-steps = {cost:.3g} > budget {budget:.3g} (lower "
                            f"sampler.max_burnin_rounds, n_stationary, max_stationary, n_chains, "
                            f"maximiser.max_trials or substeps)")
    return est
