"""Cost of the streaming filter from Python: per ``push_imu`` / ``push_range`` call, and chunked.

    python benchmarks/bench_streaming.py [--minutes 2] [--imu-hz 200]

Simulates a ``calibration-flight`` log, then feeds it to :class:`uwbimu.estimation.Eskf`
(1) sample by sample in arrival order (what a robot's callback does), (2) in 50 ms chunks, and runs
(3) :func:`run_eskf` (the same filter fed the whole log at once) in the same process, as the
baseline.  Reports CPU microseconds per IMU sample after initialisation, and the ratios.  The three
trajectories are bit-identical (``tests/test_streaming.py``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from uwbimu.estimation import Eskf, EskfOptions, run_eskf
from uwbimu.sim import builtin_scenario, simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--imu-hz", type=float, default=200.0)
    a = ap.parse_args()
    sc = builtin_scenario("calibration-flight")
    sc = sc.model_copy(update={"duration": 60.0 * a.minutes,
                               "imu": sc.imu.model_copy(update={"rate_hz": a.imu_hz})})
    ds = simulate(sc)
    opts = EskfOptions(store_covariance=False)
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    tu = ds.uwb["t"].to_numpy(float)
    au = ds.uwb["anchor"].astype(str).to_numpy()
    ru = ds.uwb["range"].to_numpy(float)
    td = ds.meta.truth.time_offset or 0.0
    run_eskf(ds, opts)  # JIT warm-up

    # (1) one call per sample; the clock starts once the filter is initialised
    f = Eskf.for_dataset(ds, opts)
    j = 0
    c_imu = c_rng = 0.0
    n_imu = n_rng = 0
    for row in imu:
        while j < len(tu) and tu[j] + td <= row[0]:
            c0 = time.process_time()
            f.push_range(tu[j], au[j], ru[j])
            if f.initialised:
                c_rng += time.process_time() - c0
                n_rng += 1
            j += 1
        c0 = time.process_time()
        f.push_imu(row[0], row[1:4], row[4:7])
        if f.initialised:
            c_imu += time.process_time() - c0
            n_imu += 1
    f.finish()

    # (2) 50 ms chunks
    f2 = Eskf.for_dataset(ds, opts)
    step = max(1, int(round(0.05 * a.imu_hz)))
    j = 0
    c0 = time.process_time()
    for i0 in range(0, len(imu), step):
        blk = imu[i0:i0 + step]
        j1 = int(np.searchsorted(tu + td, blk[-1, 0], side="right"))
        if j1 > j:
            f2.push_ranges(tu[j:j1], au[j:j1], ru[j:j1])
            j = j1
        f2.push_imu_chunk(blk[:, 0], blk[:, 1:4], blk[:, 4:7])
    f2.finish()
    c_chunk = time.process_time() - c0

    # (3) the batch baseline
    c0 = time.process_time()
    res = run_eskf(ds, opts)
    c_batch = time.process_time() - c0
    per_sample = 1e6 * c_imu / max(n_imu, 1)
    print(f"log: {a.minutes:g} min, IMU {a.imu_hz:g} Hz ({len(imu)} samples), {len(tu)} ranges")
    print(f"push_imu (one sample, after initialisation): {per_sample:.1f} us CPU per call "
          f"({1e6 / per_sample:,.0f} samples per CPU second)")
    print(f"push_range (one range, after initialisation): {1e6 * c_rng / max(n_rng, 1):.1f} us CPU per call")
    print(f"50 ms chunks, whole log incl. initialisation: {c_chunk:.2f} s CPU "
          f"({len(imu) / c_chunk:,.0f} IMU samples per CPU second)")
    print(f"run_eskf (baseline, same filter, whole log at once): {c_batch:.2f} s CPU "
          f"({len(imu) / c_batch:,.0f} IMU samples per CPU second)")
    print(f"ratios to the baseline: chunks {c_chunk / c_batch:.2f}x, sample-by-sample "
          f"{(c_imu + c_rng) / c_batch:.2f}x (after initialisation only)")
    same = np.allclose(f.state().lever_arm, res.calibration["lever_arm"], atol=0, rtol=0)
    print(f"final lever arm identical to run_eskf: {same}")


if __name__ == "__main__":
    main()
