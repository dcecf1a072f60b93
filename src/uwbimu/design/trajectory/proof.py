"""Monte Carlo proof of a calibration design: ESKF calibration on simulated flights.

For each seed, both scenarios written by :func:`.calibration.design_and_write`
(designed manoeuvre, naive figure-8 and, when present, the figure-8 with
attitude excitation at the bounds; same duration, bounds, sensors, anchors,
lever arm and time offset) are simulated with that noise seed and
calibrated by :func:`uwbimu.estimation.run_eskf`.  The estimator sees no truth:
the dataset is handed over *without* its ground-truth table and without
``meta.truth`` (the simulator writes no nominal lever arm for the tag), and the
lever-arm prior is explicitly zero with sd 0.3 m (the ESKF's default); the
time offset starts from the ESKF's own grid search (prior sd 0.03 s around the
best grid point).  Reported: final lever-arm and time-offset errors per
run, their RMSE over seeds for each trajectory, and the ratios
figure-8 / designed.

Run: ``python -m uwbimu.design.trajectory.proof DESIGN_DIR --seeds 50 --out OUT``
(``DESIGN_DIR`` from ``uwbimu plan calibration``), or
``python benchmarks/bench_plan.py --proof``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any, Optional

import numpy as np

TRAJS = ("designed", "figure8", "figure8_excited")  # the last one only when its scenario exists


def _eskf_options(lever_prior_sd: float = 0.3):
    from uwbimu.estimation import EskfOptions

    return EskfOptions.model_validate({"lever_arm": {"prior": [0.0, 0.0, 0.0], "prior_sd": lever_prior_sd}})


def blind(ds):
    """The dataset as a real flight would give it: no ground-truth table, no ``meta.truth``,
    no nominal lever arm of the tags (the truth stays with the caller)."""
    from dataclasses import replace

    tags = [t.model_copy(update={"lever_arm": None}) for t in ds.meta.tags]
    return replace(ds, groundtruth=None, meta=ds.meta.model_copy(update={"truth": None, "tags": tags}))


def run_one(scenario_file: str, seed: int, lever_prior_sd: float = 0.3) -> dict[str, Any]:
    """Simulate one flight with noise seed ``seed`` and calibrate it with the ESKF."""
    from uwbimu.estimation import run_eskf
    from uwbimu.sim import load_scenario, simulate

    sc = load_scenario(scenario_file)
    sc = sc.model_copy(update={"seeds": sc.seeds.model_copy(update={"noise": 1000 + seed, "init": 5000 + seed})})
    t0 = time.perf_counter()
    ds = blind(simulate(sc))
    res = run_eskf(ds, _eskf_options(lever_prior_sd))
    cal = res.calibration
    lever_true = np.asarray(sc.lever_arm, dtype=float)
    e_l = np.asarray(cal["lever_arm"], dtype=float) - lever_true
    e_t = float(cal["time_offset"]) - sc.time_offset
    return {
        "scenario": Path(scenario_file).stem,
        "seed": seed,
        "lever_err_x": e_l[0],
        "lever_err_y": e_l[1],
        "lever_err_z": e_l[2],
        "lever_err_norm": float(np.linalg.norm(e_l)),
        "td_err": e_t,
        "lever_sd_x": cal["lever_arm_sd"][0],
        "lever_sd_y": cal["lever_arm_sd"][1],
        "lever_sd_z": cal["lever_arm_sd"][2],
        "td_sd": cal["time_offset_sd"],
        "n_warnings": len(res.warnings),
        "runtime_s": time.perf_counter() - t0,
    }


def _job(task):
    """One Monte Carlo task ``(index, scenario_file, seed)`` -> ``(index, row)`` (picklable)."""
    i, scenario_file, seed = task
    return i, run_one(scenario_file, seed)


def summarise(df) -> dict[str, Any]:
    """RMSE per trajectory and the figure-8 / designed ratios."""
    out: dict[str, Any] = {}
    for name in TRAJS:
        d = df[df["scenario"] == f"{name}_scenario"]
        if len(d) == 0:
            continue
        out[name] = {
            "n_runs": int(len(d)),
            "lever_arm_rmse_m": float(np.sqrt(np.mean(d["lever_err_norm"] ** 2))),
            "lever_arm_rmse_xyz_m": [float(np.sqrt(np.mean(d[f"lever_err_{c}"] ** 2))) for c in "xyz"],
            "time_offset_rmse_s": float(np.sqrt(np.mean(d["td_err"] ** 2))),
            "lever_arm_mean_sd_m": [float(d[f"lever_sd_{c}"].mean()) for c in "xyz"],
            "time_offset_mean_sd_s": float(d["td_sd"].mean()),
            "mean_runtime_s": float(d["runtime_s"].mean()),
        }
    for base in TRAJS[1:]:
        if base in out and "designed" in out:
            out[f"ratio_{base}_over_designed"] = {
                "lever_arm_rmse": out[base]["lever_arm_rmse_m"] / out["designed"]["lever_arm_rmse_m"],
                "time_offset_rmse": out[base]["time_offset_rmse_s"] / out["designed"]["time_offset_rmse_s"],
            }
    return out


def run_proof(design_dir: str | Path, n_seeds: int = 50, workers: int = 1, out: Optional[str | Path] = None, progress=None) -> dict[str, Any]:
    """Monte Carlo over ``n_seeds`` noise seeds for both scenarios of a design folder.

    Returns the summary (and writes ``proof_runs.csv``, ``proof.json`` and a
    histogram figure into ``out`` when given).
    """
    import pandas as pd

    design_dir = Path(design_dir)
    files = {n: design_dir / f"{n}_scenario.yaml" for n in TRAJS}
    for n in TRAJS[:2]:
        if not files[n].is_file():
            raise FileNotFoundError(f"{files[n]}: missing (run `uwbimu plan calibration` first)")
    names = [n for n in TRAJS if files[n].is_file()]
    jobs = [(i, str(files[n]), s) for i, (s, n) in enumerate((s, n) for s in range(n_seeds) for n in names)]
    t0 = time.perf_counter()
    from uwbimu.parallel import execute

    done: dict[int, dict[str, Any]] = {}

    def collect(result) -> None:
        i, row = result
        done[i] = row
        if progress:
            progress(len(done), len(jobs))

    failed = execute(_job, jobs, collect, workers=max(1, int(workers)),
                     describe=lambda j: f"{Path(j[1]).stem} seed {j[2]}")
    if failed:
        from uwbimu.errors import EstimationError

        raise EstimationError(f"{len(failed)} proof run(s) did not finish: " + "; ".join(failed[:3]))
    rows = [done[i] for i in range(len(jobs))]  # seed-major job order, whatever order they finished in
    df = pd.DataFrame(rows)
    summary = summarise(df)
    summary["n_seeds"] = n_seeds
    summary["wall_time_s"] = time.perf_counter() - t0
    summary["design_dir"] = str(design_dir)
    if out is not None:
        from uwbimu.io.atomic import save_figure, write_csv, write_json

        out = Path(out)
        write_csv(out / "proof_runs.csv", df, float_format="%.9g")
        write_json(out / "proof.json", summary)
        save_figure(out / "proof_errors.png", _figure(df))
    return summary


def _figure(df):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 3.8))
    for k, (col, scale, lab) in enumerate((("lever_err_norm", 1e3, "lever-arm error norm [mm]"), ("td_err", 1e3, "time-offset error [ms]"))):
        ax = fig.add_subplot(1, 2, k + 1)
        for name, c in zip(TRAJS, ("tab:red", "tab:blue", "tab:gray")):
            d = df[df["scenario"] == f"{name}_scenario"][col] * scale
            ax.hist(d, bins=20, alpha=0.6, color=c, label=f"{name} (RMSE {np.sqrt(np.mean(d**2)):.2f})")
        ax.set_xlabel(lab)
        ax.legend(fontsize=8)
    return fig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Monte Carlo proof of a calibration manoeuvre design (ESKF).")
    ap.add_argument("design_dir", help="folder written by `uwbimu plan calibration`")
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--out", default=None, help="output folder (default: DESIGN_DIR/proof)")
    a = ap.parse_args(argv)
    out = a.out or str(Path(a.design_dir) / "proof")

    def prog(i, n):
        if i % 10 == 0 or i == n:
            print(f"  {i}/{n} runs", flush=True)

    s = run_proof(a.design_dir, a.seeds, a.workers, out, progress=prog)
    import json

    print(json.dumps(s, indent=2))
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
