"""Posterior CRLB (estimation/crlb.py) and the calibration states against it (reduced Monte Carlo).

The full 40-seed figure is ``python benchmarks/bench_eskf_crlb.py --seeds 40`` (docs/estimator.md)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

from uwbimu.estimation import EskfOptions
from uwbimu.estimation.crlb import posterior_crlb
from uwbimu.estimation.eskf import build_problem
from uwbimu.sim import builtin_scenario, simulate_full

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_eskf_crlb import one_seed, truth_states  # noqa: E402


@pytest.fixture(scope="module")
def short_sim():
    sc = builtin_scenario("excited-90s").model_copy(update={"duration": 20.0})
    return simulate_full(sc)


def _bound(sim, opts, P0):
    ds = sim.dataset
    prob, _ = build_problem(ds, opts)
    k0 = int(np.searchsorted(ds.imu_t, ds.uwb["t"].iloc[0] + ds.meta.truth.time_offset))
    return posterior_crlb(prob, truth_states(sim), P0, k0)


def test_bound_is_information_monotone(short_sim):
    P0 = np.diag(np.r_[np.full(6, 0.01), np.full(3, 1e-3), np.full(6, 1e-4), np.full(3, 0.0025), 1e-4])
    opts = EskfOptions()
    P = _bound(short_sim, opts, P0)
    d = np.diag(P)
    assert np.all(np.isfinite(P)) and np.all(np.linalg.eigvalsh(P) > 0)
    # data only add information about the constant calibration states
    assert np.all(d[15:19] < np.diag(P0)[15:19])
    # noisier ranges: a larger bound on every calibration state
    P_noisy = _bound(short_sim, opts.model_copy(update={"range_sigma": 4 * short_sim.dataset.meta.range_sigma}), P0)
    assert np.all(np.diag(P_noisy)[15:19] > d[15:19])


def test_calibration_errors_against_crlb_reduced_monte_carlo():
    """M = 8 seeds of the 90 s excited flight: RMS error of each lever-arm axis and t_d within
    1.15x the bound and RMS(error / sd) consistent, both with the 99 % sampling spread of M seeds."""
    M = 8
    rows = [one_seed(s, 90.0, EskfOptions(store_covariance=False)) for s in range(M)]
    E = np.array([r[0] for r in rows])
    S = np.array([r[1] for r in rows])
    C = np.array([r[2] for r in rows])
    lo, hi = np.sqrt(chi2.ppf([0.005, 0.995], M) / M)
    ratio = np.sqrt(np.mean(E**2, axis=0) / np.mean(C**2, axis=0))
    nerr = np.sqrt(np.mean((E / S) ** 2, axis=0))
    assert np.all(ratio <= 1.15 * hi), ratio
    assert np.all((nerr >= 0.8 * lo) & (nerr <= 1.2 * hi)), nerr
    # the filter's reported sd and the bound agree (linearisation at the estimate costs little here)
    np.testing.assert_allclose(S.mean(axis=0), C.mean(axis=0), rtol=0.15)
