"""Where the batch starts (issue 27 item 4): the ESKF only when its run is healthy, else a robust multilateration.

The health rule (:func:`uwbimu.calibration.start_check.eskf_health`) on constructed ESKF results, one check at a
time; the multilateration on a simulated log; the fallback start end to end on a simulated log whose ESKF is
made unhealthy (diverged, and its trajectory moved off), recorded as the ``calibration_start`` event.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from uwbimu.calibration import start_check as S


def _result(n=200, offset=0.0, events=(), accepted=0.9, lever=(0.0, 0.0, 0.0)):
    """An ESKF-like result on a straight line at 1 m/s (identity attitude), its position moved by ``offset`` [m]."""
    t = np.linspace(0.0, 20.0, n)
    st = np.zeros((n, 16))
    st[:, 0] = t + offset
    st[:, 3] = 1.0
    st[:, 6] = 1.0
    acc = np.arange(1000) < accepted * 1000
    res = pd.DataFrame({"t": np.linspace(0, 20, 1000), "accepted": acc})
    return SimpleNamespace(t=t, states=st, events=list(events), residuals=res,
                           calibration={"lever_arm": list(lever)})


def _track(n=40, sd=0.1, lever=(0.0, 0.0, 0.0)):
    t = np.linspace(0.5, 19.5, n)
    return pd.DataFrame({"t": t, "px": t + lever[0], "py": np.full(n, lever[1]), "pz": np.full(n, lever[2]),
                         "sd": np.full(n, sd), "n": 20})


def test_healthy_result_passes_every_check():
    h = S.eskf_health(_result(), _track())
    assert h["healthy"] and h["failed"] == []
    assert h["checks"]["multilateration"]["median_ratio"] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("kind", S.DIVERGENCE_EVENTS)
def test_divergence_event_fails(kind):
    h = S.eskf_health(_result(events=[{"t": 3.0, "kind": kind}]), _track())
    assert not h["healthy"] and h["failed"] == ["diverged"]
    assert h["checks"]["diverged"]["events"] == 1


def test_non_finite_states_fail():
    r = _result()
    r.states[50, 0] = np.nan
    h = S.eskf_health(r, _track())
    assert "non_finite" in h["failed"]


def test_too_few_accepted_updates_fail():
    h = S.eskf_health(_result(accepted=0.4), _track())
    assert h["failed"] == ["accepted_fraction"]
    assert h["checks"]["accepted_fraction"]["value"] == pytest.approx(0.4)
    assert S.eskf_health(_result(accepted=0.6), _track())["healthy"]


def test_agreement_bound_scales_with_the_fixes_sd():
    # 0.5 m off: 5 sd of 0.1 m fixes (fails), 1 sd of 0.5 m fixes (passes)
    h = S.eskf_health(_result(offset=0.5), _track(sd=0.1))
    assert h["failed"] == ["multilateration"]
    assert h["checks"]["multilateration"]["median_ratio"] == pytest.approx(5.0, rel=1e-6)
    assert S.eskf_health(_result(offset=0.5), _track(sd=0.5))["healthy"]


def test_agreement_uses_the_antenna_not_the_imu():
    lever = (0.0, 0.0, 0.3)  # the tag 30 cm above the IMU: the fixes are 30 cm above the ESKF's IMU track
    assert S.eskf_health(_result(lever=lever), _track(sd=0.05, lever=lever))["healthy"]
    assert not S.eskf_health(_result(), _track(sd=0.05, lever=lever))["healthy"]


def test_lost_over_part_of_the_log_fails():
    r = _result()
    r.states[r.t > 14.0, 0] += 5.0  # right for 70 % of the log, then 5 m off
    h = S.eskf_health(r, _track(sd=0.1))
    assert h["checks"]["multilateration"]["median_ratio"] <= S.AGREEMENT_K
    assert h["checks"]["multilateration"]["far_fraction"] > S.MAX_FAR_FRACTION
    assert h["failed"] == ["multilateration"]


def test_agreement_skipped_without_enough_fixes():
    h = S.eskf_health(_result(offset=3.0), _track(n=S.MIN_FIXES - 1))
    assert h["healthy"] and h["checks"]["multilateration"]["skipped"]


@pytest.fixture(scope="module")
def sim():
    from uwbimu.sim import builtin_scenario, simulate

    sc = builtin_scenario("calibration-flight")
    return simulate(sc.model_copy(update={"duration": 30.0}))


def test_multilateration_track_follows_the_antenna(sim):
    from uwbimu.metrics.filter import truth_at

    tr = S.multilaterate_track(sim)
    assert len(tr) > 40
    from uwbimu.models.quaternion import quat_to_rotmat

    ref, q, _, m = truth_at(sim, tr["t"].to_numpy())
    lever = np.asarray(sim.meta.truth.lever_arm, float)
    ant = ref + np.array([quat_to_rotmat(qq) @ lever for qq in q])
    err = np.linalg.norm(tr[["px", "py", "pz"]].to_numpy()[m] - ant[m], axis=1)
    assert np.median(err) < 0.15


def _unhealthy(eskf, shift=3.0):
    """The ESKF result with a supervisor divergence and its trajectory moved ``shift`` m in x after 10 s."""
    import copy

    bad = copy.deepcopy(eskf)
    bad.states = np.array(bad.states, float)
    bad.states[bad.t > bad.t[0] + 10.0, 0] += shift
    bad.events = list(bad.events) + [{"t": float(bad.t[0]) + 10.0, "kind": "divergence", "reason": "test"}]
    return bad


def test_seed_from_multilateration_is_near_the_truth(sim):
    from uwbimu.metrics.filter import truth_at

    tr = S.multilaterate_track(sim)
    seed = S.multilateration_seed(sim, tr, np.zeros(3), 0.0)
    ref, _, _, m = truth_at(sim, seed.t)
    err = np.linalg.norm(seed.states[m, :3] - ref[m], axis=1)
    # the antenna track with the lever arm at its prior (0): within the sim's lever arm plus the fixes' error
    assert np.median(err) < np.linalg.norm(sim.meta.truth.lever_arm) + 0.15
    assert np.all(np.isfinite(seed.states))


@pytest.mark.slow
def test_unhealthy_eskf_starts_the_batch_from_multilateration(sim):
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.metrics.filter import truth_at

    bad = _unhealthy(run_eskf(sim, EskfOptions()))
    o = CalibrationOptions.model_validate({"td_profile": {"enabled": False}})
    r = calibrate(sim, o, eskf=bad)
    ev = [e for e in r.events if e["kind"] == "calibration_start"]
    assert len(ev) == 1 and ev[0]["source"] == "multilateration"
    assert "diverged" in ev[0]["reason"].split("+")
    assert r.calibration["start"]["source"] == "multilateration"
    assert r.eskf is bad or r.eskf.events == bad.events  # the ESKF run is kept for the comparison
    c = r.calibration
    truth = np.asarray(sim.meta.truth.lever_arm, float)
    assert np.all(np.abs(np.asarray(c["lever_arm"]) - truth) < 3.0 * np.asarray(c["lever_arm_sd"]) + 0.02)
    tr = r.trajectory
    ref, _, _, m = truth_at(sim, tr["t"].to_numpy())
    rmse = float(np.sqrt(np.mean(np.sum((tr[["px", "py", "pz"]].to_numpy()[m] - ref[m]) ** 2, axis=1))))
    assert rmse < 0.1


def test_healthy_eskf_starts_the_batch_from_itself(sim):
    from uwbimu.calibration import CalibrationOptions, calibrate

    r = calibrate(sim, CalibrationOptions.model_validate({"td_profile": {"enabled": False}}))
    ev = [e for e in r.events if e["kind"] == "calibration_start"]
    assert len(ev) == 1 and ev[0]["source"] == "eskf" and ev[0]["reason"] == "healthy"
    assert ev[0]["health"]["checks"]["multilateration"]["ok"]


def test_multilateration_locates_one_tag_of_several(sim):
    """With a tag column, only the named tag's rows enter the fixes (two antennas mixed would blur them)."""
    import dataclasses

    u = sim.uwb.copy()
    other = u.copy()
    other["range"] = other["range"] + 2.0  # a second tag whose ranges would pull the fixes 2 m off
    u["tag"], other["tag"] = "t0", "t1"
    two = dataclasses.replace(sim, uwb=pd.concat([u, other]).sort_values("t", kind="stable").reset_index(drop=True))
    one = S.multilaterate_track(sim)
    only = S.multilaterate_track(two, tag="t0")
    assert len(only) == len(one)
    np.testing.assert_allclose(only[["px", "py", "pz"]].to_numpy(), one[["px", "py", "pz"]].to_numpy(), atol=1e-6)
