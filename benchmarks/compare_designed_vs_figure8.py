"""Designed multirotor calibration manoeuvre vs the excited figure-8 of the same platform (issue 16 item 2).

1. Design with ``uwbimu plan calibration`` defaults (``examples/plan/calibration.yaml``:
   platform ``multirotor``, flat attitude, thrust / tilt / rate / yaw-rate limits), with
   ``--duration`` overriding the flight length; the design writes the designed manoeuvre and
   the figure-8 with its yaw excitation grown to the same limits (``figure8_excited``), both
   flown by the simulator with the flat attitude (``attitude: flat``).
2. Each is simulated with ``--seeds`` noise seeds and calibrated blind by
   :func:`uwbimu.run_eskf` (default options, lever-arm prior 0 +- 0.3 m, t_d from the ESKF's
   grid search: :func:`uwbimu.design.trajectory.proof.run_one`), in a process pool.
3. Per seed, the posterior Cramer-Rao bound of the lever arm and t_d
   (:func:`uwbimu.estimation.crlb.posterior_crlb`, Jacobians at the truth, the data-start
   priors of ``benchmarks/bench_eskf_crlb.py --data-start``).

Prints and writes (``--out``, default ``out/compare_designed_vs_figure8``): RMS error, mean
reported sd and sqrt(mean CRLB) per lever-arm axis and t_d for both trajectories, the ratio
figure-8 / designed of the RMS errors and the ratio RMS error / CRLB.  Usage::

    PYTHONPATH=src python benchmarks/compare_designed_vs_figure8.py [--seeds 50] [--duration 40] [--workers N]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench_eskf_crlb, also in the pool's workers
NAMES = ["lever_x", "lever_y", "lever_z", "t_d"]
TRAJS = ("designed", "figure8_excited")


def crlb_sd(scenario_file: str, seed: int) -> np.ndarray:
    """sqrt of the posterior CRLB diagonal (lever arm x, y, z [m], t_d [s]) for one noise seed."""
    from uwbimu.estimation import EskfOptions
    from uwbimu.estimation.crlb import posterior_crlb
    from uwbimu.estimation.eskf import build_problem
    from uwbimu.sim import load_scenario, simulate_full

    sc = load_scenario(scenario_file)
    sc = sc.model_copy(update={"seeds": sc.seeds.model_copy(update={"noise": 1000 + seed, "init": 5000 + seed})})
    from bench_eskf_crlb import truth_states  # benchmarks/ (this script's folder)

    sim = simulate_full(sc)
    ds = sim.dataset
    X = truth_states(sim)
    td = ds.meta.truth.time_offset
    k0 = int(np.searchsorted(ds.imu_t, ds.uwb["t"].iloc[0] + td))
    opts = EskfOptions(store_covariance=False)
    n = ds.meta.imu_noise
    g = np.asarray(opts.init.td_grid)
    sd0 = np.r_[np.full(3, 0.1), np.full(3, 0.1), np.radians([2.0, 2.0, 5.0]), np.full(3, n.accel_bias_sigma0),
                np.full(3, n.gyro_bias_sigma0), np.full(3, opts.lever_arm.prior_sd), (g.max() - g.min()) / np.sqrt(12.0)]
    prob, _ = build_problem(ds, opts)
    P = posterior_crlb(prob, X, np.diag(sd0**2), k0)
    return np.sqrt(np.diag(P)[15:19])


def job(args) -> dict:
    from uwbimu.design.trajectory.proof import run_one

    scenario_file, seed, name = args
    r = run_one(scenario_file, seed)
    c = crlb_sd(scenario_file, seed)
    return {"trajectory": name, "seed": seed,
            "err": [r["lever_err_x"], r["lever_err_y"], r["lever_err_z"], r["td_err"]],
            "sd": [r["lever_sd_x"], r["lever_sd_y"], r["lever_sd_z"], r["td_sd"]], "crlb": c.tolist(),
            "runtime_s": r["runtime_s"]}


def summarise(rows: list[dict]) -> dict:
    out: dict = {}
    for name in TRAJS:
        rr = [r for r in rows if r["trajectory"] == name]
        E, S, C = (np.array([r[k] for r in rr]) for k in ("err", "sd", "crlb"))
        rms, crlb = np.sqrt(np.mean(E**2, axis=0)), np.sqrt(np.mean(C**2, axis=0))
        out[name] = {"n_runs": len(rr), "rms_error": rms.tolist(), "mean_sd": S.mean(axis=0).tolist(),
                     "crlb": crlb.tolist(), "rms_over_crlb": (rms / crlb).tolist(),
                     "rms_error_lever_norm": float(np.sqrt(np.mean(np.sum(E[:, :3] ** 2, axis=1))))}
    d, f = out["designed"], out["figure8_excited"]
    out["ratio_designed_over_figure8"] = {
        "rms_error": (np.array(d["rms_error"]) / np.array(f["rms_error"])).tolist(),
        "rms_error_lever_norm": d["rms_error_lever_norm"] / f["rms_error_lever_norm"],
    }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--duration", type=float, default=40.0, help="flight length [s] (both trajectories)")
    ap.add_argument("--workers", type=int, default=os.cpu_count() or 1)
    ap.add_argument("--config", default=str(ROOT / "examples/plan/calibration.yaml"))
    ap.add_argument("--out", default="out/compare_designed_vs_figure8")
    a = ap.parse_args()

    from uwbimu.design.trajectory.calibration import CalibrationDesignConfig, design_and_write

    out = Path(a.out)
    cfg = CalibrationDesignConfig.model_validate({**yaml.safe_load(Path(a.config).read_text()), "duration": a.duration})
    t0 = time.perf_counter()
    rep = design_and_write(cfg, out / "design")
    t_design = time.perf_counter() - t0
    print(f"design: platform {cfg.platform}, {cfg.duration:g} s, {rep['n_evals']} evaluations, {t_design:.0f} s")
    for name in TRAJS:
        fl = rep[f"{name}_flown"]
        print(f"  {name}: bound usage " + ", ".join(f"{k} {v:.2f}" for k, v in fl["bound_usage"].items())
              + f"; limit violations: {fl.get('limit_violations') or 'none'}")
    jobs = [(str(out / "design" / f"{n}_scenario.yaml"), s, n) for s in range(a.seeds) for n in TRAJS]
    t1 = time.perf_counter()
    with ProcessPoolExecutor(max_workers=a.workers) as ex:
        rows = list(ex.map(job, jobs))
    t_mc = time.perf_counter() - t1
    s = summarise(rows)
    s |= {"n_seeds": a.seeds, "duration_s": a.duration, "design_time_s": t_design, "monte_carlo_wall_s": t_mc,
          "workers": a.workers, "predicted": {n: {"sigma_lever_arm_m": rep[f"{n}_flown"]["sigma_lever_arm_m"],
                                                   "sigma_time_offset_s": rep[f"{n}_flown"]["sigma_time_offset_s"]} for n in TRAJS},
          "bound_usage": {n: rep[f"{n}_flown"]["bound_usage"] for n in TRAJS}}
    (out / "compare.json").write_text(json.dumps(s, indent=2))
    print(f"\n{a.seeds} seeds x {len(TRAJS)} trajectories, {a.duration:g} s flights, {t_mc:.0f} s wall ({a.workers} workers)")
    print(f"{'trajectory':16s} {'state':8s} {'RMS err':>9s} {'mean sd':>9s} {'CRLB':>9s} {'RMS/CRLB':>8s}")
    for name in TRAJS:
        r = s[name]
        for i, n in enumerate(NAMES):
            u = "ms" if n == "t_d" else "mm"
            print(f"{name:16s} {n:8s} {1e3 * r['rms_error'][i]:7.2f}{u} {1e3 * r['mean_sd'][i]:7.2f}{u} "
                  f"{1e3 * r['crlb'][i]:7.2f}{u} {r['rms_over_crlb'][i]:8.2f}")
    rat = s["ratio_designed_over_figure8"]
    print("designed / figure-8 RMS error: " + ", ".join(f"{n} {v:.2f}" for n, v in zip(NAMES, rat["rms_error"]))
          + f"; lever-arm norm {rat['rms_error_lever_norm']:.2f}")
    print(f"wrote {out / 'compare.json'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
