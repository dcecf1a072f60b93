"""Shared numba physics primitives (one physics layer for every fast kernel).

Everything that re-expresses :mod:`uwbimu.models.reference` for speed lives
here once: rotation from a quaternion, the nominal RK4 step, the error-state
transition and its discretisation (block form and dense form), the error
injection ``x ⊞ dx``, and the range / TDoA measurement Jacobians.  The
estimator (:mod:`uwbimu.estimation.kernels`), the point-mass EKF, the
observability window and the trajectory predictor call these; tests in
``tests/test_models_kernels.py`` and ``tests/test_eskf_jacobians.py`` pin each
of them to the reference model by finite differences.

Public API (all ``@njit``; arrays are float64, outputs written in place)
-----------------------------------------------------------------------
``rotmat(q, R)``                   R (3,3) from Hamilton ``q = [qw, qx, qy, qz]`` (body -> world)
``quat_mul(p, q, out)``            Hamilton product ``out = p ⊗ q``
``quat_exp(theta, out)``           ``Exp(theta)`` rotation vector -> quaternion
``rk4_step(x, u0, u1, dt, out)``   nominal state (20+) over ``dt`` with linear input
``propagate_interval(x, u0, u1, dt, dt_max, out)``  same, sub-stepped to ``dt_max``
``phi_blocks(x, u, dt, B)``        3x3 blocks of the 19-error-state transition (see below)
``error_transition(x, u, dt, Phi)`` dense ``Phi`` (N, N), N >= 19, second order
``cov_step(P, x, u, dt, noise)``   ``P <- Phi P Phi^T + Q`` in place (block sparse, O(N^2)), base 19-state noise
``cov_step_blocks(P, x, u, dt, pn)`` the same with the declared blocks' process-noise tables
``decay_biases(x, dt, pn)``        mean decay of the Gauss-Markov blocks
``inject(x, dx)``                  ``x <- x ⊞ dx`` (right attitude perturbation)
``range_jacobian(xt, u, anchor, bias_idx, delta, h)``  predicted range, ``h`` (N,)
``tdoa_jacobian(xt, u, anchor_a, anchor_b, bias_idx, delta, h, work)``  predicted
                                   ``|p_U-p_b| - |p_U-p_a|``, ``h`` (N,), ``work`` (N,)

Hot-loop forms (no array views, no work arrays: each view or allocation costs numba a reference count
or a ``malloc``): ``_quat_R`` (rotation as a 9-tuple), ``_deriv_s`` / ``_rk4_s`` (dynamics and RK4 step on
scalars and tuples), ``_phi_blocks_s`` (transition blocks from scalars) and ``_cov_step_rows`` (the
covariance step with ``Phi`` applied 15 rows at a time, columns in SIMD lanes), ``_cov_step_sym`` (the
filter's covariance step: only the rows and columns of ``dp, dv, dtheta`` change, the rest is copied by
symmetry; about half the work of ``_cov_step_rows``).  They perform the same floating-point operations in the
same order as the plain forms, so the results are bit-identical (``tests/test_filter_loop.py``,
``tests/test_cov_step_sparse.py``: ``_cov_step_sym`` for a covariance symmetric outside its 9x9 dynamic
block, as the filter's always is).

Layout: nominal ``x`` = ``p v q b_a b_g p_IU t_d`` (20) followed by extra
states; error ``dp dv dtheta db_a db_g dp_IU dt_d`` (19) then extras
(see :mod:`uwbimu.models.state`).  Attitude error is a right perturbation
``q = q_hat ⊗ Exp(dtheta)``.

Error-state dynamics (continuous time, ``a = a_m - b_a``, ``w = w_m - b_g``)::

    dp'     = dv
    dv'     = -R [a]x dtheta - R db_a - R n_a
    dtheta' = -[w]x dtheta - db_g - n_g
    db_a'   = n_ba,  db_g' = n_bg,  dp_IU' = 0,  dt_d' = 0

The transition matrix is its second-order series ``I + F dt + F^2 dt^2 / 2``
(with the exact rotation ``Exp(-w dt)`` for the attitude block).

numba cache across files
------------------------
numba's on-disk cache of a function is validated against the time stamp of
*its own* source file only, so a cached kernel in another module that calls a
primitive here would keep running the old machine code after this file is
edited.  Every module that calls these primitives from cached kernels ends
with ``refresh_stale_cache(globals(), [uwbimu.models.kernels])``: it keys the
cache on a SHA-256 of the dependency sources (stored next to numba's index
files) and flushes that module's cached kernels when the sources changed.
``models/state.py`` and ``models/blocks.py`` are always part of that key: the kernels index the
state by its block offsets (``N_*`` nominal, ``E_*`` error state, ``NOM_SHIFT``) and the blocks'
process-noise codes (``PN_*``), which numba freezes into the machine code as compile-time constants.

Process noise
-------------
The kernels never infer a block from an array length: the IMU densities come as a fixed (4,) array
and every other block's process noise as a row of the :class:`~uwbimu.models.blocks.ProcessNoise`
tables (kind, error / nominal offset, size, ``q``, ``1/tau``) compiled by
``StateLayout.process_noise`` from the declarations in :mod:`uwbimu.models.blocks`.
"""

from __future__ import annotations

import hashlib
import inspect
import math
from pathlib import Path

import numpy as np
from numba import njit

from uwbimu.models import state as _state
from uwbimu.models import blocks as _blocks
from uwbimu.models.blocks import PN_GAUSS_MARKOV, PN_RANDOM_WALK, ProcessNoise
from uwbimu.models.state import (E_BA, E_BG, E_L, E_P, E_TD, E_TH, E_V, ERROR_DIM, N_BA, N_BG, N_L, N_P, N_Q, N_TD,
                                 N_DYN, N_V, NOM_SHIFT, NOMINAL_DIM)

GRAVITY = 9.81  # must equal uwbimu.models.reference.GRAVITY (pinned by a test)


def refresh_stale_cache(module_globals: dict, dependencies) -> bool:
    """Flush a module's numba disk caches when the sources it calls changed.

    Parameters
    ----------
    module_globals : dict
        ``globals()`` of the calling module (its ``@njit(cache=True)`` dispatchers are found there).
    dependencies : iterable of modules
        Modules whose numba functions the caller's kernels call.

    Returns
    -------
    bool
        True when caches were flushed.  Never raises on an unwritable cache
        folder (numba then falls back to its own user-wide cache, which is
        flushed the same way).
    """
    digest = hashlib.sha256()
    # the state layout's offsets and the block declarations' codes are compile-time constants in every
    # kernel: always part of the key
    for mod in [_state, _blocks, *[m for m in dependencies if m not in (_state, _blocks)]]:
        digest.update(Path(inspect.getfile(mod)).read_bytes())
    key = digest.hexdigest()
    dispatchers = [v for v in module_globals.values()
                   if getattr(v, "_cache", None) is not None and hasattr(v._cache, "flush")
                   and getattr(v, "__module__", None) == module_globals.get("__name__")]
    if not dispatchers:
        return False
    try:
        cache_dir = Path(dispatchers[0]._cache.cache_path)
        stamp = cache_dir / (module_globals["__name__"].rsplit(".", 1)[-1] + ".deps.sha256")
        if stamp.exists() and stamp.read_text() == key:
            return False
        for d in dispatchers:
            d._cache.flush()
        cache_dir.mkdir(parents=True, exist_ok=True)
        tmp = stamp.with_suffix(".tmp")
        tmp.write_text(key)
        tmp.replace(stamp)
        return True
    except OSError:
        return False

@njit(cache=True)
def _quat_R(w, x, y, z):
    """Rotation matrix of the quaternion ``(w, x, y, z)`` as the tuple ``(R00, R01, ..., R22)`` (row major)."""
    return (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y))


@njit(cache=True)
def rotmat(q, R):
    """Fill ``R`` (3x3) with the rotation matrix of quaternion ``q`` (w, x, y, z)."""
    r = _quat_R(q[0], q[1], q[2], q[3])
    R[0, 0], R[0, 1], R[0, 2] = r[0], r[1], r[2]
    R[1, 0], R[1, 1], R[1, 2] = r[3], r[4], r[5]
    R[2, 0], R[2, 1], R[2, 2] = r[6], r[7], r[8]


@njit(cache=True)
def _deriv_s(v0, v1, v2, qw, qx, qy, qz, ba0, ba1, ba2, bg0, bg1, bg2, u0, u1, u2, u3, u4, u5):
    """:func:`_deriv` on scalars: velocity, attitude, biases and input in, the 10 derivatives out (a tuple)."""
    ax = u0 - ba0
    ay = u1 - ba1
    az = u2 - ba2
    wx = u3 - bg0
    wy = u4 - bg1
    wz = u5 - bg2
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _quat_R(qw, qx, qy, qz)
    return (v0, v1, v2,
            r00 * ax + r01 * ay + r02 * az,
            r10 * ax + r11 * ay + r12 * az,
            r20 * ax + r21 * ay + r22 * az - GRAVITY,
            0.5 * (-qx * wx - qy * wy - qz * wz),
            0.5 * (qw * wx - qz * wy + qy * wz),
            0.5 * (qz * wx + qw * wy - qx * wz),
            0.5 * (-qy * wx + qx * wy + qw * wz))


@njit(cache=True)
def _deriv(x, u, out):
    """Derivative of the first 10 nominal components (p, v, q) — reference ``continuous_dynamics``."""
    d = _deriv_s(x[N_V], x[N_V + 1], x[N_V + 2], x[N_Q], x[N_Q + 1], x[N_Q + 2], x[N_Q + 3], x[N_BA],
                 x[N_BA + 1], x[N_BA + 2], x[N_BG], x[N_BG + 1], x[N_BG + 2], u[0], u[1], u[2], u[3], u[4], u[5])
    for i in range(10):
        out[i] = d[i]


@njit(cache=True)
def _rk4_core(x, u0, um, u1, dt, out, wk):
    """RK4 step with inputs at start/middle/end; ``wk`` (6, max(10, len(x))) is not used (kept for the
    callers that keep ``um`` in ``wk[0]``).  ``out`` may be ``x``; no allocation."""
    _rk4_s(x, (u0[0], u0[1], u0[2], u0[3], u0[4], u0[5]), (um[0], um[1], um[2], um[3], um[4], um[5]),
           (u1[0], u1[1], u1[2], u1[3], u1[4], u1[5]), dt, out)


# The unrolled integrator (_rk4_s) treats p, v, q as the contiguous block 0:10 of the nominal state.
if (N_P, N_V, N_Q) != (0, 3, 6):  # pragma: no cover - a layout change must revisit _rk4_s
    raise ImportError("models.kernels._rk4_s assumes the nominal state starts with p (0:3), v (3:6), q (6:10)")


@njit(cache=True)
def _rk4_s(x, u0, um, u1, dt, out):
    """The RK4 step of :func:`_rk4_core` with the three inputs as 6-tuples (no array views: the
    compiled filter loop reads them straight from the IMU arrays)."""
    n = x.shape[0]
    b0, b1, b2, b3, b4, b5 = x[N_BA], x[N_BA + 1], x[N_BA + 2], x[N_BG], x[N_BG + 1], x[N_BG + 2]
    # p, v, q are integrated as one unrolled block x[0:10] (checked against models.state at import)
    k1 = _deriv_s(x[3], x[4], x[5], x[6], x[7], x[8], x[9], b0, b1, b2, b3, b4, b5,
                  u0[0], u0[1], u0[2], u0[3], u0[4], u0[5])
    h = 0.5 * dt
    k2 = _deriv_s(x[3] + h * k1[3], x[4] + h * k1[4], x[5] + h * k1[5], x[6] + h * k1[6], x[7] + h * k1[7],
                  x[8] + h * k1[8], x[9] + h * k1[9], b0, b1, b2, b3, b4, b5,
                  um[0], um[1], um[2], um[3], um[4], um[5])
    k3 = _deriv_s(x[3] + h * k2[3], x[4] + h * k2[4], x[5] + h * k2[5], x[6] + h * k2[6], x[7] + h * k2[7],
                  x[8] + h * k2[8], x[9] + h * k2[9], b0, b1, b2, b3, b4, b5,
                  um[0], um[1], um[2], um[3], um[4], um[5])
    k4 = _deriv_s(x[3] + dt * k3[3], x[4] + dt * k3[4], x[5] + dt * k3[5], x[6] + dt * k3[6],
                  x[7] + dt * k3[7], x[8] + dt * k3[8], x[9] + dt * k3[9], b0, b1, b2, b3, b4, b5,
                  u1[0], u1[1], u1[2], u1[3], u1[4], u1[5])
    c = dt / 6.0
    y = (x[0] + c * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]),
         x[1] + c * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1]),
         x[2] + c * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2]),
         x[3] + c * (k1[3] + 2 * k2[3] + 2 * k3[3] + k4[3]),
         x[4] + c * (k1[4] + 2 * k2[4] + 2 * k3[4] + k4[4]),
         x[5] + c * (k1[5] + 2 * k2[5] + 2 * k3[5] + k4[5]),
         x[6] + c * (k1[6] + 2 * k2[6] + 2 * k3[6] + k4[6]),
         x[7] + c * (k1[7] + 2 * k2[7] + 2 * k3[7] + k4[7]),
         x[8] + c * (k1[8] + 2 * k2[8] + 2 * k3[8] + k4[8]),
         x[9] + c * (k1[9] + 2 * k2[9] + 2 * k3[9] + k4[9]))
    for i in range(10, n):
        out[i] = x[i]
    nq = math.sqrt(y[6] ** 2 + y[7] ** 2 + y[8] ** 2 + y[9] ** 2)
    for i in range(6):
        out[i] = y[i]
    out[6] = y[6] / nq
    out[7] = y[7] / nq
    out[8] = y[8] / nq
    out[9] = y[9] / nq


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


@njit(cache=True, inline='always')
def _phi_blocks(x, u, dt, B, W):
    """:func:`phi_blocks`; ``W`` (6, 3, 3) is not used (kept for the callers' signature)."""
    r = _quat_R(x[N_Q], x[N_Q + 1], x[N_Q + 2], x[N_Q + 3])
    _phi_blocks_s(r[0], r[1], r[2], r[3], r[4], r[5], r[6], r[7], r[8], u[0] - x[N_BA], u[1] - x[N_BA + 1],
                  u[2] - x[N_BA + 2], u[3] - x[N_BG], u[4] - x[N_BG + 1], u[5] - x[N_BG + 2], dt, B)


@njit(cache=True)
def _phi_blocks_R(R, a0, a1, a2, w0, w1, w2, dt, B, W):
    """:func:`phi_blocks` from the attitude matrix ``R`` and the bias-corrected specific force ``a`` and
    body rate ``w`` (what :mod:`uwbimu.observability.window` has along a trajectory); ``W`` (6, 3, 3) is
    not used (kept for the callers' signature)."""
    _phi_blocks_s(R[0, 0], R[0, 1], R[0, 2], R[1, 0], R[1, 1], R[1, 2], R[2, 0], R[2, 1], R[2, 2],
                  a0, a1, a2, w0, w1, w2, dt, B)


@njit(cache=True, inline='always')
def _phi_blocks_s(r00, r01, r02, r10, r11, r12, r20, r21, r22, a0, a1, a2, w0, w1, w2, dt, B):
    """The blocks of :func:`phi_blocks` from the attitude matrix ``r..`` and the bias-corrected ``a``, ``w``,
    all in scalars (no array views, no work arrays: ``RA = R [a]x``, ``RAW = RA [w]x``, ``W2 = [w]x^2``
    as 3x3 products written out)."""
    ax00 = 0.0
    ax01 = -a2
    ax02 = a1
    ax10 = a2
    ax11 = 0.0
    ax12 = -a0
    ax20 = -a1
    ax21 = a0
    ax22 = 0.0
    wx00 = 0.0
    wx01 = -w2
    wx02 = w1
    wx10 = w2
    wx11 = 0.0
    wx12 = -w0
    wx20 = -w1
    wx21 = w0
    wx22 = 0.0
    ra00 = r00 * ax00 + r01 * ax10 + r02 * ax20
    ra01 = r00 * ax01 + r01 * ax11 + r02 * ax21
    ra02 = r00 * ax02 + r01 * ax12 + r02 * ax22
    ra10 = r10 * ax00 + r11 * ax10 + r12 * ax20
    ra11 = r10 * ax01 + r11 * ax11 + r12 * ax21
    ra12 = r10 * ax02 + r11 * ax12 + r12 * ax22
    ra20 = r20 * ax00 + r21 * ax10 + r22 * ax20
    ra21 = r20 * ax01 + r21 * ax11 + r22 * ax21
    ra22 = r20 * ax02 + r21 * ax12 + r22 * ax22
    rw00 = ra00 * wx00 + ra01 * wx10 + ra02 * wx20
    rw01 = ra00 * wx01 + ra01 * wx11 + ra02 * wx21
    rw02 = ra00 * wx02 + ra01 * wx12 + ra02 * wx22
    rw10 = ra10 * wx00 + ra11 * wx10 + ra12 * wx20
    rw11 = ra10 * wx01 + ra11 * wx11 + ra12 * wx21
    rw12 = ra10 * wx02 + ra11 * wx12 + ra12 * wx22
    rw20 = ra20 * wx00 + ra21 * wx10 + ra22 * wx20
    rw21 = ra20 * wx01 + ra21 * wx11 + ra22 * wx21
    rw22 = ra20 * wx02 + ra21 * wx12 + ra22 * wx22
    w200 = wx00 * wx00 + wx01 * wx10 + wx02 * wx20
    w201 = wx00 * wx01 + wx01 * wx11 + wx02 * wx21
    w202 = wx00 * wx02 + wx01 * wx12 + wx02 * wx22
    w210 = wx10 * wx00 + wx11 * wx10 + wx12 * wx20
    w211 = wx10 * wx01 + wx11 * wx11 + wx12 * wx21
    w212 = wx10 * wx02 + wx11 * wx12 + wx12 * wx22
    w220 = wx20 * wx00 + wx21 * wx10 + wx22 * wx20
    w221 = wx20 * wx01 + wx21 * wx11 + wx22 * wx21
    w222 = wx20 * wx02 + wx21 * wx12 + wx22 * wx22
    h2 = 0.5 * dt * dt
    B[0, 0, 0], B[0, 0, 1], B[0, 0, 2] = -ra00 * h2, -ra01 * h2, -ra02 * h2
    B[0, 1, 0], B[0, 1, 1], B[0, 1, 2] = -ra10 * h2, -ra11 * h2, -ra12 * h2
    B[0, 2, 0], B[0, 2, 1], B[0, 2, 2] = -ra20 * h2, -ra21 * h2, -ra22 * h2
    B[1, 0, 0], B[1, 0, 1], B[1, 0, 2] = -r00 * h2, -r01 * h2, -r02 * h2
    B[1, 1, 0], B[1, 1, 1], B[1, 1, 2] = -r10 * h2, -r11 * h2, -r12 * h2
    B[1, 2, 0], B[1, 2, 1], B[1, 2, 2] = -r20 * h2, -r21 * h2, -r22 * h2
    B[2, 0, 0], B[2, 0, 1], B[2, 0, 2] = -ra00 * dt + rw00 * h2, -ra01 * dt + rw01 * h2, -ra02 * dt + rw02 * h2
    B[2, 1, 0], B[2, 1, 1], B[2, 1, 2] = -ra10 * dt + rw10 * h2, -ra11 * dt + rw11 * h2, -ra12 * dt + rw12 * h2
    B[2, 2, 0], B[2, 2, 1], B[2, 2, 2] = -ra20 * dt + rw20 * h2, -ra21 * dt + rw21 * h2, -ra22 * dt + rw22 * h2
    B[3, 0, 0], B[3, 0, 1], B[3, 0, 2] = -r00 * dt, -r01 * dt, -r02 * dt
    B[3, 1, 0], B[3, 1, 1], B[3, 1, 2] = -r10 * dt, -r11 * dt, -r12 * dt
    B[3, 2, 0], B[3, 2, 1], B[3, 2, 2] = -r20 * dt, -r21 * dt, -r22 * dt
    B[4, 0, 0], B[4, 0, 1], B[4, 0, 2] = ra00 * h2, ra01 * h2, ra02 * h2
    B[4, 1, 0], B[4, 1, 1], B[4, 1, 2] = ra10 * h2, ra11 * h2, ra12 * h2
    B[4, 2, 0], B[4, 2, 1], B[4, 2, 2] = ra20 * h2, ra21 * h2, ra22 * h2
    B[6, 0, 0], B[6, 0, 1], B[6, 0, 2] = wx00 * h2 - dt, wx01 * h2, wx02 * h2
    B[6, 1, 0], B[6, 1, 1], B[6, 1, 2] = wx10 * h2, wx11 * h2 - dt, wx12 * h2
    B[6, 2, 0], B[6, 2, 1], B[6, 2, 2] = wx20 * h2, wx21 * h2, wx22 * h2 - dt
    # exact Exp(-w dt) for the attitude block (Rodrigues)
    th = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2) * abs(dt)
    if th < 1e-9:
        s1 = -dt
        s2 = h2
    else:
        wn = th / abs(dt)
        s1 = -math.sin(th) / wn * (1.0 if dt > 0 else -1.0)
        s2 = (1 - math.cos(th)) / (wn * wn)
    B[5, 0, 0], B[5, 0, 1], B[5, 0, 2] = s1 * wx00 + s2 * w200 + 1.0, s1 * wx01 + s2 * w201, s1 * wx02 + s2 * w202
    B[5, 1, 0], B[5, 1, 1], B[5, 1, 2] = s1 * wx10 + s2 * w210, s1 * wx11 + s2 * w211 + 1.0, s1 * wx12 + s2 * w212
    B[5, 2, 0], B[5, 2, 1], B[5, 2, 2] = s1 * wx20 + s2 * w220, s1 * wx21 + s2 * w221, s1 * wx22 + s2 * w222 + 1.0


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
def phi_left_R(M, R, f, w, dt, B, W, col):
    """In place ``M <- Phi M`` on the rows 0:15 of an error-state matrix (any number of columns).

    ``Phi`` is the error-state transition over ``dt`` at attitude ``R`` with the bias-corrected specific
    force ``f`` and body rate ``w`` (:func:`_phi_blocks_R`); ``B`` (7,3,3), ``W`` (6,3,3) and ``col``
    (>= 15,) are work arrays.  Used by the observability windows, which have the motion as attitude
    matrices."""
    _phi_blocks_R(R, f[0], f[1], f[2], w[0], w[1], w[2], dt, B, W)
    for c in range(M.shape[1]):
        for i in range(N_DYN):
            col[i] = M[i, c]
        _phi_vec(B, dt, col)
        for i in range(N_DYN):
            M[i, c] = col[i]


@njit(cache=True)
def _cov_step(P, x, u, dt, pn, B, W, col):
    """:func:`cov_step_blocks` with work arrays (B (7,3,3), W (6,3,3), col (N,))."""
    N = P.shape[0]
    _phi_blocks(x, u, dt, B, W)
    # left multiplication: columns
    for c in range(N):
        for i in range(N_DYN):
            col[i] = P[i, c]
        _phi_vec(B, dt, col)
        for i in range(N_DYN):
            P[i, c] = col[i]
    # right multiplication: rows
    for r in range(N):
        for i in range(N_DYN):
            col[i] = P[r, i]
        _phi_vec(B, dt, col)
        for i in range(N_DYN):
            P[r, i] = col[i]
    _add_process_noise(P, dt, pn)


@njit(cache=True, inline='always')
def _add_process_noise(P, dt, pn):
    """The process-noise part of :func:`cov_step`: ``P <- P + Q`` over ``dt``, read from the tables ``pn``
    (:class:`~uwbimu.models.blocks.ProcessNoise`): the IMU densities drive p, v, theta, b_a, b_g (Van Loan
    to leading order); then each declared block by its kind (random walk: ``q |dt|`` on the diagonal;
    Gauss-Markov: rows and columns scaled by ``exp(-|dt| / tau)``, ``q (1 - f^2)`` added; constant: none).
    """
    N = P.shape[0]
    adt = abs(dt)
    imu = pn.imu
    # each increment evaluated once (the same expressions, so the same bits): a store into P could alias
    # pn.imu, so the compiler would otherwise reload and recompute them for every i
    qpp = imu[0] * adt**3 / 3.0
    qpv = imu[0] * adt**2 / 2.0
    qvv = imu[0] * adt
    qth = imu[1] * adt
    qba = imu[2] * adt
    qbg = imu[3] * adt
    for i in range(3):
        P[E_P + i, E_P + i] += qpp
        P[E_P + i, E_V + i] += qpv
        P[E_V + i, E_P + i] += qpv
        P[E_V + i, E_V + i] += qvv
        P[E_TH + i, E_TH + i] += qth
        P[E_BA + i, E_BA + i] += qba
        P[E_BG + i, E_BG + i] += qbg
    for blk in range(pn.kind.shape[0]):
        kind = pn.kind[blk]
        r0 = pn.err0[blk]
        r1 = r0 + pn.size[blk]
        q = pn.q[blk]
        if kind == PN_RANDOM_WALK:
            for r in range(r0, r1):
                P[r, r] += q * adt
        elif kind == PN_GAUSS_MARKOV and pn.inv_tau[blk] > 0.0:
            # first-order Gauss-Markov (b' = -b / tau + w, stationary variance q):
            # Phi_bb = exp(-|dt| / tau) I, Q_bb = q (1 - Phi_bb^2)
            f = math.exp(-adt * pn.inv_tau[blk])
            for r in range(r0, r1):
                for c in range(N):
                    P[r, c] *= f
                    P[c, r] *= f
                P[r, r] += q * (1.0 - f * f)


@njit(cache=True, inline="always")
def _phi_dyn_rows(M, O, B, dt):
    """``O[0:9] <- (Phi M)[0:9]`` for every column of ``M``: the rows of ``Phi`` that differ from the
    identity (``p, v, theta``), blocks ``B``, columns in SIMD lanes.  The one copy of this arithmetic
    (:func:`_phi_rows`, :func:`_cov_step_sym`)."""
    nc = M.shape[1]
    for i in range(3):
        a0 = B[0, i, 0]
        a1 = B[0, i, 1]
        a2 = B[0, i, 2]
        a3 = B[1, i, 0]
        a4 = B[1, i, 1]
        a5 = B[1, i, 2]
        v0 = B[2, i, 0]
        v1 = B[2, i, 1]
        v2 = B[2, i, 2]
        v3 = B[3, i, 0]
        v4 = B[3, i, 1]
        v5 = B[3, i, 2]
        v6 = B[4, i, 0]
        v7 = B[4, i, 1]
        v8 = B[4, i, 2]
        s0 = B[5, i, 0]
        s1 = B[5, i, 1]
        s2 = B[5, i, 2]
        s3 = B[6, i, 0]
        s4 = B[6, i, 1]
        s5 = B[6, i, 2]
        for c in range(nc):
            xt0 = M[6, c]
            xt1 = M[7, c]
            xt2 = M[8, c]
            xa0 = M[9, c]
            xa1 = M[10, c]
            xa2 = M[11, c]
            xg0 = M[12, c]
            xg1 = M[13, c]
            xg2 = M[14, c]
            sp = a0 * xt0 + a1 * xt1 + a2 * xt2 + a3 * xa0 + a4 * xa1 + a5 * xa2
            sv = (v0 * xt0 + v1 * xt1 + v2 * xt2 + v3 * xa0 + v4 * xa1 + v5 * xa2
                  + v6 * xg0 + v7 * xg1 + v8 * xg2)
            st = s0 * xt0 + s1 * xt1 + s2 * xt2 + s3 * xg0 + s4 * xg1 + s5 * xg2
            O[i, c] = M[i, c] + (dt * M[3 + i, c] + sp)
            O[6 + i, c] = st
            O[3 + i, c] = M[3 + i, c] + sv


@njit(cache=True)
def _phi_rows(M, O, B, dt):
    """``O[0:15] <- Phi M[0:15]`` for every column of ``M`` (block-sparse ``Phi``, blocks ``B``); ``O`` is
    another array of the same shape.

    Element for element the same arithmetic, in the same order, as :func:`_phi_vec` applied to each
    column (so the results are bit-identical), arranged row by row so that the compiler runs the
    columns in SIMD lanes."""
    _phi_dyn_rows(M, O, B, dt)
    nc = M.shape[1]
    for r in range(E_BA, N_DYN):
        for c in range(nc):
            O[r, c] = M[r, c]


@njit(cache=True)
def _cov_step_rows(P, x, u, dt, pn, B, W, A, T, U):
    """:func:`cov_step_blocks` arranged for SIMD: bit-identical to :func:`_cov_step` (the same operations on
    every element, in the same order), faster.

    ``A = (Phi P)[0:15]`` by rows (:func:`_phi_rows`), then ``(Phi P) Phi^T`` as ``Phi`` applied to the
    transpose ``T`` of its first 15 columns (into ``U``).  Work arrays: ``B`` (7, 3, 3), ``W`` (6, 3, 3),
    ``A``, ``T``, ``U`` (N_DYN, N)."""
    N = P.shape[0]
    _phi_blocks(x, u, dt, B, W)
    _phi_rows(P, A, B, dt)
    for r in range(N_DYN):
        for c in range(N_DYN):
            T[c, r] = A[r, c]
    for r in range(N_DYN, N):
        for c in range(N_DYN):
            T[c, r] = P[r, c]
    _phi_rows(T, U, B, dt)
    for r in range(N):
        for c in range(N_DYN):
            P[r, c] = U[c, r]
    for r in range(N_DYN):
        for c in range(N_DYN, N):
            P[r, c] = A[r, c]
    _add_process_noise(P, dt, pn)


@njit(cache=True, inline='always')
def _cov_step_sym(P, x, u, dt, pn, B, A):
    """:func:`cov_step_blocks` for a covariance ``P`` that is symmetric outside its top-left 9x9 block (the
    rows and columns of ``dp, dv, dtheta``), as the filter's always is: bit-identical to :func:`_cov_step`
    there, at about a third of the work.

    Only the rows ``p, v, theta`` of ``Phi`` differ from the identity, so ``Phi P Phi^T`` changes only the
    rows and columns ``0:9``: ``A = Phi[0:9] P`` (9 x N, columns in SIMD lanes, the arithmetic of
    :func:`_phi_rows`) gives the rows ``0:9`` beyond column 9, and by symmetry the columns; the 9x9 block is
    ``Phi[0:9] A[:, 0:15]^T``, evaluated element for element as :func:`_cov_step`'s right multiplication
    (hence not mirrored: its rounding may leave that block asymmetric by an ulp, which the next step
    tolerates).  Rows and columns ``15:`` are never read by ``Phi``'s non-identity part beyond the
    ``A`` pass.  Work arrays: ``B`` (7, 3, 3), ``A`` (>= 9, N).  No allocation."""
    N = P.shape[0]
    _phi_blocks(x, u, dt, B, B)
    _phi_dyn_rows(P, A, B, dt)
    # rows / columns 0:9 beyond column 9: (Phi P)[0:9, c] (the identity rows of Phi leave them as they are);
    # written out per column (as loops the compiler turns the transposed stores into slow scatters)
    for c in range(9, N):
        v0 = A[0, c]
        v1 = A[1, c]
        v2 = A[2, c]
        v3 = A[3, c]
        v4 = A[4, c]
        v5 = A[5, c]
        v6 = A[6, c]
        v7 = A[7, c]
        v8 = A[8, c]
        P[0, c] = v0
        P[1, c] = v1
        P[2, c] = v2
        P[3, c] = v3
        P[4, c] = v4
        P[5, c] = v5
        P[6, c] = v6
        P[7, c] = v7
        P[8, c] = v8
        P[c, 0] = v0
        P[c, 1] = v1
        P[c, 2] = v2
        P[c, 3] = v3
        P[c, 4] = v4
        P[c, 5] = v5
        P[c, 6] = v6
        P[c, 7] = v7
        P[c, 8] = v8
    # the 9x9 block: row r of (Phi P) Phi^T is Phi applied to A[r, 0:15] (as _phi_vec does): the same
    # arithmetic on the transposed views
    _phi_dyn_rows(A[0:9, 0:N_DYN].T, P[0:9, 0:9].T, B, dt)
    _add_process_noise(P, dt, pn)


@njit(cache=True)
def base_process_noise(noise):
    """The tables of the base 19-state for the six densities ``noise`` =
    ``[s_a^2, s_g^2, s_ba^2, s_bg^2, s_piu^2, s_td^2]`` (IMU white noises and bias random walks, lever-arm
    and time-offset random walks): extra states beyond index 18 constant."""
    return ProcessNoise(noise[0:4].copy(), np.array([PN_RANDOM_WALK, PN_RANDOM_WALK]), np.array([E_L, E_TD]),
                        np.array([N_L, N_TD]), np.array([3, 1]), np.array([noise[4], noise[5]]), np.zeros(2))


@njit(cache=True)
def cov_step(P, x, u, dt, noise):
    """``P <- Phi P Phi^T + Q`` over ``dt`` (in place, full covariance) for the base 19-state densities.

    ``noise`` (6,) = ``[s_a^2, s_g^2, s_ba^2, s_bg^2, s_piu^2, s_td^2]``: continuous densities squared
    (accel, gyro white noise; bias, lever-arm and time-offset random walks); further error states
    (N > 19) are constant.  :func:`cov_step_blocks` takes the declared blocks' tables instead.
    ``Q`` is the Van Loan expansion to the leading order of each block (``pp = s_a^2 dt^3/3``,
    ``pv = s_a^2 dt^2/2``, ``vv = s_a^2 dt``, ...).
    """
    _cov_step(P, x, u, dt, base_process_noise(noise), np.empty((7, 3, 3)), np.empty((6, 3, 3)),
              np.empty(P.shape[0]))


@njit(cache=True)
def cov_step_blocks(P, x, u, dt, pn):
    """:func:`cov_step` with the process noise of the declared blocks: ``pn`` a
    :class:`~uwbimu.models.blocks.ProcessNoise` (``StateLayout.process_noise``)."""
    _cov_step(P, x, u, dt, pn, np.empty((7, 3, 3)), np.empty((6, 3, 3)), np.empty(P.shape[0]))


@njit(cache=True)
def decay_biases(x, dt, pn):
    """Mean of the Gauss-Markov blocks of ``pn`` over ``dt``: ``b <- exp(-|dt| / tau) b`` (no-op when
    there are none or ``1/tau = 0``)."""
    for blk in range(pn.kind.shape[0]):
        if pn.kind[blk] == PN_GAUSS_MARKOV and pn.inv_tau[blk] > 0.0:
            f = math.exp(-abs(dt) * pn.inv_tau[blk])
            for i in range(pn.nom0[blk], pn.nom0[blk] + pn.size[blk]):
                x[i] *= f


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
    # scalars only (no work arrays: the filter calls this for every range), the same operations as with
    # the matrix R
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = _quat_R(xt[N_Q], xt[N_Q + 1], xt[N_Q + 2], xt[N_Q + 3])
    l0, l1, l2 = xt[N_L], xt[N_L + 1], xt[N_L + 2]
    w0 = u_tau[3] - xt[N_BG]
    w1 = u_tau[4] - xt[N_BG + 1]
    w2 = u_tau[5] - xt[N_BG + 2]
    # w x l (body)
    c0 = w1 * l2 - w2 * l1
    c1 = w2 * l0 - w0 * l2
    c2 = w0 * l1 - w1 * l0
    pu0 = xt[N_P] + r00 * l0 + r01 * l1 + r02 * l2
    pu1 = xt[N_P + 1] + r10 * l0 + r11 * l1 + r12 * l2
    pu2 = xt[N_P + 2] + r20 * l0 + r21 * l1 + r22 * l2
    vel0 = xt[N_V] + r00 * c0 + r01 * c1 + r02 * c2
    vel1 = xt[N_V + 1] + r10 * c0 + r11 * c1 + r12 * c2
    vel2 = xt[N_V + 2] + r20 * c0 + r21 * c1 + r22 * c2
    d0 = anchor[0] - pu0
    d1 = anchor[1] - pu1
    d2 = anchor[2] - pu2
    rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if rho < 1e-9:
        rho = 1e-9
    un0 = d0 / rho
    un1 = d1 / rho
    un2 = d2 / rho
    for i in range(h.shape[0]):
        h[i] = 0.0
    uR0 = un0 * r00 + un1 * r10 + un2 * r20
    uR1 = un0 * r01 + un1 * r11 + un2 * r21
    uR2 = un0 * r02 + un1 * r12 + un2 * r22
    # u^T R [l]x
    hth0 = uR1 * l2 - uR2 * l1
    hth1 = uR2 * l0 - uR0 * l2
    hth2 = uR0 * l1 - uR1 * l0
    h[E_P] = -un0
    h[E_P + 1] = -un1
    h[E_P + 2] = -un2
    h[E_L] = -uR0
    h[E_L + 1] = -uR1
    h[E_L + 2] = -uR2
    h[E_TD] = -(un0 * vel0 + un1 * vel1 + un2 * vel2)
    # time mapping tau -> filter time
    h[E_V] = delta * un0
    h[E_V + 1] = delta * un1
    h[E_V + 2] = delta * un2
    # (H_th [w]x)_j = sum_i hth_i Wx[i, j];  row vector times skew = -(w x hth)^T ... computed explicitly
    g0 = hth1 * w2 - hth2 * w1
    g1 = hth2 * w0 - hth0 * w2
    g2 = hth0 * w1 - hth1 * w0
    h[E_TH] = hth0 + delta * g0
    h[E_TH + 1] = hth1 + delta * g1
    h[E_TH + 2] = hth2 + delta * g2
    h[E_BG] = delta * hth0
    h[E_BG + 1] = delta * hth1
    h[E_BG + 2] = delta * hth2
    bias = 0.0
    if bias_idx >= 0:
        h[bias_idx] = 1.0
        bias = xt[bias_idx + NOM_SHIFT]  # additive blocks sit NOM_SHIFT further in the nominal state
    return rho + bias


@njit(cache=True)
def inject(x, dx):
    """``x <- x ⊞ dx`` for the extended state (right attitude perturbation)."""
    for i in range(6):  # p, v: additive (E_P, E_V == N_P, N_V)
        x[N_P + i] += dx[E_P + i]
    t0, t1, t2 = dx[E_TH], dx[E_TH + 1], dx[E_TH + 2]
    th = math.sqrt(t0 * t0 + t1 * t1 + t2 * t2)
    if th < 1e-8:
        k = 0.5 - th * th / 48.0
        dw = math.cos(0.5 * th)
    else:
        k = math.sin(0.5 * th) / th
        dw = math.cos(0.5 * th)
    dq0, dq1, dq2, dq3 = dw, k * t0, k * t1, k * t2
    pw, px, py, pz = x[N_Q], x[N_Q + 1], x[N_Q + 2], x[N_Q + 3]
    qw = pw * dq0 - px * dq1 - py * dq2 - pz * dq3
    qx = pw * dq1 + px * dq0 + py * dq3 - pz * dq2
    qy = pw * dq2 - px * dq3 + py * dq0 + pz * dq1
    qz = pw * dq3 + px * dq2 - py * dq1 + pz * dq0
    n = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
    x[N_Q] = qw / n
    x[N_Q + 1] = qx / n
    x[N_Q + 2] = qy / n
    x[N_Q + 3] = qz / n
    for i in range(E_BA, dx.shape[0]):  # every block after the attitude is additive, NOM_SHIFT further on
        x[i + NOM_SHIFT] += dx[i]


@njit(cache=True)
def quat_mul(p, q, out):
    """Hamilton product ``out = p ⊗ q`` ([qw, qx, qy, qz])."""
    pw, px, py, pz = p[0], p[1], p[2], p[3]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    out[0] = pw * qw - px * qx - py * qy - pz * qz
    out[1] = pw * qx + px * qw + py * qz - pz * qy
    out[2] = pw * qy - px * qz + py * qw + pz * qx
    out[3] = pw * qz + px * qy - py * qx + pz * qw


@njit(cache=True)
def quat_exp(theta, out):
    """``out = Exp(theta)``: rotation vector [rad] to unit quaternion."""
    th = math.sqrt(theta[0] ** 2 + theta[1] ** 2 + theta[2] ** 2)
    if th < 1e-8:
        k = 0.5 - th * th / 48.0
    else:
        k = math.sin(0.5 * th) / th
    out[0] = math.cos(0.5 * th)
    out[1] = k * theta[0]
    out[2] = k * theta[1]
    out[3] = k * theta[2]


@njit(cache=True)
def error_transition(x, u, dt, Phi):
    """Dense error-state transition ``Phi`` (N, N), N >= 19, over ``dt`` [s].

    Same blocks as :func:`phi_blocks` (second-order series, exact attitude
    rotation); states beyond index 14 (lever arm, time offset, extras) are
    constant (identity rows).  For callers that need the full matrix (the
    observability window, the trajectory predictor).
    """
    B = np.empty((7, 3, 3))
    phi_blocks(x, u, dt, B)
    N = Phi.shape[0]
    for i in range(N):
        for j in range(N):
            Phi[i, j] = 0.0
        Phi[i, i] = 1.0
    for i in range(3):
        Phi[i, 3 + i] = dt
        for j in range(3):
            Phi[i, 6 + j] = B[0, i, j]
            Phi[i, 9 + j] = B[1, i, j]
            Phi[3 + i, 6 + j] = B[2, i, j]
            Phi[3 + i, 9 + j] = B[3, i, j]
            Phi[3 + i, 12 + j] = B[4, i, j]
            Phi[6 + i, 6 + j] = B[5, i, j]
            Phi[6 + i, 12 + j] = B[6, i, j]


@njit(cache=True)
def tdoa_jacobian(xt, u_tau, anchor_a, anchor_b, bias_idx, delta, h, work):
    """Predicted TDoA ``|p_U - p_b| - |p_U - p_a|`` [m] and its Jacobian ``h`` (N,).

    Difference of two :func:`range_jacobian` rows (same time mapping
    ``delta = t_filter - tau``); ``bias_idx`` >= 0 adds a per-pair bias state
    (error index; nominal index ``bias_idx + NOM_SHIFT``).  ``work`` (N,) is scratch.
    """
    ra = range_jacobian(xt, u_tau, anchor_a, -1, delta, work)
    rb = range_jacobian(xt, u_tau, anchor_b, -1, delta, h)
    for i in range(h.shape[0]):
        h[i] -= work[i]
    pred = rb - ra
    if bias_idx >= 0:
        h[bias_idx] = 1.0
        pred += xt[bias_idx + NOM_SHIFT]
    return pred



@njit(cache=True)
def _range_jacobians_batch(p, v, q, omega, lever, anchors, H, h):
    # one call of the estimator's range_jacobian per row (no time mapping, no bias)
    xt = np.zeros(NOMINAL_DIM)
    u = np.zeros(6)
    for m in range(p.shape[0]):
        for i in range(3):
            xt[N_P + i] = p[m, i]
            xt[N_V + i] = v[m, i]
            xt[N_L + i] = lever[i]
            u[3 + i] = omega[m, i]
        for i in range(4):
            xt[N_Q + i] = q[m, i]
        h[m] = range_jacobian(xt, u, anchors[m], -1, 0.0, H[m])


def range_jacobians(p, v, q, omega, lever, anchors):
    """Ranges and their Jacobians w.r.t. the 19-dim error state along a trajectory (batched).

    The estimator's :func:`range_jacobian` evaluated row by row (no time mapping, no bias), so the
    observability windows and the manoeuvre predictor use the very Jacobian the filter uses.

    Parameters
    ----------
    p, v : (M, 3) IMU position / velocity at the ranges' instants (world) [m, m/s].
    q : (M, 4) attitude quaternions ``[qw, qx, qy, qz]`` (body -> world).
    omega : (M, 3) body rate ``w_m - b_g`` [rad/s].
    lever : (3,) ``p_IU`` [m]; anchors : (M, 3) anchor of each range [m].

    Returns
    -------
    h : (M,) predicted ranges [m]; H : (M, 19) ``d h / d dx`` (``t_d`` column: ``d h / d t_d`` of a
    range that observes the motion at IMU time ``t + t_d``).
    """
    p = np.ascontiguousarray(p, dtype=float)
    M = p.shape[0]
    H = np.zeros((M, ERROR_DIM))
    h = np.zeros(M)
    _range_jacobians_batch(p, np.ascontiguousarray(v, dtype=float), np.ascontiguousarray(q, dtype=float),
                           np.ascontiguousarray(omega, dtype=float), np.ascontiguousarray(lever, dtype=float),
                           np.ascontiguousarray(anchors, dtype=float), H, h)
    return h, H

# this module's own kernels inline the state layout's offsets (models/state.py)
refresh_stale_cache(globals(), [])
