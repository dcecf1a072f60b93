"""Boundary cases of docs/observability.md reproduced against the rank computation.

The null space of a rank-deficient case is compared as a *subspace* (principal
angles, ``scipy.linalg.subspace_angles``) with the span of the generators the
docs name; printed basis vectors of a multi-dimensional null space are not
unique (they depend on BLAS / CPU) and are never compared.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import subspace_angles

from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.observability.boundary import A3, LEVER, direction_family
from uwbimu.observability.structural import structural_verdict


def _null(v: dict) -> np.ndarray:
    return np.array([d["vector"] for d in v["unobservable_directions"]]).T


def _weakest_state(v: dict) -> np.ndarray:
    return np.asarray(v["points"][v["weakest_point"]]["state"])


def _yaw_generator(x: np.ndarray, axis_point: np.ndarray) -> np.ndarray:
    """Tangent vector of a world yaw about the vertical line through ``axis_point``."""
    e = np.array([0.0, 0.0, 1.0])
    R = quat_to_rotmat(x[6:10])
    g = np.zeros(18)
    g[0:3] = np.cross(e, x[0:3] - axis_point)
    g[3:6] = np.cross(e, x[3:6])
    g[6:9] = R.T @ e
    return g[:, None]


def _constant_rotation_lever(x: np.ndarray, w_m: np.ndarray) -> np.ndarray:
    """The 3 generators (p, v, b_a, p_IU) of the lever arm under constant rotation."""
    R = quat_to_rotmat(x[6:10])
    w = w_m - x[13:16]
    W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    C = np.zeros((18, 3))
    for j in range(3):
        e = np.eye(3)[j]
        C[0:3, j], C[3:6, j], C[9:12, j], C[15 + j, j] = -R @ e, -R @ (W @ e), W @ (W @ e), 1.0
    return C


@pytest.mark.parametrize("anchors", [[[1.0, 2.0, 3.0]], [[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]]])
def test_vertical_anchor_line_leaves_exactly_the_yaw_about_it(anchors):
    v = structural_verdict({"anchors": anchors, "lever_arm": LEVER, "random_points": 3, "seed": 1})
    assert (v["rank"], v["dimension"]) == (17, 18)
    ang = subspace_angles(_null(v), _yaw_generator(_weakest_state(v), np.asarray(anchors[0])))
    assert ang.max() < 1e-6


def test_accel_only_null_space_is_the_constant_rotation_lever_family():
    w_m = np.array([0.3, -0.2, 0.5])
    v = structural_verdict({"anchors": A3, "lever_arm": LEVER, "random_points": 3, "seed": 1,
                            "excitation": {"accel": ["x", "y", "z"], "gyro": []},
                            "nominal_input": [0.1, 0.2, 9.7, *w_m]})  # fmt: skip
    assert v["rank"] == 15
    ang = subspace_angles(_null(v), _constant_rotation_lever(_weakest_state(v), w_m))
    assert ang.max() < 1e-6
    fams = {direction_family(d["name"]) for d in v["unobservable_directions"]}
    assert len(fams) <= 2 and all("lever" in f for f in fams)


# --------------------------------------------------------------------------
# issue 16 item 0: verdicts that do not depend on the Lie order, a fixed
# tolerance or the configured t_d (each case of the issue, against the rank
# computation; null spaces compared as subspaces)
# --------------------------------------------------------------------------
GYRO_XY_2H = {"anchors": [[0, 0, 0], [5, 0, 0]], "lever_arm": [0, 0, 0], "excitation": {"accel": [], "gyro": ["x", "y"]}}
GYRO_ONLY_0 = {"anchors": A3, "lever_arm": [0, 0, 0], "excitation": {"accel": [], "gyro": ["x", "y", "z"]}}


@pytest.mark.parametrize("cfg", [GYRO_XY_2H, GYRO_ONLY_0], ids=["2-horizontal-gyro-xy", "3-anchors-gyro-only"])
def test_zero_lever_arm_rank_full_at_order_4_not_named_at_order_3(cfg):
    base = {**cfg, "random_points": 3, "seed": 1}
    v = structural_verdict(base)
    assert v["verdict"] == "observable" and v["rank"] == 18 and v["lie_order"] == 4
    v3 = structural_verdict({**base, "lie_order": 3})
    assert v3["rank"] < 18 and v3["verdict"] == "not shown observable at order 3"
    # higher orders remove every order-3 null direction: none is named
    assert v3["unobservable_directions"] == [] and v3["removed_by_higher_orders"] == 18 - v3["rank"]
    assert v3["search_verdict"] == "observable"


def test_one_anchor_zero_lever_arm_has_only_the_yaw():
    """Issue: order 3 gave 15 with two spurious rotations; truly 17 (the yaw)."""
    a = [1.0, 2.0, 3.0]
    v = structural_verdict({"anchors": [a], "lever_arm": [0, 0, 0], "random_points": 3, "seed": 1})
    assert v["rank"] == 17 and v["verdict"] == "not observable" and v["cross_check"]["rank"] == 17
    ang = subspace_angles(_null(v), _yaw_generator(_weakest_state(v), np.asarray(a)))
    assert ang.max() < 1e-6


def test_near_vertical_anchor_pair_is_kept_by_the_scale_aware_cut():
    """Two anchors 1e-8 rad off vertical: the yaw about that line is (weakly) observable.
    A fixed relative tolerance 1e-8 drops the ~6e-9 singular value and reports rank 17."""
    cfg = {"anchors": [[0, 0, 0], [3e-8, 0, 3]], "lever_arm": LEVER, "random_points": 3, "seed": 1}
    v = structural_verdict(cfg)
    assert v["rank"] == 18 and v["observable"] and v["margin_decades"] < 3.5
    assert structural_verdict({**cfg, "tolerance": 1e-8, "lie_order": 3})["rank"] == 17
    # exactly vertical: the yaw is a true null direction (its singular value is rounding noise)
    v0 = structural_verdict({**cfg, "anchors": [[0, 0, 0], [0, 0, 3]]})
    assert v0["rank"] == 17 and v0["gap_decades"] > 8


def test_point_mass_off_plane_by_a_micron_vs_in_plane():
    B = [[0.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 4.0, 0.0]]
    base = {"model": "point_mass", "anchors": B, "nominal_input": [0, 0, 0]}
    v = structural_verdict({**base, "points": [{"p": [1, 1, 1e-6], "v": [0.5, 0.2, 0.0]}]})
    assert v["rank"] == 6 and v["margin_decades"] > 3
    v = structural_verdict({**base, "points": [{"p": [1, 1, 0.0], "v": [0.5, 0.2, 0.0]}]})
    assert v["rank"] == 4 and v["stop_reason"] == "stalled"
    # mirror image: the normal displacement and the normal velocity
    assert subspace_angles(_null(v), np.eye(6)[:, [2, 5]]).max() < 1e-9


def test_nondimensionalisation_maps_null_space_back_to_physical_coordinates():
    """The null space does not depend on the column scales (exact null directions are invariant)."""
    from uwbimu.observability.config import load_config
    from uwbimu.observability.structural import compiled_for, evaluation_points, tangent_scales

    cfg = load_config({"anchors": [[1.0, 2.0, 3.0]], "lever_arm": LEVER, "random_points": 1, "seed": 2})
    eng, _ = compiled_for(cfg, 3)
    ((x, p),) = evaluation_points(cfg)
    plain = eng.rank_test(x, p)
    scaled = eng.rank_test(x, p, col_scale=tangent_scales(cfg, x) * 37.0)
    assert plain.rank == scaled.rank == 17
    assert subspace_angles(plain.null_space, scaled.null_space).max() < 1e-8


def test_delay_verdict_does_not_depend_on_the_configured_time_offset():
    """Zero lever arm, gyro only: sensitivity ~ t_d^3 (7e-12 m per rad/s at 0.5 ms). The former
    fixed 1e-9 cut-off said "not identifiable" at 0.5 ms and "identifiable" at 20 ms."""
    from uwbimu.observability.delay import delay_verdict

    out = []
    for td in (5e-4, 2e-2, 0.3):
        v = delay_verdict({**GYRO_ONLY_0, "random_points": 3, "seed": 1, "time_offset": td})
        out.append((v["identifiable"], v["numeric"]["nonzero"], v["numeric"]["td_power"]))
        if td == 5e-4:
            assert max(v["numeric"]["sensitivity"].values()) < 1e-9
    assert out[0] == out[1] == out[2] == (True, True, 3.0)
    none = delay_verdict({**GYRO_ONLY_0, "excitation": {"accel": [], "gyro": []}, "time_offset": 0.3})
    assert not none["identifiable"]


@pytest.mark.parametrize(
    "case",
    [
        {"anchors": [[1.0, 6.0, 2.0]], "excitation": {"accel": ["x"], "gyro": []},
         "points": [{"antenna": [1.0, 1.0, 1.0], "q": [1, 0, 0, 0], "v": [0.5, 0.2, 0.1]}], "key": "accel"},
        {"anchors": [[2.0, 1.5, 3.0]], "excitation": {"accel": [], "gyro": ["x", "y", "z"]},
         "points": [{"p": [1.0, 1.0, 1.0], "q": [1, 0, 0, 0], "v": [0.5, 0.2, 0.1]}], "key": "gyro"},
    ],
    ids=["accel-axis-perpendicular-to-line-of-sight", "anchor-on-imu-antenna-line"],
)  # fmt: skip
def test_theorem1_pointwise_vanishing_cases_are_identifiable(case):
    from uwbimu.observability.delay import delay_verdict

    case = dict(case)
    key = case.pop("key")
    v = delay_verdict({**case, "lever_arm": LEVER, "time_offset": 0.01})
    assert v["first_order"][key] < 1e-9  # the seed's eq. (13) term vanishes at this point
    assert v["theorem1"] and v["identifiable"] and v["agree"] and v["explanation"]
    assert v["numeric"]["td_power"] >= 2  # ... the delayed input enters at higher order in t_d


# --------------------------------------------------------------------------
# issue 13 item 4: TDoA
# --------------------------------------------------------------------------
A4 = A3 + [[2.0, 2.0, 3.0]]


def test_tdoa_rank_minimum_anchors_and_degenerate_geometries():
    from uwbimu.observability.config import ConfigError

    base = {"measurement": "tdoa", "lever_arm": LEVER, "random_points": 3, "seed": 1}
    with pytest.raises(ConfigError, match="at least 2 anchors"):
        structural_verdict({**base, "anchors": [[0, 0, 0]]})
    # one difference and full IMU excitation already reach 18 (order 3)
    v = structural_verdict({**base, "anchors": A4[:2]})
    assert (v["rank"], v["dimension"], v["verdict"]) == (18, 18, "observable") and v["measurement"] == "tdoa"
    # coplanar anchors with the tag in their plane: the zeroth-order rank drops, order 3 restores it
    sq = [[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 5.0, 0.0], [5.0, 5.0, 0.0]]
    v = structural_verdict({**base, "anchors": sq, "points": [{"antenna": [1, 2, 0]}]})
    assert v["rank"] == 18 and v["order_search"][0]["rank"] == 2
    # tag on the pair's hyperboloid axis: the difference has no gradient there; the IMU-driven
    # higher-order rows still reach 18, one order later than off the axis
    v = structural_verdict({**base, "anchors": A4[:2], "points": [{"antenna": [-2, 0, -0.2]}]})
    assert v["conditions"]["tdoa_pairs_on_axis"] == [[0, 1]] and v["conditions"]["tdoa_gradient_rank"] == 0
    # the lone order-0 row is rounding noise: judged against its size at a generic point, not normalised into rank
    assert v["order_search"][0]["rank"] == 0
    assert v["rank"] == 18 and v["lie_order"] == 4
    # vertical anchor pair: the yaw about it stays (subspace check)
    a = [[0.0, 0.0, 0.0], [0.0, 0.0, 3.0]]
    v = structural_verdict({**base, "anchors": a})
    assert v["rank"] == 17 and v["cross_check"]["rank"] == 17
    assert subspace_angles(_null(v), _yaw_generator(_weakest_state(v), np.zeros(3))).max() < 1e-6


def test_tdoa_theorem1_analogue_matches_the_numeric_sensitivity():
    """docs/observability.md: for a TDoA r_i - r_0 the seed's eq. (13) terms become
    d/d a_j = -(e_i - e_0)^T R e_j t_d^2 / 2 and d/d w_j = -(e_i - e_0)^T R (e_j x p_IU) t_d."""
    from uwbimu.models import reference as ref
    from uwbimu.observability.delay import delayed_input_sensitivity
    from uwbimu.observability.models import sample_uwb_imu_state

    rng = np.random.default_rng(11)
    x = sample_uwb_imu_state(rng, lever_arm=np.array(LEVER))
    x[3:6] = 0.0
    t_d = 1e-3
    x20 = np.r_[x, t_d]
    A = np.asarray(A4)
    sens = delayed_input_sensitivity(x20, np.zeros(6), A, t_d, "tdoa")
    R = ref.rotation_matrix(x[6:10])
    tag = ref.antenna_position(x20)
    E = (A - tag) / np.linalg.norm(A - tag, axis=1, keepdims=True)
    D = E[1:] - E[0]
    for j in range(3):
        e = np.eye(3)[j]
        assert sens[:, j] == pytest.approx(-(D @ R[:, j]) * t_d**2 / 2, rel=0.05, abs=1e-10)
        assert sens[:, 3 + j] == pytest.approx(-(D @ (R @ np.cross(e, LEVER))) * t_d, rel=0.05, abs=1e-9)


def test_tdoa_time_offset_conditions():
    from uwbimu.observability.delay import delay_verdict

    base = {"measurement": "tdoa", "anchors": A4, "lever_arm": LEVER, "random_points": 3, "seed": 1, "time_offset": 0.02}
    v = delay_verdict({**base, "excitation": {"accel": [], "gyro": ["x", "y", "z"]}})
    assert v["conditions"] == {"T1": True, "T2": False, "T3": True} and v["identifiable"] and v["agree"]
    assert not delay_verdict({**base, "excitation": {"accel": [], "gyro": []}})["identifiable"]
    # on the pair's axis T1' fails and the first-order terms vanish, yet t_d enters at order t_d^2
    v = delay_verdict({**base, "anchors": A4[:2], "points": [{"antenna": [-2, 0, -0.2]}]})
    assert v["conditions"]["T1"] is False and not v["theorem1"]
    assert max(v["first_order"].values()) < 1e-9
    assert v["identifiable"] and v["numeric"]["td_power"] == 2.0 and v["explanation"]
