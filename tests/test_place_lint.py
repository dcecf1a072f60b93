"""Practitioner lint rules."""

import numpy as np

from uwbimu.design.lint import hull_outside_fraction, hull_outside_mask, lint_layout, planarity
from uwbimu.design.placement import Room


def _codes(ws):
    return {w.code for w in ws}


def test_collinear_and_coplanar():
    line = np.array([[0, 0, 1.0], [2, 0, 1.0], [4, 0, 1.0], [6, 0, 1.0]])
    assert "collinear" in _codes(lint_layout(line))
    plane = np.array([[0, 0, 2.5], [8, 0, 2.5], [8, 6, 2.5], [0, 6, 2.5], [4, 3, 2.5]])
    ws = lint_layout(plane)
    assert "coplanar" in _codes(ws) and "collinear" not in _codes(ws)
    assert planarity(plane)[1] < 1e-12


def test_flat_layout_ratio():
    flat = np.array([[0, 0, 0.5], [12, 0, 2.5], [12, 8, 0.5], [0, 8, 2.5]])  # 12 / 2 = 6 > 3
    w = [w for w in lint_layout(flat) if w.code == "flat"]
    assert w and abs(w[0].value - 6.0) < 1e-9
    ok = np.array([[0, 0, 0.2], [5, 0, 2.8], [5, 4, 0.2], [0, 4, 2.8]])  # 5 / 2.6 < 3
    assert "flat" not in _codes(lint_layout(ok))
    # the message says when the space itself cannot pass the rule (10 x 8 x 3 m room: 3.3)
    msg = [w for w in lint_layout(flat, space_extent=[10, 8, 3]) if w.code == "flat"][0].message
    assert "the space itself" in msg and "3.3" in msg
    msg = [w for w in lint_layout(flat, space_extent=[6, 5, 3]) if w.code == "flat"][0].message
    assert "the space itself" not in msg


def test_hull_and_near_wall_and_single_failure():
    room = Room.box(10, 8, 3)
    anchors = np.array([[0.1, 0.2, 0.2], [9.8, 0.2, 2.8], [9.8, 7.8, 0.2], [0.2, 7.8, 2.8], [5, 4, 2.8]])
    pts = room.flight_points(step=1.0)
    f = hull_outside_fraction(anchors, pts)
    assert 0.0 < f < 1.0
    ws = lint_layout(anchors, pts, room.surface_distance,
                     single_failure={"anchor": "A5", "coverage": 0.9, "pdop_p95": 3.0, "coverage_all": 1.0})
    codes = _codes(ws)
    assert {"outside-hull", "near-wall", "single-failure"} <= codes
    near = [w for w in ws if w.code == "near-wall"]
    assert len(near) == 1 and "A1" in near[0].message  # only the anchor 0.1 m from the wall
    sf = [w for w in ws if w.code == "single-failure"][0]
    assert sf.severity == "warning"  # coverage drops when A5 fails
    corners = np.array([[x, y, z] for x in (0.2, 9.8) for y in (0.2, 7.8) for z in (0.2, 2.8)])
    assert hull_outside_fraction(corners, pts) == 0.0
    assert "too-few" in _codes(lint_layout(corners[:3]))


def test_hull_mask_matches_delaunay_and_flat_hull_is_all_outside():
    from scipy.spatial import Delaunay

    rng = np.random.default_rng(5)
    for n in (4, 6, 9):
        a = rng.uniform(0, 5, (n, 3))
        p = rng.uniform(-1, 6, (2000, 3))
        ref = Delaunay(a).find_simplex(p) < 0
        assert np.array_equal(hull_outside_mask(a, p), ref)
    flat = np.array([[0, 0, 1.0], [4, 0, 1.0], [4, 3, 1.0], [0, 3, 1.0], [2, 1, 1.0]])
    assert hull_outside_mask(flat, rng.uniform(0, 3, (10, 3))).all()
    assert hull_outside_fraction(flat[:3], np.zeros((2, 3))) == 1.0
