"""Trajectory alignment, robust time association, ATE/RPE and the evaluate CLI."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from uwbimu.metrics.align import align_trajectories
from uwbimu.metrics.trajectory import (
    associate,
    detect_attitude_glitches,
    detect_glitches,
    evaluate_trajectory,
    relative_pose_error,
)
from uwbimu.models.quaternion import quat_exp, quat_multiply, rotmat_to_quat

COLS = ["t", "px", "py", "pz", "qw", "qx", "qy", "qz"]


def _truth(t):
    p = np.c_[2 * np.cos(0.3 * t), 1.5 * np.sin(0.5 * t), 1 + 0.3 * np.sin(0.2 * t)]
    q = quat_exp(np.c_[0.1 * np.sin(t), 0.1 * np.cos(0.7 * t), 0.5 * t])
    return p, q


def _frames(seed=0):
    R = Rotation.from_euler("zyx", [40, 5, -3], degrees=True).as_matrix()
    return R, np.array([1.0, -2.0, 0.5])


def test_align_recovers_known_se3_and_position():
    rng = np.random.default_rng(0)
    pe = rng.normal(size=(200, 3)) * [3, 2, 1]
    R, tr = _frames()
    pg = pe @ R.T + tr
    al = align_trajectories(pe, pg, "se3")
    np.testing.assert_allclose(al.R, R, atol=1e-10)
    np.testing.assert_allclose(al.t, tr, atol=1e-10)
    assert al.rms_fit < 1e-10
    al_p = align_trajectories(pe, pe + tr, "position")
    np.testing.assert_allclose(al_p.t, tr, atol=1e-12)
    np.testing.assert_allclose(al_p.R, np.eye(3))
    al_n = align_trajectories(pe, pg, "none")
    np.testing.assert_allclose(al_n.apply_positions(pe), pe)
    # quaternions are carried into the ground-truth frame too
    q = quat_exp(rng.normal(size=(5, 3)))
    np.testing.assert_allclose(np.abs(np.sum(al.apply_quaternions(q) * quat_multiply(rotmat_to_quat(R), q), axis=1)),
                               1.0, atol=1e-9)


def test_align_refuses_degenerate_and_bad_mode():
    line = np.c_[np.linspace(0, 1, 10), np.zeros(10), np.zeros(10)]
    with pytest.raises(ValueError, match="straight line"):
        align_trajectories(line, line, "se3")
    with pytest.raises(ValueError, match="align mode"):
        align_trajectories(line, line, "sim3")


def test_glitch_detection_single_and_short_bursts_without_false_alarms():
    rng = np.random.default_rng(3)
    t = np.sort(np.arange(0, 60, 0.01) + rng.uniform(-0.003, 0.003, 6000))  # jittered stamps
    p, q = _truth(t)
    p = p + rng.normal(0, 0.001, p.shape)
    assert not detect_glitches(t, p).any()
    assert not detect_attitude_glitches(q).any()
    p2 = p.copy()
    p2[1000, 0] += 0.137  # the INRoL-like single-sample mocap jump
    p2[3000:3003, 1] -= 0.3  # a three-sample burst
    bad = detect_glitches(t, p2)
    assert set(np.flatnonzero(bad)) == {1000, 3000, 3001, 3002}
    q2 = q.copy()
    q2[500] = quat_multiply(q[500], quat_exp(np.array([0.0, 0.3, 0.0])))
    assert set(np.flatnonzero(detect_attitude_glitches(q2))) == {500}


def test_associate_interpolates_bridges_glitches_and_counts_gaps():
    t = np.arange(0, 10, 0.01)
    p, q = _truth(t)
    p[200] += [0.5, 0, 0]  # glitch
    keep = (t < 5.0) | (t > 6.0)  # 1 s gap
    te = np.arange(-0.5, 10.5, 0.0137)
    asc = associate(te, t[keep], p[keep], q[keep], max_gap=0.5)
    assert asc.n_glitches == 1
    p_true, q_true = _truth(te)
    v = asc.valid
    assert np.max(np.linalg.norm(asc.p_gt[v] - p_true[v], axis=1)) < 2e-4  # linear interpolation error only
    assert asc.n_outside_span == int(np.sum((te < 0) | (te > t[-1])))
    assert asc.n_in_gaps == int(np.sum((te > 4.99) & (te < 6.01)))
    near = np.abs(te - 2.0) < 0.02  # estimate stamps around the glitch are still scored, bridged
    assert v[near].all()


def test_evaluate_recovers_frame_and_noise_level():
    rng = np.random.default_rng(5)
    tg = np.arange(0, 60, 0.01)
    pg, qg = _truth(tg)
    gt = pd.DataFrame(np.c_[tg, pg, qg], columns=COLS)
    gt.loc[1234, "px"] += 0.2
    R, tr = _frames()
    te = np.arange(0.005, 60, 0.02)
    pt, qt = _truth(te)
    pe = (pt - tr) @ R + rng.normal(0, 0.05, pt.shape)  # estimate frame: p_gt = R p_est + tr
    qe = quat_multiply(rotmat_to_quat(R.T), qt)
    traj = pd.DataFrame(np.c_[te, pe, qe], columns=COLS)
    ev = evaluate_trajectory(traj, gt, align="se3", distances=(1.0, 5.0))
    s = ev.summary
    assert s["association"]["n_groundtruth_glitches_excluded"] == 1
    assert abs(s["ate_position"]["rmse"] - 0.05 * np.sqrt(3)) < 0.01
    np.testing.assert_allclose(ev.alignment.R, R, atol=0.01)
    assert s["ate_rotation_deg"]["rmse"] < 0.5
    # RPE: relative translation error of two independent 5 cm-per-axis noises
    assert abs(s["rpe"]["1"]["translation"]["rmse"] - 0.05 * np.sqrt(6)) < 0.015
    assert s["rpe"]["5"]["n_pairs"] > 1000
    # without alignment the frame offset dominates
    bad = evaluate_trajectory(traj, gt, align="none")
    assert bad.summary["ate_position"]["rmse"] > 1.0


def test_rpe_exact_on_rigid_copy():
    t = np.arange(0, 30, 0.05)
    p, q = _truth(t)
    out = relative_pose_error(p, q, p, q, distances=(1.0, 2.0))
    assert out["1"]["translation"]["max"] < 1e-12 and out["1"]["rotation_deg"]["max"] < 1e-5
    p2 = p.copy()
    p2[len(p) // 2:] += [0.1, 0, 0]  # a step: pairs crossing it see 10 cm
    out2 = relative_pose_error(p2, q, p, q, distances=(1.0,))
    assert abs(out2["1"]["translation"]["max"] - 0.1) < 1e-9


def test_evaluate_refuses_disjoint_clocks():
    t = np.arange(0, 10, 0.01)
    p, q = _truth(t)
    gt = pd.DataFrame(np.c_[t, p, q], columns=COLS)
    traj = pd.DataFrame(np.c_[t + 1e9, p, q], columns=COLS)
    with pytest.raises(ValueError, match="same clock"):
        evaluate_trajectory(traj, gt)


def test_evaluate_cli_writes_json_and_plots(tmp_path):
    from uwbimu.cli.main import app

    t = np.arange(0, 20, 0.01)
    p, q = _truth(t)
    pd.DataFrame(np.c_[t, p, q], columns=COLS).to_csv(tmp_path / "gt.csv", index=False)
    out = tmp_path / "out"
    out.mkdir()
    pd.DataFrame(np.c_[t[::3], p[::3] + [0.03, 0, 0], q[::3]], columns=COLS).to_csv(out / "trajectory.csv", index=False)
    r = CliRunner().invoke(app, ["evaluate", str(out), "--groundtruth", str(tmp_path / "gt.csv"), "--align", "none"])
    assert r.exit_code == 0, r.output
    s = json.loads((out / "evaluation.json").read_text())
    assert abs(s["ate_position"]["rmse"] - 0.03) < 1e-6
    for f in ("evaluation_trajectory.png", "evaluation_errors.png", "evaluation_errors.csv"):
        assert (out / f).stat().st_size > 0
    r = CliRunner().invoke(app, ["evaluate", str(out), "--groundtruth", str(tmp_path / "gt.csv"), "--align", "sim3"])
    assert r.exit_code == 2 and "--align" in r.output
    (tmp_path / "bad.csv").write_text("t,px,py\n0,1,2\n")
    r = CliRunner().invoke(app, ["evaluate", str(out), "--groundtruth", str(tmp_path / "bad.csv")])
    assert r.exit_code == 1 and "pz" in r.output


def test_attitude_not_compared_when_body_frames_differ(tmp_path):
    """Ground truth of another body (tracker rotated 177 deg from the IMU): attitude error reads n/a."""
    import yaml

    from uwbimu.cli.main import app
    from uwbimu.metrics.trajectory import ATTITUDE_NA

    t = np.arange(0, 30, 0.01)
    p, q = _truth(t)
    q_off = quat_exp(np.array([[np.radians(177.0), 0.0, 0.0]]))  # constant body-frame offset
    qb = quat_multiply(q, np.repeat(q_off, len(q), axis=0))
    gt = pd.DataFrame(np.c_[t, p, qb], columns=COLS)
    traj = pd.DataFrame(np.c_[t[::2], p[::2], q[::2]], columns=COLS)
    bad = evaluate_trajectory(traj, gt, align="se3", distances=(1.0,))
    assert bad.summary["ate_rotation_deg"]["rmse"] > 170  # meaningless number when compared
    ev = evaluate_trajectory(traj, gt, align="se3", distances=(1.0,), compare_attitude=False)
    assert ev.summary["ate_rotation"] == ATTITUDE_NA and "ate_rotation_deg" not in ev.summary
    assert ev.rot_err_deg is None
    assert ev.summary["rpe"]["1"]["translation"]["max"] < 1e-6  # world-frame displacements, not body-frame
    # CLI: the dataset.yaml next to the ground truth switches it off (as the ISAS-Walk importer writes it)
    ds = tmp_path / "ds"
    ds.mkdir()
    gt.to_csv(ds / "groundtruth.csv", index=False)
    (ds / "dataset.yaml").write_text(yaml.safe_dump({"extra": {"groundtruth_attitude_comparable": False}}))
    out = tmp_path / "out"
    out.mkdir()
    traj.to_csv(out / "trajectory.csv", index=False)
    r = CliRunner().invoke(app, ["evaluate", str(out), "--groundtruth", str(ds / "groundtruth.csv"), "--no-plots"])
    assert r.exit_code == 0, r.output
    assert "n/a (frames differ)" in r.output
    assert json.loads((out / "evaluation.json").read_text())["ate_rotation"] == ATTITUDE_NA
    r = CliRunner().invoke(app, ["evaluate", str(out), "--groundtruth", str(ds / "groundtruth.csv"), "--no-plots",
                                 "--attitude"])
    assert r.exit_code == 0 and json.loads((out / "evaluation.json").read_text())["ate_rotation_deg"]["rmse"] > 170
