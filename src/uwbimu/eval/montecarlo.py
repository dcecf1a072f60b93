"""Monte Carlo studies: scenarios x seeds x estimators, on a process pool or Dask.

A study is described by a :class:`MonteCarloConfig` (YAML, see
``docs/montecarlo.md``).  For each scenario and each run index ``i`` the
scenario is simulated with seeds derived from ``(seed_base, i)`` — the same
seeds for every scenario, so that scenarios are compared on the same noise
draws (paired design) — and every estimator is run on that one dataset.

Work is shipped in *chunks* of run indices (one task = one scenario x a few
seeds, all estimators), so a task is seconds of work, not a cheap call.  The
client writes each finished chunk to ``OUT/chunks/`` atomically and fsynced
(one CSV of rows + one ``.npz`` of error traces), so a dead worker or an
interrupted study loses nothing already finished; a rerun with the same
``OUT`` skips the runs on disk, after checking that the study's configuration
is the one ``OUT`` was started with (``OUT/montecarlo_config.json``).  At the
end the chunks are merged into ``OUT/montecarlo.csv`` and aggregated into
``OUT/summary.json`` (see :mod:`uwbimu.eval.montecarlo_report` for plots).
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any, Callable, Iterable, Literal, Optional

import numpy as np
import pandas as pd
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from uwbimu.optional import require

CONFIG_FILE = "montecarlo_config.json"
CHUNK_DIR = "chunks"
FORMAT_VERSION = 1

#: Columns of ``montecarlo.csv`` (one row per scenario x run x estimator).
ROW_COLUMNS = [
    "scenario", "run", "estimator", "seed_truth", "seed_noise", "seed_init", "status", "error",
    "n_samples", "rmse_x", "rmse_y", "rmse_z", "rmse_3d", "final_err_x", "final_err_y", "final_err_z",
    "max_err_3d", "nees_pos_mean", "nees_kind", "lever_arm_err", "lever_arm_err_x", "lever_arm_err_y",
    "lever_arm_err_z", "time_offset_err", "ranges_accepted", "n_warnings", "coverage", "divergences", "sim_s",
    "est_s", "sim_cpu_s", "est_cpu_s",
]  # fmt: skip

#: Columns that depend on the machine (excluded from reproducibility checks).
TIMING_COLUMNS = ("sim_s", "est_s", "sim_cpu_s", "est_cpu_s")


class MonteCarloError(ValueError):
    """A study that cannot run (bad config, OUT started with another config...)."""


# --------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ScenarioEntry(_Strict):
    """One scenario of the study: a built-in name, a YAML file or an inline scenario."""

    name: str = Field(description="label used in the outputs")
    builtin: Optional[str] = Field(default=None, description="name of a built-in scenario")
    file: Optional[str] = Field(default=None, description="scenario YAML (relative to the config file)")
    scenario: Optional[dict[str, Any]] = Field(default=None, description="inline scenario fields")
    overrides: dict[str, Any] = Field(default_factory=dict, description="fields merged (deeply) on top")

    @model_validator(mode="after")
    def _one_source(self):
        n = sum(x is not None for x in (self.builtin, self.file, self.scenario))
        if n != 1:
            raise ValueError(f"scenario {self.name!r}: give exactly one of builtin, file, scenario")
        return self


class EstimatorEntry(_Strict):
    """One estimator of the study with its options."""

    name: str = Field(description="label used in the outputs")
    kind: Literal["eskf", "pointmass"] = "eskf"
    options: dict[str, Any] = Field(default_factory=dict, description="EskfOptions / PointMassOptions fields")
    initial_position_sd: Optional[float] = Field(
        default=None, gt=0,
        description="start from a surveyed take-off point: the true initial position plus N(0, sd^2) per axis "
        "(seeds.init), instead of the estimator's multilateration (needed by the ESKF with 3 anchors; see "
        "uwbimu.eval.montecarlo_eskf)",
    )


class MonteCarloConfig(_Strict):
    """A Monte Carlo study (YAML-loadable)."""

    name: str = "montecarlo"
    description: str = ""
    runs: int = Field(default=100, ge=1, description="seeds per scenario (CLI --runs overrides)")
    seed_base: int = Field(default=0, ge=0, description="run i uses seeds derived from (seed_base, i)")
    chunk_size: Optional[int] = Field(default=None, ge=1, description="runs per task; None: automatic")
    skip_initial_s: float = Field(default=0.0, ge=0, description="exclude the first seconds from RMSE and NEES [s]")
    trace_rate_hz: float = Field(default=5.0, gt=0, description="rate of the stored error traces (for plots) [Hz]")
    crlb: bool = Field(
        default=False,
        description="compute each scenario's posterior Cramer-Rao bound (uwbimu.eval.montecarlo_crlb) once, on the "
        "seeds of run 0, and report RMSE / calibration errors against it (does not change any run)",
    )
    scenarios: list[ScenarioEntry] = Field(min_length=1)
    estimators: list[EstimatorEntry] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique(self):
        for what, items in (("scenario", self.scenarios), ("estimator", self.estimators)):
            names = [x.name for x in items]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ValueError(f"duplicate {what} names: {dup}")
            bad = [n for n in names if not n or any(c in n for c in "/\\ ,") or n.startswith(".")]
            if bad:
                raise ValueError(f"{what} names must be non-empty without '/', '\\\\', ',' or spaces: {bad}")
        return self


def load_config(path: str | os.PathLike) -> MonteCarloConfig:
    """Read a study YAML; errors name the file and the field."""
    path = Path(path)
    if not path.is_file():
        raise MonteCarloError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise MonteCarloError(f"{path}: not valid YAML: {exc}") from None
    if not isinstance(data, dict):
        raise MonteCarloError(f"{path}: expected a mapping at top level")
    for sc in data.get("scenarios") or []:
        if isinstance(sc, dict) and isinstance(sc.get("file"), str) and not Path(sc["file"]).is_absolute():
            sc["file"] = str((path.parent / sc["file"]).resolve())
    return config_from_dict(data, str(path))


def config_from_dict(data: dict, source: str = "<config>") -> MonteCarloConfig:
    try:
        return MonteCarloConfig.model_validate(data)
    except ValidationError as err:
        lines = [f"{source}: invalid Monte Carlo config ({err.error_count()} error(s))"]
        for e in err.errors():
            loc = ".".join(str(x) for x in e["loc"]) or "(top level)"
            lines.append(f"  field '{loc}': {e['msg']}")
        raise MonteCarloError("\n".join(lines)) from None


def _deep_merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def resolve_scenario(entry: ScenarioEntry) -> dict:
    """The full scenario of an entry as a plain (JSON-able) dict, validated."""
    from uwbimu.sim import Scenario, builtin_scenario, load_scenario

    try:
        if entry.builtin is not None:
            base = builtin_scenario(entry.builtin).model_dump(mode="json", exclude_none=True)
        elif entry.file is not None:
            base = load_scenario(entry.file).model_dump(mode="json", exclude_none=True)
        else:
            base = dict(entry.scenario or {})
        sc = Scenario.model_validate(_deep_merge(base, entry.overrides))
    except (ValidationError, KeyError, ValueError) as exc:
        raise MonteCarloError(f"scenario {entry.name!r}: {exc}") from None
    return sc.model_dump(mode="json", exclude_none=True)


def resolved_study(cfg: MonteCarloConfig) -> dict:
    """Everything that determines the results except the number of runs.

    Stored in ``OUT/montecarlo_config.json``; a rerun into the same ``OUT`` must
    resolve to the same dict (scenarios are stored fully resolved, so a changed
    built-in is caught too).
    """
    d = cfg.model_dump(mode="json")
    d.pop("runs")
    d.pop("chunk_size")  # how work is cut does not change any result
    d.pop("description")
    d.pop("crlb")  # computed at the end from the scenarios; no run depends on it
    d["scenarios"] = [{"name": e.name, "scenario": resolve_scenario(e)} for e in cfg.scenarios]
    d["format_version"] = FORMAT_VERSION
    return json.loads(json.dumps(d, sort_keys=True))


def run_seeds(seed_base: int, run: int) -> tuple[int, int, int]:
    """Seeds ``(truth, noise, init)`` of run ``run`` (independent streams)."""
    s = np.random.SeedSequence([int(seed_base), int(run)]).generate_state(3, dtype=np.uint32)
    return int(s[0] >> 1), int(s[1] >> 1), int(s[2] >> 1)


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
        from uwbimu.eval.montecarlo_eskf import run_eskf_from_fix

        return run_eskf_from_fix(ds, opts, p0, sd)
    from uwbimu.eval.estimators import get_estimator

    est = get_estimator(entry["kind"])
    return est.run(ds, est.options(opts), None)


def _truth_at(ds, t: np.ndarray) -> np.ndarray:
    gt = ds.groundtruth
    tg = gt["t"].to_numpy(float)
    return np.column_stack([np.interp(t, tg, gt[c].to_numpy(float)) for c in ("px", "py", "pz")])


def run_metrics(result, ds, skip_initial_s: float = 0.0) -> tuple[dict, dict]:
    """Position RMSE per axis, NEES, calibration errors of one estimate.

    Returns ``(row fields, trace)``; the trace holds the result stamps ``t``,
    position errors ``err`` (K, 3), sds ``sd`` (K, 3) and NEES ``nees`` (K,).
    NEES uses the full 3x3 position covariance when the result has covariances,
    else the diagonal (``nees_kind`` says which).
    """
    t = np.asarray(result.t, float)
    gt_t = ds.groundtruth["t"].to_numpy(float)
    keep = (t >= gt_t[0]) & (t <= gt_t[-1])
    t = t[keep]
    p = np.asarray(result.states, float)[keep, 0:3]
    err = p - _truth_at(ds, t)
    sd = np.asarray(result.sd, float)[keep, 0:3]
    cov = None
    if result.covariances is not None:
        c = np.asarray(result.covariances)[keep][:, 0:3, 0:3]
        if np.all(np.isfinite(c)):
            cov = c
    if cov is not None:
        nees = np.einsum("ni,ni->n", err, np.linalg.solve(cov, err[..., None])[..., 0])
        kind = "full"
    else:
        nees = np.sum((err / sd) ** 2, axis=1)
        kind = "diag"
    m = t >= (t[0] + skip_initial_s) if len(t) else keep[keep]
    e = err[m]
    row: dict[str, Any] = {"n_samples": int(m.sum()), "nees_kind": kind}
    if len(e):
        rmse = np.sqrt(np.mean(e**2, axis=0))
        row.update(rmse_x=rmse[0], rmse_y=rmse[1], rmse_z=rmse[2], rmse_3d=float(np.sqrt(np.sum(rmse**2))))
        row.update(final_err_x=e[-1, 0], final_err_y=e[-1, 1], final_err_z=e[-1, 2])
        row["max_err_3d"] = float(np.max(np.linalg.norm(e, axis=1)))
        row["nees_pos_mean"] = float(np.mean(nees[m]))
    truth = ds.meta.truth
    cal = result.calibration or {}
    la_sd = np.asarray(cal.get("lever_arm_sd", [np.nan] * 3), float)
    # A calibration the estimator keeps fixed (sd NaN or 0) has no estimation error to report.
    if truth is not None and truth.lever_arm is not None and np.all(np.isfinite(la_sd)) and np.any(la_sd > 0):
        d = np.asarray(cal["lever_arm"], float) - np.asarray(truth.lever_arm, float)
        row.update(lever_arm_err=float(np.linalg.norm(d)), lever_arm_err_x=d[0], lever_arm_err_y=d[1],
                   lever_arm_err_z=d[2])
    td_sd = cal.get("time_offset_sd", np.nan)
    if truth is not None and truth.time_offset is not None and td_sd is not None and np.isfinite(td_sd) and td_sd > 0:
        row["time_offset_err"] = float(cal["time_offset"] - truth.time_offset)
    res = result.residuals
    if res is not None and len(res) and "accepted" in res:
        row["ranges_accepted"] = float(np.mean(res["accepted"].to_numpy(bool)))
    row["n_warnings"] = len(result.warnings or [])
    # An estimator that stops (e.g. the ESKF after a divergence it cannot recover from) has
    # metrics over a shorter span only: say how much of the flight the estimate covers.
    fin = np.all(np.isfinite(p), axis=1)
    span = float(gt_t[-1] - gt_t[0])
    row["coverage"] = float((t[fin][-1] - t[fin][0]) / span) if fin.sum() > 1 and span > 0 else 0.0
    div_t = [float(ev["t"]) for ev in (result.events or []) if ev.get("kind") == "divergence" and "t" in ev]
    row["divergences"] = sum(1 for ev in (result.events or []) if ev.get("kind") == "divergence")
    return row, {"t": t, "err": err, "sd": sd, "nees": nees, "divergence_t": np.asarray(div_t, float)}


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


# --------------------------------------------------------------------------
# Output folder: config lock, chunk files, resume
# --------------------------------------------------------------------------
def _fsync_write(path: Path, write: Callable[[Path], None]) -> None:
    """Write via a temporary sibling, fsync it, rename into place, fsync the folder."""
    from uwbimu.io.atomic import atomic_path

    with atomic_path(path) as tmp:
        write(tmp)
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def _diff_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b)):
            out += _diff_keys(a.get(k), b.get(k), f"{prefix}.{k}" if prefix else str(k))
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        out = []
        for i, (x, y) in enumerate(zip(a, b)):
            out += _diff_keys(x, y, f"{prefix}[{i}]")
        return out
    return [] if a == b else [prefix or "(top level)"]


def prepare_out(out: Path, study: dict) -> None:
    """Create ``out`` for ``study`` or check that it was started with the same study."""
    if out.exists() and not out.is_dir():
        raise MonteCarloError(f"{out} is a file, not a folder; refusing to write there")
    lock = out / CONFIG_FILE
    if lock.exists():
        try:
            old = json.loads(lock.read_text())
        except json.JSONDecodeError as exc:
            raise MonteCarloError(f"{lock}: unreadable ({exc}); not resuming") from None
        if old != study:
            diff = _diff_keys(old, study)
            shown = ", ".join(diff[:8]) + (f" (+{len(diff) - 8} more)" if len(diff) > 8 else "")
            raise MonteCarloError(
                f"{out} was started with a different study configuration (differs in: {shown}); "
                "refusing to mix results. Use another --out, or the original config to resume."
            )
        return
    if out.exists() and any(out.iterdir()):
        raise MonteCarloError(f"{out} exists, is not empty and holds no {CONFIG_FILE}; refusing to write into it")
    out.mkdir(parents=True, exist_ok=True)
    (out / CHUNK_DIR).mkdir(exist_ok=True)
    _fsync_write(lock, lambda p: p.write_text(json.dumps(study, sort_keys=True, indent=1)))


def _chunk_stem(scenario: str, runs: list[int]) -> str:
    return f"{scenario}__{min(runs):06d}-{max(runs):06d}__{len(runs)}"


def write_chunk(out: Path, chunk: dict) -> None:
    """Persist one finished chunk (traces first, then the rows that mark it done)."""
    d = out / CHUNK_DIR
    d.mkdir(parents=True, exist_ok=True)
    stem = _chunk_stem(chunk["scenario"], chunk["runs"])
    tr = chunk["traces"]

    def w_npz(p: Path):
        with open(p, "wb") as fh:
            np.savez_compressed(fh, runs=np.array(chunk["runs"]), **tr)

    _fsync_write(d / f"{stem}.npz", w_npz)
    df = pd.DataFrame(chunk["rows"]).reindex(columns=ROW_COLUMNS)
    _fsync_write(d / f"{stem}.csv", lambda p: df.to_csv(p, index=False, float_format="%.17g"))


def chunk_files(out: Path, ext: str, scenario: Optional[str] = None) -> list[Path]:
    """Finished chunk files (temporary files of interrupted writes start with '.' and are ignored).

    A trace file counts only when its row file exists: rows are written last and
    mark a chunk as done.
    """
    d = out / CHUNK_DIR
    if not d.is_dir():
        return []
    pat = f"{scenario}__*.{ext}" if scenario else f"*.{ext}"
    files = [f for f in sorted(d.glob(pat)) if not f.name.startswith(".")]
    if ext != "csv":
        files = [f for f in files if f.with_suffix(".csv").exists()]
    return files


def read_done(out: Path) -> pd.DataFrame:
    """All rows of the chunk files in ``out`` (empty frame if none)."""
    files = chunk_files(out, "csv")
    frames = [pd.read_csv(f, keep_default_na=True, dtype={"error": str}) for f in files]
    frames = [f for f in frames if len(f)]
    if not frames:
        return pd.DataFrame(columns=ROW_COLUMNS)
    df = pd.concat(frames, ignore_index=True)
    df["error"] = df["error"].fillna("")
    return df


def plan_tasks(cfg: MonteCarloConfig, study: dict, runs: int, done: pd.DataFrame, chunk_size: int) -> list[dict]:
    """Tasks for the runs not yet on disk (a run is done when all its estimators are)."""
    n_est = len(cfg.estimators)
    finished: set[tuple[str, int]] = set()
    if len(done):
        counts = done.groupby(["scenario", "run"]).size()
        finished = {(str(s), int(r)) for (s, r), c in counts.items() if c >= n_est}
    tasks = []
    common = {
        "estimators": [e.model_dump(mode="json") for e in cfg.estimators],
        "seed_base": cfg.seed_base,
        "skip_initial_s": cfg.skip_initial_s,
        "trace_rate_hz": cfg.trace_rate_hz,
    }
    for sc in study["scenarios"]:
        todo = [i for i in range(runs) if (sc["name"], i) not in finished]
        for k in range(0, len(todo), chunk_size):
            tasks.append({**common, "scenario_name": sc["name"], "scenario": sc["scenario"],
                          "runs": todo[k:k + chunk_size]})
    return tasks


def auto_chunk_size(total_runs: int, workers: int) -> int:
    """About four tasks per worker, between 1 and 25 runs per task."""
    return int(min(25, max(1, math.ceil(total_runs / (4 * max(workers, 1))))))


# --------------------------------------------------------------------------
# Executors
# --------------------------------------------------------------------------
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def _run_pool(tasks: list[dict], workers: int, on_chunk: Callable[[dict], None]) -> list[str]:
    import multiprocessing as mp

    ctx = mp.get_context("forkserver") if "forkserver" in mp.get_all_start_methods() else None
    if ctx is not None:
        # Workers fork from a server that has already imported the heavy modules.
        ctx.set_forkserver_preload(["uwbimu.eval.montecarlo", "uwbimu.sim", "uwbimu.estimation.pointmass"])
    failures: list[str] = []
    # One BLAS thread per worker process, as Dask workers have (same numerics, no oversubscription);
    # the forkserver and its workers inherit the environment at their start.
    saved = {k: os.environ.get(k) for k in _THREAD_VARS}
    for k in _THREAD_VARS:
        os.environ.setdefault(k, "1")
    ex = ProcessPoolExecutor(max_workers=workers, mp_context=ctx)
    try:
        try:
            pending = {ex.submit(run_chunk, t): t for t in tasks}  # workers start here
        finally:
            for k, v in saved.items():
                if v is None:
                    os.environ.pop(k, None)
                else:
                    os.environ[k] = v
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                t = pending.pop(f)
                try:
                    chunk = f.result()
                except Exception as exc:  # e.g. BrokenProcessPool: a worker died
                    failures.append(f"{t['scenario_name']} runs {t['runs'][0]}-{t['runs'][-1]}: {type(exc).__name__}: {exc}")
                    continue
                on_chunk(chunk)
    except BaseException:
        # Ctrl-C or a failed write: do not wait for the queued tasks (finished ones are on disk).
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    ex.shutdown(wait=True)
    return failures


def _run_dask(tasks: list[dict], client, on_chunk: Callable[[dict], None]) -> list[str]:
    require("distributed", "dask", "a Dask study")
    from distributed import as_completed

    failures: list[str] = []
    futs = [client.submit(run_chunk, t, pure=False, key=f"mc-{_chunk_stem(t['scenario_name'], t['runs'])}-{i}")
            for i, t in enumerate(tasks)]
    by_key = {f.key: t for f, t in zip(futs, tasks)}
    gather_retries: dict[str, int] = {}
    ac = as_completed(futs)
    for f in ac:
        t = by_key[f.key]
        try:
            chunk = f.result()
        except Exception as exc:
            # A worker that dies while its result is being fetched leaves the key re-queued
            # ("couldn't gather keys ... processing") and the fetch raises on the client although
            # the task did not fail: wait for it again. A task that itself failed on every
            # retry has status "error" and is reported.
            n = gather_retries.get(f.key, 0)
            if f.status != "error" and n < 3:
                gather_retries[f.key] = n + 1
                time.sleep(0.5)
                ac.add(f)
                continue
            failures.append(f"{t['scenario_name']} runs {t['runs'][0]}-{t['runs'][-1]}: {type(exc).__name__}: {exc}")
            continue
        on_chunk(chunk)
        f.release()
    return failures


def run_study(
    cfg: MonteCarloConfig,
    out: str | os.PathLike,
    runs: Optional[int] = None,
    workers: Optional[int] = None,
    client=None,
    scheduler: Optional[str] = None,
    dask_local: bool = False,
    progress: Optional[Callable[[int, int], None]] = None,
    plots: bool = True,
) -> dict:
    """Run (or resume) a study into ``out``; returns the summary dict.

    Parameters
    ----------
    cfg : the study.
    out : output folder (created; or resumed if it holds the same study).
    runs : seeds per scenario (default ``cfg.runs``).
    workers : local processes (default: all cores) or LocalCluster workers; with
        ``client`` / ``scheduler`` only used for chunking (default: the cluster's workers).
    client : an existing ``distributed.Client`` to run on (tests, notebooks).
    scheduler : address of a Dask scheduler (``tcp://host:8786``).
    dask_local : start a loopback Dask ``LocalCluster`` with ``workers`` workers.
    progress : ``progress(done_runs, total_runs)`` called as chunks finish.
    """
    from uwbimu.eval.montecarlo_report import finalize

    if scheduler and client is None:
        # Connect first: the cluster's size (not this machine's) sets the default chunking.
        require("distributed", "dask", "a Dask study (--scheduler)")
        from distributed import Client

        try:
            own = Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise MonteCarloError(f"cannot connect to the Dask scheduler {scheduler}: {exc}") from None
        try:
            return run_study(cfg, out, runs=runs, workers=workers, client=own, scheduler=scheduler,
                             progress=progress, plots=plots)
        finally:
            own.close()
    out = Path(out)
    runs = int(runs if runs is not None else cfg.runs)
    if runs < 1:
        raise MonteCarloError("--runs must be at least 1")
    if not workers and client is not None:
        workers = len(client.scheduler_info()["workers"])  # the cluster's workers
    workers = int(workers or os.cpu_count() or 1)
    study = resolved_study(cfg)
    prepare_out(out, study)
    done = read_done(out)
    chunk_size = cfg.chunk_size or auto_chunk_size(runs * len(cfg.scenarios), workers)
    tasks = plan_tasks(cfg, study, runs, done, chunk_size)
    total = runs * len(cfg.scenarios)
    n_done = total - sum(len(t["runs"]) for t in tasks)
    if progress:
        progress(n_done, total)

    def on_chunk(chunk: dict) -> None:
        nonlocal n_done
        write_chunk(out, chunk)
        n_done += len(chunk["runs"])
        if progress:
            progress(n_done, total)

    t0 = time.perf_counter()
    failures: list[str] = []
    if tasks:
        if client is not None or scheduler or dask_local:
            failures = _with_dask(tasks, client, scheduler, dask_local, workers, on_chunk)
        elif workers == 1:
            for t in tasks:
                on_chunk(run_chunk(t))
        else:
            failures = _run_pool(tasks, workers, on_chunk)
    wall = time.perf_counter() - t0
    summary = finalize(out, cfg, runs, plots=plots)
    summary["execution"] = {
        "backend": "dask" if (client is not None or scheduler or dask_local) else ("serial" if workers == 1 else "process-pool"),
        "workers": workers,
        "chunk_size": chunk_size,
        "tasks_this_call": len(tasks),
        "runs_resumed_from_disk": total - sum(len(t["runs"]) for t in tasks),
        "wall_s_this_call": wall,
        "task_failures": failures,
    }
    from uwbimu.io.atomic import write_json

    write_json(out / "summary.json", summary)
    if failures:
        raise MonteCarloError(
            f"{len(failures)} task(s) did not finish (finished runs are saved in {out}; rerun the same "
            f"command to resume):\n  " + "\n  ".join(failures[:10])
        )
    return summary


def _with_dask(tasks, client, scheduler, dask_local, workers, on_chunk) -> list[str]:
    if client is not None:
        return _run_dask(tasks, client, on_chunk)
    require("distributed", "dask", "a Dask study")
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as c:
            return _run_dask(tasks, c, on_chunk)
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as c:
        return _run_dask(tasks, c, on_chunk)


def iter_rows_equal_ignoring_timing(a: pd.DataFrame, b: pd.DataFrame) -> Iterable[str]:
    """Yield a description of each difference between two result tables (timing columns ignored)."""
    cols = [c for c in ROW_COLUMNS if c not in TIMING_COLUMNS]
    key = ["scenario", "run", "estimator"]
    a = a.sort_values(key).reset_index(drop=True)[cols]
    b = b.sort_values(key).reset_index(drop=True)[cols]
    if len(a) != len(b):
        yield f"row counts differ: {len(a)} vs {len(b)}"
        return
    for c in cols:
        x, y = a[c].to_numpy(), b[c].to_numpy()
        same = (x == y) | (pd.isna(x) & pd.isna(y))
        if not np.all(same):
            i = int(np.argmin(same))
            yield f"column {c} row {i}: {x[i]!r} vs {y[i]!r}"
