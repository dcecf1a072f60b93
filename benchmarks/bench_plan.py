"""Benchmarks of the trajectory-design tools (``python benchmarks/bench_plan.py``).

Prints measured figures:

1. seed OCP (seed 002 sec. XII): direct (IPOPT) and indirect (PMP gradient)
   solve times (median of repeats), agreement, cost terms, det(O) statistics,
   grid convergence, and the PD-gain sensitivity;
2. general point-mass planner: solve time and criteria per objective;
3. calibration design: cost of one candidate evaluation, and the predictor
   checked against the ESKF's own reported sd on the built-in
   ``calibration-flight``;
4. with ``--proof``: designs the manoeuvre of ``examples/plan/calibration.yaml``
   (or ``--config``) and runs the Monte Carlo proof (ESKF, ``--seeds`` seeds).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def bench_seed(repeats: int) -> None:
    from uwbimu.design.trajectory.seed_ocp import (
        SeedOcpConfig,
        pd_rollout,
        seed_cost,
        solve_direct,
        solve_indirect,
        solve_indirect_continuous,
    )

    cfg = SeedOcpConfig()
    solve_direct(cfg)  # warm-up (CasADi plugin loading)
    td, tb, ti = [], [], []
    for _ in range(repeats):
        d = solve_direct(cfg)
        td.append(d.solve_time_s)
        tb.append(d.info["build_time_s"])
        i = solve_indirect(cfg)
        ti.append(i.solve_time_s)
    xp, up = pd_rollout(cfg)
    pd = seed_cost(xp, up, cfg)
    print("== 1. seed OCP (N = %d, h = %.3f s) ==" % (cfg.n_steps, cfg.h))
    print(f"direct   : solve {statistics.median(td) * 1e3:.1f} ms (median of {repeats}), build {statistics.median(tb) * 1e3:.1f} ms, "
          f"{d.iterations} IPOPT iterations, max|H_u| at solution {d.hu_max:.1e}")
    print(f"indirect : solve {statistics.median(ti) * 1e3:.1f} ms (median of {repeats}), {i.iterations} gradient iterations, "
          f"max|H_u| {i.hu_max:.1e} (threshold {cfg.hu_tol:g})")
    print(f"ratio indirect/direct solve time: {statistics.median(ti) / statistics.median(td):.2f}")
    print(f"agreement: |J_ind - J_dir|/J = {abs(i.cost['total'] - d.cost['total']) / d.cost['total']:.2e}, "
          f"max|u_ind - u_dir| = {np.abs(i.u - d.u).max():.2e} m/s^2")
    for name, c in (("PD", pd), ("indirect", i.cost), ("direct", d.cost)):
        print(f"  {name:9s} J = {c['total']:9.4f}  (det {c['det_term']:.4f}, track {c['track_term']:.4f}, control {c['control_term']:.4f})"
              f"  det(O) mean {c['det_mean']:.4f} min {c['det_min']:.4f} max {c['det_max']:.4f} final {c['det_final']:.4f}")
    print("grid convergence: direct optimum J*, and the continuous-costate (RK4) indirect method vs the direct one:")
    for n in (58, 116, 232, 464):
        c = SeedOcpConfig(n_steps=n)
        dd = solve_direct(c)
        ic = solve_indirect_continuous(c)
        print(f"  N = {n:4d}: J* = {dd.cost['total']:.6f}; ODE-costate method: {ic.iterations} it, {ic.solve_time_s:.2f} s, "
              f"J(ODE cost) = {ic.info['continuous_cost']:.6f}, max|u - u_direct| = {np.abs(ic.u - dd.u).max():.2e} m/s^2")
    lqr = SeedOcpConfig(kp=1.0, kd=np.sqrt(2.0))
    xl, ul = pd_rollout(lqr)
    cl = seed_cost(xl, ul, lqr)
    print(f"PD-gain sensitivity (Kp=1, Kd=sqrt 2, LQR of the seed weights): J_PD = {cl['total']:.4f}, det mean {cl['det_mean']:.4f}, "
          f"final speed {np.linalg.norm(xl[-1, 3:]):.2f} m/s  (default PD: final speed {np.linalg.norm(xp[-1, 3:]):.2f} m/s)")


def bench_pointmass() -> None:
    from uwbimu.design.trajectory.pointmass import PointMassPlanConfig, plan_point_mass

    base = dict(
        beacons=[[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0.5]], x0=[1, 1, 1, 0, 0, 0], goal=[9, 9, 2],
        goal_velocity=[0, 0, 0], tf=10.0, n_steps=100, box_min=[0, 0, 0.5], box_max=[10, 10, 5],
        obstacles=[{"kind": "sphere", "center": [5, 5, 1.5], "radius": 1.5}, {"kind": "box", "center": [3, 7, 2], "half_size": [1, 1, 2]}],
        v_max=2.0, a_max=2.0, w_info=1.0,
    )  # fmt: skip
    print("\n== 2. point-mass planner (4 beacons, 2 obstacles, box, |v|<=2, |a|<=2, rest-to-rest, N=100) ==")
    for obj, plat in ((o, p) for p in ("handheld", "multirotor") for o in ("none", "logdet", "min_eig", "trace_inv")):
        r = plan_point_mass(PointMassPlanConfig(objective=obj, platform=plat, **base))
        m = r.metrics
        print(f"  {plat:10s} {obj:9s}: {r.status:22s} solve {r.solve_time_s:.2f} s, logdet {m['logdet']:.3f}, min_eig {m['min_eig']:.1f}, "
              f"trace_inv {m['trace_inv']:.3e}, effort {m['control_effort']:.3f}, max violation {max(r.constraint_violation.values()):.1e}")


def bench_calibration() -> None:
    from uwbimu.design.trajectory.calibration import CalibrationDesignConfig, evaluate_maneuver, evaluate_sim_trajectory, naive_figure8
    from uwbimu.estimation import run_eskf
    from uwbimu.sim import builtin_scenario, simulate

    cfg = CalibrationDesignConfig()
    m = naive_figure8(cfg)
    evaluate_maneuver(m, cfg)
    t = []
    for _ in range(10):
        t0 = time.perf_counter()
        evaluate_maneuver(m, cfg)
        t.append(time.perf_counter() - t0)
    print("\n== 3. calibration design ==")
    print(f"one candidate evaluation (40 s, 2000 ranges, 19-state covariance): {statistics.median(t) * 1e3:.1f} ms")
    sc = builtin_scenario("calibration-flight")
    c60 = CalibrationDesignConfig(platform="handheld", duration=sc.duration, truth={"lever_arm": list(sc.lever_arm), "time_offset": sc.time_offset})
    pred = evaluate_sim_trajectory(sc.trajectory.build(), c60)
    res = run_eskf(simulate(sc))
    cal = res.calibration
    print("predictor vs ESKF reported sd on builtin 'calibration-flight' (60 s):")
    print(f"  lever arm sd [mm]: predicted {np.round(1e3 * np.array(pred['sigma_lever_arm_m']), 2)}, ESKF {np.round(1e3 * np.array(cal['lever_arm_sd']), 2)}")
    print(f"  time offset sd [ms]: predicted {1e3 * pred['sigma_time_offset_s']:.3f}, ESKF {1e3 * cal['time_offset_sd']:.3f}")


def bench_proof(config: str, seeds: int, workers: int, out: str) -> None:
    import yaml

    from uwbimu.design.trajectory.calibration import CalibrationDesignConfig, design_and_write
    from uwbimu.design.trajectory.proof import run_proof

    cfg = CalibrationDesignConfig.model_validate(yaml.safe_load(Path(config).read_text()) or {})
    out = Path(out)
    t0 = time.perf_counter()
    rep = design_and_write(cfg, out / "design")
    print(f"\n== 4. proof: designed in {time.perf_counter() - t0:.1f} s ({rep['n_evals']} evaluations) ==")
    for k in ("figure8", "figure8_excited"):
        print(f"  predicted sigma ratio {k}/designed: {rep[f'predicted_ratio_{k}_over_designed']}")
    print("  peak / bound on the flown splines (same duration, box, speed, accel, tilt, rate):")
    for k in ("designed", "figure8", "figure8_excited"):
        print(f"    {k:16s} " + ", ".join(f"{q} {v:.3f}" for q, v in rep[f"{k}_flown"]["bound_usage"].items()))
    s = run_proof(out / "design", seeds, workers, out / "proof")
    print(json.dumps(s, indent=2))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--proof", action="store_true", help="also run the Monte Carlo proof (minutes)")
    ap.add_argument("--config", default=str(ROOT / "examples" / "plan" / "calibration.yaml"))
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", default="out/bench_plan")
    ap.add_argument("--skip", nargs="*", default=[], choices=["seed", "pointmass", "calibration"])
    a = ap.parse_args(argv)
    if "seed" not in a.skip:
        bench_seed(a.repeats)
    if "pointmass" not in a.skip:
        bench_pointmass()
    if "calibration" not in a.skip:
        bench_calibration()
    if a.proof:
        bench_proof(a.config, a.seeds, a.workers, a.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
