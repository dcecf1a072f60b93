"""Fault injection (issue 14, item 7): bounded errors and the expected warnings/events.

One short simulated calibration flight (30 s) is corrupted in memory per case and run
through the ESKF (and, for a backward clock jump in a file, the loader's clock-jump handling;
the clock-fault detector has its own tests, tests/test_clock_faults.py).  Bounds are
relative to the clean run of the same flight where a scale exists.
"""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, compute_metrics, run_eskf
from uwbimu.sim import builtin_scenario, simulate

DURATION = 30.0


@pytest.fixture(scope="module")
def flight():
    ds = simulate(builtin_scenario("calibration-flight").updated(duration=DURATION))
    res = run_eskf(ds, EskfOptions())
    return ds, res, compute_metrics(res, ds)


def _with(ds, **tables):
    out = copy.copy(ds)
    for k, v in tables.items():
        setattr(out, k, v.reset_index(drop=True))
    return out


def _lever_err(res, ds) -> float:
    return float(np.linalg.norm(np.asarray(res.calibration["lever_arm"]) - np.asarray(ds.meta.truth.lever_arm)))


def _kinds(res) -> set[str]:
    return {e.get("kind") for e in res.events}


def test_clean_run_is_the_reference(flight):
    ds, res, m = flight
    assert m["position_rmse_after"] < 0.15 and _lever_err(res, ds) < 0.05


def test_nlos_burst_is_gated(flight):
    ds, _, m0 = flight
    u = ds.uwb.copy()
    burst = (u["anchor"] == u["anchor"].iloc[0]) & (u["t"] > 12) & (u["t"] < 16)
    u.loc[burst, "range"] += 1.5
    res = run_eskf(_with(ds, uwb=u), EskfOptions())
    m = compute_metrics(res, ds)
    r = res.residuals
    in_burst = (r["anchor"] == u["anchor"].iloc[0]).to_numpy() & (r["t"] > 12.5).to_numpy() & (r["t"] < 16).to_numpy()
    assert (~r["accepted"].to_numpy(bool)[in_burst]).mean() > 0.5  # the burst is rejected
    assert m["position_rmse_after"] < 2 * m0["position_rmse_after"] + 0.05


def _anchor_outage(ds):
    u = ds.uwb
    return {"uwb": u[~((u["anchor"] == u["anchor"].iloc[0]) & (u["t"] > 10) & (u["t"] < 20))]}


def _total_outage(ds):
    return {"uwb": ds.uwb[~((ds.uwb["t"] > 14) & (ds.uwb["t"] < 17))]}


def _imu_gap(ds):
    return {"imu": ds.imu[~((ds.imu["t"] > 15) & (ds.imu["t"] < 15.3))]}


@pytest.mark.parametrize("fault, event, factor, slack", [
    (_anchor_outage, None, 2.0, 0.05),
    (_total_outage, "uwb_outage", 3.0, 0.1),
    (_imu_gap, "imu_gap", 3.0, 0.1),
])
def test_outages_are_reported_and_bounded(flight, fault, event, factor, slack):
    ds, _, m0 = flight
    res = run_eskf(_with(ds, **fault(ds)), EskfOptions())
    if event is not None:
        assert event in _kinds(res)
    assert compute_metrics(res, ds)["position_rmse_after"] < factor * m0["position_rmse_after"] + slack


def test_range_spikes_are_rejected(flight):
    ds, _, m0 = flight
    u = ds.uwb.copy()
    idx = np.random.default_rng(1).choice(len(u), size=len(u) // 100, replace=False)
    idx = idx[u["t"].to_numpy()[idx] > 5]
    u.loc[idx, "range"] += 100.0
    res = run_eskf(_with(ds, uwb=u), EskfOptions())
    assert not res.residuals.loc[res.residuals["range"] > 50, "accepted"].any()
    m = compute_metrics(res, ds)
    assert m["position_rmse_after"] < 1.5 * m0["position_rmse_after"] + 0.03


def test_range_spike_during_initialisation_does_not_consume_the_supervisor(flight):
    ds, _, m0 = flight
    u = ds.uwb.copy()
    first = np.flatnonzero(u["t"].to_numpy() < 1.0)[:3]
    u.loc[first, "range"] += 100.0
    res = run_eskf(_with(ds, uwb=u), EskfOptions())
    n_reinit = sum(e.get("kind") == "reinitialised" for e in res.events)
    m = compute_metrics(res, ds)
    assert n_reinit < EskfOptions().supervisor.max_reinit
    assert m["position_rmse_after"] < 2 * m0["position_rmse_after"] + 0.05


# Clock jumps (both ways, +0.3 / -0.3 / -0.2 / +0.12 s) and the clean-log / dropout checks of the
# clock-fault detector live in tests/test_clock_faults.py (a 60 s flight: the windowed t_d test
# needs a few windows on each side of the jump), drift in tests/test_clock_drift.py.


def test_backward_clock_jump_in_a_file_is_a_jump_not_a_sort(flight, tmp_path):
    from uwbimu.io.dataset import write_dataset
    from uwbimu.io.loader import DatasetError, load_dataset

    ds, res0, _ = flight
    u = ds.uwb.copy()
    u["t"] = np.where(u["t"] >= 20.0, u["t"] - 0.3, u["t"])
    folder = write_dataset(_with(ds, uwb=u), tmp_path / "ds")
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert "--split-clock-jumps" in exc.value.hint and "--sort" not in exc.value.hint
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        split = load_dataset(folder, clock_jumps="split")
    jump = [w for w in split.report.warnings if w["code"] == "clock_jump"]
    assert len(jump) == 1 and abs(jump[0]["size"] + 0.3) < 0.05
    res = run_eskf(split, EskfOptions())
    assert _lever_err(res, ds) < _lever_err(res0, ds) + 0.05


def test_large_time_offset(flight):
    ds = simulate(builtin_scenario("calibration-flight").updated(duration=DURATION, time_offset=0.2))
    res = run_eskf(ds, EskfOptions())
    assert abs(res.calibration["time_offset"] - 0.2) < max(0.02, 4 * res.calibration["time_offset_sd"])


def test_wrong_initial_yaw(flight):
    ds, _, m0 = flight
    q0 = ds.groundtruth[["qw", "qz"]].to_numpy()[0]
    yaw_true = 2 * np.arctan2(q0[1], q0[0])
    opts = EskfOptions()
    opts = opts.model_copy(update={"init": opts.init.model_copy(update={"yaw": float(yaw_true + np.radians(90))})})
    res = run_eskf(ds, opts)
    m = compute_metrics(res, ds)
    recovered = m["position_rmse_after"] < 2 * m0["position_rmse_after"] + 0.1
    flagged = {"divergence", "reinitialised"} & _kinds(res)
    assert recovered or flagged
