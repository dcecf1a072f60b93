"""A model-free reference: epoch-wise multilateration of the UWB tag.

Used to sanity-check an imported real dataset independently of any filter:
if the multilaterated tag track, rigidly aligned to the ground truth, is
close to it, the ranges, anchor positions, anchor ids, known biases and
clocks of the import are consistent.  It ignores the IMU and the lever arm
(it locates the antenna, not the IMU), so it is a sanity bound, not a
competitor of the ESKF.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from uwbimu.io.dataset import Dataset


def multilaterate(
    ds: Dataset,
    min_anchors: int = 4,
    epoch_s: float = 0.0,
    max_rms: float = 0.3,
    loss_scale: float = 0.1,
) -> pd.DataFrame:
    """Least-squares tag position per ranging epoch.

    Parameters
    ----------
    ds : dataset (ranges minus ``meta.known_anchor_bias``, anchors in the world frame).
    min_anchors : epochs with fewer distinct anchors are skipped.
    epoch_s : ranges within this window [s] form one epoch (0: identical stamps).
    max_rms : epochs whose robust fit leaves an RMS residual above this [m] are dropped.
    loss_scale : soft-L1 scale [m] of the robust fit.

    Returns
    -------
    DataFrame ``t, px, py, pz, rms, n`` (tag position, world frame, UWB clock).
    """
    pos = ds.anchor_positions()
    kb = ds.meta.known_anchor_bias or {}
    u = ds.uwb.sort_values("t", kind="stable")
    t = u["t"].to_numpy(float)
    key = t if epoch_s <= 0 else np.floor((t - t[0]) / epoch_s)
    anchors = u["anchor"].astype(str).to_numpy()
    r = u["range"].to_numpy(float) - np.array([kb.get(a, 0.0) for a in anchors])
    P_all = np.array([pos.get(a, (np.nan,) * 3) for a in anchors], float)
    A = np.array(list(pos.values()))
    x0 = A.mean(axis=0)
    rows = []
    bounds = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        sel = slice(i0, i1)
        ok = np.isfinite(P_all[sel]).all(axis=1)
        if len(set(anchors[sel][ok])) < min_anchors:
            continue
        P, rr = P_all[sel][ok], r[sel][ok]
        sol = least_squares(lambda x: np.linalg.norm(P - x, axis=1) - rr, x0, loss="soft_l1", f_scale=loss_scale)
        rms = float(np.sqrt(np.mean(sol.fun**2)))
        if rms <= max_rms:
            rows.append((float(np.mean(t[sel])), *sol.x, rms, int(ok.sum())))
            x0 = sol.x
    return pd.DataFrame(rows, columns=["t", "px", "py", "pz", "rms", "n"])


def gyro_truth_time_offset(
    ds: Dataset,
    max_shift: float = 0.5,
    resolution: float = 0.005,
    half_step: float = 0.1,
) -> dict:
    """Time offset between the IMU and the ground-truth clock from rotation rates.

    The gyro magnitude ``|w_imu(s)|`` (IMU clock) is cross-correlated with the
    ground-truth rotation rate ``|w_gt(t)|`` (finite difference of attitudes
    over ``±half_step``, robust to jittered stamps).  The returned ``shift``
    maximises the correlation of ``|w_imu(t + shift)|`` with ``|w_gt(t)|``,
    i.e. an IMU sample stamped ``s`` describes the motion at ground-truth time
    ``s − shift``: with ground truth on the UWB clock, ``shift`` estimates the
    time offset ``t_d`` of the convention.  Magnitudes make it independent of
    the unknown body/tracker rotation; it needs rotation, not only translation.

    Returns
    -------
    dict ``shift`` [s], ``correlation`` (at the best shift), ``correlation_at_zero``.
    """
    from uwbimu.errors import InputError
    from uwbimu.models.quaternion import quat_conjugate, quat_log, quat_multiply, quat_normalize, quat_slerp

    if ds.groundtruth is None or len(ds.groundtruth) < 10:
        n = 0 if ds.groundtruth is None else len(ds.groundtruth)
        raise InputError(f"gyro_truth_time_offset: groundtruth.csv has {n} rows; at least 10 with attitudes "
                         "(qw, qx, qy, qz) are needed")
    g = ds.groundtruth
    missing = [c for c in ("qw", "qx", "qy", "qz") if c not in g.columns]
    if missing:
        raise InputError(f"gyro_truth_time_offset: groundtruth.csv lacks the attitude column(s) {', '.join(missing)}; "
                         "the scan compares rotation rates")
    tg = g["t"].to_numpy(float)
    q = quat_normalize(g[["qw", "qx", "qy", "qz"]].to_numpy(float))
    ti = ds.imu_t
    w_imu = np.linalg.norm(ds.imu[["wx", "wy", "wz"]].to_numpy(float), axis=1)
    lo = max(tg[0], ti[0]) + max_shift + half_step
    hi = min(tg[-1], ti[-1]) - max_shift - half_step
    if hi - lo < 10 * half_step:
        raise InputError(f"gyro_truth_time_offset: imu.csv and groundtruth.csv overlap over {max(hi - lo, 0.0):.2f} s "
                         f"after the ±{max_shift:g} s scan margin; at least {10 * half_step:g} s are needed")
    grid = np.arange(lo, hi, 0.01)

    def q_at(t):
        i = np.clip(np.searchsorted(tg, t) - 1, 0, len(tg) - 2)
        a = np.clip((t - tg[i]) / np.maximum(tg[i + 1] - tg[i], 1e-9), 0.0, 1.0)
        return quat_slerp(q[i], q[i + 1], a)

    w_gt = np.linalg.norm(quat_log(quat_multiply(quat_conjugate(q_at(grid - half_step)), q_at(grid + half_step))),
                          axis=1) / (2 * half_step)
    # average the gyro over the same window as the finite difference
    csum = np.r_[0.0, np.cumsum(0.5 * (w_imu[1:] + w_imu[:-1]) * np.diff(ti))]

    def w_mean(t):
        return (np.interp(t + half_step, ti, csum) - np.interp(t - half_step, ti, csum)) / (2 * half_step)

    shifts = np.arange(-max_shift, max_shift + resolution / 2, resolution)
    corr = np.array([np.corrcoef(w_mean(grid + s), w_gt)[0, 1] for s in shifts])
    k = int(np.nanargmax(corr))
    return {"shift": float(shifts[k]), "correlation": float(corr[k]),
            "correlation_at_zero": float(corr[int(np.argmin(np.abs(shifts)))])}
