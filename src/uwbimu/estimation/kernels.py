"""numba kernels of the error-state EKF filter pass (propagation with IMU
interpolation, state at a measurement time, gated robust range update).

The physics primitives (rotation, RK4 step, error-state transition, covariance
step, injection, range/TDoA Jacobians) live once in :mod:`uwbimu.models.kernels`
and are re-exported here for existing callers.  ``tests/test_eskf_jacobians.py``
pins every one of them to the reference model.

Extended nominal state ``x`` (length ``20 + nb``): the 20 numbers of
:mod:`uwbimu.models.state` followed by ``nb`` per-anchor range biases [m].
Error state (length ``N = 19 + nb``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from uwbimu.models import kernels as _physics
from uwbimu.models.kernels import (  # noqa: F401  (re-exported)
    GRAVITY, rotmat, _deriv, _rk4_core, _rk4, rk4_step_mid, rk4_step, propagate_interval, _mm3,
    _skew3, _phi_blocks, phi_blocks, _phi_vec, _cov_step, cov_step, decay_biases, range_jacobian,
    inject, quat_mul, quat_exp, error_transition, tdoa_jacobian, refresh_stale_cache,
)

# robust loss codes
ROBUST_NONE = 0
ROBUST_HUBER = 1
ROBUST_GM = 2

# range-update status codes
UPD_OK = 0
UPD_BEFORE_IMU = 1  # tau precedes the first IMU sample


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
def _other_tag(xt, lever_err):
    """``xt`` with the lever arm of the tag whose lever block starts at error index ``lever_err`` in the
    first tag's place (nominal 16:19), so the one-tag Jacobians apply; see :func:`_move_lever_rows`."""
    x2 = xt.copy()
    for i in range(3):
        x2[16 + i] = xt[lever_err + 1 + i]
    return x2


@njit(cache=True)
def _move_lever_rows(h, lever_err):
    """Move the lever-arm columns of ``h`` (15:18) to the tag's block ``lever_err .. lever_err + 2``."""
    for i in range(3):
        h[lever_err + i] += h[15 + i]
        h[15 + i] = 0.0


@njit(cache=True)
def range_update(x, P, imu_t, imu_u, imu_um, k, tau, anchor, bias_idx, z, r_var, gate, force,
                 robust_kind, robust_c, gain_mask, dt_max, out, lever_err=15, pair_idx=-1):
    """Process one range: predict at IMU time ``tau``, gate, re-weight, Joseph update.

    ``x``, ``P`` belong to IMU time ``imu_t[k] >= tau`` and are updated in
    place when the range is accepted.  ``gain_mask`` (N,) is 1 for estimated
    error components and 0 for consider (Schmidt) or fixed ones: their gain is
    zeroed, and the Joseph form keeps ``P`` correct for that sub-optimal gain.
    ``gate`` is the NIS threshold (<= 0: no gate); ``force`` accepts regardless.
    ``out`` (7,) receives ``predicted, innovation, nis, accepted, weight, status, S``
    (``S`` the innovation variance before robust re-weighting).  ``lever_err``: error index of the
    measuring tag's lever-arm block (15: the first tag).
    """
    N = P.shape[0]
    xt = np.empty_like(x)
    u_tau = np.empty(6)
    st = state_at(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau)
    out[5] = st
    if st != UPD_OK:
        _not_processed(out)
        return
    h = np.empty(N)
    delta = imu_t[k] - tau
    if delta < 0:
        delta = 0.0
    if lever_err != 15:
        pred = range_jacobian(_other_tag(xt, lever_err), u_tau, anchor, bias_idx, delta, h)
        _move_lever_rows(h, lever_err)
    else:
        pred = range_jacobian(xt, u_tau, anchor, bias_idx, delta, h)
    scalar_update(x, P, h, pred, z, r_var, gate, force, robust_kind, robust_c, gain_mask, out)


@njit(cache=True)
def tdoa_update(x, P, imu_t, imu_u, imu_um, k, tau, anchor_a, anchor_b, bias_a, bias_b, z, r_var, gate, force,
                robust_kind, robust_c, gain_mask, dt_max, out, lever_err=15, pair_idx=-1):
    """Process one TDoA ``z = |p_U - p_b| - |p_U - p_a|`` [m] as :func:`range_update` does a range.

    Prediction and Jacobian from :func:`tdoa_jacobian` (pinned to ``reference.tdoa_measurement``);
    ``r_var`` is the TDoA variance [m^2]; ``bias_a``, ``bias_b`` the error indices of the two anchors'
    range-bias states (or -1): the TDoA then carries ``b_b - b_a``.
    """
    N = P.shape[0]
    xt = np.empty_like(x)
    u_tau = np.empty(6)
    st = state_at(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau)
    out[5] = st
    if st != UPD_OK:
        _not_processed(out)
        return
    h = np.empty(N)
    work = np.empty(N)
    delta = imu_t[k] - tau
    if delta < 0:
        delta = 0.0
    if lever_err != 15:
        pred = tdoa_jacobian(_other_tag(xt, lever_err), u_tau, anchor_a, anchor_b, -1, delta, h, work)
        _move_lever_rows(h, lever_err)
    else:
        pred = tdoa_jacobian(xt, u_tau, anchor_a, anchor_b, -1, delta, h, work)
    if bias_b >= 0:
        h[bias_b] += 1.0
        pred += xt[bias_b + 1]
    if bias_a >= 0:
        h[bias_a] -= 1.0
        pred -= xt[bias_a + 1]
    if pair_idx >= 0:
        # a constant bias of this anchor pair (error index pair_idx, nominal pair_idx + 1)
        h[pair_idx] += 1.0
        pred += xt[pair_idx + 1]
    scalar_update(x, P, h, pred, z, r_var, gate, force, robust_kind, robust_c, gain_mask, out)


@njit(cache=True)
def _not_processed(out):
    out[0] = np.nan
    out[1] = np.nan
    out[2] = np.nan
    out[3] = 0.0
    out[4] = 0.0
    out[6] = np.nan


@njit(cache=True)
def scalar_update(x, P, h, pred, z, r_var, gate, force, robust_kind, robust_c, gain_mask, out):
    """Gate, robust re-weighting and Joseph update of ``x``, ``P`` (in place) for one scalar measurement
    ``z`` with prediction ``pred`` and Jacobian ``h`` (N,); fills ``out[0:5]`` and ``out[6]`` (see
    :func:`range_update`)."""
    N = P.shape[0]
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


@njit(cache=True)
def midpoints_into(t, u, i0, i1, out):
    """Cubic mid-interval inputs of intervals ``i0 .. i1-1`` into ``out[i0:i1]``, as
    ``reference.midpoint_inputs(t, u)`` computes them on the samples given (four nodes around each
    interval, one-sided at the ends; linear with fewer than four samples).  The streaming filter
    calls it as samples arrive; an interval ``<= len(t) - 3`` never changes afterwards."""
    n = t.shape[0]
    for k in range(i0, i1):
        if n < 4:
            for c in range(6):
                out[k, c] = 0.5 * (u[k, c] + u[k + 1, c])
            continue
        f = k - 1
        if f < 0:
            f = 0
        if f > n - 4:
            f = n - 4
        tm = 0.5 * (t[k] + t[k + 1])
        for c in range(6):
            out[k, c] = 0.0
        for j in range(4):
            w = 1.0
            for m in range(4):
                if m != j:
                    w *= (tm - t[f + m]) / (t[f + j] - t[f + m])
            for c in range(6):
                out[k, c] += w * u[f + j, c]


@njit(cache=True)
def rotation_stats_into(u, k0, n, win, off, cs, cs2, rot_mean, rot_ms):
    """Trailing-window gyro statistics of samples ``k0 .. n-1`` (see ``filterpass.rotation_window_stats``).

    ``cs`` (n+1, 3) / ``cs2`` (n+1,) hold the running sums of the gyro and of its squared norm
    (``cs[0] = 0`` at the start of the log; ``off`` samples were trimmed from the front, so buffer index
    ``i`` is sample ``i + off``); entries ``k0 + 1 .. n`` are filled, and ``rot_mean[k]``, ``rot_ms[k]``
    for the new samples."""
    for k in range(k0, n):
        w0, w1, w2 = u[k, 3], u[k, 4], u[k, 5]
        cs[k + 1, 0] = cs[k, 0] + w0
        cs[k + 1, 1] = cs[k, 1] + w1
        cs[k + 1, 2] = cs[k, 2] + w2
        cs2[k + 1] = cs2[k] + (w0 * w0 + w1 * w1 + w2 * w2)
        i1 = k + 1 + off
        i0 = i1 - win
        if i0 < 0:
            i0 = 0
        cnt = float(i1 - i0)
        b0 = i0 - off
        for c in range(3):
            rot_mean[k, c] = (cs[k + 1, c] - cs[b0, c]) / cnt
        rot_ms[k] = (cs2[k + 1] - cs2[b0]) / cnt


@njit(cache=True)
def divergence_code(x, P, max_pos_var, hull_lo, hull_hi, all_rej, all_reject_run):
    """The supervisor's checks: 0 healthy, 1 non-finite state or covariance diagonal, 2 negative
    covariance diagonal, 3 position variance above ``max_pos_var``, 4 position outside the hull box,
    5 ``all_rej`` consecutive rejections."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return 1
    for i in range(P.shape[0]):
        if not math.isfinite(P[i, i]):
            return 1
    for i in range(P.shape[0]):
        if P[i, i] < -1e-9:
            return 2
    if P[0, 0] + P[1, 1] + P[2, 2] > max_pos_var:
        return 3
    for i in range(3):
        if x[i] < hull_lo[i] or x[i] > hull_hi[i]:
            return 4
    if all_rej >= all_reject_run:
        return 5
    return 0


refresh_stale_cache(globals(), [_physics])
