"""Trajectories: analytic derivatives, Euler attitude, soft start, file format, built-in limits."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from uwbimu.models.quaternion import quat_conjugate, quat_log, quat_multiply, quat_to_rotmat
from uwbimu.sim import TrajectoryFileError, builtin_scenario, list_scenarios, read_trajectory_file, write_trajectory_file
from uwbimu.sim.scenario import ANCHOR_PRESETS
from uwbimu.sim.trajectory import (
    euler_rates_to_body_rate,
    euler_zyx_to_quat,
    quat_to_euler_zyx,
    soft_start,
)
from uwbimu.sim.trajspec import TRAJECTORY_TYPES, FileSpec

ANALYTIC = [k for k in TRAJECTORY_TYPES if k != "file"]


@pytest.fixture(scope="module")
def file_trajectory(tmp_path_factory):
    path = tmp_path_factory.mktemp("traj") / "wp.csv"
    t = np.arange(0.0, 30.0 + 1e-9, 0.25)
    p = np.column_stack([5 + 2 * np.sin(0.2 * t), 4 + np.sin(0.3 * t), 1.5 + 0.3 * np.cos(0.25 * t)])
    e = np.column_stack([0.2 * np.sin(0.6 * t), 0.2 * np.sin(0.4 * t), 3.0 * np.sin(0.15 * t)])
    write_trajectory_file(path, t, p, q=euler_zyx_to_quat(e))
    return FileSpec(path=str(path)).build()


def trajectories(file_trajectory):
    out = {k: TRAJECTORY_TYPES[k]().build(truth_seed=3) for k in ANALYTIC}
    out["file"] = file_trajectory
    return out


def test_euler_quaternion_matches_scipy():
    rng = np.random.default_rng(0)
    e = rng.uniform([-3, -1.4, -3], [3, 1.4, 3], size=(200, 3))
    q = euler_zyx_to_quat(e)
    R_ref = Rotation.from_euler("ZYX", e[:, ::-1]).as_matrix()  # intrinsic yaw, pitch, roll
    np.testing.assert_allclose(quat_to_rotmat(q), R_ref, atol=1e-12)
    np.testing.assert_allclose(quat_to_euler_zyx(q), e, atol=1e-9)


def test_soft_start_is_at_rest_then_unit_speed():
    t = np.array([-1.0, 0.0, 0.5, 1.0, 2.0, 5.0])
    tau, d1, d2 = soft_start(t, 2.0)
    np.testing.assert_allclose(tau[:2], 0.0)
    np.testing.assert_allclose(d1[:2], 0.0)
    np.testing.assert_allclose(d2[:2], 0.0)
    np.testing.assert_allclose(d1[-2:], 1.0)
    np.testing.assert_allclose(tau[-1], 1.0 + 3.0)  # ramp/2 + (t - ramp)
    # derivatives by finite differences
    h = 1e-6
    tt = np.linspace(0.01, 2.5, 50)
    np.testing.assert_allclose((soft_start(tt + h, 2.0)[0] - soft_start(tt - h, 2.0)[0]) / (2 * h), soft_start(tt, 2.0)[1], atol=1e-7)
    np.testing.assert_allclose((soft_start(tt + h, 2.0)[1] - soft_start(tt - h, 2.0)[1]) / (2 * h), soft_start(tt, 2.0)[2], atol=1e-6)


@pytest.mark.parametrize("kind", ANALYTIC + ["file"])
def test_analytic_derivatives_match_finite_differences(kind, file_trajectory):
    traj = trajectories(file_trajectory)[kind]
    t = np.concatenate([np.linspace(0.05, 2.5, 40), np.linspace(2.5, 29.0, 200)])  # ramp and cruise
    h = 1e-4
    p_m, v_m, _ = traj.position(t - h)
    p_p, v_p, _ = traj.position(t + h)
    p, v, a = traj.position(t)
    np.testing.assert_allclose((p_p - p_m) / (2 * h), v, atol=1e-6)
    np.testing.assert_allclose((v_p - v_m) / (2 * h), a, atol=1e-5)
    s = traj.sample(t)
    s_m, s_p = traj.sample(t - h), traj.sample(t + h)
    # body rate from the attitude alone: Log(q(t-h)^* q(t+h)) / 2h
    w_fd = quat_log(quat_multiply(quat_conjugate(s_m.q), s_p.q)) / (2 * h)
    np.testing.assert_allclose(w_fd, s.w, atol=1e-6)
    np.testing.assert_allclose((s_p.euler - s_m.euler) / (2 * h), s.euler_rate, atol=1e-6)
    # at rest at the start
    s0 = traj.sample(np.array([-0.5, 0.0]))
    np.testing.assert_allclose(np.c_[s0.v, s0.a, s0.w], 0.0, atol=1e-12)


def test_translation_has_exactly_zero_rotation():
    traj = TRAJECTORY_TYPES["translation"](orientation=(0.1, -0.2, 1.0)).build()
    s = traj.sample(np.linspace(0, 60, 1001))
    assert np.all(s.w == 0.0)
    assert np.all(s.q == s.q[0])
    assert np.ptp(s.p, axis=0).min() > 0.5


def test_rotation_has_fixed_position_and_three_axis_motion():
    s = TRAJECTORY_TYPES["rotation"]().build().sample(np.linspace(0, 60, 3001))
    assert np.all(s.p == s.p[0]) and np.all(s.v == 0) and np.all(s.a == 0)
    assert (np.abs(s.w).max(axis=0) > 0.3).all()


def test_euler_rate_map_columns_are_unit_vectors():
    rng = np.random.default_rng(1)
    e = rng.normal(size=(50, 3))
    for i in range(3):
        ed = np.zeros((50, 3))
        ed[:, i] = 1.0
        np.testing.assert_allclose(np.linalg.norm(euler_rates_to_body_rate(e, ed), axis=1), 1.0)


def test_random_trajectory_is_seeded():
    spec = TRAJECTORY_TYPES["random"]()
    t = np.linspace(0, 30, 301)
    a = spec.build(truth_seed=5).sample(t)
    b = spec.build(truth_seed=5).sample(t)
    c = spec.build(truth_seed=6).sample(t)
    np.testing.assert_array_equal(a.p, b.p)
    np.testing.assert_array_equal(a.q, b.q)
    assert np.abs(a.p - c.p).max() > 0.1
    bounds = spec.build(truth_seed=5).bounds()
    assert bounds["speed"] <= spec.max_speed + 1e-9 and bounds["rate"] <= spec.max_rate + 1e-9


@pytest.mark.parametrize("name", list(list_scenarios()))
def test_builtins_fly_like_a_small_drone_inside_the_room(name):
    sc = builtin_scenario(name)
    traj = sc.trajectory.build(sc.seeds.truth)
    s = traj.sample(np.arange(-0.1, sc.duration + 1e-9, 0.01))
    assert np.linalg.norm(s.v, axis=1).max() <= 2.0
    assert np.linalg.norm(s.a, axis=1).max() <= 3.0
    assert np.linalg.norm(s.w, axis=1).max() <= 2.0
    assert sc.anchors in ("room8", "bitcraze8")
    # inside the anchors' box with a margin (0.5 m horizontally, 0.3 m from floor and ceiling)
    A = sc.anchor_positions()
    lo = A.min(axis=0) + np.array([0.5, 0.5, 0.3])
    hi = A.max(axis=0) - np.array([0.5, 0.5, 0.3])
    assert (s.p >= lo).all() and (s.p <= hi).all()


def test_room8_anchors_are_staggered_and_not_coplanar():
    A = np.array(list(ANCHOR_PRESETS["room8"].values()))
    assert len(A) == 8
    low, high = A[A[:, 2] < 1.0], A[A[:, 2] > 2.0]
    assert len(low) == 4 and len(high) == 4
    assert len(np.unique(A[:, 2])) >= 6  # staggered heights
    # not coplanar: the centred coordinates have full rank with a clear margin
    assert np.linalg.svd(A - A.mean(0), compute_uv=False).min() > 1.0


# --- trajectory file format --------------------------------------------------------------


def test_trajectory_file_round_trip_with_yaw(tmp_path):
    t = np.array([2.0, 3.0, 4.0, 5.0])
    p = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1.0]])
    yaw = np.array([0.0, 3.0, 6.0, 9.0])  # beyond pi: must not be wrapped
    path = write_trajectory_file(tmp_path / "y.csv", t, p, yaw=yaw)
    tt, pp, e = read_trajectory_file(path)
    np.testing.assert_allclose(tt, t - 2.0)
    np.testing.assert_allclose(pp, p)
    np.testing.assert_allclose(e[:, 2], yaw)
    np.testing.assert_allclose(e[:, :2], 0.0)


def test_quaternion_yaw_is_unwrapped(tmp_path):
    t = np.arange(0, 10.0, 0.5)
    yaw = 1.2 * t  # several turns
    q = euler_zyx_to_quat(np.column_stack([0 * t, 0 * t, yaw]))
    _, _, e = read_trajectory_file(write_trajectory_file(tmp_path / "q.csv", t, np.zeros((len(t), 3)), q=q))
    np.testing.assert_allclose(e[:, 2], yaw, atol=1e-9)


@pytest.mark.parametrize(
    "text, needle",
    [
        ("t,px,py\n0,1,2\n1,1,2\n", "missing column(s) pz;"),
        ("t,px,py,pz,pX\n0,1,2,3,4\n1,1,2,3,4\n", "unknown column(s) pX;"),
        ("t,px,py,pz\n0,1,2,3\n1,1,x,3\n", "row 2 (line 3), column 'py'"),
        ("t,px,py,pz\n0,1,2,3\n1,1,nan,3\n", "row 2 (line 3), column 'py'"),
        ("t,px,py,pz\n0,1,2,3\n1,1,2,3\n1,1,2,3\n", "row 3 (line 4), column 't'"),
        ("t,px,py,pz,qw,qx\n0,1,2,3,1,0\n1,1,2,3,1,0\n", "quaternion needs all of"),
        ("t,px,py,pz\n0,1,2,3\n", "at least 2 rows"),
        ("t,px,py,pz,qw,qx,qy,qz\n0,1,2,3,1,0,0,0\n1,1,2,3,0.7071,0,0.7071,0\n", "row 2 (line 3), attitude: pitch"),
        ("", "empty"),
    ],
)
def test_trajectory_file_errors_name_file_row_column(tmp_path, text, needle):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(TrajectoryFileError) as err:
        read_trajectory_file(path)
    assert str(path) in str(err.value)
    assert needle in str(err.value)
