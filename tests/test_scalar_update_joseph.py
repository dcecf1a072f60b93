"""The scalar measurement update of the filter (``estimation.kernels.scalar_update``, the arithmetic of
``_scalar_update_ws`` that the compiled pass runs for every range and TDoA) against an element-by-element
reference of its documented arithmetic.

Tolerance: none.  The kernel evaluates the Joseph form's rows over their whole length and mirrors the upper
triangle (a speed change); the reference evaluates the upper triangle element by element in plain Python
floats (``P[i, j] - K[i] Ph[j] - Ph[i] K[j] + K[i] K[j] S`` for ``j >= i``, mirrored), with ``Ph`` and
``h^T P h`` summed in index order as the kernel documents, so every bit must agree, the sign of zeros
included.  The input covariance is asymmetric inside its 9x9 dynamic block (as the covariance step leaves
it, by an ulp): only its upper triangle may be read.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwbimu.estimation import kernels as K


def _reference(x, P, h, pred, z, r_var, gain_mask, robust_kind, robust_c):
    """The update in plain Python floats: returns (x, P, accepted, weight)."""
    N = P.shape[0]
    r = z - pred
    Ph = [0.0] * N
    for i in range(N):
        acc = 0.0
        for j in range(N):
            acc += float(P[i, j]) * float(h[j])
        Ph[i] = acc
    hPh = 0.0
    for i in range(N):
        hPh += float(h[i]) * Ph[i]
    S0 = hPh + r_var
    w = max(K.robust_weight(r / math.sqrt(S0), robust_kind, robust_c), 1e-6)
    S = hPh + r_var / w
    Kg = [Ph[i] / S * float(gain_mask[i]) for i in range(N)]
    out = np.empty_like(P)
    for i in range(N):
        for j in range(i, N):
            out[i, j] = float(P[i, j]) - Kg[i] * Ph[j] - Ph[i] * Kg[j] + Kg[i] * Kg[j] * S
    for i in range(1, N):
        for j in range(i):
            out[i, j] = out[j, i]
    x2 = x.copy()
    K.inject(x2, np.array([k * r for k in Kg]))
    return x2, out, w


@pytest.mark.parametrize("n_extra, robust_kind", [(0, K.ROBUST_NONE), (0, K.ROBUST_HUBER), (6, K.ROBUST_GM)])
def test_scalar_update_is_bit_identical_to_the_elementwise_joseph_form(n_extra, robust_kind):
    rng = np.random.default_rng(40 + n_extra)
    N = 19 + n_extra
    for trial in range(5):
        A = rng.normal(size=(N, N))
        P = A @ A.T / N + np.eye(N)
        P[2, 7] += 1e-3  # asymmetric inside the 9x9 block: the update must read the upper triangle only
        P[8, 0] -= 2e-3
        x = rng.normal(size=N + 1)
        x[6:10] /= np.linalg.norm(x[6:10])
        h = rng.normal(size=N)
        h[rng.integers(0, N)] = 0.0
        gain_mask = np.ones(N)
        gain_mask[15:18] = 0.0 if trial % 2 else 1.0  # a consider (Schmidt) lever arm on every other trial
        pred, z, r_var = 5.0, 5.0 + rng.normal() * 3.0, 0.04
        x_ref, P_ref, w_ref = _reference(x, P, h, pred, z, r_var, gain_mask, robust_kind, 1.5)
        out = np.empty(7)
        x_k, P_k = x.copy(), P.copy()
        K.scalar_update(x_k, P_k, h, pred, z, r_var, 0.0, False, robust_kind, 1.5, gain_mask, out)
        assert out[3] == 1.0 and out[4] == w_ref
        assert np.array_equal(P_k, P_ref) and np.array_equal(np.signbit(P_k), np.signbit(P_ref))
        assert np.array_equal(x_k, x_ref)
        assert np.array_equal(P_k, P_k.T)  # mirrored: exactly symmetric after an update
        assert not np.array_equal(P_k, P)  # the update did something


def test_rejected_update_leaves_the_state_alone():
    rng = np.random.default_rng(7)
    N = 19
    A = rng.normal(size=(N, N))
    P = A @ A.T / N + np.eye(N)
    x = rng.normal(size=N + 1)
    x[6:10] /= np.linalg.norm(x[6:10])
    h = rng.normal(size=N)
    out = np.empty(7)
    x_k, P_k = x.copy(), P.copy()
    K.scalar_update(x_k, P_k, h, 0.0, 1e3, 0.01, 9.0, False, K.ROBUST_NONE, 1.5, np.ones(N), out)
    assert out[3] == 0.0 and out[2] > 9.0
    assert np.array_equal(P_k, P) and np.array_equal(x_k, x)
