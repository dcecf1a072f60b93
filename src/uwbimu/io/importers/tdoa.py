"""TDoA rows of an importer: the ``tdoa`` table from id arrays, and the rows no geometry allows.

A range difference ``|p - p_b| - |p - p_a|`` cannot exceed the two anchors'
separation ``|p_a - p_b|`` (triangle inequality).  The dataset loader refuses a
``tdoa.csv`` with a row beyond that bound plus a margin (``--tdoa-margin``,
1 m by default), which catches values in seconds or clock ticks.  A real log
(the Loco TDoA3 logs of UTIL, for one) also holds a few isolated values of
tens of metres (corrupted packets); an importer drops those rows with
:func:`drop_tdoa_outliers`, counted per anchor pair in the import changes and
in ``dataset.yaml`` (``extra.tdoa_outliers``), instead of refusing the flight.
When more than :data:`MAX_OUTLIER_FRACTION` of the rows are beyond the bound
the values are not outliers (wrong unit, wrong anchors file): that is refused.
"""

from __future__ import annotations

from uwbimu.errors import UsageError
from typing import Optional

import numpy as np
import pandas as pd

from uwbimu.io.dataset import TDOA_COLUMNS
from uwbimu.io.loader import TDOA_MARGIN_M, DatasetError, LoadOptions

__all__ = ["tdoa_table", "drop_tdoa_outliers", "tdoa_load_options", "MAX_OUTLIER_FRACTION", "TDOA_MARGIN_M"]

#: Above this fraction of rows beyond ``separation + margin`` the import is refused.
MAX_OUTLIER_FRACTION = 0.05


def tdoa_table(t: np.ndarray, id_a, id_b, diff, anchors: pd.DataFrame, source: str, what: str,
               first: int = 0) -> pd.DataFrame:
    """``tdoa`` frame from id arrays; refuses non-finite values and ids not in ``anchors``.

    Errors name ``source``, then ``what`` and the row number ``i + first``
    (e.g. ``what="line", first=2`` for a CSV with a header).
    """
    a = np.asarray(id_a)
    b = np.asarray(id_b)
    diff = np.asarray(diff, dtype=float)
    bad = ~np.isfinite(diff)
    if bad.any():
        i = int(np.argmax(bad))
        raise DatasetError(f"{source}, {what} {i + first}: TDoA value is not finite ('{diff[i]}')", file=source,
                           row=i + first, column="tdoa")
    fmt = np.vectorize(lambda v: str(int(v)) if float(v).is_integer() else str(v), otypes=[object])
    sa, sb = (fmt(a), fmt(b)) if len(a) else (a.astype(str), b.astype(str))
    known = set(anchors["anchor"].astype(str))
    for col, ids in (("anchor_a", sa), ("anchor_b", sb)):
        unknown = ~np.isin(ids, list(known))
        if unknown.any():
            i = int(np.argmax(unknown))
            raise DatasetError(f"{source}, {what} {i + first}, column '{col}': anchor id '{ids[i]}' is not in "
                               f"the anchors file ({', '.join(map(str, sorted(known)))})", file=source, row=i + first, column=col)
    return pd.DataFrame({"t": t, "anchor_a": sa.astype(str), "anchor_b": sb.astype(str), "tdoa": diff},
                        columns=TDOA_COLUMNS)


def drop_tdoa_outliers(tdoa: pd.DataFrame, anchors: pd.DataFrame, margin: float, source: str,
                       changes: list[str]) -> tuple[pd.DataFrame, dict]:
    """Drop the rows whose ``|tdoa|`` exceeds the anchors' separation plus ``margin`` (m).

    The bound is the loader's (``LoadOptions.tdoa_margin``), so the written
    dataset loads with the same margin.

    Returns
    -------
    (kept rows, record) where ``record`` holds ``margin_m``, ``rows_read``,
    ``rows_dropped``, ``by_pair`` (``"a-b"`` -> count), ``largest_abs_tdoa_m`` and
    ``first_t`` (the latter two only when rows were dropped).  A sentence with
    the counts per pair is appended to ``changes``.

    Raises
    ------
    DatasetError : more than :data:`MAX_OUTLIER_FRACTION` of the rows are beyond
        the bound (a unit or anchors-file problem, not outliers).
    """
    if not margin >= 0:
        raise UsageError(f"margin must be >= 0 m, got {margin!r}")
    if margin > TDOA_MARGIN_M:
        changes.append(f"{source}: TDoA rows kept up to the anchors' separation + {margin:g} m (wider than the "
                       f"loader's default {TDOA_MARGIN_M:g} m): read this dataset with --tdoa-margin {margin:g}")
    pos = {str(a): np.array([x, y, z], float) for a, x, y, z in anchors[["anchor", "x", "y", "z"]].itertuples(index=False)}
    n = len(tdoa)
    record: dict = {"margin_m": float(margin), "rows_read": n, "rows_dropped": 0, "by_pair": {}}
    if n == 0:
        return tdoa, record
    pa = np.array([pos[a] for a in tdoa["anchor_a"]])
    pb = np.array([pos[b] for b in tdoa["anchor_b"]])
    val = tdoa["tdoa"].to_numpy(float)
    bad = np.abs(val) > np.linalg.norm(pa - pb, axis=1) + margin
    k = int(bad.sum())
    if k == 0:
        return tdoa, record
    if k > MAX_OUTLIER_FRACTION * n:
        i = int(np.argmax(bad))
        raise DatasetError(f"{source}: {k} of {n} TDoA rows ({100.0 * k / n:.0f} %) have |tdoa| beyond the anchors' "
                           f"separation + {margin:g} m (first: {abs(val[i]):.3f} m for anchors "
                           f"'{tdoa['anchor_a'].iloc[i]}', '{tdoa['anchor_b'].iloc[i]}'): too many to be outliers; "
                           "check the unit (metres expected) and that the anchors file belongs to this flight",
                           file=source, column="tdoa",
                           hint="--tdoa-margin widens the bound if the anchors are right")
    pairs = (tdoa["anchor_a"][bad] + "-" + tdoa["anchor_b"][bad]).value_counts()
    by_pair = {str(p): int(c) for p, c in sorted(pairs.items())}
    record.update(rows_dropped=k, by_pair=by_pair, largest_abs_tdoa_m=float(np.abs(val[bad]).max()),
                  first_t=float(tdoa["t"].to_numpy()[bad][0]))
    changes.append(f"{source}: dropped {k} of {n} TDoA rows whose |tdoa| exceeds the anchors' separation + "
                   f"{margin:g} m (impossible for a range difference; largest {record['largest_abs_tdoa_m']:.1f} m), "
                   "by anchor pair: " + ", ".join(f"{p}: {c}" for p, c in by_pair.items()))
    return tdoa[~bad].reset_index(drop=True), record


def tdoa_load_options(margin: float) -> Optional[LoadOptions]:
    """Loader options that accept what an import with ``margin`` kept (None: the defaults do)."""
    return LoadOptions(tdoa_margin=margin) if margin > TDOA_MARGIN_M else None
