"""Rendering the report: the sections in order, the page, the atomic write."""

from __future__ import annotations

import datetime as _dt
import os
import re
from pathlib import Path
from typing import Optional, Union

from uwbimu.eval.files import EvalInputError
from uwbimu.eval.report.batch import _batch_section
from uwbimu.eval.report.common import SECTION_TITLES, _block, _templates
from uwbimu.eval.report.inputs import ReportInputs
from uwbimu.eval.report.sections import (_calibration_section, _convergence_section, _nis_section,
                                         _observability_section, _repeatability_section, _residuals_section,
                                         _trajectory_section, _warnings_section)
from uwbimu.io.atomic import write_text


SECTIONS = {
    "calibration": _calibration_section,
    "batch": _batch_section,
    "convergence": _convergence_section,
    "residuals": _residuals_section,
    "nis": _nis_section,
    "trajectory": _trajectory_section,
    "repeatability": _repeatability_section,
    "observability": _observability_section,
    "warnings": _warnings_section,
}


_STAGING = re.compile(r"(^|[/\\])\.([^/\\]+)\.uwbimu-tmp-[^/\\]+")


def display_path(out: Path) -> str:
    """The folder the outputs end up in: a staging folder of :func:`uwbimu.io.atomic.output_folder`
    (``PARENT/.NAME.uwbimu-tmp-XXXX``, renamed to ``PARENT/NAME`` when the verb succeeds) shows as its final
    name, so the page never names a folder that no longer exists."""
    return _STAGING.sub(lambda m: m.group(1) + m.group(2), str(out))


def run_summary(inp: ReportInputs) -> dict[str, str]:
    """``data-*`` attributes of ``#run-summary``: what the sections state, from the one source each (the
    time-offset mode and verdict, the NIS summary, the number of warnings)."""
    td = inp.time_offset()
    out = {"estimator": inp.estimator()}
    if td:
        out.update({"td-mode": td["mode"], "td-verdict": td.get("verdict") or "unknown"})
    if inp.nis is not None:
        out.update(inp.nis.attrs())
    items = inp.warning_items()
    out["warnings"] = str(sum(1 for w in items if w.severity != "info"))
    out["warning-kinds"] = " ".join(sorted({w.kind for w in items}))
    return out


def render_report(out_dir: Union[str, os.PathLike], dataset=None, title: Optional[str] = None) -> str:
    """Render the report of ``out_dir`` as an HTML string (nothing written)."""
    out = Path(out_dir)
    if not out.is_dir():
        raise EvalInputError(f"{out}: output folder not found")
    if isinstance(dataset, (str, os.PathLike)):
        from uwbimu.io.loader import load_dataset

        dataset = load_dataset(dataset)
    inp = ReportInputs(out, dataset)
    if inp.calibration is None and inp.trajectory is None and inp.residuals is None:
        raise EvalInputError(f"{out}: no estimator output (calibration.yaml, trajectory.csv, residuals.csv) found")
    body = []
    for key, fn in SECTIONS.items():
        try:
            content = fn(inp)
        except EvalInputError:
            raise
        except Exception as exc:  # one broken input must not lose the whole report; say what failed
            content = _block("warn", f"This section failed: {type(exc).__name__}: {exc}")
        if content is None:  # a section that does not apply to this folder (batch)
            continue
        attrs: dict = {}
        if isinstance(content, tuple):  # (markup, data-* attributes of the section)
            content, attrs = content
        # a section returns markup; a plain string would be escaped by the template (shown, never run)
        body.append({"key": key, "title": SECTION_TITLES[key], "content": content,
                     "attrs": [(k, str(v)) for k, v in attrs.items()]})
    try:
        from importlib.metadata import version

        ver = version("uwbimu")
    except Exception:  # not installed (source checkout)
        ver = "unknown"
    if title is None:
        name = dataset.meta.name if dataset is not None else out.name
        title = f"uwbimu calibration report — {name}"
    return _templates().get_template("report.html.j2").render(
        title=title, version=ver, out_dir=display_path(out),
        summary=list({**run_summary(inp), "out-dir": display_path(out)}.items()),
        generated=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), sections=body,
    )


def write_report(out_dir: Union[str, os.PathLike], dataset=None, path: Optional[Union[str, os.PathLike]] = None,
                 title: Optional[str] = None) -> Path:
    """Write ``OUT/report.html`` (or ``path``) atomically and return its path.

    Parameters
    ----------
    out_dir : estimator output folder (``uwbimu estimate ... --out OUT``).
    dataset : optional :class:`~uwbimu.io.dataset.Dataset` or dataset folder: adds
        anchors, the documented/true calibration and, when ``OUT/evaluation.json``
        is absent, an evaluation against the dataset's ground truth (alignment
        from ``meta.extra.groundtruth_align``, default ``none``).
    """
    html_text = render_report(out_dir, dataset=dataset, title=title)
    target = Path(path) if path is not None else Path(out_dir) / "report.html"
    return write_text(target, html_text)
