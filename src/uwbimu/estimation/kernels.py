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
from uwbimu.models.state import E_BG, E_L, N_BG, N_DYN, N_L, N_TD, NOM_SHIFT
from uwbimu.models.kernels import (  # noqa: F401  (re-exported)
    GRAVITY, rotmat, _deriv, _rk4_core, _rk4_s, _rk4, rk4_step_mid, rk4_step, propagate_interval, _mm3,
    _skew3, _phi_blocks, phi_blocks, _phi_vec, _cov_step, _cov_step_rows, _cov_step_sym, cov_step, cov_step_blocks, decay_biases,
    base_process_noise, range_jacobian,
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
def propagate_until(x, P, imu_t, imu_u, imu_um, k, t_target, pn, dt_max, cov_every, ws):
    """Advance the filter from IMU sample ``k`` until ``imu_t[k] >= t_target``.

    Nominal state by reference RK4 steps with the cubic mid-interval inputs
    ``imu_um`` (``reference.midpoint_inputs``; linear sub-steps across IMU
    gaps longer than ``dt_max``), covariance by :func:`cov_step_blocks` with the declared blocks' process
    noise ``pn`` (:class:`~uwbimu.models.blocks.ProcessNoise`, ``StateLayout.process_noise``) every ``cov_every`` samples (one step over the block, linearised at the
    block's start with its mean input); the pending block is always flushed
    before returning so that ``P`` belongs to ``imu_t[k]``.  ``ws`` is unused
    (kept for signature stability).  Returns the new sample index.
    """
    nx = x.shape[0]
    N = P.shape[0]
    return _propagate_ws(x, P, imu_t, imu_u, imu_um, k, t_target, pn, dt_max, cov_every,
                         np.empty(nx), np.empty(nx), np.zeros(6), np.empty(6), np.empty(6), np.empty(6),
                         np.empty((6, max(10, nx))), np.empty((7, 3, 3)), np.empty((6, 3, 3)), np.empty((N_DYN, N)),
                         np.empty((N_DYN, N)), np.empty((N_DYN, N)))


@njit(cache=True)
def _row6(A, k):
    """Row ``k`` of an (n, 6) array as a tuple (no array view)."""
    return A[k, 0], A[k, 1], A[k, 2], A[k, 3], A[k, 4], A[k, 5]


@njit(cache=True)
def _propagate_ws(x, P, imu_t, imu_u, imu_um, k, t_target, pn, dt_max, cov_every,
                  xn, xb, usum, ub, ua, ue, wk, B, W, A, T, U):
    """:func:`propagate_until` with its work arrays passed in (no allocation: :func:`filter_loop` calls it for
    every output and measurement); the covariance step is the block-sparse ``_cov_step_sym`` (bit-identical
    to ``cov_step_blocks`` for the filter's covariance, symmetric outside its 9x9 dynamic block)."""
    n = imu_t.shape[0]
    nx = x.shape[0]
    for i in range(6):
        usum[i] = 0.0
    dts = 0.0
    cnt = 0
    while k + 1 < n and imu_t[k] < t_target:
        dt = imu_t[k + 1] - imu_t[k]
        if dt_max > 0 and dt > dt_max:
            # IMU gap: sub-steps for the covariance as well
            if cnt > 0:
                for i in range(6):
                    ub[i] = usum[i] / cnt
                _cov_step_sym(P, xb, ub, dts, pn, B, A)
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
                _cov_step_sym(P, x, ub, h, pn, B, A)
                _rk4(x, ua, ue, h, x, wk)
                decay_biases(x, h, pn)
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
        _rk4_s(x, _row6(imu_u, k), _row6(imu_um, k), _row6(imu_u, k + 1), dt, xn)
        for i in range(nx):
            x[i] = xn[i]
        decay_biases(x, dt, pn)
        k += 1
        if cnt >= cov_every:
            for i in range(6):
                ub[i] = usum[i] / cnt
            _cov_step_sym(P, xb, ub, dts, pn, B, A)
            cnt = 0
            dts = 0.0
            for i in range(6):
                usum[i] = 0.0
    if cnt > 0:
        for i in range(6):
            ub[i] = usum[i] / cnt
        _cov_step_sym(P, xb, ub, dts, pn, B, A)
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
    return _state_at_um(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau, np.empty(6))


@njit(cache=True, inline='always')
def _state_at_um(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau, um):
    """:func:`state_at` with the work array ``um`` (6,) passed in (no allocation: the compiled filter loop
    calls it for every measurement)."""
    for i in range(x.shape[0]):
        xt[i] = x[i]
    if tau >= imu_t[k]:
        for i in range(6):
            u_tau[i] = imu_u[k, i]
        if tau > imu_t[k]:
            # (only at the very end of the IMU stream) extrapolate with a held input
            propagate_interval(xt, imu_u[k], imu_u[k], tau - imu_t[k], dt_max, xt)
        return UPD_OK
    if tau < imu_t[0]:
        return UPD_BEFORE_IMU
    return _state_at_back(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau, um)


@njit(cache=True, inline='always')
def _state_at_back(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau, um):
    """The backward integration of :func:`state_at` (``imu_t[0] <= tau < imu_t[k]``, ``xt`` = ``x``); the
    RK4 steps take their inputs as tuples (:func:`_rk4_s`, the arithmetic of ``_rk4_core``)."""
    j = k
    while j > 0 and imu_t[j - 1] >= tau:
        dt = imu_t[j - 1] - imu_t[j]
        if dt_max > 0 and -dt > dt_max:
            propagate_interval(xt, imu_u[j], imu_u[j - 1], dt, dt_max, xt)
        else:
            _rk4_s(xt, _row6(imu_u, j), _row6(imu_um, j - 1), _row6(imu_u, j - 1), dt, xt)
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
            cubic_at(imu_t, imu_u, j - 1, tau, u_tau)
            cubic_at(imu_t, imu_u, j - 1, 0.5 * (tau + t1), um)
            _rk4_s(xt, _row6(imu_u, j), (um[0], um[1], um[2], um[3], um[4], um[5]),
                   (u_tau[0], u_tau[1], u_tau[2], u_tau[3], u_tau[4], u_tau[5]), tau - t1, xt)
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
    first tag's place (nominal ``N_L``), so the one-tag Jacobians apply; see :func:`_move_lever_rows`."""
    x2 = xt.copy()
    for i in range(3):
        x2[N_L + i] = xt[lever_err + NOM_SHIFT + i]
    return x2


@njit(cache=True)
def _move_lever_rows(h, lever_err):
    """Move the lever-arm columns of ``h`` (``E_L``) to the tag's block ``lever_err .. lever_err + 2``."""
    for i in range(3):
        h[lever_err + i] += h[E_L + i]
        h[E_L + i] = 0.0


@njit(cache=True)
def range_update(x, P, imu_t, imu_u, imu_um, k, tau, anchor, bias_idx, z, r_var, gate, force,
                 robust_kind, robust_c, gain_mask, dt_max, out, lever_err=E_L, pair_idx=-1):
    """Process one range: predict at IMU time ``tau``, gate, re-weight, Joseph update.

    ``x``, ``P`` belong to IMU time ``imu_t[k] >= tau`` and are updated in
    place when the range is accepted.  ``gain_mask`` (N,) is 1 for estimated
    error components and 0 for consider (Schmidt) or fixed ones: their gain is
    zeroed, and the Joseph form keeps ``P`` correct for that sub-optimal gain.
    ``gate`` is the NIS threshold (<= 0: no gate); ``force`` accepts regardless.
    ``out`` (7,) receives ``predicted, innovation, nis, accepted, weight, status, S``
    (``S`` the innovation variance before robust re-weighting).  ``lever_err``: error index of the
    measuring tag's lever-arm block (``E_L``: the first tag).
    """
    _range_update_ws(x, P, imu_t, imu_u, imu_um, k, tau, anchor, bias_idx, z, r_var, gate, force, robust_kind,
                     robust_c, gain_mask, dt_max, out, lever_err, update_work(x.shape[0], P.shape[0]))


@njit(cache=True)
def update_work(nx, N):
    """Work arrays of one measurement update for a nominal state of ``nx`` and an error state of ``N``
    numbers: ``(xt, u_tau, um, h, work, Ph, K, dx)`` (see :func:`_range_update_ws`)."""
    return (np.empty(nx), np.empty(6), np.empty(6), np.empty(N), np.empty(N), np.empty(N), np.empty(N),
            np.empty(N))


@njit(cache=True)
def _range_update_ws(x, P, imu_t, imu_u, imu_um, k, tau, anchor, bias_idx, z, r_var, gate, force,
                     robust_kind, robust_c, gain_mask, dt_max, out, lever_err, ws):
    """:func:`range_update` with its work arrays ``ws`` (:func:`update_work`) passed in: no allocation (the
    compiled filter loop calls it for every range)."""
    xt, u_tau, um, h, work, Ph, Kg, dx = ws
    st = _state_at_um(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau, um)
    out[5] = st
    if st != UPD_OK:
        _not_processed(out)
        return
    delta = imu_t[k] - tau
    if delta < 0:
        delta = 0.0
    if lever_err != E_L:
        pred = range_jacobian(_other_tag(xt, lever_err), u_tau, anchor, bias_idx, delta, h)
        _move_lever_rows(h, lever_err)
    else:
        pred = range_jacobian(xt, u_tau, anchor, bias_idx, delta, h)
    _scalar_update_ws(x, P, h, pred, z, r_var, gate, force, robust_kind, robust_c, gain_mask, out, Ph, Kg, dx)


@njit(cache=True)
def tdoa_update(x, P, imu_t, imu_u, imu_um, k, tau, anchor_a, anchor_b, bias_a, bias_b, z, r_var, gate, force,
                robust_kind, robust_c, gain_mask, dt_max, out, lever_err=E_L, pair_idx=-1):
    """Process one TDoA ``z = |p_U - p_b| - |p_U - p_a|`` [m] as :func:`range_update` does a range.

    Prediction and Jacobian from :func:`tdoa_jacobian` (pinned to ``reference.tdoa_measurement``);
    ``r_var`` is the TDoA variance [m^2]; ``bias_a``, ``bias_b`` the error indices of the two anchors'
    range-bias states (or -1): the TDoA then carries ``b_b - b_a``.
    """
    _tdoa_update_ws(x, P, imu_t, imu_u, imu_um, k, tau, anchor_a, anchor_b, bias_a, bias_b, z, r_var, gate,
                    force, robust_kind, robust_c, gain_mask, dt_max, out, lever_err, pair_idx,
                    update_work(x.shape[0], P.shape[0]))


@njit(cache=True)
def _tdoa_update_ws(x, P, imu_t, imu_u, imu_um, k, tau, anchor_a, anchor_b, bias_a, bias_b, z, r_var, gate,
                    force, robust_kind, robust_c, gain_mask, dt_max, out, lever_err, pair_idx, ws):
    """:func:`tdoa_update` with its work arrays ``ws`` (:func:`update_work`) passed in: no allocation."""
    xt, u_tau, um, h, work, Ph, Kg, dx = ws
    st = _state_at_um(x, imu_t, imu_u, imu_um, k, tau, dt_max, xt, u_tau, um)
    out[5] = st
    if st != UPD_OK:
        _not_processed(out)
        return
    delta = imu_t[k] - tau
    if delta < 0:
        delta = 0.0
    if lever_err != E_L:
        pred = tdoa_jacobian(_other_tag(xt, lever_err), u_tau, anchor_a, anchor_b, -1, delta, h, work)
        _move_lever_rows(h, lever_err)
    else:
        pred = tdoa_jacobian(xt, u_tau, anchor_a, anchor_b, -1, delta, h, work)
    if bias_b >= 0:
        h[bias_b] += 1.0
        pred += xt[bias_b + NOM_SHIFT]
    if bias_a >= 0:
        h[bias_a] -= 1.0
        pred -= xt[bias_a + NOM_SHIFT]
    if pair_idx >= 0:
        # a constant bias of this anchor pair (error index pair_idx, nominal pair_idx + NOM_SHIFT)
        h[pair_idx] += 1.0
        pred += xt[pair_idx + NOM_SHIFT]
    _scalar_update_ws(x, P, h, pred, z, r_var, gate, force, robust_kind, robust_c, gain_mask, out, Ph, Kg, dx)


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
    _scalar_update_ws(x, P, h, pred, z, r_var, gate, force, robust_kind, robust_c, gain_mask, out, np.empty(N),
                      np.empty(N), np.empty(N))


@njit(cache=True, inline='always')
def _scalar_update_ws(x, P, h, pred, z, r_var, gate, force, robust_kind, robust_c, gain_mask, out, Ph, K, dx):
    """:func:`scalar_update` with its work arrays ``Ph``, ``K``, ``dx`` (N,) passed in (no allocation)."""
    N = P.shape[0]
    r = z - pred
    # Ph = P h, four rows at a time: four independent sums (each in the order j = 0, 1, ...) keep the
    # pipeline busy where one running sum waits for every addition
    i = 0
    while i + 4 <= N:
        a0 = 0.0
        a1 = 0.0
        a2 = 0.0
        a3 = 0.0
        for j in range(N):
            hj = h[j]
            a0 += P[i, j] * hj
            a1 += P[i + 1, j] * hj
            a2 += P[i + 2, j] * hj
            a3 += P[i + 3, j] * hj
        Ph[i] = a0
        Ph[i + 1] = a1
        Ph[i + 2] = a2
        Ph[i + 3] = a3
        i += 4
    for i in range(i, N):
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
    for i in range(N):
        K[i] = Ph[i] / S * gain_mask[i]
    # Joseph form for a scalar measurement and any gain K:
    # (I-Kh)P(I-Kh)^T + K r K^T = P - K Ph^T - Ph K^T + K K^T (hPh + r)
    # the upper triangle (i, j >= i) is the result, mirrored below; the same expression for every element as
    # the former one-pass form that stored both (i, j) and (j, i).  Each row is evaluated over its whole
    # length (j from 0, the compiler runs j in SIMD lanes): the row's elements below the diagonal get the
    # expression with the roles of i and j swapped, which the mirror then overwrites; whole rows of one
    # length cost half the time of the triangle's rows of 19, 18, ... 1 (short loops, remainders).  Row i
    # reads only its own old values, so the rows may be overwritten in place.
    for i in range(N):
        ki = K[i]
        pi = Ph[i]
        for j in range(N):
            P[i, j] = P[i, j] - ki * Ph[j] - pi * K[j] + ki * K[j] * S
    for i in range(1, N):
        for j in range(i):
            P[i, j] = P[j, i]
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



# ---------------------------------------------------------------------------------------------------
# The compiled filter pass (filterpass.advance): per-sample work in one loop, Python only for events

# columns of the per-measurement record (filterpass.REC_*) and the statuses the pass writes there
REC_PRED, REC_INNOV, REC_NIS, REC_ACC, REC_W, REC_STATUS, REC_S = range(7)
STATUS_STALE = 2  # tau older than max_lookback behind the filter
STATUS_IN_GAP = 3  # tau inside an IMU gap: the motion there is unknown, the range is not used

# why filter_loop returned
LOOP_DONE = 0  # nothing left to do with the data at hand
LOOP_MODEL = 1  # row ist[IS_J] is a Python-model measurement: Python processes that row, then calls again
LOOP_GAP = 2  # the filter reached the end of IMU gap ist[IS_GAP]: Python inflates P, then calls again
LOOP_DIVERGED = 3  # the supervisor's code is in ist[IS_DIV]
LOOP_PROGRESS = 4  # ipar[IP_PROGRESS_EVERY] outputs recorded since the call: report progress, call again
LOOP_OUT_FULL = 5  # the output arrays are full: grow them, call again
LOOP_EVENTS_FULL = 6  # the event buffer is full: drain it, call again

# ipar: integer settings
(IP_ROBUST, IP_REOPEN, IP_COV_EVERY, IP_ALL_REJECT_RUN, IP_SUPERVISE, IP_GATE_LEVER, IP_MULTI, IP_RECORD,
 IP_STORE_COV, IP_PROGRESS_EVERY, IP_HAS_B, IP_SIZE) = range(12)
# fpar: float settings
(FP_T_LAST, FP_T_UWB_END, FP_T_OUT_END, FP_DT_MAX, FP_GATE, FP_ROBUST_C, FP_MAX_LOOKBACK, FP_OUT_PERIOD,
 FP_R_VAR, FP_TDOA_VAR, FP_MAX_POS_VAR, FP_LEVER_MIN_RATE, FP_SIZE) = range(13)
# ist: integer state (in and out)
IS_K, IS_J, IS_ALL_REJ, IS_N_FROZEN, IS_N_OUT, IS_PHASE, IS_GAP, IS_DIV, IS_N_EV, IS_SIZE = range(10)
# phases of a pass: measurements in time order, then the outputs after the last one, then done
PHASE_ROWS, PHASE_TAIL, PHASE_DONE = range(3)



@njit(cache=True, inline='always')
def _propagate_gaps(x, P, imu_t, imu_u, imu_um, k, t_target, pn, dt_max, cov_every, gap_idx,
                    xn, xb, usum, ub, ua, ue, wk, B, W, A, T, U):
    """``filterpass._propagate`` up to the first IMU gap that needs an inflation of ``P``.

    Returns ``(k, i)``: ``i >= 0`` when the filter stopped at the end of gap ``i`` (``gap_idx[i] + 1``)
    and ``P`` must get ``filterpass.gap_inflation`` before propagating on; ``-1`` when it reached
    ``t_target`` (or the end of the data)."""
    n = imu_t.shape[0]
    ng = gap_idx.shape[0]
    if ng > 0:
        i = np.searchsorted(gap_idx, k)
        if not (i >= ng or gap_idx[i] + 1 >= n or imu_t[gap_idx[i]] >= t_target):
            g = gap_idx[i]
            k = _propagate_ws(x, P, imu_t, imu_u, imu_um, k, imu_t[g + 1], pn, dt_max, cov_every,
                              xn, xb, usum, ub, ua, ue, wk, B, W, A, T, U)
            if k < g + 1:
                return k, -1
            return k, i
    k = _propagate_ws(x, P, imu_t, imu_u, imu_um, k, t_target, pn, dt_max, cov_every,
                      xn, xb, usum, ub, ua, ue, wk, B, W, A, T, U)
    return k, -1


@njit(cache=True)
def _output_row(x, P, imu_t, imu_u, imu_um, k, pn, dt_max, cov_every, gap_idx, n_out, next_out, out_period,
                out_t, out_x, out_d, out_P, store_cov, ist, xn, xb, usum, ub, ua, ue, wk, B, W, A, T, U):
    """Propagate to the output time ``next_out`` and record the state there.  Returns
    ``(code, k, n_out, next_out)``: ``LOOP_DONE`` when recorded, ``LOOP_OUT_FULL`` (nothing done) or
    ``LOOP_GAP`` (stopped at the end of gap ``ist[IS_GAP]``, not recorded yet)."""
    if n_out >= out_t.shape[0]:
        return LOOP_OUT_FULL, k, n_out, next_out
    k, g = _propagate_gaps(x, P, imu_t, imu_u, imu_um, k, next_out, pn, dt_max, cov_every, gap_idx,
                           xn, xb, usum, ub, ua, ue, wk, B, W, A, T, U)
    if g >= 0:
        ist[IS_GAP] = g
        return LOOP_GAP, k, n_out, next_out
    _record_output(n_out, k, imu_t, x, P, out_t, out_x, out_d, out_P, store_cov)
    return LOOP_DONE, k, n_out + 1, next_out + out_period


@njit(cache=True)
def _record_output(n_out, k, imu_t, x, P, out_t, out_x, out_d, out_P, store_cov):
    out_t[n_out] = imu_t[k]
    for i in range(x.shape[0]):
        out_x[n_out, i] = x[i]
    N = P.shape[0]
    for i in range(N):
        out_d[n_out, i] = P[i, i]
    if store_cov:
        for i in range(N):
            for c in range(N):
                out_P[n_out, i, c] = P[i, c]


@njit(cache=True)
def filter_loop(x, P, imu_t, imu_u, imu_um, uwb_t, uwb_a, uwb_b, uwb_r, uwb_tag, anchors, bias_idx,
                gain_mask, mask_frozen, tag_lever_err, pair_mat, pn, hull_lo, hull_hi, rot_mean, rot_ms,
                gap_idx, consec, rec, out_t, out_x, out_d, out_P, ev, fpar, ipar, ist, fst):
    """The filter pass of ``filterpass.advance`` as one compiled loop: IMU propagation (covariance every
    ``cov_every`` samples), the range and TDoA updates in time order with the gate, the robust loss, the
    rotation gate of the lever arm, the supervisor, and the outputs recorded into preallocated arrays.

    The same kernels, called in the same order with the same arguments as the Python loop
    (``filterpass.advance_python``), so the results are bit-identical (``tests/test_filter_loop.py``).
    It returns to Python with a ``LOOP_*`` code for what only Python does: a measurement of a Python model
    (``LOOP_MODEL``), the covariance inflation at the end of an IMU gap (``LOOP_GAP``), the supervisor's
    verdict (``LOOP_DIVERGED``), progress reports, full output or event buffers; the state (``x``,
    ``P``, ``consec``, ``ist``, ``fst``) is then consistent and a new call resumes where it stopped.

    Arrays: the :class:`filterpass.Problem` ones (``uwb_b``/``uwb_tag``/``rot_*`` may be dummies when
    ``ipar`` says they are not used), ``mask_frozen`` the gain mask of a frozen lever arm, ``pair_mat``
    (M, M) the error index of each TDoA pair's bias (or -1), ``rec`` (m, 7) the per-measurement records,
    ``out_*`` the output rows (``out_P`` only when ``ipar[IP_STORE_COV]``), ``ev`` (cap, 3) the
    reopened-gate events ``(row, anchor, rejections before)``; ``fpar``/``ipar`` the settings
    (``FP_*``/``IP_*``), ``ist`` (``IS_*``) and ``fst`` (``[next_out]``) the pass's state.
    """
    n = imu_t.shape[0]
    m = uwb_t.shape[0]
    nx = x.shape[0]
    N = P.shape[0]
    robust_kind = ipar[IP_ROBUST]
    reopen_after = ipar[IP_REOPEN]
    cov_every = ipar[IP_COV_EVERY]
    all_reject_run = ipar[IP_ALL_REJECT_RUN]
    supervise = ipar[IP_SUPERVISE] != 0
    gate_lever = ipar[IP_GATE_LEVER] != 0
    multi = ipar[IP_MULTI] != 0
    record = ipar[IP_RECORD] != 0
    store_cov = ipar[IP_STORE_COV] != 0
    progress_every = ipar[IP_PROGRESS_EVERY]
    has_b = ipar[IP_HAS_B] != 0
    t_last = fpar[FP_T_LAST]
    t_uwb_end = fpar[FP_T_UWB_END]
    t_out_end = fpar[FP_T_OUT_END]
    dt_max = fpar[FP_DT_MAX]
    gate = fpar[FP_GATE]
    robust_c = fpar[FP_ROBUST_C]
    max_lookback = fpar[FP_MAX_LOOKBACK]
    out_period = fpar[FP_OUT_PERIOD]
    r_var = fpar[FP_R_VAR]
    tdoa_var = fpar[FP_TDOA_VAR]
    max_pos_var = fpar[FP_MAX_POS_VAR]
    lever_min_rate = fpar[FP_LEVER_MIN_RATE]
    # work arrays of the propagation
    xn = np.empty(nx)
    xb = np.empty(nx)
    usum = np.zeros(6)
    ub = np.empty(6)
    ua = np.empty(6)
    ue = np.empty(6)
    wk = np.empty((6, max(10, nx)))
    B = np.empty((7, 3, 3))
    W = np.empty((6, 3, 3))
    A = np.empty((N_DYN, N))
    T = np.empty((N_DYN, N))
    U = np.empty((N_DYN, N))
    uws = update_work(nx, N)  # of the measurement updates

    k = ist[IS_K]
    j = ist[IS_J]
    all_rej = ist[IS_ALL_REJ]
    n_frozen = ist[IS_N_FROZEN]
    n_out = ist[IS_N_OUT]
    phase = ist[IS_PHASE]
    n_ev = ist[IS_N_EV]
    next_out = fst[0]
    n_rec = 0
    code = LOOP_DONE
    while True:
        if phase == PHASE_ROWS:
            if j >= m:
                phase = PHASE_TAIL
                continue
            if n_ev >= ev.shape[0]:
                code = LOOP_EVENTS_FULL
                break
            tj = uwb_t[j]
            if tj > t_uwb_end:
                phase = PHASE_TAIL
                continue
            b = uwb_b[j] if has_b else -1
            if b <= -2:
                code = LOOP_MODEL
                break
            # a UWB-clock stamp sees the IMU-clock state t_d later
            tau = tj + x[N_TD]
            if tau > t_last:
                phase = PHASE_TAIL
                continue
            if record:
                while next_out <= tau:
                    code, k, n_out, next_out = _output_row(
                        x, P, imu_t, imu_u, imu_um, k, pn, dt_max, cov_every, gap_idx, n_out, next_out,
                        out_period, out_t, out_x, out_d, out_P, store_cov, ist, xn, xb, usum, ub, ua, ue, wk, B, W,
                        A, T, U)
                    if code != LOOP_DONE:
                        break
                    if supervise:
                        dc = divergence_code(x, P, max_pos_var, hull_lo, hull_hi, all_rej, all_reject_run)
                        if dc != 0:
                            ist[IS_DIV] = dc
                            code = LOOP_DIVERGED
                            break
                    if progress_every > 0:
                        n_rec += 1
                        if n_rec >= progress_every:
                            code = LOOP_PROGRESS
                            break
                if code != LOOP_DONE:
                    break
            k, g = _propagate_gaps(x, P, imu_t, imu_u, imu_um, k, tau, pn, dt_max, cov_every, gap_idx,
                                   xn, xb, usum, ub, ua, ue, wk, B, W, A, T, U)
            if g >= 0:
                ist[IS_GAP] = g
                code = LOOP_GAP
                break
            if imu_t[k] - tau > max_lookback:
                rec[j, REC_STATUS] = STATUS_STALE
                j += 1
                continue
            if k > 0 and imu_t[k] - imu_t[k - 1] > dt_max and imu_t[k - 1] < tau < imu_t[k]:
                rec[j, REC_STATUS] = STATUS_IN_GAP
                j += 1
                continue
            a = uwb_a[j]
            if a < 0:
                a = consec.shape[0] - 1
            force = consec[a] >= reopen_after
            # no rotation, no lever-arm information: Schmidt (consider) update for the lever arm only
            frozen = False
            if gate_lever:
                kk = min(k, rot_ms.shape[0] - 1)
                m0 = rot_mean[kk, 0]
                m1 = rot_mean[kk, 1]
                m2 = rot_mean[kk, 2]
                b0 = x[N_BG]
                b1 = x[N_BG + 1]
                b2 = x[N_BG + 2]
                ms = rot_ms[kk] - 2.0 * (m0 * b0 + m1 * b1 + m2 * b2) + (b0 * b0 + b1 * b1 + b2 * b2)
                rms = math.sqrt(ms) if ms > 0.0 else 0.0
                pv = P[E_BG, E_BG] + P[E_BG + 1, E_BG + 1] + P[E_BG + 2, E_BG + 2]
                if 0.0 > pv:  # Python's max(pv, 0.0), NaN kept
                    pv = 0.0
                frozen = rms - math.sqrt(pv) < lever_min_rate
            mask = mask_frozen if frozen else gain_mask
            lev = tag_lever_err[uwb_tag[j]] if multi else E_L
            o = rec[j]
            if b < 0:
                _range_update_ws(x, P, imu_t, imu_u, imu_um, k, tau, anchors[a], bias_idx[a], uwb_r[j], r_var,
                                 gate, force, robust_kind, robust_c, mask, dt_max, o, lev, uws)
            else:
                _tdoa_update_ws(x, P, imu_t, imu_u, imu_um, k, tau, anchors[a], anchors[b], bias_idx[a],
                                bias_idx[b], uwb_r[j], tdoa_var, gate, force, robust_kind, robust_c, mask, dt_max, o,
                                lev, pair_mat[a, b], uws)
            if o[REC_ACC] > 0:
                if frozen:
                    n_frozen += 1
                if force:
                    # a reopened gate does not prove the filter healthy: keep counting towards divergence
                    ev[n_ev, 0] = j
                    ev[n_ev, 1] = a
                    ev[n_ev, 2] = consec[a]
                    n_ev += 1
                    all_rej += 1
                else:
                    all_rej = 0
                consec[a] = 0
            elif o[REC_STATUS] == UPD_OK:
                consec[a] += 1
                all_rej += 1
            j += 1
            if supervise and all_rej >= all_reject_run:
                ist[IS_DIV] = divergence_code(x, P, max_pos_var, hull_lo, hull_hi, all_rej, all_reject_run)
                code = LOOP_DIVERGED
                break
        elif phase == PHASE_TAIL:
            if record:
                while next_out <= t_out_end:
                    code, k, n_out, next_out = _output_row(
                        x, P, imu_t, imu_u, imu_um, k, pn, dt_max, cov_every, gap_idx, n_out, next_out,
                        out_period, out_t, out_x, out_d, out_P, store_cov, ist, xn, xb, usum, ub, ua, ue, wk, B, W,
                        A, T, U)
                    if code != LOOP_DONE:
                        break
                    if k >= n - 1:
                        break
                if code != LOOP_DONE:
                    break
            phase = PHASE_DONE
        else:
            break
    ist[IS_K] = k
    ist[IS_J] = j
    ist[IS_ALL_REJ] = all_rej
    ist[IS_N_FROZEN] = n_frozen
    ist[IS_N_OUT] = n_out
    ist[IS_PHASE] = phase
    ist[IS_N_EV] = n_ev
    fst[0] = next_out
    return code


refresh_stale_cache(globals(), [_physics])
