"""Posterior CRLB of the Monte Carlo study: the shared-packet TDoA model against a batch Fisher information."""

from __future__ import annotations

import numpy as np

from uwbimu.studies.crlb import _recursion, inside_hull_fraction


def test_shared_packet_updates_equal_batch_fisher_information():
    """Static snapshot (dt = 0): differences of packets with a shared error, processed one by one
    with per-anchor packet states, give exactly the batch posterior with the differences' true
    (correlated) covariance."""
    rng = np.random.default_rng(3)
    M, D = 4, 19 + 4
    # packets: (anchor, packet id); rows difference two packets (TDoA2-like chain plus a TDoA3-like reuse)
    packets = [(0, 0), (1, 1), (2, 2), (3, 3), (0, 4), (1, 5)]
    rows = [(0, 1), (1, 2), (2, 3), (3, 4), (2, 5)]  # the last reuses anchor 2's latest packet (TDoA3-like)
    var = 0.05**2
    G = rng.normal(size=(len(packets), 3))  # d(distance of packet)/d(position)
    H = np.zeros((len(rows), D))
    refresh = np.full((len(rows), 2), -1, dtype=np.int64)
    held = np.full(M, -1)
    for m, (j, k) in enumerate(rows):
        aj, ak = packets[j][0], packets[k][0]
        H[m, :3] = G[k] - G[j]
        H[m, 19 + ak] += 1.0
        H[m, 19 + aj] -= 1.0
        for s, (anc, pk) in enumerate(((aj, j), (ak, k))):
            if held[anc] != pk:
                refresh[m, s] = 19 + anc
                held[anc] = pk
    P0 = np.diag(np.r_[np.full(3, 1.0), np.full(16, 1e-12), np.full(M, var)])
    X = np.zeros((2, 20))
    X[:, 6] = 1.0
    P = _recursion(P0.copy(), X, np.zeros((2, 6)), np.zeros(1), np.zeros(6), np.zeros(len(rows), np.int64), H,
                   np.zeros(len(rows)), refresh, var, np.zeros((2, 3)))
    # batch: z = Dm (G p + e), e ~ N(0, var I) per packet
    Dm = np.zeros((len(rows), len(packets)))
    for m, (j, k) in enumerate(rows):
        Dm[m, k], Dm[m, j] = 1.0, -1.0
    C = Dm @ Dm.T * var
    J = np.linalg.inv(P0[:3, :3]) + (Dm @ G).T @ np.linalg.solve(C, Dm @ G)
    np.testing.assert_allclose(P[:3, :3], np.linalg.inv(J), rtol=1e-8, atol=1e-12)
    # treating the differences as independent (var 2 sigma^2) would not be a lower bound here
    J_indep = np.linalg.inv(P0[:3, :3]) + (Dm @ G).T @ (Dm @ G) / (2 * var)
    assert np.trace(np.linalg.inv(J_indep)) > np.trace(P[:3, :3])


def test_inside_hull_fraction():
    box = np.array([[x, y, z] for x in (0, 4) for y in (0, 4) for z in (0, 2)], float)
    pts = np.array([[2, 2, 1], [5, 2, 1], [1, 1, 1], [2, 2, 3]], float)
    assert inside_hull_fraction(pts, box) == 0.5


def test_anchor_bias_bound_contains_the_bias_free_one():
    """The bound with an unknown constant bias per anchor (the batch calibrator's parameterisation) is the larger:
    its lever-arm / t_d block minus the bias-free one is positive semi-definite; with a vanishing bias prior it is
    the bias-free bound; the bias states are learnt from the data (final sd well below the prior's)."""
    import pytest

    from uwbimu.sim import builtin_scenario, simulate_full
    from uwbimu.studies.crlb import posterior_bound

    sc = builtin_scenario("calibration-flight").model_copy(update={"duration": 10.0})
    sim = simulate_full(sc)
    free = posterior_bound(sim, sc)
    biased = posterior_bound(sim, sc, anchor_bias_sd=0.3)
    tight = posterior_bound(sim, sc, anchor_bias_sd=1e-6)
    sl = slice(15, 19)  # lever arm and t_d in the 19-dim error state
    d = biased["P_final"][sl, sl] - free["P_final"][sl, sl]
    assert np.linalg.eigvalsh(d).min() > -1e-9 * np.abs(free["P_final"][sl, sl]).max()
    np.testing.assert_allclose(tight["P_final"][sl, sl], free["P_final"][sl, sl], rtol=1e-4)
    assert len(biased["anchor_bias_sd_final"]) == len(sc.anchor_ids())
    assert np.all(biased["anchor_bias_sd_final"] < 0.1 * 0.3)
    tdoa = builtin_scenario("crazyflie-tdoa3").model_copy(update={"duration": 1.0})
    with pytest.raises(ValueError):  # TDoA has its packet states in those slots
        posterior_bound(simulate_full(tdoa), tdoa, anchor_bias_sd=0.3)
