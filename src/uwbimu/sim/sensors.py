"""Vectorised sensor models, pinned to :mod:`uwbimu.models.reference` by tests.

These re-express, for whole batches, exactly the relations of the reference
model (``tests/test_sim_sensors.py`` compares them sample by sample):

* :func:`imu_measurements` = :func:`uwbimu.models.reference.imu_measurement`
  ``a_m = R^T (a + g e_z) + b_a + n_a``, ``w_m = w + b_g + n_g``;
* :func:`antenna_positions` / :func:`ranges` =
  :func:`uwbimu.models.reference.antenna_position` /
  :func:`~uwbimu.models.reference.range_measurement`
  ``|| anchor - (p + R p_IU) ||``.
"""

from __future__ import annotations

import numpy as np

from uwbimu.models.imu import ImuNoise
from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.models.reference import G_WORLD


def imu_measurements(q, acc_world, omega_body, b_a=0.0, b_g=0.0, n_a=0.0, n_g=0.0):
    """Batched IMU readings ``(a_m, w_m)``, each ``(N, 3)`` [m/s^2, rad/s].

    Parameters
    ----------
    q : (N, 4) attitude (body -> world); acc_world : (N, 3) ``p''`` [m/s^2];
    omega_body : (N, 3) [rad/s]; b_a, b_g, n_a, n_g : (N, 3) or broadcastable.
    """
    R = quat_to_rotmat(q)
    f = np.einsum("nji,nj->ni", R, np.asarray(acc_world, dtype=float) + G_WORLD)  # R^T (a + g)
    return f + b_a + n_a, np.asarray(omega_body, dtype=float) + b_g + n_g


def antenna_positions(p, q, lever_arm) -> np.ndarray:
    """World antenna positions ``p + R(q) p_IU``, ``(N, 3)`` [m]."""
    R = quat_to_rotmat(q)
    return np.asarray(p, dtype=float) + R @ np.asarray(lever_arm, dtype=float)


def ranges(p, q, lever_arm, anchors) -> np.ndarray:
    """Noise-free ranges ``|| anchor_n - (p_n + R(q_n) p_IU) ||`` [m].

    ``anchors`` is ``(N, 3)`` (one anchor per instant) or ``(3,)``.
    """
    d = np.asarray(anchors, dtype=float) - antenna_positions(p, q, lever_arm)
    return np.sqrt(np.einsum("ni,ni->n", d, d))


def bias_random_walk(b0, step_sd: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """``(n, 3)`` bias samples: ``b[0] = b0``, ``b[k+1] = b[k] + step_sd * N(0, I)``."""
    steps = rng.standard_normal((n, 3)) * step_sd
    steps[0] = 0.0
    return np.asarray(b0, dtype=float) + np.cumsum(steps, axis=0)


def imu_noise_streams(noise: ImuNoise, dt: float, n: int, b_a0, b_g0, rng: np.random.Generator):
    """White noises and bias random walks for ``n`` samples at period ``dt``.

    Returns ``(n_a, n_g, b_a, b_g)``, each ``(n, 3)``.  The draws are made in a
    fixed order so that a given generator state always gives the same streams.
    """
    sig = noise.discrete_sigmas(dt)
    n_a = rng.standard_normal((n, 3)) * sig["accel"]
    n_g = rng.standard_normal((n, 3)) * sig["gyro"]
    b_a = bias_random_walk(b_a0, sig["accel_bias_step"], n, rng)
    b_g = bias_random_walk(b_g0, sig["gyro_bias_step"], n, rng)
    return n_a, n_g, b_a, b_g
