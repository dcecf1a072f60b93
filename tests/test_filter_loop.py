"""The compiled filter pass (``kernels.filter_loop`` behind ``filterpass.advance``) against the Python loop
it replaced (``filterpass.advance_python``), and the SIMD covariance step against the column-wise one.

Tolerance: none.  The compiled loop calls the same kernels in the same order with the same arguments as
the Python loop, and ``_cov_step_rows`` performs the same floating-point operations, element for element
and in the same order, as ``_cov_step`` (no fused multiply-add: numba compiles without fast-math), so
every result must be bit-identical; a difference is a bookkeeping bug that a tolerance would hide.  Each
case also checks that the path it is meant to exercise was taken (IMU gaps, rotation gate, divergence,
reopened gates, Python-model rows, TDoA pair biases, several tags), so that it cannot pass vacuously.
"""

from __future__ import annotations

import ast
import functools
import inspect

import numpy as np
import pytest

from uwbimu.estimation import Eskf, EskfOptions, run_eskf
from uwbimu.estimation import filterpass as FP
from uwbimu.estimation import kernels as K
from uwbimu.estimation import streaming
from uwbimu.estimation.eskf import build_problem
from uwbimu.estimation.init import initialise
from uwbimu.models import kernels as MK
from uwbimu.models.state import StateLayout
from uwbimu.sim import builtin_scenario, simulate


def _sim(name: str, duration: float, **update):
    sc = builtin_scenario(name)
    return simulate(sc.model_copy(update={"duration": duration, **update}))


def _run_both(monkeypatch, fn):
    """``fn()`` with the compiled pass, then with the Python loop (``streaming.advance`` patched)."""
    compiled = fn()
    with monkeypatch.context() as mp:
        mp.setattr(streaming, "advance", functools.partial(FP.advance, engine="python"))
        python = fn()
    return compiled, python


def _assert_same_result(a, b):
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(a.t_imu, b.t_imu)
    np.testing.assert_array_equal(a.states, b.states)
    np.testing.assert_array_equal(a.sd, b.sd)
    if a.covariances is not None or b.covariances is not None:
        np.testing.assert_array_equal(a.covariances, b.covariances)
    for col in a.residuals.columns:
        va, vb = a.residuals[col].to_numpy(), b.residuals[col].to_numpy()
        if va.dtype.kind == "f":
            np.testing.assert_array_equal(va, vb)
        else:
            assert va.tolist() == vb.tolist(), col
    assert a.calibration == b.calibration
    assert a.events == b.events
    assert a.warnings == b.warnings


def _with_imu_gaps(ds, spans):
    imu = ds.imu
    t = imu["t"].to_numpy()
    keep = np.ones(len(t), dtype=bool)
    for t0, t1 in spans:
        keep &= ~((t > t0) & (t < t1))
    ds.imu = imu[keep].reset_index(drop=True)
    return ds


@pytest.mark.parametrize("cov_every", [1, 5])
def test_compiled_pass_equals_python_loop_with_imu_gaps_and_covariances(monkeypatch, cov_every):
    ds = _with_imu_gaps(_sim("calibration-flight", 30.0), [(12.0, 12.05), (20.0, 20.3)])
    opts = EskfOptions(cov_every=cov_every, store_covariance=True)
    a, b = _run_both(monkeypatch, lambda: run_eskf(ds, opts))
    _assert_same_result(a, b)
    assert sum(e["kind"] == "imu_gap" for e in a.events) == 2
    assert a.covariances is not None and len(a.t) > 500


def test_compiled_pass_equals_python_loop_with_rotation_gate(monkeypatch):
    ds = _sim("translation", 25.0)
    # the gate of the estimating pass is under test: no second pass holding the lever arm
    opts = EskfOptions(store_covariance=False, hold_unidentified=False)
    a, b = _run_both(monkeypatch, lambda: run_eskf(ds, opts))
    _assert_same_result(a, b)
    assert any(e["kind"] == "lever_arm_not_updated" for e in a.events)


def _corrupted(ds, t0, t1, offset, anchor=None):
    u = ds.uwb
    sel = (u["t"] > t0) & (u["t"] < t1)
    if anchor is not None:
        sel &= u["anchor"].astype(str) == anchor
    u.loc[sel, "range"] = u.loc[sel, "range"] + offset
    return ds


def test_compiled_pass_equals_python_loop_through_reopened_gates_and_divergence(monkeypatch):
    ds = _sim("calibration-flight", 40.0)
    first = str(ds.uwb["anchor"].astype(str).iloc[0])
    _corrupted(ds, 8.0, 14.0, 1.5, anchor=first)  # one anchor off: its gate reopens
    _corrupted(ds, 22.0, 28.0, 4.0)  # every anchor off: gates reopen, then the supervisor steps in
    # gates reopen before the run of rejections counts as divergence (reopened gates count towards it)
    opts = EskfOptions(store_covariance=False, gating={"reopen_after": 5}, supervisor={"all_reject_run": 60})
    a, b = _run_both(monkeypatch, lambda: run_eskf(ds, opts))
    _assert_same_result(a, b)
    kinds = [e["kind"] for e in a.events]
    assert kinds.count("gate_reopened") >= 10
    div = [e for e in a.events if e["kind"] == "divergence"]
    assert div and "consecutive ranges rejected" in div[0]["reason"] and "reinitialised" in kinds
    # the event buffer of the compiled loop drained at every slot
    monkeypatch.setattr(FP, "_EVENT_SLOTS", 1)
    c = run_eskf(ds, opts)
    _assert_same_result(a, c)


def test_compiled_pass_equals_python_loop_when_the_supervisor_stops_a_drift(monkeypatch):
    """A UWB outage: the position sd grows between outputs until the supervisor's check at an output
    declares divergence; the filter re-initialises from the ranges after the outage."""
    ds = _sim("calibration-flight", 45.0)
    t = ds.uwb["t"].to_numpy()
    ds.uwb = ds.uwb[(t < 22.0) | (t > 34.0)].reset_index(drop=True)  # position sd about 2 m at its end
    opts = EskfOptions(store_covariance=False, supervisor={"max_position_sd": 1.0})
    a, b = _run_both(monkeypatch, lambda: run_eskf(ds, opts))
    _assert_same_result(a, b)
    div = [e for e in a.events if e["kind"] == "divergence" and 22.0 < e["t"] < 34.0]
    assert div and "position sd" in div[0]["reason"]


def test_compiled_pass_equals_python_loop_on_late_and_stale_measurements(monkeypatch):
    """Measurements that arrive after the IMU moved on: within max_lookback_s they are processed at their
    own time, beyond it they are marked stale."""
    ds = _sim("calibration-flight", 20.0)
    opts = EskfOptions()
    prob, info = build_problem(ds, opts)
    ub = np.full(len(prob.uwb_t), -1)

    def feed():
        f = Eskf.from_problem(prob, info["priors"], opts, record=True)
        held = []
        for i0 in range(0, len(prob.imu_t), 50):
            i1 = min(i0 + 50, len(prob.imu_t))
            j0, j1 = np.searchsorted(prob.uwb_t, [prob.imu_t[i0], prob.imu_t[i1 - 1]])
            rows = [j for j in range(j0, j1) if j % 13]
            held += [j for j in range(j0, j1) if j % 13 == 0]
            f.feed(prob.imu_t[i0:i1], prob.imu_u[i0:i1], prob.uwb_t[rows], prob.uwb_a[rows], ub[rows],
                   prob.uwb_r[rows])
            if i0 % 200 == 0 and held:  # every 13th range arrives 0.25 s (or 1 s) late
                f.feed(np.zeros(0), np.zeros((0, 6)), prob.uwb_t[held], prob.uwb_a[held], ub[held],
                       prob.uwb_r[held])
                held = []
        f.finish()
        return f

    fa, fb = _run_both(monkeypatch, feed)
    np.testing.assert_array_equal(fa.records(), fb.records())
    for p, q in zip(fa.passes(), fb.passes(), strict=True):
        np.testing.assert_array_equal(p.states, q.states)
        np.testing.assert_array_equal(p.cov_diag, q.cov_diag)
    status = fa.records()[:, FP.REC_STATUS]
    assert (status == FP.STATUS_STALE).sum() > 5 and (status == K.UPD_OK).sum() > 800


def test_compiled_pass_equals_python_loop_on_tdoa_with_pair_biases(monkeypatch):
    ds = _sim("crazyflie-tdoa3", 20.0)
    opts = EskfOptions(tdoa_pair_bias={"mode": "estimate"}, store_covariance=False)
    a, b = _run_both(monkeypatch, lambda: run_eskf(ds, opts))
    _assert_same_result(a, b)
    assert "tdoa_pair_bias" in a.calibration and (a.residuals["kind"] == "tdoa").all()


def test_compiled_pass_equals_python_loop_with_two_tags(monkeypatch):
    ds = _sim("two-tags", 25.0)
    a, b = _run_both(monkeypatch, lambda: run_eskf(ds, EskfOptions(store_covariance=False)))
    _assert_same_result(a, b)
    assert len(a.calibration["tags"]) == 2


def test_compiled_pass_equals_python_loop_with_python_model_rows(monkeypatch):
    """Height and zero-velocity pseudo-measurements go through the Python model protocol: the compiled
    loop hands each such row to the Python loop and resumes."""
    ds = _sim("calibration-flight", 25.0)
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    tu = ds.uwb["t"].to_numpy(float)
    au = ds.uwb["anchor"].astype(str).to_numpy()
    ru = ds.uwb["range"].to_numpy(float)
    td = ds.meta.truth.time_offset or 0.0
    gt = ds.groundtruth

    def feed():
        f = Eskf.for_dataset(ds, EskfOptions(height={"bias": "estimate"}), record=True)
        j = 0
        for n, i0 in enumerate(range(0, len(imu), 40)):
            blk = imu[i0:i0 + 40]
            j1 = int(np.searchsorted(tu + td, blk[-1, 0], side="right"))
            if j1 > j:
                f.push_ranges(tu[j:j1], au[j:j1], ru[j:j1])
                j = j1
            f.push_imu_chunk(blk[:, 0], blk[:, 1:4], blk[:, 4:7])
            if n % 3 == 0:
                f.push_height(blk[-1, 0], float(np.interp(blk[-1, 0], gt["t"], gt["pz"])) + 0.3)
            if n % 7 == 0:
                f.push_zero_velocity(blk[-1, 0], sigma=5.0)
        f.finish()
        return f

    fa, fb = _run_both(monkeypatch, feed)
    pa, pb = fa.passes(), fb.passes()
    assert len(pa) == len(pb) >= 1
    for p, q in zip(pa, pb):
        np.testing.assert_array_equal(p.t_imu, q.t_imu)
        np.testing.assert_array_equal(p.states, q.states)
        np.testing.assert_array_equal(p.cov_diag, q.cov_diag)
        np.testing.assert_array_equal(p.rec, q.rec)
    np.testing.assert_array_equal(fa.records(), fb.records())
    assert fa.events() == fb.events()
    models = fa.problem().uwb_b <= -2
    assert models.sum() > 50 and np.all(fa.records()[models, FP.REC_STATUS] == K.UPD_OK)


def test_run_pass_engines_agree_and_progress_reaches_the_end():
    ds = _sim("calibration-flight", 20.0)
    opts = EskfOptions(store_covariance=True)
    prob, info = build_problem(ds, opts)
    st = initialise(prob, opts, info["priors"])
    seen = []
    a = FP.run_pass(prob, st.x, st.P, st.k, st.j, progress=seen.append)
    b = FP.run_pass(prob, st.x, st.P, st.k, st.j, engine="python")
    for name in ("t_imu", "states", "cov_diag", "covs", "rec", "x", "P"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.k, a.j_end, a.n_lever_frozen, a.diverged) == (b.k, b.j_end, b.n_lever_frozen, b.diverged)
    # about once per second of data, then at the end
    assert len(seen) >= 15 and seen == sorted(seen) and seen[-1] == a.k >= len(prob.imu_t) - 5
    with pytest.raises(ValueError, match="engine"):
        FP.run_pass(prob, st.x, st.P, st.k, st.j, engine="fortran")


@pytest.mark.parametrize("n_extra, gauss_markov", [(0, False), (4, True), (9, False)])
def test_cov_step_rows_is_bit_identical_to_cov_step(n_extra, gauss_markov):
    rng = np.random.default_rng(n_extra)
    N = 19 + n_extra
    noise = np.array([4e-4, 3e-5, 1e-6, 1e-8, 1e-9, 1e-10])
    # the declared blocks' tables: the extras are anchor biases (Gauss-Markov or constant)
    pn = StateLayout(n_extra).process_noise(noise[:4], {"lever": (noise[4], 0.0), "t_d": (noise[5], 0.0),
                                                        "anchor_bias": (0.01, 0.5 if gauss_markov else 0.0)})
    B, W = np.empty((7, 3, 3)), np.empty((6, 3, 3))
    A, T, U = np.empty((15, N)), np.empty((15, N)), np.empty((15, N))
    for dt in (1e-3, -2e-3, 0.0, 0.3):
        x = rng.normal(size=N + 1)
        x[6:10] /= np.linalg.norm(x[6:10])
        u = rng.normal(size=6) * 5.0
        A = rng.normal(size=(N, N))
        P0 = A @ A.T
        P0[3, 7] += 1e-3  # not symmetric: the two steps must agree on any matrix
        P1, P2 = P0.copy(), P0.copy()
        MK.cov_step_blocks(P1, x, u, dt, pn)
        MK._cov_step_rows(P2, x, u, dt, pn, B, W, A, T, U)
        assert np.array_equal(P1, P2) and np.array_equal(np.signbit(P1), np.signbit(P2))


def test_cross_module_numba_calls_are_covered_by_the_cache_refresh():
    """CONTRIBUTING's cache rule: a cached kernel of ``estimation/kernels.py`` that calls numba functions of
    another module keeps stale machine code unless the module's ``refresh_stale_cache`` lists it."""
    src = inspect.getsource(K)
    tree = ast.parse(src)
    calls = [n for n in ast.walk(tree)
             if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "refresh_stale_cache"]
    assert len(calls) == 1 and tree.body[-1].value is calls[0]  # the module's last statement
    listed = {getattr(K, e.id) for e in calls[0].args[1].elts}
    from numba.core.registry import CPUDispatcher

    foreign = set()
    for name, obj in vars(K).items():
        if isinstance(obj, CPUDispatcher) and obj.__module__ == K.__name__:
            for ref in obj.py_func.__code__.co_names:
                target = getattr(K, ref, None)
                if isinstance(target, CPUDispatcher) and target.__module__ != K.__name__:
                    foreign.add(inspect.getmodule(target.py_func))
    assert MK in foreign  # the filter loop calls the shared physics
    assert foreign <= listed
