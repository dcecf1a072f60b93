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
