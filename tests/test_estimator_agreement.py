"""The batch checked against the ESKF it started from (uwbimu.calibration.agreement): the stated rule."""

from __future__ import annotations

import pytest

from uwbimu.calibration.agreement import Z_DISAGREE, agreement_message, estimator_agreement


def _eskf(td=0.020, td_sd=0.004, lever=(0.1, 0.0, 0.05), lever_sd=(0.01, 0.01, 0.01), scale=1.0,
          td_verdict="identified", lever_verdict="identified"):
    return {"lever_arm": list(lever), "lever_arm_sd": list(lever_sd), "time_offset": td, "time_offset_sd": td_sd,
            "time_offset_verdict": td_verdict, "lever_arm_verdict": {c: lever_verdict for c in "xyz"},
            "sigma_scale": scale}


def _batch(td=0.020, td_sd=0.004, verdict="identified", lever=(0.1, 0.0, 0.05), lever_sd=(0.01, 0.01, 0.01)):
    return {"lever_arm": list(lever), "lever_arm_sd": list(lever_sd),
            "time_offset": {"value": td, "sd": td_sd, "verdict": verdict},
            "identifiability": {"lever_arm": {c: {"verdict": "identified"} for c in "xyz"}}}


def test_agreement_within_three_combined_sigma():
    ev = estimator_agreement(_eskf(td=0.020), _batch(td=0.020 + 2.9 * (2 ** 0.5) * 0.004))
    assert ev["kind"] == "estimators_agree" and ev["disagreeing"] == []
    assert agreement_message(ev) is None
    assert {r["name"] for r in ev["parameters"]} == {"lever_arm_x", "lever_arm_y", "lever_arm_z", "time_offset"}


@pytest.mark.parametrize("eskf_kw,batch_kw,modes,favours", [
    ({"scale": 2.5}, {}, None, "batch"),                                    # ESKF residuals refute its model
    ({}, {"verdict": "not_identified"}, None, "eskf"),                       # batch does not identify it
    ({}, {}, None, "neither"),                                               # both confident, both healthy
    ({"scale": 2.5}, {"verdict": "not_identified"}, None, "neither"),
    ({}, {}, {"time_offset": "consider"}, "batch"),                          # ESKF held it
    ({}, {"verdict": "not_identified"}, {"time_offset": "consider"}, "neither"),  # held, batch unsure
])
def test_disagreement_names_the_favoured_estimate(eskf_kw, batch_kw, modes, favours):
    ev = estimator_agreement(_eskf(td=0.020, **eskf_kw), _batch(td=-0.010, **batch_kw), modes)
    assert ev["kind"] == "estimators_disagree"
    assert ev["disagreeing"] == ["time_offset"]
    row = next(r for r in ev["parameters"] if r["name"] == "time_offset")
    assert row["z"] > Z_DISAGREE and row["favours"] == favours
    assert agreement_message(ev) is not None


def test_numeric_batch_time_offset_and_missing_sigma():
    b = _batch()
    b["time_offset"], b["time_offset_sd"] = 0.020, None  # t_d not estimated by the batch: no comparison
    ev = estimator_agreement(_eskf(), b)
    assert "time_offset" not in {r["name"] for r in ev["parameters"]}
    assert ev["kind"] == "estimators_agree"


def test_calibrate_carries_the_agreement_on_a_clean_simulation():
    """End to end: ``calibrate`` compares its answer with the initialising ESKF's; on a clean simulated flight they
    agree, the event is in the events and in calibration.yaml's ``estimators`` (plain, finite floats)."""
    pytest.importorskip("gtsam")
    import math

    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.calibration.outputs import calibration_document
    from uwbimu.sim import builtin_scenario, simulate

    # 15 s: on 8 s the ESKF's t_d is 185 +- 25 ms against the truth's 30 ms (the batch: 45 +- 25 ms), and the check
    # rightly says they disagree
    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 15.0}))
    r = calibrate(ds, CalibrationOptions(td_profile={"enabled": False}))
    ev = r.calibration["estimators"]
    assert ev["kind"] == "estimators_agree" and ev["disagreeing"] == [], ev
    assert ev["severity"] == "info" and "message" not in ev
    assert {p["name"] for p in ev["parameters"]} >= {"lever_arm_x", "lever_arm_y", "lever_arm_z"}
    # the batch's per-axis lever-arm verdicts reach the comparison (one tag: a flat identifiability section)
    assert all(p["batch_verdict"] for p in ev["parameters"] if p["name"].startswith("lever_arm"))
    for p in ev["parameters"]:
        assert all(type(p[k]) is float and math.isfinite(p[k]) for k in ("eskf", "eskf_sd", "batch", "batch_sd", "z"))
        assert p["z"] <= Z_DISAGREE
    assert [e for e in r.events if e["kind"] == "estimators_agree"] == [ev]
    assert calibration_document(r)["estimators"]["kind"] == "estimators_agree"


def test_batch_lever_verdicts_of_one_and_several_tags():
    from uwbimu.calibration.agreement import _batch_lever_verdicts

    one = {"identifiability": {"lever_arm": {c: {"verdict": "weakly identified"} for c in "xyz"}}}
    two = {"identifiability": {"lever_arm": {"front": {c: {"verdict": "identified"} for c in "xyz"},
                                             "back": {c: {"verdict": "not identified"} for c in "xyz"}}}}
    assert _batch_lever_verdicts(one) == {c: "weakly identified" for c in "xyz"}
    assert _batch_lever_verdicts(two) == {c: "identified" for c in "xyz"}
