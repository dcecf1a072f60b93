"""``uwbimu place`` with ``measurement: tdoa``: TDoA information, PDOP, objective, config, CLI."""

import json

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.design.config import ConfigError, PlacementConfig, load_config
from uwbimu.design.metrics import (
    gdop,
    information_matrix,
    pdop,
    percentiles,
    tdoa_gram,
    tdoa_information_explicit,
    tdoa_information_matrix,
    tdoa_pdop,
    unit_los,
)
from uwbimu.design.placement import (
    CandidateSet,
    LayoutEvaluator,
    Room,
    _outer6,
    info6_from_sums,
    lazy_greedy_logdet,
    pdop_from_g6,
)
from uwbimu.design.radio import LinkModel
from uwbimu.models.reference import tdoa_measurement

CEILING6 = np.array([[x, y, 2.8] for x in (0.2, 5.0, 9.8) for y in (0.2, 7.8)])


@pytest.mark.parametrize("trial", range(6))
def test_centred_information_equals_explicit_correlated_form_for_every_reference(trial):
    """(2/sigma^2) U^T (I - 11^T/n) U == H^T R^-1 H with R = (sigma^2/2)(I + 11^T), any reference."""
    rng = np.random.default_rng(100 + trial)
    n = 4 + trial
    anchors = rng.uniform(-6, 6, (n, 3))
    p = rng.uniform(-3, 3, (1, 3))
    sigma = 0.05 + 0.1 * trial
    J = tdoa_information_matrix(p, anchors, sigma)[0]
    for ref in range(n):
        Je = tdoa_information_explicit(p[0], anchors, sigma, ref)
        assert np.allclose(J, Je, rtol=1e-10, atol=1e-10 * np.abs(Je).max())
    # Links mask anchors out: same as the explicit form over the anchors in range only.
    links = np.ones((1, n), bool)
    links[0, [0, n - 1]] = False
    Jm = tdoa_information_matrix(p, anchors, sigma, links)[0]
    assert np.allclose(Jm, tdoa_information_explicit(p[0], anchors[links[0]], sigma, ref=1), rtol=1e-10, atol=1e-12)
    # Less information than the ranges with the same per-anchor arrival noise sigma/sqrt(2).
    Jr = information_matrix(p, anchors, sigma / np.sqrt(2))[0]
    assert np.linalg.eigvalsh(Jr - J).min() > -1e-9 * np.abs(Jr).max()


def test_tdoa_rows_are_the_reference_models_tdoa_gradient():
    """H rows u_i - u_ref are d(tdoa_measurement)/dp of models/reference.py (finite differences)."""
    rng = np.random.default_rng(7)
    anchors = rng.uniform(-5, 5, (5, 3))
    p = rng.uniform(-2, 2, 3)
    u, _ = unit_los(p, anchors)
    x = np.zeros(20)
    x[0:3] = p
    x[6] = 1.0  # identity quaternion, zero lever arm
    h = 1e-6
    ref = 2
    for i in range(len(anchors)):
        if i == ref:
            continue
        g = []
        for e in np.eye(3):
            xp, xm = x.copy(), x.copy()
            xp[0:3] += h * e
            xm[0:3] -= h * e
            g.append((tdoa_measurement(xp, anchors[ref], anchors[i]) - tdoa_measurement(xm, anchors[ref], anchors[i]))
                     / (2 * h))
        assert np.allclose(g, u[0, i] - u[0, ref], atol=1e-7)


def test_tdoa_pdop_is_the_position_part_of_gdop_and_needs_four_links():
    rng = np.random.default_rng(3)
    anchors = rng.uniform(-5, 5, (6, 3))
    pts = rng.uniform(-2, 2, (50, 3))
    G4 = information_matrix(pts, anchors, 1.0, clock=True)
    want = np.sqrt(np.trace(np.linalg.inv(G4)[:, :3, :3], axis1=1, axis2=2))
    got = tdoa_pdop(pts, anchors)
    assert np.allclose(got, want, rtol=1e-9)
    assert np.all(got >= pdop(pts, anchors) - 1e-12)  # never better than ranges
    assert np.all(got <= gdop(pts, anchors) + 1e-12)  # GDOP adds the clock sd
    links = np.ones((50, 6), bool)
    links[:25, 3:] = False  # 3 anchors in range: no 3-D TDoA fix, a TWR fix
    pd_ = tdoa_pdop(pts, anchors, links)
    assert np.all(np.isinf(pd_[:25])) and np.all(np.isfinite(pd_[25:]))
    assert np.all(np.isfinite(pdop(pts[:25], anchors, links[:25])))


def test_coplanar_anchors_singular_vertical_under_tdoa_not_under_twr():
    """Anchors on a circle in the ceiling plane, tag on the circle's axis: all ranges equal, so the
    centred vertical components vanish -> TDoA null space = the vertical; ranges still see it."""
    ang = np.linspace(0, 2 * np.pi, 6, endpoint=False) + 0.3
    anchors = np.column_stack([5 + 3 * np.cos(ang), 4 + 3 * np.sin(ang), np.full(6, 2.8)])
    p = np.array([[5.0, 4.0, 1.2]])
    w, v = np.linalg.eigh(tdoa_gram(p, anchors)[0])
    assert w[0] < 1e-12 * w[-1] and w[1] > 0.1  # rank 2
    assert abs(v[2, 0]) == pytest.approx(1.0, abs=1e-9)  # its null space is the z axis
    Jr = information_matrix(p, anchors)[0]
    assert np.linalg.eigvalsh(Jr)[0] > 0.1 and Jr[2, 2] > 1.0  # two-way ranges observe z
    assert np.isinf(tdoa_pdop(p, anchors)[0]) and np.isfinite(pdop(p, anchors)[0])
    # All on the ceiling of the example room: the weak TDoA direction is (near) vertical
    # and carries far less information than with ranges.
    pts = np.random.default_rng(1).uniform([0.5, 0.5, 0.3], [9.5, 7.5, 2.5], (200, 3))
    g = tdoa_gram(pts, CEILING6)
    w, v = np.linalg.eigh(g)
    assert np.median(np.abs(v[:, 2, 0])) > 0.95
    assert np.median(g[:, 2, 2] / information_matrix(pts, CEILING6)[:, 2, 2]) < 0.3
    # Off-plane anchors (Bitcraze-style 3 high / 3 low) keep it.
    bc = np.array([[0.2, 0.2, 2.8], [5.0, 0.2, 0.2], [9.8, 0.2, 2.8],
                   [9.8, 7.8, 0.2], [5.0, 7.8, 2.8], [0.2, 7.8, 0.2]])
    assert np.percentile(tdoa_pdop(pts, bc), 95) < 0.25 * np.percentile(tdoa_pdop(pts, CEILING6), 95)


@pytest.fixture(scope="module")
def small_tdoa():
    room = Room.box(6, 5, 3)
    pts = room.flight_points([0.5, 0.5, 0.3], [5.5, 4.5, 2.5], 1.0)
    link = LinkModel(max_range=4.0)  # short: some points see fewer than 4 anchors
    ev = LayoutEvaluator(pts, link, k=4, percentile=90, pdop_cap=20, sigma=0.14, measurement="tdoa",
                         weights={"coverage": 10, "pdop": 1, "n1_pdop": 0.25, "info": 0.1})
    pos, bor, *_ = room.candidates(["walls", "ceiling", "floor"], 0.2, 1.5)
    return ev, CandidateSet(ev, pos, bor), link, pts


def test_packed_tdoa_terms_pinned_to_metrics(small_tdoa):
    ev, cs, link, pts = small_tdoa
    idx = [0, 5, 11, 17, 23, 30]
    O, M = cs.O[idx], cs.M[idx]
    assert O.shape[-1] == 9
    J6 = info6_from_sums(O.sum(axis=0), M.sum(axis=0))
    ref = tdoa_gram(pts, cs.positions[idx], M.T)
    ref6 = np.stack([ref[:, 0, 0], ref[:, 1, 1], ref[:, 2, 2], ref[:, 0, 1], ref[:, 0, 2], ref[:, 1, 2]], axis=-1)
    assert np.allclose(J6, ref6, atol=1e-12)
    # Objective components: PDOP percentiles, coverage (k = 4), N-1 and information vs brute force.
    c = cs.components(idx, n1=True)
    pd_ = tdoa_pdop(pts, cs.positions[idx], M.T)
    assert np.mean(np.isinf(pd_)) > 0  # the case exercises the < 4 links cap
    assert c["pdop_q"] == pytest.approx(percentiles(pd_, (90,), cap=20)["p90"], rel=1e-9)
    assert c["coverage"] == pytest.approx(np.mean(M.sum(axis=0) >= 4))
    worst = max(percentiles(tdoa_pdop(pts, cs.positions[[j for j in idx if j != i]],
                                      cs.M[[j for j in idx if j != i]].T), (90,), cap=20)["p90"] for i in idx)
    assert c["n1_pdop_q"] == pytest.approx(worst, rel=1e-9)
    s = 0.14 / np.sqrt(2)  # arrival sd; the evaluator floors det at 1e-12 in unit-noise terms
    ld = np.log(np.maximum(np.linalg.det(tdoa_information_matrix(pts, cs.positions[idx], 0.14, M.T)), 1e-12 / s**6))
    assert c["logdet_low"] == pytest.approx(np.percentile(ld, 10, method="lower"), rel=1e-9)
    assert pdop_from_g6(_outer6(np.eye(3)).sum(axis=0), 20) == pytest.approx(np.sqrt(3))


def test_tdoa_greedy_is_lazy_exact_on_the_clock_augmented_logdet(small_tdoa):
    ev, cs, _, _ = small_tdoa
    eps = 1e-3
    U4 = np.concatenate([cs.U, np.ones(cs.U.shape[:2] + (1,))], axis=2)

    def F(idx):
        G = np.tile(np.eye(4) * eps, (U4.shape[1], 1, 1))
        for c in idx:
            u = U4[c] * cs.M[c][:, None]
            G = G + np.einsum("pi,pj->pij", u, u)
        return np.sum(np.linalg.slogdet(G)[1])

    lazy = lazy_greedy_logdet(cs, 5, eps=eps)["idx"]
    # Each lazy pick is a best plain-greedy pick given the previous ones (ties in a symmetric room).
    for k in range(5):
        best = max(F(lazy[:k] + [c]) for c in range(len(cs)) if c not in lazy[:k])
        assert F(lazy[: k + 1]) == pytest.approx(best, rel=1e-9, abs=1e-9)
    # It differs from the TWR greedy (3x3 log det) here: the objective is really the TDoA one.
    twr = lazy_greedy_logdet(CandidateSet(LayoutEvaluator(ev.points, ev.link), cs.positions, cs.boresights), 5, eps=eps)
    assert F(twr["idx"]) < F(lazy) - 1e-6
    # det of the augmented information = n det(J_tdoa) (Schur complement of the clock entry n)
    a = cs.positions[lazy]
    u4 = np.concatenate([unit_los(ev.points, a)[0], np.ones((len(ev.points), 5, 1))], axis=2)
    d4 = np.linalg.det(np.einsum("pni,pnj->pij", u4, u4))
    assert np.allclose(d4, 5 * np.linalg.det(tdoa_gram(ev.points, a)), rtol=1e-8, atol=1e-12)


def test_config_measurement_and_tdoa_sigma(tmp_path):
    base = {"mode": "room", "room": {"box": [6, 5, 3]}}
    c = PlacementConfig.model_validate(base)
    assert c.measurement == "twr" and c.radio.k == 3 and c.radio.tdoa_sigma is None
    c = PlacementConfig.model_validate({**base, "measurement": "tdoa", "radio": {"range_sigma": 0.2}})
    assert c.radio.k == 4 and c.radio.tdoa_sigma_m == pytest.approx(0.2 * np.sqrt(2))
    bad = [({**base, "measurement": "toa"}, "field 'measurement'"),
           ({**base, "radio": {"tdoa_sigma": 0}}, "field 'radio.tdoa_sigma'"),
           ({**base, "measurement": "tdoa", "radio": {"k": 3}}, "radio.k = 3"),
           ({"mode": "structure", "n_anchors": 40, "measurement": "tdoa", "structure": {"name": "jib-crane"}},
            "room mode only")]
    for i, (cfg, msg) in enumerate(bad):
        path = tmp_path / f"bad{i}.yaml"
        path.write_text(yaml.safe_dump(cfg))
        with pytest.raises(ConfigError, match=msg.replace(".", r"\.")):
            load_config(path)


def test_place_tdoa_end_to_end(tmp_path):
    cfg = {
        "mode": "room", "seed": 1, "n_anchors": 5, "measurement": "tdoa",
        "radio": {"preset": "dw1000-indoor", "range_sigma": 0.1},
        "room": {"box": [6.0, 5.0, 3.0], "mount": {"spacing": 1.5}, "grid_step": 1.0},
        "optimizer": {"swap_rounds": 1, "maxiter": 2, "popsize": 3},
        "compare": {"ceiling": [[0.2, 0.2, 2.8], [5.8, 0.2, 2.8], [5.8, 4.8, 2.8], [0.2, 4.8, 2.8], [3, 2.5, 2.8]]},
    }
    path = tmp_path / "room_tdoa.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    r = runner_invoke(["place", str(path), "--out", str(out), "--no-plots"])
    assert r.exit_code == 0, r.output
    assert "TDoA" in r.output
    js = json.loads((out / "placement.json").read_text())
    assert js["measurement"] == "tdoa" and js["noise_sigma_m"] == pytest.approx(0.1 * np.sqrt(2))
    # The reported PDOP is the TDoA PDOP of the written anchors (recomputed from scratch).
    room = Room.box(6, 5, 3)
    pts = room.flight_points([0.5, 0.5, 0.3], [5.5, 4.5, 2.5], 1.0)
    a = np.array(js["anchors"])
    links = LinkModel(max_range=15.0).links(pts, a, np.array(js["boresights"]))
    pd_ = tdoa_pdop(pts, a, links)
    assert js["pdop_p95"] == pytest.approx(percentiles(pd_, (95,), cap=20)["p95"], rel=1e-4)  # JSON: 0.1 mm
    assert js["pdop_p95"] > percentiles(pdop(pts, a, links), (95,), cap=20)["p95"]  # TDoA is not TWR
    ceil = [row for row in js["table"] if row["layout"] == "ceiling"][0]
    assert ceil["pdop_p95"] > js["pdop_p95"]  # coplanar ceiling layout is poor under TDoA


def runner_invoke(args):
    return CliRunner().invoke(app, args)
