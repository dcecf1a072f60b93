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
    rank, s, _ = numerical_rank(M)
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
