"""``anchor_frame_up: -z``: anchors given in a z-down frame (ISAS-Walk's RTLS frame).

The filter runs in the anchors' frame turned 180 deg about x and turns every output back, so a
flight whose anchors and truth are expressed in the turned frame must give exactly the original
run's outputs, turned.  Also pins the preset examples/estimator_isas.yaml."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, compute_metrics, run_eskf
from uwbimu.estimation.eskf import FLIP_X, Q_FLIP_X, flip_outputs
from uwbimu.models.quaternion import quat_multiply, quat_normalize, quat_to_rotmat
from uwbimu.sim import builtin_scenario, simulate

ROOT = Path(__file__).resolve().parents[1]


def _turn_world_about_x(ds):
    """Same flight (same IMU data) with anchors and truth expressed in the world turned 180 deg about x."""
    ds.anchors = ds.anchors.copy()
    ds.anchors[["y", "z"]] = -ds.anchors[["y", "z"]].to_numpy()
    gt = ds.groundtruth.copy()
    gt[["py", "pz"]] = -gt[["py", "pz"]].to_numpy()
    if "vy" in gt.columns:
        gt[["vy", "vz"]] = -gt[["vy", "vz"]].to_numpy()
    gt[["qw", "qx", "qy", "qz"]] = quat_multiply(np.broadcast_to(Q_FLIP_X, (len(gt), 4)),
                                                 gt[["qw", "qx", "qy", "qz"]].to_numpy())
    ds.groundtruth = gt
    return ds


def test_flip_outputs_rotates_vectors_attitude_and_covariance():
    rng = np.random.default_rng(7)
    X = rng.normal(size=(5, 21))
    X[:, 6:10] = quat_normalize(X[:, 6:10])
    A = rng.normal(size=(5, 20, 20))
    C = A @ np.transpose(A, (0, 2, 1))
    Y, D = flip_outputs(X, C)
    R = np.diag(FLIP_X)
    assert np.allclose(Y[:, 0:3], X[:, 0:3] @ R.T) and np.allclose(Y[:, 3:6], X[:, 3:6] @ R.T)
    assert np.allclose(quat_to_rotmat(Y[:, 6:10]), R @ quat_to_rotmat(X[:, 6:10]))
    assert np.allclose(Y[:, 10:], X[:, 10:])  # biases, lever arm, t_d, anchor biases: body / time quantities
    T = np.eye(20)
    T[0:3, 0:3] = R
    T[3:6, 3:6] = R
    assert np.allclose(D, T @ C @ T.T)
    Z, E = flip_outputs(Y, D)  # its own inverse
    assert np.allclose(Z[:, :6], X[:, :6]) and np.allclose(E, C)
    assert np.allclose(np.abs(np.sum(Z[:, 6:10] * X[:, 6:10], axis=1)), 1.0)


def test_z_down_anchor_frame_gives_the_turned_original_run():
    sc = builtin_scenario("calibration-flight")
    ds = simulate(sc.model_copy(update={"duration": 25.0}))
    ref = run_eskf(ds)
    turned = _turn_world_about_x(simulate(sc.model_copy(update={"duration": 25.0})))
    res = run_eskf(turned, EskfOptions(anchor_frame_up="-z"))
    assert res.states.shape == ref.states.shape
    assert np.allclose(res.t, ref.t)
    assert np.allclose(res.states[:, 0:3], ref.states[:, 0:3] * FLIP_X, atol=1e-9)
    assert np.allclose(res.states[:, 3:6], ref.states[:, 3:6] * FLIP_X, atol=1e-9)
    assert np.allclose(res.states[:, 10:], ref.states[:, 10:], atol=1e-9)
    assert np.allclose(res.sd, ref.sd, atol=1e-12, equal_nan=True)
    m = compute_metrics(res, turned)
    assert m["position_rmse_after"] < 0.08, m
    assert m["orientation_rmse_deg"] < 5.0, m
    assert m["lever_arm_within_3sigma"] and m["time_offset_within_3sigma"], m
    assert any(e["kind"] == "anchor_frame_flipped" for e in res.events)


def test_z_down_data_read_as_z_up_is_inconsistent():
    """The failure mode found on ISAS-Walk: a z-down anchor frame read as z-up gives large innovations
    (here on a short simulated flight: mean NIS well above 1) while the right setting does not."""
    sc = builtin_scenario("calibration-flight")
    turned = _turn_world_about_x(simulate(sc.model_copy(update={"duration": 20.0})))
    opts = EskfOptions(init={"refine_s": 0.0})
    wrong = run_eskf(turned, opts).residuals
    right = run_eskf(turned, opts.model_copy(update={"anchor_frame_up": "-z"})).residuals
    nis_wrong = float(np.nanmean(np.minimum(wrong.nis, 50.0)))
    nis_right = float(np.nanmean(np.minimum(right.nis, 50.0)))
    assert nis_right < 2.0
    assert nis_wrong > 2.0 * nis_right, (nis_wrong, nis_right)


def test_isas_preset_loads_and_is_documented():
    opts = EskfOptions.from_yaml(ROOT / "examples" / "estimator_isas.yaml")
    assert opts.anchor_frame_up == "-z"
    assert opts.lever_arm.prior == "dataset" and opts.lever_arm.prior_sd == pytest.approx(0.10)
    assert opts.anchor_bias.mode == "estimate" and opts.anchor_bias.correlation_time == pytest.approx(2.0)
    assert opts.time_offset.mode == "estimate"
    assert "estimator_isas.yaml" in (ROOT / "docs" / "estimator.md").read_text()
