"""The trajectory (waypoint) file format, read and written here.

A trajectory file is a CSV with a header row and the columns

* ``t`` -- time [s], strictly increasing; the first row is the start of the
  flight (UWB time 0 of the simulation), i.e. times are used as ``t - t[0]``;
* ``px, py, pz`` -- IMU position in the world frame [m];
* optionally the attitude, either ``qw, qx, qy, qz`` (Hamilton, IMU body ->
  world, normalised on reading) or ``yaw`` [rad] alone (roll = pitch = 0);
  without them the attitude is constant identity.

Other columns are refused (a typo such as ``pX`` must not be silently ignored).
The simulator fits quintic splines through the rows, at rest at both ends
(:class:`uwbimu.sim.trajectory.SplineTrajectory`).  Attitude is interpolated
as Z-Y-X Euler angles, so |pitch| must stay below 85 degrees.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

from uwbimu.errors import InputError, UsageError
from uwbimu.sim.trajectory import SplineTrajectory, quat_to_euler_zyx

POSITION_COLUMNS = ["t", "px", "py", "pz"]
QUAT_COLUMNS = ["qw", "qx", "qy", "qz"]
MAX_PITCH = np.deg2rad(85.0)


class TrajectoryFileError(InputError):
    """A trajectory file that cannot be flown (message names file, row, column; exit code 1)."""


def read_trajectory_file(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read and validate a trajectory file.

    Returns
    -------
    t : (N,) times [s] shifted so that ``t[0] = 0``.
    p : (N, 3) positions [m].
    euler : (N, 3) unwrapped roll, pitch, yaw [rad].

    Raises
    ------
    TrajectoryFileError naming the file, the data row (1-based; the line in
    the file is given too, the header being line 1) and the column.
    """
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFileError(f"{path}: trajectory file not found")
    try:
        df = pd.read_csv(path, comment="#", skipinitialspace=True)
    except pd.errors.EmptyDataError:
        raise TrajectoryFileError(f"{path}: file is empty") from None
    except Exception as exc:  # parser errors carry the line already
        raise TrajectoryFileError(f"{path}: cannot parse CSV: {exc}") from None
    df.columns = [str(c).strip() for c in df.columns]
    cols = list(df.columns)
    missing = [c for c in POSITION_COLUMNS if c not in cols]
    if missing:
        raise TrajectoryFileError(f"{path}: missing column(s) {', '.join(missing)}; found {cols}")
    has_q = any(c in cols for c in QUAT_COLUMNS)
    if has_q and not all(c in cols for c in QUAT_COLUMNS):
        raise TrajectoryFileError(f"{path}: quaternion needs all of {QUAT_COLUMNS}; found {cols}")
    if has_q and "yaw" in cols:
        raise TrajectoryFileError(f"{path}: give either qw,qx,qy,qz or yaw, not both")
    allowed = set(POSITION_COLUMNS) | set(QUAT_COLUMNS) | {"yaw"}
    unknown = [c for c in cols if c not in allowed]
    if unknown:
        raise TrajectoryFileError(f"{path}: unknown column(s) {', '.join(unknown)}; allowed {', '.join(map(str, sorted(allowed)))}")
    if len(df) < 2:
        raise TrajectoryFileError(f"{path}: need at least 2 rows, found {len(df)}")
    for c in cols:
        vals = pd.to_numeric(df[c], errors="coerce").to_numpy(float)
        bad = np.flatnonzero(~np.isfinite(vals))
        if bad.size:
            r = int(bad[0])
            raise TrajectoryFileError(
                f"{path}: row {r + 1} (line {r + 2}), column '{c}': not a finite number ({df[c].iloc[r]!r})"
            )
        df[c] = vals
    t = df["t"].to_numpy(float)
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        r = int(back[0]) + 1
        raise TrajectoryFileError(
            f"{path}: row {r + 1} (line {r + 2}), column 't': time {t[r]} is not after the previous {t[r - 1]}"
        )
    p = df[["px", "py", "pz"]].to_numpy(float)
    if has_q:
        q = df[QUAT_COLUMNS].to_numpy(float)
        n = np.linalg.norm(q, axis=1)
        bad = np.flatnonzero(n < 1e-9)
        if bad.size:
            r = int(bad[0])
            raise TrajectoryFileError(f"{path}: row {r + 1} (line {r + 2}), columns qw..qz: zero quaternion")
        euler = quat_to_euler_zyx(q / n[:, None])
    elif "yaw" in cols:
        euler = np.zeros((len(t), 3))
        euler[:, 2] = df["yaw"].to_numpy(float)
    else:
        euler = np.zeros((len(t), 3))
    steep = np.flatnonzero(np.abs(euler[:, 1]) > MAX_PITCH)
    if steep.size:
        r = int(steep[0])
        raise TrajectoryFileError(
            f"{path}: row {r + 1} (line {r + 2}), attitude: pitch {np.rad2deg(euler[r, 1]):.1f} deg beyond +-85 deg"
            " (Euler interpolation is singular there)"
        )
    # Angles that wrap at +-pi are made continuous so the spline does not spin round.
    euler[:, 0] = np.unwrap(euler[:, 0])
    euler[:, 2] = np.unwrap(euler[:, 2])
    return t - t[0], p, euler


def load_trajectory_file(path: str | os.PathLike) -> SplineTrajectory:
    """Read a trajectory file and fit the spline trajectory."""
    return SplineTrajectory(*read_trajectory_file(path))


def write_trajectory_file(path: str | os.PathLike, t, p, q=None, yaw=None) -> Path:
    """Write a trajectory file atomically (the format read by :func:`read_trajectory_file`).

    Parameters
    ----------
    t : (N,) times [s]; p : (N, 3) positions [m];
    q : optional (N, 4) quaternions ``[qw, qx, qy, qz]``; yaw : optional (N,) [rad].
    """
    from uwbimu.io.atomic import write_csv

    if q is not None and yaw is not None:
        raise UsageError("give q or yaw, not both")
    data = {"t": np.asarray(t, float)}
    p = np.asarray(p, float)
    data.update(px=p[:, 0], py=p[:, 1], pz=p[:, 2])
    if q is not None:
        q = np.asarray(q, float)
        data.update({c: q[:, i] for i, c in enumerate(QUAT_COLUMNS)})
    if yaw is not None:
        data["yaw"] = np.asarray(yaw, float)
    return write_csv(path, pd.DataFrame(data), float_format="%.10g")
