"""Evaluate an estimator output folder against ground truth and write the results.

``evaluate_output(OUT, groundtruth)`` reads ``OUT/trajectory.csv``, scores it
(:func:`uwbimu.metrics.trajectory.evaluate_trajectory`) and writes, atomically:

* ``OUT/evaluation.json``        summary (ATE, RPE, alignment, association counts)
* ``OUT/evaluation_errors.csv``  per-sample ``t, px_gt.., px_est.., ex, ey, ez, e, rot_err_deg``
  (aligned, ground-truth frame; used by the HTML report)
* ``OUT/evaluation_trajectory.png``, ``OUT/evaluation_errors.png``
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from uwbimu.eval.files import load_groundtruth, load_trajectory
from uwbimu.metrics.trajectory import Evaluation, evaluate_trajectory
from uwbimu.io.atomic import save_figure, write_csv, write_json


#: Attitude columns of a ground truth (Hamilton quaternion, body -> world).
GT_ATTITUDE_COLUMNS = ("qw", "qx", "qy", "qz")


def groundtruth_attitude_warnings(gt: pd.DataFrame, path) -> list[dict]:
    """Structured warning when a ground truth has no (or an incomplete) attitude: the attitude is not scored.

    Returns
    -------
    list of dict
        Empty when ``qw, qx, qy, qz`` are all present; else one ``{"code":
        "groundtruth_without_attitude", "file", "missing_columns", "message"}``.
    """
    from uwbimu.errors import column_list

    missing = [c for c in GT_ATTITUDE_COLUMNS if c not in gt.columns]
    if not missing:
        return []
    return [{"code": "groundtruth_without_attitude", "file": str(path), "missing_columns": missing,
             "message": f"the ground truth lacks {column_list(missing)}: attitude errors are not computed "
                        f"(position ATE and RPE only)"}]


def evaluation_table(ev: Evaluation) -> pd.DataFrame:
    """Per-sample errors as a DataFrame (ground-truth frame, after alignment)."""
    df = pd.DataFrame(
        {
            "t": ev.t,
            "px_gt": ev.p_gt[:, 0],
            "py_gt": ev.p_gt[:, 1],
            "pz_gt": ev.p_gt[:, 2],
            "px_est": ev.p_est_aligned[:, 0],
            "py_est": ev.p_est_aligned[:, 1],
            "pz_est": ev.p_est_aligned[:, 2],
            "ex": ev.pos_err[:, 0],
            "ey": ev.pos_err[:, 1],
            "ez": ev.pos_err[:, 2],
            "e": np.linalg.norm(ev.pos_err, axis=1),
        }
    )
    if ev.rot_err_deg is not None:
        df["rot_err_deg"] = ev.rot_err_deg
    return df


def plot_evaluation(ev: Evaluation):
    """Two matplotlib figures: top-view trajectory overlay and error over time."""
    from matplotlib.figure import Figure

    f1 = Figure(figsize=(6.0, 5.0))
    ax = f1.add_subplot(111)
    ax.plot(ev.p_gt[:, 0], ev.p_gt[:, 1], "k-", lw=1.2, label="ground truth")
    ax.plot(ev.p_est_aligned[:, 0], ev.p_est_aligned[:, 1], "C0-", lw=0.9, label=f"estimate ({ev.alignment.mode}-aligned)")
    ax.set_xlabel("x [m] (ground-truth frame)")
    ax.set_ylabel("y [m]")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Trajectory, top view")
    ax.grid(True, alpha=0.3)

    f2 = Figure(figsize=(8.0, 4.5))
    ax2 = f2.add_subplot(111)
    for i, c in enumerate("xyz"):
        ax2.plot(ev.t, ev.pos_err[:, i], lw=0.7, label=f"e{c}")
    ax2.plot(ev.t, np.linalg.norm(ev.pos_err, axis=1), "k-", lw=0.9, label="|e|")
    ax2.set_xlabel("t [s] (UWB clock)")
    ax2.set_ylabel("position error [m]")
    ax2.set_title(f"Position error after {ev.alignment.mode} alignment")
    ax2.legend(loc="best", fontsize=8, ncol=4)
    ax2.grid(True, alpha=0.3)
    return f1, f2


def groundtruth_attitude_comparable(groundtruth: str | os.PathLike) -> bool:
    """False when the dataset.yaml next to ``groundtruth`` marks its attitude as another body frame."""
    from uwbimu.eval.files import load_yaml

    g = Path(groundtruth)
    meta = load_yaml((g if g.is_dir() else g.parent) / "dataset.yaml") or {}
    extra = meta.get("extra") or {}
    return bool(extra.get("groundtruth_attitude_comparable", True))


def evaluate_output(
    out_dir: str | os.PathLike,
    groundtruth: str | os.PathLike,
    align: str = "se3",
    distances: Sequence[float] = (1.0, 2.0, 5.0),
    max_gap: float = 0.5,
    skip_initial: float = 0.0,
    plots: bool = True,
    trajectory: Optional[str | os.PathLike] = None,
    compare_attitude: Optional[bool] = None,
) -> dict:
    """Score ``OUT/trajectory.csv`` against ``groundtruth`` and write the results.

    ``compare_attitude=None`` (default) compares attitudes unless the
    ``dataset.yaml`` next to the ground truth says its body frame is not the IMU
    frame (``extra.groundtruth_attitude_comparable: false``, set by the
    ISAS-Walk importer); then the attitude error reads "n/a (frames differ)".

    Returns the summary dict that is written to ``OUT/evaluation.json``.
    """
    out = Path(out_dir)
    traj = load_trajectory(trajectory if trajectory is not None else out)
    gt = load_groundtruth(groundtruth)
    if compare_attitude is None:
        compare_attitude = groundtruth_attitude_comparable(groundtruth)
    warnings = groundtruth_attitude_warnings(gt, groundtruth) if compare_attitude else []
    ev = evaluate_trajectory(traj, gt, align=align, distances=distances, max_gap=max_gap, skip_initial=skip_initial,
                             compare_attitude=compare_attitude)
    summary = dict(ev.summary)
    summary["warnings"] = warnings
    summary["groundtruth_file"] = str(Path(groundtruth))
    summary["trajectory_file"] = str(Path(trajectory) if trajectory is not None else out / "trajectory.csv")
    write_csv(out / "evaluation_errors.csv", evaluation_table(ev), float_format="%.6f")
    if plots:
        f1, f2 = plot_evaluation(ev)
        save_figure(out / "evaluation_trajectory.png", f1)
        save_figure(out / "evaluation_errors.png", f2)
        summary["plots"] = ["evaluation_trajectory.png", "evaluation_errors.png"]
    write_json(out / "evaluation.json", summary)
    return summary
