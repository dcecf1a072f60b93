"""Cost of the streaming filter from Python: per ``push_imu`` / ``push_range`` call, and chunked.

    python benchmarks/bench_streaming.py [--minutes 2] [--imu-hz 200] [--chunks 10,50,200]

Simulates a ``calibration-flight`` log, then feeds it to :class:`uwbimu.estimation.Eskf`
(1) sample by sample in arrival order (what a robot's callback does), (2) in 50 ms chunks, (3) in
chunks of ``--chunks`` IMU samples (``push_imu_chunk`` + ``push_ranges`` of the ranges due by the
chunk's end), and runs (4) :func:`run_eskf` (the same filter fed the whole log at once) in the same
process, as the baseline.  Reports CPU microseconds per call / per IMU sample after initialisation
(the range pushes of a chunk included), and the ratios.  The options are the streaming filter's one
pass (``noise="preset"``, ``hold_unidentified=False``), so all runs end on the same calibration; the
trajectories are bit-identical (``tests/test_streaming.py``, ``tests/test_streaming_chunks.py``).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from uwbimu.estimation import Eskf, EskfOptions, run_eskf
from uwbimu.estimation.streaming import IMU_BATCH, MEAS_BATCH
from uwbimu.sim import builtin_scenario, simulate


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=2.0)
    ap.add_argument("--imu-hz", type=float, default=200.0)
    ap.add_argument("--chunks", type=str, default="10,50,200", help="chunk sizes [IMU samples] timed after init")
    a = ap.parse_args()
    sc = builtin_scenario("calibration-flight")
    sc = sc.model_copy(update={"duration": 60.0 * a.minutes,
                               "imu": sc.imu.model_copy(update={"rate_hz": a.imu_hz})})
    ds = simulate(sc)
    # the streaming filter's one pass (run_eskf's noise-from-data passes are not streamed)
    opts = EskfOptions(store_covariance=False, noise="preset", hold_unidentified=False)
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    tu = ds.uwb["t"].to_numpy(float)
    au = ds.uwb["anchor"].astype(str).to_numpy()
    ru = ds.uwb["range"].to_numpy(float)
    td = ds.meta.truth.time_offset or 0.0
    run_eskf(ds, opts)  # JIT warm-up

    # (1) one call per sample; each call timed, the sums taken over the calls after the initialisation
    # (found afterwards from the "initialised" event: asking the filter during the run would make it
    # process the samples push_imu keeps, IMU_BATCH)
    f = Eskf.for_dataset(ds, opts)
    j = 0
    ci = np.zeros(len(imu))
    cr = np.zeros(len(tu))
    clock = time.process_time
    # the initialiser runs inside whichever call hands over the data it waits for (a push_imu that fills
    # IMU_BATCH): its CPU (Eskf.init_cpu_seconds, read without processing anything) is taken out of that call
    for i, row in enumerate(imu):
        while j < len(tu) and tu[j] + td <= row[0]:
            i0 = f.init_cpu_seconds
            c0 = clock()
            f.push_range(tu[j], au[j], ru[j])
            cr[j] = clock() - c0 - (f.init_cpu_seconds - i0)
            j += 1
        t_, a_, g_ = row[0], row[1:4], row[4:7]
        i0 = f.init_cpu_seconds
        c0 = clock()
        f.push_imu(t_, a_, g_)
        ci[i] = clock() - c0 - (f.init_cpu_seconds - i0)
    f.finish()
    t_init = next(e["t"] for e in f.events() if e["kind"] == "initialised") + td
    after_i, after_r = imu[:, 0] > t_init + 0.1, tu + td > t_init + 0.1
    c_imu, n_imu = float(ci[after_i].sum()), int(after_i.sum())
    c_rng, n_rng = float(cr[after_r].sum()), int(after_r.sum())
    imu_max = float(ci[after_i].max())

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

    # (3) chunks of n IMU samples; the clock runs once the filter is initialised
    chunked = {}
    for n in (int(x) for x in a.chunks.split(",") if x.strip()):
        f3 = Eskf.for_dataset(ds, opts)
        j = 0
        c_in, n_in = 0.0, 0
        for i0 in range(0, len(imu), n):
            blk = imu[i0:i0 + n]
            j1 = int(np.searchsorted(tu + td, blk[-1, 0], side="right"))
            on = f3.initialised
            c0 = time.process_time()
            if j1 > j:
                f3.push_ranges(tu[j:j1], au[j:j1], ru[j:j1])
                j = j1
            f3.push_imu_chunk(blk[:, 0], blk[:, 1:4], blk[:, 4:7])
            if on:
                c_in += time.process_time() - c0
                n_in += len(blk)
        f3.finish()
        chunked[n] = (c_in, n_in, f3.state().lever_arm.tolist() == f.state().lever_arm.tolist())

    # (4) the batch baseline
    c0 = time.process_time()
    res = run_eskf(ds, opts)
    c_batch = time.process_time() - c0
    per_sample = 1e6 * c_imu / max(n_imu, 1)
    print(f"log: {a.minutes:g} min, IMU {a.imu_hz:g} Hz ({len(imu)} samples), {len(tu)} ranges")
    print(f"push_imu (one sample, after initialisation): {per_sample:.1f} us CPU per call "
          f"({1e6 / per_sample:,.0f} samples per CPU second; the longest call {1e6 * imu_max:.0f} us: one in "
          f"IMU_BATCH = {IMU_BATCH} processes the kept samples)")
    print(f"push_range (one range, after initialisation): {1e6 * c_rng / max(n_rng, 1):.1f} us CPU per call "
          f"(a checked range is kept, MEAS_BATCH = {MEAS_BATCH}, and handed over with the next IMU chunk)")
    print(f"both pushes together, after initialisation: {1e6 * (c_imu + c_rng) / max(n_imu, 1):.1f} us CPU per IMU "
          f"sample (the initialiser's {f.init_cpu_seconds:.2f} s CPU taken out)")
    print(f"50 ms chunks, whole log incl. initialisation: {c_chunk:.2f} s CPU "
          f"({len(imu) / c_chunk:,.0f} IMU samples per CPU second)")
    print(f"run_eskf (baseline, same filter, whole log at once): {c_batch:.2f} s CPU "
          f"({len(imu) / c_batch:,.0f} IMU samples per CPU second)")
    print(f"ratios to the baseline: chunks {c_chunk / c_batch:.2f}x, sample-by-sample "
          f"{(c_imu + c_rng) / c_batch:.2f}x (after initialisation only)")
    for n, (c_in, n_in, same_n) in chunked.items():
        print(f"chunks of {n} IMU samples ({n / a.imu_hz * 1000:g} ms; push_imu_chunk + push_ranges), after "
              f"initialisation: {1e6 * c_in / max(n_in, 1):.1f} us CPU per IMU sample (ranges included); "
              f"final lever arm identical to sample by sample: {same_n}")
    same = f.state().lever_arm.tolist() == res.calibration["lever_arm"]
    print(f"final lever arm identical to run_eskf: {same}")


if __name__ == "__main__":
    main()
