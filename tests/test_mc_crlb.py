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
