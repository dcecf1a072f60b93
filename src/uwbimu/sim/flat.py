"""Multirotor attitude by differential flatness (the flat outputs: position and yaw).

A multirotor's only translational force besides gravity is the thrust along
its body z axis, so the specific force ``a + g e_z`` (world, ``g`` =
:data:`uwbimu.models.reference.GRAVITY`) fixes the body z axis::

    z_b = T / |T|,   T = a + g e_z      (T: thrust per unit mass [m/s^2])

and the yaw ``psi`` (the Z-Y-X Euler yaw of :mod:`uwbimu.sim.trajectory`)
fixes the rotation about it.  With ``t = Rz(-psi) z_b = [sin th cos phi,
-sin phi, cos th cos phi]`` the roll and pitch are ``phi = -asin t_y``,
``th = atan2(t_x, t_z)``.  The rates follow from the jerk ``j = a'``:
``z_b' = (I - z_b z_b^T) j / |T|``, ``t' = Rz(-psi) (z_b' - psi' e_z x z_b)``,
so a drag-free accelerometer on this body reads ``(0, 0, |T|)`` exactly and
the gyro the body rate of these Euler angles.

:class:`FlatSplineTrajectory` is the simulator trajectory of a waypoint file
flown by a multirotor: quintic splines through the positions and the yaw (as
:class:`uwbimu.sim.trajectory.SplineTrajectory`), roll and pitch from the
flatness map of the position spline's acceleration and jerk.  Scenario YAML:
``trajectory: {type: file, path: F.csv, attitude: flat}``.
"""

from __future__ import annotations

from uwbimu.errors import InputError
import numpy as np

from uwbimu.models.reference import GRAVITY
from uwbimu.sim.trajectory import Trajectory


def flat_attitude(a: np.ndarray, jerk: np.ndarray, yaw: np.ndarray, yaw_rate: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Euler angles and rates of the multirotor whose thrust gives acceleration ``a``.

    Parameters
    ----------
    a, jerk : (N, 3) acceleration [m/s^2] and its derivative [m/s^3] (world).
    yaw, yaw_rate : (N,) Z-Y-X Euler yaw [rad] and its rate [rad/s].

    Returns
    -------
    euler : (N, 3) roll, pitch, yaw [rad]; euler_rate : (N, 3) [rad/s];
    thrust : (N,) ``|a + g e_z|`` [m/s^2] (mass-normalised collective thrust).

    Raises
    ------
    ValueError where the thrust is not upward enough to define an attitude
    (``T_z <= 0``: tilt of 90 degrees or more, or free fall).
    """
    a = np.atleast_2d(np.asarray(a, dtype=float))
    j = np.atleast_2d(np.asarray(jerk, dtype=float))
    psi = np.asarray(yaw, dtype=float).reshape(-1)
    dpsi = np.asarray(yaw_rate, dtype=float).reshape(-1)
    T = a + np.array([0.0, 0.0, GRAVITY])
    if np.any(T[:, 2] <= 0):
        k = int(np.flatnonzero(T[:, 2] <= 0)[0])
        raise InputError(f"thrust a + g e_z = {T[k].round(3).tolist()} m/s^2 at sample {k} is not upward: no multirotor attitude")
    n = np.linalg.norm(T, axis=1)
    z = T / n[:, None]
    zd = (j - np.sum(z * j, axis=1)[:, None] * z) / n[:, None]
    # psi' e_z x z_b
    ez_x_z = np.stack([-z[:, 1], z[:, 0], np.zeros_like(n)], axis=1)
    c, s = np.cos(psi), np.sin(psi)

    def rz_minus(v):  # Rz(-psi) v
        return np.stack([c * v[:, 0] + s * v[:, 1], -s * v[:, 0] + c * v[:, 1], v[:, 2]], axis=1)

    tv = rz_minus(z)
    td = rz_minus(zd - dpsi[:, None] * ez_x_z)
    ty = np.clip(tv[:, 1], -1.0, 1.0)
    phi = -np.arcsin(ty)
    th = np.arctan2(tv[:, 0], tv[:, 2])
    dphi = -td[:, 1] / np.sqrt(np.maximum(1.0 - ty * ty, 1e-300))
    dth = (tv[:, 2] * td[:, 0] - tv[:, 0] * td[:, 2]) / (tv[:, 0] ** 2 + tv[:, 2] ** 2)
    return np.stack([phi, th, psi], axis=1), np.stack([dphi, dth, dpsi], axis=1), n


class FlatSplineTrajectory(Trajectory):
    """Waypoints flown by a multirotor: position and yaw splines, roll/pitch by flatness.

    Parameters
    ----------
    t : (N,) waypoint times [s], strictly increasing, ``t[0] = 0``.
    p : (N, 3) positions [m].
    yaw : (N,) continuous (unwrapped) Z-Y-X yaw [rad].

    The splines are those of :class:`uwbimu.sim.trajectory.SplineTrajectory`
    (quintic, at rest at both ends, held at rest outside the span).  The
    attitude waypoints' roll and pitch, if any, are not used: the thrust
    direction decides them.
    """

    def __init__(self, t: np.ndarray, p: np.ndarray, yaw: np.ndarray):
        from scipy.interpolate import make_interp_spline

        t = np.asarray(t, dtype=float)
        self.t0, self.t1 = float(t[0]), float(t[-1])
        bc3 = ([(1, np.zeros(3)), (2, np.zeros(3))], [(1, np.zeros(3)), (2, np.zeros(3))])
        bc1 = ([(1, np.zeros(1)), (2, np.zeros(1))], [(1, np.zeros(1)), (2, np.zeros(1))])
        self._p = make_interp_spline(t, np.asarray(p, dtype=float), k=5, bc_type=bc3)
        self._y = make_interp_spline(t, np.asarray(yaw, dtype=float).reshape(-1, 1), k=5, bc_type=bc1)
        self._v, self._a, self._j = (self._p.derivative(k) for k in (1, 2, 3))
        self._yd = self._y.derivative(1)
        self.natural_duration = self.t1 - self.t0

    def _inside(self, t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.clip(t, self.t0, self.t1), ((t > self.t0) & (t < self.t1))[:, None]

    def position(self, t):
        tc, moving = self._inside(t)
        return self._p(tc), np.where(moving, self._v(tc), 0.0), np.where(moving, self._a(tc), 0.0)

    def euler(self, t):
        tc, moving = self._inside(t)
        a = np.where(moving, self._a(tc), 0.0)
        j = np.where(moving, self._j(tc), 0.0)
        yaw = self._y(tc)[:, 0]
        dyaw = np.where(moving[:, 0], self._yd(tc)[:, 0], 0.0)
        e, ed, _ = flat_attitude(a, j, yaw, dyaw)
        return e, ed
