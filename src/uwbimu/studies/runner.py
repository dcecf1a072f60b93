"""Monte Carlo studies: scenarios x seeds x estimators, on a process pool or Dask.

Work is shipped in *chunks* of run indices (one task = one scenario x a few seeds, all
estimators; :mod:`uwbimu.studies.worker`), so a task is seconds of work, not a cheap call.
Finished chunks are stored as they arrive (:mod:`uwbimu.studies.store`); at the end they are
merged into ``OUT/montecarlo.csv`` and aggregated into ``OUT/summary.json``
(:mod:`uwbimu.studies.report`).
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Callable, Iterable, Optional

import numpy as np
import pandas as pd

from uwbimu.optional import require
from uwbimu.studies.config import ROW_COLUMNS, TIMING_COLUMNS, MonteCarloConfig, MonteCarloError, resolved_study
from uwbimu.parallel import execute
from uwbimu.studies.store import auto_chunk_size, plan_tasks, prepare_out, read_done, write_chunk
from uwbimu.studies.worker import run_chunk

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
    from uwbimu.studies.report import finalize

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
        from uwbimu.errors import UsageError

        raise UsageError(f"runs must be at least 1, got {runs}")
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
        failures = execute(run_chunk, tasks, on_chunk, workers=workers, client=client, scheduler=scheduler,
                           dask_local=dask_local, describe=_describe,
                           preload=("uwbimu.studies.worker", "uwbimu.sim", "uwbimu.estimation.pointmass"))
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



def _describe(task: dict) -> str:
    return f"{task['scenario_name']} runs {task['runs'][0]}-{task['runs'][-1]}"
