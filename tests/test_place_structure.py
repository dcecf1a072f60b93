"""Structure mode: crane / bridge geometry, decision vectors, PSO, greedy + local search."""

import numpy as np
import pytest

from uwbimu.design.optimize import differential_evolution_opt, greedy_structure, local_search_structure, pso
from uwbimu.design.structures import StructureProblem, girder_bridge, jib_crane


def test_crane_setup_matches_seed_numbers():
    st = jib_crane()
    pr = StructureProblem(st)  # the seed's 10 variables
    assert pr.n_points == 30 * 80 * 80 == 192_000
    assert len(pr.bounds) == 10 and all(b == (0.0, 60.0) for b in pr.bounds)
    a, b = pr.decode(np.full(10, 30.0))
    assert a.shape == (40, 3) and b.shape == (40, 3)
    assert np.all((a >= 0) & (a <= [30, 80, 80])).all()
    assert np.allclose(np.linalg.norm(b, axis=1), 1.0)
    assert st.k == 3


def test_station_geometry_rotation_and_tilt():
    rail = jib_crane().rails[0]  # vertical mast
    pos, bor = rail.station(10.0)
    axis = np.array([15.0, 8.0])
    assert np.allclose(np.linalg.norm(pos[:, :2] - axis, axis=1), np.sqrt(2.0))  # square corners, half 1 m
    assert np.allclose(pos[:, 2], 15.0)
    assert np.allclose(bor[:, 2], 0.0)  # perpendicular to the bar
    # boresights point away from the bar axis (outward along the corner diagonals)
    assert np.all(np.einsum("ij,ij->i", bor[:, :2], pos[:, :2] - axis) > 0)
    _, bt = rail.station(10.0, rot=0.3, tilt=0.4)
    assert np.allclose(bt[:, 2], np.sin(0.4))
    p2, _ = rail.station(10.0, rot=np.pi / 2)
    assert np.allclose(np.sort(p2[:, 0]), np.sort(pos[:, 0]))  # 90 deg symmetry of the square


def test_structure_counts_match_reference_links():
    st = jib_crane()
    pr = StructureProblem(st, freedom="rotate-tilt", step=4.0)
    rng = np.random.default_rng(2)
    lo, hi = np.array(pr.bounds).T
    x = lo + rng.random(len(lo)) * (hi - lo)
    a, b = pr.decode(x)
    pts = st.points(4.0)
    ref = st.link.links(pts, a, b, ray_cast=False).sum(axis=1)
    got = pr.counts(x)
    assert np.mean(got == ref) > 0.999
    assert pr.coverage(x) == pytest.approx(np.mean(ref >= 3), abs=2e-3)


def test_pso_seeded_and_converges_on_sphere():
    f = lambda x: float(np.sum((x - 0.3) ** 2))  # noqa: E731
    r1 = pso(f, [(-1, 1)] * 4, n_particles=16, iters=60, seed=5)
    r2 = pso(f, [(-1, 1)] * 4, n_particles=16, iters=60, seed=5)
    assert np.array_equal(r1["x"], r2["x"])
    assert r1["fun"] < 1e-4
    assert all(np.diff(r1["history"]) <= 0)


def test_de_workers_reproducible():
    f = lambda x: float(np.sum(x**2) + np.sin(5 * x[0]))  # noqa: E731
    r1 = differential_evolution_opt(f, [(-2, 2)] * 3, seed=1, maxiter=5, popsize=5)
    r2 = differential_evolution_opt(f, [(-2, 2)] * 3, seed=1, maxiter=5, popsize=5)
    assert np.array_equal(r1["x"], r2["x"])


def test_greedy_then_local_search_on_coarse_crane():
    st = jib_crane()
    pr = StructureProblem(st, [2, 2], freedom="rotate", step=4.0)
    g = greedy_structure(pr, step=6.0, rotations=(0.0, 0.5))
    assert len(g["curve"]) == 4 and all(np.diff(g["curve"]) >= -1e-12)
    assert pr.coverage(g["x"]) == pytest.approx(g["curve"][-1])
    ls = local_search_structure(pr, g["x"], steps=(4.0,), angle_steps=(0.2,), max_rounds=1)
    assert ls["fun"] <= pr(g["x"]) + 1e-12


def test_bridge_structure():
    st = girder_bridge()
    pr = StructureProblem(st, step=2.0)
    a, b = pr.decode([10.0, 50.0, 4.0, 8.0])
    assert a.shape == (16, 3)
    assert 0.0 < pr.coverage([10.0, 50.0, 4.0, 8.0]) <= 1.0
    with pytest.raises(ValueError):
        StructureProblem(st, [1, 1])


def test_geometry_kernel_matches_reference_information():
    from uwbimu.design.metrics import information_matrix
    from uwbimu.design.placement import pdop_from_g6
    from uwbimu.design.radio import CosN, LinkModel, count_links_grid, geometry_grid

    rng = np.random.default_rng(4)
    lm = LinkModel(max_range=6.0, anchor_pattern=CosN(100.0))
    axes = (np.arange(0.5, 10, 1.0), np.arange(0.5, 9, 1.0), np.arange(0.5, 6, 1.0))
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    anchors = rng.uniform([0, 0, 0], [10, 9, 6], (7, 3))
    bores = rng.normal(size=(7, 3))
    lut = lm.reach_lut()
    counts, g6 = geometry_grid(axes, anchors, bores, lut)
    assert np.array_equal(counts, count_links_grid(axes, anchors, bores, lut))
    links = lm.links(pts, anchors, bores, ray_cast=False)
    same = counts == links.sum(axis=1)
    J = information_matrix(pts, anchors, 1.0, links)
    packed = np.stack([J[:, 0, 0], J[:, 1, 1], J[:, 2, 2], J[:, 0, 1], J[:, 0, 2], J[:, 1, 2]], axis=1)
    assert same.mean() > 0.99
    assert np.allclose(g6[same], packed[same], atol=1e-5)
    ref = pdop_from_g6(packed[same], 1e3)
    well = ref < 20.0  # float32 sums: compare where the geometry is not ill-conditioned
    assert well.sum() > 20
    assert np.allclose(pdop_from_g6(g6[same].astype(float), 1e3)[well], ref[well], rtol=1e-3)


def test_geometric_objective_on_coarse_bridge():
    st = girder_bridge()
    x = np.array([10.0, 50.0, 4.0, 8.0])
    pc = StructureProblem(st, step=2.0)
    pg = StructureProblem(st, step=2.0, objective="geometric", pdop_max=5.0)
    assert 0.0 <= pg.geometric_coverage(x) <= pc.coverage(x)
    assert pg(x) == pytest.approx(1.0 - pg.geometric_coverage(x))
    with pytest.raises(ValueError):
        StructureProblem(st, objective="nope")
