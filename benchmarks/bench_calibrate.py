"""Batch calibrator figures: range-factor cost, INRoL clock-shift recovery, full-log accuracy.

    python benchmarks/bench_calibrate.py cost
    python benchmarks/bench_calibrate.py shift DATASET [--window 40] [--shifts 0,0.05,-0.05,0.1,-0.1]
    python benchmarks/bench_calibrate.py full DATASET      # ATE of batch vs ESKF (slow: ~10 min)

DATASET: an imported INRoL folder (``uwbimu import inrol ../shared/datasets/inrol_uwb_imu DIR``).
State the machine load (``uptime``) next to any figure.  Nothing is hard-coded: every number is
measured in the run (docs/calibrate.md holds the tables).
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / "examples" / "estimator_real.yaml"


def cost() -> None:
    from uwbimu.calibration import CalibrationOptions
    from uwbimu.calibration import graph as G
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 12.0}))
    pb = G.build_problem(ds, run_eskf(ds, EskfOptions()), CalibrationOptions())
    imf = G._imu_factors(pb)
    assoc = G.associate(pb, pb.td0)
    graph, values = G.build_graph(pb, assoc, imu_factors=imf), G.initial_values(pb)
    first = graph.size() - len(assoc.used)
    ranges = [graph.at(first + i) for i in range(len(assoc.used))]
    for name, fs in (("range factor (CustomFactor)", ranges), ("CombinedImuFactor", imf)):
        t = time.perf_counter()
        for _ in range(5):
            for f in fs:
                f.linearize(values)
        print(f"{name}: {1e6 * (time.perf_counter() - t) / 5 / len(fs):.1f} us per linearize ({len(fs)} factors)")


def _window(ds, end: float, shift: float):
    imu = ds.imu[ds.imu.t < end].reset_index(drop=True)
    uwb = ds.uwb[ds.uwb.t < end - 0.2].copy()
    uwb["t"] = uwb["t"] + shift
    return dataclasses.replace(ds, imu=imu, uwb=uwb.reset_index(drop=True))


def shift(path: str, window: float, shifts: list[float]) -> None:
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.estimation import EskfOptions
    from uwbimu.io.loader import load_dataset

    ds, eo = load_dataset(path), EskfOptions.from_yaml(REAL)
    opts = CalibrationOptions.model_validate({"td_profile": {"enabled": False}})
    base = None
    for s in shifts:
        t = time.perf_counter()
        r = calibrate(_window(ds, window, s), opts, eskf_options=eo)
        td = r.calibration["time_offset"]
        base = td["value"] + s if base is None else base
        print(f"shift {1000 * s:+.0f} ms: t_d {1000 * td['value']:.1f} +/- {1000 * td['sd']:.1f} ms (expected "
              f"{1000 * (base - s):.1f}), ESKF {1000 * r.eskf.calibration['time_offset']:.1f} ms, "
              f"{time.perf_counter() - t:.0f} s")


def full(path: str) -> None:
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.estimation import EskfOptions, truth_at
    from uwbimu.io.loader import load_dataset

    ds = load_dataset(path)
    r = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False}}),
                  eskf_options=EskfOptions.from_yaml(REAL))

    def ate(t, p):
        pt, _q, _v, ok = truth_at(ds, t)
        return float(np.sqrt(np.mean(np.sum((p[ok] - pt[ok]) ** 2, axis=1))))

    tr = r.trajectory
    c = r.calibration
    print(f"ATE batch {ate(tr.t.to_numpy(), tr[['px', 'py', 'pz']].to_numpy()):.3f} m, "
          f"ESKF {ate(r.eskf.t, r.eskf.states[:, 0:3]):.3f} m; lever arm {np.round(100 * np.array(c['lever_arm']), 1)}"
          f" +/- {np.round(100 * np.array(c['lever_arm_sd']), 1)} cm; t_d {1000 * c['time_offset']['value']:.1f} ms; "
          f"{r.runtime_s:.0f} s")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["cost", "shift", "full"])
    ap.add_argument("dataset", nargs="?")
    ap.add_argument("--window", type=float, default=40.0)
    ap.add_argument("--shifts", default="0,0.05,-0.05,0.1,-0.1")
    a = ap.parse_args(argv)
    if a.what == "cost":
        cost()
    elif a.dataset is None:
        ap.error("shift and full need DATASET")
    elif a.what == "shift":
        shift(a.dataset, a.window, [float(x) for x in a.shifts.split(",")])
    else:
        full(a.dataset)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
