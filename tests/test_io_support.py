"""Shared builders for the io tests (no tests here).

``make_dataset`` builds a small exact dataset from an analytic trajectory so
that the io tests do not depend on the simulator.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from uwbimu.io.dataset import Dataset, DatasetMeta, TagMeta, TruthMeta, write_dataset
from uwbimu.models.quaternion import quat_conjugate, quat_exp, quat_rotate

ANCHORS = pd.DataFrame({
    "anchor": ["A", "B", "C", "D", "E", "F"],
    "x": [-4.0, 4.0, 4.0, -4.0, 0.5, -0.5],
    "y": [-3.5, -3.5, 3.5, 3.5, -4.5, 4.5],
    "z": [0.3, 2.6, 0.4, 2.5, 1.2, 2.8],
})
LEVER = (0.10, -0.05, 0.08)


def truth(t: np.ndarray, yaw_rate: float = 0.5):
    """Analytic pose, acceleration and body rate of a Lissajous with yawing attitude."""
    ax, ay, az, wx, wy, wz = 2.0, 1.5, 0.7, 0.4, 0.6, 0.3
    p = np.stack([ax * np.cos(wx * t), ay * np.sin(wy * t), 1.3 + az * np.sin(wz * t)], 1)
    acc = np.stack([-ax * wx**2 * np.cos(wx * t), -ay * wy**2 * np.sin(wy * t), -az * wz**2 * np.sin(wz * t)], 1)
    q = quat_exp(np.stack([0 * t, 0 * t, yaw_rate * t], 1))
    w_b = np.tile([0.0, 0.0, yaw_rate], (len(t), 1))
    return p, q, acc, w_b


def make_dataset(duration: float = 40.0, imu_rate: float = 100.0, uwb_rate: float = 50.0, sigma: float = 0.0,
                 seed: int = 0, yaw_rate: float = 0.5, anchors: pd.DataFrame | None = None) -> Dataset:
    """Exact (``sigma=0``) or noisy ranges, round-robin over the anchors, lever arm ``LEVER``."""
    rng = np.random.default_rng(seed)
    anchors = ANCHORS.copy() if anchors is None else anchors
    t = np.arange(int(duration * imu_rate)) / imu_rate
    p, q, acc, w_b = truth(t, yaw_rate)
    f_b = quat_rotate(quat_conjugate(q), acc + np.array([0.0, 0.0, 9.81]))
    imu = pd.DataFrame(np.column_stack([t, f_b, w_b]), columns=["t", "ax", "ay", "az", "wx", "wy", "wz"])
    gt = pd.DataFrame(np.column_stack([t, p, q]), columns=["t", "px", "py", "pz", "qw", "qx", "qy", "qz"])
    # Ranges between IMU stamps (so the check really interpolates).
    tr = np.arange(int(duration * uwb_rate) - 1) / uwb_rate + 0.0037
    pr, qr, _, _ = truth(tr, yaw_rate)
    ant = pr + quat_rotate(qr, np.array(LEVER))
    ids = anchors["anchor"].to_numpy()
    j = np.arange(len(tr)) % len(ids)
    A = anchors[["x", "y", "z"]].to_numpy()[j]
    r = np.linalg.norm(A - ant, axis=1) + sigma * rng.standard_normal(len(tr))
    uwb = pd.DataFrame({"t": tr, "anchor": ids[j].astype(object), "range": r})
    meta = DatasetMeta(name="synthetic", range_sigma=max(sigma, 0.01),
                       tags=[TagMeta(name="tag0", lever_arm=list(LEVER))],
                       truth=TruthMeta(lever_arm=list(LEVER), time_offset=0.0))
    return Dataset(imu=imu, uwb=uwb, anchors=anchors.copy(), groundtruth=gt, meta=meta)


def write_valid(folder: Path, **kwargs) -> Path:
    """A short valid CSV dataset folder (10 s)."""
    kwargs.setdefault("duration", 10.0)
    return write_dataset(make_dataset(**kwargs), folder)


def edit_line(path: Path, line: int, column: str, value: str) -> None:
    """Set ``column`` of 1-based file ``line`` (header = line 1) of a CSV to ``value``."""
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[line - 1].split(",")
    cells[header.index(column)] = value
    lines[line - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


def get_line(path: Path, line: int) -> str:
    return path.read_text().splitlines()[line - 1]
