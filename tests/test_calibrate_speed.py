"""Speed paths of the batch calibrator (issue 12 item 8) against their references.

* :func:`uwbimu.calibration.graph.optimize` (LM driven from Python) takes the same steps as GTSAM's
  ``LevenbergMarquardtOptimizer``;
* the fast t_d profile (secant warm starts, expected-decrease stop) against the reference full-solve
  profile (GTSAM's optimizer, its convergence rule): same grid, chi2 within a stated tolerance, same
  argmin and verdict;
* the profile on the Monte Carlo executors (``workers=2``) gives the values of the in-process run.
"""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("gtsam")

from uwbimu.calibration import CalibrationOptions, calibrate  # noqa: E402
from uwbimu.calibration import anchors as AN  # noqa: E402
from uwbimu.calibration import batch as BT  # noqa: E402
from uwbimu.calibration import graph as G  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402

#: Tolerance of the fast profile against the reference [chi-square units]: the stop rule's target
#: (:data:`uwbimu.calibration.batch.PROFILE_CHI2_TOL`) with a factor 2.5 of margin for the estimate of the
#: remaining decrease; the verdict's threshold is 9.
CHI2_TOL = 2.5 * BT.PROFILE_CHI2_TOL


def _flight(seed: int, duration: float):
    sc = builtin_scenario("calibration-flight")
    return simulate(sc.model_copy(update={"duration": duration, "seeds": sc.seeds.model_copy(update={"noise": seed})}))


@pytest.fixture(scope="module")
def problem():
    """A 10 s simulated flight: problem, IMU factors and the free solution (t_d estimated)."""
    from uwbimu.estimation import EskfOptions, run_eskf

    ds = _flight(4, 10.0)
    o = CalibrationOptions.model_validate({"td_profile": {"half_width": 0.3}})
    pb = G.build_problem(ds, run_eskf(ds, EskfOptions()), o, AN.plan_anchors(ds, o))
    imf = G._imu_factors(pb)
    graph, values, _assoc, _it = BT._solve(pb, imf, G.initial_values(pb), pb.td0, None)
    X, V, B, L, T, A = G._keys()
    return ds, pb, imf, values, float(values.atVector(T(0))[0])


@pytest.mark.parametrize("td_fixed", [None, 0.05])
def test_python_lm_takes_gtsams_steps(problem, td_fixed):
    _ds, pb, imf, _values, _td = problem
    assoc = G.associate(pb, pb.td0)
    graph = G.build_graph(pb, assoc, td_fixed=td_fixed, imu_factors=imf)
    start = G.initial_values(pb, with_td=td_fixed is None)
    ref, it_ref = G.optimize(graph, start, 50, engine="gtsam")
    got, it = G.optimize(graph, start, 50)
    assert it == it_ref > 1
    assert graph.error(got) == pytest.approx(graph.error(ref), rel=1e-12)
    assert np.abs(ref.localCoordinates(got).vector()).max() < 1e-9


def test_expected_decrease_stop_saves_iterations_within_its_tolerance(problem):
    _ds, pb, imf, values, _td = problem
    g = 0.1
    graph = G.build_graph(pb, G.associate(pb, g), td_fixed=g, imu_factors=imf)
    start = G.without_td(values)
    full, it_full = G.optimize(graph, start, 50)
    fast, it_fast = G.optimize(graph, start, 50, predicted_tol=0.01)
    assert it_fast < it_full
    assert 0.0 <= graph.error(fast) - graph.error(full) < 0.01


def test_fast_profile_matches_the_full_solve_reference(problem):
    _ds, pb, imf, values, td = problem
    ref = BT.run_profile(pb, imf, values, td, mode="reference")
    fast = BT.run_profile(pb, imf, values, td, mode="fast")
    np.testing.assert_array_equal(fast.grid, ref.grid)
    assert len(ref.grid) == 15  # coarse 0.1 s over +/-0.3 s, then 0.02 s about the coarse minimum
    assert np.abs(fast.chi2 - ref.chi2).max() < CHI2_TOL
    assert int(np.argmin(fast.chi2)) == int(np.argmin(ref.chi2))
    assert fast.verdict == ref.verdict == "identified"
    assert fast.vertex == pytest.approx(ref.vertex, abs=0.02 * ref.sigma_curvature)
    assert fast.sigma_curvature == pytest.approx(ref.sigma_curvature, rel=0.01)
    assert fast.iterations.sum() < 0.7 * ref.iterations.sum()


def test_profile_on_the_process_pool_equals_the_in_process_profile():
    ds = _flight(5, 6.0)
    o = CalibrationOptions.model_validate({"td_profile": {"half_width": 0.2}, "max_iterations": 10})
    here = calibrate(ds, o)
    pool = calibrate(ds, o, eskf=here.eskf, workers=2)
    np.testing.assert_array_equal(pool.profile.grid, here.profile.grid)
    np.testing.assert_array_equal(pool.profile.chi2, here.profile.chi2)
    np.testing.assert_array_equal(pool.profile.iterations, here.profile.iterations)
    assert pool.calibration["lever_arm"] == here.calibration["lever_arm"]
    assert pool.calibration["time_offset"] == here.calibration["time_offset"]


def test_profile_sharper_than_its_step_is_zoomed(problem):
    """A 0.15 s step against a sigma of ~0.03 s: the confidence set is one grid point until the zoom adds
    points at 0.03 s about the vertex; the result then agrees with the 0.02 s profile."""
    ds, pb, imf, values, td = problem
    coarse = pb.options.model_copy(update={"td_profile": pb.options.td_profile.model_copy(
        update={"step": 0.15, "coarse_step": None})})
    p = BT.run_profile(G.Problem(**{**pb.__dict__, "options": coarse}), imf, values, td)
    fine = BT.run_profile(pb, imf, values, td)
    zoom = p.grid[~np.isin(np.round(p.grid, 12), np.round(np.arange(-0.3, 0.3001, 0.15), 12))]
    assert len(zoom) >= 3 and np.allclose(np.round(zoom / 0.03), zoom / 0.03)  # on the 0.03 s zoom grid
    assert np.abs(zoom - p.vertex).max() <= 2.5 * 0.03  # about the vertex
    assert p.verdict == fine.verdict == "identified"
    assert np.sum(p.chi2 - p.chi2.min() < 9.0) >= 2
    assert p.vertex == pytest.approx(fine.vertex, abs=0.2 * fine.sigma_curvature)
    assert abs(p.vertex - ds.meta.truth.time_offset) < 3 * p.sigma_curvature


#: Group variants of the kernel check: (tag-side direction model, per-anchor coefficient columns, estimated anchors).
KERNEL_VARIANTS = {
    "range": (None, False, False),
    "direction-elevation-per-anchor": (((1, 2), True), True, False),
    "direction-one-column": (((2, 3), False), False, False),
    "direction-elevation-powers": (((1, 3), (1, 2)), True, False),
    "direction-per-anchor-estimated-anchors": (((1, 2), True), True, True),
    "estimated-anchors": (None, False, True),
}


@pytest.mark.parametrize("variant", list(KERNEL_VARIANTS))
@pytest.mark.parametrize("td", [0.02, 0.047, -0.013])
def test_numba_group_kernel_equals_the_numpy_group(monkeypatch, td, variant):
    """The compiled row loop (range_kernel.group_rows) against RangeGroup's NumPy implementation: residuals and
    every Jacobian on rows of three keyframes, at the association's t_d (delta = 0) and away from it; without
    and with the tag-side direction model (elevation feature or not, per-anchor or one coefficient column) and
    with estimated anchors (two of the four anchors estimated)."""
    from uwbimu.calibration import range_factor as RF

    direction, per_anchor, survey = KERNEL_VARIANTS[variant]
    rng = np.random.default_rng(21)
    t = np.arange(61) / 200.0
    u = np.empty((61, 6))
    u[:, :3] = [0.3, -0.2, 9.81] + 1.5 * np.sin(2 * np.pi * np.outer(t, [1.1, 0.7, 1.3]) + rng.uniform(0, 6, 3))
    u[:, 3:] = 0.8 * np.sin(2 * np.pi * np.outer(t, [0.9, 1.2, 0.5]) + rng.uniform(0, 6, 3))
    kk, deltas = RF.imu_deltas(t, u, np.array([0.05, -0.03, 0.02]), np.array([0.01, -0.02, 0.005]),
                               np.array([0.0, 0.1, 0.2]), np.sort(rng.uniform(0.0, 0.29, 40)))
    anchors = rng.uniform(-5, 5, (4, 3))
    col = np.arange(40) % 4
    kw, call = {}, {}
    if direction is not None:
        kw = {"direction": direction, "dir_col": col if per_anchor else np.zeros(40, np.int64)}
        n_dir = 4 if per_anchor else 1
        n_el = len(direction[1]) if isinstance(direction[1], tuple) else int(direction[1])
        call["dir_coefs"] = rng.normal(0, 0.05, (n_dir, 2 * len(direction[0]) + n_el))
    if survey:
        kw["anchor_var"] = np.array([0, -1, 1, -1])[col]
        call["anchor_pos"] = anchors[[0, 2]] + rng.normal(0, 0.3, (2, 3))
    grp = RF.RangeGroup(deltas, anchors[col], rng.normal(4.0, 1.0, 40), col, 0.02, kf=kk, **kw)
    state = (np.array([RF.so3_exp(rng.normal(size=3)) for _ in range(3)]), rng.normal(size=(3, 3)),
             rng.normal(size=(3, 3)), np.array([0.12, -0.08, 0.14]), td, rng.normal(0, 0.05, 4))
    calls = []
    kernel = RF.RangeGroup._evaluate_kernel
    monkeypatch.setattr(RF.RangeGroup, "_evaluate_kernel", lambda *a, **k: calls.append(1) or kernel(*a, **k))
    fast = grp.evaluate(*state, jacobians=True, **call)
    e_fast = grp.evaluate(*state, **call)
    assert calls == [1, 1]  # this group takes the compiled path
    monkeypatch.setattr(RF, "USE_KERNEL", False)
    ref = grp.evaluate(*state, jacobians=True, **call)
    assert calls == [1, 1]
    assert len(fast) == len(ref) == 5 + (direction is not None) + survey
    np.testing.assert_allclose(e_fast, ref[0], rtol=0, atol=1e-12)
    for a, b in zip(fast, ref):
        assert a.shape == b.shape
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_group_with_an_unknown_attribute_takes_the_numpy_path(monkeypatch):
    """A model term the kernel does not know (any new RangeGroup attribute) must not be skipped silently."""
    from uwbimu.calibration import range_factor as RF

    assert "some_future_term" not in RF._KERNEL_ATTRS
    t = np.arange(41) / 200.0
    u = np.tile([0.0, 0.0, 9.81, 0.1, 0.0, 0.2], (41, 1))
    _k, deltas = RF.imu_deltas(t, u, np.zeros(3), np.zeros(3), np.array([0.0]), np.array([0.05, 0.1]))
    grp = RF.RangeGroup(deltas, np.array([[3.0, 0, 1], [0, 3.0, 1]]), np.array([3.0, 3.0]), np.array([0, 1]), 0.0)
    calls = []
    monkeypatch.setattr(RF.RangeGroup, "_evaluate_kernel", lambda *a, **k: calls.append(1))
    grp.evaluate(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), 0.0, np.zeros(2))
    assert calls == [1]
    grp.some_future_term = 1.0  # what a later model term would add
    calls.clear()
    grp.evaluate(np.eye(3), np.zeros(3), np.zeros(3), np.zeros(3), 0.0, np.zeros(2))
    assert calls == []


def test_cli_workers_option(tmp_path):
    """``uwbimu calibrate --workers 2``: the profile on the process pool, the same td_profile.csv as in-process;
    ``--workers 0`` is a usage error."""
    import yaml
    from typer.testing import CliRunner

    from uwbimu.cli.main import app
    from uwbimu.io.dataset import write_dataset

    ds_dir = write_dataset(_flight(6, 6.0), tmp_path / "ds")
    cfg = tmp_path / "c.yaml"
    cfg.write_text(yaml.safe_dump({"td_profile": {"half_width": 0.2}, "max_iterations": 10}))
    outs = []
    for w in ("1", "2"):
        out = tmp_path / f"out{w}"
        r = CliRunner().invoke(app, ["calibrate", str(ds_dir), "--out", str(out), "--config", str(cfg), "--no-plots",
                                     "--workers", w])
        assert r.exit_code == 0, r.output
        outs.append((out / "td_profile.csv").read_text())
    assert outs[0] == outs[1]
    r = CliRunner().invoke(app, ["calibrate", str(ds_dir), "--out", str(tmp_path / "o0"), "--workers", "0"])
    assert r.exit_code == 2
