"""Smooth 6-DoF manoeuvres with few coefficients, bounds and the naive figure-8.

A manoeuvre has six channels (x, y, z [m]; roll, pitch, yaw [rad], Z-Y-X
Euler angles as in :mod:`uwbimu.sim.trajectory`), each::

    f_c(t) = center_c + w(t) * sum_i A_ci sin(2 pi F_ci t + phi_ci),   0 <= t <= T

with the envelope ``w`` rising from 0 to 1 over ``ramp`` seconds and falling
back over the last ``ramp`` seconds by the septic smoothstep (``w, w', w'',
w'''`` vanish at both ends), so the vehicle starts and stops at rest, level,
at ``center`` -- what the simulator's trajectory-file splines assume.

The designed manoeuvre uses harmonics ``F = k / period`` (k = 1..K) whose
amplitudes/phases come from ``a_k cos + b_k sin`` coefficients
(:func:`fourier_maneuver`).  The figure-8 baseline (:func:`figure8_maneuver`)
is *time-warped* instead (``warp=True``): ``f_c = center_c + sum_i A_ci
sin(2 pi F_ci s(t) + phi_ci)`` with the clock ``s' = w(t)``, so the vehicle
runs along the lemniscate itself, accelerating smoothly to its cruise speed
-- an amplitude envelope on a slow lemniscate would instead drag it off the
curve and put its speed/acceleration peaks into the ramps, leaving the
cruise far below the bounds.  :func:`fit_to_bounds` scales the position and
attitude parts so that the flight box, speed, acceleration, tilt and angular
rate bounds hold on a fine time grid.
"""

from __future__ import annotations

from uwbimu.errors import ConfigError, UsageError
from dataclasses import dataclass, replace

import numpy as np

from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.models.reference import G_WORLD
from uwbimu.sim.flat import flat_attitude
from uwbimu.sim.trajectory import euler_rates_to_body_rate, euler_zyx_to_quat

TWO_PI = 2.0 * np.pi


def envelope(t: np.ndarray, T: float, ramp: float, third: bool = False) -> tuple[np.ndarray, ...]:
    """Envelope ``w(t)`` and its first two derivatives (septic smoothstep ramps); ``third``: also the third."""
    t = np.asarray(t, dtype=float)
    w = np.ones_like(t)
    w1 = np.zeros_like(t)
    w2 = np.zeros_like(t)
    w3 = np.zeros_like(t)
    if ramp <= 0:
        return (w, w1, w2, w3) if third else (w, w1, w2)
    for u, sgn in (((t / ramp), 1.0), (((T - t) / ramp), -1.0)):
        m = u < 1.0
        uu = np.clip(u[m], 0.0, 1.0)
        S = uu**4 * (35 - 84 * uu + 70 * uu**2 - 20 * uu**3)
        dS = 140 * uu**3 * (1 - uu) ** 3
        d2S = 420 * uu**2 * (1 - uu) ** 2 * (1 - 2 * uu)
        d3S = 840 * uu * (1 - uu) * (1 - 5 * uu + 5 * uu**2)
        w[m] = w[m] * S
        w1[m] = sgn * dS / ramp
        w2[m] = d2S / ramp**2
        w3[m] = sgn * d3S / ramp**3
    return (w, w1, w2, w3) if third else (w, w1, w2)


def warped_clock(t: np.ndarray, T: float, ramp: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Clock ``s(t) = int_0^t w`` of the envelope, and ``s' = w``, ``s'' = w'``.

    ``s`` runs at rate 0 at both ends and 1 in the cruise; ``s(T) = T - ramp``
    (each septic ramp contributes ``ramp / 2``).  Needs ``T >= 2 ramp``.
    """
    t = np.asarray(t, dtype=float)
    w, w1, _ = envelope(t, T, ramp)
    if ramp <= 0:
        return t.copy(), w, w1
    if T < 2 * ramp:
        raise ConfigError(f"time warp needs duration >= 2 * ramp ({T} < {2 * ramp})")

    def integral(u):  # int_0^u S, S the septic smoothstep
        u = np.clip(u, 0.0, 1.0)
        return u**5 * (7 - 14 * u + 10 * u**2 - 2.5 * u**3)

    s = np.where(
        t < ramp,
        ramp * integral(t / ramp),
        np.where(t > T - ramp, (T - ramp) - ramp * integral((T - t) / ramp), t - 0.5 * ramp),
    )
    return s, w, w1


@dataclass(frozen=True)
class Maneuver:
    """Six sinusoid-sum channels under a rest-to-rest envelope.

    Attributes
    ----------
    center : (6,) ``[x, y, z, roll, pitch, yaw]`` at rest [m, rad].
    amp, freq, phase : (6, M) amplitude [m or rad], frequency [Hz], phase [rad].
    duration : T [s]; ramp : envelope ramp [s].
    """

    center: np.ndarray
    amp: np.ndarray
    freq: np.ndarray
    phase: np.ndarray
    duration: float
    ramp: float
    warp: bool = False  # True: time-warped clock s(t) instead of the amplitude envelope
    flat: bool = False  # True: multirotor -- roll/pitch from the thrust (uwbimu.sim.flat), channels 3-4 unused

    def channels(self, t: np.ndarray, third: bool = False) -> tuple[np.ndarray, ...]:
        """Values and first two (``third``: three) time derivatives of the six channels, each (N, 6)."""
        t = np.asarray(t, dtype=float)
        om = TWO_PI * self.freq  # (6, M)
        if self.warp:
            s, s1, s2 = warped_clock(t, self.duration, self.ramp)
            arg = om[None] * s[:, None, None] + self.phase[None]
            sn, cs = np.sin(arg), np.cos(arg)
            gc = np.sum(self.amp * om * cs, axis=2)
            gs = np.sum(self.amp * om * om * sn, axis=2)
            f = self.center + np.sum(self.amp * sn, axis=2)
            out = (f, s1[:, None] * gc, s2[:, None] * gc - (s1 * s1)[:, None] * gs)
            if not third:
                return out
            s3 = envelope(t, self.duration, self.ramp)[2]  # s''' = w''
            g3 = -np.sum(self.amp * om**3 * cs, axis=2)
            return out + (s3[:, None] * gc - 3 * (s1 * s2)[:, None] * gs + (s1**3)[:, None] * g3,)
        w, w1, w2, w3 = envelope(t, self.duration, self.ramp, third=True)
        arg = om[None] * t[:, None, None] + self.phase[None]  # (N, 6, M)
        s, c = np.sin(arg), np.cos(arg)
        g = np.sum(self.amp * s, axis=2)
        g1 = np.sum(self.amp * om * c, axis=2)
        g2 = -np.sum(self.amp * om * om * s, axis=2)
        f = self.center + w[:, None] * g
        f1 = w1[:, None] * g + w[:, None] * g1
        f2 = w2[:, None] * g + 2 * w1[:, None] * g1 + w[:, None] * g2
        if not third:
            return f, f1, f2
        g3 = -np.sum(self.amp * om**3 * c, axis=2)
        f3 = w3[:, None] * g + 3 * w2[:, None] * g1 + 3 * w1[:, None] * g2 + w[:, None] * g3
        return f, f1, f2, f3

    def kinematics(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """Truth along ``t``: ``p, v, a`` (world), ``euler``, ``q``, ``R``, body rate ``w``,
        specific force ``f = R^T (a + g)`` (IMU frame), tilt [rad]; with ``flat`` also the
        jerk ``j`` [m/s^3] and the thrust ``thrust = |a + g e_z|`` [m/s^2]."""
        extra = {}
        if self.flat:
            f, f1, f2, f3 = self.channels(t, third=True)
            eul, eul1, thrust = flat_attitude(f2[:, :3], f3[:, :3], f[:, 5], f1[:, 5])
            extra = {"j": f3[:, :3], "thrust": thrust, "yaw_rate": f1[:, 5]}
        else:
            f, f1, f2 = self.channels(t)
            eul, eul1 = f[:, 3:], f1[:, 3:]
        q = euler_zyx_to_quat(eul)
        R = quat_to_rotmat(q)
        a = f2[:, :3]
        return {
            "t": np.asarray(t, dtype=float),
            "p": f[:, :3],
            "v": f1[:, :3],
            "a": a,
            "euler": eul,
            "q": q,
            "R": R,
            "w": euler_rates_to_body_rate(eul, eul1),
            "f": np.einsum("nji,nj->ni", R, a + G_WORLD),
            "tilt": np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0)),
            **extra,
        }

    def scaled(self, s_pos: float, s_att: float) -> "Maneuver":
        k = np.array([s_pos] * 3 + [s_att] * 3)[:, None]
        return replace(self, amp=self.amp * k)


#: channels a multirotor plan chooses (x, y, z, yaw); roll and pitch follow from the thrust
FLAT_CHANNELS = (0, 1, 2, 5)


def fourier_maneuver(theta: np.ndarray, center, duration: float, ramp: float, period: float, n_harm: int, flat: bool = False) -> Maneuver:
    """Manoeuvre from ``theta`` = (6, K, 2) cosine/sine coefficients of the harmonics ``k / period``
    (``flat``: (4, K, 2) for x, y, z, yaw; roll and pitch by differential flatness)."""
    if flat:
        th = np.zeros((6, n_harm, 2))
        th[list(FLAT_CHANNELS)] = np.asarray(theta, dtype=float).reshape(4, n_harm, 2)
    else:
        th = np.asarray(theta, dtype=float).reshape(6, n_harm, 2)
    a, b = th[..., 0], th[..., 1]
    amp = np.hypot(a, b)
    phase = np.arctan2(a, b)  # a cos + b sin = amp sin(. + phase)
    freq = np.tile(np.arange(1, n_harm + 1) / period, (6, 1))
    return Maneuver(np.asarray(center, dtype=float), amp, freq, phase, float(duration), float(ramp), flat=flat)


def figure8_maneuver(center, half_size, period: float, duration: float, ramp: float, attitude_amp, attitude_freq, flat: bool = False) -> Maneuver:
    """Horizontal lemniscate of Gerono ``x = sx sin(w s)``, ``y = sy sin(2 w s)``, fixed height,
    with a gentle attitude oscillation (the simulator's ``figure8`` defaults), flown on the
    time-warped clock ``s(t)`` (:func:`warped_clock`): it starts at rest at the centre,
    speeds up along the curve during the ramp, cruises and stops at rest."""
    amp = np.zeros((6, 1))
    freq = np.zeros((6, 1))
    amp[0, 0], freq[0, 0] = half_size[0], 1.0 / period
    amp[1, 0], freq[1, 0] = half_size[1], 2.0 / period
    for i in range(2 if flat else 0, 3):  # flat: only the yaw oscillation, roll/pitch follow the thrust
        amp[3 + i, 0], freq[3 + i, 0] = attitude_amp[i], attitude_freq[i]
    return Maneuver(np.asarray(center, dtype=float), amp, freq, np.zeros((6, 1)), float(duration), float(ramp), warp=True, flat=flat)


@dataclass(frozen=True)
class MotionBounds:
    """Flight box [m], speed [m/s], acceleration [m/s^2], tilt [rad], body rate [rad/s]."""

    box_min: np.ndarray
    box_max: np.ndarray
    speed: float
    accel: float
    tilt: float
    rate: float


def bound_usage(kin: dict[str, np.ndarray], b: MotionBounds) -> dict[str, float]:
    """Peak of each bounded quantity divided by its bound (<= 1 is feasible)."""
    p = kin["p"]
    lo = np.min(p, axis=0)
    hi = np.max(p, axis=0)
    # fraction of the available room used on the worst side (> 1 leaves the box)
    centre = 0.5 * (b.box_min + b.box_max)
    half = 0.5 * (b.box_max - b.box_min)
    box = float(np.max(np.maximum(np.abs(hi - centre), np.abs(lo - centre)) / half))
    return {
        "box": box,
        "speed": float(np.max(np.linalg.norm(kin["v"], axis=1)) / b.speed),
        "accel": float(np.max(np.linalg.norm(kin["a"], axis=1)) / b.accel),
        "tilt": float(np.max(kin["tilt"]) / b.tilt),
        "rate": float(np.max(np.linalg.norm(kin["w"], axis=1)) / b.rate),
    }


def _box_scale(m: Maneuver, t: np.ndarray, b: MotionBounds) -> float:
    """Largest position scale (about ``center``) keeping the path in the box."""
    dev = m.channels(t)[0][:, :3] - m.center[:3]
    s = np.inf
    for i in range(3):
        up, down = dev[:, i].max(), -dev[:, i].min()
        if up > 1e-12:
            s = min(s, (b.box_max[i] - m.center[i]) / up)
        if down > 1e-12:
            s = min(s, (m.center[i] - b.box_min[i]) / down)
    return s


def fit_to_bounds(m: Maneuver, b: MotionBounds, dt: float = 0.02, margin: float = 0.99, grow: bool = True) -> Maneuver:
    """Scale the position and attitude amplitudes so that every bound holds.

    The position part scales linearly (box, speed, acceleration), so one
    scale fixes it exactly; tilt and rate are nearly linear in the attitude
    scale and are fixed by a few multiplicative corrections.  With
    ``grow=True`` a manoeuvre below its bounds is also enlarged up to them
    (more motion never costs information here).  Checked on a grid of step
    ``dt`` with the safety factor ``margin``.
    """
    t = np.arange(0.0, m.duration + 0.5 * dt, dt)
    kin = m.kinematics(t)
    sp = np.inf
    vmax = np.max(np.linalg.norm(kin["v"], axis=1))
    amax = np.max(np.linalg.norm(kin["a"], axis=1))
    if vmax > 1e-12:
        sp = min(sp, b.speed / vmax)
    if amax > 1e-12:
        sp = min(sp, b.accel / amax)
    sp = min(sp, _box_scale(m, t, b))
    if not np.isfinite(sp):
        sp = 1.0
    sp *= margin
    if not grow:
        sp = min(sp, 1.0)
    ma = m.scaled(sp, 1.0)
    # Attitude: roll/pitch (scale s_rp) are limited by the tilt and the rate,
    # yaw (scale s_y) only by the rate -- separate scales so that a tilt-bound
    # manoeuvre can still use the rate budget for yaw.
    s_rp, s_y = 1.0, 1.0
    for _ in range(12):
        kin = _scale_att(ma, s_rp, s_y).kinematics(t)
        tl = np.max(kin["tilt"])
        rt = np.max(np.linalg.norm(kin["w"], axis=1))
        f_t = b.tilt / tl if tl > 1e-12 else np.inf
        f_r = b.rate / rt if rt > 1e-12 else np.inf
        if not np.isfinite(min(f_t, f_r)):
            break
        has_rp = bool(np.any(ma.amp[3:5] > 0))
        new_rp = s_rp * min(f_t, f_r) * margin if has_rp else s_rp
        new_y = s_y * f_r * margin
        new_rp, new_y = min(new_rp, 50.0), min(new_y, 50.0)
        if not grow:
            new_rp, new_y = min(new_rp, 1.0), min(new_y, 1.0)
        if abs(new_rp / s_rp - 1.0) < 1e-4 and abs(new_y / s_y - 1.0) < 1e-4:
            break
        s_rp, s_y = new_rp, new_y
    out = _scale_att(ma, s_rp, s_y)
    # final guarantee on the grid (the loop converges from below in practice)
    kin = out.kinematics(t)
    over = max(np.max(kin["tilt"]) / b.tilt, np.max(np.linalg.norm(kin["w"], axis=1)) / b.rate)
    if over > 1.0:
        out = _scale_att(out, 1.0 / over * margin, 1.0 / over * margin)
    return out


def _scale_att(m: Maneuver, s_rp: float, s_y: float) -> Maneuver:
    k = np.array([1.0, 1.0, 1.0, s_rp, s_rp, s_y])[:, None]
    return replace(m, amp=m.amp * k)


def fit_flat_to_bounds(m: Maneuver, b: MotionBounds, lim, dt: float = 0.02, margin: float = 0.99, grow: bool = True) -> Maneuver:
    """Scale a multirotor manoeuvre (``m.flat``) so that the motion bounds and the vehicle limits hold.

    Box, speed and acceleration are linear in the position scale (one factor);
    thrust and tilt depend on the position scale only (the yaw does not tilt
    the thrust) and grow with it, so a bisection on that scale enforces them;
    the yaw scale is fixed by the yaw-rate limit (linear); the body rate
    depends on both, and a common bisection factor on both scales enforces
    it.  ``lim``: :class:`uwbimu.design.trajectory.platform.MultirotorLimits`;
    ``b.tilt`` / ``b.rate`` are not used (the limits' tilt and rate are).
    Checked on a grid of step ``dt`` with the safety factor ``margin``; with
    ``grow=False`` the manoeuvre is only ever shrunk.
    """
    from uwbimu.design.trajectory.platform import platform_usage

    if not m.flat:
        raise UsageError("fit_flat_to_bounds needs a flat (multirotor) manoeuvre")
    t = np.arange(0.0, m.duration + 0.5 * dt, dt)
    _, f1, f2 = m.channels(t)  # the raw candidate may have no attitude (thrust down): channels only
    sp = min(
        b.speed / max(np.max(np.linalg.norm(f1[:, :3], axis=1)), 1e-300),
        b.accel / max(np.max(np.linalg.norm(f2[:, :3], axis=1)), 1e-300),
        _box_scale(m, t, b),
    )
    sp = 1.0 if not np.isfinite(sp) else sp * margin
    yr = np.max(np.abs(f1[:, 5]))
    sy = lim.yaw_rate_max / yr * margin if yr > 1e-300 else 1.0
    if not grow:
        sp, sy = min(sp, 1.0), min(sy, 1.0)

    def usage(s_pos, s_yaw, keys):
        try:
            u = platform_usage(_scale_att(m.scaled(s_pos, 1.0), 1.0, s_yaw).kinematics(t), lim)
        except ValueError:  # thrust not upward: no attitude at all
            return np.inf
        return max(u[k] for k in keys)

    def shrink(f_ok, hi):
        """Largest factor in (0, hi] with f_ok true (f_ok monotone in practice; 40 halvings)."""
        if f_ok(hi):
            return hi
        lo = 0.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if f_ok(mid) else (lo, mid)
        return lo

    # thrust (both sides) and tilt: position scale only (yaw cannot change the thrust)
    sp = shrink(lambda x: usage(x, 0.0, ("thrust_max", "thrust_min", "tilt")) <= margin, sp)
    lam = shrink(lambda x: usage(sp * x, sy * x, ("rate",)) <= margin, 1.0)
    return _scale_att(m.scaled(sp * lam, 1.0), 1.0, sy * lam)
