"""UWB clock drift relative to the IMU (issue 14, item 4): detected, rate recovered within 3 sd, handled.

A 180 s simulated calibration flight (300 ppm changes the offset by 54 ms over it, about 20 final
t_d sds); the UWB clock runs fast by ``ppm``: a range at UWB time ``t`` is stamped
``t + ppm 1e-6 (t - t0)``.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.eval.clock_faults import handle_clock_faults
from uwbimu.sim import builtin_scenario, simulate

DURATION = 180.0


@pytest.fixture(scope="module")
def flight():
    return simulate(builtin_scenario("calibration-flight").updated(duration=DURATION))


def drifted(ds, ppm: float):
    u = ds.uwb.copy()
    t = u["t"].to_numpy()
    u["t"] = t + ppm * 1e-6 * (t - t.min())
    out = copy.copy(ds)
    out.uwb = u
    return out


@pytest.mark.parametrize("ppm", [3000.0, 300.0])
def test_clock_drift_detected_rate_recovered_and_handled(flight, ppm):
    bad = drifted(flight, ppm)
    res = run_eskf(bad, EskfOptions())
    fixed, _ = handle_clock_faults(res, bad, lambda d: run_eskf(d, EskfOptions()))
    events = [e for e in fixed.events if str(e.get("kind", "")).startswith("clock_")]
    assert [e["kind"] for e in events] == ["clock_drift"]
    ev = events[0]
    assert ev["z"] > ev["crit"]
    assert ev["t0"] == pytest.approx(float(bad.uwb["t"].min())) and ev["t1"] > ev["t0"]
    assert 0 < ev["sigma_ppm"] < ppm / 3
    assert abs(ev["rate_ppm"] - ppm) < 3 * ev["sigma_ppm"]
    # handled: t_d0 (the offset at t0, where the simulated drift starts) and the lever arm within
    # 3 sd of the truth
    c, tr = fixed.calibration, flight.meta.truth
    assert ev["t_d0_sd"] >= c["time_offset_sd"]
    assert abs(ev["t_d0"] - tr.time_offset) < 3 * ev["t_d0_sd"]
    assert np.all(np.abs(np.asarray(c["lever_arm"]) - tr.lever_arm) < 3 * np.asarray(c["lever_arm_sd"]))


def test_no_drift_reported_on_the_clean_long_log(flight):
    res = run_eskf(flight, EskfOptions())
    out, _ = handle_clock_faults(copy.deepcopy(res), flight, lambda d: run_eskf(d, EskfOptions()))
    assert not [e for e in out.events if str(e.get("kind", "")).startswith("clock_")]
