"""Time-offset grid search: widening at an edge, flat scores, parabolic refinement; verdict."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwbimu.estimation.timeoffset import search_time_offset, time_offset_verdict


def _quadratic(td_true, sd, n=200):
    """Mean NLL per innovation whose total (x n/2) is (td - td_true)^2 / (2 sd^2) + const."""
    def score(tds):
        tds = np.asarray(tds, dtype=float)
        total = (tds - td_true) ** 2 / (2 * sd**2)
        return 1.0 + 2.0 * total / n, np.full(len(tds), n)
    return score


GRID = [round(-0.25 + 0.05 * i, 3) for i in range(11)]


def test_interior_minimum_is_refined_with_curvature_sd():
    out = search_time_offset(_quadratic(0.037, 0.01), GRID)
    assert out["status"] == "found"
    assert out["time_offset"] == pytest.approx(0.037, abs=1e-9)
    assert out["time_offset_sd"] == pytest.approx(0.01, rel=1e-6)


def test_edge_minimum_widens_the_grid_instead_of_returning_the_edge():
    out = search_time_offset(_quadratic(0.502, 0.02), GRID, max_abs_s=1.0)
    assert out["status"] == "found"
    assert max(out["grid"]) > 0.55
    assert out["time_offset"] == pytest.approx(0.502, abs=1e-9)


def test_edge_beyond_the_widest_grid_is_not_identified():
    out = search_time_offset(_quadratic(2.0, 0.02), GRID, max_abs_s=0.5)
    assert out["status"] == "not identified" and out["time_offset"] is None
    assert max(out["grid"]) == pytest.approx(0.5)


def test_flat_scores_are_not_identified():
    out = search_time_offset(_quadratic(0.0, 1.0), GRID)  # sd 1 s: < 0.05 nats across the grid
    assert out["status"] == "not identified"
    assert "flat" in out["reason"]


def test_failed_scores_are_not_identified():
    out = search_time_offset(lambda tds: (np.full(len(tds), np.inf), np.zeros(len(tds), int)), GRID)
    assert out["status"] == "not identified"


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_verdict_is_scale_free(scale):
    assert time_offset_verdict(0.005 * scale, 0.1 * scale)[0] == "identified"
    assert time_offset_verdict(0.05 * scale, 0.1 * scale)[0] == "weakly identified"
    assert time_offset_verdict(0.09 * scale, 0.1 * scale)[0] == "not identified"
    assert time_offset_verdict(0.0, 0.1, fixed=True)[0] == "fixed"


def test_verdict_after_a_failed_initial_search_is_not_identified():
    assert time_offset_verdict(0.001, 0.1, init_status="not identified")[0] == "not identified"


def test_hover_time_offset_is_not_identified_and_held_at_its_prior():
    """Near-hover (no velocity change): the start cannot locate t_d, so it is held at its prior and
    reported "not identified" (before: -129 +/- 26 ms for a true 30 ms, 6 sigma off)."""
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("hover").model_copy(update={"duration": 25.0}))
    opts = EskfOptions(store_covariance=False)
    res = run_eskf(ds, opts)
    cal = res.calibration
    assert cal["time_offset_verdict"] == "not identified"
    assert cal["time_offset"] == (opts.time_offset.prior or 0.0)
    assert cal["time_offset_sd"] == pytest.approx(opts.time_offset.prior_sd)
    assert abs(cal["time_offset"] - ds.meta.truth.time_offset) < 3 * cal["time_offset_sd"]
    kinds = [e["kind"] for e in res.events]
    assert "time_offset_held" in kinds and "time_offset_verdict" in kinds


def test_uwb_clock_shift_moves_time_offset_by_the_opposite_amount():
    """Issue 11 item 6 clock-shift check on a simulated flight (INRoL figures: docs/estimator.md):
    stamping the UWB log 100 ms late (outside the default +-0.25 s grid's centre cell, so the grid
    must find it) moves t_d by -100 ms within 3 sd and 20 ms, with an "identified" verdict."""
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 30.0}))
    opts = EskfOptions(store_covariance=False)
    base = run_eskf(ds, opts).calibration
    ds.uwb = ds.uwb.assign(t=ds.uwb["t"] + 0.1)
    shifted = run_eskf(ds, opts).calibration
    move = shifted["time_offset"] - base["time_offset"]
    sd = math.hypot(base["time_offset_sd"], shifted["time_offset_sd"])
    assert abs(move + 0.1) < min(3 * sd, 0.02)
    assert base["time_offset_verdict"] == shifted["time_offset_verdict"] == "identified"
