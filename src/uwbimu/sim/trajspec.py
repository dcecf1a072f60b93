"""Typed trajectory specifications (the ``trajectory:`` block of a scenario).

Each spec is a pydantic model tagged by ``type`` with a :meth:`build` method
returning a :class:`~uwbimu.sim.trajectory.Trajectory`.  Times are UWB-clock
seconds, positions metres (world frame, z up), angles radians, frequencies Hz.
Analytic trajectories start at rest and reach full motion after ``ramp``
seconds (:func:`~uwbimu.sim.trajectory.soft_start`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from uwbimu.sim.trajectory import SinusoidChannel, SinusoidTrajectory, Trajectory, constant_channel

Vec3 = tuple[float, float, float]
Vec2 = tuple[float, float]
#: Centre of the default room (10 x 8 x 3 m), the default place to fly.
ROOM_CENTER: Vec3 = (5.0, 4.0, 1.5)


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid")


class AttitudeSpec(_Spec):
    """Euler-angle attitude ``angle_i = offset_i + amplitude_i sin(2 pi frequency_i tau + phase_i)``.

    Order of every triple: roll, pitch, yaw (Z-Y-X convention, IMU body -> world).
    """

    offset: Vec3 = Field(default=(0.0, 0.0, 0.0), description="constant roll, pitch, yaw [rad]")
    amplitude: Vec3 = Field(default=(0.0, 0.0, 0.0), description="oscillation amplitudes [rad]")
    frequency: Vec3 = Field(default=(0.0, 0.0, 0.0), description="oscillation frequencies [Hz]")
    phase: Vec3 = Field(default=(0.0, 0.0, 0.0), description="oscillation phases [rad]")
    yaw_rate: float = Field(default=0.0, description="constant yaw spin added to yaw [rad/s]")

    def channels(self, extra_yaw_rate: float = 0.0, extra_yaw: float = 0.0) -> list[SinusoidChannel]:
        chans = []
        for i in range(3):
            c1 = self.yaw_rate + extra_yaw_rate if i == 2 else 0.0
            c0 = self.offset[i] + (extra_yaw if i == 2 else 0.0)
            if self.amplitude[i] != 0.0:
                chans.append(SinusoidChannel(c0, c1, (self.amplitude[i],), (self.frequency[i],), (self.phase[i],)))
            else:
                chans.append(SinusoidChannel(c0, c1))
        return chans


class _Analytic(_Spec):
    ramp: float = Field(default=2.0, ge=0, description="soft-start duration [s]; 0 starts at full motion")


def _lissajous_channels(center, amplitude, frequency, phase) -> list[SinusoidChannel]:
    return [
        SinusoidChannel(center[i], 0.0, (amplitude[i],), (frequency[i],), (phase[i],)) if amplitude[i] else constant_channel(center[i])
        for i in range(3)
    ]


class HoverSpec(_Analytic):
    """Near-hover: small position wobble and small attitude oscillations (zero amplitudes: static)."""

    type: Literal["hover"] = "hover"
    center: Vec3 = Field(default=ROOM_CENTER, description="hover point [m]")
    amplitude: Vec3 = Field(default=(0.05, 0.05, 0.03), description="position wobble amplitude [m]")
    frequency: Vec3 = Field(default=(0.21, 0.17, 0.13), description="position wobble frequency [Hz]")
    attitude: AttitudeSpec = AttitudeSpec(amplitude=(0.02, 0.02, 0.05), frequency=(0.3, 0.25, 0.1))

    def build(self, truth_seed: int = 0) -> Trajectory:
        pos = _lissajous_channels(self.center, self.amplitude, self.frequency, (0.0, 0.0, 0.0))
        return SinusoidTrajectory(pos, self.attitude.channels(), self.ramp)


class CircleSpec(_Analytic):
    """Horizontal circle at constant speed ``2 pi radius / period`` (after the ramp)."""

    type: Literal["circle"] = "circle"
    center: Vec3 = Field(default=ROOM_CENTER, description="circle centre [m]")
    radius: float = Field(default=2.0, gt=0, description="[m]")
    period: float = Field(default=10.0, gt=0, description="time per lap [s] (counter-clockwise)")
    z_amplitude: float = Field(default=0.0, ge=0, description="vertical oscillation amplitude [m]")
    z_frequency: float = Field(default=0.1, ge=0, description="vertical oscillation frequency [Hz]")
    heading: Literal["follow", "fixed"] = Field(default="follow", description="yaw follows the tangent, or stays fixed")
    attitude: AttitudeSpec = AttitudeSpec(amplitude=(0.1, 0.1, 0.0), frequency=(0.3, 0.23, 0.0))

    def build(self, truth_seed: int = 0) -> Trajectory:
        f = 1.0 / self.period
        cx, cy, cz = self.center
        pos = [
            SinusoidChannel(cx, 0.0, (self.radius,), (f,), (math.pi / 2,)),  # r cos(w tau)
            SinusoidChannel(cy, 0.0, (self.radius,), (f,), (0.0,)),  # r sin(w tau)
            SinusoidChannel(cz, 0.0, (self.z_amplitude,), (self.z_frequency,), (0.0,)),
        ]
        if self.heading == "follow":
            att = self.attitude.channels(extra_yaw_rate=2 * math.pi * f, extra_yaw=math.pi / 2)
        else:
            att = self.attitude.channels()
        return SinusoidTrajectory(pos, att, self.ramp)


class Figure8Spec(_Analytic):
    """Horizontal figure-8 (lemniscate of Gerono): ``x = sx sin(w tau)``, ``y = sy sin(2 w tau)``."""

    type: Literal["figure8"] = "figure8"
    center: Vec3 = Field(default=ROOM_CENTER, description="[m]")
    size: Vec2 = Field(default=(3.0, 1.5), description="half extents along x and y [m]")
    period: float = Field(default=20.0, gt=0, description="time per full figure-8 [s]")
    z_amplitude: float = Field(default=0.3, ge=0, description="[m]")
    z_frequency: float = Field(default=0.1, ge=0, description="[Hz]")
    attitude: AttitudeSpec = AttitudeSpec(amplitude=(0.15, 0.15, 0.4), frequency=(0.3, 0.23, 0.07))

    def build(self, truth_seed: int = 0) -> Trajectory:
        f = 1.0 / self.period
        cx, cy, cz = self.center
        pos = [
            SinusoidChannel(cx, 0.0, (self.size[0],), (f,), (0.0,)),
            SinusoidChannel(cy, 0.0, (self.size[1],), (2 * f,), (0.0,)),
            SinusoidChannel(cz, 0.0, (self.z_amplitude,), (self.z_frequency,), (0.0,)),
        ]
        return SinusoidTrajectory(pos, self.attitude.channels(), self.ramp)


class LissajousSpec(_Analytic):
    """3-D Lissajous ``p_i = center_i + amplitude_i sin(2 pi frequency_i tau + phase_i)`` with attitude excitation."""

    type: Literal["lissajous"] = "lissajous"
    center: Vec3 = Field(default=ROOM_CENTER, description="[m]")
    amplitude: Vec3 = Field(default=(2.8, 2.5, 0.6), description="[m]")
    frequency: Vec3 = Field(default=(0.07, 0.09, 0.13), description="[Hz]")
    phase: Vec3 = Field(default=(0.0, 0.0, 0.0), description="[rad]")
    attitude: AttitudeSpec = AttitudeSpec(amplitude=(0.35, 0.35, 0.8), frequency=(0.3, 0.23, 0.05))

    def build(self, truth_seed: int = 0) -> Trajectory:
        pos = _lissajous_channels(self.center, self.amplitude, self.frequency, self.phase)
        return SinusoidTrajectory(pos, self.attitude.channels(), self.ramp)


class TranslationSpec(_Analytic):
    """Pure translation: Lissajous position, constant attitude (angular velocity exactly zero)."""

    type: Literal["translation"] = "translation"
    center: Vec3 = Field(default=ROOM_CENTER, description="[m]")
    amplitude: Vec3 = Field(default=(2.5, 2.0, 0.5), description="[m]")
    frequency: Vec3 = Field(default=(0.08, 0.1, 0.13), description="[Hz]")
    phase: Vec3 = Field(default=(0.0, 0.0, 0.0), description="[rad]")
    orientation: Vec3 = Field(default=(0.0, 0.0, 0.0), description="constant roll, pitch, yaw [rad]")

    def build(self, truth_seed: int = 0) -> Trajectory:
        pos = _lissajous_channels(self.center, self.amplitude, self.frequency, self.phase)
        return SinusoidTrajectory(pos, [constant_channel(a) for a in self.orientation], self.ramp)


class RotationSpec(_Analytic):
    """Pure rotation about a fixed point (roll, pitch and yaw oscillations plus a yaw spin)."""

    type: Literal["rotation"] = "rotation"
    center: Vec3 = Field(default=ROOM_CENTER, description="fixed IMU position [m]")
    attitude: AttitudeSpec = AttitudeSpec(
        amplitude=(0.6, 0.5, 0.8), frequency=(0.2, 0.15, 0.1), phase=(0.0, 0.0, 0.0), yaw_rate=0.3
    )

    def build(self, truth_seed: int = 0) -> Trajectory:
        return SinusoidTrajectory([constant_channel(c) for c in self.center], self.attitude.channels(), self.ramp)


class RandomSpec(_Analytic):
    """Seeded random smooth motion: per axis a sum of sinusoids of random frequency,
    phase and amplitude (``seeds.truth``), scaled so that the bounds below hold."""

    type: Literal["random"] = "random"
    center: Vec3 = Field(default=ROOM_CENTER, description="[m]")
    extent: Vec3 = Field(default=(3.0, 2.5, 0.7), description="max excursion from centre per axis [m]")
    n_components: int = Field(default=4, ge=1, le=32, description="sinusoids per axis")
    max_frequency: float = Field(default=0.2, gt=0, description="highest position frequency [Hz]")
    max_speed: float = Field(default=1.5, gt=0, description="bound on the speed [m/s]")
    max_accel: float = Field(default=2.0, gt=0, description="bound on the acceleration after the ramp [m/s^2]")
    attitude_amplitude: Vec3 = Field(default=(0.3, 0.3, 1.0), description="max roll, pitch, yaw excursion [rad]")
    attitude_max_frequency: float = Field(default=0.3, gt=0, description="[Hz]")
    max_rate: float = Field(default=1.2, gt=0, description="bound on the body angular rate [rad/s]")

    def build(self, truth_seed: int = 0) -> Trajectory:
        rng = np.random.default_rng(np.random.SeedSequence([int(truth_seed), 0x7A7]))
        K = self.n_components

        def draw(limit_amp, fmax, limit_d1, limit_d2, c0):
            freq = rng.uniform(0.2, 1.0, K) * fmax
            phase = rng.uniform(0.0, 2 * np.pi, K)
            amp = rng.uniform(0.3, 1.0, K) * rng.choice([-1.0, 1.0], K)
            om = 2 * np.pi * freq
            a = np.abs(amp)
            scale = min(limit_amp / a.sum(), limit_d1 / (a * om).sum(), limit_d2 / (a * om * om).sum())
            return SinusoidChannel(c0, 0.0, tuple(amp * scale), tuple(freq), tuple(phase))

        # Per-axis limits split so that the norms of the bounds respect max_speed / max_accel.
        vlim, alim = self.max_speed / math.sqrt(3), self.max_accel / math.sqrt(3)
        pos = [draw(self.extent[i], self.max_frequency, vlim, alim, self.center[i]) for i in range(3)]
        rlim = self.max_rate / 3.0  # |w| <= sum of |Euler rates|
        att = [draw(self.attitude_amplitude[i], self.attitude_max_frequency, rlim, np.inf, 0.0) for i in range(3)]
        return SinusoidTrajectory(pos, att, self.ramp)


class FileSpec(_Spec):
    """Waypoints from a trajectory file (see :mod:`uwbimu.sim.trajfile`), relative to the scenario file."""

    type: Literal["file"] = "file"
    path: str = Field(description="CSV trajectory file; relative paths are relative to the scenario file")
    attitude: Literal["file", "flat"] = Field(
        "file", description="file: the file's attitude; flat: multirotor (roll/pitch from the thrust, yaw from the file)"
    )

    def build(self, truth_seed: int = 0) -> Trajectory:
        from uwbimu.sim.trajfile import load_trajectory_file, read_trajectory_file

        if self.attitude == "flat":
            from uwbimu.sim.flat import FlatSplineTrajectory

            t, p, euler = read_trajectory_file(Path(self.path))
            return FlatSplineTrajectory(t, p, euler[:, 2])
        return load_trajectory_file(Path(self.path))


TrajectorySpec = Annotated[
    Union[HoverSpec, CircleSpec, Figure8Spec, LissajousSpec, TranslationSpec, RotationSpec, RandomSpec, FileSpec],
    Field(discriminator="type"),
]

TRAJECTORY_TYPES: dict[str, type] = {
    "hover": HoverSpec,
    "circle": CircleSpec,
    "figure8": Figure8Spec,
    "lissajous": LissajousSpec,
    "translation": TranslationSpec,
    "rotation": RotationSpec,
    "random": RandomSpec,
    "file": FileSpec,
}
