"""The range model chosen on the log by blocked cross-validation (issue 27, item 7).

Seeded simulations with a known range-error model: white noise, a direction-dependent bias in the
tag's body frame (order-2 Fourier terms, added to the simulated ranges from the true trajectory),
and per-anchor AR(1) errors (the benchmark's coloured-noise model).  The selection must name the true
family; assertions on the structured record.
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import numpy as np
import pytest

from uwbimu.calibration.options import CalibrationOptions
from uwbimu.calibration.range_model_select import (FAMILIES, HUBER_GRID, apply_selection, range_residuals,
                                                   select_range_model)
from uwbimu.errors import InputError
from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.sim import builtin_scenario, simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from check_clock_false_alarms import ar1_ranges  # noqa: E402  (one copy of the coloured-noise model)
from bench_range_model_select import COEF, with_direction_bias  # noqa: E402  (one copy of the injected bias)


@pytest.fixture(scope="module")
def flight():
    return simulate(builtin_scenario("calibration-flight").updated(duration=60.0, seeds={"noise": 1}))


def _select(ds):
    return select_range_model(ds, run_eskf(ds, EskfOptions()))


def test_white_noise_log_chooses_the_white_model(flight):
    sel = _select(flight)
    assert sel.chosen == "white"
    assert sel.candidates == list(FAMILIES) and sel.folds == 5 and len(sel.block_edges) == 6
    assert np.all(np.diff(sel.block_edges) > 0)
    for f in FAMILIES:
        assert set(sel.scores[f]) == {str(k) for k in HUBER_GRID}
        assert all(len(v) == sel.folds and np.all(np.isfinite(v)) for v in sel.scores[f].values())
        assert sel.family_k[f] in HUBER_GRID
    assert sel.huber_k in HUBER_GRID and sel.reason
    # the white sd recovered about the simulated 5 cm
    assert 0.035 < sel.params["sigma"] < 0.07 and "drift_sd" not in sel.params and "direction" not in sel.params


def test_direction_bias_log_chooses_the_direction_model(flight):
    sel = _select(with_direction_bias(flight))
    assert sel.chosen == "direction"
    # it beats white and drift on every fold
    for other in ("white", "drift"):
        assert np.all(np.asarray(sel.family_scores["direction"]) > np.asarray(sel.family_scores[other]))
    c = sel.params["direction"]
    assert abs(c["cos2"] - COEF[2]) < 0.02 and abs(c["sin2"] - COEF[3]) < 0.02


def test_coloured_noise_log_chooses_the_drift_model(flight):
    sel = _select(ar1_ranges(flight, sigma=0.10, tau=3.0, seed=1001))
    assert sel.chosen == "drift"
    assert 0.05 < sel.params["drift_sd"] < 0.2 and 0.5 < sel.params["correlation_time"] < 10.0


def test_apply_selection_sets_the_options(flight):
    sel = _select(with_direction_bias(flight))
    o = apply_selection(CalibrationOptions(range_bias_drift={"sd": 0.1}), sel)
    assert o.range_model.direction is not None and o.range_bias_drift is None and o.huber_k == sel.huber_k
    sel.chosen = "drift"
    sel.params.update({"drift_sd": 0.08, "correlation_time": 3.0})
    o = apply_selection(CalibrationOptions(), sel)
    assert o.range_model.direction is None and o.range_bias_drift.sd == 0.08
    assert o.range_bias_drift.knot_spacing <= o.range_bias_drift.correlation_time / 2


def test_residuals_about_the_true_trajectory_are_the_noise(flight):
    """Sign and geometry: about the ESKF trajectory the residuals are about the simulated noise (5 cm, zero mean)."""
    res = run_eskf(flight, EskfOptions())
    d = range_residuals(flight, res)
    assert len(d["r"]) > 0.8 * len(flight.uwb)
    assert abs(np.median(d["r"])) < 0.02 and 0.03 < 1.4826 * np.median(np.abs(d["r"])) < 0.1
    assert np.allclose(np.linalg.norm(d["u"], axis=1), 1.0)


def test_repeated_stamps_in_the_trajectory_use_the_last_state(flight):
    """A trajectory with several states at one stamp (a filter's updates at one instant) is read with the
    last state of each stamp: the residuals equal those about the trajectory without the earlier copies."""
    from types import SimpleNamespace

    res = run_eskf(flight, EskfOptions())
    t, X = np.asarray(res.t, float), np.asarray(res.states, float)
    k = np.arange(5, len(t) - 5, 97)  # an earlier, different copy before every 97th state
    early = X[k].copy()
    early[:, :3] += 0.5
    t2 = np.insert(t, k, t[k])
    X2 = np.insert(X, k, early, axis=0)
    dup = SimpleNamespace(t=t2, states=X2, calibration=res.calibration)
    ref = range_residuals(flight, SimpleNamespace(t=t, states=X, calibration=res.calibration))
    got = range_residuals(flight, dup)
    np.testing.assert_array_equal(got["r"], ref["r"])


def test_bad_input_is_refused(flight):
    res = run_eskf(flight, EskfOptions())
    with pytest.raises(InputError):
        select_range_model(flight, res, folds=2)
    with pytest.raises(InputError):
        select_range_model(flight, res, families=["white", "nonsense"])
    with pytest.raises(InputError):
        select_range_model(flight, res, folds=20 * 5)  # blocks of ~30 ranges, fewer than MIN_BLOCK_ROWS
    empty = copy.copy(flight)
    empty.uwb = flight.uwb.iloc[0:0]
    with pytest.raises(InputError):
        select_range_model(empty, res)


def test_calibrate_with_select_cv_records_and_applies_the_choice():
    """``range_model.select: cv`` in ``calibrate``: the choice is an event and calibration.yaml's
    ``range_model.selection`` (made on the batch's own free solve); the graph's Huber threshold stays huber_k's rule
    (a number: kept; adaptive: chosen on the graph's residuals); ``select: given`` selects nothing."""
    from uwbimu.calibration import CalibrationOptions, calibrate

    ds = simulate(builtin_scenario("calibration-flight").updated(duration=30.0, seeds={"noise": 2}))
    opts = CalibrationOptions.model_validate({"td_profile": {"enabled": False}, "range_model": {"select": "cv"}})
    cal = calibrate(ds, opts).calibration
    (ev,) = [e for e in cal["events"] if e["kind"] == "range_model_selected"]
    sel = cal["range_model"]["selection"]
    assert sel["chosen"] == ev["chosen"] and sel["select"] == "cv" and sel["basis"] == "free_solve"
    # the default adaptive threshold is the graph's (the selection's k is in its own innovation-sd units)
    assert cal["range_model"]["huber"]["selection"] == "adaptive"
    fixed = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False}, "huber_k": 2.0,
                                                             "range_model": {"select": "cv"}})).calibration
    assert fixed["range_model"]["selection"]["huber_grid"] == [2.0] and fixed["range_model"]["huber_k"] == 2.0
    given = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False},
                                                             "range_model": {"select": "given"}})).calibration
    assert given["range_model"]["selection"] == {"select": "given"}
    assert not any(e["kind"] == "range_model_selected" for e in given["events"])


# ------------------------------------------------------------------ the stage on the batch's own free solve
def _free_solve(ds, options=None):
    """The batch's first free solve of ``ds`` (graph frame = the simulation's) and its problem."""
    from uwbimu.calibration import graph
    from uwbimu.calibration.profile_walk import solve

    o = options or CalibrationOptions()
    pb = graph.build_problem(ds, run_eskf(ds, EskfOptions()), o)
    imf = graph._imu_factors(pb)
    return pb, imf, solve(pb, imf, graph.initial_values(pb), pb.td0, None)


def test_solve_residuals_are_the_graphs_residuals_without_the_model(flight):
    """About a white-model solve, ``range - |p_U - a|`` equals the graph's own residual (measured - predicted) plus
    the anchor's constant bias: the stage scores the ranges as the graph places the antenna."""
    from uwbimu.calibration import graph, keys
    from uwbimu.calibration.range_model_stage import solve_residuals

    pb, _, sv = _free_solve(flight)
    d = solve_residuals(pb, sv)
    e = graph.range_residuals(sv.graph, sv.assoc, sv.values, sv.time_offset())  # predicted - measured
    bias = np.array([sv.values.atVector(keys.anchor_bias(j))[0] for j in pb.anchor_j[sv.assoc.used]])
    order = np.argsort(pb.t_range[sv.assoc.used], kind="stable")
    np.testing.assert_allclose(d["r"], (-e + bias)[order], atol=1e-9)
    assert np.all(np.diff(d["t"]) >= 0) and len(d["r"]) == len(sv.assoc.used)
    np.testing.assert_allclose(np.linalg.norm(d["u"], axis=1), 1.0)
    # the body-frame line of sight has the world one's length (|a - p_U|)
    np.testing.assert_allclose(np.linalg.norm(d["wb"], axis=1), (pb.rho[sv.assoc.used][order] - d["r"]), rtol=1e-9)
    assert [str(a) for a in d["anchors"]] == sorted({pb.anchor_ids[j] for j in pb.anchor_j[sv.assoc.used]})


def test_warm_values_add_and_drop_the_model_variables(flight):
    """The re-solve under the chosen model starts at the free solve: shared variables copied, the drift knots
    added at zero; going back to the white model drops them."""
    from uwbimu.calibration import graph, keys
    from uwbimu.calibration.range_model_stage import warm_values

    pb, _, sv = _free_solve(flight)
    o2 = CalibrationOptions.model_validate({"range_bias_drift": {"sd": 0.05, "correlation_time": 2.0}})
    pb2 = graph.build_problem(flight, run_eskf(flight, EskfOptions()), o2)
    v2 = warm_values(pb2, sv.values)
    assert set(v2.keys()) == set(graph.initial_values(pb2).keys()) | {keys.time_offset()}
    np.testing.assert_array_equal(v2.atVector(keys.lever_arm(0)), sv.values.atVector(keys.lever_arm(0)))
    assert v2.atVector(keys.bias_drift(0, 0))[0] == 0.0
    back = warm_values(pb, v2)
    assert set(back.keys()) == set(sv.values.keys())


def test_selection_mode_rule(flight):
    """Default ``auto``: select unless a model is configured (kept, ``configured``) or the log is one the
    candidates do not describe (TDoA: ``not_applicable``); ``cv`` refuses such a log; ``given`` never selects."""
    from types import SimpleNamespace

    from uwbimu.calibration import graph
    from uwbimu.calibration.range_model_stage import selection_mode
    from uwbimu.errors import UsageError

    pb = graph.build_problem(flight, run_eskf(flight, EskfOptions()), CalibrationOptions())
    assert CalibrationOptions().range_model.select == "auto"
    assert selection_mode(CalibrationOptions(), flight, pb) == ("select", None)
    for cfg in ({"range_bias_drift": {"sd": 0.05}}, {"range_bias_drift": None},
                {"range_model": {"direction": {"harmonics": 2}}}):
        mode, why = selection_mode(CalibrationOptions.model_validate(cfg), flight, pb)
        assert mode == "configured" and why
    # a configured model with select: cv is replaced (selected)
    cv = CalibrationOptions.model_validate({"range_bias_drift": {"sd": 0.05}, "range_model": {"select": "cv"}})
    assert selection_mode(cv, flight, pb)[0] == "select"
    given = CalibrationOptions.model_validate({"range_model": {"select": "given"}})
    assert selection_mode(given, flight, pb)[0] == "given"
    tdoa = copy.copy(pb)
    tdoa.anchor_b = np.zeros(len(pb.rho), np.int64)
    ds_tdoa = SimpleNamespace(tdoa=flight.uwb.head(3))
    assert selection_mode(CalibrationOptions(), ds_tdoa, tdoa)[0] == "not_applicable"
    with pytest.raises(UsageError):
        selection_mode(CalibrationOptions.model_validate({"range_model": {"select": "cv"}}), ds_tdoa, tdoa)


def test_default_calibrate_chooses_drift_on_coloured_ranges_and_keeps_a_configured_model():
    """The default (``select: auto``) on a log with per-anchor AR(1) range errors (10 cm, 3 s): the stage chooses
    the drift family on the batch's free solve, the graph is solved with a drift model (calibration.yaml
    ``range_model.drift``), the lever arm lands within 3 sigma of the truth; with a model configured it is kept
    (``select: configured``, no selection event)."""
    from uwbimu.calibration import calibrate

    # 30 s (not the module's 60 s flight): two calibrations with a drift graph are the suite's costliest test
    short = simulate(builtin_scenario("calibration-flight").updated(duration=30.0, seeds={"noise": 1}))
    ds = ar1_ranges(short, sigma=0.10, tau=3.0, seed=1001)
    cal = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False}})).calibration
    sel = cal["range_model"]["selection"]
    assert sel["select"] == "cv" and sel["basis"] == "free_solve" and "drift" in sel["chosen"], sel["reason"]
    assert cal["range_model"]["drift"] is not None
    assert cal["range_model"]["drift"]["sd"] == pytest.approx(sel["params"]["drift_sd"])
    err = np.abs(np.subtract(cal["lever_arm"], ds.meta.truth.lever_arm))
    assert np.all(err < 3.0 * np.asarray(cal["lever_arm_sd"])), (cal["lever_arm"], cal["lever_arm_sd"])
    # a configured model is kept as configured (a drift model other than the chosen one: its sd shows it; the
    # white model configured explicitly takes ~2 min on these coloured ranges, ten times this)
    kept = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False},
                                                            "range_bias_drift": {"sd": 0.2, "correlation_time": 5.0}}
                                                           )).calibration
    assert kept["range_model"]["selection"]["select"] == "configured"
    assert kept["range_model"]["drift"]["sd"] == pytest.approx(0.2)
    assert kept["range_model"]["drift"]["sd"] != pytest.approx(sel["params"]["drift_sd"])
    assert not any(e["kind"] == "range_model_selected" for e in kept["events"])
