"""The diagnosis report explains itself: a verdict, each round's candidates and their fate, the error before and
after in the data's units, the residual tests before and after, and its figures."""

from __future__ import annotations

import re

from ardflow.ardcore.loop.config import DiagnoseConfig
from ardflow.ardcore.loop.diagnose import diagnose
from ardflow.ardcore.selection.spec import DataSpec
from ardflow.service.reports.diagnosis import write_diagnosis
from tests.ardcore.test_diagnose import duffing_free_decay, duffing_spec


def _cells(html: str, heading: str) -> list[list[str]]:
    """The rows of the first table after ``heading``, as cell texts."""
    table = html.split(heading, 1)[1].split("</table>", 1)[0]
    return [[re.sub("<[^>]+>", "", c) for c in re.findall(r"<t[dh][^>]*>(.*?)</t[dh]>", row)]
            for row in re.findall(r"<tr>(.*?)</tr>", table)]


def test_diagnosis_report_rounds_errors_in_units_and_tests(tmp_path):
    data = duffing_free_decay(-4.0, 3)
    d = diagnose(duffing_spec(), data.slice(0, 1000), test_data=data.slice(1000, None),
                 config=DiagnoseConfig(top_k=2, max_rounds=2))
    label = DataSpec(path="x.csv", units={"y": "mm", "t": "s"}, labels={"y": "displacement"}).axis_label
    write_diagnosis(d, data.slice(0, 1000).t, tmp_path, "y", label)
    html = (tmp_path / "diagnosis.html").read_text()
    rep = d.to_json()
    # the diagnosed model's name heads the page, and one reported model is described with its free run
    assert f"<h1>Diagnosis of {rep['model']}</h1>" in html
    model = html.split("<h3>The model reported</h3>", 1)[1].split("</details>", 1)[0]
    assert model.startswith("<p>One model:") and f"{rep['reported']['free_run']['rms_error']:.4g}" in model
    assert "<th>99 % interval</th>" in model
    # one coefficient, one value: an added effect's coefficient in the model's units, as "Effects added" gives it
    from ardflow.service.reports.diagnosis import effect_scales

    scales = effect_scales(rep)
    for p in (a for x in rep["added"] for a in x["posterior"]):
        assert f"<td>{p}</td><td>{rep['reported']['parameters'][p]['mean'] * scales[p]:.4g}</td>" in model
    # the verdict first, at most three sentences
    verdict = html.split("<b>Verdict.</b>", 1)[1].split("</p>", 1)[0]
    assert 1 <= len(re.findall(r"[.!?](\s|$)", verdict.strip())) <= 3, verdict
    # one table per round; the added effect says so, every confirmed candidate has a fate
    assert html.count("<h3>Round ") == len(rep["rounds"]) == 2
    r0 = _cells(html, "<h3>Round 0")
    fates = {row[0]: row[4] for row in r0[1:] if row[0]}
    assert fates["cubic_stiffness(y)"] == "added"
    for c in rep["rounds"][0]["confirmed"]:
        assert fates[c["effect"]], c["effect"]
    # its coefficient with the 99 % interval that holds the truth
    row = next(r for r in r0 if r[0] == "cubic_stiffness(y)")
    lo, hi = map(float, row[7].strip("[]").split(","))
    assert lo < -4.0 < hi
    # the error table in the data's unit, before and after
    err = {r[0]: r for r in _cells(html, "<h2>Error before and after</h2>")[1:]}
    fr = err["free-run RMS error"]
    assert fr[1] == "mm" and float(fr[3]) < 0.5 * float(fr[2])
    # the posterior predictive band of the final model, calibrated out of sample on the estimation record's end,
    # holds at least about 90 % of the held-out data (a decay's quiet tail is easier than that end block, so it
    # errs wide) and is not wider than a few free-run errors
    assert 75 <= float(err["share of the data inside the 90 % posterior predictive band"][3])
    band = rep["reported"]["free_run"]
    assert band["band_halfwidth_rms"] < 4 * band["rms_error"], band
    # the residual tests before and after: white after, not before
    tests = {r[0]: r for r in _cells(html, "<h2>Residual tests before and after</h2>")[1:]}
    lb = tests["Ljung-Box Q"]
    p = [float(re.search(r"p = ([0-9.e+-]+)", x).group(1)) for x in lb[1:3]]
    assert p[0] < 0.01 < p[1], lb
    # every figure the page links exists
    for name in re.findall(r"<img src='([^']+)'", html):
        assert (tmp_path / name).stat().st_size > 1000, name


def test_less_white_innovations_after_the_loop_are_said():
    from ardflow.service.reports.diagnosis import _tests_table

    before, after = {"ljung_box": 3.6e4, "ljung_box_p": 0.0}, {"ljung_box": 6.1e4, "ljung_box_p": 0.0}
    text = _tests_table({"tests_before": {"y": before}, "tests_after": {"y": after}}, "y")
    assert "less white after the loop" in text and "3.6e+04 -> 6.1e+04" in text
    text = _tests_table({"tests_before": {"y": after}, "tests_after": {"y": before}}, "y")
    assert "less white" not in text


def test_a_candidate_confirmed_under_its_refined_shape_keeps_its_colour():
    """The screen names a shaped candidate by its screened shape, the confirmation by its refined one: the
    figure matches them, and tells added from confirmed-not-added from screened-only."""
    from ardflow.service.reports.diagnosis_figures import candidate_fates

    report = {"confirmed": [{"effect": "dry_friction(v,vs=6.5)", "screened_effect": "dry_friction(v,vs=7)",
                             "target": "v"},
                            {"effect": "cubic_damping(v)", "screened_effect": "cubic_damping(v)", "target": "v"}],
              "added": [{"effect": "dry_friction(v,vs=6.5)", "target": "v"}]}
    screened = [{"effect": "dry_friction(v,vs=7)", "target": "v"}, {"effect": "cubic_damping(v)", "target": "v"},
                {"effect": "offset", "target": "v"}]
    assert candidate_fates(report, screened) == ["added", "confirmed", "screened"]


def test_progress_promises_no_time_left_and_the_demo_speaks_the_users_words():
    from ardflow.service.client import _progress_line
    from ardflow.service.commands.study import CHECKS_TITLE
    from ardflow.service.reports.paper import reference_checks

    st = {"models": {"M2": {"trials_done": 3, "max_trials": 60, "elapsed_s": 40.0, "eta_s": 760.0,
                            "stage": "trial", "best_log_evidence": 1.5}}}
    line = _progress_line(st)
    assert "3 of at most 60 trials" in line and "eta" not in line.lower() and "left" not in line
    summary = {"models": [{"name": "M1", "probability": 0.0, "pruned": ["a3", "a5", "a6"], "kept": ["a4"]},
                          {"name": "M2", "probability": 1.0, "pruned": ["a5", "a6"], "kept": ["a3", "a4"],
                           "q005": {}, "q995": {}}]}
    text = CHECKS_TITLE + " ".join(str(c) for c in reference_checks(summary, {}))
    assert "documented difference" in text or "docs/" in text
    assert "issue" not in text.lower() and "README" not in text


def test_an_added_mode_shows_its_frequency_and_parameters_with_intervals():
    """The page's "States added" gives a second mode's equation, its frequency in cycles per time unit (its
    angular frequency w over 2 pi, with w's interval) and each parameter's 99 % interval."""
    import html
    import math
    from types import SimpleNamespace

    from ardflow.ardcore.effects.states import Lag
    from ardflow.ardcore.loop.states import state_summary
    from ardflow.service.reports.diagnosis import _states_table

    names = ("w_mode_y", "z_mode_y", "mu_mode_y")
    mean, sd = dict(zip(names, (9.0, 0.03, 0.3))), dict(zip(names, (0.01, 0.001, 0.004)))
    row = SimpleNamespace(mean=mean, sd=sd, q005={n: mean[n] - 2.6 * sd[n] for n in names},
                          q995={n: mean[n] + 2.6 * sd[n] for n in names})
    state = state_summary(row, Lag("y", "v", "mode"))
    cells = _cells(_states_table([state]), "States added")
    assert cells[1][:3] == ["mode_y", "mode", html.escape(state["equation"])] and "mu_mode_y" in state["equation"]
    freq = next(c for c in cells if c[3].startswith("frequency"))
    assert math.isclose(float(freq[4]), 9.0 / (2 * math.pi), rel_tol=1e-3), freq
    lo, hi = (float(x) for x in freq[5].strip("[]").split(","))
    assert math.isclose(lo, 8.974 / (2 * math.pi), rel_tol=1e-3)
    assert math.isclose(hi, 9.026 / (2 * math.pi), rel_tol=1e-3)
    assert [c[3] for c in cells[1:]] == ["frequency (cycles per time unit)", *names]
