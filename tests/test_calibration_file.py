"""calibration.yaml's one schema (uwbimu.io.calibration_file): version 1 of both estimators reads as version 2."""

from __future__ import annotations


import pytest
import yaml

from uwbimu.io.calibration_file import (SCHEMA_VERSION, effective_time_offset_mode, migrate, read_calibration,
                                        time_offset_entry, time_offset_sd, time_offset_value)


def test_eskf_schema_1_becomes_the_mapping():
    old = {"lever_arm": [0.1, 0.0, 0.0], "lever_arm_sd": [0.01, float("nan"), 0.02], "time_offset": 0.03,
           "time_offset_sd": 0.002, "time_offset_mode": "estimate", "time_offset_verdict": "identified",
           "time_offset_verdict_reason": "gain 100x"}
    new = migrate(old)
    assert new["schema_version"] == SCHEMA_VERSION
    assert new["time_offset"] == {"value": 0.03, "sd": 0.002, "unit": "s", "mode": "estimate",
                                  "verdict": "identified", "verdict_reason": "gain 100x"}
    assert not {"time_offset_sd", "time_offset_mode", "time_offset_verdict"} & set(new)
    assert new["lever_arm_sd"] == [0.01, None, 0.02]  # never NaN
    assert old["time_offset"] == 0.03  # the input is not changed
    assert migrate(new) == new  # idempotent


def test_batch_schema_1_gains_unit_and_mode():
    held = migrate({"time_offset": {"value": 0.3, "sd": None, "verdict": "at_grid_edge", "held_at_prior": True,
                                    "advice": "widen"}, "time_offset_sd": None})
    assert held["time_offset"]["mode"] == "fixed" and held["time_offset"]["sd"] is None
    assert held["time_offset"]["sd_status"] == "not estimated" and held["time_offset"]["advice"] == "widen"
    assert "time_offset_sd" not in held
    free = migrate({"time_offset": {"value": 0.01, "sd": 0.002, "verdict": "identified", "held_at_prior": False}})
    assert free["time_offset"]["mode"] == "estimate" and free["time_offset"]["unit"] == "s"


def test_entry_never_writes_nan():
    e = time_offset_entry(0.01, float("nan"), "estimate", "not identified")
    assert e["sd"] is None and e["sd_status"] == "not estimated"
    assert time_offset_entry(0.01, 0.002, "fixed")["sd"] is None  # a fixed t_d has no sigma
    assert time_offset_entry(0.01, 0.002, "consider", configured_mode="estimate")["configured_mode"] == "estimate"
    assert "configured_mode" not in time_offset_entry(0.01, 0.002, "estimate", configured_mode="estimate")


def test_helpers_read_both_shapes():
    assert time_offset_value({"time_offset": 0.02}) == time_offset_value({"time_offset": {"value": 0.02}}) == 0.02
    assert time_offset_sd({"time_offset": 0.02, "time_offset_sd": 0.001}) == 0.001
    assert time_offset_sd({"time_offset": {"value": 0.02, "sd": None}}) is None
    assert time_offset_sd({"time_offset": 0.0, "time_offset_sd": float("nan")}) is None


def test_mode_from_the_events():
    assert effective_time_offset_mode("estimate", []) == ("estimate", "estimate")
    assert effective_time_offset_mode("estimate", [{"kind": "time_offset_held"}]) == ("consider", "estimate")
    # the rerun with the unidentified blocks held already reports consider: the user's mode was estimate
    held = [{"kind": "calibration_held", "blocks": ["lever_arm", "time_offset"]}]
    assert effective_time_offset_mode("consider", held) == ("consider", "estimate")
    assert effective_time_offset_mode("estimate", [{"kind": "calibration_held", "blocks": ["lever_arm"]}]) == \
        ("estimate", "estimate")


def test_read_calibration(tmp_path):
    assert read_calibration(tmp_path) is None
    (tmp_path / "calibration.yaml").write_text(yaml.safe_dump({"time_offset": 0.01, "time_offset_sd": 0.001}))
    assert read_calibration(tmp_path)["time_offset"]["sd"] == 0.001
    (tmp_path / "calibration.yaml").write_text("schema_version: 9\n")
    with pytest.raises(ValueError, match="schema_version"):
        read_calibration(tmp_path / "calibration.yaml")
    (tmp_path / "calibration.yaml").write_text("- 1\n")
    with pytest.raises(ValueError, match="calibration.yaml"):
        read_calibration(tmp_path / "calibration.yaml")


def test_eskf_extra_time_offset_keys_fold_into_the_mapping():
    new = migrate({"time_offset": 0.03, "time_offset_sd": 0.004, "time_offset_sd_filter": 0.002,
                   "time_offset_filter": 0.025, "lever_arm_sd_filter": [0.01, 0.01, 0.01]})
    assert new["time_offset"]["sd_filter"] == 0.002 and new["time_offset"]["value_filter"] == 0.025
    assert "time_offset_sd_filter" not in new and "time_offset_filter" not in new
    assert new["lever_arm_sd_filter"] == [0.01, 0.01, 0.01]  # per-axis lists stay beside lever_arm_sd
