"""Per-window observability of a trajectory or a real log.

For each time window the Fisher information of the 19-dim error state at the
window start ``dx0 = (dp, dv, dtheta, db_a, db_g, dp_IU, dt_d)`` (right/body
attitude perturbation, :mod:`uwbimu.models.state`) given the window's ranges is

    I = sum_r  (H_r Phi(t_r + t_d, t0))^T (H_r Phi(t_r + t_d, t0)) / s_r^2,

i.e. the linearised, noise-weighted observability Gramian along the recorded
IMU and UWB stamps.  ``Phi`` is the error-state transition of the linearised
kinematics (seed eq. 4-7) along the trajectory, ``H_r`` the range Jacobian
(seed eq. 8) including the time-offset column ``-e^T (v + R (w x p_IU))``.

IMU noise is included as an inflation of each range's variance,
``s_r^2 = sigma_r^2 + H_r P_imu(t_r) H_r^T`` where ``P_imu`` is the covariance
that IMU white noise and bias random walks accumulate from the window start.
Correlations between ranges through the shared IMU noise are neglected (so the
bound is approximate; it is exact for a noise-free IMU).

Per window the module reports the Cramér-Rao lower bounds on the standard
deviations ``sqrt(diag(I^-1))`` (SI units), and — on the information matrix
made dimensionless with typical scales ``D`` (``D I D``; 1 m, 1 m/s, 1 rad,
0.1 m/s^2, 0.01 rad/s, 0.1 m, 0.01 s by default) — its smallest eigenvalue,
condition number and weakest direction (named as in
:mod:`uwbimu.observability.directions`).  A window whose lever-arm (time-offset)
bound exceeds a threshold is flagged as not exciting it.

The inner loop (transition and IMU covariance along ~4000 IMU samples) is a
numba kernel built on the estimator's error-state transition
(:mod:`uwbimu.models.kernels`, written once); tests pin it to finite differences of
:func:`uwbimu.models.reference.propagate` and
:func:`uwbimu.models.reference.range_measurement`.
"""

from __future__ import annotations

from uwbimu.errors import InputError, UsageError
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
import pandas as pd
from numba import njit

from uwbimu.models.imu import BMI088, ImuNoise
from uwbimu.models.kernels import phi_left_R, refresh_stale_cache
from uwbimu.models import kernels as _physics
from uwbimu.models.quaternion import quat_normalize, quat_slerp, quat_to_rotmat, rotmat_to_quat
from uwbimu.models.state import (BA, BG, E_L, E_TD, EBA, EBG, ERROR_DIM, ERROR_STATE_NAMES, ETD, ETH,
                                 EV, P as NP_, PIU, Q, TD, V as NV_, StateLayout)
from uwbimu.models.blocks import BLOCKS, CALIBRATION_BLOCKS, legacy_name_map
from uwbimu.observability.directions import candidates_for, name_directions

#: the blocks of the 19-dim error state the analysis runs on, in state order (models.blocks declarations)
_BASE_BLOCKS = tuple(b for b in BLOCKS if b.multiplicity == "one")

#: Typical magnitudes used to make the information dimensionless, per block symbol (``BlockSpec.obs_scale``:
#: 1 m, 1 m/s, 1 rad, 0.1 m/s^2, 0.01 rad/s, 0.1 m, 0.01 s).
DEFAULT_SCALES = {b.symbol: b.obs_scale for b in _BASE_BLOCKS}

#: Prior sd per block symbol at each window's start [m, m/s, rad, m/s^2, rad/s, m, s]
#: (``BlockSpec.obs_prior_sd``): the ESKF's defaults (``EskfOptions``: position 0.3 m, velocity 0.5 m/s,
#: lever arm 0.3 m, t_d 0.1 s; attitude 0.1 rad ~ 6 deg roll/pitch after
#: levelling; biases of a consumer IMU).
DEFAULT_PRIOR_SD = {b.symbol: b.obs_prior_sd for b in _BASE_BLOCKS}

#: the WindowOptions field of each calibration block's optional absolute sd threshold (by output key)
_SD_THRESHOLD_OPTION = {"lever_arm": "lever_sd_threshold", "time_offset": "td_sd_threshold"}

#: the calibration blocks and their error-state slices (flags ``<output_key>_excited``, ``_info_gain``)
_CAL = tuple((b, StateLayout().err(b.name)) for b in CALIBRATION_BLOCKS)


@dataclass
class Trajectory:
    """Linearisation trajectory on the UWB clock.

    Attributes
    ----------
    t : (K,) UWB-clock stamps [s].
    p, v : (K, 3) IMU position / velocity, world [m, m/s].
    q : (K, 4) attitude quaternions (body -> world).
    b_a, b_g : (K, 3) or (3,) biases (IMU frame).
    lever_arm : (3,) ``p_IU`` [m]; t_d : time offset [s].
    """

    t: np.ndarray
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray
    b_a: np.ndarray
    b_g: np.ndarray
    lever_arm: np.ndarray
    t_d: float = 0.0


@dataclass
class WindowOptions:
    """Options of :func:`window_observability`.

    Attributes
    ----------
    window : window length [s] (one window spanning the log: the whole-log bound).
    range_sigma, imu_noise : noise model (None: dataset meta, else 0.1 m / BMI088).
    include_imu_noise : IMU white noise and bias random walks as process noise.
    bound : ``"pcrb"`` (default): posterior Cramer-Rao bound from the stated
        prior ``prior_sd`` at the window start, IMU noise as process noise;
        ``"gramian"``: the former noise-weighted Gramian of the start state
        with no prior and the IMU noise as a range-variance inflation
        (approximate, correlations dropped; kept for comparison).
    prior_sd : prior sd per block at each window start (see :data:`DEFAULT_PRIOR_SD`).
    chain : ``True`` (default): the windows are chained like the estimator —
        the prior of a window is the bound at the end of the previous one (the
        first starts from ``prior_sd``), so ``sd_<state>`` at a window's end is
        what a matched filter's sigma should be then; ``False``: every window
        stands alone from ``prior_sd``.
    excited_sd_ratio : a window excites the lever arm (time offset) when the
        marginal precision its ranges add, ``1/sd_end^2 - 1/sd_prior_end^2``,
        is at least ``1/ratio^2 - 1`` times the prior precision ``1/prior_sd^2``
        (every lever-arm axis): the window alone would take the prior sd to
        ``ratio`` x prior.  0.5 is the estimator's own ``excitation.sd_ratio_warn``.
    lever_sd_threshold, td_sd_threshold : optional absolute accuracy [m, s]
        the flags also require (None: not used).
    scales : typical magnitudes making the information dimensionless.
    min_ranges : fewer ranges in a window: "no data".
    """

    window: float = 20.0
    range_sigma: Optional[float] = None
    imu_noise: Optional[ImuNoise] = None
    include_imu_noise: bool = True
    bound: str = "pcrb"
    prior_sd: dict = field(default_factory=lambda: dict(DEFAULT_PRIOR_SD))
    chain: bool = True
    excited_sd_ratio: float = 0.5
    lever_sd_threshold: Optional[float] = None
    td_sd_threshold: Optional[float] = None
    scales: dict = field(default_factory=lambda: dict(DEFAULT_SCALES))
    min_ranges: int = 10


# --------------------------------------------------------------------------
# trajectories
# --------------------------------------------------------------------------
def trajectory_from_groundtruth(ds, lever_arm=None, t_d: Optional[float] = None) -> Trajectory:
    """Ground-truth trajectory of a dataset (biases zero, calibration from meta)."""
    gt = ds.groundtruth
    if gt is None or len(gt) < 2:
        raise InputError("the dataset has no ground truth; pass an estimator trajectory")
    if not all(c in gt.columns for c in ("qw", "qx", "qy", "qz")):
        raise InputError("the dataset's ground truth has no attitude (qw, qx, qy, qz); pass an estimator "
                         "trajectory (--trajectory states.csv) to linearise about")
    t = gt["t"].to_numpy(float)
    p = gt[["px", "py", "pz"]].to_numpy(float)
    q = quat_normalize(gt[["qw", "qx", "qy", "qz"]].to_numpy(float))
    if all(c in gt.columns for c in ("vx", "vy", "vz")) and not gt[["vx", "vy", "vz"]].isna().any().any():
        v = gt[["vx", "vy", "vz"]].to_numpy(float)
    else:
        v = np.gradient(p, t, axis=0)
    meta = ds.meta
    if lever_arm is None:
        truth = meta.truth.lever_arm if meta.truth is not None else None
        tag = meta.tags[0].lever_arm if meta.tags else None
        lever_arm = truth if truth is not None else (tag if tag is not None else [0.0, 0.0, 0.0])
    if t_d is None:
        t_d = meta.truth.time_offset if meta.truth is not None and meta.truth.time_offset is not None else 0.0
    z = np.zeros(3)
    return Trajectory(t, p, v, q, z, z, np.asarray(lever_arm, float), float(t_d))


def trajectory_from_result(result) -> Trajectory:
    """Trajectory of an :class:`uwbimu.estimation.result.EstimationResult`."""
    X = np.asarray(result.states, float)
    return Trajectory(
        np.asarray(result.t, float), X[:, NP_], X[:, NV_], quat_normalize(X[:, Q]),
        X[:, BA], X[:, BG], np.nanmedian(X[:, PIU], axis=0), float(np.nanmedian(X[:, TD])),
    )  # fmt: skip


def trajectory_from_states_csv(path) -> Trajectory:
    """Trajectory from an estimator's ``states.csv`` (or the output folder holding it).

    Needs the columns ``t`` (UWB clock) and the 20 nominal-state names of
    :mod:`uwbimu.models.state` (``px .. qz, bax .. bgz, lx, ly, lz, time_offset``; ``td`` in older
    files); the lever arm and time offset are taken as their medians over the run.
    """
    from pathlib import Path

    from uwbimu.models.state import NOMINAL_STATE_NAMES

    path = Path(path)
    if path.is_dir():
        path = path / "states.csv"
    if not path.is_file():
        raise InputError(f"{path}: no such estimator states file")
    df = pd.read_csv(path)
    # an older file's columns under their current names (td -> time_offset)
    df = df.rename(columns={o: n for o, n in legacy_name_map().items() if o in df.columns and n not in df.columns})
    missing = [c for c in ("t", *NOMINAL_STATE_NAMES) if c not in df.columns]
    if missing:
        raise InputError(f"{path}: missing column(s) {', '.join(missing)}")
    X = df[list(NOMINAL_STATE_NAMES)].apply(pd.to_numeric, errors="coerce").to_numpy(float)
    t = pd.to_numeric(df["t"], errors="coerce").to_numpy(float)
    bad = ~np.isfinite(t) | ~np.isfinite(X[:, :16]).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise InputError(f"{path}: row {row + 2} (line in file): non-numeric or missing state value")
    if np.any(np.diff(t) <= 0):
        row = int(np.flatnonzero(np.diff(t) <= 0)[0]) + 1
        raise InputError(f"{path}: row {row + 2} (line in file), column 't': time not increasing")
    return Trajectory(
        t, X[:, NP_], X[:, NV_], quat_normalize(X[:, Q]), X[:, BA], X[:, BG],
        np.nanmedian(X[:, PIU], axis=0), float(np.nanmedian(X[:, TD])),
    )  # fmt: skip


def _interp_traj(tr: Trajectory, t: np.ndarray):
    """Interpolate p, v, q, biases at UWB-clock times ``t`` (clamped to the ends)."""
    tt = np.clip(t, tr.t[0], tr.t[-1])
    idx = np.clip(np.searchsorted(tr.t, tt, side="right") - 1, 0, len(tr.t) - 2)
    a = (tt - tr.t[idx]) / np.maximum(tr.t[idx + 1] - tr.t[idx], 1e-12)
    lin = lambda X: X[idx] + a[:, None] * (X[idx + 1] - X[idx])  # noqa: E731
    q = quat_slerp(tr.q[idx], tr.q[idx + 1], a)
    ba = lin(tr.b_a) if np.ndim(tr.b_a) == 2 else np.broadcast_to(tr.b_a, (len(t), 3))
    bg = lin(tr.b_g) if np.ndim(tr.b_g) == 2 else np.broadcast_to(tr.b_g, (len(t), 3))
    return lin(tr.p), lin(tr.v), quat_normalize(q), ba, bg


# --------------------------------------------------------------------------
# Jacobians (re-expressed physics, pinned to the reference by tests)
# --------------------------------------------------------------------------
def range_jacobians(p, v, R, omega, lever, anchors) -> tuple[np.ndarray, np.ndarray]:
    """Range predictions and Jacobians w.r.t. the 19-dim error state (batched).

    Parameters
    ----------
    p, v : (M, 3) IMU position / velocity at the ranges' instants (world).
    R : (M, 3, 3) attitude; omega : (M, 3) body rate ``w_m - b_g`` [rad/s].
    lever : (3,) ``p_IU`` [m]; anchors : (M, 3) anchor of each range [m].

    Returns
    -------
    h : (M,) ranges [m]; H : (M, 19) ``d h / d dx`` with ``dx`` as in
    :mod:`uwbimu.models.state`.  The estimator's Jacobian
    (:func:`uwbimu.models.kernels.range_jacobians`), written once.
    """
    q = np.array([rotmat_to_quat(Ri) for Ri in np.asarray(R, float).reshape(-1, 3, 3)]).reshape(-1, 4)
    return _physics.range_jacobians(p, v, q, omega, lever, anchors)


#: ``M <- Phi M`` on rows 0:15 with the estimator's transition (written once, in models.kernels)
_step_rows = phi_left_R


@njit(cache=True)
def _window_information(R, f, w, dt, rng_idx, Hr, sig2, qdiag, use_noise):
    """Information matrix (19x19) of one window.

    R (K,3,3), f (K,3), w (K,3), dt (K,) per IMU step; ranges sorted by
    ``rng_idx`` (IMU step index at which they observe the state), with
    Jacobians ``Hr`` (M,19) and variances ``sig2`` (M,).  ``qdiag`` (15,)
    continuous noise densities squared for (p, v, th, ba, bg).
    """
    K = R.shape[0]
    M = Hr.shape[0]
    # E_L: size of the IMU-driven core (p, v, theta, b_a, b_g); E_TD: of the core with the lever arm
    Phi = np.eye(ERROR_DIM)
    P = np.zeros((E_L, E_L))
    PT = np.zeros((E_L, E_L))
    B = np.zeros((7, 3, 3))
    W = np.zeros((6, 3, 3))
    col = np.zeros(E_L)
    info = np.zeros((ERROR_DIM, ERROR_DIM))
    j = 0
    row = np.empty(ERROR_DIM)
    for k in range(K):
        while j < M and rng_idx[j] == k:
            s2 = sig2[j]
            if use_noise:
                for a in range(E_L):
                    ha = Hr[j, a]
                    if ha != 0.0:
                        for b in range(E_L):
                            s2 += ha * P[a, b] * Hr[j, b]
            for c in range(ERROR_DIM):
                s = 0.0
                for a in range(E_TD):
                    s += Hr[j, a] * Phi[a, c]
                row[c] = s
            row[E_TD] += Hr[j, E_TD]  # t_d is a constant: its column of Phi is e_td
            for a in range(ERROR_DIM):
                ra = row[a] / s2
                for b in range(a, ERROR_DIM):
                    info[a, b] += ra * row[b]
            j += 1
        if k == K - 1:
            break
        _step_rows(Phi, R[k], f[k], w[k], dt[k], B, W, col)
        if use_noise:
            _step_rows(P, R[k], f[k], w[k], dt[k], B, W, col)  # F P
            for a in range(E_L):
                for b in range(E_L):
                    PT[a, b] = P[b, a]
            _step_rows(PT, R[k], f[k], w[k], dt[k], B, W, col)  # F (F P)^T = F P F^T
            for a in range(E_L):
                for b in range(E_L):
                    P[a, b] = PT[a, b]
                P[a, a] += qdiag[a] * dt[k]
    for a in range(ERROR_DIM):
        for b in range(a):
            info[a, b] = info[b, a]
    return info


@njit(cache=True)
def _propagate_cov(P, PT, R, f, w, dt, qdiag, B, W, col):
    """In place ``P <- F P F^T + Q dt`` (19x19; the lever arm and t_d are constants)."""
    _step_rows(P, R, f, w, dt, B, W, col)  # F P
    n = P.shape[0]
    for a in range(n):
        for b in range(n):
            PT[a, b] = P[b, a]
    _step_rows(PT, R, f, w, dt, B, W, col)  # F (F P)^T = F P F^T
    for a in range(n):
        for b in range(n):
            P[a, b] = 0.5 * (PT[a, b] + PT[b, a])
    for a in range(E_L):
        P[a, a] += qdiag[a] * dt


@njit(cache=True)
def _window_pcrb(R, f, w, dt, rng_idx, Hr, sig2, qdiag, P0):
    """Posterior Cramer-Rao bound of the 19-dim error state at the window end.

    The covariance form of the information recursion of the linear-Gaussian
    error-state model along the trajectory (Tichavsky et al. 1998): between
    ranges ``P <- F P F^T + Q dt`` (IMU white noise and bias random walks as
    process noise, ``qdiag`` (15,) densities squared of p, v, th, b_a, b_g), at
    a range ``P <- P - P h^T h P / (h P h^T + sigma^2)``.  ``P0`` (19x19) is the
    prior at the window start.  Same inputs as :func:`_window_information`.
    Returns ``(P_end, P_prior_end)``: the bound with the window's ranges and
    the prior propagated without them.
    """
    K = R.shape[0]
    M = Hr.shape[0]
    P = P0.copy()
    Pn = P0.copy()
    PT = np.zeros((ERROR_DIM, ERROR_DIM))
    B = np.zeros((7, 3, 3))
    W = np.zeros((6, 3, 3))
    col = np.zeros(E_L)
    Ph = np.empty(ERROR_DIM)
    j = 0
    for k in range(K):
        while j < M and rng_idx[j] == k:
            s2 = sig2[j]
            for a in range(ERROR_DIM):
                acc = 0.0
                for b in range(ERROR_DIM):
                    acc += P[a, b] * Hr[j, b]
                Ph[a] = acc
            for a in range(ERROR_DIM):
                s2 += Hr[j, a] * Ph[a]
            for a in range(ERROR_DIM):
                for b in range(ERROR_DIM):
                    P[a, b] -= Ph[a] * Ph[b] / s2
            j += 1
        if k == K - 1:
            break
        _propagate_cov(P, PT, R[k], f[k], w[k], dt[k], qdiag, B, W, col)
        _propagate_cov(Pn, PT, R[k], f[k], w[k], dt[k], qdiag, B, W, col)
    return P, Pn


@njit(cache=True)
def _transition(R, f, w, dt):
    Phi = np.eye(ERROR_DIM)
    B = np.zeros((7, 3, 3))
    W = np.zeros((6, 3, 3))
    col = np.zeros(E_L)
    for k in range(R.shape[0] - 1):
        _step_rows(Phi, R[k], f[k], w[k], dt[k], B, W, col)
    return Phi


def transition_matrix(R, f, w, dt) -> np.ndarray:
    """Error-state transition ``Phi(t_{K-1}, t_0)`` along K IMU samples (the kernel's).

    Parameters
    ----------
    R : (K, 3, 3) attitude; f : (K, 3) specific force ``a_m - b_a`` (body);
    w : (K, 3) rate ``w_m - b_g`` (body); dt : (K,) step to the next sample [s].
    """
    return _transition(
        np.ascontiguousarray(R, dtype=float), np.ascontiguousarray(f, dtype=float),
        np.ascontiguousarray(w, dtype=float), np.ascontiguousarray(dt, dtype=float),
    )  # fmt: skip


# --------------------------------------------------------------------------
# analysis of one information matrix
# --------------------------------------------------------------------------
def _inv_psd(P: np.ndarray) -> np.ndarray:
    """Inverse of a symmetric positive (semi)definite matrix via its eigenvalues."""
    lam, V = np.linalg.eigh(0.5 * (P + P.T))
    lam = np.maximum(lam, 1e-300)
    return (V / lam) @ V.T


def _scale_vector(scales: dict) -> np.ndarray:
    """Per-component vector (error-state order) of a per-block-symbol dict (``DEFAULT_SCALES`` keys; a dict
    keyed by a block's former name, ``td``, is read too)."""
    def of(b):
        old = [n for n in b.legacy_names if n in scales and b.symbol not in scales]
        return scales[old[0] if old else b.symbol]

    return np.array([of(b) for b in _BASE_BLOCKS for _ in range(b.size)], float)


def analyse_information(info: np.ndarray, scales: dict, x_ref=None, anchors=None) -> dict:
    """Smallest eigenvalue, condition number, weakest direction and CRLB sd."""
    D = _scale_vector(scales)
    Is = D[:, None] * info * D[None, :]
    lam, V = np.linalg.eigh(0.5 * (Is + Is.T))
    lmax = max(lam[-1], 1e-300)
    lmin = lam[0]
    cond = float(lmax / lmin) if lmin > 1e-14 * lmax else float("inf")
    good = lam > 1e-14 * lmax
    # CRLB in SI: (D Is^-1 D) with Is^-1 = V diag(1/lam) V^T over the good eigenvalues;
    # components touching a (numerically) singular direction are unbounded.
    inv_diag = (V[:, good] ** 2) @ (1.0 / lam[good])
    sd = D * np.sqrt(inv_diag)
    bad = (V[:, ~good] ** 2).sum(axis=1) > 1e-6
    sd[bad] = np.inf
    weakest = V[:, 0] / np.linalg.norm(V[:, 0])
    names = list(ERROR_STATE_NAMES)
    label = None
    if x_ref is not None and anchors is not None:
        # name in scaled coordinates: map the generator candidates through D^-1
        cands = candidates_for("uwb_imu", names[:ETD], x_ref, anchors)
        for c in cands:
            c.basis = c.basis / D[:ETD, None]
        named = name_directions(weakest[:ETD, None] if abs(weakest[ETD]) < 0.5 else np.zeros((ETD, 0)), cands,
                                names[:ETD])
        if named and not named[0]["name"].startswith("unnamed"):
            label = named[0]["name"]
    if label is None:
        order = np.argsort(-np.abs(weakest))[:3]
        label = " ".join(f"{weakest[i]:+.2f} {names[i]}" for i in order if abs(weakest[i]) > 0.15)
    return {"min_eigenvalue": float(lmin), "condition_number": cond, "weakest_direction": label, "sd": sd}


# --------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------
def _prepare(ds, tr: Trajectory, opts: WindowOptions):
    imu_t = ds.imu_t
    u = ds.imu_u
    order = np.argsort(imu_t, kind="stable")
    imu_t, u = imu_t[order], u[order]
    # motion at IMU stamp s is at UWB time s - t_d
    p, v, q, ba, bg = _interp_traj(tr, imu_t - tr.t_d)
    R = quat_to_rotmat(q)
    f = u[:, 0:3] - ba
    w = u[:, 3:6] - bg
    dt = np.r_[np.diff(imu_t), 0.0]

    uwb = ds.uwb.sort_values("t", kind="stable")
    n_other_tag = 0
    if "tag" in uwb.columns and uwb["tag"].nunique() > 1:
        # one lever arm per analysis: keep the first tag's ranges (counted)
        tag = str(ds.meta.tags[0].name) if ds.meta.tags else str(uwb["tag"].iloc[0])
        keep = uwb["tag"].astype(str) == tag
        if not keep.any():
            tag = str(uwb["tag"].iloc[0])
            keep = uwb["tag"].astype(str) == tag
        n_other_tag = int((~keep).sum())
        uwb = uwb[keep]
    anchors_pos = ds.anchor_positions()
    ids = uwb["anchor"].astype(str).to_numpy()
    known = np.array([i in anchors_pos for i in ids], bool)
    uwb_t = uwb["t"].to_numpy(float)[known]
    ids = ids[known]
    A = np.array([anchors_pos[i] for i in ids]).reshape(-1, 3)
    pr, vr, qr, _, bgr = _interp_traj(tr, uwb_t)
    # body rate at the IMU time that the range observes
    t_imu = uwb_t + tr.t_d
    wr = np.column_stack([np.interp(t_imu, imu_t, u[:, 3 + i]) for i in range(3)]) - bgr
    hpred, H = _physics.range_jacobians(pr, vr, qr, wr, tr.lever_arm, A)
    # consistency of trajectory and ranges (a ground truth in another frame
    # would make every Jacobian meaningless): median |measured - predicted|
    meas = uwb["range"].to_numpy(float)[known]
    # nearest IMU step at or before the observed IMU time
    ridx = np.clip(np.searchsorted(imu_t, t_imu, side="right") - 1, 0, len(imu_t) - 1)
    inside = (t_imu >= imu_t[0]) & (t_imu <= imu_t[-1])
    return {
        "imu_t": imu_t, "R": R, "f": f, "w": w, "dt": dt,
        "uwb_t": uwb_t[inside], "H": H[inside], "ridx": ridx[inside], "anchors": A[inside],
        "n_unknown_anchor": int((~known).sum()), "n_outside": int((~inside).sum()), "n_other_tag": n_other_tag,
        "residual_median": float(np.median(np.abs(meas - hpred))) if len(meas) else float("nan"),
        "traj_at_imu": (p, v, q, ba, bg),
    }  # fmt: skip


def _noise_model(ds, opts: "WindowOptions"):
    sigma = opts.range_sigma or (ds.meta.range_sigma if ds.meta.range_sigma else 0.1)
    noise = opts.imu_noise or (ds.meta.imu_noise if ds.meta.imu_noise is not None else BMI088)
    qd = np.zeros(E_L)  # white-noise densities of the IMU-driven core (p, v, theta, b_a, b_g)
    qd[EV] = noise.accel_noise_density**2
    qd[ETH] = noise.gyro_noise_density**2
    qd[EBA] = noise.accel_bias_rw**2
    qd[EBG] = noise.gyro_bias_rw**2
    return sigma, noise, (qd if opts.include_imu_noise else np.zeros(E_L))


def posterior_crb(ds, trajectory: Optional[Trajectory] = None, t_start: Optional[float] = None,
                  t_end: Optional[float] = None, prior_cov: Optional[np.ndarray] = None,
                  options: Optional[WindowOptions] = None) -> tuple[np.ndarray, np.ndarray]:
    """Posterior Cramer-Rao bound of the 19-dim error state over ``[t_start, t_end]``.

    Parameters
    ----------
    ds : dataset (IMU, UWB, anchors); trajectory : linearisation trajectory
        (default: the ground truth).
    t_start, t_end : IMU-clock interval [s] (default: the whole IMU span).
    prior_cov : (19, 19) error-state covariance at ``t_start`` (default:
        ``diag(options.prior_sd)^2``), e.g. an estimator's covariance at that
        instant for a matched comparison.
    options : :class:`WindowOptions` (noise model).

    Returns
    -------
    ``(P_end, P_prior_end)``: the bound at ``t_end`` and the prior propagated
    without ranges (both (19, 19), error-state order of :mod:`uwbimu.models.state`).
    """
    opts = options or WindowOptions()
    tr = trajectory if trajectory is not None else trajectory_from_groundtruth(ds)
    sigma, _, qd = _noise_model(ds, opts)
    pre = _prepare(ds, tr, opts)
    imu_t = pre["imu_t"]
    k0 = int(np.searchsorted(imu_t, imu_t[0] if t_start is None else t_start, side="left"))
    k1 = int(np.searchsorted(imu_t, imu_t[-1] if t_end is None else t_end, side="right"))
    sel = (pre["ridx"] >= k0) & (pre["ridx"] < k1)
    P0 = np.diag(_scale_vector(opts.prior_sd) ** 2) if prior_cov is None else np.asarray(prior_cov, float)
    return _window_pcrb(
        np.ascontiguousarray(pre["R"][k0:k1]), np.ascontiguousarray(pre["f"][k0:k1]),
        np.ascontiguousarray(pre["w"][k0:k1]), np.ascontiguousarray(pre["dt"][k0:k1]),
        pre["ridx"][sel] - k0, np.ascontiguousarray(pre["H"][sel]), np.full(int(sel.sum()), sigma**2),
        qd, np.ascontiguousarray(P0),
    )  # fmt: skip


def window_observability(ds, trajectory: Optional[Trajectory] = None, options: Optional[WindowOptions] = None) -> tuple[pd.DataFrame, dict]:
    """Per-window information analysis of a dataset along a trajectory.

    Parameters
    ----------
    ds : :class:`uwbimu.io.dataset.Dataset` (IMU, UWB, anchors).
    trajectory : linearisation trajectory; default the dataset's ground truth.
    options : :class:`WindowOptions`.

    Returns
    -------
    table : one row per window: ``t_start, t_end`` (IMU clock, s),
        ``min_eigenvalue, condition_number`` (of the scaled information),
        ``weakest_direction``, ``sd_<state>`` (CRLB, SI units) for the 19
        error states, ``n_ranges``, ``gyro_rms`` (rad/s), ``lever_arm_excited``,
        ``time_offset_excited``.
    info : counts of ranges not used (unknown anchor, outside the IMU span,
        other tags than the first: one lever arm per analysis),
        the noise values used and ``range_residual_median`` (median |measured -
        predicted| range along the trajectory [m]; large values mean the
        trajectory is not in the anchors' frame or the calibration is off).
    """
    opts = options or WindowOptions()
    if opts.window <= 0:
        raise UsageError(f"window must be positive, got {opts.window}")
    tr = trajectory if trajectory is not None else trajectory_from_groundtruth(ds)
    sigma, noise, qd_used = _noise_model(ds, opts)
    qd = _noise_model(ds, WindowOptions(range_sigma=sigma, imu_noise=noise))[2]
    pre = _prepare(ds, tr, opts)
    imu_t = pre["imu_t"]
    edges = np.arange(imu_t[0], imu_t[-1] + 1e-9, opts.window)
    if len(edges) < 2 or edges[-1] < imu_t[-1] - 1e-9:
        edges = np.r_[edges, imu_t[-1]]
    rows = []
    p, v, q, _, _ = pre["traj_at_imu"]
    prior_sd = _scale_vector(opts.prior_sd)
    P_chain = None
    for t0, t1 in zip(edges[:-1], edges[1:]):
        k0 = int(np.searchsorted(imu_t, t0, side="left"))
        k1 = int(np.searchsorted(imu_t, t1, side="right"))
        sel = (pre["ridx"] >= k0) & (pre["ridx"] < k1)
        nr = int(sel.sum())
        row = {"t_start": float(t0), "t_end": float(t1), "n_ranges": nr}
        gyro = pre["w"][k0:k1]
        row["gyro_rms"] = float(np.sqrt(np.mean(np.sum(gyro**2, axis=1)))) if len(gyro) else 0.0
        if opts.bound == "pcrb" and k1 - k0 >= 2:
            start = np.diag(prior_sd**2) if (P_chain is None or not opts.chain) else P_chain
            args = (
                np.ascontiguousarray(pre["R"][k0:k1]), np.ascontiguousarray(pre["f"][k0:k1]),
                np.ascontiguousarray(pre["w"][k0:k1]), np.ascontiguousarray(pre["dt"][k0:k1]),
                pre["ridx"][sel] - k0, np.ascontiguousarray(pre["H"][sel]), np.full(nr, sigma**2),
                qd_used, np.ascontiguousarray(start),
            )  # fmt: skip
            P_end, P_prior = _window_pcrb(*args)
            P_chain = P_end
            # marginal precision the window's ranges add, in units of the prior precision
            prec = lambda P, i: 1.0 / max(P[i, i], 1e-300)  # noqa: E731
            for b, sl in _CAL:  # the weakest component's gain
                row[f"{b.output_key}_info_gain"] = float(min((prec(P_end, i) - prec(P_prior, i)) * prior_sd[i] ** 2
                                                             for i in range(sl.start, sl.stop)))
        if nr < opts.min_ranges or k1 - k0 < 2:
            row.update({"min_eigenvalue": 0.0, "condition_number": float("inf"), "weakest_direction": "no data"})
            if opts.bound == "pcrb":
                Pc = P_chain if (P_chain is not None and opts.chain) else np.diag(prior_sd**2)
                row.update({f"sd_{n}": float(np.sqrt(Pc[i, i])) for i, n in enumerate(ERROR_STATE_NAMES)})
            else:
                row.update({f"sd_{n}": float("inf") for n in ERROR_STATE_NAMES})
        elif opts.bound == "pcrb":
            # information the window's ranges add to the state at its end (prior removed)
            gained = _inv_psd(P_end) - _inv_psd(P_prior)
            x_ref = np.r_[p[k1 - 1], v[k1 - 1], q[k1 - 1], np.zeros(6), tr.lever_arm]
            res = analyse_information(gained, opts.scales, x_ref, np.unique(pre["anchors"][sel], axis=0))
            row.update({k: res[k] for k in ("min_eigenvalue", "condition_number", "weakest_direction")})
            row.update({f"sd_{n}": float(np.sqrt(max(P_end[i, i], 0.0))) for i, n in enumerate(ERROR_STATE_NAMES)})
        else:
            info = _window_information(
                np.ascontiguousarray(pre["R"][k0:k1]), np.ascontiguousarray(pre["f"][k0:k1]),
                np.ascontiguousarray(pre["w"][k0:k1]), np.ascontiguousarray(pre["dt"][k0:k1]),
                pre["ridx"][sel] - k0, np.ascontiguousarray(pre["H"][sel]),
                np.full(nr, sigma**2), qd, bool(opts.include_imu_noise),
            )  # fmt: skip
            x_ref = np.r_[p[k0], v[k0], q[k0], np.zeros(6), tr.lever_arm]
            res = analyse_information(info, opts.scales, x_ref, np.unique(pre["anchors"][sel], axis=0))
            row.update({k: res[k] for k in ("min_eigenvalue", "condition_number", "weakest_direction")})
            row.update({f"sd_{n}": float(s) for n, s in zip(ERROR_STATE_NAMES, res["sd"])})
        for b, _ in _CAL:
            key = f"{b.output_key}_excited"
            sd_b = max(row[f"sd_{n}"] for n in b.output_names)  # the weakest component's bound
            if opts.bound == "pcrb":
                need = 1.0 / opts.excited_sd_ratio**2 - 1.0  # gain that takes the prior sd to ratio x prior
                row[key] = bool(row.get(f"{b.output_key}_info_gain", 0.0) >= need)
            else:
                row[key] = bool(np.isfinite(sd_b))
            threshold = getattr(opts, _SD_THRESHOLD_OPTION[b.output_key])
            if threshold is not None:
                row[key] &= bool(sd_b < threshold)
        rows.append(row)
    cols = ["t_start", "t_end", "min_eigenvalue", "condition_number", "weakest_direction"]
    cols += [f"sd_{n}" for n in ERROR_STATE_NAMES] + ["n_ranges", "gyro_rms"]
    cols += [f"{b.output_key}_excited" for b, _ in _CAL]
    gains = [f"{b.output_key}_info_gain" for b, _ in _CAL] if opts.bound == "pcrb" else []
    cols += gains
    table = pd.DataFrame(rows)
    for c in gains:
        if c not in table.columns:
            table[c] = 0.0
    table = table[cols]
    meta = {
        "range_sigma": sigma,
        "imu_noise": noise.model_dump(),
        "include_imu_noise": opts.include_imu_noise,
        "bound": opts.bound,
        "prior_sd": dict(opts.prior_sd) if opts.bound == "pcrb" else None,
        "excited_sd_ratio": opts.excited_sd_ratio if opts.bound == "pcrb" else None,
        "chain": opts.chain if opts.bound == "pcrb" else None,
        "ranges_unknown_anchor": pre["n_unknown_anchor"],
        "ranges_outside_imu_span": pre["n_outside"],
        "ranges_other_tags": pre["n_other_tag"],
        "windows": len(rows),
        "range_residual_median": pre["residual_median"] if np.isfinite(pre["residual_median"]) else None,
        "lever_arm": tr.lever_arm.tolist(),
        "time_offset": tr.t_d,
    }
    return table, meta


def plot_timeline(table: pd.DataFrame, path, lever_sd_threshold: Optional[float] = None, td_sd_threshold: Optional[float] = None) -> None:
    """Timeline PNG: min eigenvalue, CRLB of lever arm and time offset, flags (thresholds dashed)."""
    from matplotlib.figure import Figure

    from uwbimu.io.atomic import save_figure

    tc = 0.5 * (table["t_start"] + table["t_end"])
    fig = Figure(figsize=(9, 7))
    ax = fig.subplots(1 + len(_CAL), 1, sharex=True)
    ax[0].semilogy(tc, np.maximum(table["min_eigenvalue"], 1e-20), "o-")
    ax[0].set_ylabel("min eigenvalue\n(scaled information)")
    thresholds = {"lever_arm": lever_sd_threshold, "time_offset": td_sd_threshold}
    for a, (b, _) in zip(ax[1:], _CAL):  # one panel per calibration block
        for n in b.output_names:
            a.semilogy(tc, table[f"sd_{n}"].replace(np.inf, np.nan), "o-", label=f"sd {n}",
                       **({} if b.size > 1 else {"color": "C3"}))
        if thresholds.get(b.output_key):
            a.axhline(thresholds[b.output_key], ls="--", color="k", lw=0.8)
        a.set_ylabel(f"CRLB {b.label} [{b.unit}]")
        if b.size > 1:
            a.legend(fontsize=8)
        for i, r in table.iterrows():
            if not r[f"{b.output_key}_excited"]:
                a.axvspan(r["t_start"], r["t_end"], color="orange", alpha=0.15)
    ax[-1].set_xlabel("window centre, IMU clock [s]")
    fig.suptitle("Per-window observability (shaded: not excited)")
    save_figure(path, fig)


refresh_stale_cache(globals(), [_physics])
