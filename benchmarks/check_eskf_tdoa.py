"""TDoA fusion in the ESKF on simulated Loco TDoA2/TDoA3 flights (40 s, noise seeds 1 and 2).

    PYTHONPATH=src python benchmarks/check_eskf_tdoa.py

Prints, per scenario and seed, the position RMSE after 10 s, the lever-arm error / reported sd and the
time-offset error and sd (see docs/estimator.md, "TDoA in the filter").
"""
import numpy as np
from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.sim import builtin_scenario, simulate_full
for name, upd in [("crazyflie-tdoa3", {"tdoa3_max_age": 0.005}), ("crazyflie-tdoa3", {}), ("crazyflie-tdoa2", {})]:
  for seed in (1, 2):
    sc = builtin_scenario(name).updated(duration=40.0)
    if upd: sc = sc.updated(uwb=upd)
    sc = sc.updated(seeds={"noise": seed})
    ds = simulate_full(sc).dataset
    res = run_eskf(ds, EskfOptions())
    cal = res.calibration; tr = ds.meta.truth
    gt = ds.groundtruth
    p = np.column_stack([np.interp(res.t, gt["t"], gt[c]) for c in ("px", "py", "pz")])
    late = res.t > res.t[0] + 10.0
    rmse = float(np.sqrt(np.mean(np.sum((res.states[late, :3] - p[late]) ** 2, axis=1))))
    el = (np.array(cal["lever_arm"]) - np.array(tr.lever_arm)) / np.array(cal["lever_arm_sd"])
    et = (cal["time_offset"] - tr.time_offset)
    print(name, upd, seed, f"rmse {rmse*100:.1f} cm lever err/sd {np.round(el,2)} td err {et*1e3:.2f} ms sd {cal['time_offset_sd']*1e3:.2f} ms", cal["time_offset_verdict"], f"acc {np.mean(res.residuals['accepted']):.3f}")
