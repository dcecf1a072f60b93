"""Importers: convert third-party recordings into the uwbimu dataset format.

One module per source (``inrol.py``; ``isas_walk.py``, ``rosbag.py`` ...).
Each module exposes

* ``convert(src, ...) -> ImportResult``: read the source, return the
  :class:`~uwbimu.io.dataset.Dataset` plus the files to copy next to it
  (licence, attribution) and a list of the changes it made (never silent);
* ``import_dataset(src, dst, force=False, ...) -> ImportResult``: convert and
  write with :func:`write_import`.

The CLI (:mod:`uwbimu.cli.import_cmd`) adds one subcommand per importer.
The helpers below are shared: reading whitespace-separated text tables with a
``#`` header (with file/line/column errors) and writing the result
atomically, refusing a non-empty destination unless ``force``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np
import pandas as pd

from uwbimu.io.dataset import Dataset, write_dataset
from uwbimu.io.loader import DatasetError, load_dataset

__all__ = ["ImportResult", "require_files", "read_text_table", "sort_by_time", "write_import"]


@dataclass
class ImportResult:
    """A converted dataset, the files to place next to it and what was changed."""

    dataset: Dataset
    extra_files: dict[str, Union[bytes, str, Path]] = field(default_factory=dict)
    changes: list[str] = field(default_factory=list)
    path: Optional[Path] = None  # set once written


def require_files(src: Path, names: list[str]) -> None:
    """Refuse a source folder that lacks any of ``names`` (listing what it holds)."""
    src = Path(src)
    if not src.is_dir():
        raise DatasetError(f"{src}: source folder does not exist", file=str(src))
    missing = [n for n in names if not (src / n).is_file()]
    if missing:
        present = sorted(p.name for p in src.iterdir())
        raise DatasetError(f"{src}: missing source file(s) {', '.join(missing)}; the folder holds: "
                           f"{', '.join(present) if present else '(nothing)'}", file=missing[0])


def read_text_table(path: Path, columns: list[str]) -> pd.DataFrame:
    """Read a whitespace-separated numeric table whose first line is ``# col col ...``.

    The header must name exactly ``columns``.  Errors name the file, the line
    (the header is line 1) and the column.
    """
    path = Path(path)
    with open(path) as fh:
        header = fh.readline()
    if not header.strip():
        raise DatasetError(f"{path.name}: file is empty", file=path.name)
    names = header.lstrip("#").split()
    if names != columns:
        raise DatasetError(f"{path.name}, line 1: header columns {names} differ from the expected {columns}",
                           file=path.name, row=1, column=next((c for c in columns if c not in names), None))
    try:
        df = pd.read_csv(path, sep=r"\s+", comment=None, skiprows=1, header=None, names=columns,
                         dtype=str, skip_blank_lines=False)
    except pd.errors.ParserError as exc:
        raise DatasetError(f"{path.name}: malformed table: {exc}", file=path.name) from None
    if len(df) == 0:
        raise DatasetError(f"{path.name}: header but no data rows", file=path.name)
    out = pd.DataFrame(index=df.index)
    for c in columns:
        vals = pd.to_numeric(df[c], errors="coerce")
        bad = vals.isna() | ~np.isfinite(vals.to_numpy(float))
        if bad.any():
            i = int(np.argmax(bad.to_numpy()))
            raise DatasetError(f"{path.name}, line {i + 2}, column '{c}': not a finite number "
                               f"({df[c].iloc[i]!r})", file=path.name, row=i + 2, column=c)
        out[c] = vals.astype(float)
    return out


def sort_by_time(df: pd.DataFrame, tcol: str, fname: str, changes: list[str]) -> pd.DataFrame:
    """Stable-sort rows by ``tcol``; record how many were out of order (with the first line)."""
    t = df[tcol].to_numpy()
    out = t < np.maximum.accumulate(t)
    n = int(out.sum())
    if n:
        i = int(np.argmax(out))
        changes.append(f"{fname}: {n} row(s) out of time order (first at line {i + 2}: t={float(t[i])!r} "
                       f"after t={float(np.maximum.accumulate(t)[i])!r}); rows sorted by time (stable)")
        df = df.sort_values(tcol, kind="stable").reset_index(drop=True)
    return df


def write_import(result: ImportResult, dst: Union[str, os.PathLike], force: bool = False,
                 src: Optional[Union[str, os.PathLike]] = None) -> Path:
    """Write a converted dataset plus its extra files to ``dst`` atomically, then re-load it.

    The whole folder is built next to ``dst`` and renamed into place, so a
    failure leaves nothing half-written.  A non-empty ``dst`` is refused unless
    ``force``, and a ``dst`` that is or contains ``src`` always.  The written dataset is read back with :func:`load_dataset`
    (a converter bug surfaces as a :class:`DatasetError` before ``dst`` changes).
    """
    dst = Path(dst)
    if src is not None:
        s_res, d_res = Path(src).resolve(), dst.resolve()
        if s_res == d_res or d_res in s_res.parents:
            raise FileExistsError(f"{dst} holds the source {src}; choose another destination")
    if dst.exists() and not dst.is_dir():
        raise FileExistsError(f"{dst} exists and is not a folder")
    if dst.exists() and any(dst.iterdir()) and not force:
        raise FileExistsError(f"{dst} exists and is not empty; refusing to overwrite (use --force)")
    dst.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{dst.name}.import.", dir=dst.parent))
    try:
        staged = write_dataset(result.dataset, work / "ds")
        for name, content in result.extra_files.items():
            target = staged / name
            if isinstance(content, Path):
                shutil.copyfile(content, target)
            elif isinstance(content, bytes):
                target.write_bytes(content)
            else:
                target.write_text(content)
        load_dataset(staged)  # validate what we wrote
        if dst.exists():
            old = work / "old"
            dst.rename(old)
            try:
                staged.rename(dst)
            except BaseException:
                old.rename(dst)  # put the previous folder back
                raise
        else:
            staged.rename(dst)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result.path = dst
    return dst
