"""``metrics.filter.nees_series``: one stacked solve instead of a Python loop of per-row solves.

Tolerance: ``1e-12`` relative against the per-row ``err @ np.linalg.solve(cov, err)`` (the same LAPACK
solve per matrix; the quadratic form's sum of ``d`` products may be summed in another order).  A singular
matrix makes only its own row NaN, as before.
"""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.errors import InputError
from uwbimu.metrics.filter import nees_series


def _per_row(err, cov):
    out = np.full(len(err), np.nan)
    for i in range(len(err)):
        try:
            out[i] = float(err[i] @ np.linalg.solve(cov[i], err[i]))
        except np.linalg.LinAlgError:
            pass
    return out


def _problem(rng, K, d):
    A = rng.normal(size=(K, d, d))
    cov = A @ A.transpose(0, 2, 1) + 0.1 * np.eye(d)
    err = rng.normal(size=(K, d)) * 0.3
    return err, cov


@pytest.mark.parametrize("d", [3, 6, 15])
def test_stacked_nees_equals_the_per_row_solves(d):
    rng = np.random.default_rng(d)
    err, cov = _problem(rng, 500, d)
    got = nees_series(err, cov)
    want = _per_row(err, cov)
    assert got.shape == (500,)
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    # a scaled covariance scales the NEES inversely (the quadratic form is really e^T P^-1 e)
    np.testing.assert_allclose(nees_series(err, 4.0 * cov), want / 4.0, rtol=1e-12)


def test_a_singular_matrix_makes_only_its_row_nan():
    rng = np.random.default_rng(1)
    err, cov = _problem(rng, 50, 6)
    cov[7] = 0.0
    got = nees_series(err, cov)
    assert np.isnan(got[7])
    keep = np.arange(50) != 7
    np.testing.assert_allclose(got[keep], _per_row(err, cov)[keep], rtol=1e-12)


def test_mismatched_shapes_are_refused():
    with pytest.raises(InputError):
        nees_series(np.zeros((4, 3)), np.zeros((4, 2, 2)))
