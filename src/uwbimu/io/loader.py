"""Validating reader of the dataset folder format.

:func:`load_dataset` reads a dataset folder (see :mod:`uwbimu.io.dataset` and
``docs/dataset_format.md``) and refuses bad input with a :class:`DatasetError`
whose message names the file, the row and the column.

Row convention
--------------
For CSV files the location is the *line number in the file*, counting the
header as line 1 (so the first data row is line 2); the 1-based data row is
given too: ``imu.csv line 7 (data row 6), column 'ax'``.  Parquet files have
no header line, so they are located by 1-based data row: ``imu.parquet data
row 6, column 'ax'``.

Repairs
-------
Nothing is dropped or changed unless asked for through :class:`LoadOptions`
(``drop_duplicate_rows``, ``sort``, ``gyro_units``, ``accel_units``); every
repair is counted in the :class:`LoadReport` attached to the returned dataset
(``ds.report``) and announced with :func:`warnings.warn`.
"""

from __future__ import annotations

import csv
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
import pandas as pd
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from uwbimu.errors import InputError
from uwbimu.optional import require
from uwbimu.io.anchor_ranges import parse_range_sd, parse_surveyed
from uwbimu.io import plausibility
from uwbimu.io.textio import decode_text, find_non_utf8
from uwbimu.io.yamlconfig import find_non_finite, yaml_line
from uwbimu.io.dataset import (
    ANCHOR_COLUMNS,
    ANCHOR_QUAT_COLUMNS,
    ANCHOR_RANGE_COLUMNS,
    TDOA_COLUMNS,
    GT_COLUMNS,
    GT_VEL_COLUMNS,
    IMU_COLUMNS,
    UWB_COLUMNS,
    Dataset,
    DatasetMeta,
)

__all__ = [
    "DatasetError",
    "LoadOptions",
    "LoadReport",
    "LoadRepairWarning",
    "LoadWarning",
    "load_dataset",
    "load_meta",
    "MAX_RANGE_M",
]

#: Ranges above this are refused as absurd for UWB two-way ranging [m].
MAX_RANGE_M = 1000.0
#: Largest plausible |angular rate| of a MEMS gyro in rad/s (2000 deg/s full scale).
GYRO_MAX_RAD_S = math.radians(2000.0)
#: Accepted band for the median specific-force norm [m/s^2] (gravity included).
ACCEL_NORM_BAND = (4.0, 30.0)
#: Quaternions whose norm differs from 1 by more than this are refused.
QUAT_NORM_TOL = 1e-2

#: Default margin [m] by which |tdoa| may exceed the two anchors' separation (noise, NLOS bias).
TDOA_MARGIN_M = 1.0

#: Every |tdoa| below this [m] means the column holds seconds (10 m is 33 ns).
TDOA_SECONDS_MAX = 1e-6
#: A median |tdoa| above this many times the largest anchor separation cannot be metres, whatever the margin.
TDOA_UNIT_RATIO = 20.0
#: One DW1000 time-stamp tick (1 / (128 x 499.2 MHz) = 15.65 ps) as a distance [m].
DW1000_TICK_M = 299_792_458.0 / (128 * 499.2e6)

_TEXT_COLUMNS = ("anchor", "tag", "anchor_a", "anchor_b")


def fmt_num(x: Any) -> str:
    """A number as plain text for messages (never ``np.float64(1.6)``)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    return repr(int(v)) if v.is_integer() and abs(v) < 1e15 else repr(v)


class DatasetError(InputError):
    """A dataset that cannot be used as is (an :class:`uwbimu.errors.InputError`, exit code 1).

    Attributes
    ----------
    file : name of the offending file (or None)
    row : location in that file (CSV: line number with the header as line 1;
        parquet: 1-based data row), or None when the problem is file-wide
    column : offending column / key (or None)
    """

    def __init__(self, message: str, file: Optional[str] = None, row: Optional[int] = None,
                 column: Optional[str] = None, hint: Optional[str] = None):
        super().__init__(message, hint=hint)
        self.file = file
        self.row = row
        self.column = column


def _plain(v: Any) -> Any:
    if isinstance(v, np.generic):
        return v.item()
    return v


class LoadWarning(UserWarning):
    """Emitted by :func:`load_dataset` for data it accepts but doubts (low rate, coplanar anchors, ...)."""


class LoadRepairWarning(UserWarning):
    """Emitted when :func:`load_dataset` repaired (dropped, sorted, rescaled) data on request."""


class LoadOptions(BaseModel):
    """Options of :func:`load_dataset` (all repairs are off by default)."""

    model_config = ConfigDict(extra="forbid")

    drop_duplicate_rows: bool = Field(
        default=False,
        description="drop rows that repeat an earlier row exactly (same key and same values); "
        "counted in the report. Duplicates with different values are still refused.",
    )
    sort: bool = Field(default=False, description="sort every table by time (stable); counted in the report")
    gyro_units: Literal["rad/s", "deg/s"] = Field(
        default="rad/s", description="unit of wx, wy, wz in the file; deg/s is converted (x pi/180)"
    )
    accel_units: Literal["m/s^2", "g"] = Field(
        default="m/s^2", description="unit of ax, ay, az in the file; g is converted (x 9.81)"
    )
    check_units: bool = Field(default=True, description="refuse gyro/accelerometer data that looks like deg/s or g")
    max_range: float = Field(default=MAX_RANGE_M, gt=0, description="largest accepted range, m")
    lenient: bool = Field(
        default=False,
        description="accept an IMU below 10 Hz and degenerate anchor geometry (one anchor, all anchors at one "
        "point or on one line) with a warning instead of refusing them")
    clock_jumps: Literal["refuse", "split"] = Field(
        default="refuse",
        description="a clock that jumps back once (stamps increasing before and after): refuse, or keep the "
        "longest monotonic part of that table (split) and report the jump")
    tdoa_margin: float = Field(
        default=TDOA_MARGIN_M, ge=0,
        description="|tdoa| may exceed the two anchors' separation by this much (m) before it is refused")
    start: Optional[float] = Field(
        default=None, allow_inf_nan=False,
        description="use the IMU, UWB and TDoA rows stamped at or after this time [s] (ground truth kept whole)")
    end: Optional[float] = Field(
        default=None, allow_inf_nan=False,
        description="use the IMU, UWB and TDoA rows stamped at or before this time [s] (ground truth kept whole)")


@dataclass
class LoadReport:
    """What :func:`load_dataset` read and every repair it made."""

    path: Path
    files: dict[str, str] = field(default_factory=dict)
    rows_read: dict[str, int] = field(default_factory=dict)
    rows_kept: dict[str, int] = field(default_factory=dict)
    dropped: dict[str, int] = field(default_factory=dict)  # "imu: duplicate rows" -> count
    reordered: dict[str, int] = field(default_factory=dict)  # table -> rows that were out of order
    actions: list[str] = field(default_factory=list)  # human-readable repairs
    notes: list[str] = field(default_factory=list)  # harmless observations (extra columns...)
    #: structured warnings ``{"code", "file", "message", ...}`` (codes: :mod:`uwbimu.io.plausibility`)
    warnings: list[dict] = field(default_factory=list)

    def warn(self, code: str, file: str, message: str, **fields: Any) -> None:
        """Record a structured warning (announced by ``load_dataset`` as a :class:`LoadWarning`)."""
        self.warnings.append({"code": code, "file": file, "message": message,
                              **{k: _plain(v) for k, v in fields.items()}})

    @property
    def repaired(self) -> bool:
        return bool(self.actions)

    def summary(self) -> str:
        lines = [f"loaded {self.path}: " + ", ".join(f"{k} {v} rows" for k, v in self.rows_kept.items())]
        lines += [f"repair: {a}" for a in self.actions]
        lines += [f"note: {n}" for n in self.notes]
        lines += [f"warning ({w['code']}): {w['file']}: {w['message']}" for w in self.warnings]
        return "\n".join(lines)


# ---------------------------------------------------------------------------
# Locating rows in files
# ---------------------------------------------------------------------------
@dataclass
class _Source:
    """A table file and how to name a location in it."""

    table: str
    path: Path

    @property
    def name(self) -> str:
        return self.path.name

    @property
    def is_csv(self) -> bool:
        return self.path.suffix != ".parquet"

    def row_number(self, idx: int) -> int:
        """Location number of 0-based data row ``idx`` (CSV: file line, header = 1)."""
        return int(idx) + 2 if self.is_csv else int(idx) + 1

    def at(self, idx: Optional[int] = None, column: Optional[str] = None) -> str:
        parts = [self.name]
        if idx is not None:
            if self.is_csv:
                parts.append(f"line {int(idx) + 2} (data row {int(idx) + 1})")
            else:
                parts.append(f"data row {int(idx) + 1}")
        if column is not None:
            parts.append(f"column '{column}'")
        return ", ".join(parts)

    def rows_span(self, df: pd.DataFrame) -> str:
        if self.is_csv:
            return f"lines {int(df.index.min()) + 2}-{int(df.index.max()) + 2} (all data rows)"
        return f"data rows 1-{int(df.index.max()) + 1} (all)"

    def error(self, msg: str, idx: Optional[int] = None, column: Optional[str] = None,
              hint: Optional[str] = None) -> DatasetError:
        return DatasetError(f"{self.at(idx, column)}: {msg}", file=self.name,
                            row=None if idx is None else self.row_number(idx), column=column, hint=hint)


# ---------------------------------------------------------------------------
# Reading one table
# ---------------------------------------------------------------------------
def _find_table(folder: Path, table: str, required: bool) -> Optional[_Source]:
    found = [p for p in (folder / f"{table}.csv", folder / f"{table}.parquet") if p.is_file()]
    if len(found) > 1:
        raise DatasetError(
            f"{folder}: both {found[0].name} and {found[1].name} exist; keep only one of them",
            file=found[0].name)
    if not found:
        if required:
            present = sorted(p.name for p in folder.iterdir()) if folder.is_dir() else []
            raise DatasetError(
                f"{folder}: required file {table}.csv (or {table}.parquet) is missing; "
                f"the folder holds: {', '.join(present) if present else '(nothing)'}",
                file=f"{table}.csv")
        return None
    return _Source(table, found[0])


def _read_raw(src: _Source, columns: list[str]) -> pd.DataFrame:
    """Read a table file, keeping row positions aligned with file lines.

    ``columns`` are the required columns, named in the refusal of an empty file.
    """
    expected = ", ".join(repr(c) for c in columns)
    empty_msg = (f"{src.name}, line 1: file is empty (no header, no data); expected a header line with "
                 f"columns {expected} followed by data rows")
    if src.is_csv:
        if src.path.stat().st_size == 0:
            raise DatasetError(empty_msg, file=src.name, row=1, column=columns[0])
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", pd.errors.ParserWarning)
                # index_col=False: a first data row longer than the header must not turn the
                # first column into the index (pandas' default); such rows are refused below
                df = pd.read_csv(src.path, dtype={c: str for c in _TEXT_COLUMNS}, index_col=False,
                                 skip_blank_lines=False, skipinitialspace=True)
        except pd.errors.EmptyDataError:
            raise DatasetError(empty_msg, file=src.name, row=1, column=columns[0]) from None
        except pd.errors.ParserError as exc:
            line = _first_long_line(src.path)
            raise DatasetError(f"{src.name}{f', line {line}' if line else ''}: malformed CSV: {exc}",
                               file=src.name, row=line) from None
        except UnicodeDecodeError as exc:
            raise DatasetError(f"{src.name}: not a text CSV file ({exc})", file=src.name) from None
        if any(issubclass(w.category, pd.errors.ParserWarning) for w in caught):
            # pandas dropped the extra fields of rows longer than the header: refuse instead
            line = _first_long_line(src.path)
            raise DatasetError(f"{src.name}{f', line {line}' if line else ''}: the row has more fields than the "
                               f"header line; remove the extra fields or name them in the header",
                               file=src.name, row=line)
    else:
        require("pyarrow", "parquet", f"reading {src.name}")
        try:
            df = pd.read_parquet(src.path)
        except Exception as exc:  # pyarrow raises many types for a broken file
            raise DatasetError(f"{src.name}: cannot read parquet file: {exc}", file=src.name) from None
        df = df.reset_index(drop=True)
    df.columns = [str(c).strip() for c in df.columns]
    if src.is_csv:
        # pandas renames a repeated header name 'x' to 'x.1'; read the header
        # itself so a repeated column is refused instead of silently ignored.
        with open(src.path, newline="", encoding="utf-8", errors="replace") as fh:
            header = [h.strip() for h in next(csv.reader(fh), [])]
        seen: set[str] = set()
        for h in header:
            if h in seen:
                raise DatasetError(f"{src.name}, line 1 (header), column '{h}': the column appears more than "
                                   f"once in the header ({', '.join(header)})", file=src.name, row=1, column=h)
            seen.add(h)
    if src.is_csv and len(df) and not _first_column_complete(df):
        # Blank lines at the end of a file are not data: strip them.  Blank
        # lines inside the data are refused below (they would shift nothing,
        # but usually mean a broken export).
        blank = df.isna().all(axis=1).to_numpy()
        n_trailing = 0
        while n_trailing < len(blank) and blank[len(blank) - 1 - n_trailing]:
            n_trailing += 1
        if n_trailing:
            df = df.iloc[: len(df) - n_trailing]
        inner = np.flatnonzero(df.isna().all(axis=1).to_numpy())
        if len(inner):
            raise src.error("blank line inside the data; remove it", int(inner[0]))
    if len(df) == 0:
        where = "line 2" if src.is_csv else "data row 1"
        raise DatasetError(f"{src.name}, {where}: file has a header but no data rows "
                           f"(expected rows with columns {expected})",
                           file=src.name, row=2 if src.is_csv else 1, column=columns[0])
    return df


def _first_column_complete(df: pd.DataFrame) -> bool:
    """True when the first column is floats without NaN: then no row is blank (a blank line reads as a row of
    NaN in every column), and the two whole-frame NaN scans for blank rows are skipped (a 10-minute 1 kHz log:
    millions of cells)."""
    col = df.iloc[:, 0]
    if not (isinstance(col.dtype, np.dtype) and col.dtype.kind == "f"):
        return False
    return not bool(np.isnan(col.to_numpy()).any())


def _first_long_line(path: Path) -> Optional[int]:
    """Line number (header = 1) of the first row with more fields than the header (None: no such row)."""
    with open(path, newline="", encoding="utf-8", errors="replace") as fh:
        reader = csv.reader(fh, skipinitialspace=True)
        header = next(reader, [])
        for row in reader:
            if len(row) > len(header):
                return reader.line_num
    return None


def _require_columns(src: _Source, df: pd.DataFrame, required: list[str], report: LoadReport,
                     optional: tuple[str, ...] = ()) -> None:
    missing = [c for c in required if c not in df.columns]
    if missing:
        where = ", line 1 (header)" if src.is_csv else ""
        raise DatasetError(
            f"{src.name}{where}: missing column(s) {', '.join(repr(c) for c in missing)}; "
            f"found {', '.join(repr(c) for c in df.columns)}; required: {', '.join(required)}",
            file=src.name, row=1 if src.is_csv else None, column=missing[0])
    extra = [c for c in df.columns if c not in required and c not in optional]
    if extra:
        report.notes.append(f"{src.name}: extra column(s) ignored: {', '.join(extra)}")
    dup = df.columns[df.columns.duplicated()].tolist()
    if dup:
        raise DatasetError(f"{src.name}{', line 1 (header)' if src.is_csv else ''}: column(s) "
                           f"{', '.join(repr(c) for c in dup)} appear more than once in the header",
                           file=src.name, row=1 if src.is_csv else None, column=dup[0])


def _to_numeric(src: _Source, df: pd.DataFrame, columns: list[str]) -> pd.DataFrame:
    """Convert ``columns`` to float, refusing text, missing values, NaN and inf."""
    if all(df[c].dtype == np.float64 and np.isfinite(df[c].to_numpy()).all() for c in columns):
        # what the parser gives a clean log: already the floats the loop below would make (one check of
        # the block instead of a copy of the frame and a column assignment per column)
        return df
    out = df.copy()
    for col in columns:
        raw = df[col]
        if pd.api.types.is_bool_dtype(raw):
            raise src.error("boolean values where numbers are expected", int(raw.index[0]), col)
        if pd.api.types.is_numeric_dtype(raw):
            vals = raw.astype(float)
        else:
            vals = pd.to_numeric(raw, errors="coerce")
            bad = vals.isna() & raw.notna()
            if bad.any():
                i = bad.idxmax()
                raise src.error(f"non-numeric value {str(raw[i])!r}", i, col)
            vals = vals.astype(float)
        arr = vals.to_numpy()
        nan = np.isnan(arr)
        if nan.any():
            i = vals.index[int(np.argmax(nan))]
            raise src.error("missing or NaN value", i, col)
        inf = np.isinf(arr)
        if inf.any():
            i = vals.index[int(np.argmax(inf))]
            raise src.error(f"infinite value ({arr[int(np.argmax(inf))]})", i, col)
        out[col] = arr
    return out


def _to_text(src: _Source, df: pd.DataFrame, col: str) -> pd.DataFrame:
    """Normalise an id column to stripped, non-empty strings."""
    raw = df[col]
    if pd.api.types.is_float_dtype(raw):
        # Parquet with float ids: 3.0 -> "3" (never silently different ids).
        vals = raw.astype(float)
        if vals.isna().any():
            i = vals.index[int(np.argmax(vals.isna().to_numpy()))]
            raise src.error("empty id", i, col)
        if not np.all(np.mod(vals.to_numpy(), 1) == 0):
            i = vals.index[int(np.argmax(np.mod(vals.to_numpy(), 1) != 0))]
            raise src.error(f"id {fmt_num(vals[i])} is a non-integer number; use text ids", i, col)
        txt = vals.astype(np.int64).astype(str)
    else:
        missing = raw.isna()
        if missing.any():
            raise src.error("empty id", missing.idxmax(), col)
        txt = raw.astype(str).str.strip()
    empty = txt == ""
    if empty.any():
        raise src.error("empty id", empty.idxmax(), col)
    out = df.copy()
    out[col] = txt.astype(object)
    return out


def _sort_by_time(src: _Source, df: pd.DataFrame, report: LoadReport) -> pd.DataFrame:
    t = df["t"].to_numpy()
    out_of_order = int(np.sum(t < np.maximum.accumulate(t)))
    if out_of_order:
        df = df.sort_values("t", kind="stable")
        report.actions.append(f"{src.name}: sorted by t ({out_of_order} rows were out of order)")
        report.reordered[src.table] = out_of_order
    return df


def _check_time_order(src: _Source, df: pd.DataFrame, options: Optional[LoadOptions] = None,
                      report: Optional[LoadReport] = None) -> pd.DataFrame:
    """Refuse time going backwards; recognise a clock jump (monotonic before and after)."""
    t = df["t"].to_numpy()
    back = np.flatnonzero(np.diff(t) < 0)
    if not len(back):
        return df
    k = int(back[0])
    i_prev, i = df.index[k], df.index[k + 1]
    step = float(t[k] - t[k + 1])
    dt = np.diff(t)
    typical = float(np.median(dt[dt > 0])) if np.any(dt > 0) else 0.0
    if len(back) == 1 and typical > 0 and step > 5 * typical:
        # One backward step much larger than the sample interval, increasing on both sides: a clock
        # jump (reset), not shuffled rows. Sorting would interleave the two parts.
        if options is not None and options.clock_jumps == "split" and report is not None:
            before, after = df.iloc[: k + 1], df.iloc[k + 1:]
            keep, drop = (before, after) if len(before) >= len(after) else (after, before)
            report.warn("clock_jump", src.name, f"the clock jumps back by {step:.6g} s at "
                        f"{src.at(i).split(', ', 1)[1]}; kept the longer monotonic part ({len(keep)} rows), "
                        f"dropped {len(drop)} rows", t=float(t[k + 1]), size=-step, table=src.table,
                        rows_dropped=int(len(drop)))
            report.dropped[f"{src.table}: rows on the other side of a clock jump"] = int(len(drop))
            report.actions.append(f"{src.name}: split at a backward clock jump of {step:.6g} s, "
                                  f"dropped {len(drop)} rows")
            return keep
        raise src.error(
            f"the clock jumps back by {step:.6g} s (t={fmt_num(t[k + 1])} after t={fmt_num(t[k])} at "
            f"{src.at(i_prev).split(', ', 1)[1]}); the stamps increase before and after it, so this is a clock "
            f"jump, not shuffled rows (sorting would interleave the two parts)", i, "t",
            hint="--split-clock-jumps keeps the longer monotonic part and reports the jump")
    raise src.error(
        f"timestamp goes backwards: t={fmt_num(t[k + 1])} after t={fmt_num(t[k])} "
        f"(at {src.at(i_prev).split(', ', 1)[1]}); pass sort=True (--sort) to sort the rows by time",
        i, "t", hint="--sort sorts the rows by time")


def _drop_or_refuse_duplicates(src: _Source, df: pd.DataFrame, key: list[str], what: str,
                               options: LoadOptions, report: LoadReport) -> pd.DataFrame:
    """Refuse rows whose ``key`` repeats; drop exact repeats if asked to."""
    if "t" in key and len(df) > 1 and bool(np.all(np.diff(df["t"].to_numpy()) > 0)):
        # strictly increasing stamps: no key holding t can repeat (no hashing of every row)
        return df
    dup_key = df.duplicated(subset=key, keep="first")
    if not dup_key.any():
        return df
    exact = df.duplicated(keep="first")
    if options.drop_duplicate_rows:
        conflicting = dup_key & ~exact
        if conflicting.any():
            i = conflicting.idxmax()
            first = df.index[(df[key] == df.loc[i, key]).all(axis=1).to_numpy()][0]
            raise src.error(
                f"duplicate {what} {_key_text(df, i, key)} with different values than "
                f"{src.at(first).split(', ', 1)[1]}; cannot choose which to keep", i, key[-1] if len(key) > 1 else key[0])
        n = int(exact.sum())
        report.dropped[f"{src.table}: duplicate rows"] = n
        report.actions.append(f"{src.name}: dropped {n} exact duplicate row(s)")
        return df[~exact]
    i = dup_key.idxmax()
    first = df.index[(df[key] == df.loc[i, key]).all(axis=1).to_numpy()][0]
    hint = ("; it repeats that row exactly: pass drop_duplicate_rows=True (--drop-duplicates) to drop such rows"
            if exact[i] else "; the values differ, fix the file")
    raise src.error(f"duplicate {what} {_key_text(df, i, key)}, first at "
                    f"{src.at(first).split(', ', 1)[1]}{hint}", i, key[0],
                    hint="--drop-duplicates drops exact repeats" if exact[i] else None)


def _key_text(df: pd.DataFrame, i, key: list[str]) -> str:
    return ", ".join(f"{k}={fmt_num(df.loc[i, k])}" if k == "t" else f"{k}={str(df.loc[i, k])!r}" for k in key)


# ---------------------------------------------------------------------------
# Per-table validation
# ---------------------------------------------------------------------------
def _load_imu(src: _Source, options: LoadOptions, report: LoadReport) -> pd.DataFrame:
    df = _read_raw(src, IMU_COLUMNS)
    report.rows_read["imu"] = len(df)
    _require_columns(src, df, IMU_COLUMNS, report)
    df = _to_numeric(src, df, IMU_COLUMNS)
    if options.sort:
        df = _sort_by_time(src, df, report)
    df = _check_time_order(src, df, options, report)
    df = _drop_or_refuse_duplicates(src, df, ["t"], "IMU timestamp", options, report)
    if options.gyro_units == "deg/s":
        df[["wx", "wy", "wz"]] = df[["wx", "wy", "wz"]] * (math.pi / 180.0)
        report.actions.append(f"{src.name}: gyro converted from deg/s to rad/s (x pi/180)")
    if options.accel_units == "g":
        df[["ax", "ay", "az"]] = df[["ax", "ay", "az"]] * 9.81
        report.actions.append(f"{src.name}: accelerometer converted from g to m/s^2 (x 9.81)")
    if options.check_units:
        _check_imu_units(src, df)
    return df[IMU_COLUMNS]


def _check_imu_units(src: _Source, df: pd.DataFrame) -> None:
    acc = df[["ax", "ay", "az"]].to_numpy()
    gyr = df[["wx", "wy", "wz"]].to_numpy()
    a_med = float(np.median(np.linalg.norm(acc, axis=1)))
    where = src.rows_span(df)
    if 0.5 <= a_med <= 2.0:
        raise DatasetError(
            f"{src.name}, {where}, columns 'ax', 'ay', 'az': the accelerometer looks like it is in g "
            f"(median |a| = {a_med:.3f}, expected about 9.81 m/s^2 with gravity included); "
            f"multiply ax, ay, az by 9.81 or load with accel_units='g' (--accel-units g)",
            file=src.name, row=src.row_number(df.index[0]), column="ax", hint="--accel-units g converts from g")
    if not ACCEL_NORM_BAND[0] <= a_med <= ACCEL_NORM_BAND[1]:
        hint = ("gravity seems to have been removed; this toolkit needs specific force (gravity included)"
                if a_med < ACCEL_NORM_BAND[0] else "the unit looks wrong (mg? ft/s^2?); m/s^2 is expected")
        raise DatasetError(
            f"{src.name}, {where}, columns 'ax', 'ay', 'az': median |a| = {a_med:.3g} is implausible for "
            f"specific force in m/s^2 (about 9.81 expected): {hint}",
            file=src.name, row=src.row_number(df.index[0]), column="ax")
    w_norm = np.linalg.norm(gyr, axis=1)
    w99 = float(np.percentile(w_norm, 99))
    if w99 > GYRO_MAX_RAD_S:
        raise DatasetError(
            f"{src.name}, {where}, columns 'wx', 'wy', 'wz': the gyro looks like it is in deg/s "
            f"(99th percentile of |w| = {w99:.1f}, above the {GYRO_MAX_RAD_S:.1f} rad/s (2000 deg/s) full "
            f"scale of MEMS gyros); multiply wx, wy, wz by pi/180 or load with gyro_units='deg/s' "
            f"(--gyro-units deg)",
            file=src.name, row=src.row_number(df.index[0]), column="wx", hint="--gyro-units deg converts from deg/s")


def _check_gyro_against_truth(src: _Source, imu: pd.DataFrame, gt: pd.DataFrame) -> None:
    """Compare gyro magnitude with the ground-truth rotation rate (catches slow deg/s data)."""
    t_gt = gt["t"].to_numpy()
    q = gt[["qw", "qx", "qy", "qz"]].to_numpy()
    # Rotation rate over ~0.1 s windows: robust to jittered mocap stamps.
    step = max(1, int(round(0.1 / max(np.median(np.diff(t_gt)), 1e-6)))) if len(t_gt) > 1 else 1
    if len(t_gt) <= step + 2:
        return
    dots = np.abs(np.sum(q[step:] * q[:-step], axis=1)).clip(0.0, 1.0)
    dt = t_gt[step:] - t_gt[:-step]
    ok = dt > 0
    if not ok.any():
        return
    rate_gt = 2.0 * np.arccos(dots[ok]) / dt[ok]
    g90 = float(np.percentile(rate_gt, 90))
    t0, t1 = t_gt[0], t_gt[-1]
    t_imu = imu["t"].to_numpy()
    sel = (t_imu >= t0) & (t_imu <= t1)
    if g90 < 0.1 or sel.sum() < 10:
        return  # not enough rotation to tell
    w90 = float(np.percentile(np.linalg.norm(imu[["wx", "wy", "wz"]].to_numpy()[sel], axis=1), 90))
    ratio = w90 / g90
    if 25.0 < ratio < 130.0:
        raise DatasetError(
            f"{src.name}, {src.rows_span(imu)}, columns 'wx', 'wy', 'wz': the gyro looks like it is in deg/s "
            f"(90th percentile |w| = {w90:.2f} is {ratio:.0f} times the ground-truth rotation rate "
            f"{g90:.3f} rad/s; 57.3 is expected for deg/s); multiply wx, wy, wz by pi/180 or load with "
            f"gyro_units='deg/s' (--gyro-units deg)",
            file=src.name, row=src.row_number(imu.index[0]), column="wx", hint="--gyro-units deg converts from deg/s")


def _load_uwb(src: _Source, options: LoadOptions, report: LoadReport) -> pd.DataFrame:
    df = _read_raw(src, UWB_COLUMNS)
    report.rows_read["uwb"] = len(df)
    _require_columns(src, df, UWB_COLUMNS, report, optional=("tag",))
    df = _to_numeric(src, df, ["t", "range"])
    df = _to_text(src, df, "anchor")
    has_tag = "tag" in df.columns
    if has_tag:
        df = _to_text(src, df, "tag")
    if options.sort:
        df = _sort_by_time(src, df, report)
    df = _check_time_order(src, df, options, report)
    r = df["range"].to_numpy()
    bad = np.flatnonzero(r <= 0)
    if len(bad):
        i = df.index[bad[0]]
        raise src.error(f"range {fmt_num(r[bad[0]])} m is not positive", i, "range")
    bad = np.flatnonzero(r > options.max_range)
    if len(bad):
        i = df.index[bad[0]]
        raise src.error(f"range {fmt_num(r[bad[0]])} m is absurd (> {options.max_range:g} m); ranges are in metres",
                        i, "range")
    key = ["t", "anchor"] + (["tag"] if has_tag else [])
    df = _drop_or_refuse_duplicates(src, df, key, "range (same time and anchor)", options, report)
    return df[UWB_COLUMNS + (["tag"] if has_tag else [])]


def _refuse_same_anchor(src: _Source, df: pd.DataFrame) -> None:
    same = np.flatnonzero((df["anchor_a"] == df["anchor_b"]).to_numpy())
    if len(same):
        i = df.index[same[0]]
        raise src.error(f"anchor_a and anchor_b are the same anchor '{df.loc[i, 'anchor_a']}'; a pair "
                        f"needs two different anchors", i, "anchor_b")


def _load_tdoa(src: _Source, options: LoadOptions, report: LoadReport) -> pd.DataFrame:
    """``tdoa.csv``: ``t, anchor_a, anchor_b, tdoa [, tag]`` (anchor checks come later)."""
    df = _read_raw(src, TDOA_COLUMNS)
    report.rows_read["tdoa"] = len(df)
    _require_columns(src, df, TDOA_COLUMNS, report, optional=("tag",))
    df = _to_numeric(src, df, ["t", "tdoa"])
    df = _to_text(src, df, "anchor_a")
    df = _to_text(src, df, "anchor_b")
    has_tag = "tag" in df.columns
    if has_tag:
        df = _to_text(src, df, "tag")
    _refuse_same_anchor(src, df)
    if options.sort:
        df = _sort_by_time(src, df, report)
    df = _check_time_order(src, df, options, report)
    key = ["t", "anchor_a", "anchor_b"] + (["tag"] if has_tag else [])
    df = _drop_or_refuse_duplicates(src, df, key, "TDoA (same time and anchor pair)", options, report)
    return df[TDOA_COLUMNS + (["tag"] if has_tag else [])]


def _load_anchor_ranges(src: _Source, options: LoadOptions, report: LoadReport) -> pd.DataFrame:
    """``anchor_ranges.csv``: measured anchor-to-anchor ranges (several per pair allowed)."""
    df = _read_raw(src, ANCHOR_RANGE_COLUMNS)
    report.rows_read["anchor_ranges"] = len(df)
    _require_columns(src, df, ANCHOR_RANGE_COLUMNS, report, optional=("sd",))
    df = _to_text(src, df, "anchor_a")
    df = _to_text(src, df, "anchor_b")
    df = _to_numeric(src, df, ["range"])
    _refuse_same_anchor(src, df)
    r = df["range"].to_numpy()
    bad = np.flatnonzero((r <= 0) | (r > options.max_range))
    if len(bad):
        i = df.index[bad[0]]
        raise src.error(f"range {fmt_num(r[bad[0]])} m is not in (0, {options.max_range:g}] m", i, "range")
    if "sd" in df.columns:
        df["sd"] = parse_range_sd(src, df)
    return df[ANCHOR_RANGE_COLUMNS + (["sd"] if "sd" in df.columns else [])]


def _quaternion_group(src: _Source, df: pd.DataFrame, columns: list[str], what: str,
                      name_found: bool = False) -> list[str]:
    """The quaternion columns present: all four or none (a partial group is refused, naming the missing)."""
    present = [c for c in columns if c in df.columns]
    if present and len(present) != 4:
        missing = [c for c in columns if c not in present]
        found = f", found {', '.join(map(str, df.columns))}" if name_found else ""
        raise DatasetError(f"{src.name}: {what} must come as qw, qx, qy, qz together; missing "
                           f"{', '.join(missing)}{found}", file=src.name,
                           row=1 if src.is_csv else None, column=missing[0])
    return present


def _load_anchors(src: _Source, options: LoadOptions, report: LoadReport) -> pd.DataFrame:
    df = _read_raw(src, ANCHOR_COLUMNS)
    report.rows_read["anchors"] = len(df)
    _require_columns(src, df, ANCHOR_COLUMNS, report, optional=tuple(ANCHOR_QUAT_COLUMNS) + ("surveyed",))
    quat = _quaternion_group(src, df, list(ANCHOR_QUAT_COLUMNS), "antenna orientation columns")
    df = _to_text(src, df, "anchor")
    df = _to_numeric(src, df, ["x", "y", "z"] + quat)
    df = _drop_or_refuse_duplicates(src, df, ["anchor"], "anchor id", options, report)
    if quat:
        q = df[ANCHOR_QUAT_COLUMNS].to_numpy()
        n = np.linalg.norm(q, axis=1)
        bad = np.flatnonzero(np.abs(n - 1.0) > QUAT_NORM_TOL)
        if len(bad):
            raise src.error(f"antenna orientation (qw, qx, qy, qz) has norm {n[bad[0]]:.4f}, not 1 "
                            f"(a unit Hamilton quaternion, antenna frame -> world, is expected)",
                            df.index[bad[0]], "qw")
        df[ANCHOR_QUAT_COLUMNS] = q / n[:, None]
    if "surveyed" in df.columns:
        df["surveyed"] = parse_surveyed(src, df)
    return df[ANCHOR_COLUMNS + (ANCHOR_QUAT_COLUMNS if quat else []) + (["surveyed"] if "surveyed" in df.columns else [])]


def _check_anchor_ids(src: _Source, df: pd.DataFrame, columns: tuple[str, ...], anchors_src: _Source,
                      known: set[str]) -> None:
    """Every anchor id in ``columns`` of ``df`` must be in anchors.csv."""
    for col in columns:
        unknown = [a for a in pd.unique(df[col]) if a not in known]
        if unknown:
            firsts = [f"'{a}' (first at {src.at(df.index[(df[col] == a).to_numpy()][0]).split(', ', 1)[1]})"
                      for a in unknown]
            i0 = df.index[(df[col] == unknown[0]).to_numpy()][0]
            raise DatasetError(
                f"{src.name}, column '{col}': anchor id(s) used in {src.name} but missing from "
                f"{anchors_src.name}: {', '.join(firsts)}; {anchors_src.name} has: {', '.join(sorted(known))}",
                file=src.name, row=src.row_number(i0), column=col)


def _tdoa_separation(tdoa: pd.DataFrame, anchors: pd.DataFrame) -> np.ndarray:
    """Distance between the two anchors of every TDoA row [m]."""
    pos = {a: np.array([x, y, z]) for a, x, y, z in anchors[["anchor", "x", "y", "z"]].itertuples(index=False)}
    pa = np.array([pos[a] for a in tdoa["anchor_a"]])
    pb = np.array([pos[b] for b in tdoa["anchor_b"]])
    return np.linalg.norm(pa - pb, axis=1)


def _check_tdoa_unit(src: _Source, tdoa: pd.DataFrame, anchors: pd.DataFrame, margin: float) -> None:
    """Refuse a tdoa column that is not in metres as a whole, naming the unit it looks like.

    Seconds: every |tdoa| below :data:`TDOA_SECONDS_MAX` while the anchors are metres apart (a range
    difference of metres is tens of nanoseconds).  DW1000 ticks (15.65 ps, 4.69 mm each) or raw
    timestamps: most rows exceed the anchors' separation plus the margin, or the median |tdoa| is more
    than :data:`TDOA_UNIT_RATIO` times the largest separation (whatever the margin).  Single rows
    beyond the separation are left to :func:`_check_tdoa_bound` (outliers).
    """
    val = np.abs(tdoa["tdoa"].to_numpy(float))
    sep = _tdoa_separation(tdoa, anchors)
    if not len(val) or sep.max() <= 0.1:
        return
    first = tdoa.index[0]
    if val.max() < TDOA_SECONDS_MAX:
        raise src.error(
            f"every |tdoa| is below {TDOA_SECONDS_MAX:g} (largest {val.max():.3g}) while the anchors are up to "
            f"{sep.max():.2f} m apart: the values look like seconds; tdoa is the range difference in metres "
            f"(time difference x c, c = 299792458 m/s)", first, "tdoa")
    over = val > sep + margin
    if over.mean() > 0.5 or np.median(val) > TDOA_UNIT_RATIO * sep.max():
        in_ticks = np.mean(val * DW1000_TICK_M <= sep + margin) > 0.9
        unit = (f"DW1000 ticks (15.65 ps, {DW1000_TICK_M * 1e3:.2f} mm each: multiply by {DW1000_TICK_M:.6g} "
                f"to get metres)" if in_ticks else "clock ticks or raw timestamps, not a range difference in metres")
        raise src.error(
            f"{int(over.sum())} of {len(val)} rows have |tdoa| beyond the anchors' separation plus the {margin:g} m "
            f"margin (median |tdoa| {np.median(val):.4g}, largest separation {sep.max():.2f} m): the values look "
            f"like {unit}", first, "tdoa")


def _check_tdoa_bound(src: _Source, tdoa: pd.DataFrame, anchors: pd.DataFrame, margin: float) -> None:
    """|tdoa| cannot exceed the anchors' separation (triangle inequality) plus a noise margin."""
    sep = _tdoa_separation(tdoa, anchors)
    val = tdoa["tdoa"].to_numpy()
    bad = np.flatnonzero(np.abs(val) > sep + margin)
    if len(bad):
        k = int(bad[0])
        i = tdoa.index[k]
        raise src.error(
            f"|tdoa| = {abs(val[k]):.3f} m exceeds the separation {sep[k]:.3f} m of anchors "
            f"'{tdoa.loc[i, 'anchor_a']}' and '{tdoa.loc[i, 'anchor_b']}' plus the {margin:g} m margin "
            f"({len(bad)} such row(s)); a range difference cannot exceed the anchors' distance: check the "
            f"unit (metres expected, not seconds or ticks) and the anchor positions", i, "tdoa",
            hint="--tdoa-margin widens the margin if these are genuine outliers")


def _load_groundtruth(src: _Source, options: LoadOptions, report: LoadReport) -> pd.DataFrame:
    df = _read_raw(src, GT_COLUMNS)
    report.rows_read["groundtruth"] = len(df)
    quat = ["qw", "qx", "qy", "qz"]
    present_q = _quaternion_group(src, df, quat, "attitude columns", name_found=True)
    has_q = bool(present_q)
    if not has_q:
        # a position-only ground truth (e.g. a total station): accepted, attitude not compared -- said once
        report.warn("groundtruth_without_attitude", src.name,
                    "no attitude columns (qw, qx, qy, qz): positions only; attitude errors are not computed",
                    missing_columns=quat)
    required = GT_COLUMNS if has_q else [c for c in GT_COLUMNS if c not in quat]
    _require_columns(src, df, required, report, optional=tuple(GT_VEL_COLUMNS))
    vel = [c for c in GT_VEL_COLUMNS if c in df.columns]
    if vel and len(vel) != 3:
        missing = [c for c in GT_VEL_COLUMNS if c not in vel]
        raise DatasetError(f"{src.name}: velocity columns must come as vx, vy, vz together; "
                           f"missing {', '.join(missing)}, found {', '.join(map(str, df.columns))}", file=src.name,
                           row=1 if src.is_csv else None, column=missing[0])
    df = _to_numeric(src, df, required + vel)
    if options.sort:
        df = _sort_by_time(src, df, report)
    df = _check_time_order(src, df, options, report)
    df = _drop_or_refuse_duplicates(src, df, ["t"], "ground-truth timestamp", options, report)
    if not has_q:
        return df[required + vel]
    q = df[["qw", "qx", "qy", "qz"]].to_numpy()
    n = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(np.abs(n - 1.0) > QUAT_NORM_TOL)
    if len(bad):
        i = df.index[bad[0]]
        raise src.error(f"quaternion (qw, qx, qy, qz) has norm {n[bad[0]]:.4f}, not 1 "
                        f"(columns qw..qz must hold a unit Hamilton quaternion)", i, "qw")
    # Renormalise small rounding deviations (not a repair: the rotation is
    # unchanged); rows already unit to 1e-9 are left bit-exact.
    fix = np.abs(n - 1.0) > 1e-9
    if fix.any():
        q[fix] = q[fix] / n[fix, None]
        df[["qw", "qx", "qy", "qz"]] = q
    return df[GT_COLUMNS + vel]


# ---------------------------------------------------------------------------
# dataset.yaml
# ---------------------------------------------------------------------------
def load_meta(path: str | Path) -> DatasetMeta:
    """Read and validate a ``dataset.yaml``; errors name the file, line and key."""
    return _read_meta(Path(path))[0]


def _read_meta(path: Path) -> tuple[DatasetMeta, str]:
    """``dataset.yaml`` as :class:`DatasetMeta` and its text (for the lines of later refusals)."""
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise DatasetError(f"{path.name}: cannot read: {exc.strerror or exc}", file=path.name) from None
    bad = find_non_utf8(raw)
    text = decode_text(raw, path.name, what="dataset metadata",
                       error=lambda m: DatasetError(m, file=path.name, row=bad.line if bad else None))
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = mark.line + 1 if mark is not None else None
        raise DatasetError(f"{path.name}{f', line {line}' if line else ''}: invalid YAML: {exc}",
                           file=path.name, row=line) from None
    if data is None:
        return DatasetMeta(), text
    if not isinstance(data, dict):
        raise DatasetError(f"{path.name}: must hold a mapping of keys (name, description, ...), "
                           f"got {type(data).__name__}", file=path.name, row=1)
    _refuse_non_finite_meta(path, data, text)
    try:
        meta = DatasetMeta.model_validate(data)
    except ValidationError as exc:
        problems = []
        first_line, first_key = None, None
        for err in exc.errors():
            loc = tuple(err["loc"])
            key = ".".join(str(k) for k in loc)
            line = yaml_line(text, loc)
            if first_key is None:
                first_line, first_key = line, key
            msg = "unknown key (not allowed here)" if err["type"] == "extra_forbidden" else err["msg"]
            problems.append(f"{path.name}{f', line {line}' if line else ''}, key '{key}': {msg}"
                            f" (got {err.get('input')!r})")
        allowed = ", ".join(DatasetMeta.model_fields)
        raise DatasetError("; ".join(problems) + f". Top-level keys allowed: {allowed}",
                           file=path.name, row=first_line, column=first_key) from None
    # strings such as "inf" that a float field read as a number
    _refuse_non_finite_meta(path, meta.model_dump(), text)
    return meta, text


def _refuse_non_finite_meta(path: Path, data: dict, text: str) -> None:
    found = find_non_finite(data)
    if found is not None:
        loc, value = found
        key = ".".join(str(k) for k in loc)
        line = yaml_line(text, loc)
        raise DatasetError(f"{path.name}{f', line {line}' if line else ''}, key '{key}': {value} is not a finite "
                           f"number; dataset.yaml holds finite numbers only", file=path.name, row=line, column=key)


def _check_meta_ids(meta: DatasetMeta, meta_name: str, text: Optional[str], anchors_src: _Source, known: set[str],
                    tagged: list[tuple[_Source, pd.DataFrame]]) -> None:
    """dataset.yaml against the tables: ``known_anchor_bias`` ids must be anchors of anchors.csv, and the
    ``tag`` ids of uwb.csv / tdoa.csv must be tags of dataset.yaml when the file lists its tags."""
    for a in (meta.known_anchor_bias or {}):
        if a not in known:
            loc = ("known_anchor_bias", a)
            line = yaml_line(text, loc) if text is not None else None
            raise DatasetError(f"{meta_name}{f', line {line}' if line else ''}, key 'known_anchor_bias.{a}': anchor "
                               f"{a!r} is not in {anchors_src.name} (which has: {', '.join(sorted(known))}); its "
                               f"bias would be ignored", file=meta_name, row=line, column=f"known_anchor_bias.{a}")
    if "tags" not in meta.model_fields_set:
        return  # tags not listed: every tag of the tables takes the defaults (no lever arm)
    declared = [t.name for t in meta.tags]
    for src, df in tagged:
        if "tag" not in df.columns:
            continue
        unknown = [g for g in pd.unique(df["tag"]) if g not in declared]
        if unknown:
            i0 = df.index[(df["tag"] == unknown[0]).to_numpy()][0]
            raise src.error(f"tag id(s) {', '.join(repr(g) for g in unknown)} are not among the tags of {meta_name} "
                            f"({', '.join(repr(g) for g in declared)}); their lever arm would be unknown", i0, "tag",
                            hint=f"name every tag of {src.name} under tags: in {meta_name}")


# ---------------------------------------------------------------------------
# The loader
# ---------------------------------------------------------------------------
def _time_span(opts: LoadOptions, report: "LoadReport", **tables):
    """The tables cut to ``[opts.start, opts.end]`` (counted in the report); a span that leaves no IMU or
    no UWB/TDoA row is a :class:`DatasetError`."""
    lo = -np.inf if opts.start is None else float(opts.start)
    hi = np.inf if opts.end is None else float(opts.end)
    if not lo < hi:
        raise DatasetError(f"--start {opts.start} s is not before --end {opts.end} s")
    out = []
    for name, df in tables.items():
        if df is not None:
            keep = (df["t"] >= lo) & (df["t"] <= hi)
            if (~keep).any():
                report.actions.append(f"{name}: {int((~keep).sum())} row(s) outside --start/--end "
                                      f"[{opts.start}, {opts.end}] s left out")
            df = df[keep]
        out.append(df)
    imu, uwb, tdoa = out
    if len(imu) < 10 or (len(uwb) == 0 and (tdoa is None or len(tdoa) == 0)):
        raise DatasetError(f"--start/--end [{opts.start}, {opts.end}] s leaves {len(imu)} IMU rows and no "
                           f"usable measurement span", hint="choose a span inside the log (uwbimu check shows it)")
    return imu, uwb, tdoa


def load_dataset(path: str | Path, options: Optional[LoadOptions] = None, **kwargs: Any) -> Dataset:
    """Read and validate a dataset folder.

    Parameters
    ----------
    path : the dataset folder (or its ``dataset.yaml``).
    options : :class:`LoadOptions`; keyword arguments (``drop_duplicate_rows=True``,
        ``sort=True``, ``gyro_units="deg/s"``, ...) are accepted as a shortcut.

    Returns
    -------
    Dataset with ``imu`` (IMU clock, m/s^2, rad/s, IMU frame), ``uwb`` (UWB
    clock, anchor ids as strings, m), ``anchors`` (world, m), optional
    ``groundtruth`` (UWB clock) and ``meta``; ``ds.report`` is the
    :class:`LoadReport` (rows read/kept, repairs made).

    Raises
    ------
    DatasetError
        naming the file, the row (CSV: line with the header as line 1) and the column.
    """
    if options is None:
        options = LoadOptions(**kwargs)
    elif kwargs:
        options = options.model_copy(update=kwargs)
    folder = Path(path)
    if folder.is_file() and folder.name in ("dataset.yaml", "dataset.yml"):
        folder = folder.parent
    if not folder.exists():
        raise DatasetError(f"{folder}: no such dataset folder", file=str(folder))
    if not folder.is_dir():
        raise DatasetError(f"{folder}: a dataset is a folder (imu.csv, uwb.csv, anchors.csv, ...), "
                           f"not a file", file=str(folder))
    report = LoadReport(path=folder)

    tdoa_src = _find_table(folder, "tdoa", False)
    srcs = {
        "imu": _find_table(folder, "imu", True),
        "uwb": _find_table(folder, "uwb", tdoa_src is None),
        "tdoa": tdoa_src,
        "anchors": _find_table(folder, "anchors", True),
        "anchor_ranges": _find_table(folder, "anchor_ranges", False),
        "groundtruth": _find_table(folder, "groundtruth", False),
    }
    for k, s in srcs.items():
        if s is not None:
            report.files[k] = s.name

    meta_path = next((folder / n for n in ("dataset.yaml", "dataset.yml") if (folder / n).is_file()), None)
    meta, meta_text = _read_meta(meta_path) if meta_path is not None else (DatasetMeta(), None)
    if meta_path is not None:
        report.files["meta"] = meta_path.name

    imu = _load_imu(srcs["imu"], options, report)
    if srcs["uwb"] is not None:
        uwb = _load_uwb(srcs["uwb"], options, report)
    else:
        uwb = pd.DataFrame({"t": pd.Series(dtype=float), "anchor": pd.Series(dtype=object),
                            "range": pd.Series(dtype=float)})
    tdoa = _load_tdoa(srcs["tdoa"], options, report) if srcs["tdoa"] else None
    anchors = _load_anchors(srcs["anchors"], options, report)
    anchor_ranges = (_load_anchor_ranges(srcs["anchor_ranges"], options, report)
                     if srcs["anchor_ranges"] else None)
    gt = _load_groundtruth(srcs["groundtruth"], options, report) if srcs["groundtruth"] else None

    # Every anchor that ranges must have a position.
    known = set(anchors["anchor"])
    if srcs["uwb"] is not None:
        _check_anchor_ids(srcs["uwb"], uwb, ("anchor",), srcs["anchors"], known)
    if tdoa is not None:
        _check_anchor_ids(srcs["tdoa"], tdoa, ("anchor_a", "anchor_b"), srcs["anchors"], known)
        _check_tdoa_unit(srcs["tdoa"], tdoa, anchors, options.tdoa_margin)
        _check_tdoa_bound(srcs["tdoa"], tdoa, anchors, options.tdoa_margin)
    if anchor_ranges is not None:
        _check_anchor_ids(srcs["anchor_ranges"], anchor_ranges, ("anchor_a", "anchor_b"), srcs["anchors"], known)
    _check_meta_ids(meta, meta_path.name if meta_path is not None else "dataset.yaml", meta_text, srcs["anchors"],
                    known, [(srcs[k], df) for k, df in (("uwb", uwb), ("tdoa", tdoa)) if srcs[k] is not None])

    # Time base, rates and physics across tables (see uwbimu.io.plausibility).
    timed = {"imu": (srcs["imu"], imu)}
    for name, df in (("uwb", uwb if srcs["uwb"] is not None else None), ("tdoa", tdoa), ("groundtruth", gt)):
        if df is not None:
            timed[name] = (srcs[name], df)
    plausibility.check_time_base(timed, options.lenient, report.warn)
    plausibility.check_imu_physics(srcs["imu"], imu, report.warn)
    plausibility.check_coordinates(srcs["anchors"], anchors, ["x", "y", "z"], "anchor")
    if gt is not None:
        plausibility.check_coordinates(srcs["groundtruth"], gt, ["px", "py", "pz"], "ground-truth")
    plausibility.check_anchor_geometry(srcs["anchors"], anchors, options.lenient, report.warn)

    if gt is not None and "qw" in gt.columns and options.check_units and options.gyro_units == "rad/s":
        _check_gyro_against_truth(srcs["imu"], imu, gt)

    if options.start is not None or options.end is not None:
        imu, uwb, tdoa = _time_span(options, report, imu=imu, uwb=uwb, tdoa=tdoa)
    for name, df in (("imu", imu), ("uwb", uwb), ("tdoa", tdoa), ("anchors", anchors),
                     ("anchor_ranges", anchor_ranges), ("groundtruth", gt)):
        if df is not None:
            report.rows_kept[name] = len(df)
    ds = Dataset(
        imu=imu.reset_index(drop=True),
        uwb=uwb.reset_index(drop=True),
        anchors=anchors.reset_index(drop=True),
        groundtruth=None if gt is None else gt.reset_index(drop=True),
        meta=meta,
        path=folder,
        report=report,
        tdoa=None if tdoa is None else tdoa.reset_index(drop=True),
        anchor_ranges=None if anchor_ranges is None else anchor_ranges.reset_index(drop=True),
    )
    if report.actions:
        warnings.warn("; ".join(report.actions), LoadRepairWarning, stacklevel=2)
    for w in report.warnings:
        warnings.warn(f"{w['file']}: {w['message']}", LoadWarning, stacklevel=2)
    return ds
