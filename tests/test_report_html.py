"""The one-file HTML report: structure (html.parser) and rendering in headless Chromium."""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from uwbimu.eval.report import anchor_residual_table, render_report, write_report
from uwbimu.io.dataset import Dataset, DatasetMeta, TruthMeta

ALL_FIGURES = {"fig-convergence", "fig-nis", "fig-trajectory", "fig-errors", "fig-repeatability", "fig-observability"}
ALL_SECTIONS = {"calibration", "convergence", "residuals", "nis", "trajectory", "repeatability", "observability", "warnings"}


def make_output(folder: Path, seed: int = 0, with_eval: bool = True, with_extras: bool = True) -> Path:
    """A synthetic estimator output folder with every file the report reads."""
    rng = np.random.default_rng(seed)
    folder.mkdir(parents=True, exist_ok=True)
    t = np.arange(0.0, 30.0, 0.1)
    n = len(t)
    sd_l = 0.2 * np.exp(-t / 5) + 0.005
    traj = pd.DataFrame({
        "t": t, "px": np.cos(0.3 * t), "py": np.sin(0.3 * t), "pz": 1.0 + 0 * t,
        "qw": np.cos(0.15 * t), "qx": 0 * t, "qy": 0 * t, "qz": np.sin(0.15 * t),
        "vx": -0.3 * np.sin(0.3 * t), "vy": 0.3 * np.cos(0.3 * t), "vz": 0 * t,
        "sd_px": 0.03 + 0 * t, "sd_py": 0.03 + 0 * t, "sd_pz": 0.05 + 0 * t,
        "lx": 0.1 + sd_l * rng.normal(size=n) * 0.3, "ly": -0.025 + 0 * t, "lz": 0.0 + 0 * t, "td": 0.01 + 0 * t,
        "sd_lx": sd_l, "sd_ly": sd_l, "sd_lz": sd_l, "sd_td": 0.05 * np.exp(-t / 5) + 0.002,
    })
    traj.to_csv(folder / "trajectory.csv", index=False)
    cal = {"lever_arm": [0.101, -0.02, 0.003], "lever_arm_sd": [0.005, 0.005, 0.006], "time_offset": 0.012,
           "time_offset_sd": 0.002, "accel_bias": [0.01, 0.0, -0.02], "accel_bias_sd": [0.01, 0.01, 0.01],
           "gyro_bias": [0.001, 0.0, 0.0], "gyro_bias_sd": [1e-4, 1e-4, 1e-4],
           "warnings": ["time offset weakly excited during 0-5 s"]}
    (folder / "calibration.yaml").write_text(yaml.safe_dump(cal))
    m = 2000
    anchors = rng.choice(["1", "2", "3", "4"], size=m)
    innov = rng.normal(0, 0.05, m) + np.where(anchors == "3", 0.15, 0.0)
    nis = (innov / 0.05) ** 2
    pd.DataFrame({"t": np.sort(rng.uniform(0, 30, m)), "anchor": anchors, "range": 3 + innov,
                  "predicted": 3.0 + 0 * innov, "innovation": innov, "nis": nis, "accepted": nis < 9}).to_csv(
        folder / "residuals.csv", index=False)
    (folder / "metrics.yaml").write_text(yaml.safe_dump({"position_rmse": 0.05, "nees_mean": 19.3}))
    if with_eval:
        pd.DataFrame({"t": t, "px_gt": traj.px, "py_gt": traj.py, "pz_gt": traj.pz,
                      "px_est": traj.px + 0.02, "py_est": traj.py, "pz_est": traj.pz,
                      "ex": 0.02 + 0 * t, "ey": 0 * t, "ez": 0 * t, "e": 0.02 + 0 * t}).to_csv(
            folder / "evaluation_errors.csv", index=False)
        stats = {"rmse": 0.02, "mean": 0.02, "median": 0.02, "max": 0.02, "n": n}
        (folder / "evaluation.json").write_text(json.dumps({
            "align": {"mode": "none", "rotation_deg": 0.0, "translation": [0, 0, 0]},
            "association": {"n_groundtruth_glitches_excluded": 1, "n_groundtruth_attitude_glitches_excluded": 0},
            "ate_position": stats, "rpe": {"1": {"n_pairs": 10, "translation": stats, "translation_percent": 2.0,
                                                 "rotation_deg": stats}}}))
    if with_extras:
        wins = [{"i": i, "t0": 10.0 * i, "t1": 10.0 * (i + 1), "t_mid": 10.0 * i + 5,
                 "values": {"lx": 0.1 + 0.003 * i, "td": 0.01}, "sd": {"lx": 0.004, "td": 0.001}} for i in range(3)]
        (folder / "repeatability.json").write_text(json.dumps({
            "k": 3, "window_s": 10.0, "windows": wins,
            "parameters": {"lx": {"n": 3, "mean": 0.103, "std": 0.003, "rms_sd": 0.004, "ratio": 0.75, "chi2": 1.1,
                                  "dof": 2, "p_value": 0.57, "verdict": "consistent"},
                           "td": {"n": 3, "mean": 0.01, "std": 0.0, "rms_sd": 0.001, "ratio": 0.0, "chi2": 0.0,
                                  "dof": 2, "p_value": 1.0, "verdict": "under-confident"}}}))
        pd.DataFrame({"t": t, "excitation_rot": 1 + np.sin(t), "sigma_min": np.exp(-t)}).to_csv(
            folder / "observability.csv", index=False)
    return folder


class _Collector(HTMLParser):
    def __init__(self):
        super().__init__()
        self.sections, self.figures, self.imgs, self.external = set(), set(), [], []
        self._fig = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "section":
            self.sections.add(a.get("id"))
        if tag == "figure":
            self._fig = a.get("id")
            self.figures.add(self._fig)
        if tag == "img":
            self.imgs.append((self._fig, a.get("src", "")))
        for k in ("src", "href"):
            v = a.get(k)
            if v and not (v.startswith("data:") or v.startswith("#")):
                self.external.append(v)
        if tag in ("script", "link"):
            self.external.append(tag)


def _parse(text: str) -> _Collector:
    c = _Collector()
    c.feed(text)
    return c


@pytest.fixture(scope="module")
def full_report(tmp_path_factory):
    """One report with every input, shared by the structure and the browser test."""
    out = make_output(tmp_path_factory.mktemp("report") / "out")
    return write_report(out)


def test_report_structure_every_figure_decodes(full_report):
    path, out = full_report, full_report.parent
    assert path == out / "report.html"
    c = _parse(path.read_text())
    assert ALL_SECTIONS <= c.sections
    assert ALL_FIGURES <= c.figures
    assert c.external == []  # self-contained: no script, no external URL
    assert len(c.imgs) == len(ALL_FIGURES)
    for fig, src in c.imgs:
        assert src.startswith("data:image/png;base64,"), fig
        png = base64.b64decode(src.split(",", 1)[1])
        assert png[:8] == b"\x89PNG\r\n\x1a\n", fig
        w, h = int.from_bytes(png[16:20], "big"), int.from_bytes(png[20:24], "big")
        assert w > 100 and h > 100, fig
    text = path.read_text()
    assert "10.10 ± 0.50" in text  # lever arm x ± sigma [cm], Kalibr-style (uwbimu.formatting)
    assert "12.0 ± 2.0" in text  # time offset ± sigma [ms]
    assert "biased" in text  # anchor 3 carries +15 cm
    assert "time offset weakly excited" in text


def test_report_missing_inputs_say_so(tmp_path):
    out = make_output(tmp_path / "out", with_eval=False, with_extras=False)
    (out / "trajectory.csv").write_text(pd.read_csv(out / "trajectory.csv")[["t", "px", "py", "pz"]].to_csv(index=False))
    text = render_report(out)
    c = _parse(text)
    assert ALL_SECTIONS <= c.sections
    assert "fig-convergence" not in c.figures and "fig-repeatability" not in c.figures
    assert "no calibration history" in text and "repeatability.json</code> not found" in text
    assert "observability.csv</code> not found" in text
    assert "fig-trajectory" in c.figures and "fig-nis" in c.figures


def test_report_with_dataset_evaluates_and_shows_reference(tmp_path):
    out = make_output(tmp_path / "out", with_eval=False, with_extras=False)
    traj = pd.read_csv(out / "trajectory.csv")
    gt = traj[["t", "px", "py", "pz", "qw", "qx", "qy", "qz"]].copy()
    gt["px"] += 0.01
    an = pd.DataFrame({"anchor": ["1", "2", "3", "4"], "x": [0, 3, 0, 3.0], "y": [0, 0, 3, 3.0], "z": [0, 1, 2, 0.5]})
    ds = Dataset(imu=pd.DataFrame(), uwb=pd.DataFrame(), anchors=an, groundtruth=gt,
                 meta=DatasetMeta(name="synthetic", truth=TruthMeta(lever_arm=[0.1, -0.025, 0.0], time_offset=0.01)))
    text = render_report(out, dataset=ds)
    c = _parse(text)
    assert {"fig-trajectory", "fig-errors", "fig-convergence"} <= c.figures
    # one position RMSE: with no alignment, metrics.yaml's (the figure `uwbimu estimate` printed)
    rmse = re.findall(r'data-position-rmse="([^"]+)"', text)
    assert rmse and all(float(x) == 0.05 for x in rmse)
    assert "+0.20" in text  # z-score of lever x: (0.101 - 0.1) / 0.005
    assert "n/a (ground truth in another frame)" not in text and "0.05" in text  # metrics.yaml as written
    # without metrics.yaml the one figure is the report's own evaluation: the ATE of the 1 cm shift
    (out / "metrics.yaml").unlink()
    rmse = re.findall(r'data-position-rmse="([^"]+)"', render_report(out, dataset=ds))
    assert rmse and abs(float(rmse[0]) - 0.010) < 5e-4


def test_report_ground_truth_in_other_frame(tmp_path):
    """ISAS-Walk-like dataset: tracker pose in another world and body frame; no meaningless numbers shown."""
    from uwbimu.models.quaternion import quat_exp, quat_multiply

    out = make_output(tmp_path / "out", with_eval=False, with_extras=False)
    traj = pd.read_csv(out / "trajectory.csv")
    gt = traj[["t", "px", "py", "pz", "qw", "qx", "qy", "qz"]].copy()
    gt[["px", "py"]] = gt[["py", "px"]].to_numpy() * [1, -1] + [5.0, 2.0]  # rotated 90 deg and shifted world
    q_off = np.repeat(quat_exp(np.array([[np.pi * 177 / 180, 0.0, 0.0]])), len(gt), axis=0)
    gt[["qw", "qx", "qy", "qz"]] = quat_multiply(gt[["qw", "qx", "qy", "qz"]].to_numpy(), q_off)
    an = pd.DataFrame({"anchor": ["1", "2", "3", "4"], "x": [0, 3, 0, 3.0], "y": [0, 0, 3, 3.0], "z": [0, 1, 2, 0.5]})
    ds = Dataset(imu=pd.DataFrame(), uwb=pd.DataFrame(), anchors=an, groundtruth=gt,
                 meta=DatasetMeta(name="other-frame", extra={"groundtruth_align": "se3",
                                                              "groundtruth_attitude_comparable": False}))
    text = render_report(out, dataset=ds)
    c = _parse(text)
    assert {"fig-trajectory", "fig-errors"} <= c.figures
    assert "<b>se3</b> alignment" in text and "attitude n/a (frames differ)" in text
    assert "attitude RMSE" not in text
    assert "n/a (ground truth in another frame)" in text  # metrics.yaml's unaligned position_rmse / nees


def test_anchor_table_flags():
    rng = np.random.default_rng(1)
    m = 3000
    anchors = np.array(["a", "b", "c"])[rng.integers(0, 3, m)]
    innov = rng.normal(0, 0.05, m)
    innov[anchors == "b"] *= 4  # noisy
    acc = np.ones(m, bool)
    acc[(anchors == "c") & (rng.uniform(size=m) < 0.5)] = False  # rejected half
    tab = anchor_residual_table(pd.DataFrame({"anchor": anchors, "innovation": innov, "nis": innov**2 / 0.0025,
                                              "accepted": acc})).set_index("anchor")
    assert tab.loc["a", "flags"] == ""
    assert "noisy" in tab.loc["b", "flags"]
    assert "rejections" in tab.loc["c", "flags"]
    assert 40 < tab.loc["c", "rejected_pct"] < 60
    assert abs(tab.loc["a", "mad"] * 1.4826 - 0.05) < 0.006


def test_report_cli(tmp_path):
    from uwbimu.cli.main import app

    out = make_output(tmp_path / "out")
    r = CliRunner().invoke(app, ["report", str(out)])
    assert r.exit_code == 0, r.output
    assert (out / "report.html").is_file()
    r = CliRunner().invoke(app, ["report", str(tmp_path / "nothing")])
    assert r.exit_code == 2  # a folder that is not an estimator output: a usage error (issue 30 item 4)


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")

_CHECK_SCRIPT = """<script>window.addEventListener('load', function () {
  var r = Array.prototype.map.call(document.images, function (i) {
    return [i.closest('figure') ? i.closest('figure').id : '', i.complete, i.naturalWidth, i.naturalHeight]; });
  var p = document.createElement('pre'); p.id = 'imgcheck'; p.textContent = JSON.stringify(r);
  document.body.appendChild(p); });</script>"""


@pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install chromium); "
                                              "the HTML structure is still tested without a browser")
def test_report_renders_in_headless_chromium(full_report, tmp_path):
    page = full_report.read_text()
    # The report has no script of its own; a copy gets a probe that lists every image as decoded.
    probe = tmp_path / "probe.html"
    probe.write_text(page.replace("</body>", _CHECK_SCRIPT + "</body>"))
    cmd = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
           "--disable-component-update", "--disable-sync", "--no-first-run", "--disable-dev-shm-usage",
           f"--user-data-dir={tmp_path / 'profile'}", "--virtual-time-budget=10000", "--dump-dom",
           probe.as_uri()]
    env = dict(os.environ, HOME=str(tmp_path))
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    dom = proc.stdout
    start = dom.index('<pre id="imgcheck">') + len('<pre id="imgcheck">')
    res = json.loads(dom[start:dom.index("</pre>", start)])
    figs = {r[0] for r in res}
    assert ALL_FIGURES <= figs
    for fig, complete, w, h in res:
        assert complete and w > 100 and h > 100, (fig, w, h)


def test_report_observability_window_table(tmp_path):
    """The per-window table written by `uwbimu observability` (t_start, t_end, sd_*, flags)."""
    from uwbimu.models.state import ERROR_STATE_NAMES

    out = make_output(tmp_path / "out", with_eval=False, with_extras=False)
    n = 6
    tab = {"t_start": np.arange(n) * 5.0, "t_end": np.arange(1, n + 1) * 5.0,
           "min_eigenvalue": np.logspace(-6, -1, n), "condition_number": np.logspace(6, 2, n),
           "weakest_direction": ["lever arm x"] * n}
    for name in ERROR_STATE_NAMES:
        tab[f"sd_{name}"] = np.r_[np.inf, np.logspace(-1, -3, n - 1)]
    tab.update(n_ranges=np.arange(n) * 10, gyro_rms=np.linspace(0, 1, n),
               lever_arm_excited=[False, False, True, True, True, True],
               time_offset_excited=[False, True, True, True, True, True])
    pd.DataFrame(tab).to_csv(out / "observability.csv", index=False)
    text = render_report(out)
    c = _parse(text)
    assert "fig-observability" in c.figures
    assert "lever arm not excited" in text and "0.0–5.0" in text and "5.0–10.0" in text
    assert "time offset not excited" in text
    # the bound is compared with every sigma of calibration.yaml, the time offset's included (either schema)
    assert 'data-bound-params="lx ly lz time_offset"' in text


def test_report_repeatability_shows_the_per_window_bound(tmp_path):
    """With a dataset the repeatability table carries each window's posterior Cramer-Rao bound
    (RMS over windows), the same numbers posterior_crb gives; without IMU data it says '–'."""
    sim = pytest.importorskip("uwbimu.sim")
    from uwbimu.observability.window import posterior_crb

    ds = sim.simulate(sim.builtin_scenario("calibration-flight").model_copy(update={"duration": 30.0}))
    out = make_output(tmp_path / "out")
    text = render_report(out, dataset=ds)
    row = re.search(r"lx \[cm\]</td>(.*?)</tr>", text, flags=re.S)
    assert row is not None
    cells = re.findall(r"<td[^>]*>(.*?)</td>", row.group(1))
    wins = json.loads((out / "repeatability.json").read_text())["windows"]
    expect = np.sqrt(np.mean([posterior_crb(ds, t_start=w["t0"], t_end=w["t1"])[0][15, 15] for w in wins]))
    # cells: windows, mean ± σ, truth, mean − truth, z, spread, predicted σ, bound, ...
    assert float(cells[7]) == pytest.approx(100 * expect, rel=0.01)
    # no IMU in the dataset: no bound, a warning, no failure
    bare = Dataset(imu=pd.DataFrame(), uwb=pd.DataFrame(), anchors=ds.anchors, groundtruth=ds.groundtruth, meta=ds.meta)
    text = render_report(out, dataset=bare)
    assert "no per-window Cramér-Rao bound" in text
