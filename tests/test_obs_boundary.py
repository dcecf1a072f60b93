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
