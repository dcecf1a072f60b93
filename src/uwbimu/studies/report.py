"""Monte Carlo outputs: merged table, per-cell aggregates and plots.

Reads the chunk files of a study folder (see :mod:`uwbimu.studies.store`) and
writes ``montecarlo.csv``, ``summary.json`` and the figures:

* ``rmse_distribution.png`` — per-axis position RMSE of every run, box plots
  per scenario x estimator;
* ``nees.png`` — position NEES averaged over the runs alive at each time,
  with the two-sided 95% chi-square band for that many runs (3 dof each),
  the number of runs alive (dotted, right axis) and divergences (red ticks),
  per scenario x estimator;
* ``position_vs_truth.png`` — estimated and true position per axis against
  time for the first run, one column per scenario, every estimator (the seed's
  figure 2);
* ``error_vs_time_<estimator>.png`` — position error per axis against time,
  one column per scenario (median, 5-95% band, first run and the 2-sigma
  envelope; the seed's figure 3), and below them the number of runs alive
  at each time with the divergences marked: a run whose estimator stopped
  is NaN from then on, so the bands describe the survivors only.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from uwbimu.studies.config import ROW_COLUMNS
from uwbimu.studies.store import chunk_files, read_done

AXES = ("x", "y", "z")


def _nanstats(x: np.ndarray) -> dict[str, Any]:
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if not len(x):
        return {"n": 0}
    return {
        "n": int(len(x)),
        "mean": float(np.mean(x)),
        "median": float(np.median(x)),
        "std": float(np.std(x, ddof=1)) if len(x) > 1 else 0.0,
        "p05": float(np.percentile(x, 5)),
        "p95": float(np.percentile(x, 95)),
        "max": float(np.max(x)),
    }


def _rms_se(v: np.ndarray) -> tuple:
    """RMS of the finite values and its standard error ``sd(v^2) / (2 RMS sqrt(n))`` (None, None if empty)."""
    v = np.asarray(v, float)
    v = v[np.isfinite(v)]
    if not len(v):
        return None, None
    rms = float(np.sqrt(np.mean(v**2)))
    se = float(np.std(v**2, ddof=1) / (2 * rms * np.sqrt(len(v)))) if len(v) > 1 and rms > 0 else None
    return rms, se


def summarize(df: pd.DataFrame, cfg, runs: int, traces: dict | None = None, bounds: dict | None = None) -> dict:
    """Aggregates per scenario x estimator (means, medians, percentiles).

    Every estimated quantity is reported per cell: position RMSE per axis, lever-arm error per
    axis and time-offset error (``*_rms_all_runs``: RMS over runs), with ``runs_diverged`` and the
    fewest runs still alive (``runs_alive_min``; bands are over those).  ``bounds`` (scenario ->
    :func:`uwbimu.studies.crlb.scenario_bound`) adds ``crlb`` and ``ratio_to_crlb``.
    """
    from scipy import stats

    cells = []
    for sc in cfg.scenarios:
        for est in cfg.estimators:
            d = df[(df["scenario"] == sc.name) & (df["estimator"] == est.name)]
            ok = d[d["status"] == "ok"]
            cell: dict[str, Any] = {
                "scenario": sc.name,
                "estimator": est.name,
                "kind": est.kind,
                "runs": int(len(d)),
                "failed": int((d["status"] != "ok").sum()),
                "failure_messages": sorted(set(d.loc[d["status"] != "ok", "error"].astype(str)))[:5],
            }
            for c in ("rmse_x", "rmse_y", "rmse_z", "rmse_3d", "max_err_3d", "nees_pos_mean", "lever_arm_err",
                      "lever_arm_err_x", "lever_arm_err_y", "lever_arm_err_z", "time_offset_err", "ranges_accepted",
                      "coverage", "divergences", "sim_s", "est_s"):
                cell[c] = _nanstats(ok[c].to_numpy(float)) if c in ok else {"n": 0}
            # runs whose estimate stops before the end of the flight: their RMSE covers less time
            cov = ok["coverage"].to_numpy(float) if "coverage" in ok else np.zeros(0)
            cell["runs_truncated"] = int(np.sum(cov < 0.98))
            # RMS over runs of the per-run RMSE: the "per-axis RMSE over all seeds".
            for a in AXES:
                cell[f"rmse_{a}_all_runs"], cell[f"rmse_{a}_all_runs_se"] = _rms_se(ok[f"rmse_{a}"].to_numpy(float))
            # every estimated calibration quantity: RMS over runs of the final error (None: not estimated),
            # with the standard error of that RMS from the spread over runs (delta method)
            m2 = np.sum([ok[f"rmse_{a}"].to_numpy(float) ** 2 for a in AXES], axis=0) if len(ok) else np.zeros(0)
            cell["rmse_3d_all_runs"], cell["rmse_3d_all_runs_se"] = _rms_se(np.sqrt(m2))
            for c in ("lever_arm_err_x", "lever_arm_err_y", "lever_arm_err_z", "time_offset_err"):
                v = ok[c].to_numpy(float) if c in ok else np.zeros(0)
                cell[f"{c}_rms_all_runs"], cell[f"{c}_rms_all_runs_se"] = _rms_se(v)
            cell["runs_diverged"] = int(np.sum(ok["divergences"].to_numpy(float) > 0)) if "divergences" in ok else 0
            cell["nees_kind"] = sorted(set(ok["nees_kind"].dropna().astype(str)))
            if traces is not None and traces.get(sc.name) is not None and est.name in traces[sc.name]["estimators"]:
                k = traces[sc.name]["estimators"].index(est.name)
                nees_t = traces[sc.name]["nees"][:, k, :]
                n_t = np.sum(np.isfinite(nees_t), axis=0)
                valid = n_t > 0
                if np.any(valid):
                    avg = np.nansum(np.where(np.isfinite(nees_t), nees_t, 0.0), axis=0)[valid] / n_t[valid]
                    lo = stats.chi2.ppf(0.025, 3 * n_t[valid]) / n_t[valid]
                    hi = stats.chi2.ppf(0.975, 3 * n_t[valid]) / n_t[valid]
                    # Bar-Shalom test: the NEES averaged over independent runs at each
                    # time lies in the two-sided 95% band of chi2(3 N)/N at ~95% of times.
                    cell["nees_time_steps_within_95pct_band"] = float(np.mean((avg > lo) & (avg < hi)))
                    cell["nees_time_steps_above_band"] = float(np.mean(avg >= hi))
                # survivorship: error bands and NEES are over the runs still producing estimates
                alive = alive_counts(np.isfinite(nees_t))
                cell["runs_alive_max"] = int(np.max(alive))
                cell["runs_alive_min"] = int(np.min(alive[int(np.argmax(alive == np.max(alive))):]))
                cell["runs_alive_end"] = int(alive[-1])
            cells.append(cell)
    if bounds:
        for cell in cells:
            b = bounds.get(cell["scenario"])
            if b is None:
                continue
            cell["crlb"] = b
            ratios, ratio_se = {}, {}
            pairs = [(f"rmse_{a}", f"rmse_{a}_all_runs", f"rmse_{a}") for a in (*AXES, "3d")]
            pairs += [(f"lever_arm_err_{a}", f"lever_arm_err_{a}_rms_all_runs", f"lever_arm_sd_{a}") for a in AXES]
            pairs += [("time_offset_err", "time_offset_err_rms_all_runs", "time_offset_sd")]
            for name, key, bkey in pairs:
                if cell.get(key) is not None and b.get(bkey):
                    ratios[name] = cell[key] / b[bkey]
                    if cell.get(f"{key}_se") is not None:  # sampling uncertainty of the ratio
                        ratio_se[name] = cell[f"{key}_se"] / b[bkey]
            cell["ratio_to_crlb"], cell["ratio_to_crlb_se"] = ratios, ratio_se
    return {"name": cfg.name, "description": cfg.description, "runs_per_scenario": runs,
            "seed_base": cfg.seed_base, "skip_initial_s": cfg.skip_initial_s, "cells": cells}


def load_traces(out: Path, scenario: str, runs: int) -> dict | None:
    """Concatenate the trace files of one scenario (runs ``< runs``), sorted by run."""
    files = chunk_files(out, "npz", scenario)
    parts = []
    for f in files:
        with np.load(f, allow_pickle=False) as z:
            parts.append({k: z[k] for k in z.files})
    if not parts:
        return None
    runs_all = np.concatenate([p["runs"] for p in parts])
    order = np.argsort(runs_all, kind="stable")
    _, first = np.unique(runs_all[order], return_index=True)  # one trace per run
    order = order[first]
    idx = order[runs_all[order] < runs]
    keys = ["err", "sd", "nees"] + [k for k in ("truth", "divergence") if all(k in p for p in parts)]
    cat = {k: np.concatenate([p[k] for p in parts], axis=0)[idx] for k in keys}
    cat["t"] = parts[0]["t"]
    cat["estimators"] = [str(x) for x in parts[0]["estimators"]]
    cat["runs"] = runs_all[idx]
    return cat


def finalize(out: Path, cfg, runs: int, plots: bool = True) -> dict:
    """Merge chunks into ``montecarlo.csv``, aggregate, plot; return the summary."""
    from uwbimu.io.atomic import write_csv

    df = read_done(out)
    df = df[df["run"].astype(int) < runs] if len(df) else df
    df = df.reindex(columns=ROW_COLUMNS)
    if len(df):
        df = df.sort_values(["scenario", "run", "estimator"], kind="stable").reset_index(drop=True)
    write_csv(out / "montecarlo.csv", df, float_format="%.17g")
    traces = {s.name: load_traces(out, s.name, runs) for s in cfg.scenarios}
    bounds = study_bounds(out, cfg) if getattr(cfg, "crlb", False) else None
    summary = summarize(df, cfg, runs, traces, bounds)
    if plots and len(df):
        summary["figures"] = make_plots(out, df, cfg, runs, traces)
    return summary


def study_bounds(out: Path, cfg) -> dict:
    """Posterior CRLB of every scenario (run 0's seeds), cached in ``OUT/crlb.json``."""
    import json

    from uwbimu.studies.config import resolved_study, run_seeds
    from uwbimu.studies.crlb import scenario_bound
    from uwbimu.io.atomic import write_json

    study = resolved_study(cfg)
    cache = out / "crlb.json"
    old = json.loads(cache.read_text()) if cache.is_file() else {}
    bounds = {}
    for sc in study["scenarios"]:
        key = json.dumps(sc["scenario"], sort_keys=True)
        if old.get(sc["name"], {}).get("key") == key:
            bounds[sc["name"]] = old[sc["name"]]["bound"]
        else:
            bounds[sc["name"]] = scenario_bound(sc["scenario"], run_seeds(cfg.seed_base, 0), cfg.skip_initial_s)
    write_json(cache, {n: {"key": json.dumps(s["scenario"], sort_keys=True), "bound": bounds[n]}
                       for n, s in zip(bounds, study["scenarios"])})
    return bounds


def alive_counts(valid: np.ndarray) -> np.ndarray:
    """Runs alive at each grid time: between a run's first and last finite estimate (plus one grid
    step, so that an output rate not aligned with the grid does not read as a loss).  ``valid`` is
    (R, T) bool; returns (T,) ints."""
    valid = np.asarray(valid, bool)
    R, T = valid.shape
    idx = np.arange(T)
    out = np.zeros(T, int)
    for r in range(R):
        f = np.flatnonzero(valid[r])
        if len(f):
            out += (idx >= f[0]) & (idx <= f[-1] + 1)
    return out


def _mark_divergences(ax, tr: dict, k: int, label: bool = False) -> None:
    """Red vertical ticks at the grid times where any run's estimator declared a divergence."""
    if "divergence" not in tr:
        return
    hits = np.flatnonzero(np.any(tr["divergence"][:, k, :], axis=0))
    for n, i in enumerate(hits):
        ax.axvline(tr["t"][i], color="r", lw=0.6, alpha=0.6,
                   label=(f"divergence ({int(tr['divergence'][:, k, :].sum())} events)" if label and n == 0 else None))
    if label and len(hits):
        ax.legend(fontsize=7, loc="lower left")


def make_plots(out: Path, df: pd.DataFrame, cfg, runs: int, traces: dict) -> list[str]:
    import warnings

    with warnings.catch_warnings():
        # all-NaN time columns (a run shorter than the grid) are expected
        warnings.simplefilter("ignore", RuntimeWarning)
        return _make_plots(out, df, cfg, runs, traces)


def _make_plots(out: Path, df: pd.DataFrame, cfg, runs: int, traces: dict) -> list[str]:
    from matplotlib.figure import Figure  # object-oriented: no pyplot, no backend switch
    from scipy import stats

    from uwbimu.io.atomic import save_figure

    written = []
    ok = df[df["status"] == "ok"]
    cells = [(s.name, e.name) for s in cfg.scenarios for e in cfg.estimators]

    # --- error distributions ------------------------------------------------
    fig = Figure(figsize=(4 + 1.6 * len(cells), 4.2), layout="constrained")
    axs = fig.subplots(1, 3, sharey=True)
    for a, ax in zip(AXES, axs):
        data = [ok[(ok["scenario"] == s) & (ok["estimator"] == e)][f"rmse_{a}"].dropna().to_numpy() for s, e in cells]
        ax.boxplot([d if len(d) else [np.nan] for d in data], showfliers=True)
        ax.set_xticks(range(1, len(cells) + 1), [f"{s}\n{e}" for s, e in cells], rotation=60, fontsize=7)
        ax.set_title(f"RMSE {a}")
        ax.set_yscale("log")
        ax.grid(alpha=0.3)
    axs[0].set_ylabel("position RMSE per run [m]")
    fig.suptitle(f"{cfg.name}: per-axis position RMSE over {runs} runs")
    save_figure(out / "rmse_distribution.png", fig)
    written.append("rmse_distribution.png")

    # --- NEES against chi-square bounds --------------------------------------
    fig = Figure(figsize=(5 * len(cfg.estimators), 3.2 * len(cfg.scenarios)), layout="constrained")
    axs = np.atleast_2d(fig.subplots(len(cfg.scenarios), len(cfg.estimators), squeeze=False))
    for i, s in enumerate(cfg.scenarios):
        tr = traces[s.name]
        for j, e in enumerate(cfg.estimators):
            ax = axs[i, j]
            if tr is None or e.name not in tr["estimators"]:
                continue
            k = tr["estimators"].index(e.name)
            nees = tr["nees"][:, k, :]
            n_ok = np.sum(np.isfinite(nees), axis=0)
            with np.errstate(invalid="ignore"):
                avg = np.nanmean(np.where(np.isfinite(nees), nees, np.nan), axis=0)
            n_t = np.maximum(n_ok, 1)
            lo_t, hi_t = stats.chi2.ppf(0.025, 3 * n_t) / n_t, stats.chi2.ppf(0.975, 3 * n_t) / n_t
            ax.semilogy(tr["t"], avg, lw=1, label="mean over the runs alive at t")
            ax.axhline(3, color="k", lw=0.8, ls="--", label="3 (dof)")
            ax.fill_between(tr["t"], lo_t, hi_t, color="g", alpha=0.2, label="95% band for that many runs")
            _mark_divergences(ax, tr, k)
            ax2 = ax.twinx()
            ax2.plot(tr["t"], alive_counts(np.isfinite(nees)), color="0.4", lw=0.8, ls=":", label="runs alive")
            ax2.set_ylim(0, max(int(np.max(n_ok)) if n_ok.size else 1, 1) * 1.05)
            ax2.set_ylabel("runs alive", fontsize=8)
            ax.set_title(f"{s.name} / {e.name}", fontsize=9)
            ax.set_xlabel("t [s]")
            ax.set_ylabel("position NEES")
            ax.grid(alpha=0.3)
            if i == 0 and j == 0:
                ax.legend(fontsize=7)
    save_figure(out / "nees.png", fig)
    written.append("nees.png")

    # --- estimate vs truth per axis, first run (seed fig. 2) ------------------
    if any(traces[s.name] is not None and "truth" in traces[s.name] for s in cfg.scenarios):
        fig = Figure(figsize=(5 * len(cfg.scenarios), 7), layout="constrained")
        axs = fig.subplots(3, len(cfg.scenarios), squeeze=False, sharex=True)
        for j, s in enumerate(cfg.scenarios):
            tr = traces[s.name]
            if tr is None or "truth" not in tr or not len(tr["runs"]):
                continue
            for a in range(3):
                ax = axs[a, j]
                ax.plot(tr["t"], tr["truth"][0, :, a], "k", lw=1.6, label="truth")
                for e in cfg.estimators:
                    if e.name in tr["estimators"]:
                        k = tr["estimators"].index(e.name)
                        ax.plot(tr["t"], tr["truth"][0, :, a] + tr["err"][0, k, :, a], lw=0.9, label=e.name)
                ax.set_ylabel(f"{AXES[a]} [m]")
                ax.grid(alpha=0.3)
                if a == 0:
                    ax.set_title(f"{s.name} (run {int(tr['runs'][0])})", fontsize=10)
                if a == 0 and j == 0:
                    ax.legend(fontsize=7)
            axs[2, j].set_xlabel("t [s]")
        fig.suptitle("estimated vs true position")
        save_figure(out / "position_vs_truth.png", fig)
        written.append("position_vs_truth.png")

    # --- error vs time per axis, one figure per estimator (seed fig. 3) -----
    for e in cfg.estimators:
        fig = Figure(figsize=(5 * len(cfg.scenarios), 8.5), layout="constrained")
        axs = fig.subplots(4, len(cfg.scenarios), squeeze=False, sharex=True,
                           gridspec_kw={"height_ratios": [1, 1, 1, 0.45]})
        for j, s in enumerate(cfg.scenarios):
            tr = traces[s.name]
            if tr is None or e.name not in tr["estimators"]:
                continue
            k = tr["estimators"].index(e.name)
            # Survivorship: the bands below are over the runs still producing estimates at t.
            alive = alive_counts(np.all(np.isfinite(tr["err"][:, k, :, :]), axis=-1))
            axs[3, j].plot(tr["t"], alive, color="0.2", lw=1)
            axs[3, j].set_ylim(0, len(tr["runs"]) * 1.05 + 0.5)
            axs[3, j].set_ylabel("runs alive")
            axs[3, j].grid(alpha=0.3)
            _mark_divergences(axs[3, j], tr, k, label=True)
            for a in range(3):
                ax = axs[a, j]
                err = tr["err"][:, k, :, a]
                sd = tr["sd"][:, k, :, a]
                if not np.any(np.isfinite(err)):
                    continue
                with np.errstate(invalid="ignore"):
                    lo, med, hi = np.nanpercentile(err, [5, 50, 95], axis=0)
                    sd_med = np.nanmedian(sd, axis=0)
                ax.fill_between(tr["t"], lo, hi, alpha=0.3, label="5-95% of runs alive at t")
                ax.plot(tr["t"], med, lw=1, label="median")
                ax.plot(tr["t"], err[0], lw=0.6, color="0.3", label=f"run {int(tr['runs'][0])}")
                ax.plot(tr["t"], 2 * sd_med, "r--", lw=0.7, label="±2 sd (median)")
                ax.plot(tr["t"], -2 * sd_med, "r--", lw=0.7)
                ax.set_ylabel(f"error {AXES[a]} [m]")
                ax.grid(alpha=0.3)
                if a == 0:
                    ax.set_title(s.name, fontsize=10)
                _mark_divergences(ax, tr, k)
                if a == 0 and j == 0:
                    ax.legend(fontsize=7)
            axs[3, j].set_xlabel("t [s]")
        fig.suptitle(f"{e.name}: position error per axis over {runs} runs (bands over the runs alive; "
                     "red ticks: divergences)")
        name = f"error_vs_time_{e.name}.png"
        save_figure(out / name, fig)
        written.append(name)
    return written
