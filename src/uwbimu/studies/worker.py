"""One task of a study, run on a worker: simulate a scenario for a chunk of seeds, run every
estimator (looked up in the estimator registry), score each run.
"""

from __future__ import annotations

import copy
import time

import numpy as np

from uwbimu.metrics.filter import _truth_at, run_metrics  # noqa: F401 (run_metrics: public here too)
from uwbimu.studies.config import run_seeds

# --------------------------------------------------------------------------
# One run (executed on workers)
# --------------------------------------------------------------------------
def _surveyed_start(entry: dict, ds, seed_init: int):
    """True initial position plus N(0, sd^2) per axis (the run's init seed), or None."""
    sd = entry.get("initial_position_sd")
    if not sd:
        return None, None
    rng = np.random.default_rng(np.random.SeedSequence([int(seed_init), 0x9E5]))
    p0 = ds.groundtruth[["px", "py", "pz"]].to_numpy(float)[0] + rng.normal(size=3) * float(sd)
    return p0, float(sd)


def _estimate(entry: dict, ds, seed_init: int):
    opts = copy.deepcopy(entry["options"])
    p0, sd = _surveyed_start(entry, ds, seed_init)
    if entry["kind"] == "pointmass":
        if p0 is not None:
            opts.setdefault("initial_position", p0.tolist())
            opts.setdefault("initial_position_sd", sd)
        opts.setdefault("full_covariance", True)
    if p0 is not None and entry["kind"] == "eskf":
        from uwbimu.studies.eskf_fix import run_eskf_from_fix

        return run_eskf_from_fix(ds, opts, p0, sd)
    from uwbimu.estimators import get_estimator

    est = get_estimator(entry["kind"])
    return est.run(ds, est.options(opts), None)


def run_chunk(task: dict) -> dict:
    """Quiet wrapper of :func:`_run_chunk`: per-run warnings are counted in the rows
    (``n_warnings``) instead of flooding the console from every worker (the estimators
    return their warnings; Python ``warnings`` raised inside a run are suppressed here only)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return _run_chunk(task)


def _run_chunk(task: dict) -> dict:
    """Simulate and estimate the runs of one task (a scenario x a chunk of run indices).

    ``task``: ``scenario_name``, ``scenario`` (resolved dict), ``runs`` (list of
    ints), ``estimators`` (list of EstimatorEntry dicts), ``seed_base``,
    ``skip_initial_s``, ``trace_rate_hz``.  A run whose simulation or
    estimation raises becomes a ``status="failed"`` row carrying the message;
    nothing is dropped.  Returns ``{"rows": [...], "traces": {...}}``.
    """
    from uwbimu.sim import Scenario, simulate

    names = [e["name"] for e in task["estimators"]]
    rows: list[dict] = []
    dur = float(task["scenario"].get("duration") or 0.0)
    grid = np.arange(0.0, dur + 1e-9, 1.0 / float(task["trace_rate_hz"])) if dur > 0 else np.zeros(0)
    R, E, T = len(task["runs"]), len(names), len(grid)
    tr_err = np.full((R, E, T, 3), np.nan)
    tr_sd = np.full((R, E, T, 3), np.nan)
    tr_nees = np.full((R, E, T), np.nan)
    tr_truth = np.full((R, T, 3), np.nan)  # true position on the grid (for estimate-vs-truth plots)
    tr_div = np.zeros((R, E, T), bool)  # a divergence event in the grid cell (marked in the figures)
    for ri, run in enumerate(task["runs"]):
        st, sn, si = run_seeds(task["seed_base"], run)
        base = {"scenario": task["scenario_name"], "run": int(run), "seed_truth": st, "seed_noise": sn,
                "seed_init": si}
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            sc = Scenario.model_validate({**task["scenario"], "seeds": {"truth": st, "noise": sn, "init": si}})
            ds = simulate(sc)
            sim_err = None
        except Exception as exc:  # recorded per run, never silently dropped
            ds, sim_err = None, f"simulate: {type(exc).__name__}: {exc}"
        sim_s, sim_cpu = time.perf_counter() - t0, time.process_time() - c0
        if ds is not None and T:
            gt_t = ds.groundtruth["t"].to_numpy(float)
            inside_gt = grid <= gt_t[-1] - gt_t[0]
            tr_truth[ri, inside_gt] = _truth_at(ds, gt_t[0] + grid[inside_gt])
        for ei, est in enumerate(task["estimators"]):
            row = {**base, "estimator": est["name"], "sim_s": sim_s, "sim_cpu_s": sim_cpu, "status": "ok", "error": ""}
            if ds is None:
                row.update(status="failed", error=sim_err, est_s=np.nan)
                rows.append(row)
                continue
            t1, c1 = time.perf_counter(), time.process_time()
            try:
                result = _estimate(est, ds, si)
                row["est_s"] = time.perf_counter() - t1
                row["est_cpu_s"] = time.process_time() - c1
                fields, trace = run_metrics(result, ds, float(task["skip_initial_s"]))
                row.update(fields)
                if T and len(trace["t"]):
                    tt = trace["t"] - float(ds.groundtruth["t"].iloc[0])
                    inside = (grid >= tt[0]) & (grid <= tt[-1])
                    for a in range(3):
                        tr_err[ri, ei, inside, a] = np.interp(grid[inside], tt, trace["err"][:, a])
                        tr_sd[ri, ei, inside, a] = np.interp(grid[inside], tt, trace["sd"][:, a])
                    tr_nees[ri, ei, inside] = np.interp(grid[inside], tt, trace["nees"])
                dv = trace.get("divergence_t", np.zeros(0)) - float(ds.groundtruth["t"].iloc[0])
                if T and len(dv):
                    tr_div[ri, ei, np.clip(np.rint(dv * float(task["trace_rate_hz"])).astype(int), 0, T - 1)] = True
            except Exception as exc:
                row.update(status="failed", error=f"{type(exc).__name__}: {exc}", est_s=time.perf_counter() - t1,
                           est_cpu_s=time.process_time() - c1)
            rows.append(row)
    return {
        "scenario": task["scenario_name"],
        "runs": [int(r) for r in task["runs"]],
        "rows": rows,
        "traces": {"t": grid, "err": tr_err, "sd": tr_sd, "nees": tr_nees, "truth": tr_truth,
                   "divergence": tr_div, "estimators": np.array(names)},
    }
