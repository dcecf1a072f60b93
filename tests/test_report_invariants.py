"""The report says what the console says, and only what holds (issue 30 item 3).

Three runs go through the writers and the report: the demo's simulated flight (ESKF), an ISAS-Walk run (the bundled
excerpt: ground truth in another frame, t_d held in consider mode) and a batch calibration. Each page is checked on
its structured ``data-*`` attributes, never on message text:

* the time-offset mode and verdict are the same in the run summary, the calibration section and calibration.yaml,
  and a run whose events held t_d reads ``consider``;
* every NIS figure on the page is the one summary, equal to what residuals.csv gives, and its verdict follows the
  documented rule (no "consistent" next to a mean the tail dominates);
* every warning the console prints (the ESKF's ``result.warnings``, the batch's warning events) is in the warnings
  section, with its kind;
* one position RMSE per page; with the ground truth in another frame the unaligned comparisons are n/a and the
  aligned figure names its alignment;
* the error band is named for the estimator that made it (filter / smoother) and the page says when the errors leave it;
* anchors in natural order; the page names the final output folder, not a staging one.
"""

from __future__ import annotations

import re
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from uwbimu.eval.report import render_report
from uwbimu.eval.report.inputs import CHI2_1_95, CHI2_1_MEDIAN
from uwbimu.eval.report.render import display_path
from uwbimu.formatting import natural_key
from uwbimu.io.calibration_file import time_offset_held

EXCERPT = Path(__file__).parent / "data" / "isas_walk_excerpt"


class _Attrs(HTMLParser):
    """Every element with data-* attributes: (tag, id, {name: value}), and the first-column cells of each table
    under a section id."""

    def __init__(self):
        super().__init__()
        self.elements: list[tuple[str, str, dict]] = []
        self.sections: dict[str, dict] = {}
        self.first_cells: dict[str, list[str]] = {}
        self._section = None
        self._cell = None
        self._col = 0

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        data = {k[5:]: v for k, v in a.items() if k.startswith("data-")}
        if tag == "section":
            self._section = a.get("id")
            self.sections[self._section] = data
        if data:
            self.elements.append((tag, a.get("id") or "", data))
        if tag == "tr":
            self._col = 0
        if tag == "td":
            self._col += 1
            self._cell = "" if self._col == 1 else None

    def handle_data(self, d):
        if self._cell is not None:
            self._cell += d

    def handle_endtag(self, tag):
        if tag == "td" and self._cell is not None:
            self.first_cells.setdefault(self._section, []).append(self._cell.strip())
            self._cell = None

    def all(self, name: str) -> list[str]:
        return [d[name] for _, _, d in self.elements if name in d]

    def summary(self) -> dict:
        return next(d for _, i, d in self.elements if i == "run-summary")


def _page(html: str) -> _Attrs:
    p = _Attrs()
    p.feed(html)
    return p


def check_invariants(html: str, out: Path, console_warnings: list[str], console_events: list[dict]) -> _Attrs:
    """The invariants every report holds (see the module docstring)."""
    page = _page(html)
    s = page.summary()
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    td = cal["time_offset"]
    # one schema: the time offset is a mapping with a unit and a mode, never a NaN sigma
    assert cal["schema_version"] == 2 and td["unit"] == "s"
    assert td["sd"] is None or (np.isfinite(td["sd"]) and td["sd"] > 0)
    # mode and verdict: one source
    assert s["td-mode"] == page.sections["calibration"]["td-mode"] == td["mode"]
    assert set(page.all("mode")) == {td["mode"]}
    assert s["td-verdict"] == page.sections["calibration"]["td-verdict"] == td["verdict"]
    if time_offset_held(console_events):  # the run's events held t_d: every part of the page says consider
        assert s["td-mode"] == "consider"
    # NIS: one summary, the one residuals.csv gives, and a verdict by the documented rule
    res = pd.read_csv(out / "residuals.csv")
    if "nis" in res.columns:
        nis = pd.to_numeric(res["nis"], errors="coerce").to_numpy(float)
        acc = res["accepted"].astype(str).str.lower().isin(["true", "1"]).to_numpy()
        fin = np.isfinite(nis)
        for key in ("nis-mean", "nis-mean-all", "nis-above95-pct", "nis-verdict"):
            assert len(set(page.all(key))) == 1, key
        assert float(s["nis-mean"]) == pytest.approx(np.mean(nis[fin & acc]))
        assert float(s["nis-mean-all"]) == pytest.approx(np.mean(nis[fin]))
        above = 100 * np.mean(nis[fin] > CHI2_1_95)
        assert float(s["nis-above95-pct"]) == pytest.approx(above)
        med = np.median(nis[fin])
        expect = ("over-confident" if above > 10 or med > 2 * CHI2_1_MEDIAN else
                  "under-confident" if above < 1 and med < 0.5 * CHI2_1_MEDIAN else
                  "heavy-tailed" if np.mean(nis[fin]) > 3 else "consistent")
        assert s["nis-verdict"] == expect
    # every console warning is in the report, with its kind
    kinds = [d.get("warning-kind") for _, _, d in page.elements if "warning-kind" in d]
    text_warnings = [d for _, _, d in page.elements
                     if d.get("warning-kind") == "estimator_warning" and d.get("warning-source") == "calibration.yaml"]
    assert len(text_warnings) == len(console_warnings)
    for ev in console_events:
        if ev.get("severity") == "warning":
            assert ev["kind"] in kinds, ev["kind"]
    n_warn = sum(1 for _, _, d in page.elements if "warning-kind" in d and d.get("severity") != "info")
    assert int(s["warnings"]) == int(page.sections["warnings"]["warnings"]) == n_warn
    # one position RMSE per page
    assert len(set(page.all("position-rmse"))) <= 1
    # the band is named for the estimator that made it, and the page says when the errors leave it
    tr = page.sections.get("trajectory", {})
    if "band" in tr:
        assert tr["band"] == ("smoother ±3σ" if s["estimator"] == "batch" else "filter ±3σ")
        if "outside-band-pct" in tr:
            limit = 1.0 if tr["align"] in ("none", "position") else 5.0
            assert tr["band-exceeded"] == ("yes" if float(tr["outside-band-pct"]) > limit else "no")
    # natural anchor order in the per-anchor table
    ids = page.first_cells.get("residuals", [])
    assert ids == sorted(ids, key=natural_key)
    # the folder the outputs are in
    assert s["out-dir"] == str(out)
    return page


# --------------------------------------------------------------------------- the three runs
@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    """The demo's simulated calibration flight (shortened to 20 s), ESKF, outputs, report with the dataset."""
    from uwbimu.eval.estimators import get_estimator
    from uwbimu.estimation.outputs import write_outputs
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0}))
    e = get_estimator("eskf")
    res = e.run(ds, e.options(None), None)
    out = tmp_path_factory.mktemp("demo") / "estimate"
    write_outputs(res, ds, out, plots=False)
    return out, ds, res


@pytest.fixture(scope="module")
def isas_run(tmp_path_factory):
    """The bundled ISAS-Walk excerpt (VIVE ground truth in another frame), ESKF with the isas-walk preset."""
    from uwbimu.eval.estimators import get_estimator
    from uwbimu.estimation.outputs import write_outputs
    from uwbimu.estimation.presets import load_preset
    from uwbimu.io.importers.isas_walk import import_dataset
    from uwbimu.io.loader import load_dataset

    root = tmp_path_factory.mktemp("isas")
    import_dataset(EXCERPT, root / "ds")
    ds = load_dataset(root / "ds")
    res = get_estimator("eskf").run(ds, load_preset("isas-walk"), None)
    out = root / "out"
    write_outputs(res, ds, out, plots=False)
    return out, ds, res


@pytest.fixture(scope="module")
def batch_run(tmp_path_factory):
    """A 10 s simulated flight through the batch calibrator (``uwbimu calibrate``'s writer)."""
    pytest.importorskip("gtsam")
    from uwbimu.calibration import CalibrationOptions, calibrate, write_calibration
    from uwbimu.sim import builtin_scenario, simulate

    sc = builtin_scenario("calibration-flight")
    ds = simulate(sc.model_copy(update={"duration": 10.0, "seeds": sc.seeds.model_copy(update={"noise": 4})}))
    res = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"half_width": 0.2, "step": 0.1}}))
    out = tmp_path_factory.mktemp("batch") / "out"
    out.mkdir()
    write_calibration(res, out, plots=False)
    return out, ds, res


def test_demo_report_invariants(demo_run):
    out, ds, res = demo_run
    page = check_invariants(render_report(out, dataset=ds), out, list(res.warnings), res.events)
    s = page.summary()
    assert s["estimator"] == "eskf"
    tr = page.sections["trajectory"]
    assert tr["align"] == "none" and tr["band"] == "filter ±3σ"
    # the one position RMSE is the console's (metrics.yaml)
    met = yaml.safe_load((out / "metrics.yaml").read_text())
    assert float(tr["position-rmse"]) == met["position_rmse"]
    assert page.sections["calibration"]["metrics-vs-truth"] == "shown"


def test_isas_walk_report_invariants(isas_run):
    out, ds, res = isas_run
    page = check_invariants(render_report(out, dataset=ds), out, list(res.warnings), res.events)
    s = page.summary()
    # this excerpt is too short to locate t_d: the run held it, and every part of the page says so
    assert time_offset_held(res.events)
    assert s["td-mode"] == "consider" and s["td-verdict"] == "not identified"
    # ground truth in another frame: unaligned comparisons n/a, the aligned figure names its alignment
    assert page.sections["calibration"]["metrics-vs-truth"] == "n/a"
    assert page.sections["trajectory"]["align"] == ds.meta.extra["groundtruth_align"] != "none"


def test_batch_report_invariants(batch_run):
    out, ds, res = batch_run
    page = check_invariants(render_report(out, dataset=ds), out, [], res.events)
    s = page.summary()
    assert s["estimator"] == "batch"
    assert page.sections["trajectory"]["band"] == "smoother ±3σ"
    # the batch residual reads measured − predicted, as the ESKF's innovation
    assert page.sections["calibration"]["td-mode"] in ("estimate", "fixed")


def test_console_warning_events_reach_the_report(batch_run, tmp_path):
    """A warning event the console prints (range_errors_correlated_over_blocks) is in the report with its kind,
    even when this run did not raise it: written into a copy of the run's calibration.yaml."""
    import shutil

    out, ds, res = batch_run
    o = tmp_path / "o"
    shutil.copytree(out, o)
    cal = yaml.safe_load((o / "calibration.yaml").read_text())
    ev = {"kind": "range_errors_correlated_over_blocks", "severity": "warning", "blocks": 8,
          "parameters": ["lever_arm_z"], "advice": "record a longer log"}
    cal["events"] = list(cal.get("events") or []) + [ev]
    (o / "calibration.yaml").write_text(yaml.safe_dump(cal, sort_keys=False))
    page = check_invariants(render_report(o, dataset=ds), o, [], cal["events"])
    assert "range_errors_correlated_over_blocks" in page.all("warning-kind")
    assert "range_errors_correlated_over_blocks" in page.summary()["warning-kinds"].split()


def test_old_calibration_yaml_reads_as_the_new_schema(demo_run, tmp_path):
    """A calibration.yaml of schema 1 (ESKF: time_offset a number beside time_offset_sd / _mode / _verdict) renders
    with the same mode and verdict as the new one."""
    import shutil

    from uwbimu.io.calibration_file import read_calibration

    out, ds, res = demo_run
    o = tmp_path / "old"
    shutil.copytree(out, o)
    new = yaml.safe_load((o / "calibration.yaml").read_text())
    old = {k: v for k, v in new.items() if k not in ("schema_version", "time_offset")}
    td = new["time_offset"]
    old.update({"time_offset": td["value"], "time_offset_sd": td["sd"], "time_offset_mode": td["mode"],
                "time_offset_verdict": td["verdict"]})
    (o / "calibration.yaml").write_text(yaml.safe_dump(old, sort_keys=False))
    got = read_calibration(o / "calibration.yaml")
    assert got["time_offset"]["value"] == td["value"] and got["time_offset"]["sd"] == td["sd"]
    assert got["time_offset"]["mode"] == td["mode"] and got["schema_version"] == 2
    s = _page(render_report(o, dataset=ds)).summary()
    assert (s["td-mode"], s["td-verdict"]) == (td["mode"], td["verdict"])


def test_staging_folder_shows_its_final_name(tmp_path):
    """The page names the folder the outputs end up in (uwbimu.io.atomic.output_folder stages in
    PARENT/.NAME.uwbimu-tmp-XXXX, then renames it to PARENT/NAME)."""
    assert display_path(tmp_path / ".estimate.uwbimu-tmp-abc123") == str(tmp_path / "estimate")
    assert display_path(tmp_path / ".demo.uwbimu-tmp-x1" / "estimate") == str(tmp_path / "demo" / "estimate")
    assert display_path(tmp_path / "plain") == str(tmp_path / "plain")


def test_residual_tables_list_tdoa_by_pair_in_natural_order():
    """residual_table.csv (estimation.outputs.residual_table) and the report's per-anchor table: ranges per anchor,
    TDoA rows per pair "a-b" (column ``pair``), never under anchor a; anchors 1, 2, ..., 10."""
    from types import SimpleNamespace

    from uwbimu.eval.report import anchor_residual_table
    from uwbimu.estimation.outputs import residual_table

    anchors = ["10", "2", "1", "3", "10", "2", "1", "3"]
    res = pd.DataFrame({"t": np.arange(8.0), "anchor": anchors, "range": 1.0, "predicted": 1.0,
                        "innovation": [0.01, -0.02, 0.0, 0.03, 0.01, 0.0, -0.01, 0.02], "nis": 0.5, "accepted": True,
                        "kind": ["range"] * 4 + ["tdoa"] * 4, "anchor_b": ["", "", "", "", "1", "1", "2", "2"]})
    tab = residual_table(SimpleNamespace(residuals=res))
    rng, tdoa = tab[tab["kind"] == "range"], tab[tab["kind"] == "tdoa"]
    assert rng["anchor"].tolist() == ["1", "2", "3", "10"] and set(rng["pair"]) == {""}
    assert tdoa["pair"].tolist() == ["1-2", "2-1", "3-2", "10-1"] and set(tdoa["anchor"]) == {""}
    rep = anchor_residual_table(res)
    assert rep["anchor"].tolist() == sorted(rep["anchor"], key=natural_key)
    assert {"1-2", "2-1", "3-2", "10-1"} <= set(rep["anchor"]) and rep.set_index("anchor").loc["10", "n"] == 1
    # a range-only run keeps the historical columns
    plain = residual_table(SimpleNamespace(residuals=res[res["kind"] == "range"].drop(columns=["kind", "anchor_b"])))
    assert list(plain.columns) == ["anchor", "ranges", "processed", "accepted", "rejected_pct", "median", "mad"]
