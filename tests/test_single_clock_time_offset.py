"""A log whose streams share one clock (dataset.yaml ``single_clock: true``) holds t_d at 0 unless asked."""

from __future__ import annotations

import dataclasses

import pytest

from uwbimu.estimation.eskf import run_eskf
from uwbimu.estimation.options import EskfOptions, TimeOffsetOptions
from uwbimu.sim import builtin_scenario, simulate


@pytest.fixture(scope="module")
def single_clock_log():
    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0}))
    return dataclasses.replace(ds, meta=ds.meta.model_copy(update={"single_clock": True}))


def _events(r, kind):
    return [e for e in r.events if e["kind"] == kind]


def test_single_clock_log_holds_t_d_at_zero_with_an_event(single_clock_log):
    r = run_eskf(single_clock_log, EskfOptions(noise="preset"))
    (ev,) = _events(r, "time_offset_single_clock")
    assert ev["mode"] == "fixed" and ev["t_d"] == 0.0
    assert r.calibration["time_offset"] == 0.0
    assert r.calibration["time_offset_verdict"] == "fixed"
    assert r.config["resolved"]["modes"]["time_offset"] == "fixed"


def test_configured_time_offset_is_estimated_on_a_single_clock_log(single_clock_log):
    opts = EskfOptions(noise="preset", time_offset=TimeOffsetOptions(mode="estimate"))
    r = run_eskf(single_clock_log, opts)
    assert _events(r, "time_offset_single_clock") == []
    assert r.config["resolved"]["modes"]["time_offset"] == "estimate"
    assert r.calibration["time_offset_sd"] > 0.0


def test_log_without_the_single_clock_fact_estimates_t_d(single_clock_log):
    ds = dataclasses.replace(single_clock_log, meta=single_clock_log.meta.model_copy(update={"single_clock": None}))
    r = run_eskf(ds, EskfOptions(noise="preset"))
    assert _events(r, "time_offset_single_clock") == []
    assert r.calibration["time_offset_sd"] > 0.0


def test_batch_holds_t_d_at_its_prior_on_a_single_clock_log(single_clock_log):
    """The batch follows the ESKF's rule: one answer for t_d on a single-clock log (held, event, verdict)."""
    from uwbimu.calibration import calibrate

    r = calibrate(single_clock_log)
    (ev,) = _events(r, "time_offset_single_clock")
    assert ev["mode"] == "fixed" and ev["t_d"] == 0.0
    td = r.calibration["time_offset"]
    assert td["value"] == 0.0 and td["held_at_prior"] is True and td["verdict"] == "fixed"
    assert td["sd"] is None and r.calibration["conditional_on_time_offset"] == 0.0


@pytest.mark.parametrize("field", [{"time_offset_prior_sd": 0.1}, {"time_offset_prior": 0.05},
                                   {"td_profile": {"enabled": True}}])
def test_batch_estimates_t_d_when_the_user_configures_it(single_clock_log, field):
    from uwbimu.calibration.batch import single_clock_hold
    from uwbimu.calibration.options import CalibrationOptions

    assert single_clock_hold(single_clock_log, CalibrationOptions()) is not None
    assert single_clock_hold(single_clock_log, CalibrationOptions(**field)) is None
    ds = dataclasses.replace(single_clock_log, meta=single_clock_log.meta.model_copy(update={"single_clock": None}))
    assert single_clock_hold(ds, CalibrationOptions()) is None
