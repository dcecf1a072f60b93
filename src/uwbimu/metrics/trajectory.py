"""Trajectory error metrics against ground truth: ATE, RPE, robust time association.

Pipeline (:func:`evaluate_trajectory`):

1. **Glitch screening** of the ground truth (:func:`detect_glitches`): each
   sample is compared with the running median of its neighbourhood (position,
   and attitude when given); for smooth motion the residual is a curvature
   (acceleration) term of a few mm, for a mocap jump it is the jump.  Samples
   whose residual exceeds ``median + k * 1.4826 * MAD`` (and an absolute
   floor) are excluded; the test is repeated on the remaining samples.  Excluded samples are bridged by
   interpolating between their good neighbours and counted.
2. **Time association** (:func:`associate`): ground truth is interpolated at
   the estimate stamps (both on the UWB clock).  Estimate samples outside the
   ground-truth span or inside a ground-truth gap longer than ``max_gap`` are
   not scored (counted).
3. **Alignment** (:mod:`uwbimu.metrics.align`), then
4. **ATE** (position and attitude) and **RPE** over travelled distances.

Conventions: positions in m, angles reported in degrees, quaternions
``[qw, qx, qy, qz]`` rotating body vectors into the world.
"""

from __future__ import annotations

from uwbimu.errors import InputError
from dataclasses import dataclass, field
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from uwbimu.metrics.align import Alignment, align_trajectories
from uwbimu.models.quaternion import (
    quat_conjugate,
    quat_log,
    quat_multiply,
    quat_normalize,
    quat_slerp,
    quat_to_rotmat,
)

POS_COLS = ["px", "py", "pz"]
QUAT_COLS = ["qw", "qx", "qy", "qz"]


# --------------------------------------------------------------------------- glitches
def _rolling_median(x: np.ndarray, half: int) -> np.ndarray:
    """Centred running median over ``2 * half + 1`` samples (per column)."""
    return pd.DataFrame(x).rolling(2 * half + 1, center=True, min_periods=1).median().to_numpy()


def _local_residuals(p: np.ndarray, q: Optional[np.ndarray], half: int):
    """Distance of each sample from the running median of its neighbourhood.

    A running median ignores up to ``half`` consecutive outliers, so a glitch
    does not spill over onto its good neighbours (a neighbour-interpolation
    test would flag those too).  For smooth motion the median of a short
    window is the centre sample up to a curvature term (a * (half dt)^2 / 2,
    a few mm for walking speeds at >= 50 Hz).
    """
    e_pos = np.linalg.norm(p - _rolling_median(p, half), axis=1)
    e_rot = np.zeros(len(p))
    if q is not None:
        # make the quaternion sequence sign-continuous before taking medians
        s = np.sign(np.r_[1.0, np.sum(q[1:] * q[:-1], axis=1)])
        s[s == 0] = 1.0
        qc = q * np.cumprod(s)[:, None]
        qm = quat_normalize(_rolling_median(qc, half))
        e_rot = np.linalg.norm(quat_log(quat_multiply(quat_conjugate(qm), qc)), axis=1)
    return e_pos, e_rot


def _robust_threshold(x: np.ndarray, k: float, floor: float) -> float:
    med = float(np.median(x))
    mad = float(np.median(np.abs(x - med)))
    return max(floor, med + k * 1.4826 * mad)


def _iterate_mask(x_bad: np.ndarray, residual_fn, k: float, floor: float, half: int, max_iter: int) -> np.ndarray:
    bad = x_bad.copy()
    for _ in range(max_iter):
        keep = np.flatnonzero(~bad)
        if len(keep) < 2 * half + 2:
            break
        e = residual_fn(keep)
        new = e > _robust_threshold(e, k, floor)
        if not new.any():
            break
        bad[keep[new]] = True
    return bad


def detect_glitches(
    t: np.ndarray,
    p: np.ndarray,
    k: float = 8.0,
    floor: float = 0.02,
    half_window: int = 4,
    max_iter: int = 3,
) -> np.ndarray:
    """Flag ground-truth position samples that jump away from their neighbours.

    Each sample is compared with the running median of the ``2 * half_window + 1``
    samples around it; residuals above ``median + k * 1.4826 * MAD`` and above
    ``floor`` are excluded.  The test is repeated on the surviving samples.

    Parameters
    ----------
    t : (N,) stamps [s], increasing.  The running median works on sample index
        (ground-truth stamps jitter; the README of INRoL warns against
        per-sample differences), ``t`` only fixes the order and length.
    p : (N, 3) positions [m].
    k : MAD multiplier of the robust threshold.
    floor : absolute minimum threshold [m] so that a very clean trajectory
        (MAD ~ 0) does not flag its ordinary noise.
    half_window : glitches up to this many consecutive samples are caught.
    max_iter : passes.

    Returns
    -------
    (N,) bool mask, True for an excluded (glitch or non-finite) sample.
    """
    p = np.asarray(p, float)
    if len(np.asarray(t)) != len(p):
        raise InputError("t and p must have the same length")
    bad = ~np.isfinite(p).all(axis=1)
    return _iterate_mask(bad, lambda keep: _local_residuals(p[keep], None, half_window)[0], k, floor, half_window, max_iter)


def detect_attitude_glitches(
    q: np.ndarray,
    k: float = 8.0,
    floor_deg: float = 2.0,
    half_window: int = 4,
    max_iter: int = 3,
) -> np.ndarray:
    """Same test as :func:`detect_glitches` for attitudes (N, 4) ``[qw, qx, qy, qz]``.

    Kept separate from positions: a motion-capture body can have a noisy
    attitude (INRoL: several-degree single-sample spikes) while its position is
    clean, and an attitude spike must not remove a good position.
    """
    q = np.asarray(q, float)
    bad = ~np.isfinite(q).all(axis=1)
    return _iterate_mask(
        bad,
        lambda keep: _local_residuals(np.zeros((len(keep), 3)), quat_normalize(q[keep]), half_window)[1],
        k,
        np.radians(floor_deg),
        half_window,
        max_iter,
    )


# --------------------------------------------------------------------------- association
@dataclass
class Association:
    """Ground truth interpolated at estimate stamps.

    ``valid`` marks estimate samples with an interpolated ground-truth position;
    ``valid_q`` those with an interpolated attitude (attitude glitches are
    screened separately, so the two can differ).
    """

    valid: np.ndarray  # (M,) bool
    p_gt: np.ndarray  # (M, 3), NaN where not valid
    q_gt: np.ndarray  # (M, 4), NaN where not valid_q
    valid_q: np.ndarray  # (M,) bool
    n_gt: int = 0
    n_duplicates: int = 0
    n_glitches: int = 0
    glitch_times: list = field(default_factory=list)
    n_attitude_glitches: int = 0
    n_outside_span: int = 0
    n_in_gaps: int = 0


def _bracket(t_query: np.ndarray, tg: np.ndarray, max_gap: float):
    """Indices/weights of the good samples bracketing each query stamp."""
    inside = (t_query >= tg[0]) & (t_query <= tg[-1])
    idx = np.clip(np.searchsorted(tg, t_query, side="right"), 1, len(tg) - 1)
    i0, i1 = idx - 1, idx
    span = tg[i1] - tg[i0]
    in_gap = inside & (span > max_gap)
    alpha = np.where(span > 0, (t_query - tg[i0]) / np.where(span > 0, span, 1.0), 0.0)
    return inside, in_gap, i0, i1, alpha


def associate(
    t_est: np.ndarray,
    t_gt: np.ndarray,
    p_gt: np.ndarray,
    q_gt: Optional[np.ndarray] = None,
    max_gap: float = 0.5,
    screen_glitches: bool = True,
    glitch_k: float = 8.0,
) -> Association:
    """Interpolate ground truth at the estimate stamps, robust to glitches.

    Positions are interpolated linearly, attitudes by slerp, each between the
    nearest *good* samples (glitches excluded and bridged).

    Parameters
    ----------
    t_est : (M,) estimate stamps [s] (UWB clock).
    t_gt, p_gt, q_gt : ground-truth stamps [s], positions [m], attitudes.
    max_gap : an estimate stamp is scored only if the bracketing good
        ground-truth samples are at most this far apart [s].
    screen_glitches : run :func:`detect_glitches` / :func:`detect_attitude_glitches`.
    glitch_k : MAD multiplier of the glitch test.

    Returns
    -------
    Association
    """
    t_est = np.asarray(t_est, float)
    t_gt = np.asarray(t_gt, float)
    p_gt = np.asarray(p_gt, float)
    q_gt = None if q_gt is None else quat_normalize(np.asarray(q_gt, float))
    order = np.argsort(t_gt, kind="stable")
    t_gt, p_gt = t_gt[order], p_gt[order]
    if q_gt is not None:
        q_gt = q_gt[order]
    # repeated stamps cannot be interpolated between: keep the first of each
    dup = np.r_[False, np.diff(t_gt) <= 0]
    bad = dup | ~np.isfinite(p_gt).all(axis=1)
    bad_q = dup.copy() if q_gt is None else dup | ~np.isfinite(q_gt).all(axis=1)
    keep0 = np.flatnonzero(~dup)
    if screen_glitches and len(keep0) >= 12:
        bad[keep0] |= detect_glitches(t_gt[keep0], p_gt[keep0], k=glitch_k)
        if q_gt is not None:
            bad_q[keep0] |= detect_attitude_glitches(q_gt[keep0], k=glitch_k)
    n_glitch = int((bad & ~dup).sum())
    glitch_times = t_gt[bad & ~dup].tolist()

    m = len(t_est)
    out_p = np.full((m, 3), np.nan)
    out_q = np.full((m, 4), np.nan)
    valid = np.zeros(m, bool)
    valid_q = np.zeros(m, bool)
    n_out, n_gap = m, 0
    good = np.flatnonzero(~bad)
    if len(good) >= 2:
        tg, pg = t_gt[good], p_gt[good]
        inside, in_gap, i0, i1, a = _bracket(t_est, tg, max_gap)
        valid = inside & ~in_gap
        v = np.flatnonzero(valid)
        out_p[v] = pg[i0[v]] + a[v, None] * (pg[i1[v]] - pg[i0[v]])
        n_out, n_gap = int((~inside).sum()), int(in_gap.sum())
    good_q = np.flatnonzero(~bad_q)
    if q_gt is not None and len(good_q) >= 2:
        tq, qg = t_gt[good_q], q_gt[good_q]
        inside_q, in_gap_q, j0, j1, b = _bracket(t_est, tq, max_gap)
        valid_q = inside_q & ~in_gap_q
        v = np.flatnonzero(valid_q)
        out_q[v] = quat_slerp(qg[j0[v]], qg[j1[v]], b[v])
    return Association(
        valid=valid,
        p_gt=out_p,
        q_gt=out_q,
        valid_q=valid_q,
        n_gt=len(t_gt),
        n_duplicates=int(dup.sum()),
        n_glitches=n_glitch,
        glitch_times=glitch_times,
        n_attitude_glitches=int((bad_q & ~dup).sum()) if q_gt is not None else 0,
        n_outside_span=n_out,
        n_in_gaps=n_gap,
    )


# --------------------------------------------------------------------------- statistics
def error_stats(e: np.ndarray) -> dict:
    """RMSE, mean, median, max (and count) of non-negative errors."""
    e = np.asarray(e, float)
    e = e[np.isfinite(e)]
    if len(e) == 0:
        return {"rmse": float("nan"), "mean": float("nan"), "median": float("nan"), "max": float("nan"), "n": 0}
    return {
        "rmse": float(np.sqrt(np.mean(e**2))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "max": float(np.max(e)),
        "n": int(len(e)),
    }


def rotation_angle_deg(q_a: np.ndarray, q_b: np.ndarray) -> np.ndarray:
    """Angle [deg] of the rotation between two (N, 4) attitude sequences."""
    dq = quat_multiply(quat_conjugate(quat_normalize(q_a)), quat_normalize(q_b))
    return np.degrees(np.linalg.norm(quat_log(dq), axis=-1))


def relative_pose_error(
    p_est: np.ndarray,
    q_est: Optional[np.ndarray],
    p_gt: np.ndarray,
    q_gt: Optional[np.ndarray],
    distances: Sequence[float] = (1.0, 2.0, 5.0),
    max_pairs: int = 20000,
) -> dict:
    """Relative pose error over travelled ground-truth distances.

    For each start sample ``i`` the end sample ``j`` is the first one where the
    ground-truth path length from ``i`` reaches ``d``.  With relative motions
    ``T_ij = T_i^-1 T_j`` the error is ``E = T_ij,gt^-1 T_ij,est``; we report
    ``|trans(E)|`` [m] and ``angle(E)`` [deg].  With attitudes, RPE is invariant
    to a rigid change of world frame; with world-frame displacements (no
    attitudes) it depends on the alignment's rotation.

    Parameters
    ----------
    p_est, q_est, p_gt, q_gt : matched (N, 3) / (N, 4) sequences.
    distances : path lengths [m].
    max_pairs : start samples are thinned evenly to at most this many per distance.

    Returns
    -------
    dict keyed by ``f"{d:g}"`` with translation/rotation statistics and pair count.
    """
    p_est = np.asarray(p_est, float)
    p_gt = np.asarray(p_gt, float)
    seg = np.linalg.norm(np.diff(p_gt, axis=0), axis=1)
    cum = np.r_[0.0, np.cumsum(seg)]
    out = {}
    use_q = q_est is not None and q_gt is not None
    if use_q:
        R_est = quat_to_rotmat(q_est)
        R_gt = quat_to_rotmat(q_gt)
    for d in distances:
        j = np.searchsorted(cum, cum + d, side="left")
        i = np.flatnonzero(j < len(cum))
        key = f"{d:g}"
        if len(i) == 0:
            out[key] = {"n_pairs": 0, "translation": error_stats([]), "rotation_deg": error_stats([])}
            continue
        if len(i) > max_pairs:
            i = i[np.linspace(0, len(i) - 1, max_pairs).astype(int)]
        jj = j[i]
        if use_q:
            # relative translations expressed in the start body frame
            d_est = np.einsum("nji,nj->ni", R_est[i], p_est[jj] - p_est[i])
            d_gt = np.einsum("nji,nj->ni", R_gt[i], p_gt[jj] - p_gt[i])
            rel_est = np.einsum("nji,njk->nik", R_est[i], R_est[jj])
            rel_gt = np.einsum("nji,njk->nik", R_gt[i], R_gt[jj])
            E = np.einsum("nji,njk->nik", rel_gt, rel_est)
            cosang = np.clip((np.trace(E, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
            rot = np.degrees(np.arccos(cosang))
        else:
            d_est = p_est[jj] - p_est[i]
            d_gt = p_gt[jj] - p_gt[i]
            rot = np.array([])
        trans = np.linalg.norm(d_est - d_gt, axis=1)
        out[key] = {
            "n_pairs": int(len(i)),
            "translation": error_stats(trans),
            "translation_percent": float(100.0 * np.mean(trans) / d),
            "rotation_deg": error_stats(rot),
        }
    return out


# --------------------------------------------------------------------------- top level
@dataclass
class Evaluation:
    """Everything :func:`evaluate_trajectory` computed (summary + arrays for plots)."""

    summary: dict
    t: np.ndarray  # (K,) scored stamps
    p_est_aligned: np.ndarray  # (K, 3) in the ground-truth frame
    p_gt: np.ndarray  # (K, 3)
    pos_err: np.ndarray  # (K, 3) aligned estimate - truth
    rot_err_deg: Optional[np.ndarray]
    alignment: Alignment


#: What the attitude error reads when the ground-truth body frame differs from the IMU frame.
ATTITUDE_NA = "n/a (frames differ)"


def evaluate_trajectory(
    traj: pd.DataFrame,
    gt: pd.DataFrame,
    align: str = "se3",
    distances: Sequence[float] = (1.0, 2.0, 5.0),
    max_gap: float = 0.5,
    skip_initial: float = 0.0,
    screen_glitches: bool = True,
    compare_attitude: bool = True,
) -> Evaluation:
    """Score an estimated trajectory against ground truth.

    Parameters
    ----------
    traj : estimator ``trajectory.csv`` as a DataFrame (``t, px, py, pz`` and
        optionally ``qw, qx, qy, qz``).
    gt : ground truth (``t, px, py, pz`` and optionally ``qw..qz``), same clock.
    align : ``none | position | se3`` (see :mod:`uwbimu.metrics.align`).
    distances : RPE path lengths [m].
    max_gap : longest ground-truth gap bridged by interpolation [s].
    skip_initial : ignore estimate samples in the first ``skip_initial`` seconds
        (convergence), counted in the summary.
    screen_glitches : exclude ground-truth jumps (see :func:`detect_glitches`).
    compare_attitude : False when the ground-truth body frame is not the IMU
        frame (undocumented rotation, e.g. ISAS-Walk's Vive tracker): attitudes
        are ignored, the attitude ATE is reported as ``"n/a (frames differ)"``
        (``summary["ate_rotation"]``) and RPE uses world-frame displacements.

    Returns
    -------
    Evaluation
    """
    t_est = traj["t"].to_numpy(float)
    p_est = traj[POS_COLS].to_numpy(float)
    has_q = (compare_attitude and all(c in traj.columns for c in QUAT_COLS)
             and all(c in gt.columns for c in QUAT_COLS))
    q_est = quat_normalize(traj[QUAT_COLS].to_numpy(float)) if has_q else None
    q_gt_raw = gt[QUAT_COLS].to_numpy(float) if has_q else None
    asc = associate(
        t_est, gt["t"].to_numpy(float), gt[POS_COLS].to_numpy(float), q_gt_raw, max_gap=max_gap, screen_glitches=screen_glitches
    )
    finite = np.isfinite(p_est).all(axis=1)
    early = t_est < (t_est[0] + skip_initial) if len(t_est) else np.zeros(0, bool)
    use = asc.valid & finite & ~early
    n_use = int(use.sum())
    if n_use < 3:
        raise InputError(
            f"only {n_use} estimate samples overlap the ground truth "
            f"(estimate {t_est.min() if len(t_est) else float('nan'):.3f}..{t_est.max() if len(t_est) else float('nan'):.3f} s, "
            f"ground truth {gt['t'].min():.3f}..{gt['t'].max():.3f} s): are both on the same clock?"
        )
    pe, pg = p_est[use], asc.p_gt[use]
    al = align_trajectories(pe, pg, align)
    pe_al = al.apply_positions(pe)
    err = pe_al - pg
    en = np.linalg.norm(err, axis=1)
    summary: dict = {
        "align": al.as_dict(),
        "association": {
            "n_estimate": int(len(t_est)),
            "n_scored": n_use,
            "n_groundtruth": asc.n_gt,
            "n_groundtruth_duplicate_stamps": asc.n_duplicates,
            "n_groundtruth_glitches_excluded": asc.n_glitches,
            "n_groundtruth_attitude_glitches_excluded": asc.n_attitude_glitches,
            "groundtruth_glitch_times": [round(x, 6) for x in asc.glitch_times[:50]],
            "n_estimate_outside_groundtruth_span": asc.n_outside_span,
            "n_estimate_in_groundtruth_gaps": asc.n_in_gaps,
            "n_estimate_nonfinite": int((~finite).sum()),
            "n_estimate_skipped_initial": int((early & asc.valid & finite).sum()),
            "max_gap_s": max_gap,
            "skip_initial_s": skip_initial,
            "scored_time_span_s": [float(t_est[use][0]), float(t_est[use][-1])],
        },
        "ate_position": error_stats(en),
        "ate_position_per_axis_rmse": np.sqrt(np.mean(err**2, axis=0)).tolist(),
    }
    rot = None
    if not compare_attitude:
        summary["ate_rotation"] = ATTITUDE_NA
    if has_q:
        use_q = use & asc.valid_q
        q_al = al.apply_quaternions(q_est[use_q])
        rot_all = np.full(len(t_est), np.nan)
        rot_all[use_q] = rotation_angle_deg(q_al, asc.q_gt[use_q])
        rot = rot_all[use]
        summary["ate_rotation_deg"] = error_stats(rot)
        # RPE needs a pose at both ends: use samples with position and attitude
        summary["rpe"] = relative_pose_error(
            al.apply_positions(p_est[use_q]), q_al, asc.p_gt[use_q], asc.q_gt[use_q], distances=distances
        )
    else:
        summary["rpe"] = relative_pose_error(pe_al, None, pg, None, distances=distances)
    return Evaluation(summary, t_est[use], pe_al, pg, err, rot, al)
