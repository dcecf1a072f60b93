"""The seed's 6-state point-mass EKF (seed 002, sections IV and IX).

State ``X = [p, v]`` (world frame, m and m/s), input the world-frame
acceleration ``U = a_w`` (m/s^2), dynamics ``X' = A X + B U`` (seed eq. 1) and
range updates ``h = || p_anchor - (p + R p_IU) ||`` (the reference range model
of :func:`uwbimu.models.reference.range_measurement` with the lever arm and
time offset *fixed*, not estimated).

Where the world-frame acceleration comes from
---------------------------------------------
The seed assumes the inertial-frame acceleration is available from a separate
attitude system.  Our datasets only hold body-frame IMU readings, so this
estimator builds its own attitude (ground truth is never used):

* ``attitude="gyro"`` (default): roll and pitch from the mean accelerometer
  reading over the first ``init_window`` seconds (the vehicle is assumed
  still, or at least unaccelerated, then), the gyro bias as the mean gyro
  reading over the same window (only if that window looks static), then pure
  gyro integration.  Yaw cannot be observed from ranges by a point-mass model,
  so it comes from outside: ``initial_yaw`` when given, otherwise a bank of
  ``yaw_hypotheses`` initial yaws (then 5 finer ones around the best) is run
  over the first ``yaw_window`` seconds and the yaw with the smallest sum of
  range NIS is kept (needs horizontal acceleration in that window).  The world
  acceleration is ``R(q) a_m - g``; the accelerometer bias is not estimated.

Honest covariance (docs/montecarlo.md, "Noise model"): the acceleration error
caused by the growing attitude error (levelling, yaw, gyro-bias residual, angle
and bias random walk, from the dataset's IMU noise model) and by the
unestimated accelerometer bias enters the process noise per world axis
(:func:`acceleration_error_psd`, a slowly varying error of sd sigma as white
noise of PSD ``2 tau sigma^2``); the fixed lever arm and time offset are
*consider* parameters whose uncertainty (``lever_arm_sd``, ``time_offset_sd``)
is added to the output covariance to first order.
* ``attitude="identity"``: the IMU axes are taken to be world-aligned, i.e. the
  IMU columns already hold world-frame specific force — the seed's own
  simulation assumption; only valid for datasets whose IMU frame does not
  rotate.

Kernels are numba-compiled; tests pin them to the reference model
(:mod:`uwbimu.models.reference`) and to finite differences.
"""

from __future__ import annotations

import math
import time
from typing import Any, Callable, Literal, Optional

import numpy as np
import pandas as pd
from numba import njit
from pydantic import BaseModel, ConfigDict, Field

from uwbimu.errors import InputError
from uwbimu.estimation.result import EstimationResult
from uwbimu.models import state as S
from uwbimu.models.imu import ICM20948
from uwbimu.models import kernels as _physics
from uwbimu.models.kernels import quat_exp as quat_exp_nb, quat_mul as quat_mul_nb, refresh_stale_cache
from uwbimu.models.quaternion import quat_exp, quat_from_euler, quat_multiply, quat_normalize, quat_to_rotmat, skew
from uwbimu.models.reference import G_WORLD, GRAVITY

__all__ = [
    "PointMassOptions",
    "run_pointmass",
    "range_and_jacobian",
    "predict_step",
    "integrate_attitude",
    "multilaterate",
    "acceleration_error_psd",
]


class PointMassOptions(BaseModel):
    """Options of the 6-state point-mass EKF (all SI units)."""

    model_config = ConfigDict(extra="forbid")

    attitude: Literal["gyro", "identity"] = Field(
        "gyro", description="source of the body->world rotation used to build world accelerations"
    )
    init_window: float = Field(0.25, gt=0, description="s; levelling / gyro-bias / multilateration window")
    initial_yaw: Optional[float] = Field(
        None, description="rad; yaw of the IMU at start; None: best of a bank of hypotheses scored on the ranges"
    )
    yaw_hypotheses: int = Field(12, ge=1, description="initial-yaw hypotheses of the bank (then 5 finer ones)")
    yaw_window: float = Field(8.0, gt=0, description="s of data each yaw hypothesis is scored on (sum of NIS)")
    estimate_gyro_bias: bool = Field(True, description="gyro bias = mean gyro over a static init window")
    static_gyro_max: float = Field(0.05, gt=0, description="rad/s; max gyro sd for the window to count as static")
    accel_noise_density: Optional[float] = Field(
        None, ge=0, description="m/s^2/sqrt(Hz); default: dataset imu_noise, else 0.01"
    )
    accel_error_sd: float = Field(
        0.05, ge=0, description="m/s^2; extra unmodelled acceleration error (vibration, model error), correlated over "
        "accel_error_time"
    )
    accel_error_time: float = Field(
        0.25, gt=0, description="s; correlation time tau of the slowly varying acceleration errors: an error of sd "
        "sigma enters as white noise of PSD 2 tau sigma^2"
    )
    attitude_error_model: bool = Field(
        True, description="add the acceleration error caused by the growing attitude error (levelling, yaw, gyro "
        "bias and noise: from the IMU noise model) and by the unestimated accelerometer bias to the process noise"
    )
    initial_yaw_sd: Optional[float] = Field(
        None, ge=0, description="rad; sd of the initial yaw; None: 2 deg when initial_yaw is given, else the bank "
        "resolution"
    )
    lever_arm_sd: Optional[float] = Field(
        None, ge=0, description="m per axis; uncertainty of the fixed lever arm, added to the output covariance; "
        "None: 0 when the lever arm is known (dataset tag or lever_arm option), else 0.1"
    )
    time_offset_sd: float = Field(
        0.03, ge=0, description="s; uncertainty of the fixed time offset, added to the output covariance (0 when "
        "t_d is known)"
    )
    range_sigma: Optional[float] = Field(None, gt=0, description="m; default: dataset range_sigma, else 0.1")
    gate_sigma: float = Field(5.0, gt=0, description="reject ranges with |innovation| > gate_sigma * sqrt(S)")
    initial_position: Optional[list[float]] = Field(None, min_length=3, max_length=3)
    initial_position_sd: float = Field(1.0, gt=0, description="m; sd when initial_position is given")
    initial_velocity_sd: float = Field(1.0, gt=0, description="m/s; initial velocity is zero")
    mirror: Literal["upper", "lower"] = Field(
        "upper", description="with 3 (or coplanar) anchors: which mirror solution of the multilateration to take"
    )
    lever_arm: Optional[list[float]] = Field(
        None, min_length=3, max_length=3, description="m, IMU frame; default: dataset tag lever arm, else 0"
    )
    time_offset: float = Field(0.0, description="s; fixed (not estimated) t_d")
    full_covariance: bool = Field(
        False, description="also return (K, 19, 19) covariances (p, v block filled, NaN elsewhere)"
    )


# --------------------------------------------------------------------------
# Kernels (numba).  Same relations as models.reference; pinned by tests.
# --------------------------------------------------------------------------
@njit(cache=True)
def _integrate_attitude(q0, t, w, b_g):
    """Gyro integration ``q_{k+1} = q_k ⊗ Exp(dt (w_k + w_{k+1})/2 - dt b_g)``."""
    n = t.shape[0]
    out = np.empty((n, 4))
    q = q0.copy()
    dq = np.empty(4)
    out[0] = q
    for k in range(n - 1):
        dt = t[k + 1] - t[k]
        phi = dt * (0.5 * (w[k] + w[k + 1]) - b_g)
        quat_exp_nb(phi, dq)
        quat_mul_nb(q.copy(), dq, q)
        q = q / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        out[k + 1] = q
    return out


@njit(cache=True)
def _predict(x, P, a0, a1, h, q2):
    """Exact propagation of ``p' = v, v' = a`` over ``h`` with ``a`` linear from a0 to a1.

    Process noise: white acceleration of spectral density ``q2[i]`` [m^2/s^3]
    on world axis ``i``.  Scalar loops (no BLAS) keep the compile time short.
    """
    for i in range(3):
        x[i] += h * x[3 + i] + h * h * (a0[i] / 3.0 + a1[i] / 6.0)
        x[3 + i] += 0.5 * h * (a0[i] + a1[i])
    # P <- F P F^T + Q with F = [[I, hI], [0, I]]: rows then columns.
    for i in range(3):
        for j in range(6):
            P[i, j] += h * P[3 + i, j]
    for j in range(3):
        for i in range(6):
            P[i, j] += h * P[i, 3 + j]
    for i in range(3):
        P[i, i] += q2[i] * h * h * h / 3.0
        P[i, 3 + i] += q2[i] * h * h / 2.0
        P[3 + i, i] += q2[i] * h * h / 2.0
        P[3 + i, 3 + i] += q2[i] * h


@njit(cache=True)
def _range_h(x, anchor, offset):
    """Range from antenna ``p + offset`` to ``anchor`` and its Jacobian w.r.t. ``[p, v]``."""
    d0 = anchor[0] - x[0] - offset[0]
    d1 = anchor[1] - x[1] - offset[1]
    d2 = anchor[2] - x[2] - offset[2]
    r = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    H = np.zeros(6)
    if r > 1e-9:
        H[0] = -d0 / r
        H[1] = -d1 / r
        H[2] = -d2 / r
    return r, H


@njit(cache=True)
def _filter(s, aw, x0, P0, q2, tau, anchors, offsets, ranges, sigma, gate):
    """Run the EKF over IMU stamps ``s`` with ranges at IMU-clock times ``tau`` (sorted).

    ``q2`` (N, 3): process-noise PSD per IMU interval (left sample) and world axis.

    Returns states (N, 6), covariances (N, 6, 6) and, per range, predicted
    range, innovation, NIS and accepted flag.
    """
    n = s.shape[0]
    m = tau.shape[0]
    X = np.empty((n, 6))
    Pd = np.empty((n, 6, 6))
    pred = np.full(m, np.nan)
    innov = np.full(m, np.nan)
    nis = np.full(m, np.nan)
    acc = np.zeros(m, dtype=np.bool_)
    x = x0.copy()
    P = P0.copy()
    X[0] = x
    Pd[0] = P
    j = 0
    while j < m and tau[j] < s[0]:
        j += 1  # before the first IMU sample: not usable (counted by the caller)
    r2 = sigma * sigma
    for k in range(n - 1):
        dt = s[k + 1] - s[k]
        tc = s[k]
        ac = aw[k].copy()
        while j < m and tau[j] < s[k + 1]:
            frac = (tau[j] - s[k]) / dt
            aj = aw[k] + frac * (aw[k + 1] - aw[k])
            _predict(x, P, ac, aj, tau[j] - tc, q2[k])
            tc = tau[j]
            ac = aj
            r, H = _range_h(x, anchors[j], offsets[j])
            # H is non-zero on the position block only.
            PHt = np.zeros(6)
            for i in range(6):
                PHt[i] = P[i, 0] * H[0] + P[i, 1] * H[1] + P[i, 2] * H[2]
            Sv = H[0] * PHt[0] + H[1] * PHt[1] + H[2] * PHt[2] + r2
            y = ranges[j] - r
            pred[j] = r
            innov[j] = y
            nis[j] = y * y / Sv
            if nis[j] <= gate * gate:
                for i in range(6):
                    x[i] += PHt[i] * y / Sv
                # P - K S K^T with K = P H^T / S, written to stay exactly symmetric.
                for i in range(6):
                    for k2 in range(6):
                        P[i, k2] -= PHt[i] * PHt[k2] / Sv
                acc[j] = True
            j += 1
        _predict(x, P, ac, aw[k + 1], s[k + 1] - tc, q2[k])
        X[k + 1] = x
        Pd[k + 1] = P
    return X, Pd, pred, innov, nis, acc


# --------------------------------------------------------------------------
# Python-level helpers (also the functions tests pin to the reference)
# --------------------------------------------------------------------------
def range_and_jacobian(x6: np.ndarray, anchor: np.ndarray, offset=(0.0, 0.0, 0.0)) -> tuple[float, np.ndarray]:
    """Predicted range [m] and its (6,) Jacobian w.r.t. ``[p, v]`` (world frame).

    ``offset`` is the world-frame antenna offset ``R(q) p_IU`` [m].
    """
    r, H = _range_h(np.asarray(x6, float), np.asarray(anchor, float), np.asarray(offset, float))
    return float(r), H


def predict_step(x6, P, a0, a1, h: float, q2) -> tuple[np.ndarray, np.ndarray]:
    """One prediction over ``h`` seconds with world accelerations ``a0 -> a1`` (copies in, out).

    ``q2``: white acceleration PSD [m^2/s^3], a scalar or one per world axis (3,).
    """
    x = np.array(x6, float)
    Pc = np.array(P, float)
    q = np.ascontiguousarray(np.broadcast_to(np.asarray(q2, float), (3,)))
    _predict(x, Pc, np.asarray(a0, float), np.asarray(a1, float), float(h), q)
    return x, Pc


def integrate_attitude(q0, t, w, b_g=(0.0, 0.0, 0.0)) -> np.ndarray:
    """(N, 4) attitudes from gyro readings ``w`` (N, 3) [rad/s] starting at ``q0``."""
    return _integrate_attitude(
        np.asarray(q0, float), np.asarray(t, float), np.ascontiguousarray(w, float), np.asarray(b_g, float)
    )


def multilaterate(
    anchors: np.ndarray, ranges: np.ndarray, mirror: str = "upper", iters: int = 30
) -> tuple[np.ndarray, np.ndarray, bool]:
    """Least-squares position from ranges to anchors (Gauss-Newton).

    Returns ``(p, cov_unit, ambiguous)``: ``cov_unit`` is ``(J^T J)^-1`` (multiply
    by the range variance); ``ambiguous`` is true when the anchors are coplanar
    (always the case for 3), in which case the solution mirrored through the
    anchor plane fits equally well and ``mirror`` picks the one with the larger
    (``"upper"``) or smaller (``"lower"``) height.
    """
    A = np.asarray(anchors, float)
    rr = np.asarray(ranges, float)
    c = A.mean(axis=0)
    _, sv, vt = np.linalg.svd(A - c)
    ambiguous = len(A) < 4 or sv[-1] < 1e-3 * max(sv[0], 1e-9)
    n = vt[-1]
    if n[2] < 0 or (abs(n[2]) < 1e-9 and n[0] < 0):
        n = -n
    p = c + (n if mirror == "upper" else -n) * max(float(np.mean(rr)), 1.0) * 0.5
    if not ambiguous:
        p = c.copy()
    for _ in range(iters):
        d = p - A
        r = np.linalg.norm(d, axis=1)
        J = d / np.maximum(r, 1e-9)[:, None]
        step, *_ = np.linalg.lstsq(J, rr - r, rcond=None)
        p = p + step
        if np.linalg.norm(step) < 1e-9:
            break
    if ambiguous:
        # Gauss-Newton may converge onto the other side; reflect onto the requested one.
        side = float((p - c) @ n)
        if (mirror == "upper" and side < 0) or (mirror == "lower" and side > 0):
            p = p - 2.0 * side * n
    d = p - A
    J = d / np.maximum(np.linalg.norm(d, axis=1), 1e-9)[:, None]
    cov = np.linalg.pinv(J.T @ J)
    return p, cov, bool(ambiguous)


def acceleration_error_psd(
    f_world: np.ndarray,
    t: np.ndarray,
    *,
    accel_noise_density: float,
    accel_bias_sd: float = 0.0,
    extra_sd: float = 0.0,
    tau: float = 0.5,
    tilt0_sd: float = 0.0,
    yaw0_sd: float = 0.0,
    gyro_bias_sd: float = 0.0,
    gyro_noise_density: float = 0.0,
    gyro_bias_rw: float = 0.0,
    lever_accel_sd: Optional[np.ndarray] = None,
) -> np.ndarray:
    """Process-noise PSD (N, 3) [m^2/s^3] of the world acceleration input, per world axis.

    The input ``a = R(q) f - g`` is wrong by (i) the accelerometer's white
    noise (PSD ``accel_noise_density^2``) and (ii) slowly varying errors: the
    unestimated accelerometer bias (sd ``accel_bias_sd``), an extra allowance
    ``extra_sd`` and, to first order, ``dtheta x (R f)`` for a world-frame
    attitude error ``dtheta`` whose variance grows from the initial levelling
    (``tilt0_sd`` about x, y) and yaw (``yaw0_sd`` about z) errors with the gyro
    bias residual, angle random walk and bias random walk:
    ``s(t) = s0^2 + b^2 t^2 + n_g^2 t + rw^2 t^3 / 3``.  A slowly varying error
    of sd ``sigma`` and correlation time ``tau`` has the low-frequency PSD
    ``2 tau sigma^2`` (first-order Gauss-Markov); that is the white-noise
    equivalent used here.  ``lever_accel_sd`` (N,) adds an isotropic term
    (acceleration of an unknown antenna offset).

    Parameters
    ----------
    f_world : (N, 3) specific force in the world frame [m/s^2].
    t : (N,) time since the start [s].
    """
    f = np.asarray(f_world, float)
    t = np.maximum(np.asarray(t, float), 0.0)
    grow = gyro_bias_sd**2 * t**2 + gyro_noise_density**2 * t + gyro_bias_rw**2 * t**3 / 3.0
    s1 = tilt0_sd**2 + grow  # about world x and y
    s3 = yaw0_sd**2 + grow  # about world z
    f1, f2, f3 = f[:, 0] ** 2, f[:, 1] ** 2, f[:, 2] ** 2
    # diag([f]x diag(s1, s1, s3) [f]x^T)
    var = np.column_stack([f3 * s1 + f2 * s3, f3 * s1 + f1 * s3, (f2 + f1) * s1])
    var += accel_bias_sd**2 + extra_sd**2
    if lever_accel_sd is not None:
        var += np.asarray(lever_accel_sd, float)[:, None] ** 2
    return np.ascontiguousarray(accel_noise_density**2 + 2.0 * tau * var)


def _lever_arms(ds, opts: PointMassOptions) -> dict[str, np.ndarray]:
    arms = {}
    for tag in ds.meta.tags:
        arms[tag.name] = np.array(tag.lever_arm if tag.lever_arm is not None else [0.0, 0.0, 0.0], float)
    if opts.lever_arm is not None:
        arms = {k: np.array(opts.lever_arm, float) for k in (arms or {"tag0": None})}
    return arms


# --------------------------------------------------------------------------
# The estimator
# --------------------------------------------------------------------------
def run_pointmass(
    dataset, options: PointMassOptions | dict | None = None, progress: Optional[Callable[[float], Any]] = None
) -> EstimationResult:
    """Run the 6-state point-mass EKF over a dataset.

    Parameters
    ----------
    dataset : :class:`uwbimu.io.dataset.Dataset` (IMU readings in the IMU frame on
        the IMU clock, ranges on the UWB clock).
    options : :class:`PointMassOptions` or a dict of its fields.
    progress : optional callable receiving the fraction done (0 then 1; the
        filter loop itself is compiled and does not report).

    Returns
    -------
    :class:`EstimationResult` with output at every IMU sample (stamps on the
    UWB clock).  Position and velocity carry standard deviations (filter
    covariance plus the lever-arm / time-offset consider terms); attitude is
    the integrated attitude (sd NaN), biases are zero except the gyro bias of
    the static window (sd NaN), lever arm and time offset are the fixed values
    (sd NaN).
    """
    t_start = time.perf_counter()
    if options is None:
        opts = PointMassOptions()
    elif isinstance(options, PointMassOptions):
        opts = options
    else:
        opts = PointMassOptions.model_validate(options)
    if progress is not None:
        progress(0.0)
    warnings: list[str] = []
    events: list[dict[str, Any]] = []

    s = dataset.imu_t
    u = dataset.imu_u
    if len(s) < 2:
        raise InputError("point-mass EKF needs at least two IMU samples")
    if np.any(np.diff(s) <= 0):
        raise InputError("IMU stamps must be strictly increasing")
    t_d = float(opts.time_offset)

    # ---- attitude source (yaw 0 first; a yaw is a left rotation about world z) ----
    win = s <= s[0] + opts.init_window
    if win.sum() < 2:
        win[:2] = True
    b_g = np.zeros(3)
    static = False
    if opts.attitude == "gyro":
        f = u[win, 0:3].mean(axis=0)
        roll = math.atan2(f[1], f[2])
        pitch = math.atan2(-f[0], math.hypot(f[1], f[2]))
        q0 = quat_from_euler(roll, pitch, 0.0)
        static = bool(np.all(u[win, 3:6].std(axis=0) < opts.static_gyro_max)) and abs(np.linalg.norm(f) - GRAVITY) < 0.3
        if opts.estimate_gyro_bias:
            if static:
                b_g = u[win, 3:6].mean(axis=0)
            else:
                warnings.append(
                    f"initial window ({opts.init_window:g} s) is not static: gyro bias not estimated, levelling may be off"
                )
                events.append({"t": float(s[0] - t_d), "kind": "init_not_static"})
        quats0 = integrate_attitude(q0, s, u[:, 3:6], b_g)
        R0 = quat_to_rotmat(quats0)
        f_world0 = np.einsum("nij,nj->ni", R0, u[:, 0:3])
    else:
        quats0 = np.tile(np.array([1.0, 0.0, 0.0, 0.0]), (len(s), 1))
        R0 = np.broadcast_to(np.eye(3), (len(s), 3, 3))
        f_world0 = u[:, 0:3].copy()

    # ---- ranges ----------------------------------------------------------
    uwb = dataset.uwb.sort_values("t", kind="stable")
    anchor_pos = dataset.anchor_positions()
    ids = uwb["anchor"].astype(str).to_numpy()
    unknown = sorted(set(ids) - set(anchor_pos))
    if unknown:
        raise InputError(f"uwb ranges reference anchors not in anchors table: {unknown}")
    rng_meas = uwb["range"].to_numpy(float).copy()
    if dataset.meta.known_anchor_bias:
        for a, b in dataset.meta.known_anchor_bias.items():
            rng_meas[ids == str(a)] -= b
    tau = uwb["t"].to_numpy(float) + t_d  # IMU-clock time of each range
    A = dataset.anchor_array(ids) if len(ids) else np.zeros((0, 3))
    arms = _lever_arms(dataset, opts)
    if "tag" in uwb.columns:
        tags = uwb["tag"].astype(str).to_numpy()
        missing = sorted(set(tags) - set(arms))
        if missing:
            raise InputError(f"uwb ranges from tags without a lever arm in dataset.yaml: {missing}")
        arm_per = np.array([arms[tg] for tg in tags]) if len(tags) else np.zeros((0, 3))
    else:
        arm0 = next(iter(arms.values())) if arms else np.zeros(3)
        arm_per = np.tile(arm0, (len(ids), 1))
    kk = np.clip(np.searchsorted(s, tau), 0, len(s) - 1)
    off_world0 = np.einsum("nij,nj->ni", R0[kk], arm_per) if len(ids) else np.zeros((0, 3))

    # ---- process noise: IMU noise model (dataset.yaml, else a consumer-grade preset) ----
    noise = dataset.meta.imu_noise
    if noise is None:
        noise = ICM20948
        warnings.append("no imu_noise in dataset.yaml: process noise from the ICM20948 preset")
    dens = opts.accel_noise_density if opts.accel_noise_density is not None else noise.accel_noise_density
    lever_known = opts.lever_arm is not None or any(tg.lever_arm is not None for tg in dataset.meta.tags)
    sd_lever = opts.lever_arm_sd if opts.lever_arm_sd is not None else (0.0 if lever_known else 0.1)
    if not lever_known:
        warnings.append(f"lever arm unknown: taken as 0 (not estimated), sd {sd_lever:g} m per axis in the output")
    w_body = u[:, 3:6] - b_g
    if sd_lever > 0:
        # acceleration of an antenna offset L: w' x L + w x (w x L), |.| <= (|w'| + |w|^2) |L|
        k_s = max(1, int(round(0.05 / max(float(np.median(np.diff(s))), 1e-6))))
        w_s = np.column_stack([np.convolve(w_body[:, i], np.ones(k_s) / k_s, mode="same") for i in range(3)])
        w_dot = np.gradient(w_s, s, axis=0)
        lever_acc = sd_lever * (np.linalg.norm(w_dot, axis=1) + np.sum(w_s**2, axis=1))
    else:
        lever_acc = None
    noise_kw: dict[str, Any] = {"accel_noise_density": float(dens), "extra_sd": opts.accel_error_sd,
                                "tau": opts.accel_error_time, "lever_accel_sd": lever_acc}
    if opts.attitude == "gyro" and opts.attitude_error_model:
        if opts.estimate_gyro_bias and static:
            t_win = max(float(s[win][-1] - s[win][0]), 1e-3)
            gyro_bias_sd = math.sqrt(noise.gyro_noise_density**2 / t_win + noise.gyro_bias_rw**2 * t_win)
            tilt0 = noise.accel_bias_sigma0 / GRAVITY  # levelling absorbs the accelerometer bias
        else:
            gyro_bias_sd = noise.gyro_bias_sigma0
            tilt0 = math.radians(5.0)  # levelling on a moving vehicle
        if opts.initial_yaw_sd is not None:
            yaw0 = opts.initial_yaw_sd
        elif opts.initial_yaw is not None:
            yaw0 = math.radians(2.0)
        else:  # the fine bank step is 1/4 of the coarse one: uniform error over +-step/8
            yaw0 = (2 * math.pi / opts.yaw_hypotheses / 4) / math.sqrt(12.0)
        noise_kw.update(accel_bias_sd=noise.accel_bias_sigma0, tilt0_sd=tilt0, yaw0_sd=yaw0,
                        gyro_bias_sd=gyro_bias_sd, gyro_noise_density=noise.gyro_noise_density,
                        gyro_bias_rw=noise.gyro_bias_rw)
    t_rel = s - s[0]

    def inputs(yaw: float):
        """World accelerations, antenna offsets and process-noise PSD for an initial yaw (about world z)."""
        c, sn = math.cos(yaw), math.sin(yaw)
        Rz = np.array([[c, -sn, 0.0], [sn, c, 0.0], [0.0, 0.0, 1.0]])
        f_w = f_world0 @ Rz.T
        q2y = acceleration_error_psd(f_w, t_rel, **noise_kw)
        return np.ascontiguousarray(f_w - G_WORLD), np.ascontiguousarray(off_world0 @ Rz.T), Rz, q2y
    n_before = int(np.sum(tau < s[0]))
    n_after = int(np.sum(tau >= s[-1]))
    if n_before or n_after:
        warnings.append(f"{n_before + n_after} ranges outside the IMU time span were not used")

    sigma = opts.range_sigma or dataset.meta.range_sigma or 0.1

    # ---- initial state ---------------------------------------------------
    x0 = np.zeros(6)
    P0 = np.zeros((6, 6))
    p_ant = None
    if opts.initial_position is not None:
        x0[0:3] = opts.initial_position
        P0[0:3, 0:3] = np.eye(3) * opts.initial_position_sd**2
    else:
        first = tau <= s[0] + opts.init_window
        if len(set(ids[first])) < 3:
            first = np.zeros(len(tau), bool)
            seen: set = set()
            for i, a in enumerate(ids):
                first[i] = True
                seen.add(a)
                if len(seen) >= 4 or (len(seen) == len(anchor_pos) and len(seen) >= 3):
                    break
        win_ids = ids[first]
        uniq = sorted(set(win_ids))
        if len(uniq) < 3:
            from uwbimu.estimation.init import InitialisationError

            raise InitialisationError("cannot initialise: fewer than 3 anchors heard and no initial_position given")
        med = np.array([np.median(rng_meas[first][win_ids == a]) for a in uniq])
        p_ant, cov, ambiguous = multilaterate(np.array([anchor_pos[a] for a in uniq]), med, opts.mirror)
        P0[0:3, 0:3] = cov * sigma**2 + np.eye(3) * 0.05**2
        if ambiguous:
            warnings.append(
                f"initial position from {len(uniq)} coplanar anchors is ambiguous (mirror solution); "
                f"took the {opts.mirror} one"
            )
            events.append({"t": float(s[0] - t_d), "kind": "init_mirror_ambiguity", "choice": opts.mirror})
    P0[3:6, 3:6] = np.eye(3) * opts.initial_velocity_sd**2
    arm0 = next(iter(arms.values())) if arms else np.zeros(3)
    tau_c = np.ascontiguousarray(tau)
    A_c = np.ascontiguousarray(A)

    def start(Rz):
        x = x0.copy()
        if p_ant is not None:
            x[0:3] = p_ant - Rz @ (R0[0] @ arm0)
        return x

    # ---- initial yaw: given, or the best of a bank of hypotheses ---------
    if opts.attitude == "identity":
        yaw = 0.0
    elif opts.initial_yaw is not None:
        yaw = float(opts.initial_yaw)
    else:
        n_w = int(np.searchsorted(s, s[0] + opts.yaw_window)) + 1
        n_w = min(max(n_w, 2), len(s))
        m_w = int(np.searchsorted(tau_c, s[n_w - 1]))
        gate2 = float(opts.gate_sigma) ** 2

        def score(y):
            aw_y, off_y, Rz, q2y = inputs(y)
            out = _filter(s[:n_w], aw_y[:n_w], start(Rz), P0, q2y[:n_w], tau_c[:m_w], A_c[:m_w], off_y[:m_w],
                          rng_meas[:m_w], float(sigma), float(opts.gate_sigma))
            nis_y = out[4]
            return float(np.sum(np.minimum(np.nan_to_num(nis_y, nan=0.0), gate2)))

        K = opts.yaw_hypotheses
        grid = 2 * math.pi * np.arange(K) / K
        scores = [score(y) for y in grid]
        best = float(grid[int(np.argmin(scores))])
        step = 2 * math.pi / K
        fine = best + step * np.linspace(-0.5, 0.5, 5)
        fine_scores = [score(y) for y in fine]
        yaw = float(math.remainder(float(fine[int(np.argmin(fine_scores))]), 2 * math.pi))
        events.append({"t": float(s[0] - t_d), "kind": "yaw_bank", "yaw": yaw, "hypotheses": K + 5})
    aw, offsets, Rz, q2 = inputs(yaw)
    quats = quat_normalize(quat_multiply(quat_exp(np.array([0.0, 0.0, yaw])), quats0)) if yaw != 0.0 else quats0

    X, Pd, pred, innov, nis, accepted = _filter(
        s, aw, start(Rz), P0, q2, tau_c, A_c, offsets, rng_meas, float(sigma), float(opts.gate_sigma)
    )
    in_span = (tau >= s[0]) & (tau < s[-1])
    n_rej = int(np.sum(in_span & ~accepted))
    if n_rej:
        warnings.append(f"{n_rej} of {int(in_span.sum())} ranges rejected by the {opts.gate_sigma:g}-sigma gate")

    # ---- assemble the common result -------------------------------------
    n = len(s)
    states = np.zeros((n, S.NOMINAL_DIM))
    states[:, S.P] = X[:, 0:3]
    states[:, S.V] = X[:, 3:6]
    states[:, S.Q] = quats
    states[:, S.BG] = b_g
    lever = next(iter(arms.values())) if arms else np.zeros(3)
    states[:, S.PIU] = lever
    states[:, S.TD] = t_d
    # Consider terms: the fixed lever arm and time offset are not estimated; their
    # uncertainty maps into the output (IMU) position and velocity to first order:
    # p_IMU = p_ant - R L  (d/dL: -R),  v_IMU = v_ant - R (w x L)  (d/dL: -R [w]x),
    # and a state at t + dt_d differs by (v, a) dt_d.
    P_out = Pd.copy()
    if sd_lever > 0:
        R_all = quat_to_rotmat(quats)
        J = np.concatenate([-R_all, -np.einsum("nij,njk->nik", R_all, skew(w_body))], axis=1)  # (n, 6, 3)
        P_out += sd_lever**2 * np.einsum("nik,njk->nij", J, J)
    if opts.time_offset_sd > 0:
        Jt = np.concatenate([X[:, 3:6], aw], axis=1)
        P_out += opts.time_offset_sd**2 * np.einsum("ni,nj->nij", Jt, Jt)
    sd = np.full((n, S.ERROR_DIM), np.nan)
    sd[:, 0:6] = np.sqrt(np.maximum(np.diagonal(P_out, axis1=1, axis2=2), 0.0))
    covariances = None
    if opts.full_covariance:
        covariances = np.full((n, S.ERROR_DIM, S.ERROR_DIM), np.nan)
        covariances[:, 0:6, 0:6] = P_out
    residuals = pd.DataFrame(
        {
            "t": uwb["t"].to_numpy(float),
            "anchor": ids,
            "range": rng_meas,
            "predicted": pred,
            "innovation": innov,
            "nis": nis,
            "accepted": accepted,
        }
    )
    calibration = {
        "lever_arm": lever.tolist(),
        "lever_arm_sd": [float("nan")] * 3,
        "time_offset": t_d,
        "time_offset_sd": float("nan"),
        "accel_bias": [0.0, 0.0, 0.0],
        "accel_bias_sd": [float("nan")] * 3,
        "gyro_bias": b_g.tolist(),
        "gyro_bias_sd": [float("nan")] * 3,
    }
    if progress is not None:
        progress(1.0)
    return EstimationResult(
        t=s - t_d,
        states=states,
        sd=sd,
        residuals=residuals,
        calibration=calibration,
        covariances=covariances,
        warnings=warnings,
        events=events,
        estimator="pointmass",
        config=opts.model_dump(),
        runtime_s=time.perf_counter() - t_start,
        t_imu=s.copy(),
        extra={
            "initial_yaw": yaw,
            "lever_arm_sd": sd_lever,
            "time_offset_sd": opts.time_offset_sd,
            "accel_psd_start": q2[0].tolist(),
            "accel_psd_end": q2[-1].tolist(),
            "filter_position_sd_end": np.sqrt(np.maximum(np.diagonal(Pd[-1])[0:3], 0.0)).tolist(),
        },
    )


refresh_stale_cache(globals(), [_physics])
