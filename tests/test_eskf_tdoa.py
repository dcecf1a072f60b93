"""TDoA in the ESKF: Jacobian pinned to the reference model, convergence on a simulated TDoA3 flight."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.estimation import kernels as K
from uwbimu.models import reference as ref
from uwbimu.sim import builtin_scenario, simulate_full

MAX_AGE = 0.005  # s: oldest packet a TDoA3 difference may use (bounds the model mismatch below)


@pytest.fixture(scope="module")
def tdoa3_run():
    sc = builtin_scenario("crazyflie-tdoa3").updated(duration=40.0)
    sc = sc.updated(uwb={"tdoa3_max_age": MAX_AGE})
    ds = simulate_full(sc).dataset
    assert len(ds.uwb) == 0 and ds.tdoa is not None
    return ds, run_eskf(ds, EskfOptions())


def test_tdoa_update_matches_reference_and_finite_differences():
    rng = np.random.default_rng(3)
    x = np.zeros(20)
    x[0:3] = [0.5, -0.3, 1.2]
    x[3:6] = [0.4, 0.1, -0.2]
    q = rng.normal(size=4)
    x[6:10] = q / np.linalg.norm(q)
    x[16:19] = [0.02, -0.01, 0.08]
    u = np.array([0.3, -0.2, 9.7, 0.5, -0.4, 0.9])
    a, b = np.array([3.0, 2.0, 2.5]), np.array([-2.0, 1.0, 0.2])
    h = np.empty(19)
    work = np.empty(19)
    pred = K.tdoa_jacobian(x, u, a, b, -1, 0.0, h, work)
    assert pred == pytest.approx(float(ref.tdoa_measurement(x, a, b)), abs=1e-12)
    # error-state finite differences (position, attitude, lever arm) against the reference model
    eps = 1e-6
    for i in list(range(0, 3)) + list(range(6, 9)) + list(range(15, 18)):
        dx = np.zeros(19)
        dx[i] = eps
        xp = x.copy()
        K.inject(xp, dx)
        xm = x.copy()
        K.inject(xm, -dx)
        fd = (float(ref.tdoa_measurement(xp, a, b)) - float(ref.tdoa_measurement(xm, a, b))) / (2 * eps)
        assert h[i] == pytest.approx(fd, abs=1e-6), i


def test_tdoa_only_flight_converges(tdoa3_run):
    ds, res = tdoa3_run
    truth = ds.meta.truth
    sig = float(ds.meta.extra["tdoa_sigma"])
    gt = ds.groundtruth
    p = np.column_stack([np.interp(res.t, gt["t"], gt[c]) for c in ("px", "py", "pz")])
    late = res.t > res.t[0] + 10.0
    rmse = float(np.sqrt(np.mean(np.sum((res.states[late, :3] - p[late]) ** 2, axis=1))))
    assert rmse < sig  # below one TDoA sd once converged
    cal = res.calibration
    err = np.array(cal["lever_arm"]) - np.array(truth.lever_arm)
    assert np.all(np.abs(err) < 3 * np.array(cal["lever_arm_sd"]))
    # the simulator takes each distance at its own packet's arrival (up to MAX_AGE apart); the filter
    # takes both at the stamp, which shifts t_d by at most MAX_AGE / 2 on top of the noise
    assert abs(cal["time_offset"] - truth.time_offset) < 3 * cal["time_offset_sd"] + MAX_AGE / 2
    assert cal["time_offset_verdict"] == "identified"
    assert np.mean(res.residuals["accepted"].to_numpy(bool)) > 0.9


def test_ranges_and_tdoa_together_with_tdoa_spikes_rejected(tdoa3_run):
    ds_td, _ = tdoa3_run
    sc = builtin_scenario("crazyflie-twr").updated(duration=40.0)  # same truth seed: same flight and calibration
    ds = simulate_full(sc).dataset
    td = ds_td.tdoa.copy()
    spikes = np.arange(2000, len(td), 1000)
    td.loc[td.index[spikes], "tdoa"] += 3.0  # metres: gross outliers
    ds.tdoa = td
    ds.meta.extra["tdoa_sigma"] = ds_td.meta.extra["tdoa_sigma"]
    res = run_eskf(ds, EskfOptions())
    r = res.residuals
    assert set(r["kind"]) == {"range", "tdoa"}
    tdr = r[r["kind"] == "tdoa"]
    bad = np.isin(tdr["t"].to_numpy(), td["t"].to_numpy()[spikes])
    assert bad.sum() == len(spikes) and not tdr["accepted"].to_numpy(bool)[bad].any()
    assert tdr["accepted"].to_numpy(bool)[~bad].mean() > 0.95
    cal = res.calibration
    err = np.array(cal["lever_arm"]) - np.array(ds.meta.truth.lever_arm)
    assert np.all(np.abs(err) < 3 * np.array(cal["lever_arm_sd"]))
    assert abs(cal["time_offset"] - ds.meta.truth.time_offset) < 3 * cal["time_offset_sd"] + MAX_AGE / 2


def test_tdoa_with_anchor_bias_states_recovers_a_bias_difference(tdoa3_run):
    """Anchor "3" ranges 0.2 m long: its TDoA rows carry +0.2 m as anchor_b and -0.2 m as anchor_a; with
    anchor-bias states the filter sees b_b - b_a and recovers the bias relative to the others."""
    ds, _ = tdoa3_run
    td = ds.tdoa.copy()
    td["tdoa"] += 0.2 * (td["anchor_b"].astype(str) == "3") - 0.2 * (td["anchor_a"].astype(str) == "3")
    ds2 = copy.copy(ds)
    ds2.tdoa = td
    opts = EskfOptions.model_validate({"anchor_bias": {"mode": "estimate", "prior_sd": 0.3}})
    res = run_eskf(ds2, opts)
    cal = res.calibration
    ids = [str(a) for a in ds.anchors["anchor"]]
    b = np.array([cal["anchor_bias"][i] for i in ids])
    sd = np.array([cal["anchor_bias_sd"][i] for i in ids])
    i3 = ids.index("3")
    rel = b[i3] - np.mean(np.delete(b, i3))  # only differences are observable from TDoA
    print(f"bias of anchor 3 relative to the others {rel:.4f} m, sd {sd[i3]:.4f} m")
    assert abs(rel - 0.2) < 0.05 and abs(rel - 0.2) < 3 * sd[i3] + 0.02
    err = np.array(cal["lever_arm"]) - np.array(ds.meta.truth.lever_arm)
    assert np.all(np.abs(err) < 3 * np.array(cal["lever_arm_sd"]))


def test_per_pair_tdoa_bias_is_recovered_and_others_stay_near_zero():
    """``tdoa_pair_bias: estimate``: one constant bias state per anchor pair; a 0.25 m bias on one pair is
    recovered within 3 sd while the others stay within 4 sd of zero (56 pairs: no false detections)."""
    import numpy as np

    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("crazyflie-tdoa3").model_copy(update={"duration": 40.0}))
    td = ds.tdoa.copy()
    pa = sorted(set(zip(td.anchor_a.astype(str), td.anchor_b.astype(str))))[0]
    hit = (td.anchor_a.astype(str) == pa[0]) & (td.anchor_b.astype(str) == pa[1])
    td.loc[hit, "tdoa"] += 0.25
    ds.tdoa = td
    cal = run_eskf(ds, EskfOptions(tdoa_pair_bias={"mode": "estimate"}, store_covariance=False)).calibration
    key = f"{pa[0]}-{pa[1]}"
    b, sd = cal["tdoa_pair_bias"][key], cal["tdoa_pair_bias_sd"][key]
    assert abs(b - 0.25) < 3 * sd and sd < 0.02
    others = [abs(v) / cal["tdoa_pair_bias_sd"][k] for k, v in cal["tdoa_pair_bias"].items() if k != key]
    assert len(others) > 10 and max(others) < 4.0
    assert np.isfinite(cal["time_offset"])
