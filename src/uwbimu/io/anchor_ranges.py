"""Optional self-survey columns: ``anchors.csv`` ``surveyed`` and ``anchor_ranges.csv`` ``sd``.

* ``surveyed`` (anchors.csv): ``true``/``false`` (also ``yes``/``no``, ``1``/``0``, any case).
  ``false`` marks an anchor whose coordinates are only a rough guess: ``uwbimu calibrate``
  estimates its position with no prior (docs/calibrate.md, "Anchor self-survey").
* ``sd`` (anchor_ranges.csv): standard deviation of the measured inter-anchor range [m], finite
  and positive; without the column the calibrator's ``anchor_range_sigma`` applies.

Every refusal names the file, line and column.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

_TRUE = {"true", "yes", "1", "1.0", "t", "y"}
_FALSE = {"false", "no", "0", "0.0", "f", "n"}


def parse_surveyed(src, df: pd.DataFrame) -> pd.Series:
    """``surveyed`` column as bool; refuses empty or other values (naming line and column)."""
    raw = df["surveyed"]
    if pd.api.types.is_bool_dtype(raw):
        return raw.astype(bool)
    out = []
    for i, v in raw.items():
        t = "" if v is None or (isinstance(v, float) and np.isnan(v)) else str(v).strip().lower()
        if t in _TRUE:
            out.append(True)
        elif t in _FALSE:
            out.append(False)
        else:
            raise src.error(f"surveyed must be true or false, got {'an empty value' if not t else repr(str(v))}",
                            i, "surveyed")
    return pd.Series(out, index=raw.index, dtype=bool)


def parse_range_sd(src, df: pd.DataFrame) -> pd.Series:
    """``sd`` column [m] as float; refuses non-numeric, missing, non-finite and non-positive values."""
    raw = df["sd"]
    vals = pd.to_numeric(raw, errors="coerce")
    for i, v in vals.items():
        if not np.isfinite(v):
            what = "missing or non-numeric" if pd.isna(raw[i]) or np.isnan(v) else "non-finite"
            raise src.error(f"sd '{raw[i]}' is {what}; a finite standard deviation in m is expected", i, "sd")
        if v <= 0:
            raise src.error(f"sd {v:g} m is not positive", i, "sd")
    return vals.astype(float)
