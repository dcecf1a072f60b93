"""numba kernels of the error-state EKF (propagation, covariance, range update).

These re-express the reference model of :mod:`uwbimu.models.reference` for
speed; ``tests/test_eskf_jacobians.py`` pins every one of them to the
reference (nominal RK4 step, transition matrix, noise Jacobian and range
Jacobians against finite differences).

Layout
------
Extended nominal state ``x`` (length ``20 + nb``): the 20 numbers of
:mod:`uwbimu.models.state` followed by ``nb`` per-anchor constant range biases
[m].  Error state (length ``N = 19 + nb``): ``dp dv dtheta db_a db_g dp_IU
dt_d`` then the bias errors.  Attitude error is a right perturbation
``q = q_hat ⊗ Exp(dtheta)``.

Error-state dynamics (continuous time, ``a = a_m - b_a``, ``w = w_m - b_g``)::

    dp'     = dv
    dv'     = -R [a]x dtheta - R db_a - R n_a
    dtheta' = -[w]x dtheta - db_g - n_g
    db_a'   = n_ba,  db_g' = n_bg,  dp_IU' = 0,  dt_d' = 0

The transition matrix is its second-order series ``I + F dt + F^2 dt^2 / 2``
(with the exact rotation ``Exp(-w dt)`` for the attitude block), applied block
by block so that a step costs O(N) instead of O(N^3).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

GRAVITY = 9.81  # must equal uwbimu.models.reference.GRAVITY (pinned by a test)

# robust loss codes
ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_GM = 2

# range-update status codes
UPD_OK = 0
UPD_BEFORE_IMU = 1  # tau precedes the first IMU sample


@njit(cache=True)
def rotmat(q, R):
    """Fill ``R`` (3x3) with the rotation matrix of quaternion ``q`` (w, x, y, z)."""
    w, x, y, z = q[0], q[1], q[2], q[3]
    R[0, 0] = 1 - 2 * (y * y + z * z)
    R[0, 1] = 2 * (x * y - w * z)
    R[0, 2] = 2 * (x * z + w * y)
    R[1, 0] = 2 * (x * y + w * z)
    R[1, 1] = 1 - 2 * (x * x + z * z)
    R[1, 2] = 2 * (y * z - w * x)
    R[2, 0] = 2 * (x * z - w * y)
    R[2, 1] = 2 * (y * z + w * x)
    R[2, 2] = 1 - 2 * (x * x + y * y)


@njit(cache=True)
def _deriv(x, u, out):
    """Derivative of the first 10 nominal components (p, v, q) — reference ``continuous_dynamics``."""
    qw, qx, qy, qz = x[6], x[7], x[8], x[9]
    ax = u[0] - x[10]
    ay = u[1] - x[11]
    az = u[2] - x[12]
    wx = u[3] - x[13]
    wy = u[4] - x[14]
    wz = u[5] - x[15]
    r00 = 1 - 2 * (qy * qy + qz * qz)
    r01 = 2 * (qx * qy - qw * qz)
    r02 = 2 * (qx * qz + qw * qy)
    r10 = 2 * (qx * qy + qw * qz)
    r11 = 1 - 2 * (qx * qx + qz * qz)
    r12 = 2 * (qy * qz - qw * qx)
    r20 = 2 * (qx * qz - qw * qy)
    r21 = 2 * (qy * qz + qw * qx)
    r22 = 1 - 2 * (qx * qx + qy * qy)
    out[0] = x[3]
    out[1] = x[4]
    out[2] = x[5]
    out[3] = r00 * ax + r01 * ay + r02 * az
    out[4] = r10 * ax + r11 * ay + r12 * az
    out[5] = r20 * ax + r21 * ay + r22 * az - GRAVITY
    out[6] = 0.5 * (-qx * wx - qy * wy - qz * wz)
    out[7] = 0.5 * (qw * wx - qz * wy + qy * wz)
    out[8] = 0.5 * (qz * wx + qw * wy - qx * wz)
    out[9] = 0.5 * (-qy * wx + qx * wy + qw * wz)


@njit(cache=True)
def _rk4_core(x, u0, um, u1, dt, out, wk):
    """RK4 step with inputs at start/middle/end and a work array ``wk`` (6, max(10, len(x))).

    ``wk[0]`` is not touched (callers may keep ``um`` there); no allocation.
    """
    n = x.shape[0]
    k1 = wk[1]
    k2 = wk[2]
    k3 = wk[3]
    k4 = wk[4]
    xt = wk[5]
    for i in range(n):
        xt[i] = x[i]
    _deriv(x, u0, k1)
    for i in range(10):
        xt[i] = x[i] + 0.5 * dt * k1[i]
    _deriv(xt, um, k2)
    for i in range(10):
        xt[i] = x[i] + 0.5 * dt * k2[i]
    _deriv(xt, um, k3)
    for i in range(10):
        xt[i] = x[i] + dt * k3[i]
    _deriv(xt, u1, k4)
    for i in range(n):
        out[i] = x[i]
    for i in range(10):
        out[i] = x[i] + dt / 6.0 * (k1[i] + 2 * k2[i] + 2 * k3[i] + k4[i])
    nq = math.sqrt(out[6] ** 2 + out[7] ** 2 + out[8] ** 2 + out[9] ** 2)
    for i in range(6, 10):
        out[i] /= nq


@njit(cache=True)
def _rk4(x, u0, u1, dt, out, wk):
    """RK4 step with the linearly interpolated (average) mid-interval input."""
    for i in range(6):
        wk[0, i] = 0.5 * (u0[i] + u1[i])
    _rk4_core(x, u0, wk[0], u1, dt, out, wk)


@njit(cache=True)
def rk4_step_mid(x, u0, um, u1, dt, out):
    """Reference ``propagate(x, u0, u1, dt, um=um)``: RK4 with an explicit mid-interval input."""
    wk = np.empty((6, max(10, x.shape[0])))
    _rk4_core(x, u0, um, u1, dt, out, wk)


@njit(cache=True)
def cubic_at(imu_t, imu_u, i, t, out):
    """IMU input at time ``t`` inside interval ``i`` (``imu_t[i] .. imu_t[i+1]``).

    Lagrange cubic through the four samples around the interval (centred,
    one-sided at the ends of the log), as ``reference.midpoint_inputs``; linear
    with fewer than four samples.
    """
    n = imu_t.shape[0]
    if n < 4:
        al = (t - imu_t[i]) / (imu_t[i + 1] - imu_t[i])
        for c in range(6):
            out[c] = imu_u[i, c] + al * (imu_u[i + 1, c] - imu_u[i, c])
        return
    f = i - 1
    if f < 0:
        f = 0
    if f > n - 4:
        f = n - 4
    for c in range(6):
        out[c] = 0.0
    for j in range(4):
        w = 1.0
        for m in range(4):
            if m != j:
                w *= (t - imu_t[f + m]) / (imu_t[f + j] - imu_t[f + m])
        for c in range(6):
            out[c] += w * imu_u[f + j, c]


@njit(cache=True)
def rk4_step(x, u0, u1, dt, out):
    """One step of the reference ``propagate`` (RK4, linearly interpolated input).

    ``x`` and ``out`` are extended nominal states (only the first 10
    components change); ``dt`` may be negative (backward integration).
    ``out`` may be the same array as ``x``.
    """
    wk = np.empty((6, max(10, x.shape[0])))
    _rk4(x, u0, u1, dt, out, wk)


@njit(cache=True)
def propagate_interval(x, u0, u1, dt, dt_max, out):
    """Propagate over one IMU interval, splitting it when ``|dt| > dt_max`` (IMU gaps).

    The input is interpolated linearly over the whole interval, as in the
    reference; each sub-step is one reference RK4 step.
    """
    n = 1
    if dt_max > 0 and abs(dt) > dt_max:
        n = int(math.ceil(abs(dt) / dt_max))
    if n == 1:
        rk4_step(x, u0, u1, dt, out)
        return
    ua = np.empty(6)
    ub = np.empty(6)
    h = dt / n
    for i in range(x.shape[0]):
        out[i] = x[i]
    for s in range(n):
        fa = s / n
        fb = (s + 1) / n
        for i in range(6):
            ua[i] = u0[i] + fa * (u1[i] - u0[i])
            ub[i] = u0[i] + fb * (u1[i] - u0[i])
        rk4_step(out, ua, ub, h, out)


@njit(cache=True)
def _mm3(A, B, C):
    """``C = A @ B`` for 3x3 arrays (loops: no BLAS call, no allocation)."""
    for i in range(3):
        for j in range(3):
            C[i, j] = A[i, 0] * B[0, j] + A[i, 1] * B[1, j] + A[i, 2] * B[2, j]


@njit(cache=True)
def _skew3(v0, v1, v2, S):
    S[0, 0] = 0.0
    S[0, 1] = -v2
    S[0, 2] = v1
    S[1, 0] = v2
    S[1, 1] = 0.0
    S[1, 2] = -v0
    S[2, 0] = -v1
    S[2, 1] = v0
    S[2, 2] = 0.0


@njit(cache=True)
def _phi_blocks(x, u, dt, B, W):
    """:func:`phi_blocks` with a work array ``W`` (6, 3, 3)."""
    R = W[0]
    Ax = W[1]
    Wx = W[2]
    RA = W[3]
    RAW = W[4]
    W2 = W[5]
    rotmat(x[6:10], R)
    a0 = u[0] - x[10]
    a1 = u[1] - x[11]
    a2 = u[2] - x[12]
    w0 = u[3] - x[13]
    w1 = u[4] - x[14]
    w2 = u[5] - x[15]
    _skew3(a0, a1, a2, Ax)
    _skew3(w0, w1, w2, Wx)
    _mm3(R, Ax, RA)
    _mm3(RA, Wx, RAW)
    _mm3(Wx, Wx, W2)
    h2 = 0.5 * dt * dt
    for i in range(3):
        for j in range(3):
            B[0, i, j] = -RA[i, j] * h2
            B[1, i, j] = -R[i, j] * h2
            B[2, i, j] = -RA[i, j] * dt + RAW[i, j] * h2
            B[3, i, j] = -R[i, j] * dt
            B[4, i, j] = RA[i, j] * h2
            B[6, i, j] = Wx[i, j] * h2
        B[6, i, i] -= dt
    # exact Exp(-w dt) for the attitude block (Rodrigues)
    th = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) * abs(dt)
    if th < 1e-9:
        s1 = -dt
        s2 = h2
    else:
        wn = th / abs(dt)
        s1 = -math.sin(th) / wn * (1.0 if dt > 0 else -1.0)
        s2 = (1 - math.cos(th)) / (wn * wn)
    for i in range(3):
        for j in range(3):
            B[5, i, j] = s1 * Wx[i, j] + s2 * W2[i, j]
        B[5, i, i] += 1.0


@njit(cache=True)
def phi_blocks(x, u, dt, B):
    """3x3 blocks of the error-state transition matrix over ``dt``.

    ``B`` (7, 3, 3) receives ``Phi_p_th, Phi_p_ba, Phi_v_th, Phi_v_ba,
    Phi_v_bg, Phi_th_th, Phi_th_bg``; the other blocks are ``I``, ``dt I`` or 0.
    Evaluated at the nominal state ``x`` with the IMU input ``u`` (6,).
    """
    W = np.empty((6, 3, 3))
    _phi_blocks(x, u, dt, B, W)


@njit(cache=True)
def _phi_vec(B, dt, X):
    """In place ``X[0:15] <- Phi X[0:15]`` for one vector ``X`` (block-sparse Phi)."""
    xv0, xv1, xv2 = X[3], X[4], X[5]
    xt0, xt1, xt2 = X[6], X[7], X[8]
    xa0, xa1, xa2 = X[9], X[10], X[11]
    xg0, xg1, xg2 = X[12], X[13], X[14]
    for i in range(3):
        sp = (B[0, i, 0] * xt0 + B[0, i, 1] * xt1 + B[0, i, 2] * xt2
              + B[1, i, 0] * xa0 + B[1, i, 1] * xa1 + B[1, i, 2] * xa2)
        sv = (B[2, i, 0] * xt0 + B[2, i, 1] * xt1 + B[2, i, 2] * xt2
              + B[3, i, 0] * xa0 + B[3, i, 1] * xa1 + B[3, i, 2] * xa2
              + B[4, i, 0] * xg0 + B[4, i, 1] * xg1 + B[4, i, 2] * xg2)
        st = (B[5, i, 0] * xt0 + B[5, i, 1] * xt1 + B[5, i, 2] * xt2
              + B[6, i, 0] * xg0 + B[6, i, 1] * xg1 + B[6, i, 2] * xg2)
        X[i] += dt * X[3 + i] + sp
        X[6 + i] = st
        X[3 + i] += sv


@njit(cache=True)
def _cov_step(P, x, u, dt, noise, B, W, col):
    """:func:`cov_step` with work arrays (B (7,3,3), W (6,3,3), col (N,))."""
    N = P.shape[0]
    _phi_blocks(x, u, dt, B, W)
    # left multiplication: columns
    for c in range(N):
        for i in range(15):
            col[i] = P[i, c]
        _phi_vec(B, dt, col)
        for i in range(15):
            P[i, c] = col[i]
    # right multiplication: rows
    for r in range(N):
        for i in range(15):
            col[i] = P[r, i]
        _phi_vec(B, dt, col)
        for i in range(15):
            P[r, i] = col[i]
    adt = abs(dt)
    for i in range(3):
        P[i, i] += noise[0] * adt**3 / 3.0
        P[i, 3 + i] += noise[0] * adt**2 / 2.0
        P[3 + i, i] += noise[0] * adt**2 / 2.0
        P[3 + i, 3 + i] += noise[0] * adt
        P[6 + i, 6 + i] += noise[1] * adt
        P[9 + i, 9 + i] += noise[2] * adt
        P[12 + i, 12 + i] += noise[3] * adt
        P[15 + i, 15 + i] += noise[4] * adt
    P[18, 18] += noise[5] * adt
    if noise.shape[0] >= 8 and noise[7] > 0.0 and N > 19:
        # per-anchor range biases as first-order Gauss-Markov processes
        # (b' = -b / tau + w, stationary variance noise[6], 1 / tau = noise[7]):
        # Phi_bb = exp(-|dt| / tau) I, Q_bb = var (1 - Phi_bb^2)
        f = math.exp(-adt * noise[7])
        for r in range(19, N):
            for c in range(N):
                P[r, c] *= f
                P[c, r] *= f
            P[r, r] += noise[6] * (1.0 - f * f)


@njit(cache=True)
def cov_step(P, x, u, dt, noise):
    """``P <- Phi P Phi^T + Q`` over ``dt`` (in place, full covariance).

    ``noise`` = ``[s_a^2, s_g^2, s_ba^2, s_bg^2, s_piu^2, s_td^2]``: continuous
    densities squared (accel, gyro white noise; bias, lever-arm and time-offset
    random walks), optionally followed by ``[var_b, 1 / tau_b]``: the per-anchor
    range biases (error components 19..N-1) are then first-order Gauss-Markov
    processes of stationary variance ``var_b`` and correlation time ``tau_b``
    (``1 / tau_b = 0``: constant biases).  ``Q`` is the Van Loan expansion to the leading order of
    each block (``pp = s_a^2 dt^3/3``, ``pv = s_a^2 dt^2/2``, ``vv = s_a^2 dt``, ...).
    """
    _cov_step(P, x, u, dt, noise, np.empty((7, 3, 3)), np.empty((6, 3, 3)), np.empty(P.shape[0]))


@njit(cache=True)
def decay_biases(x, dt, noise):
    """Mean of Gauss-Markov range biases over ``dt``: ``b <- exp(-|dt| / tau) b`` (no-op when constant)."""
    if noise.shape[0] >= 8 and noise[7] > 0.0 and x.shape[0] > 20:
        f = math.exp(-abs(dt) * noise[7])
        for i in range(20, x.shape[0]):
            x[i] *= f


@njit(cache=True)
def propagate_until(x, P, imu_t, imu_u, imu_um, k, t_target, noise, dt_max, cov_every, ws):
    """Advance the filter from IMU sample ``k`` until ``imu_t[k] >= t_target``.

    Nominal state by reference RK4 steps with the cubic mid-interval inputs
    ``imu_um`` (``reference.midpoint_inputs``; linear sub-steps across IMU
    gaps longer than ``dt_max``), covariance by :func:`cov_step`
    every ``cov_every`` samples (one step over the block, linearised at the
    block's start with its mean input); the pending block is always flushed
    before returning so that ``P`` belongs to ``imu_t[k]``.  ``ws`` is unused
    (kept for signature stability).  Returns the new sample index.
    """
    n = imu_t.shape[0]
    nx = x.shape[0]
    xn = np.empty(nx)
    xb = x.copy()
    usum = np.zeros(6)
    ub = np.empty(6)
    ua = np.empty(6)
    ue = np.empty(6)
    wk = np.empty((6, max(10, nx)))
    B = np.empty((7, 3, 3))
    W = np.empty((6, 3, 3))
    col = np.empty(P.shape[0])
    dts = 0.0
    cnt = 0
    while k + 1 < n and imu_t[k] < t_target:
        dt = imu_t[k + 1] - imu_t[k]
        if dt_max > 0 and dt > dt_max:
            # IMU gap: sub-steps for the covariance as well
            if cnt > 0:
                for i in range(6):
                    ub[i] = usum[i] / cnt
                _cov_step(P, xb, ub, dts, noise, B, W, col)
                cnt = 0
                dts = 0.0
                for i in range(6):
                    usum[i] = 0.0
            m = int(math.ceil(dt / dt_max))
            h = dt / m
            for s in range(m):
                for i in range(6):
                    ua[i] = imu_u[k, i] + (s / m) * (imu_u[k + 1, i] - imu_u[k, i])
                    ue[i] = imu_u[k, i] + ((s + 1) / m) * (imu_u[k + 1, i] - imu_u[k, i])
                    ub[i] = 0.5 * (ua[i] + ue[i])
                _cov_step(P, x, ub, h, noise, B, W, col)
                _rk4(x, ua, ue, h, x, wk)
                decay_biases(x, h, noise)
            k += 1
            continue
        if cnt == 0:
            for i in range(nx):
                xb[i] = x[i]
        for i in range(6):
            # Simpson mean of the input over the interval (for the linearisation)
            usum[i] += (imu_u[k, i] + 4.0 * imu_um[k, i] + imu_u[k + 1, i]) / 6.0
        dts += dt
        cnt += 1
        _rk4_core(x, imu_u[k], imu_um[k], imu_u[k + 1], dt, xn, wk)
        for i in range(nx):
            x[i] = xn[i]
        decay_biases(x, dt, noise)
        k += 1
        if cnt >= cov_every:
            for i in range(6):
                ub[i] = usum[i] / cnt
            _cov_step(P, xb, ub, dts, noise, B, W, col)
            cnt = 0
            dts = 0.0
            for i in range(6):
                usum[i] = 0.0
    if cnt > 0:
        for i in range(6):
            ub[i] = usum[i] / cnt
        _cov_step(P, xb, ub, dts, noise, B, W, col)
    return k


@njit(cache=True)
def state_at(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau):
    """Nominal state at IMU time ``tau <= imu_t[k]`` from the current state ``x`` (at ``imu_t[k]``).

    Integrates the actual IMU samples backward (reference RK4 steps with
    negative ``dt`` and the cubic mid-interval inputs ``imu_um``), ending with
    a partial step to ``tau`` whose inputs are the same cubic evaluated at
    ``tau`` and at the partial step's middle (linear inside an IMU gap).
    Because it starts from the current, already corrected estimate, every
    earlier update is accounted for.  Fills ``xt`` and the input ``u_tau``;
    returns an UPD_* code.
    """
    for i in range(x.shape[0]):
        xt[i] = x[i]
    j = k
    if tau >= imu_t[k]:
        for i in range(6):
            u_tau[i] = imu_u[k, i]
        if tau > imu_t[k]:
            # (only at the very end of the IMU stream) extrapolate with a held input
            propagate_interval(xt, imu_u[k], imu_u[k], tau - imu_t[k], dt_max, xt)
        return UPD_OK
    if tau < imu_t[0]:
        return UPD_BEFORE_IMU
    wk = np.empty((6, max(10, x.shape[0])))
    while j > 0 and imu_t[j - 1] >= tau:
        dt = imu_t[j - 1] - imu_t[j]
        if dt_max > 0 and -dt > dt_max:
            propagate_interval(xt, imu_u[j], imu_u[j - 1], dt, dt_max, xt)
        else:
            _rk4_core(xt, imu_u[j], imu_um[j - 1], imu_u[j - 1], dt, xt, wk)
        j -= 1
    if tau < imu_t[j]:
        t0 = imu_t[j - 1]
        t1 = imu_t[j]
        if dt_max > 0 and t1 - t0 > dt_max:
            al = (tau - t0) / (t1 - t0)
            for i in range(6):
                u_tau[i] = imu_u[j - 1, i] + al * (imu_u[j, i] - imu_u[j - 1, i])
            propagate_interval(xt, imu_u[j], u_tau, tau - t1, dt_max, xt)
        else:
            um = np.empty(6)
            cubic_at(imu_t, imu_u, j - 1, tau, u_tau)
            cubic_at(imu_t, imu_u, j - 1, 0.5 * (tau + t1), um)
            _rk4_core(xt, imu_u[j], um, u_tau, tau - t1, xt, wk)
    else:
        for i in range(6):
            u_tau[i] = imu_u[j, i]
    return UPD_OK


@njit(cache=True)
def range_jacobian(xt, u_tau, anchor, bias_idx, delta, h):
    """Predicted range and its Jacobian ``h`` (N,) w.r.t. the error state at filter time.

    ``xt``: extended nominal state at ``tau`` (IMU clock), ``u_tau`` the IMU input
    there, ``anchor`` (3,) world position, ``bias_idx`` the error index of the
    anchor's range bias (or -1), ``delta = t_filter - tau`` >= 0 [s].

    At ``tau`` (``u`` = unit vector from antenna to anchor, ``w = w_m - b_g``)::

        H_p = -u^T,  H_th = u^T R [p_IU]x,  H_pIU = -u^T R,
        H_td = -u^T (v + R [w]x p_IU),  H_bias = 1

    and the error at ``tau`` is mapped to the filter time by
    ``dx(tau) = (I - F delta) dx(t)`` (first order), which adds
    ``H_v = -delta H_p``, ``H_th += delta H_th [w]x`` and ``H_bg = delta H_th``.
    Returns the predicted range [m].
    """
    R = np.empty((3, 3))
    rotmat(xt[6:10], R)
    l0, l1, l2 = xt[16], xt[17], xt[18]
    w0 = u_tau[3] - xt[13]
    w1 = u_tau[4] - xt[14]
    w2 = u_tau[5] - xt[15]
    pu = np.empty(3)
    # w x l (body)
    c0 = w1 * l2 - w2 * l1
    c1 = w2 * l0 - w0 * l2
    c2 = w0 * l1 - w1 * l0
    vel = np.empty(3)
    for i in range(3):
        pu[i] = xt[i] + R[i, 0] * l0 + R[i, 1] * l1 + R[i, 2] * l2
        vel[i] = xt[3 + i] + R[i, 0] * c0 + R[i, 1] * c1 + R[i, 2] * c2
    d0 = anchor[0] - pu[0]
    d1 = anchor[1] - pu[1]
    d2 = anchor[2] - pu[2]
    rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if rho < 1e-9:
        rho = 1e-9
    un = np.array([d0 / rho, d1 / rho, d2 / rho])
    for i in range(h.shape[0]):
        h[i] = 0.0
    uR = np.empty(3)
    for j in range(3):
        uR[j] = un[0] * R[0, j] + un[1] * R[1, j] + un[2] * R[2, j]
    # u^T R [l]x
    hth0 = uR[1] * l2 - uR[2] * l1
    hth1 = uR[2] * l0 - uR[0] * l2
    hth2 = uR[0] * l1 - uR[1] * l0
    for i in range(3):
        h[i] = -un[i]
        h[15 + i] = -uR[i]
    h[18] = -(un[0] * vel[0] + un[1] * vel[1] + un[2] * vel[2])
    # time mapping tau -> filter time
    for i in range(3):
        h[3 + i] = delta * un[i]
    # (H_th [w]x)_j = sum_i hth_i Wx[i, j];  row vector times skew = -(w x hth)^T ... computed explicitly
    g0 = hth1 * w2 - hth2 * w1
    g1 = hth2 * w0 - hth0 * w2
    g2 = hth0 * w1 - hth1 * w0
    h[6] = hth0 + delta * g0
    h[7] = hth1 + delta * g1
    h[8] = hth2 + delta * g2
    h[12] = delta * hth0
    h[13] = delta * hth1
    h[14] = delta * hth2
    bias = 0.0
    if bias_idx >= 0:
        h[bias_idx] = 1.0
        bias = xt[bias_idx + 1]
    return rho + bias


@njit(cache=True)
def robust_weight(e, kind, c):
    """Weight in (0, 1] of a normalised innovation ``e`` (in sigmas)."""
    a = abs(e)
    if kind == ROBUST_HUBER:
        if a <= c:
            return 1.0
        return c / a
    if kind == ROBUST_GM:
        r = 1.0 + (e / c) ** 2
        return 1.0 / (r * r)
    return 1.0


@njit(cache=True)
def inject(x, dx):
    """``x <- x ⊞ dx`` for the extended state (right attitude perturbation)."""
    for i in range(6):
        x[i] += dx[i]
    t0, t1, t2 = dx[6], dx[7], dx[8]
    th = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if th < 1e-8:
        k = 0.5 - th * th / 48.0
        dw = math.cos(0.5 * th)
    else:
        k = math.sin(0.5 * th) / th
        dw = math.cos(0.5 * th)
    dq0, dq1, dq2, dq3 = dw, k * t0, k * t1, k * t2
    pw, px, py, pz = x[6], x[7], x[8], x[9]
    qw = pw * dq0 - px * dq1 - py * dq2 - pz * dq3
    qx = pw * dq1 + px * dq0 + py * dq3 - pz * dq2
    qy = pw * dq2 - px * dq3 + py * dq0 + pz * dq1
    qz = pw * dq3 + px * dq2 - py * dq1 + pz * dq0
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    x[6] = qw / n
    x[7] = qx / n
    x[8] = qy / n
    x[9] = qz / n
    for i in range(9, dx.shape[0]):
        x[i + 1] += dx[i]


@njit(cache=True)
def range_update(x, P, imu_t, imu_u, imu_um, k, tau, anchor, bias_idx, z, r_var, gate, force,
                 robust_kind, robust_c, gain_mask, dt_max, out):
    """Process one range: predict at IMU time ``tau``, gate, re-weight, Joseph update.

    ``x``, ``P`` belong to IMU time ``imu_t[k] >= tau`` and are updated in
    place when the range is accepted.  ``gain_mask`` (N,) is 1 for estimated
    error components and 0 for consider (Schmidt) or fixed ones: their gain is
    zeroed, and the Joseph form keeps ``P`` correct for that sub-optimal gain.
    ``gate`` is the NIS threshold (<= 0: no gate); ``force`` accepts regardless.
    ``out`` (7,) receives ``predicted, innovation, nis, accepted, weight, status, S``
    (``S`` the innovation variance before robust re-weighting).
    """
    N = P.shape[0]
    xt = np.empty_like(x)
    u_tau = np.empty(6)
    st = state_at(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau)
    out[5] = st
    if st != UPD_OK:
        out[0] = np.nan
        out[1] = np.nan
        out[2] = np.nan
        out[3] = 0.0
        out[4] = 0.0
        out[6] = np.nan
        return
    h = np.empty(N)
    delta = imu_t[k] - tau
    if delta < 0:
        delta = 0.0
    pred = range_jacobian(xt, u_tau, anchor, bias_idx, delta, h)
    r = z - pred
    Ph = np.zeros(N)
    for i in range(N):
        acc = 0.0
        for j in range(N):
            acc += P[i, j] * h[j]
        Ph[i] = acc
    hPh = 0.0
    for i in range(N):
        hPh += h[i] * Ph[i]
    S0 = hPh + r_var
    nis = r * r / S0
    out[0] = pred
    out[1] = r
    out[2] = nis
    out[6] = S0
    accepted = force or gate <= 0 or nis <= gate
    if not accepted:
        out[3] = 0.0
        out[4] = 0.0
        return
    w = robust_weight(r / math.sqrt(S0), robust_kind, robust_c)
    if w < 1e-6:
        w = 1e-6
    S = hPh + r_var / w
    K = np.empty(N)
    for i in range(N):
        K[i] = Ph[i] / S * gain_mask[i]
    # Joseph form for a scalar measurement and any gain K:
    # (I-Kh)P(I-Kh)^T + K r K^T = P - K Ph^T - Ph K^T + K K^T (hPh + r)
    for i in range(N):
        for j in range(i, N):
            v = P[i, j] - K[i] * Ph[j] - Ph[i] * K[j] + K[i] * K[j] * S
            P[i, j] = v
            P[j, i] = v
    dx = np.empty(N)
    for i in range(N):
        dx[i] = K[i] * r
    inject(x, dx)
    out[3] = 1.0
    out[4] = w
