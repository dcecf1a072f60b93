"""``filterpass.cubic_midpoints`` (the compiled mid-interval inputs) against ``reference.midpoint_inputs``:
bit-identical (no tolerance), on a simulated log, on jittered stamps, at the log's ends and with < 4 samples."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.errors import InputError
from uwbimu.estimation.filterpass import cubic_midpoints
from uwbimu.models.reference import midpoint_inputs
from uwbimu.sim import builtin_scenario, simulate


def test_equal_to_the_reference_on_a_simulated_log():
    ds = simulate(builtin_scenario("calibration-flight").updated(duration=20.0))
    t = ds.imu["t"].to_numpy(float)
    u = ds.imu[["ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    got = cubic_midpoints(t, u)
    assert got.shape == (len(t) - 1, 6)
    assert np.array_equal(got, midpoint_inputs(t, u))


@pytest.mark.parametrize("n", [2, 3, 4, 5, 1000])
def test_equal_to_the_reference_on_jittered_stamps(n):
    rng = np.random.default_rng(n)
    t = np.cumsum(rng.uniform(0.5e-3, 1.5e-3, size=n))
    u = rng.normal(size=(n, 6)) * [3, 3, 3, 1, 1, 1]
    got = cubic_midpoints(t, u)
    assert np.array_equal(got, midpoint_inputs(t, u))
    # a cubic input is reproduced exactly at the midpoints (up to rounding): the interpolant is a cubic
    if n >= 4:
        tm = 0.5 * (t[:-1] + t[1:])
        cub = lambda s: 1.0 + 2.0 * s - 3.0 * s**2 + 0.5 * s**3  # noqa: E731
        v = cubic_midpoints(t, np.repeat(cub(t)[:, None], 6, axis=1))
        np.testing.assert_allclose(v[:, 0], cub(tm), rtol=1e-9, atol=1e-9)


def test_wrong_shapes_are_refused():
    with pytest.raises(InputError):
        cubic_midpoints(np.arange(5.0), np.zeros((5, 3)))
