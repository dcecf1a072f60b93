"""The reference UWB-IMU model, written once for numbers and for symbols.

Every physical relation of the toolkit (kinematics, IMU, range) is defined here
as a function of an *ops* backend, so the very same lines are evaluated

* numerically with NumPy (simulator, estimator reference, tests), and
* symbolically with CasADi ``SX`` (Lie derivatives of the observability engine).

Fast kernels (numba, vectorised NumPy) elsewhere re-express these relations and
are pinned to them by tests; never edit physics there without editing it here.

Seed 001, section 2:

* kinematics (eq. 4-7): ``p' = v``, ``v' = R(q) a - g``, ``q' = 0.5 Omega(w) q``,
  ``b_a' = n_ba``, ``b_g' = n_bg``, ``p_IU' = 0``, ``t_d' = 0``;
* IMU (eq. 2-3): ``w_m = w + b_g + n_g``, ``a_m = R^T (p'' + g e_z) + b_a + n_a``
  (specific force: at rest the up axis reads +9.81);
* range (eq. 8): ``h = || p_anchor - (p + R(q) p_IU) ||``.

Gravity is ``g = [0, 0, 9.81]`` (world z up); ``v' = R (a_m - b_a) - g``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from uwbimu.models import state as S

GRAVITY = 9.81
#: Gravity vector as it appears in the kinematics, ``v' = R a - G_WORLD``.
G_WORLD = np.array([0.0, 0.0, GRAVITY])


# --------------------------------------------------------------------------
# Backends
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class Ops:
    """Minimal array backend so that one formula serves NumPy and CasADi."""

    name: str
    matrix: Callable[[Sequence[Sequence[Any]]], Any]  # rows -> 2-D matrix
    vector: Callable[[Sequence[Any]], Any]  # items -> column/1-D vector
    concat: Callable[[Sequence[Any]], Any]  # stack vectors end to end
    sqrt: Callable[[Any], Any]
    sumsq: Callable[[Any], Any]
    zeros: Callable[[int], Any]


def _np_vector(items):
    return np.array([np.asarray(i, dtype=float).reshape(()) for i in items])


NUMPY = Ops(
    name="numpy",
    matrix=lambda rows: np.array(rows, dtype=float),
    vector=_np_vector,
    concat=lambda vs: np.concatenate([np.atleast_1d(np.asarray(v, dtype=float)).ravel() for v in vs]),
    sqrt=np.sqrt,
    sumsq=lambda v: float(np.dot(np.ravel(v), np.ravel(v))),
    zeros=lambda n: np.zeros(n),
)


def casadi_ops():
    """The CasADi backend (imported lazily: CasADi is only needed for symbols)."""
    import casadi as ca

    return Ops(
        name="casadi",
        matrix=lambda rows: ca.vertcat(*[ca.horzcat(*r) for r in rows]),
        vector=lambda items: ca.vertcat(*items),
        concat=lambda vs: ca.vertcat(*vs),
        sqrt=ca.sqrt,
        sumsq=ca.sumsqr,
        zeros=lambda n: ca.DM.zeros(n, 1),
    )


def _el(v, i):
    return v[i]


# --------------------------------------------------------------------------
# Elementary relations
# --------------------------------------------------------------------------
def rotation_matrix(q, ops: Ops = NUMPY):
    """``R(q)`` (body -> world) of a Hamilton quaternion ``[qw, qx, qy, qz]``."""
    w, x, y, z = (_el(q, i) for i in range(4))
    return ops.matrix(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quaternion_rate_matrix(q, ops: Ops = NUMPY):
    """``Xi(q)`` (4x3) with ``q' = 0.5 Omega(w) q = 0.5 Xi(q) w`` (body rate ``w``)."""
    w, x, y, z = (_el(q, i) for i in range(4))
    return ops.matrix(
        [
            [-x, -y, -z],
            [w, -z, y],
            [z, w, -x],
            [-y, x, w],
        ]
    )


def gravity(ops: Ops = NUMPY):
    return ops.vector([0.0, 0.0, GRAVITY])


def split_state(x):
    """Return the blocks ``(p, v, q, b_a, b_g, p_IU, t_d)`` of a nominal state."""
    return x[S.P], x[S.V], x[S.Q], x[S.BA], x[S.BG], x[S.PIU], x[S.TD]


# --------------------------------------------------------------------------
# Kinematics (seed eq. 4-7)
# --------------------------------------------------------------------------
def control_affine_fields(x, ops: Ops = NUMPY):
    """Drift and input fields of the kinematics in control-affine form.

    ``x' = f0(x) + F_a(x) a_m + F_w(x) w_m`` with inputs the raw IMU readings
    ``a_m`` (specific force, m/s^2) and ``w_m`` (rate, rad/s), noise-free.

    Returns
    -------
    f0 : (20,) drift field.
    F : (20, 6) input fields, columns ``[a_x, a_y, a_z, w_x, w_y, w_z]``.
    """
    p, v, q, b_a, b_g, p_IU, t_d = split_state(x)
    R = rotation_matrix(q, ops)
    Xi = quaternion_rate_matrix(q, ops)
    g = gravity(ops)
    z3 = ops.zeros(3)
    f0 = ops.concat([v, -(R @ b_a) - g, -0.5 * (Xi @ b_g), z3, z3, z3, ops.zeros(1)])
    zero_rows = lambda n: [[0.0] * 6 for _ in range(n)]  # noqa: E731
    rows = (
        zero_rows(3)
        + [[R[i, 0], R[i, 1], R[i, 2], 0.0, 0.0, 0.0] for i in range(3)]
        + [[0.0, 0.0, 0.0, 0.5 * Xi[i, 0], 0.5 * Xi[i, 1], 0.5 * Xi[i, 2]] for i in range(4)]
        + zero_rows(10)
    )
    F = ops.matrix(rows)
    return f0, F


def continuous_dynamics(x, u, ops: Ops = NUMPY):
    """``x' = f(x, u)`` of seed eq. (4)-(7), noise-free; ``u = [a_m, w_m]`` (6,)."""
    p, v, q, b_a, b_g, p_IU, t_d = split_state(x)
    a_m = u[0:3]
    w_m = u[3:6]
    R = rotation_matrix(q, ops)
    Xi = quaternion_rate_matrix(q, ops)
    z3 = ops.zeros(3)
    vdot = R @ (a_m - b_a) - gravity(ops)
    qdot = 0.5 * (Xi @ (w_m - b_g))
    return ops.concat([v, vdot, qdot, z3, z3, z3, ops.zeros(1)])


# --------------------------------------------------------------------------
# Measurement (seed eq. 8)
# --------------------------------------------------------------------------
def antenna_position(x, ops: Ops = NUMPY):
    """World position of the UWB antenna, ``p + R(q) p_IU``."""
    p, v, q, b_a, b_g, p_IU, t_d = split_state(x)
    return p + rotation_matrix(q, ops) @ p_IU


def range_measurement(x, anchor, ops: Ops = NUMPY):
    """Noise-free range ``|| p_anchor - (p + R(q) p_IU) ||`` [m].

    ``x`` must be the state at the instant of the range *on the IMU clock*,
    i.e. at IMU time ``t_uwb + t_d`` (see :func:`imu_time_of_range`).
    """
    d = anchor - antenna_position(x, ops)
    return ops.sqrt(ops.sumsq(d))


def tdoa_measurement(x, anchor_a, anchor_b, ops: Ops = NUMPY):
    """Noise-free TDoA ``|p_U - p_b| - |p_U - p_a|`` [m] (same clock convention as ranges)."""
    return range_measurement(x, anchor_b, ops) - range_measurement(x, anchor_a, ops)


def imu_time_of_range(t_uwb, t_d):
    """IMU-clock time whose motion a range stamped ``t_uwb`` (UWB clock) observes.

    An IMU sample stamped ``s`` describes the motion at UWB time ``s - t_d``,
    so the motion at UWB time ``t`` is at IMU stamp ``t + t_d``.
    """
    return t_uwb + t_d


def imu_stamp_of_truth(t_truth_uwb, t_d):
    """IMU stamp of a motion sample at UWB time ``t`` (used by the simulator)."""
    return t_truth_uwb + t_d


# --------------------------------------------------------------------------
# IMU model (seed eq. 2-3)
# --------------------------------------------------------------------------
def specific_force(R, acc_world, ops: Ops = NUMPY):
    """Noise-free accelerometer reading ``R^T (p'' + g e_z)`` (body frame)."""
    return R.T @ (acc_world + gravity(ops))


def imu_measurement(q, acc_world, omega_body, b_a, b_g, n_a=0.0, n_g=0.0):
    """IMU readings ``(a_m, w_m)`` for the true motion (NumPy).

    ``a_m = R^T (p'' + g e_z) + b_a + n_a`` and ``w_m = w + b_g + n_g``.
    """
    R = rotation_matrix(np.asarray(q, dtype=float))
    a_m = R.T @ (np.asarray(acc_world, dtype=float) + G_WORLD) + b_a + n_a
    w_m = np.asarray(omega_body, dtype=float) + b_g + n_g
    return a_m, w_m


# --------------------------------------------------------------------------
# Discrete propagation (numeric reference)
# --------------------------------------------------------------------------
def _normalize_q(x):
    x = np.array(x, dtype=float)
    n = np.linalg.norm(x[S.Q])
    x[S.Q] /= n
    return x


def midpoint_inputs(t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """IMU input at the midpoint of every interval, ``(N-1, m)``.

    Lagrange cubic through the four samples around the interval (centred
    inside, one-sided on the first and last interval); exact for inputs that
    are cubic polynomials of time, on any strictly increasing ``t``.  With
    fewer than four samples, the linear average.

    Why not the plain average of the two ends: for a rotating body the
    linear-input error does not cancel (coning); at 200 Hz over 60 s it drifts
    3-90 mm on the simulator's rotating trajectories, against < 0.03 mm with
    the cubic midpoint (``tests/test_sim_integration.py``).
    """
    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    n = len(t)
    if n < 4:
        return 0.5 * (u[:-1] + u[1:])
    k = np.arange(n - 1)
    first = np.clip(k - 1, 0, n - 4)  # index of the first of the 4 nodes
    nodes = first[:, None] + np.arange(4)  # (n-1, 4)
    tn = t[nodes]
    tm = 0.5 * (t[k] + t[k + 1])
    w = np.ones((n - 1, 4))
    for j in range(4):
        for m in range(4):
            if m != j:
                w[:, j] *= (tm - tn[:, m]) / (tn[:, j] - tn[:, m])
    return np.einsum("kj,kjc->kc", w, u[nodes])


def propagate(
    x: np.ndarray, u0: np.ndarray, u1: np.ndarray, dt: float, um: np.ndarray | None = None
) -> np.ndarray:
    """Propagate the nominal state over one IMU interval (noise-free).

    Classical Runge-Kutta 4 on :func:`continuous_dynamics` with the IMU input
    ``u0`` at the start, ``um`` at the middle and ``u1`` at the end of the
    interval.  ``um`` defaults to the average of the ends (linear
    interpolation); :func:`integrate_imu` passes the cubic
    :func:`midpoint_inputs`, which keeps the global drift well below a
    millimetre over a minute at 200 Hz.

    Parameters
    ----------
    x : (20,) nominal state at the start of the interval.
    u0, u1 : (6,) IMU readings ``[a_m, w_m]`` at the start and end [m/s^2, rad/s].
    dt : interval length [s]; may be negative (backward propagation).
    um : (6,) optional IMU reading at the middle of the interval.
    """
    u0 = np.asarray(u0, dtype=float)
    u1 = np.asarray(u1, dtype=float)
    um = 0.5 * (u0 + u1) if um is None else np.asarray(um, dtype=float)
    k1 = continuous_dynamics(x, u0)
    k2 = continuous_dynamics(x + 0.5 * dt * k1, um)
    k3 = continuous_dynamics(x + 0.5 * dt * k2, um)
    k4 = continuous_dynamics(x + dt * k3, u1)
    return _normalize_q(x + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4))


def integrate_imu(x0: np.ndarray, t: np.ndarray, u: np.ndarray, cubic: bool = True) -> np.ndarray:
    """Integrate a whole IMU stream with :func:`propagate`.

    Parameters
    ----------
    x0 : (20,) state at ``t[0]``.
    t : (N,) IMU stamps [s].
    u : (N, 6) IMU readings ``[ax, ay, az, wx, wy, wz]``.
    cubic : mid-interval input from :func:`midpoint_inputs` (default) or the
        linear average of the interval's ends.

    Returns
    -------
    (N, 20) states at each stamp.
    """
    t = np.asarray(t, dtype=float)
    u = np.asarray(u, dtype=float)
    um = midpoint_inputs(t, u) if cubic else 0.5 * (u[:-1] + u[1:])
    out = np.empty((len(t), S.NOMINAL_DIM))
    out[0] = x0
    for k in range(len(t) - 1):
        out[k + 1] = propagate(out[k], u[k], u[k + 1], t[k + 1] - t[k], um[k])
    return out
