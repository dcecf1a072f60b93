"""Multilateration baseline used to sanity-check imported real data."""

from __future__ import annotations

import numpy as np
import pytest
import pandas as pd

from uwbimu.eval.baseline import multilaterate
from uwbimu.io.dataset import Dataset, DatasetMeta


def test_multilateration_recovers_track_and_applies_known_bias():
    rng = np.random.default_rng(0)
    A = np.array([[0, 0, 0.3], [5, 0, 2.5], [5, 4, 0.3], [0, 4, 2.5], [2.5, -1, 1.5], [2.5, 5, 0.5]], float)
    ids = [str(i) for i in range(len(A))]
    bias = {a: b for a, b in zip(ids, [0.1, -0.15, 0.0, 0.05, 0.0, 0.2])}
    t = np.arange(0, 10, 0.1)
    p = np.c_[2.5 + np.cos(t), 2 + np.sin(t), 1.0 + 0.2 * np.sin(0.5 * t)]
    rows = [(ti, a, np.linalg.norm(pi - A[j]) + bias[a] + rng.normal(0, 0.01))
            for ti, pi in zip(t, p) for j, a in enumerate(ids) if rng.uniform() > 0.1]
    uwb = pd.DataFrame(rows, columns=["t", "anchor", "range"])
    an = pd.DataFrame({"anchor": ids, "x": A[:, 0], "y": A[:, 1], "z": A[:, 2]})
    ds = Dataset(imu=pd.DataFrame(), uwb=uwb, anchors=an, meta=DatasetMeta(known_anchor_bias=bias))
    ml = multilaterate(ds)
    assert len(ml) > 90
    truth = np.array([p[np.argmin(np.abs(t - ti))] for ti in ml["t"]])
    err = np.linalg.norm(ml[["px", "py", "pz"]].to_numpy() - truth, axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.05
    # without the known biases the fit is visibly worse: the baseline uses them
    ds.meta = DatasetMeta()
    ml2 = multilaterate(ds, max_rms=10.0)
    truth2 = np.array([p[np.argmin(np.abs(t - ti))] for ti in ml2["t"]])
    err2 = np.linalg.norm(ml2[["px", "py", "pz"]].to_numpy() - truth2, axis=1)
    assert np.sqrt(np.mean(err2**2)) > 2 * np.sqrt(np.mean(err**2))


def test_gyro_truth_time_offset_recovers_shift():
    from uwbimu.eval.baseline import gyro_truth_time_offset
    from uwbimu.models.quaternion import quat_exp, quat_multiply

    dt, td = 0.005, 0.07
    t = np.arange(0, 30, dt)
    w = np.c_[np.sin(1.1 * t), 0.5 * np.cos(0.7 * t), 0.8 * np.sin(0.4 * t) + 0.2 * np.sin(2.3 * t)]
    q = np.zeros((len(t), 4))
    q[0] = [1, 0, 0, 0]
    dq = quat_exp(w[:-1] * dt)
    for k in range(len(t) - 1):
        q[k + 1] = quat_multiply(q[k], dq[k])
    gt = pd.DataFrame({"t": t[::4], "px": 0.0, "py": 0.0, "pz": 0.0, "qw": q[::4, 0], "qx": q[::4, 1],
                       "qy": q[::4, 2], "qz": q[::4, 3]})
    # an IMU sample stamped s describes the motion at ground-truth time s - td
    imu = pd.DataFrame({"t": t[::2] + td, "ax": 0.0, "ay": 0.0, "az": 9.81,
                        "wx": w[::2, 0], "wy": w[::2, 1], "wz": w[::2, 2]})
    ds = Dataset(imu=imu, uwb=pd.DataFrame(), anchors=pd.DataFrame(), groundtruth=gt)
    r = gyro_truth_time_offset(ds, max_shift=0.3)
    assert abs(r["shift"] - td) <= 0.006
    assert r["correlation"] > 0.99


def test_gyro_truth_time_offset_refusals_are_input_errors():
    """A ground truth without attitude columns (or too short an overlap) is refused as an InputError naming the
    missing columns (exit 1), not a bare ValueError."""
    from uwbimu.errors import InputError
    from uwbimu.eval.baseline import gyro_truth_time_offset

    t = np.arange(0.0, 30.0, 0.01)
    imu = pd.DataFrame({"t": t, "ax": 0.0, "ay": 0.0, "az": 9.81, "wx": 0.1, "wy": 0.0, "wz": 0.0})
    gt = pd.DataFrame({"t": t, "px": 0.0, "py": 0.0, "pz": 0.0})
    ds = Dataset(imu=imu, uwb=pd.DataFrame(), anchors=pd.DataFrame(), groundtruth=gt)
    with pytest.raises(InputError, match="qw, qx, qy, qz"):
        gyro_truth_time_offset(ds)
    ds_none = Dataset(imu=imu, uwb=pd.DataFrame(), anchors=pd.DataFrame(), groundtruth=None)
    with pytest.raises(InputError):
        gyro_truth_time_offset(ds_none)
    short = gt.assign(qw=1.0, qx=0.0, qy=0.0, qz=0.0).iloc[:50]  # 0.5 s of overlap
    with pytest.raises(InputError, match="overlap"):
        gyro_truth_time_offset(Dataset(imu=imu, uwb=pd.DataFrame(), anchors=pd.DataFrame(), groundtruth=short))
