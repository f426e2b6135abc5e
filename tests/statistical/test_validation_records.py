"""Two records of the validation set (tests.bench.validation) through the closed loop, as the bench runs them.

* backlash: the user's coupling k (u - y) is a gear with slack; the loop must replace the declared law by its
  dead-zone form (not stack stand-ins beside it), find the slack's half-width, and free-run the held-out half
  better than the user's model, with a 90 % band that holds 80-97 % of it.
* hysteresis: a Bouc-Wen element no term of the library holds; the evidence supports stand-ins that extrapolate
  badly to the larger motions of the held-out half. The loop's criterion (ardcore.loop.criterion) takes a move
  only when its model free-runs better on held-out blocks of the estimation record: what it took improved
  every round, what it refused did not, it says what it did not keep, and the model it reports free-runs the
  test half no worse than the user's (the hysteretic state that repairs it: tests/statistical/test_loop_states.py).
* the real cascaded tanks from the user's linear and from the physical square-root model: the loop keeps going
  while a move free-runs better held out, and the model it reports free-runs the separate validation experiment
  below a linear ARX tuned as its users tune it and within the published nonlinear models' 0.34-0.45 V (the
  linear start reaches it once a sensor state reads tank 2's level: ardcore/loop/states.py).
"""

import functools

import pytest

from ardflow.ardcore.loop.config import DiagnoseConfig
from ardflow.ardcore.loop.criterion import Score, improves
from ardflow.ardcore.loop.diagnose import diagnose

from ..bench import peers
from ..bench.validation import backlash, hysteresis, tanks

pytestmark = pytest.mark.timeout(900)


@pytest.mark.slow  # a loop of three rounds on a kinked record (make test stays under 15 min)
def test_a_coupling_with_slack_is_replaced_by_its_dead_zone_form():
    rec = backlash()
    d = diagnose(rec.spec, rec.est, test_data=rec.test, config=DiagnoseConfig(max_rounds=2))
    rep = d.report
    assert [x["form"] for x in rep["replaced"]] == ["dead_zone"] and rep["replaced"][0]["parameter"] == "k"
    gap = rep["replaced"][0]["shape"]
    assert gap["q005"] < 0.1 < gap["q995"] or abs(gap["mean"] - 0.1) < 0.02, gap
    before, after = rep["before"]["free_run"]["rms_error"], rep["reported"]["free_run"]
    assert after["rms_error"] < 0.7 * before, (before, after)
    assert 0.8 <= after["band_coverage"] <= 0.97, after


@functools.lru_cache(maxsize=None)  # one loop, shared by the two hysteresis tests below
def _hysteresis_loop():
    rec = hysteresis()
    return diagnose(rec.spec, rec.est, test_data=rec.test, config=DiagnoseConfig(max_rounds=3)).report


@pytest.mark.slow  # three rounds of five stand-ins on the hysteresis record, 2-3 min
def test_stand_ins_that_free_run_worse_held_out_are_not_kept():
    rep = _hysteresis_loop()
    assert rep["withheld"], "the stand-ins the evidence supported are listed as not kept"
    h = rep["held_out"]
    # no move taken made the held-out free run worse
    assert all(b <= 1.01 * a for a, b in zip(h["overall"], h["overall"][1:])), h["overall"]
    for rnd in h["moves"]:
        cur = Score(rnd["score"]["blocks"])
        taken = [m for m in rnd["moves"] if m["taken"]]
        judged = [m for m in rnd["moves"] if "blocks" in m]  # those after the one taken are not scored
        # a round takes at most one move, one that free-runs better held out; with none taken, none did
        assert len(taken) <= 1 and all(improves(Score(m["blocks"]), cur) for m in taken if m["kind"] != "add"
                                       or "noise" not in m["move"]), rnd
        if not taken:  # the loop stopped: nothing it judged free-ran better
            assert not any(improves(Score(m["blocks"]), cur) for m in judged), rnd
    before = rep["before"]["free_run"]["rms_error"]
    assert rep["reported"]["free_run"]["rms_error"] <= 1.01 * before
    assert "not kept" in rep["headline"]


@pytest.mark.slow
@pytest.mark.xfail(reason="issue 42, open: with the Bouc-Wen state the model is right and its band, calibrated on "
                          "three blocks of the estimation record, holds 77 % of the test half (80-97 % asked)")
def test_the_band_of_the_hysteretic_model_holds_80_to_97_percent():
    cover = _hysteresis_loop()["reported"]["free_run"]["band_coverage"]
    assert 0.8 <= cover <= 0.97, cover



@functools.lru_cache(maxsize=None)  # one loop per start, shared by the two tests below (each is minutes long)
def _tanks_against_arx(start):
    rec = tanks(start)
    rep = diagnose(rec.spec, rec.est, test_data=rec.test, config=DiagnoseConfig()).report
    y, u = rec.est.columns["y"], rec.est.columns["u"]
    yt, ut = rec.test.columns["y"], rec.test.columns["u"]
    arx = peers.tuned_narx(y, u, degrees=(1,), runs=peers.heads([(yt, ut)])).free_run_rms(yt, ut)
    return rep, rep["reported"]["free_run"], arx


@pytest.mark.slow  # up to five rounds on the real tanks record, 4-12 min on 2 cores per start
@pytest.mark.timeout(2400)
@pytest.mark.parametrize("start", ["linear", "sqrt"])
def test_the_tanks_free_run_below_a_tuned_arx_from_either_start(start):
    rep, after, arx = _tanks_against_arx(start)
    assert after["rms_error"] < arx, (after, arx)
    assert after["rms_error"] < 0.8 * rep["before"]["free_run"]["rms_error"], (rep["before"], after)


@pytest.mark.slow
@pytest.mark.timeout(2400)
@pytest.mark.parametrize("start", ["linear", "sqrt"])
def test_the_tanks_reach_the_published_nonlinear_models(start):
    """Published nonlinear state-space models free-run the validation experiment at 0.34-0.45 V."""
    _, after, _ = _tanks_against_arx(start)
    assert after["rms_error"] <= 0.45 and 0.8 <= after["band_coverage"] <= 0.97, after
