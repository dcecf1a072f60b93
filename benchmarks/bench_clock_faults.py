"""Clock-fault detector: detection, time and size errors, drift rates, clean-log statistics, cost.

Prints the tables of docs/estimator.md ("Clock faults").  Usage::

    uwbimu import inrol ../shared/datasets/inrol_uwb_imu /tmp/inrol
    PYTHONPATH=src python benchmarks/bench_clock_faults.py [--inrol /tmp/inrol] [--seeds 5]

Simulated cases: the built-in 60 s calibration flight (noise seeds 1..N) with the UWB clock
jumping at 30 s (a backward jump comes with a dropout of its length, so the stamps stay
monotonic), drifts on the 180 s flight (300, 3000 ppm) and the 60 s one (1e4 ppm), and clean
logs.  On INRoL the same faults are injected into the real log (jump at 100 s); its truth is
unknown, so the clean run's t_d is the reference there.
"""

from __future__ import annotations

import argparse
import copy
import time

import numpy as np

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.eval.clock_faults import handle_clock_faults
from uwbimu.eval.clock_windows import consistency_tests, windowed_time_offsets
from uwbimu.sim import builtin_scenario, simulate


def _with_uwb(ds, u):
    out = copy.copy(ds)
    out.uwb = u.reset_index(drop=True)
    return out


def jumped(ds, jump, at):
    u = ds.uwb.copy()
    t = u["t"].to_numpy().copy()
    if jump < 0:
        keep = ~((t >= at) & (t < at - jump))
        u, t = u[keep].copy(), t[keep]
    t[t >= at] += jump
    u["t"] = t
    return _with_uwb(ds, u)


def drifted(ds, ppm):
    u = ds.uwb.copy()
    t = u["t"].to_numpy()
    u["t"] = t + ppm * 1e-6 * (t - t.min())
    return _with_uwb(ds, u)


def flight(duration, seed):
    return simulate(builtin_scenario("calibration-flight").updated(duration=duration, seeds={"noise": seed}))


def handled(ds, opts):
    n = [0]

    def rerun(d):
        n[0] += 1
        return run_eskf(d, opts)

    c0 = time.process_time()
    res = run_eskf(ds, opts)
    c1 = time.process_time()
    out, _ = handle_clock_faults(res, ds, rerun)
    c2 = time.process_time()
    return out, [e for e in out.events if str(e.get("kind", "")).startswith("clock_")], n[0], c1 - c0, c2 - c1


def jump_table(seeds):
    print("\n| jump [s] | detected | max abs(t error) [s] | max abs(size error) / sd | max t_d error / sd | re-runs (mean) |")
    print("| --- | --- | --- | --- | --- | --- |")
    for jump in (0.3, -0.3, -0.2, 0.12):
        det, terr, serr, tderr, runs = 0, [], [], [], []
        for seed in range(1, seeds + 1):
            ds = flight(60.0, seed)
            out, ev, n, _, _ = handled(jumped(ds, jump, 30.0), EskfOptions())
            runs.append(n)
            j = [e for e in ev if e["kind"] == "clock_jump"]
            if len(ev) == 1 and j:
                det += 1
                terr.append(abs(j[0]["t"] - 30.0 - max(jump, 0)))
                serr.append(abs(j[0]["size"] + jump) / j[0]["sigma"])
                c = out.calibration
                tderr.append(abs(c["time_offset"] - ds.meta.truth.time_offset) / c["time_offset_sd"])
        print(f"| {jump:+.2f} | {det}/{seeds} | {max(terr, default=np.nan):.3f} | {max(serr, default=np.nan):.1f} | "
              f"{max(tderr, default=np.nan):.1f} | {np.mean(runs):.1f} |", flush=True)


def drift_table(seeds):
    print("\n| drift [ppm] | log [s] | seed | detected | rate +- sd [ppm] | error / sd | t_d0 error / sd | re-runs |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    for ppm, dur in ((300.0, 180.0), (3000.0, 180.0), (10000.0, 60.0), (-10000.0, 60.0)):
        for seed in range(1, seeds + 1):
            ds = flight(dur, seed)
            out, ev, n, _, _ = handled(drifted(ds, ppm), EskfOptions())
            d = [e for e in ev if e["kind"] == "clock_drift"]
            if len(ev) == 1 and d:
                e = d[0]
                print(f"| {ppm:+.0f} | {dur:.0f} | {seed} | yes | {e['rate_ppm']:+.0f} +- {e['sigma_ppm']:.0f} | "
                      f"{(e['rate_ppm'] - ppm) / e['sigma_ppm']:+.1f} | "
                      f"{(e['t_d0'] - ds.meta.truth.time_offset) / e['t_d0_sd']:+.1f} | {n} |", flush=True)
            else:
                print(f"| {ppm:+.0f} | {dur:.0f} | {seed} | no ({[e['kind'] for e in ev]}) | | | | {n} |", flush=True)


def clean_table(n60, n180):
    print("\n| clean logs | count | with a clock event | max z_jump / crit | max z_drift / crit |")
    print("| --- | --- | --- | --- | --- |")
    for dur, n in ((60.0, n60), (180.0, n180)):
        zj, zd, flagged = [], [], 0
        for seed in range(n):
            res = run_eskf(flight(dur, seed), EskfOptions())
            c = consistency_tests(windowed_time_offsets(res), float(res.t[0]))
            flagged += c["verdict"] is not None
            zj.append(c["z_jump"] / c["crit_jump"])
            zd.append(c["z_drift"] / c["crit_drift"])
        print(f"| {dur:.0f} s, noise seeds 0..{n - 1} | {n} | {flagged} | {max(zj):.2f} | {max(zd):.2f} |", flush=True)


def inrol(path):
    from rich.console import Console

    from uwbimu.cli.dataset_options import apply_dataset_properties, estimator_options, load
    from pathlib import Path

    ds = load(Path(path), None)
    opts = apply_dataset_properties(estimator_options("eskf", None, None), ds, Console(file=open("/dev/null", "w")))
    out, ev, n, c_run, c_check = handled(ds, opts)
    td_ref, td_sd = out.calibration["time_offset"], out.calibration["time_offset_sd"]
    print(f"\nINRoL clean: events {[e['kind'] for e in ev]}, ESKF {c_run:.1f} s CPU, clock check {c_check:.2f} s CPU "
          f"({n} re-runs), t_d = {1000 * td_ref:.1f} +- {1000 * td_sd:.1f} ms")
    print("\n| INRoL + injected fault | events | t [s] | size [ms] / rate [ppm] (+- sd) | t_d [ms] (+- sd) | "
          "re-runs | CPU run + check [s] |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    cases = [("jump -0.2 s at 100 s", jumped(ds, -0.2, 100.0)), ("jump +0.3 s at 100 s", jumped(ds, 0.3, 100.0)),
             ("drift 300 ppm", drifted(ds, 300.0)), ("drift 3000 ppm", drifted(ds, 3000.0))]
    for name, bad in cases:
        out, ev, n, c_run, c_check = handled(bad, opts)
        for e in ev or [{}]:
            if e.get("kind") == "clock_jump":
                val, td = f"{1000 * e['size']:+.0f} +- {1000 * e['sigma']:.0f}", (e["t_d"], e["t_d_sd"])
            elif e.get("kind") == "clock_drift":
                val, td = f"{e['rate_ppm']:+.0f} +- {e['sigma_ppm']:.0f}", (e["t_d0"], e["t_d0_sd"])
            else:
                val, td = "", (out.calibration["time_offset"], out.calibration["time_offset_sd"])
            print(f"| {name} | {e.get('kind', 'none')} | {e.get('t', float('nan')):.2f} | {val} | "
                  f"{1000 * td[0]:.1f} +- {1000 * td[1]:.1f} | {n} | {c_run:.1f} + {c_check:.1f} |", flush=True)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--inrol", default=None, help="imported INRoL dataset folder")
    ap.add_argument("--seeds", type=int, default=5)
    a = ap.parse_args()
    t0 = time.perf_counter()
    jump_table(a.seeds)
    drift_table(max(1, a.seeds // 2))
    clean_table(20, 8)
    if a.inrol:
        inrol(a.inrol)
    print(f"\n(total {time.perf_counter() - t0:.0f} s wall)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
