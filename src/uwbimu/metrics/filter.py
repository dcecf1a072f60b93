"""Accuracy and consistency metrics of an :class:`EstimationResult` against ground truth.

Works for any estimator filling the shared result type.  Ground truth is on
the UWB clock.  A state output at IMU time ``s`` describes the motion at UWB
time ``s - t_d``; when the true time offset is known (``dataset.meta.truth``)
the truth is taken there, which scores the state itself; otherwise at the
result's own stamps ``result.t`` (``s - t_d_hat``).

:func:`compute_metrics` is what ``uwbimu estimate`` prints and writes; :func:`run_metrics`
is the per-run row (RMSE, NEES, calibration errors, coverage) of a Monte Carlo study.
"""

from __future__ import annotations

from uwbimu.errors import InputError
from typing import Any, Optional

import numpy as np

from uwbimu.models import state as ST
from uwbimu.io.dataset import Dataset
from uwbimu.models.quaternion import quat_conjugate, quat_log, quat_multiply, quat_normalize


#: half window [s] of the finite-difference truth velocity when the ground truth has no velocity columns
VEL_HALF_WINDOW_S = 0.05


def truth_at(dataset: Dataset, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, Optional[np.ndarray], np.ndarray]:
    """Ground truth interpolated at UWB times ``t``.

    Returns ``p`` (K, 3), ``q`` (K, 4) (normalised linear interpolation),
    ``v`` (K, 3) (from the table, else central differences of the interpolated
    ``p`` over +/- ``VEL_HALF_WINDOW_S``; None when the truth has fewer than 2
    rows) and ``valid`` (K,) bool (inside the truth span).
    """
    gt = dataset.groundtruth
    if gt is None or len(gt) == 0:
        raise InputError("the dataset has no ground truth")
    gt = gt.sort_values("t")
    tg = gt["t"].to_numpy(float)
    t = np.asarray(t, dtype=float)
    valid = (t >= tg[0]) & (t <= tg[-1])
    P = gt[["px", "py", "pz"]].to_numpy(float)
    p = np.column_stack([np.interp(t, tg, P[:, i]) for i in range(3)])
    q = None  # a position-only ground truth has no attitude
    if all(c in gt.columns for c in ("qw", "qx", "qy", "qz")):
        Q = gt[["qw", "qx", "qy", "qz"]].to_numpy(float)
        # make the quaternion sequence continuous in sign before interpolating
        s = np.sign(np.sum(Q[1:] * Q[:-1], axis=1))
        s = np.concatenate([[1.0], np.cumprod(np.where(s == 0, 1.0, s))])
        Q = Q * s[:, None]
        q = quat_normalize(np.column_stack([np.interp(t, tg, Q[:, i]) for i in range(4)]))
    if all(c in gt.columns for c in ("vx", "vy", "vz")):
        V = gt[["vx", "vy", "vz"]].to_numpy(float)
        v = np.column_stack([np.interp(t, tg, V[:, i]) for i in range(3)])
    elif len(tg) > 1:
        # central difference of the interpolated positions over +/- VEL_HALF_WINDOW_S: per-sample
        # differences of a jittered motion-capture log (stamps 0.25 ms apart) are pure noise
        h = min(VEL_HALF_WINDOW_S, 0.5 * (tg[-1] - tg[0]))
        ta = np.clip(t - h, tg[0], tg[-1])
        tb = np.clip(t + h, tg[0], tg[-1])
        dt = np.where(tb - ta > 0, tb - ta, np.nan)
        v = np.column_stack([(np.interp(tb, tg, P[:, i]) - np.interp(ta, tg, P[:, i])) / dt for i in range(3)])
    else:
        v = None
    return p, q, v, valid


def attitude_error(q_est: np.ndarray, q_true: np.ndarray) -> np.ndarray:
    """Right-perturbation attitude error ``Log(q_est^-1 ⊗ q_true)`` (K, 3) [rad]."""
    return quat_log(quat_multiply(quat_conjugate(q_est), q_true))


def nees_series(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """``e_k^T P_k^-1 e_k`` for each row: errors ``err`` (K, d), covariances ``cov`` (K, d, d) in the same
    units and frame; NaN where ``P_k`` is singular.

    One stacked ``np.linalg.solve`` over all rows (LAPACK ``gesv`` per matrix, as a solve per row: the same
    solutions) instead of a Python loop of K solves (a 10-minute log at 20 Hz has 12,000 rows); when some
    matrix is singular, which fails the whole stack, the rows are solved one by one so that only those rows
    are NaN.  The quadratic form is a per-row sum of ``d`` products (``tests/test_speed_nees.py``: equal to
    the per-row ``err @ solve(cov, err)`` within 1e-12 relative).
    """
    err = np.asarray(err, dtype=float)
    cov = np.asarray(cov, dtype=float)
    if err.ndim != 2 or cov.shape != err.shape + err.shape[1:]:
        raise InputError(f"nees_series needs errors (K, d) and covariances (K, d, d); got {err.shape} and "
                         f"{cov.shape}")
    if len(err) == 0:
        return np.full(0, np.nan)
    try:
        sol = np.linalg.solve(cov, err[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        return _nees_rows(err, cov)
    return np.einsum("kd,kd->k", err, sol)


def _nees_rows(err: np.ndarray, cov: np.ndarray) -> np.ndarray:
    """:func:`nees_series` one row at a time (the stack holds a singular matrix: NaN for those rows)."""
    out = np.full(len(err), np.nan)
    for i in range(len(err)):
        try:
            out[i] = float(err[i] @ np.linalg.solve(cov[i], err[i]))
        except np.linalg.LinAlgError:
            pass
    return out


def compute_metrics(result, dataset: Dataset, skip_s: float = 10.0) -> dict[str, Any]:
    """Accuracy and consistency of ``result`` against the dataset's ground truth.

    Returns a plain dict: ``position_rmse`` [m] (whole run), ``position_rmse_after``
    [m] (after the first ``skip_s`` seconds), ``orientation_rmse_deg``,
    ``velocity_rmse`` (when available), ``nees_mean`` (pose + velocity + known
    calibration blocks; ``nees_dof`` its dimension), and when the truth
    calibration is in ``dataset.yaml``: ``lever_arm_error`` [m] per axis,
    ``lever_arm_error_norm``, ``lever_arm_within_3sigma``, ``time_offset_error``
    [s], ``time_offset_within_3sigma``.
    """
    truth = dataset.meta.truth
    td_true = truth.time_offset if truth is not None else None
    lever_true = None
    if truth is not None:
        lever_true = truth.lever_arm
    if result.t_imu is not None and td_true is not None:
        tt = np.asarray(result.t_imu) - td_true
    else:
        tt = np.asarray(result.t)
    p, q, v, valid = truth_at(dataset, tt)
    X = result.states
    sd = np.asarray(result.sd)

    def estimated(sl) -> bool:  # a block another estimator does not estimate has NaN sd
        return bool(np.any(np.all(np.isfinite(sd[:, sl]), axis=1)))

    has_att = estimated(ST.ETH) and q is not None  # no attitude in a position-only ground truth
    has_vel = estimated(ST.EV) and v is not None
    ok = valid & np.all(np.isfinite(X[:, ST.P]), axis=1)
    if not ok.any():
        raise InputError("no estimate overlaps the ground truth")
    ep = X[:, ST.P] - p
    eth = attitude_error(X[:, ST.Q], q) if has_att else None
    t0 = tt[ok][0]
    after = ok & (tt >= t0 + skip_s)
    out: dict[str, Any] = {
        "estimator": result.estimator,
        "n_outputs": int(ok.sum()),
        "position_rmse": float(np.sqrt(np.mean(np.sum(ep[ok] ** 2, axis=1)))),
        "position_rmse_after": float(np.sqrt(np.mean(np.sum(ep[after] ** 2, axis=1)))) if after.any() else None,
        "position_rmse_after_skip_s": float(skip_s),
        "position_rmse_axes": np.sqrt(np.mean(ep[ok] ** 2, axis=0)).tolist(),
        "orientation_rmse_deg": float(np.degrees(np.sqrt(np.mean(np.sum(eth[ok] ** 2, axis=1))))) if has_att else None,
    }
    if has_vel:
        ev = X[:, ST.V] - v
        out["velocity_rmse"] = float(np.sqrt(np.mean(np.sum(ev[ok] ** 2, axis=1))))
    # NEES on the estimated blocks with truth (error = truth ⊟ estimate)
    blocks = [(ST.EP, -ep)]
    if has_att:
        blocks.append((ST.ETH, eth))
    if has_vel:
        blocks.append((ST.EV, v - X[:, ST.V]))
    if lever_true is not None and estimated(ST.EPIU):
        blocks.append((ST.EPIU, np.asarray(lever_true) - X[:, ST.PIU]))
    td_err = slice(ST.ETD, ST.ETD + 1)
    if td_true is not None and estimated(td_err):
        blocks.append((td_err, (td_true - X[:, ST.TD])[:, None]))
    idx = np.concatenate([np.arange(ST.ERROR_DIM)[s] for s, _ in blocks])
    err = np.concatenate([e for _, e in blocks], axis=1)  # truth ⊟ estimate
    if result.covariances is not None:
        cov = result.covariances[:, idx][:, :, idx]
    else:
        cov = np.zeros((len(sd), len(idx), len(idx)))
        cov[:, np.arange(len(idx)), np.arange(len(idx))] = sd[:, idx] ** 2
    nees = nees_series(err[ok], cov[ok])
    out["nees_mean"] = float(np.nanmean(nees))
    out["nees_dof"] = int(len(idx))
    # position block alone (3 dof): robust to glitches of a motion-capture attitude / velocity
    out["nees_position_mean"] = float(np.nanmean(nees_series(-ep[ok], cov[ok][:, :3, :3])))
    if lever_true is not None and estimated(slice(15, 18)):
        e = X[-1, 16:19] - np.asarray(lever_true)
        sdl = result.sd[-1, 15:18]
        out["lever_arm_error"] = e.tolist()
        out["lever_arm_error_norm"] = float(np.linalg.norm(e))
        out["lever_arm_within_3sigma"] = bool(np.all(np.abs(e) <= 3 * sdl)) if np.all(np.isfinite(sdl)) else None
    if td_true is not None and estimated(slice(18, 19)):
        e = float(X[-1, 19] - td_true)
        s = float(result.sd[-1, 18])
        out["time_offset_error"] = e
        out["time_offset_within_3sigma"] = bool(abs(e) <= 3 * s) if np.isfinite(s) else None
    return out


def _truth_at(ds, t: np.ndarray) -> np.ndarray:
    gt = ds.groundtruth
    tg = gt["t"].to_numpy(float)
    return np.column_stack([np.interp(t, tg, gt[c].to_numpy(float)) for c in ("px", "py", "pz")])


def run_metrics(result, ds, skip_initial_s: float = 0.0) -> tuple[dict, dict]:
    """Position RMSE per axis, NEES, calibration errors of one estimate.

    Returns ``(row fields, trace)``; the trace holds the result stamps ``t``,
    position errors ``err`` (K, 3), sds ``sd`` (K, 3) and NEES ``nees`` (K,).
    NEES uses the full 3x3 position covariance when the result has covariances,
    else the diagonal (``nees_kind`` says which).
    """
    t = np.asarray(result.t, float)
    gt_t = ds.groundtruth["t"].to_numpy(float)
    keep = (t >= gt_t[0]) & (t <= gt_t[-1])
    t = t[keep]
    p = np.asarray(result.states, float)[keep, 0:3]
    err = p - _truth_at(ds, t)
    sd = np.asarray(result.sd, float)[keep, 0:3]
    cov = None
    if result.covariances is not None:
        c = np.asarray(result.covariances)[keep][:, 0:3, 0:3]
        if np.all(np.isfinite(c)):
            cov = c
    if cov is not None:
        nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
        kind = "full"
    else:
        nees = np.sum((err / sd) ** 2, axis=1)
        kind = "diag"
    m = t >= (t[0] + skip_initial_s) if len(t) else keep[keep]
    e = err[m]
    row: dict[str, Any] = {"n_samples": int(m.sum()), "nees_kind": kind}
    if len(e):
        rmse = np.sqrt(np.mean(e**2, axis=0))
        row.update(rmse_x=rmse[0], rmse_y=rmse[1], rmse_z=rmse[2], rmse_3d=float(np.sqrt(np.sum(rmse**2))))
        row.update(final_err_x=e[-1, 0], final_err_y=e[-1, 1], final_err_z=e[-1, 2])
        row["max_err_3d"] = float(np.max(np.linalg.norm(e, axis=1)))
        row["nees_pos_mean"] = float(np.mean(nees[m]))
    truth = ds.meta.truth
    cal = result.calibration or {}
    la_sd = np.asarray(cal.get("lever_arm_sd", [np.nan] * 3), float)
    # A calibration the estimator keeps fixed (sd NaN or 0) has no estimation error to report.
    if truth is not None and truth.lever_arm is not None and np.all(np.isfinite(la_sd)) and np.any(la_sd > 0):
        d = np.asarray(cal["lever_arm"], float) - np.asarray(truth.lever_arm, float)
        row.update(lever_arm_err=float(np.linalg.norm(d)), lever_arm_err_x=d[0], lever_arm_err_y=d[1],
                   lever_arm_err_z=d[2])
    td_sd = cal.get("time_offset_sd", np.nan)
    if truth is not None and truth.time_offset is not None and td_sd is not None and np.isfinite(td_sd) and td_sd > 0:
        row["time_offset_err"] = float(cal["time_offset"] - truth.time_offset)
    res = result.residuals
    if res is not None and len(res) and "accepted" in res:
        row["ranges_accepted"] = float(np.mean(res["accepted"].to_numpy(bool)))
    row["n_warnings"] = len(result.warnings or [])
    # An estimator that stops (e.g. the ESKF after a divergence it cannot recover from) has
    # metrics over a shorter span only: say how much of the flight the estimate covers.
    fin = np.all(np.isfinite(p), axis=1)
    span = float(gt_t[-1] - gt_t[0])
    row["coverage"] = float((t[fin][-1] - t[fin][0]) / span) if fin.sum() > 1 and span > 0 else 0.0
    div_t = [float(ev["t"]) for ev in (result.events or []) if ev.get("kind") == "divergence" and "t" in ev]
    row["divergences"] = sum(1 for ev in (result.events or []) if ev.get("kind") == "divergence")
    return row, {"t": t, "err": err, "sd": sd, "nees": nees, "divergence_t": np.asarray(div_t, float)}
