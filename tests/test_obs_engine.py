"""Engine of the Lie-derivative rank test: user models, pinning to the reference, manifold, naming."""

from __future__ import annotations

import casadi as ca
import numpy as np
import pytest

from uwbimu.models import reference as ref
from uwbimu.models import state as S
from uwbimu.observability.engine import ControlAffineModel, LieObservability, ObservabilityCache, numerical_rank
from uwbimu.observability.models import (
    PointMassSpec,
    UwbImuSpec,
    compiled_point_mass,
    compiled_uwb_imu,
    sample_uwb_imu_state,
    uwb_imu_model,
)
from uwbimu.observability.structural import structural_verdict


def linear_model(A: np.ndarray, C: np.ndarray) -> ControlAffineModel:
    """A user-defined model in a few lines (the documented example)."""
    n = A.shape[0]
    x = ca.SX.sym("x", n)
    return ControlAffineModel(
        name="linear",
        x=x,
        params=ca.SX(0, 1),
        drift=ca.mtimes(ca.DM(A), x),
        fields=[],
        field_names=[],
        outputs=ca.mtimes(ca.DM(C), x),
        state_names=[f"x{i}" for i in range(n)],
        sampler=lambda rng: (rng.normal(size=n), np.zeros(0)),
    )


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_linear_system_matches_kalman_rank(seed):
    rng = np.random.default_rng(seed)
    n = 5
    # a block structure with a known unobservable part: x3, x4 never reach y
    A = rng.normal(size=(n, n))
    A[:3, 3:] = 0.0
    C = np.c_[rng.normal(size=(1, 3)), np.zeros((1, 2))]
    kalman = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(n)])
    expected = np.linalg.matrix_rank(kalman)
    eng = LieObservability(linear_model(A, C), order=n - 1)
    r = eng.rank_test(rng.normal(size=n), ())
    assert expected == 3
    assert r.rank == expected and r.dim == n
    # the unobservable directions are exactly span(e3, e4)
    N = r.null_space
    assert N.shape == (n, 2)
    assert np.allclose(np.abs(N[:3]).max(), 0.0, atol=1e-9)


def test_user_unicycle_in_a_few_lines():
    # planar unicycle with range to the origin: rotation about the origin is unobservable
    x = ca.SX.sym("x", 3)  # px, py, heading
    model = ControlAffineModel(
        name="unicycle", x=x, params=ca.SX(0, 1),
        drift=ca.vertcat(ca.cos(x[2]), ca.sin(x[2]), 0),
        fields=[ca.vertcat(0, 0, 1)], field_names=["turn"],
        outputs=ca.sumsqr(x[0:2]), state_names=["px", "py", "th"],
        sampler=lambda rng: (rng.normal(size=3), np.zeros(0)),
    )  # fmt: skip
    r = LieObservability(model, order=3).rank_test([1.0, 2.0, 0.3])
    assert r.rank == 2
    gen = np.array([-2.0, 1.0, 1.0]) / np.sqrt(6)  # d/dalpha of a rotation about the origin
    assert abs(abs(r.null_space[:, 0] @ gen) - 1) < 1e-9


def test_uwb_model_pinned_to_reference():
    """The symbolic model evaluates to the reference functions (same lines, checked)."""
    model = uwb_imu_model(UwbImuSpec(3))
    rng = np.random.default_rng(5)
    A = rng.uniform(-5, 5, (3, 3))
    u0 = rng.normal(size=6)
    fh = ca.Function("h", [model.x, model.params], [model.outputs, model.drift, ca.horzcat(*model.fields)])
    for _ in range(5):
        x = sample_uwb_imu_state(rng)
        x20 = np.r_[x, 0.0]
        h, f, F = (np.asarray(v) for v in fh(x, np.r_[A.ravel(), u0]))
        ranges = np.array([ref.range_measurement(x20, a) for a in A])
        assert np.allclose(h.ravel(), 0.5 * ranges**2, rtol=1e-12)
        assert np.allclose(f.ravel(), ref.continuous_dynamics(x20, u0)[:19], atol=1e-12)
        f0, Fr = ref.control_affine_fields(x20)
        assert np.allclose(F, Fr[:19], atol=1e-12)


def test_tangent_basis_is_right_perturbation():
    eng = compiled_uwb_imu(UwbImuSpec(3), 1)
    rng = np.random.default_rng(2)
    x = sample_uwb_imu_state(rng)
    x[6:10] *= np.sign(x[6])  # boxplus returns the qw >= 0 representative
    T = eng.tangent_basis(x, np.zeros(15))
    q = x[6:10]
    assert np.allclose(q @ T[6:10], 0.0, atol=1e-12)  # tangent to the unit sphere
    eps = 1e-6
    x20 = np.r_[x, 0.0]
    for i in range(3):
        dx = np.zeros(19)
        dx[S.ETH][i] = eps
        dq = (S.boxplus(x20, dx)[S.Q] - S.boxplus(x20, -dx)[S.Q]) / (2 * eps)
        assert np.allclose(dq, T[6:10, 6 + i], atol=1e-8)


def test_manifold_rank_counts():
    """Rank against 18 tangent dims; the 4-vector count (19 columns) differs."""
    v = structural_verdict(
        {"anchors": [[0, 0, 0], [5, 0, 0.5], [0, 5, 1.0]], "lever_arm": [0.1, 0.05, 0.2], "all_words": True, "random_points": 3}
    )
    assert v["dimension"] == 18 and v["rank"] == 18 and v["observable"]
    assert v["raw_dimension"] == 19
    # off the unit sphere R(q) is not a rotation, so the radial quaternion
    # direction changes the range formula: the 4-vector count reaches 19
    assert v["raw_rank"] == 19


def test_pruned_words_agree_with_all_words():
    eng = compiled_uwb_imu(UwbImuSpec(3), 3)
    rng = np.random.default_rng(11)
    for _ in range(5):
        x = sample_uwb_imu_state(rng)
        p = np.r_[rng.uniform(-5, 5, 9), rng.normal(0, 2, 6)]
        fast = eng.rank_test(x, p, words="pruned")
        full = eng.rank_test(x, p, words="all")
        assert fast.rank == full.rank == 18
        assert fast.words == "pruned" and full.words == "all"
        assert fast.gap_decades > 6 and full.gap_decades > 6
    assert len(eng.pruned_words) == 18


def test_fallback_to_all_words_on_deficiency():
    # zero lever arm: the pruned words (chosen at a generic point) lose rank, all words do not
    eng = compiled_uwb_imu(UwbImuSpec(3), 3)
    rng = np.random.default_rng(4)
    x = sample_uwb_imu_state(rng, lever_arm=np.zeros(3))
    p = np.r_[rng.uniform(-5, 5, 9), rng.normal(0, 2, 6)]
    r = eng.rank_test(x, p)
    assert r.rank == 18 and r.words == "all"


def test_numerically_zero_rows_do_not_fake_rank():
    M = np.vstack([np.eye(3)[:2], 1e-17 * np.random.default_rng(0).normal(size=(5, 3))])
    rank, s, *_ = numerical_rank(M)
    assert rank == 2


def test_cache_returns_same_compiled_object():
    a = compiled_point_mass(PointMassSpec(3), 1)
    b = compiled_point_mass(PointMassSpec(3), 1)
    assert a is b
    cache = ObservabilityCache()
    e1 = cache.get(PointMassSpec(4), 1, lambda s: compiled_point_mass(s, 1).model)
    assert cache.get(PointMassSpec(4), 1, lambda s: None) is e1
    cache.clear()
    assert not cache.entries


def test_single_anchor_yaw_named():
    v = structural_verdict({"anchors": [[1.0, 2.0, 3.0]], "lever_arm": [0.1, 0.05, 0.2], "random_points": 3})
    assert v["rank"] == 17 and v["dimension"] == 18
    assert [d["name"] for d in v["unobservable_directions"]] == ["global yaw about the vertical line through anchor 0"]
    assert v["gap_decades"] > 8


def test_two_anchor_line_rotation_named():
    v = structural_verdict(
        {"model": "point_mass", "anchors": [[0, 0, 0], [4, 0, 0.5]], "lie_order": 3, "nominal_input": [0, 0, 0], "random_points": 5}
    )
    assert v["rank"] == 5
    assert v["unobservable_directions"][0]["name"] == "rotation about the line through anchors 0 and 1"


def test_vertical_anchor_line_is_yaw():
    v = structural_verdict({"anchors": [[0, 0, 0], [0, 0, 3]], "lever_arm": [0.1, 0.05, 0.2], "random_points": 3})
    assert v["rank"] == 17
    assert v["unobservable_directions"][0]["name"] == "global yaw about the vertical line through anchors 0 and 1"


def test_lever_arm_tradeoff_named_without_rotation():
    v = structural_verdict(
        {"anchors": [[0, 0, 0], [5, 0, 0.5], [0, 5, 1.0]], "lever_arm": [0.1, 0.05, 0.2],
         "excitation": {"accel": ["x", "y", "z"], "gyro": []}, "random_points": 2}
    )  # fmt: skip
    assert v["rank"] == 15
    assert any(d["name"].startswith("position / lever-arm trade-off") for d in v["unobservable_directions"])
    for d in v["unobservable_directions"]:
        assert len(d["vector"]) == 18 and abs(np.linalg.norm(d["vector"]) - 1) < 1e-9


# --------------------------------------------------------------------------
# named directions are the physical generators (independent construction)
# --------------------------------------------------------------------------
def _weakest(cfg):
    from uwbimu.observability.config import load_config
    from uwbimu.observability.structural import compiled_for, evaluation_points

    cfg = load_config(cfg)
    v = structural_verdict(cfg)
    eng, _ = compiled_for(cfg, v["lie_order"])
    x, p = evaluation_points(cfg)[v["weakest_point"]]
    O = eng.matrix(x, p, words="all")
    n = np.linalg.norm(O, axis=1)
    return v, x, O[n > 1e-10 * n.max()] / n[n > 1e-10 * n.max(), None]


def _rigid_generator(x, w, anchor_on_axis, with_attitude=True):
    """World rotation with angular velocity w about the axis through anchor_on_axis."""
    t = -np.cross(w, anchor_on_axis)
    g = [np.cross(w, x[0:3]) + t, np.cross(w, x[3:6])]
    if with_attitude:
        g += [ref.rotation_matrix(x[6:10]).T @ w, np.zeros(9)]
    g = np.concatenate(g)
    return g / np.linalg.norm(g)


def test_single_anchor_yaw_is_the_physical_generator():
    """Yaw about the vertical through the anchor: in the kernel, reported exactly, and a finite
    yaw of the initial state leaves every range of an IMU-driven trajectory unchanged."""
    a = np.array([1.0, 2.0, 3.0])
    v, x, On = _weakest({"anchors": [a.tolist()], "lever_arm": [0.1, 0.05, 0.2], "random_points": 3})
    g = _rigid_generator(x, np.array([0.0, 0.0, 1.0]), a)
    assert np.linalg.norm(On @ g) < 1e-9
    assert abs(np.dot(v["unobservable_directions"][0]["vector"], g)) > 1 - 1e-9
    # finite check with the reference model (the simulator's physics)
    from uwbimu.models.quaternion import quat_multiply

    rng = np.random.default_rng(4)
    t = np.arange(0, 2.0, 0.005)
    u = np.c_[rng.normal(0, 1, 3) + np.sin(t[:, None] * [1.0, 2.0, 3.0]) + [0, 0, 9.81], 0.5 * np.cos(t[:, None] * [1.5, 0.7, 2.0])]
    x0 = np.r_[x, 0.0]
    psi = 0.7
    Rz = np.array([[np.cos(psi), -np.sin(psi), 0], [np.sin(psi), np.cos(psi), 0], [0, 0, 1]])
    x1 = x0.copy()
    x1[0:3] = a + Rz @ (x0[0:3] - a)
    x1[3:6] = Rz @ x0[3:6]
    x1[6:10] = quat_multiply(np.array([np.cos(psi / 2), 0, 0, np.sin(psi / 2)]), x0[6:10])
    X0, X1 = ref.integrate_imu(x0, t, u), ref.integrate_imu(x1, t, u)
    r0 = np.array([ref.range_measurement(s, a) for s in X0])
    r1 = np.array([ref.range_measurement(s, a) for s in X1])
    assert np.abs(r0 - r1).max() < 1e-9 * r0.max()
    # a roll instead of a yaw does change the ranges (gravity breaks it)
    x2 = x1.copy()
    x2[6:10] = quat_multiply(np.array([np.cos(psi / 2), np.sin(psi / 2), 0, 0]), x0[6:10])
    r2 = np.array([ref.range_measurement(s, a) for s in ref.integrate_imu(x2, t, u)])
    assert np.abs(r2 - r0).max() > 1e-2


def test_vertical_anchor_pair_yaw_and_point_mass_line_rotation_are_generators():
    v, x, On = _weakest({"anchors": [[0, 0, 0], [0, 0, 3]], "lever_arm": [0.1, 0.05, 0.2], "random_points": 3})
    g = _rigid_generator(x, np.array([0.0, 0.0, 1.0]), np.zeros(3))
    assert np.linalg.norm(On @ g) < 1e-9 and abs(np.dot(v["unobservable_directions"][0]["vector"], g)) > 1 - 1e-9
    # point mass, drift only: rotation about the (non-vertical) line through the two beacons
    A = np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.5]])
    n = (A[1] - A[0]) / np.linalg.norm(A[1] - A[0])
    v, x, On = _weakest({"model": "point_mass", "anchors": A.tolist(), "lie_order": 3, "nominal_input": [0, 0, 0], "random_points": 5})
    g = _rigid_generator(x, n, A[0], with_attitude=False)
    assert v["rank"] == 5 and np.linalg.norm(On @ g) < 1e-9
    assert abs(np.dot(v["unobservable_directions"][0]["vector"], g)) > 1 - 1e-9
    # the 19-state model with the same two beacons: gravity breaks that rotation
    assert structural_verdict({"anchors": A.tolist(), "lever_arm": [0.1, 0.05, 0.2], "random_points": 3})["rank"] == 18


def test_coplanar_point_mass_directions_are_plane_normals():
    """Tag in the beacons' plane (z = 0): order 0 loses dp along the normal (mirror image);
    order 1 with v leaving the plane loses exactly dv along the normal (see the derivation in
    docs/observability.md): [[a, 0], [b, a]] @ [0; n] = [0; a n] = 0."""
    B3 = [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0]]
    base = {"model": "point_mass", "anchors": B3, "nominal_input": [0, 0, 0], "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.7]}]}
    from scipy.linalg import subspace_angles

    # explicit orders 0 and 1 are "not shown observable"; the order-2 rows restore full rank, so
    # no direction is *named* unobservable (issue 16 item 0), but the order's null space is reported
    v0, _, On0 = _weakest({**base, "lie_order": 0})
    assert np.linalg.norm(On0 @ np.r_[0, 0, 1.0, 0, 0, 0]) < 1e-12
    assert v0["verdict"] == "not shown observable at order 0" and v0["search_verdict"] == "observable"
    assert v0["unobservable_directions"] == [] and v0["removed_by_higher_orders"] == 4
    assert subspace_angles(np.array(v0["order_null_space"]).T, np.eye(6)[:, [2]]).max() < 1e-9
    v1, _, On1 = _weakest({**base, "lie_order": 1})
    assert v1["rank"] == 5 and v1["unobservable_directions"] == []
    assert subspace_angles(np.array(v1["order_null_space"]).T, np.eye(6)[:, [5]]).max() < 1e-9
    assert np.linalg.norm(On1 @ np.r_[0, 0, 0, 0, 0, 1.0]) < 1e-12
    # with the velocity in the plane the drift never removes the mirror image: named at every order
    vin = structural_verdict({**base, "points": [{"p": [1, 1, 0], "v": [0.5, 0.2, 0.0]}]})
    assert vin["rank"] == 4 and vin["stop_reason"] == "stalled"
    assert any("mirror-image" in d["name"] for d in vin["unobservable_directions"])


def test_constant_rotation_lever_arm_generator_named_and_physical():
    """Gyro not excited (constant rate w): the whole lever arm trades off against the IMU's
    position, velocity and accelerometer bias, dp = -R e, dv = -R [w]x e, db_a = [w]x^2 e,
    dl = e.  Checked (1) by the rank test's naming, (2) with a finite e on the reference model."""
    A3 = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.5], [0.0, 5.0, 1.0]]
    cfg = {"anchors": A3, "lever_arm": [0.1, 0.05, 0.2], "excitation": {"accel": ["x", "y", "z"], "gyro": []}, "random_points": 3}
    v = structural_verdict(cfg)
    names = [d["name"] for d in v["unobservable_directions"]]
    assert v["rank"] == 15 and len(names) == 3
    assert names[0].startswith("position / lever-arm trade-off")
    assert all("under constant rotation" in n for n in names[1:])
    # (2) finite transformation, reference propagation with the constant gyro reading
    from uwbimu.models.quaternion import skew

    x = np.r_[sample_uwb_imu_state(np.random.default_rng(8), lever_arm=np.array([0.1, 0.05, 0.2])), 0.0]
    w_m = np.array([0.4, -0.3, 0.8])
    t = np.arange(0, 3.0, 0.005)
    u = np.c_[np.array([0.5, -0.2, 9.81]) + np.sin(t[:, None] * [1.3, 2.1, 0.7]), np.tile(w_m, (len(t), 1))]
    W = skew(w_m - x[S.BG])
    R = ref.rotation_matrix(x[S.Q])
    e = np.array([0.05, -0.08, 0.03])
    y = x.copy()
    y[S.P] -= R @ e
    y[S.V] -= R @ (W @ e)
    y[S.BA] += W @ W @ e
    y[S.PIU] += e
    anchors = np.array(A3)
    rx = np.array([[ref.range_measurement(s, a) for a in anchors] for s in ref.integrate_imu(x, t, u)])
    ry = np.array([[ref.range_measurement(s, a) for a in anchors] for s in ref.integrate_imu(y, t, u)])
    assert np.abs(rx - ry).max() < 1e-9
    # with the gyro excited the same change is visible
    u2 = u.copy()
    u2[:, 3:6] += 0.5 * np.sin(t[:, None] * [0.9, 1.7, 2.3])
    rx2 = np.array([[ref.range_measurement(s, a) for a in anchors] for s in ref.integrate_imu(x, t, u2)])
    ry2 = np.array([[ref.range_measurement(s, a) for a in anchors] for s in ref.integrate_imu(y, t, u2)])
    assert np.abs(rx2 - ry2).max() > 1e-3
