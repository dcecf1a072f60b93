"""Numba kernel of the grouped range factor: residuals and Jacobians of :class:`RangeGroup` rows.

:meth:`uwbimu.calibration.range_factor.RangeGroup.evaluate` spends most of its time in NumPy call
overhead (~50 array operations on ~85 rows per call, called once per group and LM evaluation).
:func:`group_rows` does the same arithmetic row by row in one compiled loop; with the tag-side direction
model it also returns each row's geometry, on which the caller adds the (vectorised) direction term.  It is
the model of :func:`uwbimu.calibration.range_factor.range_error` (which is pinned to
:mod:`uwbimu.models.reference` by ``tests/test_calibrate_factor.py``) and is pinned to the NumPy
implementation of ``RangeGroup.evaluate`` by ``tests/test_calibrate_speed.py`` (1e-12), on top of
the finite-difference and per-range tests of ``tests/test_calibrate_factor.py`` that now run through
it.  It calls the 3x3 product of :mod:`uwbimu.models.kernels`, so it ends with that module's
``refresh_stale_cache`` (its disk cache is flushed when that source changes).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from uwbimu.models import kernels as _physics
from uwbimu.models.kernels import _mm3, refresh_stale_cache


@njit(cache=True)
def group_rows(R_k, p_k, v_k, kf, tau, dR, dv, dp, acc, omega, dRacc, anchor, lever, delta, g, jac,
               r_out, Jp, Jv, Jl, Jt, geo, u_out, Rs_out, M_out, v_out, a_out, body_out):
    """Distance ``|p_U - anchor|`` of every row and, with ``jac``, its Jacobians (GTSAM tangents).

    Parameters
    ----------
    R_k, p_k, v_k : (K, 3, 3), (K, 3), (K, 3) keyframe attitudes (body -> world), positions [m] and
        velocities [m/s].
    kf : (N,) int64 keyframe index of every row.
    tau, dR, dv, dp, acc, omega, dRacc : the rows' IMU deltas (:class:`RangeDelta` fields, stacked; ``dRacc``
        = ``dR @ acc``) [s, -, m/s, m, m/s^2, rad/s, m/s^2].
    anchor : (N, 3) anchor positions [m]; lever : (3,) lever arm p_IU [m] (IMU frame).
    delta : ``t_d - td0`` [s]; g : gravity magnitude [m/s^2] (``G_WORLD = [0, 0, g]``).
    r_out : (N,) output distances [m] (the residual is ``r + bias - rho``, added by the caller).
    Jp, Jv, Jl, Jt : (N, 6), (N, 3), (N, 3), (N,) outputs (written only with ``jac``): pose ``[theta, p]``,
        velocity, lever arm, t_d.
    geo : also write every row's geometry (for the tag-side direction term, evaluated by the caller):
    u_out, Rs_out, M_out, v_out, a_out, body_out : (N, 3), (N, 3, 3), (N, 3, 3), (N, 3), (N, 3), (N, 3)
        outputs (written only with ``geo``): ``u = p_U - anchor`` [m] (world), ``R_s`` (body -> world) and
        ``M = dR Exp(omega delta)`` at the range instant, ``v_s0`` [m/s], ``a_s0`` [m/s^2] (world, gravity
        removed) and ``body = dp + delta dv + delta^2/2 dR acc + M lever`` [m] (keyframe body frame).
    """
    E = np.empty((3, 3))
    M = np.empty((3, 3))
    Rs = np.empty((3, 3))
    Rs0 = np.empty((3, 3))
    R = np.empty((3, 3))
    vs = np.empty(3)
    asv = np.empty(3)
    u = np.empty(3)
    for i in range(tau.shape[0]):
        k = kf[i]
        for a in range(3):
            for b in range(3):
                R[a, b] = R_k[k, a, b]
        # E = Exp(omega * delta) (Rodrigues, as so3_exp_batch)
        wx, wy, wz = omega[i, 0] * delta, omega[i, 1] * delta, omega[i, 2] * delta
        th = math.sqrt(wx * wx + wy * wy + wz * wz)
        if th < 1e-8:
            ca, cb = 1.0, 0.5
        else:
            ca, cb = math.sin(th) / th, (1.0 - math.cos(th)) / (th * th)
        # K = [w]x ; K @ K = w w^T - |w|^2 I
        E[0, 0] = 1.0 + cb * (wx * wx - th * th)
        E[1, 1] = 1.0 + cb * (wy * wy - th * th)
        E[2, 2] = 1.0 + cb * (wz * wz - th * th)
        E[0, 1] = -ca * wz + cb * wx * wy
        E[1, 0] = ca * wz + cb * wx * wy
        E[0, 2] = ca * wy + cb * wx * wz
        E[2, 0] = -ca * wy + cb * wx * wz
        E[1, 2] = -ca * wx + cb * wy * wz
        E[2, 1] = ca * wx + cb * wy * wz
        _mm3(dR[i], E, M)
        _mm3(R, M, Rs)
        _mm3(R, dR[i], Rs0)
        t = tau[i]
        for c in range(3):
            gc = g if c == 2 else 0.0
            Rdv = R[c, 0] * dv[i, 0] + R[c, 1] * dv[i, 1] + R[c, 2] * dv[i, 2]
            Rdp = R[c, 0] * dp[i, 0] + R[c, 1] * dp[i, 1] + R[c, 2] * dp[i, 2]
            vs[c] = v_k[k, c] - gc * t + Rdv
            asv[c] = Rs0[c, 0] * acc[i, 0] + Rs0[c, 1] * acc[i, 1] + Rs0[c, 2] * acc[i, 2] - gc
            ps0 = p_k[k, c] + v_k[k, c] * t - 0.5 * gc * t * t + Rdp
            Rl = Rs[c, 0] * lever[0] + Rs[c, 1] * lever[1] + Rs[c, 2] * lever[2]
            u[c] = ps0 + vs[c] * delta + 0.5 * asv[c] * delta * delta + Rl - anchor[i, c]
        u0, u1, u2 = u[0], u[1], u[2]
        r = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        r_out[i] = r
        hd = 0.5 * delta * delta
        if geo:
            for a in range(3):
                u_out[i, a] = u[a]
                v_out[i, a] = vs[a]
                a_out[i, a] = asv[a]
                body_out[i, a] = (dp[i, a] + delta * dv[i, a] + hd * dRacc[i, a]
                                  + M[a, 0] * lever[0] + M[a, 1] * lever[1] + M[a, 2] * lever[2])
                for b in range(3):
                    Rs_out[i, a, b] = Rs[a, b]
                    M_out[i, a, b] = M[a, b]
        if not jac:
            continue
        n0, n1, n2 = u0 / r, u1 / r, u2 / r
        m0 = R[0, 0] * n0 + R[1, 0] * n1 + R[2, 0] * n2
        m1 = R[0, 1] * n0 + R[1, 1] * n1 + R[2, 1] * n2
        m2 = R[0, 2] * n0 + R[1, 2] * n1 + R[2, 2] * n2
        b0 = dp[i, 0] + delta * dv[i, 0] + hd * dRacc[i, 0] + M[0, 0] * lever[0] + M[0, 1] * lever[1] + M[0, 2] * lever[2]
        b1 = dp[i, 1] + delta * dv[i, 1] + hd * dRacc[i, 1] + M[1, 0] * lever[0] + M[1, 1] * lever[1] + M[1, 2] * lever[2]
        b2 = dp[i, 2] + delta * dv[i, 2] + hd * dRacc[i, 2] + M[2, 0] * lever[0] + M[2, 1] * lever[1] + M[2, 2] * lever[2]
        Jp[i, 0] = b1 * m2 - b2 * m1
        Jp[i, 1] = b2 * m0 - b0 * m2
        Jp[i, 2] = b0 * m1 - b1 * m0
        Jp[i, 3] = m0
        Jp[i, 4] = m1
        Jp[i, 5] = m2
        s = t + delta
        Jv[i, 0] = n0 * s
        Jv[i, 1] = n1 * s
        Jv[i, 2] = n2 * s
        for c in range(3):
            Jl[i, c] = Rs[0, c] * n0 + Rs[1, c] * n1 + Rs[2, c] * n2
        # omega x lever, turned by R_s
        ox, oy, oz = omega[i, 0], omega[i, 1], omega[i, 2]
        c0 = oy * lever[2] - oz * lever[1]
        c1 = oz * lever[0] - ox * lever[2]
        c2 = ox * lever[1] - oy * lever[0]
        jt = 0.0
        for c in range(3):
            w = vs[c] + asv[c] * delta + Rs[c, 0] * c0 + Rs[c, 1] * c1 + Rs[c, 2] * c2
            jt += u[c] / r * w
        Jt[i] = jt


@njit(cache=True)
def direction_rows(orders, powers, C, u, Rs, M, vs, asv, body, omega, tau, lever, delta, jac,
                   e, F, Jp, Jv, Jl, Jt, Rg_out):
    """Tag-side direction term of every row on the geometry of :func:`group_rows` (``geo``), added in place.

    The model of :func:`uwbimu.calibration.range_factor.direction_features` and of the direction part of
    ``RangeGroup.evaluate`` (pinned to them by ``tests/test_calibrate_speed.py``, 1e-12).

    Parameters
    ----------
    orders, powers : (n_o,), (n_q,) int64 Fourier orders in body azimuth and powers of the elevation [rad].
    C : (N, P) each row's coefficient vector (P = 2 n_o + n_q) [m, m/rad^q].
    u, Rs, M, vs, asv, body : the rows' geometry from :func:`group_rows` (``geo``).
    omega : (N, 3) [rad/s]; tau : (N,) [s]; lever : (3,) [m]; delta : ``t_d - td0`` [s].
    e : (N,) residuals [m], the term is added; F : (N, P) output features.
    Jp, Jv, Jl, Jt : the range's Jacobians from :func:`group_rows`, the term's derivatives added (with ``jac``).
    Rg_out : (N, 3) output ``R_s dg/dw_b`` (with ``jac``): the term's derivative with respect to the anchor.
    """
    n_o = orders.shape[0]
    P = C.shape[1]
    for i in range(e.shape[0]):
        x = -(Rs[i, 0, 0] * u[i, 0] + Rs[i, 1, 0] * u[i, 1] + Rs[i, 2, 0] * u[i, 2])
        y = -(Rs[i, 0, 1] * u[i, 0] + Rs[i, 1, 1] * u[i, 1] + Rs[i, 2, 1] * u[i, 2])
        z = -(Rs[i, 0, 2] * u[i, 0] + Rs[i, 1, 2] * u[i, 1] + Rs[i, 2, 2] * u[i, 2])
        h2 = max(x * x + y * y, 1e-12)
        az = math.atan2(y, x)
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        for k in range(n_o):
            n = orders[k]
            c, s = math.cos(n * az), math.sin(n * az)
            F[i, 2 * k] = c
            F[i, 2 * k + 1] = s
            daz = -n * s * C[i, 2 * k] + n * c * C[i, 2 * k + 1]  # d(term)/d(az)
            g0 += daz * (-y / h2)
            g1 += daz * (x / h2)
        if powers.shape[0] > 0:
            h = math.sqrt(h2)
            el = math.atan2(z, h)
            r2 = h2 + z * z
            d0, d1, d2 = -x * z / (r2 * h), -y * z / (r2 * h), h / r2
            for k in range(powers.shape[0]):
                q = powers[k]
                F[i, 2 * n_o + k] = el ** q
                de = q * el ** (q - 1) * C[i, 2 * n_o + k]
                g0 += de * d0
                g1 += de * d1
                g2 += de * d2
        term = 0.0
        for p in range(P):
            term += F[i, p] * C[i, p]
        e[i] += term
        if not jac:
            continue
        Mg0 = M[i, 0, 0] * g0 + M[i, 0, 1] * g1 + M[i, 0, 2] * g2
        Mg1 = M[i, 1, 0] * g0 + M[i, 1, 1] * g1 + M[i, 1, 2] * g2
        Mg2 = M[i, 2, 0] * g0 + M[i, 2, 1] * g1 + M[i, 2, 2] * g2
        Rg0 = Rs[i, 0, 0] * g0 + Rs[i, 0, 1] * g1 + Rs[i, 0, 2] * g2
        Rg1 = Rs[i, 1, 0] * g0 + Rs[i, 1, 1] * g1 + Rs[i, 1, 2] * g2
        Rg2 = Rs[i, 2, 0] * g0 + Rs[i, 2, 1] * g1 + Rs[i, 2, 2] * g2
        # z = M w_b + body (see RangeGroup.evaluate for the derivatives of w_b)
        z0 = M[i, 0, 0] * x + M[i, 0, 1] * y + M[i, 0, 2] * z + body[i, 0]
        z1 = M[i, 1, 0] * x + M[i, 1, 1] * y + M[i, 1, 2] * z + body[i, 1]
        z2 = M[i, 2, 0] * x + M[i, 2, 1] * y + M[i, 2, 2] * z + body[i, 2]
        Jp[i, 0] += Mg1 * z2 - Mg2 * z1
        Jp[i, 1] += Mg2 * z0 - Mg0 * z2
        Jp[i, 2] += Mg0 * z1 - Mg1 * z0
        Jp[i, 3] -= Mg0
        Jp[i, 4] -= Mg1
        Jp[i, 5] -= Mg2
        s = tau[i] + delta
        Jv[i, 0] -= Rg0 * s
        Jv[i, 1] -= Rg1 * s
        Jv[i, 2] -= Rg2 * s
        Jl[i, 0] -= g0
        Jl[i, 1] -= g1
        Jl[i, 2] -= g2
        # omega x (w_b + lever)
        a0, a1, a2 = x + lever[0], y + lever[1], z + lever[2]
        o0, o1, o2 = omega[i, 0], omega[i, 1], omega[i, 2]
        c0 = o1 * a2 - o2 * a1
        c1 = o2 * a0 - o0 * a2
        c2 = o0 * a1 - o1 * a0
        Jt[i] -= g0 * c0 + g1 * c1 + g2 * c2 + Rg0 * (vs[i, 0] + asv[i, 0] * delta) \
            + Rg1 * (vs[i, 1] + asv[i, 1] * delta) + Rg2 * (vs[i, 2] + asv[i, 2] * delta)
        Rg_out[i, 0] = Rg0
        Rg_out[i, 1] = Rg1
        Rg_out[i, 2] = Rg2


refresh_stale_cache(globals(), [_physics])
