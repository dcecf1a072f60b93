"""Building blocks of the report: templates, tables, figures, the formatting of figures."""

from __future__ import annotations

import base64
import functools
import io
from pathlib import Path
from typing import Any, Optional, Sequence

import numpy as np
import pandas as pd
from markupsafe import Markup

from uwbimu.eval.files import EvalInputError
from uwbimu.io.calibration_file import sd_or_none
from uwbimu.models.blocks import BlockSpec, calibration_components, legacy_name_map

#: Columns of the calibration history: the calibration blocks' components (lever arm, time offset: ``lx, ly, lz,
#: time_offset``) as ``uwbimu estimate`` writes them into ``states.csv`` (with ``sd_<name>``), declared once in
#: :mod:`uwbimu.models.blocks`.
CAL_COLUMNS = tuple(calibration_components())


def calibration_estimate(cal: Optional[dict], b: BlockSpec) -> tuple[Optional[list[float]], list[Optional[float]]]:
    """``(values, sds)`` of calibration block ``b`` in a calibration mapping [SI, one per component].

    The estimate is under the block's ``output_key`` (a value, a list, or schema 2's ``{value, sd}`` mapping),
    its sd under ``<output_key>_sd`` (or the mapping's ``sd``); values None when absent, an sd None when not
    estimated (:func:`~uwbimu.io.calibration_file.sd_or_none`).
    """
    cal = cal or {}
    v, sd = cal.get(b.output_key), cal.get(f"{b.output_key}_sd")
    if isinstance(v, dict):
        v, sd = v.get("value"), v.get("sd")
    values = None if v is None else [float(x) for x in np.atleast_1d(np.asarray(v, dtype=float))]
    sds = [None] * b.size if sd is None else [sd_or_none(x) for x in np.atleast_1d(np.asarray(sd, dtype=object))]
    return values, (sds + [None] * b.size)[:b.size]


SECTION_TITLES = {
    "calibration": "Calibration",
    "batch": "Batch calibration",
    "convergence": "Convergence",
    "residuals": "Per-anchor residuals",
    "nis": "NIS",
    "trajectory": "Trajectory and errors",
    "repeatability": "Repeatability",
    "observability": "Observability / excitation",
    "warnings": "Warnings",
}


# --------------------------------------------------------------------------- helpers
def figure_data_uri(fig, dpi: int = 90) -> str:
    """PNG of a matplotlib ``Figure`` as a ``data:`` URI (figure is not kept)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


# HTML is rendered by jinja2 with autoescape from templates shipped as package data
# (uwbimu/eval/templates): a value is escaped unless the code marks it as markup.  Sentences
# with inline markup are built with ``Markup("...{}...").format(value)``, which escapes the
# values (markupsafe, the same escaping jinja2 applies).
@functools.lru_cache(maxsize=1)
def _templates():
    import jinja2

    return jinja2.Environment(loader=jinja2.PackageLoader("uwbimu.eval", "templates"),
                              autoescape=True, trim_blocks=False, undefined=jinja2.StrictUndefined)


def _block(name: str, *args) -> Markup:
    """Call the macro ``name`` of ``templates/blocks.html.j2`` (returns markup)."""
    return Markup(getattr(_templates().get_template("blocks.html.j2").module, name)(*args))


def _join(parts) -> Markup:
    return Markup("").join(parts)


def _fig(name: str, fig, caption: str) -> Markup:
    return _block("figure", name, figure_data_uri(fig), caption)


def _span(cls: str, text: Any) -> Markup:
    return _block("span", cls, text)


def _fmt(x: Any, nd: int = 4) -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not np.isfinite(v):
        return "–"
    return f"{v:.{nd}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]], row_classes: Optional[Sequence[str]] = None,
           left: int = 1) -> Markup:
    """An HTML table; cells are escaped unless they are markup (e.g. :func:`_span`)."""
    return _block("table", list(header), [list(r) for r in rows], list(row_classes or []), left)


def _missing(text: Any) -> Markup:
    return _block("missing", text)


def _sd_col(df: pd.DataFrame, col: str) -> Optional[str]:
    return f"sd_{col}" if f"sd_{col}" in df.columns else None


def _read_csv(path: Path) -> Optional[pd.DataFrame]:
    if not path.is_file():
        return None
    try:
        return current_names(pd.read_csv(path))
    except Exception as exc:  # malformed file: report, do not crash the report
        raise EvalInputError(f"cannot read {path}: {exc}") from exc


def current_names(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` with the columns of an older output under their current names (``td`` -> ``time_offset``,
    ``sd_td`` -> ``sd_time_offset``: :func:`~uwbimu.models.blocks.legacy_name_map`); a column whose current
    name is also present is left alone."""
    ren = {old: new for old, new in legacy_name_map().items() if old in df.columns and new not in df.columns}
    return df.rename(columns=ren) if ren else df


def current_parameter_names(rep: dict) -> dict:
    """A ``repeatability.json`` mapping with the parameters of an older file (``td``) under their current names:
    ``parameters`` and every window's ``values`` / ``sd`` (a new dict; the input is not changed)."""
    if not isinstance(rep, dict):
        return rep
    ren = legacy_name_map()

    def keys(d):
        return {ren.get(k, k): v for k, v in d.items()} if isinstance(d, dict) else d

    out = dict(rep, parameters=keys(rep.get("parameters", {})))
    if isinstance(rep.get("windows"), list):
        out["windows"] = [dict(w, **{k: keys(w[k]) for k in ("values", "sd") if k in w}) if isinstance(w, dict) else w
                          for w in rep["windows"]]
    return out


def _as_bool(s: pd.Series) -> np.ndarray:
    if s.dtype == bool:
        return s.to_numpy()
    return s.astype(str).str.strip().str.lower().isin(["true", "1", "yes", "1.0"]).to_numpy()


