"""The reference model: one formula, two backends (NumPy, CasADi), and its physics."""

import casadi as ca
import numpy as np
import pytest

from uwbimu.models import quaternion as Q
from uwbimu.models import reference as M
from uwbimu.models import state as S
from uwbimu.models.imu import BMI088, ICM20948, imu_preset


def random_state(rng, t_d=0.03):
    return S.make_state(
        p=rng.normal(size=3),
        v=rng.normal(size=3),
        q=rng.normal(size=4),
        b_a=0.1 * rng.normal(size=3),
        b_g=0.01 * rng.normal(size=3),
        p_IU=0.2 * rng.normal(size=3),
        t_d=t_d,
    )


def test_numpy_and_casadi_backends_agree():
    rng = np.random.default_rng(0)
    ops = M.casadi_ops()
    xs, us, ans = ca.SX.sym("x", 20), ca.SX.sym("u", 6), ca.SX.sym("a", 3)
    f_sym = ca.Function("f", [xs, us], [M.continuous_dynamics(xs, us, ops)])
    h_sym = ca.Function("h", [xs, ans], [M.range_measurement(xs, ans, ops)])
    f0s, Fs = M.control_affine_fields(xs, ops)
    fields_sym = ca.Function("fields", [xs], [f0s, Fs])
    for _ in range(10):
        x, u, a = random_state(rng), rng.normal(size=6), rng.normal(size=3) * 3
        np.testing.assert_allclose(np.array(f_sym(x, u)).ravel(), M.continuous_dynamics(x, u), atol=1e-12)
        assert float(h_sym(x, a)) == pytest.approx(M.range_measurement(x, a), abs=1e-12)
        f0, F = fields_sym(x)
        f0n, Fn = M.control_affine_fields(x)
        np.testing.assert_allclose(np.array(f0).ravel(), f0n, atol=1e-12)
        np.testing.assert_allclose(np.array(F), Fn, atol=1e-12)


def test_control_affine_form_equals_dynamics():
    rng = np.random.default_rng(1)
    for _ in range(10):
        x, u = random_state(rng), rng.normal(size=6)
        f0, F = M.control_affine_fields(x)
        np.testing.assert_allclose(f0 + F @ u, M.continuous_dynamics(x, u), atol=1e-12)


def test_accelerometer_reads_plus_g_at_rest():
    a_m, w_m = M.imu_measurement(Q.quat_identity(), np.zeros(3), np.zeros(3), np.zeros(3), np.zeros(3))
    np.testing.assert_allclose(a_m, [0, 0, 9.81])
    np.testing.assert_allclose(w_m, 0)
    # At rest the kinematics then give zero acceleration.
    x = S.make_state()
    np.testing.assert_allclose(M.continuous_dynamics(x, np.r_[a_m, w_m])[S.V], 0, atol=1e-12)


def test_range_includes_lever_arm():
    q = Q.quat_exp(np.array([0, 0, np.pi / 2]))  # yaw 90 deg: body x -> world y
    x = S.make_state(p=[1, 2, 3], q=q, p_IU=[0.5, 0, 0])
    np.testing.assert_allclose(M.antenna_position(x), [1, 2.5, 3], atol=1e-12)
    assert M.range_measurement(x, np.array([1, 2.5, 5])) == pytest.approx(2.0)


def test_time_offset_convention():
    # An IMU sample stamped s describes UWB time s - t_d, so a range at UWB time t
    # sees the IMU-clock instant t + t_d.
    assert M.imu_time_of_range(10.0, 0.03) == pytest.approx(10.03)


def test_propagate_constant_rotation_and_acceleration_exactly():
    # Constant body rate and a specific force that keeps a constant world acceleration
    # cannot be represented by constant IMU readings unless rotation is zero; check the
    # pure-translation and pure-rotation cases separately against closed forms.
    x = S.make_state(p=[0, 0, 1], v=[1, 0, 0])
    a_world = np.array([0.2, -0.1, 0.3])
    u = np.r_[a_world + M.G_WORLD, 0, 0, 0]
    dt, n = 0.01, 100
    for _ in range(n):
        x = M.propagate(x, u, u, dt)
    T = dt * n
    np.testing.assert_allclose(x[S.P], [0, 0, 1] + np.array([1, 0, 0]) * T + 0.5 * a_world * T**2, atol=1e-12)
    w = np.array([0.3, -0.2, 0.5])
    x = S.make_state()
    u = np.r_[0, 0, 9.81, w]
    for _ in range(n):
        x = M.propagate(x, u, u, dt)
    np.testing.assert_allclose(Q.quat_log(x[S.Q]), w * T, atol=1e-9)


def test_boxplus_boxminus_roundtrip():
    rng = np.random.default_rng(3)
    x = random_state(rng)
    dx = 0.1 * rng.normal(size=S.ERROR_DIM)
    np.testing.assert_allclose(S.boxminus(S.boxplus(x, dx), x), dx, atol=1e-12)


def test_imu_presets_and_discretisation():
    s = BMI088.discrete_sigmas(0.005)
    assert s["gyro"] == pytest.approx(BMI088.gyro_noise_density / np.sqrt(0.005))
    assert s["accel_bias_step"] == pytest.approx(BMI088.accel_bias_rw * np.sqrt(0.005))
    assert imu_preset("ICM-20948") is ICM20948
    with pytest.raises(KeyError, match="unknown IMU preset"):
        imu_preset("nope")
    with pytest.raises(ValueError):
        BMI088.discrete_sigmas(0.0)
