"""Trajectories with analytic derivatives (the truth of the simulator).

Every trajectory maps UWB-clock time ``t`` [s] to the pose of the IMU frame
and its exact derivatives:

* position ``p`` [m], velocity ``v`` [m/s], acceleration ``a`` [m/s^2] (world);
* attitude quaternion ``q`` (Hamilton ``[qw, qx, qy, qz]``, body -> world);
* body angular velocity ``w`` [rad/s] (IMU frame).

Attitude is built from Z-Y-X Euler angles (yaw ``psi``, pitch ``theta``,
roll ``phi``; ``R = Rz(psi) Ry(theta) Rx(phi)``) whose first derivatives are
known in closed form, so the body rate follows *exactly* from the Euler rates
(:func:`euler_rates_to_body_rate`).  Constant Euler angles give exactly zero
angular velocity.

Two families are implemented:

* :class:`SinusoidTrajectory` -- each position / Euler channel is
  ``c0 + c1 tau + sum_i A_i sin(2 pi f_i tau + phi_i)`` of a *soft-start warped
  time* ``tau(t)`` (:func:`soft_start`): the vehicle is at rest for ``t <= 0``
  and smoothly reaches full speed after ``ramp`` seconds.  Hover, circle,
  figure-8, Lissajous, random, translation and rotation are all of this form.
* :class:`SplineTrajectory` -- quintic interpolating splines through
  user waypoints (position and Euler angles), at rest at both ends.
"""

from __future__ import annotations

from uwbimu.errors import ConfigError, UsageError
from dataclasses import dataclass

import numpy as np

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True)
class MotionSample:
    """Truth at a batch of instants (all arrays have leading length ``N``)."""

    t: np.ndarray  # (N,) UWB time [s]
    p: np.ndarray  # (N, 3) position [m]
    v: np.ndarray  # (N, 3) velocity [m/s]
    a: np.ndarray  # (N, 3) acceleration [m/s^2]
    q: np.ndarray  # (N, 4) attitude body -> world
    w: np.ndarray  # (N, 3) body angular velocity [rad/s]
    euler: np.ndarray  # (N, 3) roll, pitch, yaw [rad]
    euler_rate: np.ndarray  # (N, 3) their time derivatives [rad/s]


# --------------------------------------------------------------------------
# Euler angles
# --------------------------------------------------------------------------
def euler_zyx_to_quat(euler: np.ndarray) -> np.ndarray:
    """Quaternion ``qz(yaw) ⊗ qy(pitch) ⊗ qx(roll)`` of ``(..., 3)`` ``[roll, pitch, yaw]``."""
    e = np.asarray(euler, dtype=float)
    cr, sr = np.cos(0.5 * e[..., 0]), np.sin(0.5 * e[..., 0])
    cp, sp = np.cos(0.5 * e[..., 1]), np.sin(0.5 * e[..., 1])
    cy, sy = np.cos(0.5 * e[..., 2]), np.sin(0.5 * e[..., 2])
    q = np.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=-1,
    )
    # Canonical sign (qw >= 0) like quaternion.quat_normalize; the sign flip
    # does not change the rotation.
    return np.where(q[..., :1] < 0, -q, q)


def quat_to_euler_zyx(q: np.ndarray) -> np.ndarray:
    """``[roll, pitch, yaw]`` (rad) of quaternions ``(..., 4)``; pitch in [-pi/2, pi/2]."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    roll = np.arctan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = np.arcsin(np.clip(2 * (w * y - z * x), -1.0, 1.0))
    yaw = np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return np.stack([roll, pitch, yaw], axis=-1)


def euler_rates_to_body_rate(euler: np.ndarray, euler_rate: np.ndarray) -> np.ndarray:
    """Exact body angular velocity of Z-Y-X Euler angles and their rates.

    ``w = [phi' - psi' sin th, th' cos phi + psi' cos th sin phi,
    -th' sin phi + psi' cos th cos phi]`` (IMU frame, rad/s).
    """
    e = np.asarray(euler, dtype=float)
    ed = np.asarray(euler_rate, dtype=float)
    phi, th = e[..., 0], e[..., 1]
    dphi, dth, dpsi = ed[..., 0], ed[..., 1], ed[..., 2]
    sphi, cphi = np.sin(phi), np.cos(phi)
    sth, cth = np.sin(th), np.cos(th)
    return np.stack(
        [dphi - dpsi * sth, dth * cphi + dpsi * cth * sphi, -dth * sphi + dpsi * cth * cphi],
        axis=-1,
    )


# --------------------------------------------------------------------------
# Soft start
# --------------------------------------------------------------------------
def soft_start(t: np.ndarray, ramp: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Warped time ``tau(t)`` and its first two derivatives.

    ``tau' = S(t / ramp)`` with the septic smoothstep ``S`` (``S, S', S'', S'''``
    vanish at 0), so ``tau = 0`` for ``t <= 0`` and ``tau' = 1`` for
    ``t >= ramp``.  Any trajectory ``f(tau(t))`` then starts exactly at rest
    (velocity, acceleration, jerk, angular velocity and angular acceleration
    all zero at ``t = 0``), like a vehicle that takes off from standstill.
    A zero ramp gives ``tau = t`` everywhere.
    """
    t = np.asarray(t, dtype=float)
    if ramp <= 0:
        return t.copy(), np.ones_like(t), np.zeros_like(t)
    u = np.clip(t / ramp, 0.0, 1.0)
    S = u**4 * (35 - 84 * u + 70 * u**2 - 20 * u**3)
    dS = 140 * u**3 * (1 - u) ** 3  # = 140u^3 - 420u^4 + 420u^5 - 140u^6
    intS = u**5 * (7 - 14 * u + 10 * u**2 - 2.5 * u**3)  # integral of S from 0 to u
    tau = np.where(t >= ramp, 0.5 * ramp + (t - ramp), ramp * intS)
    tau1 = np.where(t >= ramp, 1.0, S)
    tau2 = np.where((t > 0) & (t < ramp), dS / ramp, 0.0)
    return tau, tau1, tau2


# --------------------------------------------------------------------------
# Channels
# --------------------------------------------------------------------------
@dataclass(frozen=True)
class SinusoidChannel:
    """``f(tau) = c0 + c1 tau + sum_i amp_i sin(2 pi freq_i tau + phase_i)``."""

    c0: float = 0.0
    c1: float = 0.0
    amp: tuple[float, ...] = ()
    freq: tuple[float, ...] = ()  # Hz
    phase: tuple[float, ...] = ()  # rad

    def __post_init__(self):
        if not (len(self.amp) == len(self.freq) == len(self.phase)):
            raise ConfigError("amp, freq and phase must have the same length")

    def eval(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Value and first two derivatives with respect to ``tau``."""
        tau = np.asarray(tau, dtype=float)
        f = self.c0 + self.c1 * tau
        f1 = np.full_like(tau, self.c1)
        f2 = np.zeros_like(tau)
        for A, fr, ph in zip(self.amp, self.freq, self.phase):
            om = TWO_PI * fr
            arg = om * tau + ph
            s, c = np.sin(arg), np.cos(arg)
            f = f + A * s
            f1 = f1 + A * om * c
            f2 = f2 - A * om * om * s
        return f, f1, f2

    def bounds(self) -> tuple[float, float, float]:
        """Upper bounds of ``|f - c0 - c1 tau|``, ``|f'|`` and ``|f''|`` (triangle inequality)."""
        A = np.abs(np.asarray(self.amp, dtype=float))
        om = TWO_PI * np.asarray(self.freq, dtype=float)
        return float(A.sum()), float(abs(self.c1) + (A * om).sum()), float((A * om * om).sum())


def constant_channel(value: float) -> SinusoidChannel:
    return SinusoidChannel(c0=float(value))


class Trajectory:
    """Base class: subclasses implement :meth:`position` and :meth:`euler`."""

    #: suggested flight duration [s] (``None``: any)
    natural_duration: float | None = None

    def position(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(p, v, a)``, each ``(N, 3)`` world frame."""
        raise NotImplementedError

    def euler(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``([roll, pitch, yaw], their rates)``, each ``(N, 3)``."""
        raise NotImplementedError

    def sample(self, t: np.ndarray) -> MotionSample:
        """Full truth at UWB times ``t`` (1-D array, s)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p, v, a = self.position(t)
        e, ed = self.euler(t)
        return MotionSample(
            t=t, p=p, v=v, a=a, q=euler_zyx_to_quat(e), w=euler_rates_to_body_rate(e, ed), euler=e, euler_rate=ed
        )

    def pose(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Only ``(p, q)`` (cheaper, for ranging)."""
        t = np.atleast_1d(np.asarray(t, dtype=float))
        p, _, _ = self.position(t)
        e, _ = self.euler(t)
        return p, euler_zyx_to_quat(e)


class SinusoidTrajectory(Trajectory):
    """Sum-of-sinusoids position and Euler channels of soft-start warped time.

    Parameters
    ----------
    pos : three :class:`SinusoidChannel` for x, y, z [m] (functions of ``tau``).
    att : three channels for roll, pitch, yaw [rad].
    ramp : soft-start duration [s] (see :func:`soft_start`).
    """

    def __init__(self, pos, att, ramp: float = 2.0):
        if len(pos) != 3 or len(att) != 3:
            raise UsageError("need three position and three attitude channels")
        self.pos = tuple(pos)
        self.att = tuple(att)
        self.ramp = float(ramp)

    def _chan(self, chans, t, order2: bool):
        tau, tau1, tau2 = soft_start(t, self.ramp)
        vals, d1, d2 = [], [], []
        for ch in chans:
            f, f1, f2 = ch.eval(tau)
            vals.append(f)
            d1.append(f1 * tau1)
            if order2:
                d2.append(f2 * tau1 * tau1 + f1 * tau2)  # chain rule
        out = [np.stack(vals, -1), np.stack(d1, -1)]
        if order2:
            out.append(np.stack(d2, -1))
        return out

    def position(self, t):
        p, v, a = self._chan(self.pos, t, True)
        return p, v, a

    def euler(self, t):
        e, ed = self._chan(self.att, t, False)
        return e, ed

    def bounds(self) -> dict[str, float]:
        """Conservative bounds of speed [m/s], acceleration [m/s^2], body rate [rad/s]."""
        _, vb, ab = np.array([c.bounds() for c in self.pos]).T
        _, rb, _ = np.array([c.bounds() for c in self.att]).T
        # tau'' <= max S'/ramp = 140/64/ramp adds f' tau'' to the acceleration.
        extra = 140.0 / 64.0 / self.ramp if self.ramp > 0 else 0.0
        return {
            "speed": float(np.linalg.norm(vb)),
            "accel": float(np.linalg.norm(ab + vb * extra)),
            # |w| <= |phi'| + |th'| + |psi'|: each column of the Euler-rate map is a unit vector.
            "rate": float(rb.sum()),
        }


class SplineTrajectory(Trajectory):
    """Quintic splines through waypoints, at rest at both ends.

    Position channels and the (unwrapped) Euler angles are interpolated by
    ``scipy.interpolate.make_interp_spline(k=5)`` with zero first and second
    derivatives at both ends; outside the waypoint span the vehicle holds the
    end pose at rest (the splines are C2 there, so the IMU stream stays smooth).

    Parameters
    ----------
    t : (N,) waypoint times [s], strictly increasing, ``t[0] = 0``.
    p : (N, 3) positions [m].
    euler : (N, 3) roll, pitch, yaw [rad], continuous (unwrapped).
    """

    def __init__(self, t: np.ndarray, p: np.ndarray, euler: np.ndarray):
        from scipy.interpolate import make_interp_spline

        t = np.asarray(t, dtype=float)
        self.t0, self.t1 = float(t[0]), float(t[-1])
        k = 5 if len(t) >= 2 else 1
        bc = ([(1, np.zeros(3)), (2, np.zeros(3))], [(1, np.zeros(3)), (2, np.zeros(3))])
        self._p = make_interp_spline(t, np.asarray(p, dtype=float), k=k, bc_type=bc)
        self._e = make_interp_spline(t, np.asarray(euler, dtype=float), k=k, bc_type=bc)
        self._v, self._a = self._p.derivative(1), self._p.derivative(2)
        self._ed = self._e.derivative(1)
        self.natural_duration = self.t1 - self.t0

    def _inside(self, t):
        t = np.asarray(t, dtype=float)
        tc = np.clip(t, self.t0, self.t1)
        moving = ((t > self.t0) & (t < self.t1))[:, None]
        return tc, moving

    def position(self, t):
        tc, moving = self._inside(t)
        return self._p(tc), np.where(moving, self._v(tc), 0.0), np.where(moving, self._a(tc), 0.0)

    def euler(self, t):
        tc, moving = self._inside(t)
        return self._e(tc), np.where(moving, self._ed(tc), 0.0)
