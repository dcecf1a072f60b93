"""Monte Carlo throughput: local process pool vs a 2-worker Dask LocalCluster.

Job (the issue's target): N runs (default 100) of a 90 s flight — built-in
``excited-90s``: 200 Hz BMI088-class IMU, 50 Hz round-robin UWB, 8 anchors —
each simulated and estimated with the 19-state ESKF (default options,
including its yaw / time-offset initialisation bank).

Prints

1. the per-run breakdown simulate vs estimate (in-process, a few runs);
2. the wall time of the job on the local process pool (``--workers`` processes);
3. the same job on a loopback Dask LocalCluster with as many workers, both
   including and excluding the cluster start-up, then the pool again, and the
   ratio of Dask to the mean of the two pool runs (each measurement in a fresh
   Python process; the machine may be shared, so the bracketing shows drift);
4. that both backends produced bit-identical metrics.

Targets: (2) < 60 s with 2 workers; (3)/(2) <= 1.3.

Usage::

    python benchmarks/bench_montecarlo.py [--runs 100] [--workers 2] [--estimator eskf|pointmass]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
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
    ap.add_argument("--child", choices=["pool", "dask"], help=argparse.SUPPRESS)
    ap.add_argument("--child-out", help=argparse.SUPPRESS)
    args = ap.parse_args()

    import pandas as pd

    from uwbimu import studies as mc

    if args.child:
        _child(args)
        return
    cfg = _config(mc, args)
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
        # Each measurement runs in a fresh Python process (no warm forkserver / imports carried over).
        res = {}
        for label in ("pool", "dask", "pool2") if not args.skip_dask else ("pool",):
            backend = "dask" if label == "dask" else "pool"
            res[label] = _measure_in_subprocess(args, backend, tmp / label)
            r = res[label]
            extra = f" ({r['startup_s']:.1f} s cluster start-up, {r['job_s']:.1f} s job only)" if backend == "dask" else ""
            print(f"{label:6s}: {r['wall_s']:.1f} s wall for {args.runs} runs incl. process start-up{extra}; "
                  f"CPU inside the runs {r['cpu_s']:.1f} s (= {r['cpu_s'] / args.workers:.1f} s on "
                  f"{args.workers} otherwise idle cores); chunk size {r['chunk_size']}")
        print(f"target (100 runs of the 90 s flight, ESKF, 2 cores): < 60 s -> measured {res['pool']['wall_s']:.1f} s for {args.runs} runs (process pool)")
        if args.skip_dask:
            return
        ref = 0.5 * (res["pool"]["wall_s"] + res["pool2"]["wall_s"])
        print(f"ratio dask / pool (pool = mean of the runs before and after, {ref:.1f} s): "
              f"{res['dask']['wall_s'] / ref:.2f} incl. cluster start-up/shutdown, "
              f"{res['dask']['job_s'] / ref:.2f} job only  [target <= 1.3]")
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


def _measure_in_subprocess(args, backend: str, out: Path) -> dict:
    cmd = [sys.executable, __file__, "--child", backend, "--child-out", str(out), "--runs", str(args.runs),
           "--workers", str(args.workers), "--estimator", args.estimator, "--scenario", args.scenario]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"{backend} run failed:\n{proc.stderr[-3000:]}")
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    r["wall_s"] = wall
    r["cpu_s"] = _run_cpu(out)
    return r


def _child(args) -> None:
    """One measurement: the whole study on one backend; prints a JSON line."""
    from uwbimu import studies as mc

    cfg = _config(mc, args)
    out = Path(args.child_out)
    t0 = time.perf_counter()
    if args.child == "dask":
        from distributed import Client, LocalCluster

        with LocalCluster(n_workers=args.workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                          dashboard_address=None) as cluster, Client(cluster) as client:
            t_up = time.perf_counter() - t0
            t1 = time.perf_counter()
            s = mc.run_study(cfg, out, client=client, workers=args.workers, plots=False)
            job = time.perf_counter() - t1
    else:
        t_up = 0.0
        s = mc.run_study(cfg, out, workers=args.workers, plots=False)
        job = time.perf_counter() - t0
    print(json.dumps({"startup_s": t_up, "job_s": job, "chunk_size": s["execution"]["chunk_size"]}))


def _config(mc, args):
    return mc.config_from_dict({
        "name": "bench",
        "runs": args.runs,
        "seed_base": 123,
        "scenarios": [{"name": args.scenario, "builtin": args.scenario}],
        "estimators": [{"name": args.estimator, "kind": args.estimator}],
    })


if __name__ == "__main__":
    main()
