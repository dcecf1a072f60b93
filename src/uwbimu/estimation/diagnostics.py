"""Run diagnostics: IMU gaps, UWB outages and excitation (observability) warnings.

The excitation monitor answers "can this motion calibrate the lever arm /
time offset?": the lever arm needs rotation (``R p_IU`` must change, else it
is indistinguishable from a position offset), the time offset needs a
changing velocity (a constant-velocity shift ``v t_d`` is a position offset
too).  It measures, over a sliding window, the RMS body rate and the RMS
world acceleration of the estimated motion, and it checks that the final
standard deviations really shrank below their priors.  Warnings are plain
sentences; events carry the intervals.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from uwbimu.estimation.filterpass import REC_ACC, Problem
from uwbimu.estimation.problem import block_mode, block_prior_sd
from uwbimu.models.blocks import CALIBRATION_BLOCKS
from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.models.reference import G_WORLD
from uwbimu.models import state as S

_MAX_LISTED = 8


def imu_gap_events(imu_t: np.ndarray, dt_max: float) -> tuple[list[dict[str, Any]], list[str]]:
    """Events and warnings for IMU intervals longer than ``dt_max`` (propagated across)."""
    d = np.diff(imu_t)
    idx = np.flatnonzero(d > dt_max)
    events = [{"t": float(imu_t[i]), "kind": "imu_gap", "duration": float(d[i])} for i in idx]
    warnings = [f"IMU gap of {d[i]:.3f} s at IMU t={imu_t[i]:.3f} s: propagated across (covariance grows)"
                for i in idx[:_MAX_LISTED]]
    if len(idx) > _MAX_LISTED:
        warnings.append(f"... and {len(idx) - _MAX_LISTED} more IMU gaps (see events)")
    return events, warnings


def _intervals(t: np.ndarray, bad: np.ndarray, min_len: float) -> list[tuple[float, float]]:
    """Maximal runs of ``bad`` longer than ``min_len`` as ``(t_start, t_end)``."""
    out = []
    if not len(t):
        return out
    b = np.concatenate([[False], bad, [False]]).astype(int)
    starts = np.flatnonzero(np.diff(b) == 1)
    ends = np.flatnonzero(np.diff(b) == -1) - 1
    for s, e in zip(starts, ends):
        if t[e] - t[s] >= min_len:
            out.append((float(t[s]), float(t[e])))
    return out


def _sliding_rms(x: np.ndarray, n: int) -> np.ndarray:
    """Centred sliding RMS of a 1-D signal over ``n`` samples."""
    n = max(1, min(n, len(x)))
    c = np.concatenate([[0.0], np.cumsum(x * x)])
    lo = np.clip(np.arange(len(x)) - n // 2, 0, len(x) - n)
    return np.sqrt((c[lo + n] - c[lo]) / n)


def excitation_profile(prob: Problem, t_imu_out: np.ndarray, X: np.ndarray, window_s: float):
    """Sliding-window RMS body rate [rad/s] and world acceleration [m/s^2] of the estimated motion.

    Returns ``(t, rot_rms, acc_rms)`` on a decimated IMU grid (about 100 Hz, IMU clock).
    """
    step = max(1, int(round(0.01 / prob.dt_nom)))
    t = prob.imu_t[::step]
    u = prob.imu_u[::step]
    if len(t_imu_out) == 0:
        return t, np.zeros(len(t)), np.zeros(len(t))
    i = np.clip(np.searchsorted(t_imu_out, t), 0, len(t_imu_out) - 1)
    xs = X[i]
    w = u[:, 3:6] - xs[:, S.BG]
    R = quat_to_rotmat(xs[:, S.Q])
    acc = np.einsum("nij,nj->ni", R, u[:, :3] - xs[:, S.BA]) - G_WORLD
    n = max(1, int(round(window_s / (prob.dt_nom * step))))
    return t, _sliding_rms(np.linalg.norm(w, axis=1), n), _sliding_rms(np.linalg.norm(acc, axis=1), n)


def excitation_warnings(prob: Problem, t_imu_out, X, sd, priors, opts) -> tuple[list[str], list[dict[str, Any]]]:
    """Warnings when the motion does not excite a calibration block (lever arm, time offset).

    Loops over the estimated :data:`~uwbimu.models.blocks.CALIBRATION_BLOCKS`: the block's declared
    ``excitation`` measure (RMS body rate or world acceleration) against its threshold (events
    ``low_excitation`` with ``parameter`` the block's label), then its final sd against its prior
    (:func:`~uwbimu.estimation.problem.block_prior_sd`) in the block's table unit.
    """
    ex = opts.excitation
    warnings: list[str] = []
    events: list[dict[str, Any]] = []
    if len(X) == 0:
        return warnings, events
    t, rot, acc = excitation_profile(prob, t_imu_out, X, ex.window_s)
    # the motion measures a calibration block can need (BlockSpec.excitation): signal, threshold, unit
    measures = {"rotation": (rot, ex.min_rotation_rate, "rad/s"), "acceleration": (acc, ex.min_acceleration, "m/s^2")}
    estimated = [b for b in CALIBRATION_BLOCKS if block_mode(opts, b) == "estimate"]
    for b in estimated:
        if b.excitation is None:
            continue
        name, what, (sig, thr, unit) = b.label, b.excitation, measures[b.excitation]
        low = sig < thr
        frac = float(np.mean(~low)) if len(sig) else 0.0
        for a, e in _intervals(t, low, ex.window_s):
            events.append({"t": a, "kind": "low_excitation", "parameter": name, "t_end": e,
                           "measure": f"RMS {what}", "threshold": thr})
        if frac < 0.1:
            warnings.append(
                f"{name}: weak excitation, RMS {what} >= {thr} {unit} in only {100 * frac:.0f}% of the log "
                f"(max {float(sig.max()):.3g} {unit}); the {name} is poorly observable from this motion"
            )
    # the honest test: did the uncertainty actually shrink below the prior (the grid's when t_d was searched)?
    sd_end = sd[-1]
    layout = prob.state_layout()
    for b in estimated:
        s_b, prior = sd_end[layout.err(b.name)], block_prior_sd(priors, opts, b.name)
        ratio = s_b / np.where(prior > 0, prior, np.nan)
        if np.any(ratio > ex.sd_ratio_warn):
            scale, unit = b.table
            warnings.append(f"{b.label} not well determined: final sd {_fmt(scale * s_b)} {unit} vs prior "
                            f"{_fmt(scale * prior)} {unit}; {b.excitation_advice}")
    return warnings, events


def _fmt(v: np.ndarray) -> str:
    """A block's values in a warning: ``1.5`` for a scalar, ``[1.5, 0.2, 3.0]`` for a vector (0.1 resolution)."""
    return f"{float(v[0]):.1f}" if len(v) == 1 else str(np.round(v, 1).tolist())


def outage_warnings(prob: Problem, rec: np.ndarray, opts) -> tuple[list[str], list[dict[str, Any]]]:
    """UWB outages (no accepted range) and silent anchors."""
    warnings: list[str] = []
    events: list[dict[str, Any]] = []
    acc = rec[:, REC_ACC] > 0
    ta = prob.uwb_t[acc]
    if len(ta) > 1:
        gaps = np.diff(ta)
        idx = np.flatnonzero(gaps > opts.uwb_outage_s)
        for i in idx:
            events.append({"t": float(ta[i]), "kind": "uwb_outage", "duration": float(gaps[i])})
        for i in idx[:_MAX_LISTED]:
            warnings.append(f"UWB outage: no accepted range for {gaps[i]:.2f} s from t={ta[i]:.2f} s "
                            f"(IMU-only propagation, covariance grows)")
        if len(idx) > _MAX_LISTED:
            warnings.append(f"... and {len(idx) - _MAX_LISTED} more UWB outages (see events)")
    t0, t1 = (prob.uwb_t[0], prob.uwb_t[-1]) if len(prob.uwb_t) else (0.0, 0.0)
    listed = 0
    for ai, name in enumerate(prob.anchor_ids):
        ts = prob.uwb_t[prob.uwb_a == ai]
        if len(ts) == 0:
            warnings.append(f"anchor {name}: no range in the log")
            continue
        med = float(np.median(np.diff(ts))) if len(ts) > 1 else np.inf
        lim = max(opts.uwb_outage_s, 10 * med)
        full = np.concatenate([[t0], ts, [t1]])
        gaps = np.diff(full)
        for i in np.flatnonzero(gaps > lim):
            events.append({"t": float(full[i]), "kind": "anchor_silent", "anchor": name, "duration": float(gaps[i])})
            if listed < _MAX_LISTED:
                warnings.append(f"anchor {name}: no range for {gaps[i]:.2f} s from t={full[i]:.2f} s")
            listed += 1
    if listed > _MAX_LISTED:
        warnings.append(f"... and {listed - _MAX_LISTED} more silent-anchor intervals (see events)")
    return warnings, events
