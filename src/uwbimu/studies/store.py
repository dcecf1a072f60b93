"""The study's output folder: configuration lock, atomic chunk files, resume, task planning.

The client writes each finished chunk to ``OUT/chunks/`` atomically and fsynced (one CSV of
rows + one ``.npz`` of error traces), so a dead worker or an interrupted study loses nothing
already finished; a rerun with the same ``OUT`` skips the runs on disk, after checking that
the study's configuration is the one ``OUT`` was started with (``OUT/montecarlo_config.json``).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import pandas as pd

from uwbimu.errors import OutputError
from uwbimu.studies.config import CHUNK_DIR, CONFIG_FILE, ROW_COLUMNS, MonteCarloConfig, MonteCarloError

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
    """Create ``out`` for ``study`` or check that it was started with the same study.

    The output rule of every verb, for a study folder: a rerun into it resumes the same study; a
    folder of another study, a file, or a non-empty folder that is not a study folder is refused
    (:class:`uwbimu.errors.OutputError`, exit 4; nothing written).
    """
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out} is a file, not a folder; refusing to write there")
    lock = out / CONFIG_FILE
    if lock.exists():
        try:
            old = json.loads(lock.read_text())
        except json.JSONDecodeError as exc:
            raise OutputError(f"{lock}: unreadable ({exc}); not resuming") from None
        if old != study:
            diff = _diff_keys(old, study)
            shown = ", ".join(diff[:8]) + (f" (+{len(diff) - 8} more)" if len(diff) > 8 else "")
            raise OutputError(
                f"{out} was started with a different study configuration (differs in: {shown}); "
                "refusing to mix results. Use another --out, or the original config to resume."
            )
        return
    if out.exists() and any(out.iterdir()):
        raise OutputError(f"{out} exists, is not empty and holds no {CONFIG_FILE}; refusing to write into it")
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
