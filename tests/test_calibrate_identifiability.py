"""Identifiability verdicts of the batch calibration (uwbimu.calibration.identifiability)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gtsam")

from uwbimu.calibration import CalibrationOptions, calibrate  # noqa: E402
from uwbimu.estimation.timeoffset import information_verdict  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402

NO_PROFILE = {"td_profile": {"enabled": False}}


def _calibrate(name: str, duration: float = 20.0):
    sc = builtin_scenario(name)
    sc = sc.model_copy(update={"duration": duration})
    return calibrate(simulate(sc), CalibrationOptions.model_validate(NO_PROFILE))


def test_information_verdict_thresholds():
    assert information_verdict(0.01, 1.0) == ("identified", pytest.approx(9999.0))
    assert information_verdict(0.5, 1.0)[0] == "weakly identified"  # gain 3
    assert information_verdict(0.9, 1.0)[0] == "not identified"  # gain 0.23
    assert information_verdict(float("nan"), 1.0)[0] == "not identified"


def test_excited_flight_identifies_every_lever_axis():
    res = _calibrate("calibration-flight")
    cal = res.calibration
    idf = cal["identifiability"]
    assert set(idf["lever_arm"]) == {"x", "y", "z"}
    for i, c in enumerate("xyz"):
        e = idf["lever_arm"][c]
        assert e["verdict"] == "identified"
        assert e["sd"] == cal["lever_arm_sd"][i]  # the reported (honest) sigma
        assert e["information_gain"] == pytest.approx((0.5 / e["sd"]) ** 2 - 1.0, rel=1e-3)
    assert idf["time_offset"]["verdict"] == cal["time_offset"]["verdict"]
    assert set(idf["anchor_bias"]) == set(cal["anchor_bias_sd"])
    assert not [e for e in res.events if e["kind"] == "lever_arm_not_identified"]


def test_pure_translation_leaves_the_lever_arm_to_the_prior():
    """Constant attitude: the antenna offset is a constant shift of the trajectory, seen only through the prior."""
    res = _calibrate("translation")
    idf = res.calibration["identifiability"]["lever_arm"]
    assert all(idf[c]["verdict"] == "not identified" for c in "xyz"), idf
    assert all(0.3 < res.calibration["lever_arm_sd"][i] / 0.5 <= 1.0 for i in range(3))
    ev = [e for e in res.events if e["kind"] == "lever_arm_not_identified"]
    assert len(ev) == 1 and set(ev[0]["axes"]) == {"x", "y", "z"}
    assert ev[0]["severity"] == "warning"
    assert np.all(np.isfinite([idf[c]["information_gain"] for c in "xyz"]))


def test_one_verdict_per_tag_and_axis():
    res = _calibrate("two-tags")
    cal = res.calibration
    idf = cal["identifiability"]["lever_arm"]
    assert set(idf) == set(cal["tags"])
    for tag, t in cal["tags"].items():
        assert [idf[tag][c]["sd"] for c in "xyz"] == t["lever_arm_sd"]
