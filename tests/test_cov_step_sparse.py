"""The filter's covariance step ``models.kernels._cov_step_sym`` (block-sparse ``Phi P Phi^T + Q`` that touches
only the rows and columns of ``dp, dv, dtheta``).

Tolerance: none against :func:`cov_step_blocks` (the same floating-point operations on every element it
writes, in the same order, for a covariance symmetric outside its 9x9 dynamic block, which the filter's
always is: checked on a real pass here); ``1e-12`` of ``max |P|`` against a dense ``Phi P Phi^T + Q`` built
from :func:`error_transition` (a different summation order, so a few ulps of the largest entry).
"""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions
from uwbimu.estimation.eskf import build_problem
from uwbimu.estimation.filterpass import run_pass
from uwbimu.estimation.init import initialise
from uwbimu.models import kernels as MK
from uwbimu.models.state import StateLayout
from uwbimu.sim import builtin_scenario, simulate

NOISE = np.array([4e-4, 3e-5, 1e-6, 1e-8, 1e-9, 1e-10])


def _tables(n_extra: int, gauss_markov: bool):
    return StateLayout(n_extra).process_noise(NOISE[:4], {"lever": (NOISE[4], 0.0), "t_d": (NOISE[5], 0.0),
                                                          "anchor_bias": (0.01, 0.5 if gauss_markov else 0.0)})


def _state(rng, N):
    x = rng.normal(size=N + 1)
    x[6:10] /= np.linalg.norm(x[6:10])
    return x


def _spd(rng, N):
    A = rng.normal(size=(N, N))
    return A @ A.T / N + np.eye(N)


@pytest.mark.parametrize("n_extra, gauss_markov", [(0, False), (4, True), (9, False)])
def test_cov_step_sym_is_bit_identical_to_cov_step_blocks(n_extra, gauss_markov):
    rng = np.random.default_rng(10 + n_extra)
    N = 19 + n_extra
    pn = _tables(n_extra, gauss_markov)
    B, A = np.empty((7, 3, 3)), np.empty((15, N))
    for dt in (1e-3, -2e-3, 0.0, 0.3):
        x = _state(rng, N)
        u = rng.normal(size=6) * 5.0
        P0 = _spd(rng, N)
        P0[1, 7] += 1e-3  # asymmetric inside the 9x9 block (the step's rounding leaves such ulps there)
        P1, P2 = P0.copy(), P0.copy()
        for _ in range(4):  # chained: the asymmetry the step leaves in the 9x9 block stays harmless
            MK.cov_step_blocks(P1, x, u, dt, pn)
            MK._cov_step_sym(P2, x, u, dt, pn, B, A)
            assert np.array_equal(P1, P2) and np.array_equal(np.signbit(P1), np.signbit(P2))
            # symmetric outside the 9x9 block, as the next step requires
            assert np.array_equal(P2[9:, :], P2[:, 9:].T)


@pytest.mark.parametrize("n_extra", [0, 5])
def test_cov_step_sym_equals_dense_phi_p_phit_plus_q(n_extra):
    """Against the textbook dense product (constant and random-walk blocks, so that ``Q`` is additive: it is
    the step applied to ``P = 0``)."""
    rng = np.random.default_rng(3 + n_extra)
    N = 19 + n_extra
    pn = _tables(n_extra, False)
    B, A = np.empty((7, 3, 3)), np.empty((15, N))
    for dt in (1e-3, 5e-3, -1e-3):
        x = _state(rng, N)
        u = rng.normal(size=6) * 3.0
        P = _spd(rng, N)
        Phi = np.empty((N, N))
        MK.error_transition(x, u, dt, Phi)
        Q = np.zeros((N, N))
        MK._cov_step_sym(Q, x, u, dt, pn, B, A)
        expect = Phi @ P @ Phi.T + Q
        got = P.copy()
        MK._cov_step_sym(got, x, u, dt, pn, B, A)
        np.testing.assert_allclose(got, expect, rtol=0, atol=1e-12 * np.abs(expect).max())
        assert not np.array_equal(got, P)  # the step did something


def test_filter_pass_keeps_p_symmetric_outside_the_dynamic_block():
    """The precondition of ``_cov_step_sym`` on a real pass (range updates, outputs): ``P`` is exactly symmetric
    outside its 9x9 block after the pass, and the covariance did evolve."""
    sc = builtin_scenario("calibration-flight")
    ds = simulate(sc.model_copy(update={"duration": 20.0}))
    opts = EskfOptions(store_covariance=False)
    prob, info = build_problem(ds, opts)
    st = initialise(prob, opts, info["priors"])
    prob.cov_every = 1
    res = run_pass(prob, st.x, st.P, st.k, st.j)
    P = res.P
    assert np.all(np.isfinite(P)) and not np.array_equal(P, st.P)
    assert np.array_equal(P[9:, :], P[:, 9:].T)
    assert np.count_nonzero(res.rec[:, 3] > 0) > 100  # updates were applied
    # the 9x9 block differs from its transpose by rounding only
    D = P[:9, :9]
    np.testing.assert_allclose(D, D.T, rtol=0, atol=1e-12 * np.abs(D).max())
