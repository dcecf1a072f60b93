"""Reading the tables that evaluation and reports consume, with clear errors.

Estimator output folder (``uwbimu estimate DATASET --out OUT``)::

    trajectory.csv   t, px, py, pz, qw, qx, qy, qz, vx, vy, vz, sd_px, ...  (+ calibration columns)
    calibration.yaml lever_arm, lever_arm_sd, time_offset, time_offset_sd, ...
    residuals.csv    t, anchor, range, predicted, innovation, nis, accepted
    metrics.yaml     position_rmse, ...  (only with ground truth)

Ground truth follows the dataset format (``groundtruth.csv``: ``t, px, py,
pz, qw, qx, qy, qz``).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import pandas as pd

from uwbimu.errors import InputError, column_list


class EvalInputError(InputError):
    """An input file is missing, unreadable or lacks a required column (exit code 1)."""


def read_table(path: str | os.PathLike, required: Sequence[str], what: str) -> pd.DataFrame:
    """Read a CSV/Parquet table and check its columns.

    Parameters
    ----------
    path : file to read (``.csv`` or ``.parquet``).
    required : columns that must be present and numeric/finite in ``t``.
    what : human name of the table, used in error messages.

    Raises
    ------
    EvalInputError
        Naming the file, and the column or row at fault.
    """
    path = Path(path)
    if not path.is_file():
        raise EvalInputError(f"{what}: file not found: {path}")
    try:
        df = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path)
    except Exception as exc:  # pandas raises many types for malformed files
        raise EvalInputError(f"{what}: cannot read {path}: {exc}") from exc
    df.columns = [str(c).strip() for c in df.columns]
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise EvalInputError(f"{what}: {path} lacks {column_list(missing)}; it has {column_list(df.columns)}")
    for c in required:
        if c == "anchor":
            continue
        col = pd.to_numeric(df[c], errors="coerce")
        bad = col.isna() & df[c].notna()
        if bad.any():
            row = int(np.flatnonzero(bad.to_numpy())[0])
            raise EvalInputError(
                f"{what}: {path} row {row + 2} (line in file), column '{c}': not a number: '{df[c].iloc[row]}'"
            )
        df[c] = col
    if "t" in required:
        tnan = df["t"].isna().to_numpy()
        if tnan.any():
            raise EvalInputError(f"{what}: {path} row {int(np.flatnonzero(tnan)[0]) + 2}, column 't': missing time")
    return df


def load_trajectory(path: str | os.PathLike) -> pd.DataFrame:
    """Estimator ``trajectory.csv`` (or a folder containing one)."""
    path = Path(path)
    if path.is_dir():
        path = path / "trajectory.csv"
    return read_table(path, ["t", "px", "py", "pz"], "trajectory")


def load_groundtruth(path: str | os.PathLike) -> pd.DataFrame:
    """Ground truth in the dataset format (file, or a dataset folder with ``groundtruth.csv``)."""
    path = Path(path)
    if path.is_dir():
        for name in ("groundtruth.csv", "groundtruth.parquet"):
            if (path / name).is_file():
                path = path / name
                break
        else:
            raise EvalInputError(f"ground truth: {path} is a folder without groundtruth.csv/.parquet")
    return read_table(path, ["t", "px", "py", "pz"], "ground truth")


def load_yaml(path: str | os.PathLike) -> Optional[dict]:
    """A YAML mapping, or None when the file does not exist."""
    from uwbimu.io.yamlconfig import read_yaml_mapping

    path = Path(path)
    if not path.is_file():
        return None
    return read_yaml_mapping(path, what="YAML", error=EvalInputError)[0]
