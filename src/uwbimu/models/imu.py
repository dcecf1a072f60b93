"""IMU noise model: continuous-time densities, discrete sampling, presets.

The IMU is modelled as (seed 001 eq. 2-3)::

    w_m = w + b_g + n_g,            b_g' = n_bg
    a_m = R^T (p'' + g e_z) + b_a + n_a,   b_a' = n_ba

with white noises given as *continuous-time densities*:

* ``gyro_noise_density``   sigma_g  [rad/s/sqrt(Hz)]   (angle random walk)
* ``accel_noise_density``  sigma_a  [m/s^2/sqrt(Hz)]   (velocity random walk)
* ``gyro_bias_rw``         sigma_bg [rad/s^2/sqrt(Hz)] (bias random walk)
* ``accel_bias_rw``        sigma_ba [m/s^3/sqrt(Hz)]

Sampled at period ``dt`` the white noise has per-sample standard deviation
``sigma / sqrt(dt)`` and the bias random walk steps by ``sigma_b * sqrt(dt)``.
"""

from __future__ import annotations

from uwbimu.errors import UsageError
import math

from pydantic import BaseModel, ConfigDict, Field


class ImuNoise(BaseModel):
    """Continuous-time IMU noise densities (SI units, per axis)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    gyro_noise_density: float = Field(ge=0, description="rad/s/sqrt(Hz)")
    accel_noise_density: float = Field(ge=0, description="m/s^2/sqrt(Hz)")
    gyro_bias_rw: float = Field(ge=0, description="rad/s^2/sqrt(Hz)")
    accel_bias_rw: float = Field(ge=0, description="m/s^3/sqrt(Hz)")
    gyro_bias_sigma0: float = Field(default=0.0, ge=0, description="initial gyro bias sd, rad/s")
    accel_bias_sigma0: float = Field(default=0.0, ge=0, description="initial accel bias sd, m/s^2")

    def discrete_sigmas(self, dt: float) -> dict[str, float]:
        """Per-sample white-noise sd and per-step bias increment sd for period ``dt``."""
        if dt <= 0:
            raise UsageError(f"dt must be positive, got {dt}")
        return {
            "gyro": self.gyro_noise_density / math.sqrt(dt),
            "accel": self.accel_noise_density / math.sqrt(dt),
            "gyro_bias_step": self.gyro_bias_rw * math.sqrt(dt),
            "accel_bias_step": self.accel_bias_rw * math.sqrt(dt),
        }

    def scaled(self, factor: float) -> "ImuNoise":
        """All densities multiplied by ``factor`` (e.g. 0 for a noise-free IMU)."""
        d = self.model_dump()
        return ImuNoise(**{k: v * factor for k, v in d.items()})


def _dps(x: float) -> float:
    return x * math.pi / 180.0


#: Bosch BMI088 class (datasheet: gyro 0.014 deg/s/sqrt(Hz), accel 175 ug/sqrt(Hz));
#: bias instabilities translated to random-walk densities as commonly tuned for VIO.
BMI088 = ImuNoise(
    gyro_noise_density=_dps(0.014),
    accel_noise_density=175e-6 * 9.81,
    gyro_bias_rw=2.0e-5,
    accel_bias_rw=3.0e-4,
    gyro_bias_sigma0=_dps(0.5),
    accel_bias_sigma0=0.05,
)

#: TDK ICM-20948 class (datasheet: gyro 0.015 deg/s/sqrt(Hz), accel 230 ug/sqrt(Hz)).
ICM20948 = ImuNoise(
    gyro_noise_density=_dps(0.015),
    accel_noise_density=230e-6 * 9.81,
    gyro_bias_rw=4.0e-5,
    accel_bias_rw=6.0e-4,
    gyro_bias_sigma0=_dps(1.0),
    accel_bias_sigma0=0.1,
)

#: A noise-free IMU (for tests of the kinematics).
IDEAL = ImuNoise(gyro_noise_density=0.0, accel_noise_density=0.0, gyro_bias_rw=0.0, accel_bias_rw=0.0)

IMU_PRESETS: dict[str, ImuNoise] = {"bmi088": BMI088, "icm20948": ICM20948, "ideal": IDEAL}


def imu_preset(name: str) -> ImuNoise:
    """Look up a preset by (case-insensitive) name, with a clear error."""
    key = name.lower().replace("-", "").replace("_", "")
    if key not in IMU_PRESETS:
        raise KeyError(f"unknown IMU preset {name!r}; choose one of {', '.join(map(str, sorted(IMU_PRESETS)))}")
    return IMU_PRESETS[key]
