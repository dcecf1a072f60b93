"""The report's batch-calibration section (issue 12 item 7): t_d profile, residual vs line-of-sight
angle, anchor error ellipses and residuals without / with the range bias, read from the files
``uwbimu calibrate`` writes."""

from __future__ import annotations

import base64
import shutil
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from uwbimu.eval.report import error_ellipse, line_of_sight_azimuth, render_report

PARTS = ("td-profile", "residual-angle", "anchor-ellipses", "before-after", "sigma")
ESTIMATED = "A7"


class _Doc(HTMLParser):
    """Sections, batch parts (with their data- attributes), figures and the tables of each part."""

    def __init__(self):
        super().__init__()
        self.sections, self.figures, self.parts, self.tables = set(), {}, {}, {}
        self._part, self._fig, self._row, self._cell = None, None, None, None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "section":
            self.sections.add(a["id"])
        if tag == "div" and "data-part" in a:
            self._part = a["data-part"]
            self.parts[self._part] = {k[5:]: v for k, v in a.items() if k.startswith("data-")}
            self.tables[self._part] = []
        if tag == "figure":
            self._fig = a["id"]
        if tag == "img" and self._fig:
            self.figures[self._fig] = a["src"]
        if tag == "tr" and self._part:
            self._row = []
            self.tables[self._part].append(self._row)
        if tag in ("td", "th") and self._row is not None:
            self._cell = []

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self._cell is not None:
            self._row.append("".join(self._cell).strip())
            self._cell = None
        if tag == "tr":
            self._row = None
        if tag == "section":
            self._part = None

    def handle_data(self, data):
        if self._cell is not None:
            self._cell.append(data)


def _parse(text: str) -> _Doc:
    d = _Doc()
    d.feed(text)
    return d


def _table(doc: _Doc, part: str) -> pd.DataFrame:
    rows = doc.tables[part]
    return pd.DataFrame(rows[1:], columns=rows[0])


@pytest.fixture(scope="module")
def batch_out(tmp_path_factory):
    """A 10 s simulated calibration flight through the batch calibrator (profile on, one anchor estimated)."""
    pytest.importorskip("gtsam")
    from uwbimu.calibration import CalibrationOptions, calibrate, write_calibration
    from uwbimu.sim import builtin_scenario, simulate

    sc = builtin_scenario("calibration-flight")
    sc = sc.model_copy(update={"duration": 10.0, "seeds": sc.seeds.model_copy(update={"noise": 4})})
    ds = simulate(sc)
    opts = CalibrationOptions.model_validate({"td_profile": {"half_width": 0.2, "step": 0.1},
                                              "estimate_anchors": [ESTIMATED]})
    out = tmp_path_factory.mktemp("batch") / "out"
    out.mkdir()
    write_calibration(calibrate(ds, opts), out, plots=False)
    return out, ds


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_section_has_its_four_parts(batch_out):
    out, _ds = batch_out
    doc = _parse(render_report(out))
    assert "batch" in doc.sections
    assert set(PARTS) <= set(doc.parts)
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    assert doc.parts["td-profile"]["verdict"] == cal["time_offset"]["verdict"]
    # the IMU noise scale the profile was computed under (estimated by default)
    assert float(doc.parts["td-profile"]["imu-noise-scale"]) == cal["imu_noise"]["scale"]["scale"]
    # attitude in trajectory.csv and anchors in anchors_estimated.csv: angle, not time
    assert doc.parts["residual-angle"]["x-axis"] == "azimuth"
    assert doc.parts["residual-angle"]["anchors-from"] == "anchors_estimated.csv"
    assert doc.parts["anchor-ellipses"]["estimated"] == "1"
    # the systematic part of the estimated anchor's sigma, from calibration.yaml anchors.systematic
    sysm = cal["anchors"]["systematic"]
    assert doc.parts["anchor-ellipses"]["surveyed-used"] == str(sysm["surveyed_anchors_used"]) == "7"
    assert doc.parts["anchor-ellipses"]["systematic-sd-cm"] == f"{100 * sysm['sd']:.1f}"
    assert doc.parts["before-after"]["before"] == "present"
    assert doc.parts["before-after"]["drift"] == "absent"  # the writer adds bias_drift only with range_bias_drift
    # the Huber threshold behind the down-weighted counts, as calibration.yaml range_model.huber states it
    hub = cal["range_model"]["huber"]
    assert doc.parts["before-after"]["huber-k"] == f"{hub['k']:.3f}" == f"{cal['ranges']['huber_k']:.3f}"
    assert doc.parts["before-after"]["huber-selection"] == hub["selection"] == "adaptive"
    for name in ("fig-batch-td-profile", "fig-batch-residual-angle", "fig-batch-anchor-ellipses"):
        png = base64.b64decode(doc.figures[name].split(",", 1)[1])
        assert png[:8] == b"\x89PNG\r\n\x1a\n", name
    # the ellipse table: the estimated anchor with its 2-sigma semi-axes, the others fixed
    ell = _table(doc, "anchor-ellipses").set_index("anchor")
    an = pd.read_csv(out / "anchors_estimated.csv").set_index("anchor")
    assert set(ell.index[ell["position"] == "estimated"]) == {ESTIMATED}
    major = float(ell.loc[ESTIMATED, "2σ major [cm]"])
    sx, sy = an.loc[ESTIMATED, ["sd_x", "sd_y"]]
    assert 2 * 100 * max(sx, sy) - 0.05 <= major <= 2 * 100 * np.hypot(sx, sy) + 0.05


def test_sigma_table_is_calibration_yaml(batch_out):
    """The "how the sigma were formed" table: the model and reported sigma and the block check, per parameter."""
    out, _ds = batch_out
    doc = _parse(render_report(out))
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    bc = cal["covariance"]["block_check"]
    assert doc.parts["sigma"]["method"] == "sandwich" and doc.parts["sigma"]["blocks"] == str(bc["blocks"])
    assert doc.parts["sigma"]["widened"] == str(sum(p["widened"] for p in bc["parameters"].values()))
    tab = _table(doc, "sigma").set_index("parameter")
    assert list(tab.index) == ["lever_arm_x", "lever_arm_y", "lever_arm_z", "time_offset"]
    for i, c in enumerate("xyz"):
        assert float(tab.loc[f"lever_arm_{c}", "σ reported"]) == pytest.approx(100 * cal["lever_arm_sd"][i], rel=1e-3)
        assert float(tab.loc[f"lever_arm_{c}", "σ model"]) == pytest.approx(100 * cal["lever_arm_sd_model"][i],
                                                                            rel=1e-3)
    assert [tab.loc[f"lever_arm_{c}", "verdict"] for c in "xyz"] == \
        [cal["identifiability"]["lever_arm"][c]["verdict"] for c in "xyz"]
    assert tab.loc["time_offset", "verdict"] == cal["time_offset"]["verdict"]
    p = bc["parameters"]["time_offset"]
    assert float(tab.loc["time_offset", "σ reported"]) == pytest.approx(1000 * cal["time_offset"]["sd"], rel=1e-3)
    assert float(tab.loc["time_offset", "block / HAC variance"]) == pytest.approx(p["variance_ratio"], rel=1e-3)
    assert tab.loc["time_offset", "widened"] == ("yes" if p["widened"] else "no")


def test_sigma_part_without_a_block_check(batch_out, tmp_path):
    """A calibration.yaml without ``covariance.block_check`` (blocks 0, model, or an older file): the part says
    so and shows the sigma without block columns' values."""
    out, _ds = batch_out
    o = _copy(out, tmp_path / "noblocks")
    cal = yaml.safe_load((o / "calibration.yaml").read_text())
    del cal["covariance"]["block_check"]
    (o / "calibration.yaml").write_text(yaml.safe_dump(cal, sort_keys=False))
    doc = _parse(render_report(o))
    assert doc.parts["sigma"]["blocks"] == "0" and doc.parts["sigma"]["widened"] == "0"
    tab = _table(doc, "sigma").set_index("parameter")
    assert (tab["widened"] == "–").all()
    assert float(tab.loc["lever_arm_x", "σ reported"]) == pytest.approx(100 * cal["lever_arm_sd"][0], rel=1e-3)


def test_before_after_table_uses_the_written_columns(batch_out):
    """"with" = measured − predicted as written (bias inside); "without" = that + anchor_bias, per anchor."""
    out, _ds = batch_out
    doc = _parse(render_report(out))
    tab = _table(doc, "before-after").set_index("anchor")
    res = pd.read_csv(out / "residuals.csv")
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    assert set(tab.index) == set(res["anchor"].astype(str)) | {"all"}
    for a, g in res.groupby(res["anchor"].astype(str)):
        mmp = g["range"] - g["predicted"]  # measured − predicted, the ESKF's sign (issue 30)
        with_ = 100 * mmp.median()
        without = 100 * (mmp + cal["anchor_bias"][a]).median()
        assert float(tab.loc[a, "median with [cm]"]) == pytest.approx(with_, abs=0.006)
        assert float(tab.loc[a, "median without [cm]"]) == pytest.approx(without, abs=0.006)
        assert int(tab.loc[a, "ranges"]) == len(g)
        assert int(tab.loc[a, "down-weighted"]) == int(g["outlier"].sum())
    assert int(tab.loc["all", "ranges"]) == len(res)


def test_residual_vs_time_when_no_attitude_or_anchors(batch_out, tmp_path):
    out, ds = batch_out
    o = _copy(out, tmp_path / "o")
    (o / "anchors_estimated.csv").unlink()
    # without anchors_estimated.csv: the dataset's anchors give the angle; no ellipses
    doc = _parse(render_report(o, dataset=ds))
    assert doc.parts["residual-angle"]["x-axis"] == "azimuth"
    assert doc.parts["residual-angle"]["anchors-from"] == "dataset anchors.csv"
    assert doc.parts["anchor-ellipses"]["estimated"] == "0"
    assert "fig-batch-anchor-ellipses" not in doc.figures
    # no anchors at all: residual vs time, said in the part's attribute and shown as a figure
    doc = _parse(render_report(o))
    assert doc.parts["residual-angle"]["x-axis"] == "time"
    assert "fig-batch-residual-angle" in doc.figures
    # no attitude in trajectory.csv: time as well
    o2 = _copy(out, tmp_path / "o2")
    tr = pd.read_csv(o2 / "trajectory.csv").drop(columns=["qw", "qx", "qy", "qz"])
    tr.to_csv(o2 / "trajectory.csv", index=False)
    assert _parse(render_report(o2)).parts["residual-angle"]["x-axis"] == "time"


def test_batch_text_is_escaped(batch_out, tmp_path):
    out, _ds = batch_out
    o = _copy(out, tmp_path / "o")
    evil_id = '<img src=x onerror="alert(1)">'
    evil_verdict = '"><script>alert(2)</script>'
    for name in ("residuals.csv", "anchors_estimated.csv"):
        df = pd.read_csv(o / name)
        df["anchor"] = df["anchor"].astype(str).replace({"A0": evil_id})
        df.to_csv(o / name, index=False)
    cal = yaml.safe_load((o / "calibration.yaml").read_text())
    cal["anchor_bias"][evil_id] = cal["anchor_bias"].pop("A0")
    cal["time_offset"]["verdict"] = evil_verdict
    (o / "calibration.yaml").write_text(yaml.safe_dump(cal))
    html = render_report(o)
    assert "<script>" not in html and "<img src=x" not in html
    doc = _parse(html)
    assert doc.parts["td-profile"]["verdict"] == evil_verdict  # escaped in the attribute, read back intact
    assert evil_id in _table(doc, "before-after")["anchor"].tolist()
    assert evil_id in _table(doc, "anchor-ellipses")["anchor"].tolist()


def test_folder_without_batch_outputs_has_no_section(tmp_path):
    """An estimator folder (scalar time_offset, no td_profile.csv / anchors_estimated.csv): no batch section."""
    out = tmp_path / "est"
    out.mkdir()
    (out / "calibration.yaml").write_text(yaml.safe_dump({
        "lever_arm": [0.1, 0.0, 0.0], "lever_arm_sd": [0.01, 0.01, 0.01], "time_offset": 0.01,
        "time_offset_sd": 0.002}))
    pd.DataFrame({"t": [0.0, 0.1], "px": [0.0, 0.1], "py": [0.0, 0.0], "pz": [1.0, 1.0]}).to_csv(
        out / "trajectory.csv", index=False)
    pd.DataFrame({"t": [0.0, 0.1], "anchor": ["A0", "A1"], "innovation": [0.01, -0.01], "nis": [0.5, 0.4],
                  "accepted": [True, True]}).to_csv(out / "residuals.csv", index=False)
    doc = _parse(render_report(out))
    assert "calibration" in doc.sections and "batch" not in doc.sections
    assert doc.parts == {}
    # td_profile.csv alone makes it a batch folder
    pd.DataFrame({"time_offset": [-0.1, 0.0, 0.1], "chi2": [9.0, 0.0, 9.0], "delta_chi2": [9.0, 0.0, 9.0],
                  "iterations": [3, 3, 3]}).to_csv(out / "td_profile.csv", index=False)
    doc = _parse(render_report(out))
    assert "batch" in doc.sections and set(PARTS) <= set(doc.parts)


def test_line_of_sight_azimuth_body_frame():
    """Azimuth of the anchor seen from the tag antenna, in the body frame (lever arm included)."""
    s = np.sqrt(0.5)
    traj = pd.DataFrame({"t": [0.0, 1.0, 2.0], "px": 0.0, "py": 0.0, "pz": 0.0,
                         # identity, identity, then 90 deg yaw (body x along world y)
                         "qw": [1.0, 1.0, s], "qx": 0.0, "qy": 0.0, "qz": [0.0, 0.0, s]})
    anchors = pd.DataFrame({"anchor": ["N", "E"], "x": [0.0, 1.0], "y": [1.0, 0.0], "z": [0.0, 0.0]})
    res = pd.DataFrame({"t": [0.0, 0.0, 2.0, 2.0, 5.0], "anchor": ["N", "E", "N", "E", "N"]})
    az = line_of_sight_azimuth(res, traj, anchors)
    np.testing.assert_allclose(az[:4], [90.0, 0.0, 0.0, -90.0], atol=1e-9)
    assert np.isnan(az[4])  # outside the trajectory's span
    # tag antenna 1 m along body x.  t=0: anchor N at world (0, 1, 0) is seen at (-1, 1) -> 135 deg;
    # t=2 (yaw 90 deg, antenna at world (0, 1, 0)): anchor E at world offset (1, -1) = body (-1, -1) -> -135 deg
    az = line_of_sight_azimuth(res.iloc[[0, 3]], traj, anchors, lever_arm=[1.0, 0.0, 0.0])
    np.testing.assert_allclose(az, [135.0, -135.0], atol=1e-9)
    # several tags: each row uses its own tag's lever arm (tag "b" at the IMU origin)
    two = res.iloc[[0, 3, 0]].assign(tag=["a", "a", "b"])
    az = line_of_sight_azimuth(two, traj, anchors, lever_arm={"a": [1.0, 0.0, 0.0], "b": [0.0, 0.0, 0.0]})
    np.testing.assert_allclose(az, [135.0, -135.0, 90.0], atol=1e-9)


def test_error_ellipse():
    major, minor, ang = error_ellipse(0.02, 0.01, 0.0)
    assert (major, minor) == pytest.approx((0.04, 0.02))
    assert ang % 180.0 == pytest.approx(0.0, abs=1e-9) or ang % 180.0 == pytest.approx(180.0, abs=1e-9)
    major, minor, ang = error_ellipse(0.01, 0.01, 0.9)
    assert major == pytest.approx(2 * 0.01 * np.sqrt(1.9))
    assert minor == pytest.approx(2 * 0.01 * np.sqrt(0.1))
    assert ang % 180.0 == pytest.approx(45.0)


def test_cli_report_on_a_calibrate_folder(batch_out, tmp_path):
    """``uwbimu calibrate DS --out OUT`` then ``uwbimu report OUT --dataset DS``: report.html next to the outputs."""
    from typer.testing import CliRunner

    from uwbimu.cli.main import app
    from uwbimu.io.dataset import write_dataset

    _out, ds = batch_out
    ds_dir = write_dataset(ds, tmp_path / "ds")
    cfg = tmp_path / "calibrate.yaml"
    cfg.write_text(yaml.safe_dump({"td_profile": {"enabled": False}, "max_iterations": 10}))
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["calibrate", str(ds_dir), "--out", str(out), "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["report", str(out), "--dataset", str(ds_dir)])
    assert r.exit_code == 0, r.output
    doc = _parse((out / "report.html").read_text())
    assert "batch" in doc.sections and set(PARTS) <= set(doc.parts)
    # profile disabled: no td_profile.csv, the part says so (verdict from calibration.yaml)
    assert not (out / "td_profile.csv").exists()
    assert doc.parts["td-profile"]["verdict"] == "not_profiled"
    assert "fig-batch-td-profile" not in doc.figures
    assert doc.parts["anchor-ellipses"]["estimated"] == "0"


def test_a_malformed_input_fails_its_part_only(batch_out, tmp_path):
    out, _ds = batch_out
    o = _copy(out, tmp_path / "o")
    df = pd.read_csv(o / "anchors_estimated.csv")
    df["sd_x"] = "not a number"
    df.to_csv(o / "anchors_estimated.csv", index=False)
    doc = _parse(render_report(o))
    assert doc.parts["anchor-ellipses"].get("failed") == "yes"
    assert all("failed" not in doc.parts[k] for k in PARTS if k != "anchor-ellipses")


def test_residual_without_removes_the_named_model_terms():
    """calibration.outputs.residual_without: measured − predicted (here: the residual, no range/predicted columns) +
    anchor bias + each present model column; an anchor without a bias and a non-numeric cell give NaN."""
    from uwbimu.calibration.outputs import residual_without

    res = pd.DataFrame({"anchor": ["A", "B", "C", "A"], "residual": [0.10, -0.20, 0.05, "x"],
                        "bias_drift": [0.01, 0.02, 0.0, 0.0], "bias_direction": [0.03, 0.0, 0.0, 0.0]})
    out = residual_without(res, {"A": 0.05, "B": -0.1})
    np.testing.assert_allclose(out[:2], [0.10 + 0.05 + 0.01 + 0.03, -0.20 - 0.1 + 0.02])
    assert np.isnan(out[2]) and np.isnan(out[3])
    only_drift = residual_without(res, {"A": 0.05, "B": -0.1}, columns=("bias_drift",))
    assert only_drift[0] == pytest.approx(0.10 + 0.05 + 0.01)
    # with range and predicted columns, the residual column's sign does not matter
    both = pd.DataFrame({"anchor": ["A"], "range": [5.0], "predicted": [5.2], "residual": [99.0]})
    assert residual_without(both, {"A": 0.05}, columns=())[0] == pytest.approx(5.0 - 5.2 + 0.05)


def test_estimators_part_says_whether_the_batch_agrees_with_the_eskf(batch_out, tmp_path):
    """calibration.yaml ``estimators`` (the batch against its initialising ESKF) in the batch section: attribute
    ``estimators`` agree / disagree, the disagreeing parameters named; a file without the check reads unknown."""
    out, _ds = batch_out
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    ev = cal["estimators"]
    assert ev["kind"] in ("estimators_agree", "estimators_disagree")
    assert any(e["kind"] == ev["kind"] for e in cal["events"])
    doc = _parse(render_report(out))
    assert doc.parts["estimators"]["estimators"] == ("agree" if ev["kind"] == "estimators_agree" else "disagree")
    # the same run with a time offset 10 combined sigma away from the ESKF's
    o = _copy(out, tmp_path / "o")
    row = {"name": "time_offset", "eskf": 0.03, "eskf_sd": 0.003, "batch": -0.0124, "batch_sd": 0.003, "z": 10.0,
           "eskf_verdict": "identified", "batch_verdict": "identified", "favours": "neither", "reason": "r"}
    cal["estimators"] = {"kind": "estimators_disagree", "severity": "warning", "parameters": [row],
                         "disagreeing": ["time_offset"], "z_threshold": 3.0}
    (o / "calibration.yaml").write_text(yaml.safe_dump(cal))
    part = _parse(render_report(o)).parts["estimators"]
    assert part["estimators"] == "disagree" and part["disagreeing"] == "time_offset"
    del cal["estimators"]
    (o / "calibration.yaml").write_text(yaml.safe_dump(cal))
    assert _parse(render_report(o)).parts["estimators"]["estimators"] == "unknown"
