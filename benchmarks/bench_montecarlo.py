"""Monte Carlo throughput: local process pool vs a 2-worker Dask LocalCluster.

Job (the issue's target): N runs (default 100) of a 90 s flight — built-in
``excited-90s``: 200 Hz BMI088-class IMU, 50 Hz round-robin UWB, 8 anchors —
each simulated and estimated with the 19-state ESKF (default options,
including its yaw / time-offset initialisation bank).

Prints

1. the per-run breakdown simulate vs estimate (in-process, a few runs);
2. the wall time of the job on the local process pool (``--workers`` processes);
3. the same job on a loopback Dask LocalCluster with as many workers, both
   including and excluding the cluster start-up, and the ratio to (2);
4. that both backends produced bit-identical metrics.

Targets: (2) < 60 s with 2 workers; (3)/(2) <= 1.3.

Usage::

    python benchmarks/bench_montecarlo.py [--runs 100] [--workers 2] [--estimator eskf|pointmass]
"""

from __future__ import annotations

import argparse
import os
import shutil
import tempfile
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=100)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--estimator", default="eskf", choices=["eskf", "pointmass"])
    ap.add_argument("--scenario", default="excited-90s")
    ap.add_argument("--breakdown-runs", type=int, default=3)
    ap.add_argument("--skip-dask", action="store_true")
    args = ap.parse_args()

    import pandas as pd

    from uwbimu.eval import montecarlo as mc

    cfg = mc.config_from_dict({
        "name": "bench",
        "runs": args.runs,
        "seed_base": 123,
        "scenarios": [{"name": args.scenario, "builtin": args.scenario}],
        "estimators": [{"name": args.estimator, "kind": args.estimator}],
    })
    print(f"job: {args.runs} runs of '{args.scenario}' with the {args.estimator} estimator, "
          f"{args.workers} workers, {os.cpu_count()} cores on this machine "
          f"(load average {os.getloadavg()[0]:.1f} at start)")
    study = mc.resolved_study(cfg)
    sc = study["scenarios"][0]["scenario"]
    print(f"flight: {sc['duration']} s, IMU {sc['imu']['rate_hz']} Hz, UWB {sc['uwb']['rate_hz']} Hz")

    # 1. breakdown, in this process (first warm-up run excluded: numba cache load / compile)
    task = {"scenario_name": args.scenario, "scenario": sc, "estimators": [e.model_dump() for e in cfg.estimators],
            "seed_base": 999, "skip_initial_s": 0.0, "trace_rate_hz": cfg.trace_rate_hz}
    t0 = time.perf_counter()
    mc.run_chunk({**task, "runs": [0]})
    print(f"warm-up run (imports, numba cache): {time.perf_counter() - t0:.2f} s")
    ch = mc.run_chunk({**task, "runs": list(range(1, 1 + args.breakdown_runs))})
    rows = pd.DataFrame(ch["rows"])
    sim, est = rows["sim_s"].mean(), rows["est_s"].mean()
    simc, estc = rows["sim_cpu_s"].mean(), rows["est_cpu_s"].mean()
    print(f"per run (mean of {len(rows)}): simulate {sim:.3f} s wall / {simc:.3f} s CPU, estimate {est:.3f} s wall / "
          f"{estc:.3f} s CPU -> {args.runs} runs on {args.workers} idle cores: "
          f"{args.runs * (simc + estc) / args.workers:.1f} s")

    tmp = Path(tempfile.mkdtemp(prefix="bench_mc_"))
    try:
        # 2. local process pool
        wall_pool, cpu_pool, s_pool = _pool(mc, cfg, tmp / "pool", args.workers)
        print(f"process pool: {wall_pool:.1f} s wall for {args.runs} runs, chunk size "
              f"{s_pool['execution']['chunk_size']}  [target < 60 s]; CPU in the runs {cpu_pool:.1f} s "
              f"(= {cpu_pool / args.workers:.1f} s on {args.workers} otherwise idle cores)")
        if args.skip_dask:
            return
        # 3. Dask LocalCluster (loopback), same job; then the pool again (the machine is shared:
        #    bracketing the Dask run shows how much the load drifted)
        from distributed import Client, LocalCluster

        t0 = time.perf_counter()
        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=None) as cluster, Client(cluster) as client:
            t_up = time.perf_counter() - t0
            t1 = time.perf_counter()
            mc.run_study(cfg, tmp / "dask", client=client, workers=args.workers, plots=False)
            wall_dask_job = time.perf_counter() - t1
        wall_dask = time.perf_counter() - t0
        cpu_dask = _run_cpu(tmp / "dask")
        print(f"dask LocalCluster: {wall_dask:.1f} s wall incl. start-up/shutdown ({t_up:.1f} s start-up), "
              f"{wall_dask_job:.1f} s for the job itself; CPU in the runs {cpu_dask:.1f} s")
        wall_pool2, cpu_pool2, _ = _pool(mc, cfg, tmp / "pool2", args.workers)
        print(f"process pool again: {wall_pool2:.1f} s wall; CPU in the runs {cpu_pool2:.1f} s")
        ref = 0.5 * (wall_pool + wall_pool2)
        print(f"ratio dask / pool (pool = mean of the two pool runs, {ref:.1f} s): "
              f"{wall_dask / ref:.2f} incl. cluster start-up/shutdown, {wall_dask_job / ref:.2f} job only  "
              f"[target <= 1.3]")
        diffs = list(mc.iter_rows_equal_ignoring_timing(pd.read_csv(tmp / "pool" / "montecarlo.csv"),
                                                        pd.read_csv(tmp / "dask" / "montecarlo.csv")))
        print("metrics bit-identical between backends:", "yes" if not diffs else f"NO: {diffs[:3]}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def _run_cpu(out: Path) -> float:
    """CPU seconds spent inside the runs (simulate + estimate), from the rows."""
    import pandas as pd

    df = pd.read_csv(out / "montecarlo.csv")
    per_run = df.groupby(["scenario", "run"]).agg(sim=("sim_cpu_s", "first"), est=("est_cpu_s", "sum"))
    return float(per_run["sim"].sum() + per_run["est"].sum())


def _pool(mc, cfg, out: Path, workers: int):
    t0 = time.perf_counter()
    summary = mc.run_study(cfg, out, workers=workers, plots=False)
    return time.perf_counter() - t0, _run_cpu(out), summary


if __name__ == "__main__":
    main()
