"""Batch calibrator figures: range-factor cost, INRoL clock-shift recovery, full-log accuracy.

    python benchmarks/bench_calibrate.py cost
    python benchmarks/bench_calibrate.py shift DATASET [--window 40] [--shifts 0,0.05,-0.05,0.1,-0.1]
    python benchmarks/bench_calibrate.py full DATASET      # ATE of batch vs ESKF (slow: ~10 min)
    python benchmarks/bench_calibrate.py profile DATASET [--workers N] [--baseline]
    python benchmarks/bench_calibrate.py long [--duration 600] [--imu-rate 1000] [--workers N] [--baseline]
    python benchmarks/bench_calibrate.py tdoa [--duration 30]
    python benchmarks/bench_calibrate.py workers [DATASET] [--duration 120] [--imu-rate 200] [--repeat 2] [--windows 4]

DATASET: an imported INRoL folder (``uwbimu import inrol ../shared/datasets/inrol_uwb_imu DIR``).

``profile`` (issue 12 item 8, target: a 3-minute real log with the t_d profile in < 60 s CPU on one
core): ``calibrate`` of the whole log with the default options (t_d profile on), the initialising
ESKF included; CPU seconds of this process (``time.process_time``) and wall seconds, the result
(lever arm, t_d +/- sigma, verdict, ATE against the ground truth).  ``--baseline``: the same
calibration with ``reference_solver=True`` (GTSAM's own optimizer, every profile point solved to its
convergence rule: the code before item 8) in the same process, on the same ESKF (run once, its
time added to both), and the ratio.  ``--workers N``: the profile's walks on a process pool (its CPU
is in the workers, so only the wall time means something then).

``long`` (target: a 10-minute 1 kHz log in < 5 minutes): the built-in ``calibration-flight``
simulated with ``--duration`` and an IMU at ``--imu-rate``; the same figures, the result against
the simulation's truth (lever arm and t_d error in sigmas, ATE).  The simulation is not timed.
``tdoa``: the built-in ``crazyflie-tdoa3`` (Loco TDoA3, 400 TDoA/s) simulated for ``--duration`` s,
calibrated (profile off) with the TDoA rows grouped per block of keyframes (default) and, in the same run,
with one factor per row (``group_range_factors: false``, the baseline): CPU of each, their ratio, and the
difference of the results (final cost, lever arm, t_d).
``workers`` (issue 31): in one run, ``calibrate`` (t_d profile on) with ``workers=1`` and ``workers=2`` (the
profile's walks on a process pool, the caller walking too) on the same ESKF, and ``--windows`` repeatability
windows (ESKF; of a ``--windows-duration`` log, 600 s by default) with ``workers=1`` and ``2``, both through :func:`uwbimu.eval.repeatability.repeatability` as it
is and through ``execute(..., caller=True)``; wall seconds, the best of ``--repeat`` runs each (the 2-core
machine is shared: the minimum is the figure), the ratio 1 worker / 2 workers, and whether the results are
identical.  DATASET: an imported folder (default: the built-in ``calibration-flight`` of ``--duration`` s).
State the machine load (``uptime``) next to any figure.  Nothing is hard-coded: every number is
measured in the run (docs/calibrate.md holds the tables).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
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


def _ate(ds, traj) -> float:
    from uwbimu.estimation import truth_at

    pt, _q, _v, ok = truth_at(ds, traj.t.to_numpy())
    return float(np.sqrt(np.mean(np.sum((traj[["px", "py", "pz"]].to_numpy()[ok] - pt[ok]) ** 2, axis=1))))


def _timed_calibrate(ds, opts, eo, eskf, **kw):
    from uwbimu.calibration import calibrate

    c0, w0 = time.process_time(), time.perf_counter()
    r = calibrate(ds, opts, eskf=eskf, eskf_options=eo, **kw)
    return r, time.process_time() - c0, time.perf_counter() - w0


def _describe(label: str, r, cpu: float, wall: float, ds, eskf_cpu: float) -> str:
    c = r.calibration
    td = c["time_offset"]
    sd = "held at prior" if td["sd"] is None else f"+/- {1000 * td['sd']:.2f} (curvature {1000 * td['sd_curvature']:.2f})"
    truth = ds.meta.truth
    vs = ""
    if truth is not None and truth.lever_arm is not None:
        el = (np.array(c["lever_arm"]) - truth.lever_arm) / np.array(c["lever_arm_sd"])
        vs = f"; vs truth: lever arm error {np.round(el, 2)} sigma"
        if truth.time_offset is not None and td["sd"] is not None:
            vs += f", t_d error {(td['value'] - truth.time_offset) / td['sd']:+.2f} sigma"
    p = r.profile
    prof = "" if p is None else (f"; profile {len(p.grid)} points, {int(p.iterations.sum())} LM steps, "
                                 f"argmin {1000 * p.best:.0f} ms")
    return (f"{label}: {cpu + eskf_cpu:.1f} s CPU ({eskf_cpu:.1f} ESKF + {cpu:.1f} batch), {wall:.1f} s wall (batch); "
            f"lever arm [cm] {np.round(100 * np.array(c['lever_arm']), 2)} +/- {np.round(100 * np.array(c['lever_arm_sd']), 2)}; "
            f"t_d {1000 * td['value']:.2f} ms {sd}, {td['verdict']}; ATE {_ate(ds, r.trajectory):.3f} m{prof}{vs}")


def _profile_bench(ds, eo, workers: int, baseline: bool) -> None:
    from uwbimu.calibration import CalibrationOptions
    from uwbimu.estimation import run_eskf

    print(f"load before: {os.getloadavg()}")
    opts = CalibrationOptions()
    c0 = time.process_time()
    eskf = run_eskf(ds, eo)  # the anchors' frame, as calibrate() takes it
    eskf_cpu = time.process_time() - c0
    r, cpu, wall = _timed_calibrate(ds, opts, eo, eskf, workers=workers)
    print(_describe(f"fast (workers={workers})", r, cpu, wall, ds, eskf_cpu))
    if baseline:
        rb, cpu_b, wall_b = _timed_calibrate(ds, opts, eo, eskf, reference_solver=True)
        print(_describe("reference (GTSAM optimizer, full-solve profile)", rb, cpu_b, wall_b, ds, eskf_cpu))
        if workers == 1:
            print(f"ratio reference / fast: {(cpu_b + eskf_cpu) / (cpu + eskf_cpu):.2f} (CPU, ESKF included), "
                  f"{cpu_b / cpu:.2f} (batch only)")
        d = np.abs(np.subtract(r.profile.chi2, rb.profile.chi2)).max() if np.array_equal(r.profile.grid, rb.profile.grid) \
            else float("nan")
        print(f"max |chi2 fast - chi2 reference| over the profile grid: {d:.4f}")
    print(f"load after: {os.getloadavg()}")


def profile(path: str, workers: int, baseline: bool) -> None:
    from uwbimu.estimation import EskfOptions
    from uwbimu.io.loader import load_dataset

    _profile_bench(load_dataset(path), EskfOptions.from_yaml(REAL), workers, baseline)


def long(duration: float, imu_rate: float, workers: int, baseline: bool) -> None:
    from uwbimu.estimation import EskfOptions
    from uwbimu.sim import builtin_scenario, simulate

    sc = builtin_scenario("calibration-flight")
    sc = sc.model_copy(update={"duration": duration, "imu": sc.imu.model_copy(update={"rate_hz": imu_rate})})
    w0 = time.perf_counter()
    ds = simulate(sc)
    print(f"simulated calibration-flight: {duration:g} s, IMU {imu_rate:g} Hz ({len(ds.imu)} samples), "
          f"{len(ds.uwb)} ranges ({time.perf_counter() - w0:.0f} s, not timed below)")
    _profile_bench(ds, EskfOptions(), workers, baseline)


def tdoa(duration: float) -> None:
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("crazyflie-tdoa3").model_copy(update={"duration": float(duration)}))
    base = {"td_profile": {"enabled": False}}
    print(f"load before: {os.getloadavg()}; {len(ds.tdoa)} TDoA rows over {duration:g} s")
    out = {}
    for label, extra in (("grouped", {}), ("per-row (baseline)", {"group_range_factors": False})):
        c0 = time.process_time()
        r = calibrate(ds, CalibrationOptions.model_validate(base | extra))
        out[label] = (time.process_time() - c0, r.calibration)
        c = r.calibration
        print(f"{label}: {out[label][0]:.1f} s CPU; lever arm [mm] {np.round(1000 * np.array(c['lever_arm']), 3)} "
              f"+/- {np.round(1000 * np.array(c['lever_arm_sd']), 3)}; t_d {1000 * c['time_offset']['value']:.3f} ms; "
              f"cost {c['solver']['final_cost']:.4f}")
    (tg, cg), (tp, cp) = out["grouped"], out["per-row (baseline)"]
    print(f"speed-up {tp / tg:.1f}x; |lever arm difference| {1000 * np.max(np.abs(np.subtract(cg['lever_arm'], cp['lever_arm']))):.4f} mm, "
          f"|t_d difference| {1000 * abs(cg['time_offset']['value'] - cp['time_offset']['value']):.4f} ms; "
          f"load after: {os.getloadavg()}")


def _window_tasks(ds, k: int):
    from uwbimu.estimators import get_estimator
    from uwbimu.eval.repeatability import split_windows

    opts = get_estimator("eskf").options(None)
    return [(i, w, "eskf", opts) for i, w in enumerate(split_windows(ds, k))]


def workers_bench(path, duration: float, imu_rate: float, repeat: int, k: int, win_duration: float) -> None:
    from uwbimu.calibration import CalibrationOptions
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.eval.repeatability import _window_task, repeatability
    from uwbimu.parallel import execute

    if path:
        from uwbimu.io.loader import load_dataset

        ds, eo = load_dataset(path), EskfOptions.from_yaml(REAL)
    else:
        from uwbimu.sim import builtin_scenario, simulate

        sc = builtin_scenario("calibration-flight")
        ds = simulate(sc.model_copy(update={"duration": duration, "imu": sc.imu.model_copy(update={"rate_hz": imu_rate})}))
        eo = EskfOptions()
    print(f"log: {ds.duration:.0f} s, {len(ds.imu)} IMU samples, {len(ds.uwb)} ranges; load before: {os.getloadavg()}")
    eskf = run_eskf(ds, eo)
    opts = CalibrationOptions()
    best: dict = {}
    res: dict = {}
    for _ in range(max(1, repeat)):
        for w in (1, 2):
            r, _cpu, wall = _timed_calibrate(ds, opts, eo, eskf, workers=w)
            best[w] = min(best.get(w, np.inf), wall)
            res[w] = r
    a, b = res[1], res[2]
    same = (np.array_equal(a.profile.grid, b.profile.grid) and np.array_equal(a.profile.chi2, b.profile.chi2)
            and a.calibration["lever_arm"] == b.calibration["lever_arm"]
            and a.calibration["time_offset"]["value"] == b.calibration["time_offset"]["value"])
    print(f"calibrate (t_d profile, {len(a.profile.grid)} points): 1 worker {best[1]:.1f} s wall, 2 workers "
          f"{best[2]:.1f} s wall (best of {repeat}); RATIO 1 worker / 2 workers {best[1] / best[2]:.2f}x; "
          f"profile and calibration identical: {same}")

    if not path:  # the windows on a longer log: a window's ESKF run must not be small against a worker's start
        sc = builtin_scenario("calibration-flight")
        ds = simulate(sc.model_copy(update={"duration": win_duration,
                                            "imu": sc.imu.model_copy(update={"rate_hz": imu_rate})}))
        print(f"windows log: {ds.duration:.0f} s, {len(ds.imu)} IMU samples")
    tasks = _window_tasks(ds, k)
    wins: dict = {}
    outs: dict = {}
    for _ in range(max(1, repeat)):
        for label, run in (
            ("repeatability(), 1 worker", lambda: repeatability(ds, k, "eskf", workers=1)["windows"]),
            ("repeatability(), 2 workers", lambda: repeatability(ds, k, "eskf", workers=2)["windows"]),
            ("execute(caller=True), 2 workers", lambda: _collect(execute, _window_task, tasks)),
        ):
            w0 = time.perf_counter()
            out = run()
            wins[label] = min(wins.get(label, np.inf), time.perf_counter() - w0)
            outs[label] = sorted((r["i"], r.get("values")) for r in out)
    one = wins["repeatability(), 1 worker"]
    for label, wall in wins.items():
        print(f"{k} repeatability windows (ESKF), {label}: {wall:.2f} s wall (best of {repeat}); RATIO 1 worker / "
              f"this {one / wall:.2f}x; windows identical to 1 worker: "
              f"{outs[label] == outs['repeatability(), 1 worker']}")
    print(f"load after: {os.getloadavg()}")


def _collect(execute, fn, tasks):
    got = []
    failed = execute(fn, tasks, got.append, workers=2, preload=("uwbimu.sim", "uwbimu.estimation", "uwbimu.estimators"),
                     caller=True)
    assert not failed, failed
    return got


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("what", choices=["cost", "shift", "full", "profile", "long", "tdoa", "workers"])
    ap.add_argument("dataset", nargs="?")
    ap.add_argument("--window", type=float, default=40.0)
    ap.add_argument("--shifts", default="0,0.05,-0.05,0.1,-0.1")
    ap.add_argument("--workers", type=int, default=1, help="profile / long: processes for the t_d profile")
    ap.add_argument("--baseline", action="store_true", help="profile / long: also the reference solver, same run")
    ap.add_argument("--duration", type=float, default=None, help="long / tdoa: simulated log length [s] (600 / 30)")
    ap.add_argument("--imu-rate", type=float, default=None, help="long / workers: IMU rate [Hz] (1000 / 200)")
    ap.add_argument("--repeat", type=int, default=2, help="workers: runs of each variant (the best is reported)")
    ap.add_argument("--windows", type=int, default=4, help="workers: repeatability windows")
    ap.add_argument("--windows-duration", type=float, default=600.0,
                    help="workers: simulated log [s] the windows split (without DATASET)")
    a = ap.parse_args(argv)
    if a.what == "cost":
        cost()
    elif a.what == "tdoa":
        tdoa(a.duration or 30.0)
    elif a.what == "long":
        long(a.duration or 600.0, a.imu_rate or 1000.0, a.workers, a.baseline)
    elif a.what == "workers":
        workers_bench(a.dataset, a.duration or 120.0, a.imu_rate or 200.0, a.repeat, a.windows, a.windows_duration)
    elif a.dataset is None:
        ap.error("shift, full and profile need DATASET")
    elif a.what == "profile":
        profile(a.dataset, a.workers, a.baseline)
    elif a.what == "shift":
        shift(a.dataset, a.window, [float(x) for x in a.shifts.split(",")])
    else:
        full(a.dataset)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
