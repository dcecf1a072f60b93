"""UWB clock jumps (issue 14, item 4): detected with their time, corrected, calibration restored.

A 60 s simulated calibration flight; the UWB clock jumps mid-log (t = 30 s).  Assertions are on
the structured events of :func:`uwbimu.eval.clock_faults.handle_clock_faults`.  Drift lives in
``tests/test_clock_drift.py`` (it needs a longer log).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.eval.clock_faults import detect_clock_faults, handle_clock_faults
from uwbimu.eval.clock_windows import ALPHA, consistency_tests, windowed_time_offsets
from uwbimu.sim import builtin_scenario, simulate

DURATION = 60.0
AT = 30.0
#: Stated tolerance of the jump time [s] (docs/estimator.md, "Clock faults").
TIME_TOL = 0.5


def _flight(seed: int = 1):
    return simulate(builtin_scenario("calibration-flight").updated(duration=DURATION, seeds={"noise": seed}))


@pytest.fixture(scope="module")
def flight():
    return _flight()


def _with_uwb(ds, u):
    out = copy.copy(ds)
    out.uwb = u.reset_index(drop=True)
    return out


def jumped(ds, jump: float, at: float = AT):
    """The UWB clock jumps by ``jump`` s at ``at`` (later stamps when jump > 0).

    A backward jump (jump < 0) comes with a dropout of its length, so the stamps stay monotonic
    and gap-free: nothing in the stamps shows it.
    """
    u = ds.uwb.copy()
    t = u["t"].to_numpy().copy()
    if jump < 0:
        keep = ~((t >= at) & (t < at - jump))
        u, t = u[keep].copy(), t[keep]
    t[t >= at] += jump
    u["t"] = t
    return _with_uwb(ds, u)


def _rerun(d):
    return run_eskf(d, EskfOptions())


def _clock_events(res):
    return [e for e in res.events if str(e.get("kind", "")).startswith("clock_")]


def _within_3sd(res, ds):
    c, tr = res.calibration, ds.meta.truth
    lever = np.abs(np.asarray(c["lever_arm"]) - np.asarray(tr.lever_arm)) / np.asarray(c["lever_arm_sd"])
    td = abs(c["time_offset"] - tr.time_offset) / c["time_offset_sd"]
    return lever, td


@pytest.mark.parametrize("jump", [0.3, -0.3, -0.2, 0.12])
def test_clock_jump_detected_timed_and_corrected(flight, jump):
    bad = jumped(flight, jump)
    res = run_eskf(bad, EskfOptions())
    fixed, corrected = handle_clock_faults(res, bad, _rerun)
    events = _clock_events(fixed)
    assert [e["kind"] for e in events] == ["clock_jump"]
    ev = events[0]
    # the first range stamped after the jump: AT + jump for a forward jump, AT for a backward one
    assert abs(ev["t"] - (AT + max(jump, 0.0))) < TIME_TOL
    assert ev["z"] > ev["crit"] and ev["alpha"] == ALPHA
    # size = change of the effective offset = -jump, within 3 sd of its final estimate
    assert np.isfinite(ev["sigma"]) and ev["sigma"] > 0
    assert abs(ev["size"] + jump) < 3 * ev["sigma"]
    # after the correction the calibration is that of a healthy log (3 sd)
    lever, td = _within_3sd(fixed, flight)
    assert np.all(lever < 3) and td < 3
    # and the corrected log itself passes the test
    assert detect_clock_faults(fixed, corrected) == []


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_no_clock_fault_on_clean_logs(seed, flight):
    ds = flight if seed == 1 else _flight(seed)
    res = run_eskf(ds, EskfOptions())
    out, same = handle_clock_faults(copy.deepcopy(res), ds, _rerun)
    assert _clock_events(out) == [] and same is ds


def test_a_dropout_is_no_jump(flight):
    u = flight.uwb
    dropout = _with_uwb(flight, u[~((u["t"] > 30) & (u["t"] < 30.3))])
    out, _ = handle_clock_faults(run_eskf(dropout, EskfOptions()), dropout, _rerun)
    assert _clock_events(out) == []


def test_window_estimates_are_scale_aware(flight):
    """The verdict does not change when the window sds are misstated: the measured scatter rescales them."""
    res = run_eskf(jumped(flight, -0.2), EskfOptions())
    win = windowed_time_offsets(res)
    c1 = consistency_tests(win, float(res.t[0]))
    shrunk = dict(win, sd=win["sd"] / 10)  # sds 10x too optimistic
    c2 = consistency_tests(shrunk, float(res.t[0]))
    assert c1["verdict"] == c2["verdict"] == "jump"
    assert c2["scale"] > 5 * c1["scale"]
    clean = windowed_time_offsets(run_eskf(flight, EskfOptions()))
    assert consistency_tests(dict(clean, sd=clean["sd"] / 10), float(res.t[0]))["verdict"] is None
