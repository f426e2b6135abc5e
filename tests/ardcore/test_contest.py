"""The states against the terms (ardcore.loop.criterion.contest): the round's move once the state moves have
competed with the terms' move, on the real criterion (decide, pick, dominates) with held-out scores the loop
measured. The fits are stand-ins that carry only an evidence; their scores are the criterion's own cache, so
nothing here is refitted."""

from types import SimpleNamespace

import pytest

from ardflow.ardcore.loop.config import DiagnoseConfig
from ardflow.ardcore.loop.criterion import Criterion, Move, Score, contest
from ardflow.ardcore.sampling.chains import serial_map

# the two-mass record, round 1: the model, the terms that stand in for its second store, and the store
MODEL = Score({"start": 6.657, "end": 13.52, "loudest": 6.657})
STAND_INS = Score({"start": 5.303, "end": 3.589, "loudest": 5.303})
STORE = Score({"start": 0.1527, "end": 0.1864, "loudest": 0.1527})
# a state that free-runs better than the model but not on every block better than the terms
HALF = Score({"start": 0.1527, "end": 4.0, "loudest": 0.1527})
WORSE = Score({"start": 7.0, "end": 14.0, "loudest": 7.0})  # a state the criterion refuses


def _fit(log_evidence: float):
    return SimpleNamespace(row=SimpleNamespace(log_evidence=log_evidence), cand=SimpleNamespace(label="model"))


def _criterion(*scored) -> Criterion:
    crit = Criterion(DiagnoseConfig(), serial_map, lambda m: None)
    for fit, score in scored:
        crit._kept[id(fit.row)] = (fit.row, score)  # what the pool measured: scored once per fit
    return crit


def _state(name: str, fit):
    return fit, [{"by": f"the state {name}"}], 100.0


def _round(terms_fit):
    held = _fit(0.0)
    rnd = SimpleNamespace(record={"round": 1})
    move = Move("add", terms_fit, "overflow with cube with forcing") if terms_fit is not None else None
    judged = {"moves": [{"move": move.name, "kind": "add", "taken": True}] if move else []}
    ctx = SimpleNamespace(config=DiagnoseConfig(), say=lambda m: None)
    return held, rnd, move, judged, ctx


@pytest.mark.parametrize("state_score, state_wins", [(STORE, True), (HALF, False)], ids=["every_block", "not_every"])
def test_a_state_displaces_the_terms_only_when_it_free_runs_better_on_every_block(state_score, state_wins):
    """The two-mass store free-runs every block better than the terms that stand in for it and displaces them;
    a state better than the model but not on every block better than the terms leaves them to go first. The
    loser is refused in the round's record, and a displaced move is no longer marked taken."""
    terms, state = _fit(50.0), _fit(40.0)
    held, rnd, move, judged, ctx = _round(terms)
    crit = _criterion((held, MODEL), (terms, STAND_INS), (state, state_score))
    swap = ("the terms' swap",)
    got, got_swap = contest(ctx, crit, held, (move, swap), iter([_state("store_T2", state)]), rnd, judged)
    if state_wins:
        assert got.fit is state and got_swap[0] is state
        assert [r["effect"] for r in rnd.record["refused"]] == [move.name]
        assert [j["taken"] for j in judged["moves"] if j["move"] == move.name] == [False]
    else:
        assert got is move and got_swap is swap
        assert [r["effect"] for r in rnd.record["refused"]] == ["the state store_T2"]


def test_a_state_the_criterion_refuses_does_not_hide_the_next_and_the_rest_are_not_fitted():
    worse, store, never = _fit(90.0), _fit(40.0), _fit(10.0)
    held, rnd, move, judged, ctx = _round(None)
    crit = _criterion((held, MODEL), (worse, WORSE), (store, STORE))
    asked = []

    def states():
        for name, fit in (("pick_y", worse), ("store_T2", store), ("mode_y", never)):
            asked.append(name)
            yield _state(name, fit)

    got, _ = contest(ctx, crit, held, (None, None), states(), rnd, judged)
    assert got.fit is store
    assert asked == ["pick_y", "store_T2"]  # the generator fits each on demand: the third is never fitted
    assert [j["move"] for j in judged["moves"]] == ["the state pick_y", "the state store_T2"]


def test_no_state_qualifies_and_the_terms_stand():
    terms, worse = _fit(50.0), _fit(90.0)
    held, rnd, move, judged, ctx = _round(terms)
    crit = _criterion((held, MODEL), (terms, STAND_INS), (worse, WORSE))
    got, _ = contest(ctx, crit, held, (move, "swap"), iter([_state("pick_y", worse)]), rnd, judged)
    assert got is move
    assert [j["taken"] for j in judged["moves"] if j["move"] == move.name] == [True]


# the real tanks from the square-root model, round 0: the upper outflow's forms the evidence supports
KNEE = Score({"start": 0.8891, "end": 0.9074, "loudest": 0.7484})
POWER = Score({"start": 0.70, "end": 0.60, "loudest": 0.55})
TANKS = Score({"start": 0.7415, "end": 1.045, "loudest": 0.9241})


MIXED = Score({"start": 0.95, "end": 0.60, "loudest": 0.55})  # better than the knee on two blocks, worse on one


@pytest.mark.parametrize("scores, taken", [((KNEE, POWER), 1), ((KNEE, MIXED), 0), ((WORSE, Score({
    "start": 0.75, "end": 1.05, "loudest": 0.93})), 1), ((Score({}), Score({})), 0)],
    ids=["better_on_every_block", "blocks_disagree_evidence", "none_improves_least_worse", "no_score_evidence"])
def test_between_the_forms_of_a_law_the_held_out_free_run_chooses(scores, taken):
    """A law's forms the evidence supports: one that free-runs better on every held-out block is taken over one a
    few nats more probable; between forms the blocks disagree on, the evidence; when neither improves, the one that changes the blocks least for the worse; on a record
    without a score, the evidence."""
    held = _fit(0.0)
    forms = [_fit(40.0), _fit(35.0)]  # the first has the higher evidence
    crit = _criterion((held, TANKS if scores[0].errors else Score({})), *zip(forms, scores))
    k, got = crit.alternative(held, forms)
    assert k == taken
    assert got == list(scores)
