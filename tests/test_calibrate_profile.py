"""The t_d profile verdict: never a grid-edge value reported as found, flat / multi-modal refused with advice."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.calibration.profile import confidence_interval, motion_advice, profile_verdict

GRID = np.round(np.arange(-0.5, 0.5001, 0.02), 10)


def _parabola(centre, sigma, grid=GRID, offset=100.0):
    return offset + ((grid - centre) / sigma) ** 2


@pytest.mark.parametrize("centre,sigma", [(0.013, 0.04), (-0.21, 0.025), (0.3, 0.06)])
def test_clear_minimum_is_identified_with_curvature_sigma(centre, sigma):
    verdict, best, vertex, sig = profile_verdict(GRID, _parabola(centre, sigma))
    assert verdict == "identified"
    assert abs(best - centre) <= 0.01 + 1e-12
    assert vertex == pytest.approx(centre, abs=1e-9)  # exact parabola: exact vertex and curvature
    assert sig == pytest.approx(sigma, rel=1e-6)
    lo, hi = confidence_interval(GRID, _parabola(centre, sigma), 9.0)
    assert lo == pytest.approx(centre - 3 * sigma, abs=0.003) and hi == pytest.approx(centre + 3 * sigma, abs=0.003)


@pytest.mark.parametrize("centre", [0.62, -0.55, 0.5, -0.5])
def test_minimum_at_or_beyond_the_grid_edge_is_never_found(centre):
    verdict, best, vertex, sig = profile_verdict(GRID, _parabola(centre, 0.05))
    assert verdict == "at_grid_edge"
    assert best in (GRID[0], GRID[-1])
    assert np.isnan(vertex) and np.isnan(sig)


def test_minimum_one_step_inside_an_edge_whose_set_reaches_the_edge_is_flat():
    # minimum one step inside, but the confidence set (chi2 - min < 9) still touches the edge
    verdict, *_ = profile_verdict(GRID, _parabola(0.48, 0.05))
    assert verdict == "flat"


def test_flat_profile_is_not_identified():
    chi2 = 50.0 + 2.0 * np.sin(7 * GRID) + 0.5 * GRID  # varies by < 9 over the grid
    verdict, _best, vertex, sig = profile_verdict(GRID, chi2)
    assert verdict == "flat" and np.isnan(vertex) and np.isnan(sig)


def test_two_separated_minima_are_multi_modal():
    # periodic-motion aliasing: two minima 0.3 s apart, a hump of 40 between them
    chi2 = np.minimum(_parabola(-0.15, 0.03), _parabola(0.15, 0.03) + 2.0)
    chi2 = np.minimum(chi2, 140.0)
    verdict, _best, vertex, _sig = profile_verdict(GRID, chi2)
    assert verdict == "multi_modal" and np.isnan(vertex)


def test_failed_point_is_not_identified():
    chi2 = _parabola(0.0, 0.05)
    chi2[10] = np.nan
    assert profile_verdict(GRID, chi2)[0] == "failed_points"


class _Eskf:
    t = np.linspace(0.0, 10.0, 1001)
    states = np.zeros((1001, 16))
    states[:, 3] = 0.3 * np.sin(t)


def test_advice_names_the_remedy_of_each_verdict():
    edge = motion_advice(_Eskf(), "at_grid_edge", GRID)
    assert "widen td_profile.half_width" in edge and "[-500, 500] ms" in edge
    assert "periodic" in motion_advice(_Eskf(), "multi_modal", GRID)
    flat = motion_advice(_Eskf(), "flat", GRID)
    assert "RMS speed 0.21 m/s" in flat and "back-and-forth" in flat
