"""Geometry / information metrics and the seed's observability determinant."""

import itertools

import numpy as np
import pytest

from uwbimu.design.metrics import (
    dop,
    gdop,
    information_matrix,
    logdet_information,
    min_eig_information,
    pdop,
    percentiles,
    region_metrics,
    seed_observability_det,
    seed_observability_matrix,
    unit_los,
)
from uwbimu.design.placement import _outer6, pdop_from_g6
from uwbimu.models.reference import range_measurement

RNG = np.random.default_rng(42)


def _random_case(n, rng):
    anchors = rng.uniform(-5, 5, (n, 3))
    p = rng.uniform(-3, 3, 3)
    return anchors, p


@pytest.mark.parametrize("trial", range(5))
def test_three_beacons_seed_det_equals_range_weighted_fisher_det(trial):
    """det(O^T O) = (r1 r2 r3)^2 sigma^6 det(J) for three beacons (O = diag(r) U)."""
    rng = np.random.default_rng(trial)
    anchors, p = _random_case(3, rng)
    sigma = 0.07
    O = seed_observability_matrix(p, anchors)
    u, r = unit_los(p, anchors)
    J = information_matrix(p, anchors, sigma)[0]
    lhs = np.linalg.det(O.T @ O)
    rhs = np.prod(r[0]) ** 2 * sigma**6 * np.linalg.det(J)
    assert lhs == pytest.approx(rhs, rel=1e-9)
    assert seed_observability_det(p, anchors)[0] == pytest.approx(lhs, rel=1e-9)
    # the seed's normalised matrix (rows divided by their ranges; its Sec. XI uses
    # det = det(a) / (r1 r2 r3)) has determinant det(U), and det(U)^2 = sigma^6 det(J)
    assert np.linalg.det(O / r[0][:, None]) == pytest.approx(np.linalg.det(u[0]), rel=1e-9)
    assert np.linalg.det(O) / np.prod(r[0]) == pytest.approx(np.linalg.det(u[0]), rel=1e-9)
    assert np.linalg.det(u[0]) ** 2 == pytest.approx(np.linalg.det(J) * sigma**6, rel=1e-9)


def test_first_order_matrix_determinant_is_square_of_zeroth():
    anchors, p = _random_case(3, np.random.default_rng(3))
    v = np.array([0.3, -1.2, 0.5])
    O6 = seed_observability_matrix(p, anchors, v, order=1)
    O3 = seed_observability_matrix(p, anchors)
    assert np.linalg.det(O6) == pytest.approx(np.linalg.det(O3) ** 2, rel=1e-9)
    assert np.linalg.det(O6.T @ O6) == pytest.approx(np.linalg.det(O3.T @ O3) ** 2, rel=1e-8)


def test_first_order_matrix_matches_numeric_lie_derivatives():
    """Rows of O_6 are gradients of L0 = |p-a|^2/2 and L1 = grad(L0) . f, f = [v, u]."""
    anchors, p = _random_case(3, np.random.default_rng(5))
    v = np.array([0.4, 0.1, -0.7])
    x = np.r_[p, v]

    def lie(xx, a):
        pp, vv = xx[:3], xx[3:]
        return np.array([0.5 * np.sum((pp - a) ** 2), (pp - a) @ vv])  # L0, L1 (u does not enter)

    h = 1e-6
    rows0, rows1 = [], []
    for a in anchors:
        g = np.array([(lie(x + h * e, a) - lie(x - h * e, a)) / (2 * h) for e in np.eye(6)]).T
        rows0.append(g[0])
        rows1.append(g[1])
    O_num = np.vstack([rows0, rows1])
    assert np.allclose(O_num, seed_observability_matrix(p, anchors, v, order=1), atol=1e-6)


def test_cauchy_binet_for_n_beacons():
    anchors, p = _random_case(5, np.random.default_rng(8))
    u, r = unit_los(p, anchors)
    O = seed_observability_matrix(p, anchors)
    s_seed, s_fish = 0.0, 0.0
    for i, j, k in itertools.combinations(range(5), 3):
        d = np.linalg.det(u[0, [i, j, k]])
        s_seed += (r[0, i] * r[0, j] * r[0, k]) ** 2 * d**2
        s_fish += d**2
    assert np.linalg.det(O.T @ O) == pytest.approx(s_seed, rel=1e-9)
    assert np.linalg.det(information_matrix(p, anchors)[0]) == pytest.approx(s_fish, rel=1e-9)


def test_unit_los_is_reference_range_gradient():
    """The LOS vector used by the Fisher information is d(range)/d(p) of the reference model."""
    anchors, p = _random_case(4, np.random.default_rng(11))
    u, r = unit_los(p, anchors)
    x = np.zeros(20)
    x[0:3] = p
    x[6] = 1.0  # identity quaternion, zero lever arm
    h = 1e-6
    for i, a in enumerate(anchors):
        assert range_measurement(x, a) == pytest.approx(r[0, i], rel=1e-12)
        g = []
        for e in np.eye(3):
            xp, xm = x.copy(), x.copy()
            xp[0:3] += h * e
            xm[0:3] -= h * e
            g.append((range_measurement(xp, a) - range_measurement(xm, a)) / (2 * h))
        assert np.allclose(g, u[0, i], atol=1e-7)


def test_pdop_regular_tetrahedron_centre_is_1p5():
    t = np.array([[1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]], float)
    # H^T H = (4/3) I at the centre, PDOP = sqrt(3 * 3/4)
    assert pdop(np.zeros(3), t)[0] == pytest.approx(1.5, rel=1e-12)
    J = information_matrix(np.zeros(3), t, sigma=0.1)[0]
    assert np.allclose(J, np.eye(3) * (4 / 3) / 0.01)
    assert logdet_information(np.zeros(3), t, 0.1)[0] == pytest.approx(3 * np.log(400 / 3))
    assert min_eig_information(np.zeros(3), t, 0.1)[0] == pytest.approx(400 / 3)


def test_pdop_matches_direct_inverse_and_fast_closed_form():
    anchors = RNG.uniform(0, 10, (6, 3))
    pts = RNG.uniform(1, 9, (50, 3))
    links = RNG.random((50, 6)) > 0.2
    ref = []
    for i, p in enumerate(pts):
        H = unit_los(p, anchors)[0][0][links[i]]
        G = H.T @ H
        ref.append(np.sqrt(np.trace(np.linalg.inv(G))) if np.linalg.matrix_rank(G) == 3 else np.inf)
    got = pdop(pts, anchors, links)
    fin = np.isfinite(ref)
    assert np.allclose(got[fin], np.array(ref)[fin], rtol=1e-9)
    u, _ = unit_los(pts, anchors)
    g6 = np.einsum("pn,pnk->pk", links.astype(float), _outer6(u))
    fast = pdop_from_g6(g6, cap=1e6)
    assert np.allclose(fast[fin], got[fin], rtol=1e-8)


def test_gdop_at_least_pdop_and_clock_needs_four():
    anchors = RNG.uniform(0, 10, (5, 3))
    pts = RNG.uniform(2, 8, (20, 3))
    assert np.all(gdop(pts, anchors) >= pdop(pts, anchors) - 1e-12)
    assert np.all(np.isinf(dop(pts, anchors[:3], clock=True)))


def test_coplanar_anchors_tag_in_plane_unobservable():
    anchors = np.array([[0, 0, 2.0], [5, 0, 2.0], [0, 5, 2.0], [5, 5, 2.0]])
    in_plane = np.array([[2.0, 2.0, 2.0]])
    off_plane = np.array([[2.0, 2.0, 1.0]])
    assert np.isinf(pdop(in_plane, anchors)[0])
    assert seed_observability_det(in_plane, anchors)[0] == pytest.approx(0.0, abs=1e-9)
    assert np.isfinite(pdop(off_plane, anchors)[0])


def test_percentiles_cap_and_region_summary():
    v = np.array([1.0, 2.0, 3.0, np.inf, np.inf])
    assert percentiles(v, (50,), cap=10)["p50"] == 3.0
    assert percentiles(v, (95,), cap=10)["p95"] == 10.0
    anchors = RNG.uniform(0, 10, (5, 3))
    m = region_metrics(RNG.uniform(2, 8, (30, 3)), anchors, sigma=0.1)
    assert set(m["summary"]) >= {"pdop", "logdet", "min_eig", "seed_det", "observable_fraction"}
    assert m["summary"]["observable_fraction"] == 1.0
