"""Importers: convert third-party recordings into the uwbimu dataset format.

One module per source (``inrol.py``; ``isas_walk.py``, ``rosbag.py`` ...).
Each module exposes

* ``convert(src, ...) -> ImportResult``: read the source, return the
  :class:`~uwbimu.io.dataset.Dataset` plus the files to copy next to it
  (licence, attribution) and a list of the changes it made (never silent);
* ``import_dataset(src, dst, force=False, ...) -> ImportResult``: convert and
  write with :func:`write_import`.

The CLI (:mod:`uwbimu.cli.import_cmd`) adds one subcommand per importer.
The helpers below are shared: reading a source text file (UTF-8 only, every
line complete: a file cut short is refused, never imported up to the cut),
whitespace-separated text tables with a ``#`` header and comma-separated
tables (with file/line/column errors), and writing the result atomically,
refusing a non-empty destination unless ``force``.
"""

from __future__ import annotations

import io
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Union

import numpy as np
import pandas as pd

from uwbimu.io.dataset import Dataset, write_dataset
from uwbimu.io.loader import DatasetError, LoadOptions, load_dataset
from uwbimu.io.textio import decode_text, find_non_utf8

__all__ = ["ImportResult", "require_files", "source_text", "check_complete", "read_source_text", "read_csv_source", "read_text_table",
           "sort_by_time", "write_import"]


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


def source_text(path: Union[str, os.PathLike], what: str = "source file") -> str:
    """A source file's text with universal newlines; refused unless it exists and is UTF-8.

    Raises
    ------
    DatasetError : a missing file, or a byte that is not UTF-8 (the line of the first one).
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: {what} not found", file=path.name)
    data = path.read_bytes()
    bad = find_non_utf8(data)
    if bad is not None:
        raise DatasetError(f"{path.name}, line {bad.line}: the {what} is not UTF-8 text: {bad.describe()}; "
                           "save it as UTF-8", file=path.name, row=bad.line)
    return decode_text(data, path.name, what=what).replace("\r\n", "\n").replace("\r", "\n")


def check_complete(text: str, name: str, sep: Optional[str] = None, what: str = "source file",
                   fields: bool = True) -> None:
    """Refuse an empty text, a line whose field count differs from the header's, or a last line cut short.

    Parameters
    ----------
    text : the file's text (universal newlines).
    name : file name for messages.
    sep : field separator (``","``) or None for whitespace.
    fields : check that every non-blank line has as many fields as the first (header)
        line (a leading ``#`` of the header is not a field).

    A last line without a line end is refused: the sources write every line
    whole, so such a line is where the file was cut, and its last value may be
    cut too (``0.0159`` of ``0.01593``) without any field missing.
    """
    if not text.strip():
        raise DatasetError(f"{name}: the {what} is empty", file=name)
    lines = text.split("\n")
    if fields:
        split = (lambda ln: ln.split(sep)) if sep is not None else str.split
        n_head = len(split(lines[0].lstrip("#")))  # a "# a b c" header names the columns after "#"
        for i, ln in enumerate(lines[1:], start=2):
            if ln.strip() and len(split(ln)) != n_head:
                raise DatasetError(f"{name}, line {i}: {len(split(ln))} field(s) where the header has {n_head}"
                                   + (" (the file ends inside this line: cut short?)" if i == len(lines) else ""),
                                   file=name, row=i)
    if not text.endswith("\n"):
        raise DatasetError(f"{name}, line {len(lines)}: the last line has no line end: the file looks cut "
                           "short (its last value may be cut as well)", file=name, row=len(lines),
                           hint="re-export the complete file; if this line is complete, end it with a newline")


def read_source_text(path: Union[str, os.PathLike], sep: Optional[str] = None, what: str = "source file",
                     fields: bool = True) -> str:
    """The text of a source table: :func:`source_text` then :func:`check_complete`."""
    path = Path(path)
    text = source_text(path, what)
    check_complete(text, path.name, sep, what, fields)
    return text


def read_csv_source(path: Union[str, os.PathLike], what: str = "source file") -> pd.DataFrame:
    """A comma-separated source table as text cells (header stripped), via :func:`read_source_text`."""
    path = Path(path)
    text = read_source_text(path, ",", what=what)
    try:
        df = pd.read_csv(io.StringIO(text), dtype=str, skip_blank_lines=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
        raise DatasetError(f"{path.name}: malformed CSV: {exc}", file=path.name) from None
    df.columns = [str(c).strip() for c in df.columns]
    return df


def read_text_table(path: Path, columns: list[str]) -> pd.DataFrame:
    """Read a whitespace-separated numeric table whose first line is ``# col col ...``.

    The header must name exactly ``columns``.  Errors name the file, the line
    (the header is line 1) and the column; the text is read by
    :func:`read_source_text` (UTF-8, no line cut short).
    """
    path = Path(path)
    text = read_source_text(path)
    header = text.split("\n", 1)[0]
    names = header.lstrip("#").split()
    if names != columns:
        raise DatasetError(f"{path.name}, line 1: header columns {' '.join(names)} differ from the expected "
                           f"{' '.join(columns)}",
                           file=path.name, row=1, column=next((c for c in columns if c not in names), None))
    try:
        df = pd.read_csv(io.StringIO(text), sep=r"\s+", comment=None, skiprows=1, header=None, names=columns,
                         dtype=str, skip_blank_lines=False)
    except (pd.errors.ParserError, pd.errors.EmptyDataError) as exc:
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
                               f"('{df[c].iloc[i]}')", file=path.name, row=i + 2, column=c)
        out[c] = vals.astype(float)
    return out


def sort_by_time(df: pd.DataFrame, tcol: str, fname: str, changes: list[str]) -> pd.DataFrame:
    """Stable-sort rows by ``tcol``; record how many were out of order (with the first line)."""
    t = df[tcol].to_numpy()
    out = t < np.maximum.accumulate(t)
    n = int(out.sum())
    if n:
        i = int(np.argmax(out))
        changes.append(f"{fname}: {n} row(s) out of time order (first at line {i + 2}: t={float(t[i])} "
                       f"after t={float(np.maximum.accumulate(t)[i])}); rows sorted by time (stable)")
        df = df.sort_values(tcol, kind="stable").reset_index(drop=True)
    return df


def write_import(result: ImportResult, dst: Union[str, os.PathLike], force: bool = False,
                 src: Optional[Union[str, os.PathLike]] = None,
                 load_options: Optional[LoadOptions] = None) -> Path:
    """Write a converted dataset plus its extra files to ``dst`` atomically, then re-load it.

    The whole folder is built next to ``dst`` and renamed into place, so a
    failure leaves nothing half-written.  A non-empty ``dst`` is refused unless
    ``force``, and a ``dst`` that is or contains ``src`` always.  The written dataset is read back with :func:`load_dataset`
    (a converter bug surfaces as a :class:`DatasetError` before ``dst`` changes), with
    ``load_options`` when the importer kept data the default options refuse (a wider
    ``tdoa_margin``).
    """
    dst = Path(dst)
    if src is not None:
        s_res, d_res = Path(src).resolve(), dst.resolve()
        if s_res == d_res or d_res in s_res.parents:
            raise FileExistsError(f"{dst} holds the source {src}; choose another destination")
    if dst.exists() and not dst.is_dir():
        raise FileExistsError(f"{dst} exists and is not a folder")
    if dst.exists() and any(dst.iterdir()) and not force:
        from uwbimu.io.atomic import foreign_files

        foreign = foreign_files(dst)  # the output rule: a folder of our own unchanged outputs may be replaced
        if foreign:
            raise FileExistsError(f"{dst} exists and is not empty: it holds files uwbimu did not write or that changed "
                                  f"since ({', '.join(foreign[:5])}); refusing to overwrite (use --force)")
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
        load_dataset(staged, load_options)  # validate what we wrote
        from uwbimu.io.atomic import record_outputs

        record_outputs(staged, [staged])  # a rerun may replace this folder while it is unchanged
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
