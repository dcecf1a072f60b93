"""One rounding rule for every printed figure (console, report, tables); imports nothing of ours.

* A quantity with an uncertainty is printed Kalibr-style, ``value ± σ unit``: σ to two
  significant digits, the value to the same decimal place (``29.9 ± 1.2 ms``,
  ``-0.0160 ± 0.0030 m``). A σ that was not estimated (None, NaN, inf, negative) prints the value
  with three significant digits and ``(σ not estimated)``.
* A figure without an uncertainty is printed to three significant digits
  (:func:`format_number`); counts print as integers.
* Anchor ids sort naturally (:func:`natural_key`): ``1, 2, ..., 10`` and ``A2 < A10``.
"""

from __future__ import annotations

import math
import re
from typing import Any, Optional

__all__ = ["NOT_ESTIMATED", "finite_or_none", "format_number", "format_value_sigma", "natural_key",
           "sigma_decimals"]

#: What a σ that was not estimated reads as, in files (next to ``null``) and in print.
NOT_ESTIMATED = "not estimated"
#: What a value that does not exist prints as.
NOT_AVAILABLE = "n/a"


def finite_or_none(x: Any) -> Optional[float]:
    """``float(x)`` when it is a finite number, else None (None, NaN, inf, text that is no number)."""
    if x is None or isinstance(x, bool):
        return None
    try:
        v = float(x)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def sigma_decimals(sigma: float, digits: int = 2) -> int:
    """Decimal places that show ``sigma`` (> 0) to ``digits`` significant digits after rounding.

    Negative for a σ of tens or more (``-1``: round to tens). A σ that rounds up to the next power of
    ten (``9.96`` with 2 digits -> ``10``) keeps two significant digits of the rounded σ (``10``,
    not ``10.0``).
    """
    if not (sigma > 0 and math.isfinite(sigma)):
        raise ValueError(f"sigma must be positive and finite, got {sigma!r}")
    d = digits - 1 - math.floor(math.log10(sigma))
    r = round(sigma, d)
    if r > 0 and math.floor(math.log10(r)) > math.floor(math.log10(sigma)):
        d -= 1
    return d


def _fixed(x: float, decimals: int) -> str:
    """``x`` rounded to ``decimals`` places (negative: tens, hundreds, ...), without a negative zero."""
    s = f"{round(x, decimals):.{max(decimals, 0)}f}"
    return s[1:] if s.startswith("-") and not s.strip("-0.") else s


def format_number(x: Any, unit: str = "", digits: int = 3) -> str:
    """``x`` to ``digits`` significant digits (integer digits kept; integers as integers), with the unit.

    ``n/a`` for None, NaN or inf.

    Parameters
    ----------
    x : float, int or None
        The figure, already in ``unit``.
    unit : str
        Unit text appended after a space (``""``: none).
    digits : int
        Significant digits of a non-integer figure.
    """
    suffix = f" {unit}" if unit else ""
    if isinstance(x, bool):
        return f"{x}{suffix}"
    if isinstance(x, int):
        return f"{x}{suffix}"
    v = finite_or_none(x)
    if v is None:
        return NOT_AVAILABLE
    if v == 0:
        return f"0{suffix}"
    if float(v).is_integer() and abs(v) < 10 ** digits:
        return f"{int(v)}{suffix}"
    d = max(digits - 1 - math.floor(math.log10(abs(v))), 0)  # integer digits are never dropped
    r = round(v, d)
    if d > 0 and r != 0 and math.floor(math.log10(abs(r))) > math.floor(math.log10(abs(v))):
        d -= 1  # 9.996 -> 10.0, not 10.00
    return f"{_fixed(v, d)}{suffix}"


def format_value_sigma(value: Any, sigma: Any, unit: str = "", digits: int = 2) -> str:
    """Kalibr-style ``value ± σ unit``: σ to ``digits`` significant digits, the value to the same place.

    Parameters
    ----------
    value : float or None
        Estimate, already in ``unit``.
    sigma : float or None
        One-sigma uncertainty in ``unit``; None, NaN, inf or <= 0 reads as not estimated.
    unit : str
        Unit text (``"ms"``, ``"cm"``, ``""``).
    digits : int
        Significant digits of σ.

    Returns
    -------
    str
        ``"29.9 ± 1.2 ms"``; ``"29.9 ms (σ not estimated)"`` without a σ; ``"n/a"`` without a value.

    Examples
    --------
    >>> format_value_sigma(0.02994, 0.00123, "s")
    '0.0299 ± 0.0012 s'
    >>> format_value_sigma(-16.04, 3.0, "cm")
    '-16.0 ± 3.0 cm'
    >>> format_value_sigma(1.5, None, "m")
    '1.50 m (σ not estimated)'
    """
    suffix = f" {unit}" if unit else ""
    v = finite_or_none(value)
    if v is None:
        return NOT_AVAILABLE
    s = finite_or_none(sigma)
    if s is None or s <= 0:
        return f"{format_number(v, digits=3)}{suffix} (σ {NOT_ESTIMATED})"
    d = sigma_decimals(s, digits)
    return f"{_fixed(v, d)} ± {_fixed(s, d)}{suffix}"


_DIGITS = re.compile(r"(\d+)")


def natural_key(anchor_id: Any) -> tuple:
    """Sort key that orders anchor ids naturally: ``1, 2, ..., 10``; ``A2 < A10``; ``3-10 < 10-3``.

    Numbers compare as numbers, text case-insensitively; ids of any type (int, float, str) mix.
    """
    if isinstance(anchor_id, bool):
        anchor_id = int(anchor_id)
    if isinstance(anchor_id, (int, float)) and not (isinstance(anchor_id, float) and not math.isfinite(anchor_id)):
        if float(anchor_id).is_integer():
            anchor_id = int(anchor_id)
    text = str(anchor_id)
    parts = _DIGITS.split(text)
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p.lower()) for p in parts if p != "")
