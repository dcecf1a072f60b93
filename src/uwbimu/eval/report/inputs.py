"""What the report reads from an output folder, and the summaries every section shares.

The sections never recompute a summary: the time-offset mode and verdict (:meth:`ReportInputs.time_offset`), the
NIS statistics (:func:`nis_summary`) and the warnings (:meth:`ReportInputs.warning_items`) are derived once here,
from the run's structured outputs (calibration.yaml in the one schema with its ``warnings`` and ``events``,
residuals.csv), and the page carries them as ``data-*`` attributes (``#run-summary``). A console that prints a run
uses the same functions (:func:`nis_summary` of ``result.residuals``, :func:`run_warning_items` of
``result.warnings`` and ``result.events``) so that both say the same.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Optional

import numpy as np
import pandas as pd

from uwbimu.eval.files import EvalInputError, load_yaml
from uwbimu.eval.report.common import _as_bool, _read_csv, current_parameter_names
from uwbimu.formatting import format_number
from uwbimu.io.calibration_file import effective_time_offset_mode, read_calibration, sd_or_none

#: 95 % point of χ²(1) (the range NIS has one degree of freedom)
CHI2_1_95 = 3.841458820694124
#: median of χ²(1)
CHI2_1_MEDIAN = 0.454936423119572


@dataclass
class NisSummary:
    """NIS statistics of the range/TDoA updates (1 dof each), from residuals.csv's ``nis`` and ``accepted``.

    ``mean_accepted`` is the figure to compare with 1 (the gate removes the outliers it rejects); ``mean_all`` is
    over every processed update, rejected ones included, and is dominated by them when they are far out.
    ``verdict``: ``over-confident`` when more than 10 % of the processed updates exceed the 95 % bound or the median
    exceeds twice χ²(1)'s; ``under-confident`` when under 1 % exceed it and the median is under half χ²(1)'s;
    ``heavy-tailed`` when neither holds but the mean over all processed updates exceeds 3 (a few far outliers);
    else ``consistent``.
    """

    n: int
    n_accepted: int
    mean_all: float
    mean_accepted: float
    median: float
    above_95_pct: float
    verdict: str

    def attrs(self) -> dict[str, str]:
        """``data-*`` attributes (numbers as repr of the float, the one source the test compares)."""
        return {"nis-n": str(self.n), "nis-n-accepted": str(self.n_accepted), "nis-mean": repr(self.mean_accepted),
                "nis-mean-all": repr(self.mean_all), "nis-median": repr(self.median),
                "nis-above95-pct": repr(self.above_95_pct), "nis-verdict": self.verdict}


def nis_summary(res: Optional[pd.DataFrame]) -> Optional[NisSummary]:
    """:class:`NisSummary` of a residuals.csv (None without a ``nis`` column or a finite NIS)."""
    if res is None or "nis" not in res.columns:
        return None
    nis = pd.to_numeric(res["nis"], errors="coerce").to_numpy(float)
    acc = _as_bool(res["accepted"]) if "accepted" in res.columns else np.ones(len(res), bool)
    fin = np.isfinite(nis)
    if not fin.any():
        return None
    x, xa = nis[fin], nis[fin & acc]
    above = 100.0 * float(np.mean(x > CHI2_1_95))
    med = float(np.median(x))
    mean_all = float(np.mean(x))
    if above > 10.0 or med > 2 * CHI2_1_MEDIAN:
        verdict = "over-confident"
    elif above < 1.0 and med < 0.5 * CHI2_1_MEDIAN:
        verdict = "under-confident"
    elif mean_all > 3.0:
        verdict = "heavy-tailed"
    else:
        verdict = "consistent"
    return NisSummary(n=int(len(x)), n_accepted=int(len(xa)), mean_all=mean_all,
                      mean_accepted=float(np.mean(xa)) if len(xa) else math.nan, median=med, above_95_pct=above,
                      verdict=verdict)


@dataclass
class WarningItem:
    """One warning or event of the run as the console shows it: ``kind`` (event kind, or ``estimator_warning``
    for the ESKF's text warnings), ``source`` (the file it came from), ``severity`` and a one-line ``text``."""

    kind: str
    source: str
    text: str
    severity: str = "warning"


#: event kinds a console prints (prefixes): these and every event of severity warning / refused are warnings
PRINTED_EVENT_KINDS = ("flight_segment", "anchor_", "lever_arm_not_identified", "range_errors_correlated_over_blocks",
                       "time_offset_held", "time_offset_not_identified", "calibration_held", "divergence", "clock_",
                       "second_start_won", "range_model_selected", "forward_backward")


def run_warning_items(text_warnings, events, source: str = "calibration.yaml events") -> list[WarningItem]:
    """The warnings of a run as the console should print them and the report shows them, in this order.

    Parameters
    ----------
    text_warnings : list of str or WarningItem
        The estimator's text warnings (``result.warnings``; calibration.yaml ``warnings``).
    events : list of dict
        Its structured events (``result.events``; calibration.yaml ``events``).
    source : str
        Where the events came from (shown in the report).

    Returns
    -------
    list of WarningItem
        The text warnings (kind ``estimator_warning``), then the events of severity ``warning`` / ``refused`` or of
        a kind in :data:`PRINTED_EVENT_KINDS` without a severity (a ``flight_segment`` only with a message), then
        those of severity ``info`` of such a kind (severity ``info``).
    """
    items = [w if isinstance(w, WarningItem) else WarningItem("estimator_warning", "calibration.yaml", str(w))
             for w in text_warnings]
    info = []
    for ev in events or []:
        if not isinstance(ev, dict) or "kind" not in ev:
            continue
        kind = str(ev["kind"])
        sev = str(ev.get("severity", ""))
        if kind == "flight_segment" and not ev.get("message"):
            continue
        if sev in ("warning", "refused") or (sev not in ("info", "warning", "refused") and kind.startswith(PRINTED_EVENT_KINDS)):
            items.append(WarningItem(kind, source, event_text(ev), "warning"))
        elif sev == "info" and kind.startswith(PRINTED_EVENT_KINDS):
            info.append(WarningItem(kind, source, event_text(ev), "info"))
    return items + info


def event_text(ev: dict) -> str:
    """A one-line text of an event: its ``message`` (or ``advice``), else its fields ``key = value`` (numbers by
    the one rounding rule, lists joined; never a Python repr)."""
    for key in ("message", "advice"):
        if ev.get(key):
            return str(ev[key])

    def val(v: Any) -> str:
        if isinstance(v, (list, tuple)):
            return ", ".join(val(x) for x in v)
        if isinstance(v, dict):
            return "; ".join(f"{k} {val(x)}" for k, x in v.items())
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            return format_number(v)
        return "n/a" if v is None else str(v)

    return "; ".join(f"{k} = {val(v)}" for k, v in ev.items() if k not in ("kind", "severity"))


# --------------------------------------------------------------------------- inputs
class ReportInputs:
    """Everything the report reads from an output folder (each item may be missing)."""

    def __init__(self, out_dir: Path, dataset=None):
        self.out = out_dir
        self.dataset = dataset
        # either schema version, read as version 2 (uwbimu.io.calibration_file)
        self.calibration = read_calibration(out_dir / "calibration.yaml", error=EvalInputError)
        self.metrics = load_yaml(out_dir / "metrics.yaml")
        self.trajectory = _read_csv(out_dir / "trajectory.csv")
        self.residuals = _read_csv(out_dir / "residuals.csv")
        # calibration history: states.csv of `uwbimu estimate` (lx, ly, lz, time_offset + sd_*; td in older files)
        self.states = _read_csv(out_dir / "states.csv")
        self.observability = _read_csv(out_dir / "observability.csv")
        # outputs of `uwbimu calibrate` (batch calibration section)
        self.td_profile = _read_csv(out_dir / "td_profile.csv")
        self.anchors_estimated = _read_csv(out_dir / "anchors_estimated.csv")
        self.eval_errors = _read_csv(out_dir / "evaluation_errors.csv")
        self.evaluation = None
        if (out_dir / "evaluation.json").is_file():
            self.evaluation = json.loads((out_dir / "evaluation.json").read_text())
        self.repeatability = None
        if (out_dir / "repeatability.json").is_file():
            # older files name the time offset td: read under the current names
            self.repeatability = current_parameter_names(json.loads((out_dir / "repeatability.json").read_text()))
        #: structured events of the run that the console prints from: calibration.yaml ``events`` (batch; the
        #: ESKF's console prints its text ``warnings``, and its calibration.yaml carries the time-offset mode the
        #: events decided)
        evs = (self.calibration or {}).get("events")
        self.events: list[dict] = [e for e in evs if isinstance(e, dict) and "kind" in e] if isinstance(evs, list) else []
        #: text warnings: calibration.yaml / metrics.yaml ``warnings``, warnings.txt, and the report's own
        self.warnings: list[WarningItem] = []
        for name, src in (("calibration.yaml", self.calibration or {}), ("metrics.yaml", self.metrics or {})):
            w = src.get("warnings")
            if isinstance(w, list):
                self.warnings += [WarningItem("estimator_warning", name, str(x)) for x in w]
        if (out_dir / "warnings.txt").is_file():
            self.warnings += [WarningItem("estimator_warning", "warnings.txt", ln)
                              for ln in (out_dir / "warnings.txt").read_text().splitlines() if ln.strip()]
        self.nis = nis_summary(self.residuals)
        # ground truth from a dataset given in memory, if no evaluation was written
        if self.evaluation is None and dataset is not None and dataset.groundtruth is not None and self.trajectory is not None:
            self._evaluate_in_memory()

    def _evaluate_in_memory(self) -> None:
        from uwbimu.eval.evaluate import evaluation_table
        from uwbimu.metrics.trajectory import evaluate_trajectory

        extra = self.dataset.meta.extra or {}
        align = str(extra.get("groundtruth_align", "none"))
        try:
            ev = evaluate_trajectory(self.trajectory, self.dataset.groundtruth, align=align,
                                     compare_attitude=bool(extra.get("groundtruth_attitude_comparable", True)))
        except (ValueError, KeyError) as exc:
            self.warn("report_evaluation_failed", f"could not evaluate against the dataset's ground truth: {exc}")
            return
        self.evaluation = ev.summary
        self.eval_errors = evaluation_table(ev)

    def warn(self, kind: str, text: str) -> None:
        """A warning of the report itself (shown in the warnings section, source ``report``)."""
        self.warnings.append(WarningItem(kind, "report", text))

    def warning_items(self) -> list[WarningItem]:
        """Every warning the console printed for this run (:func:`run_warning_items` of the folder's text warnings
        and calibration.yaml ``events``), then the report's own."""
        own = [w for w in self.warnings if w.source == "report"]
        items = run_warning_items([w for w in self.warnings if w.source != "report"], self.events) + own
        sm = (self.calibration or {}).get("smoothing")
        if isinstance(sm, dict) and sm.get("message") and not any(w.kind == "forward_backward" for w in items):
            # the ESKF's calibration.yaml carries no events: its smoothing block says what the console's
            # forward_backward note said, in the same words
            items.append(WarningItem("forward_backward", "calibration.yaml smoothing", str(sm["message"]), "info"))
        return items

    def time_offset(self) -> dict[str, Any]:
        """The time offset as every section shows it: ``value, sd`` [s] (sd None when not estimated), ``mode`` (the
        run's: calibration.yaml's, corrected by a ``time_offset_held`` event for files written before the schema
        carried it), ``configured_mode``, ``verdict``; {} without one."""
        td = (self.calibration or {}).get("time_offset")
        if not isinstance(td, dict):
            return {}
        mode, configured = effective_time_offset_mode(td.get("configured_mode") or td.get("mode") or "estimate",
                                                      self.events)
        if td.get("mode") in ("consider", "fixed") and mode == "estimate":
            mode = td["mode"]
        return {"value": td.get("value"), "sd": sd_or_none(td.get("sd")), "mode": mode, "configured_mode": configured,
                "verdict": td.get("verdict"), "verdict_reason": td.get("verdict_reason")}

    def estimator(self) -> str:
        """``eskf``, ``batch``, another registry name, or ``unknown``."""
        c = self.calibration or {}
        if c.get("estimator"):
            return str(c["estimator"])
        return "batch" if str(c.get("method", "")).startswith("batch") else "unknown"

    def reference_lever_arm(self) -> tuple[Optional[list], str]:
        """Documented or true lever arm, with a label saying which."""
        ds = self.dataset
        if ds is not None:
            if ds.meta.truth is not None and ds.meta.truth.lever_arm is not None:
                return list(ds.meta.truth.lever_arm), "reference"
            if ds.meta.tags and ds.meta.tags[0].lever_arm is not None:
                return list(ds.meta.tags[0].lever_arm), "nominal"
        return None, ""

    def reference(self, b) -> Optional[list[float]]:
        """Documented or true value of calibration block ``b`` (one per component, SI), or None: dataset.yaml
        ``truth.<output_key>``, else the first tag's ``<output_key>`` (the nominal lever arm)."""
        ds = self.dataset
        if ds is None:
            return None
        v = getattr(ds.meta.truth, b.output_key, None) if ds.meta.truth is not None else None
        if v is None and ds.meta.tags:
            v = getattr(ds.meta.tags[0], b.output_key, None)
        return None if v is None else [float(x) for x in np.atleast_1d(np.asarray(v, dtype=float))]

    def reference_time_offset(self) -> Optional[float]:
        ds = self.dataset
        if ds is not None and ds.meta.truth is not None:
            return ds.meta.truth.time_offset
        return None


