"""Platform models for trajectory design: ``multirotor`` (differentially flat) and ``handheld``.

* ``handheld`` -- a free rigid body: position and attitude are independent
  (today's calibration design: six channels).
* ``multirotor`` (default) -- the attitude follows the thrust: body z along
  ``a + g e_z`` with a free yaw (:mod:`uwbimu.sim.flat`).  A plan is then
  position + yaw, and must respect the vehicle's limits
  (:class:`MultirotorLimits`): collective thrust per unit mass between
  ``thrust_min_g`` and ``thrust_max_g`` times ``g``, tilt, body rate and yaw
  rate.

:func:`platform_usage` gives each limit's peak / bound (<= 1 feasible);
:func:`check_multirotor` names every exceeded limit, its peak and where it
happens, so a plan that a multirotor cannot fly is refused with a reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from uwbimu.models.reference import GRAVITY

Platform = Literal["multirotor", "handheld"]


class MultirotorLimits(BaseModel):
    """Limits of a small quadrotor (defaults: thrust-to-weight 2, 35 deg tilt, 3 rad/s body rate)."""

    model_config = ConfigDict(extra="forbid")

    # thrust_min_g < 1 < thrust_max_g: the vehicle must be able to hover
    thrust_max_g: float = Field(2.0, gt=1.0, description="max collective thrust per unit mass [g] (thrust-to-weight ratio)")
    thrust_min_g: float = Field(0.3, ge=0.0, lt=1.0, description="min collective thrust per unit mass [g] (rotors never stop)")
    tilt_max_deg: float = Field(35.0, gt=0, lt=80, description="max angle of the body z axis from vertical [deg]")
    rate_max: float = Field(3.0, gt=0, description="max body angular rate |w| [rad/s]")
    yaw_rate_max: float = Field(2.0, gt=0, description="max yaw rate |psi'| [rad/s]")

    @property
    def thrust_max(self) -> float:
        """[m/s^2]"""
        return self.thrust_max_g * GRAVITY

    @property
    def thrust_min(self) -> float:
        """[m/s^2]"""
        return self.thrust_min_g * GRAVITY

    @property
    def tilt_max(self) -> float:
        """[rad]"""
        return float(np.deg2rad(self.tilt_max_deg))


#: the limits of :class:`MultirotorLimits`, in the order they are reported
LIMIT_NAMES = ("thrust_max", "thrust_min", "tilt", "rate", "yaw_rate")
_UNITS = {"thrust_max": "m/s^2", "thrust_min": "m/s^2", "tilt": "deg", "rate": "rad/s", "yaw_rate": "rad/s"}


@dataclass(frozen=True)
class LimitViolation:
    """One exceeded limit: its name, the worst value, the bound, where (time [s]) and by how much."""

    limit: str
    peak: float
    bound: float
    t: float
    usage: float  # peak / bound (thrust_min: bound / peak); > 1 is a violation

    def message(self) -> str:
        u = _UNITS[self.limit]
        rel = "below" if self.limit == "thrust_min" else "above"
        return f"{self.limit}: {self.peak:.4g} {u} at t = {self.t:.2f} s, {rel} the limit {self.bound:.4g} {u} (usage {self.usage:.3f})"


def _series(kin: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    T = kin["a"] + np.array([0.0, 0.0, GRAVITY])
    thrust = np.linalg.norm(T, axis=1)
    yaw_rate = kin["yaw_rate"] if "yaw_rate" in kin else _euler_yaw_rate(kin)
    return {
        "thrust": thrust,
        "tilt": np.asarray(kin["tilt"], dtype=float),
        "rate": np.linalg.norm(kin["w"], axis=1),
        "yaw_rate": np.abs(yaw_rate),
    }


def _euler_yaw_rate(kin) -> np.ndarray:
    """Z-Y-X yaw rate from the body rate: ``psi' = (w_y sin phi + w_z cos phi) / cos th``."""
    phi, th = kin["euler"][:, 0], kin["euler"][:, 1]
    w = kin["w"]
    return (w[:, 1] * np.sin(phi) + w[:, 2] * np.cos(phi)) / np.cos(th)


def platform_usage(kin: dict[str, np.ndarray], lim: MultirotorLimits) -> dict[str, float]:
    """Peak / bound of every multirotor limit along a truth dictionary (``t, a, w, tilt, euler``).

    ``thrust_min`` is ``thrust_min / min thrust`` so that, like the others, > 1 violates it.
    """
    s = _series(kin)
    return {
        "thrust_max": float(np.max(s["thrust"]) / lim.thrust_max),
        "thrust_min": float(lim.thrust_min / max(np.min(s["thrust"]), 1e-300)),
        "tilt": float(np.max(s["tilt"]) / lim.tilt_max),
        "rate": float(np.max(s["rate"]) / lim.rate_max),
        "yaw_rate": float(np.max(s["yaw_rate"]) / lim.yaw_rate_max),
    }


# arccos near 1 resolves angles only down to sqrt(2 eps) ~ 2e-8 rad: the default tolerance on the
# thrust-direction angle sits 50x above that numerical floor, far below any physical misalignment
def check_multirotor(kin: dict[str, np.ndarray], lim: MultirotorLimits, attitude_tol: float = 1e-6) -> list[LimitViolation]:
    """Every limit a multirotor would exceed along ``kin``, plus whether the attitude is flat.

    A violation is a peak above its bound (relative: usage > 1, no absolute cut-off).
    If the attitude's body z axis is not along the thrust (angle above
    ``attitude_tol`` rad, i.e. not a multirotor attitude), a ``thrust_direction``
    entry reports the worst angle (bound: ``attitude_tol``).

    Returns
    -------
    list of :class:`LimitViolation` (empty: flyable).
    """
    t = np.asarray(kin["t"], dtype=float)
    s = _series(kin)
    out = []
    for name, val, bound, worst in (
        ("thrust_max", s["thrust"], lim.thrust_max, np.argmax),
        ("thrust_min", s["thrust"], lim.thrust_min, np.argmin),
        ("tilt", np.rad2deg(s["tilt"]), lim.tilt_max_deg, np.argmax),
        ("rate", s["rate"], lim.rate_max, np.argmax),
        ("yaw_rate", s["yaw_rate"], lim.yaw_rate_max, np.argmax),
    ):
        k = int(worst(val))
        usage = bound / max(val[k], 1e-300) if name == "thrust_min" else val[k] / bound
        if usage > 1.0:
            out.append(LimitViolation(name, float(val[k]), float(bound), float(t[k]), float(usage)))
    ang = thrust_axis_angle(kin)
    k = int(np.argmax(ang))
    if ang[k] > attitude_tol:
        out.append(LimitViolation("thrust_direction", float(np.rad2deg(ang[k])), float(np.rad2deg(attitude_tol)), float(t[k]), float(ang[k] / attitude_tol)))
    return out


_UNITS["thrust_direction"] = "deg"


def thrust_axis_angle(kin: dict[str, np.ndarray]) -> np.ndarray:
    """Angle [rad] between the body z axis (``R[:, :, 2]``) and the thrust ``a + g e_z``."""
    T = kin["a"] + np.array([0.0, 0.0, GRAVITY])
    z = kin["R"][:, :, 2]
    c = np.sum(z * T, axis=1) / np.linalg.norm(T, axis=1)
    return np.arccos(np.clip(c, -1.0, 1.0))
