"""Simulator and reference model agree: integrating the ideal IMU stream recovers the truth.

For every trajectory type a noise-free, bias-free 200 Hz IMU stream of 60 s
is integrated from the true initial state with the reference kinematics
(:func:`uwbimu.models.reference.continuous_dynamics`, classical RK4) and must
stay within 1 mm of the ground truth.

Note on the integrator: :func:`uwbimu.models.reference.integrate_imu` takes
the mid-interval IMU input from the 4-point cubic through the neighbouring
samples (:func:`uwbimu.models.reference.midpoint_inputs`).  The plain linear
average (``cubic=False``) leaves an O(dt^2) attitude error that does not
cancel when the body rotates (coning): at 200 Hz it drifts 3-90 mm in 60 s on
the rotating trajectories (``test_linear_input_error_is_its_interpolation``).
"""

import numpy as np
import pytest

from uwbimu.models import reference as M
from uwbimu.models import state as S
from uwbimu.models.quaternion import quat_conjugate, quat_log, quat_multiply, quat_slerp
from uwbimu.sim import Scenario, builtin_scenario, simulate, simulate_full, write_trajectory_file
from uwbimu.models.reference import midpoint_inputs
from uwbimu.sim.trajectory import euler_zyx_to_quat

TYPES = ["hover", "circle", "figure8", "lissajous", "random", "translation", "rotation"]


def ideal(sc: Scenario, **update) -> Scenario:
    imu = {"noise": "ideal", "accel_bias": (0, 0, 0), "gyro_bias": (0, 0, 0)}
    return sc.updated(imu=imu, uwb={"sigma": 0.0}, **update)


def truth_arrays(ds):
    g = ds.groundtruth
    return (
        g[["px", "py", "pz"]].to_numpy(),
        g[["vx", "vy", "vz"]].to_numpy(),
        g[["qw", "qx", "qy", "qz"]].to_numpy(),
    )


def errors(ds, X):
    p, v, q = truth_arrays(ds)
    dp = np.linalg.norm(X[:, S.P] - p, axis=1)
    dv = np.linalg.norm(X[:, S.V] - v, axis=1)
    dth = np.linalg.norm(quat_log(quat_multiply(quat_conjugate(q), X[:, S.Q])), axis=1)
    return dp, dv, dth


def initial_state(ds, p_IU=(0, 0, 0), t_d=0.0):
    p, v, q = truth_arrays(ds)
    return S.make_state(p=p[0], v=v[0], q=q[0], p_IU=p_IU, t_d=t_d)


def check_recovers_truth(ds):
    assert ds.duration == pytest.approx(60.0)
    assert len(ds.imu) == 12001
    X = M.integrate_imu(initial_state(ds), ds.imu_t, ds.imu_u)
    dp, dv, dth = errors(ds, X)
    assert dp.max() < 1e-3, f"position drift {dp.max() * 1e3:.3f} mm"
    assert dv.max() < 1e-4, f"velocity error {dv.max():.2e} m/s"
    assert dth.max() < 1e-5, f"attitude error {dth.max():.2e} rad"
    return X


@pytest.mark.parametrize("kind", TYPES)
def test_ideal_imu_integrates_to_truth(kind):
    sc = ideal(builtin_scenario(kind), time_offset=0.0)
    assert sc.trajectory.type == kind
    ds = simulate(sc)
    np.testing.assert_array_equal(ds.groundtruth["t"].to_numpy(), ds.imu_t)  # t_d = 0
    check_recovers_truth(ds)


def test_ideal_imu_of_trajectory_file_integrates_to_truth(tmp_path):
    # Waypoints every 0.5 s of a smooth 3-D path with roll/pitch/yaw motion.
    t = np.arange(0.0, 60.0 + 1e-9, 0.5)
    p = np.column_stack([5 + 2.5 * np.sin(0.1 * t), 4 + 2 * np.sin(0.13 * t + 0.5), 1.5 + 0.4 * np.sin(0.2 * t)])
    e = np.column_stack([0.3 * np.sin(0.7 * t), 0.25 * np.sin(0.5 * t), 2.0 * np.sin(0.2 * t) + 0.2 * t])
    write_trajectory_file(tmp_path / "path.csv", t, p, q=euler_zyx_to_quat(e))
    base = ideal(builtin_scenario("calibration-flight"), time_offset=0.0).model_dump()
    sc = Scenario.model_validate(
        {**base, "duration": None, "trajectory": {"type": "file", "path": str(tmp_path / "path.csv")}}
    )
    assert sc.duration is None  # the file's span (60 s) is used
    ds = simulate(sc)
    check_recovers_truth(ds)
    # the spline passes through the waypoints (times shifted to start at 0; ends at rest)
    gt = ds.groundtruth.set_index(np.round(ds.groundtruth["t"].to_numpy(), 6))
    np.testing.assert_allclose(gt.loc[np.round(t, 6), ["px", "py", "pz"]].to_numpy(), p, atol=1e-9)


def test_time_offset_stamps_and_range_instants():
    """With t_d != 0: IMU row k is the motion at UWB time s_k - t_d, and a range
    stamped t observes the state integrated to IMU time t + t_d."""
    t_d = 0.03
    sc = ideal(builtin_scenario("calibration-flight"), time_offset=t_d)
    res = simulate_full(sc)
    ds = res.dataset
    np.testing.assert_allclose(ds.groundtruth["t"].to_numpy(), ds.imu_t - t_d, atol=1e-12)
    assert ds.imu_t[0] == 0.0 and ds.meta.truth.time_offset == t_d
    X = check_recovers_truth(ds)

    lever = np.array(ds.meta.truth.lever_arm)
    A = ds.anchor_positions()
    dt = 1.0 / ds.meta.imu_rate_hz
    uwb = ds.uwb.iloc[50::7]  # a spread of ranges is enough
    k = np.rint((uwb["t"].to_numpy() + t_d) / dt).astype(int)  # IMU index of t + t_d (exact grid here)
    np.testing.assert_allclose(ds.imu_t[k], uwb["t"].to_numpy() + t_d, atol=1e-9)
    pred, wrong = [], []
    for kk, a in zip(k, uwb["anchor"]):
        x = X[kk].copy()
        x[S.PIU] = lever
        x[S.TD] = t_d
        pred.append(M.range_measurement(x, A[a]))
        xw = X[kk - 12].copy()  # the opposite sign convention: IMU time t - t_d
        xw[S.PIU] = lever
        wrong.append(M.range_measurement(xw, A[a]))
    err = np.abs(np.array(pred) - uwb["range"].to_numpy())
    assert err.max() < 1e-5
    assert np.abs(np.array(wrong) - uwb["range"].to_numpy()).max() > 100 * err.max()


def _interp_truth(ds, t):
    """Cubic-Hermite position (uses the true velocity) and slerp attitude at UWB times ``t``."""
    gt_t = ds.groundtruth["t"].to_numpy()
    p, v, q = truth_arrays(ds)
    i = np.clip(np.searchsorted(gt_t, t, side="right") - 1, 0, len(gt_t) - 2)
    h = gt_t[i + 1] - gt_t[i]
    s = ((t - gt_t[i]) / h)[:, None]
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    pos = h00 * p[i] + h10 * h[:, None] * v[i] + h01 * p[i + 1] + h11 * h[:, None] * v[i + 1]
    att = quat_slerp(q[i], q[i + 1], s[:, 0])
    return pos, att


@pytest.mark.parametrize("name", ["calibration-flight", "two-tags"])
def test_noise_free_ranges_equal_geometric_distance(name):
    sc = ideal(builtin_scenario(name), time_offset=0.05)
    ds = simulate(sc)
    t = ds.uwb["t"].to_numpy()
    pos, att = _interp_truth(ds, t)  # ground truth is on the UWB clock: no offset to apply
    A = ds.anchor_positions()
    levers = ds.meta.truth.tags
    tags = ds.uwb["tag"].to_numpy() if "tag" in ds.uwb else np.full(len(t), "tag0")
    assert ("tag" in ds.uwb) == (name == "two-tags")
    pred = np.array(
        [
            M.range_measurement(S.make_state(p=pk, q=qk, p_IU=levers[tg], t_d=0.05), A[a])
            for pk, qk, tg, a in zip(pos, att, tags, ds.uwb["anchor"])
        ]
    )
    np.testing.assert_allclose(ds.uwb["range"].to_numpy(), pred, atol=1e-6)
    # the lever arm matters at this tolerance
    no_lever = np.array([M.range_measurement(S.make_state(p=pk, q=qk), A[a]) for pk, qk, a in zip(pos, att, ds.uwb["anchor"])])
    assert np.abs(no_lever - pred).max() > 0.05


def test_linear_input_error_is_its_interpolation():
    """reference.integrate_imu with cubic=False (linear input) is exact enough without rotation, and on a
    rotating trajectory its drift falls ~4x when the rate doubles (O(dt^2) interpolation
    error of the integrator, not a simulator inconsistency)."""
    ds = simulate(ideal(builtin_scenario("translation"), time_offset=0.0))
    X = M.integrate_imu(initial_state(ds), ds.imu_t, ds.imu_u, cubic=False)
    assert errors(ds, X)[0].max() < 1e-4

    drift = {}
    for rate in (100.0, 200.0):
        sc = ideal(builtin_scenario("rotation"), time_offset=0.0, duration=10.0).updated(imu={"rate_hz": rate})
        ds = simulate(sc)
        X = M.integrate_imu(initial_state(ds), ds.imu_t, ds.imu_u, cubic=False)
        drift[rate] = errors(ds, X)[2][-1]  # attitude error at the end [rad]
    ratio = drift[100.0] / drift[200.0]
    assert 3.0 < ratio < 5.0, (drift, ratio)


def test_midpoint_inputs_exact_for_cubics_on_any_grid():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.uniform(0.002, 0.008, 40))
    c = rng.normal(size=(4, 6))
    poly = lambda x: c[0] + np.outer(x, c[1]) + np.outer(x**2, c[2]) + np.outer(x**3, c[3])  # noqa: E731
    um = midpoint_inputs(t, poly(t))
    np.testing.assert_allclose(um, poly(0.5 * (t[:-1] + t[1:])), rtol=1e-9, atol=1e-9)
    tu = np.arange(10) * 0.005
    u = rng.normal(size=(10, 6))
    np.testing.assert_allclose(midpoint_inputs(tu, u)[1:-1], (-u[:-3] + 9 * u[1:-2] + 9 * u[2:-1] - u[3:]) / 16, atol=1e-12)
    np.testing.assert_allclose(midpoint_inputs(tu[:3], u[:3]), 0.5 * (u[:2] + u[1:3]))
