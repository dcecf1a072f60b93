"""``uwbimu calibrate`` end to end on a short simulated flight: files, exit codes, refusals."""

from __future__ import annotations

import pytest
import yaml
from typer.testing import CliRunner

pytest.importorskip("gtsam")

from uwbimu.cli.main import app  # noqa: E402
from uwbimu.io.dataset import write_dataset  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402


@pytest.fixture(scope="module")
def dataset_dir(tmp_path_factory):
    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 8.0}))
    return write_dataset(ds, tmp_path_factory.mktemp("cal") / "ds")


def test_calibrate_writes_its_files(dataset_dir, tmp_path):
    cfg = tmp_path / "calibrate.yaml"
    cfg.write_text(yaml.safe_dump({"td_profile": {"half_width": 0.2, "step": 0.1}, "max_iterations": 10}))
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["calibrate", str(dataset_dir), "--out", str(out), "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    assert {p.name for p in out.iterdir() if not p.name.startswith(".")} == {"calibration.yaml", "trajectory.csv", "residuals.csv", "anchors_estimated.csv",
                                               "td_profile.csv", "td_profile.png"}
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    assert cal["time_offset"]["verdict"] in {"identified", "flat", "multi_modal", "at_grid_edge", "not_curved"}
    assert len(cal["correlations"]["matrix"]) == len(cal["correlations"]["names"])


def test_bad_config_is_a_usage_error(dataset_dir, tmp_path):
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("keyframe_hz: -1\n")
    r = CliRunner().invoke(app, ["calibrate", str(dataset_dir), "--out", str(tmp_path / "o"), "--config", str(cfg)])
    assert r.exit_code == 2
    assert not (tmp_path / "o").exists()


def test_refuses_to_write_into_the_dataset(dataset_dir):
    r = CliRunner().invoke(app, ["calibrate", str(dataset_dir), "--out", str(dataset_dir)])
    assert r.exit_code == 4


def test_estimate_anchors_option(dataset_dir, tmp_path):
    import pandas as pd

    cfg = tmp_path / "calibrate.yaml"
    cfg.write_text(yaml.safe_dump({"td_profile": {"enabled": False}, "max_iterations": 10}))
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["calibrate", str(dataset_dir), "--out", str(out), "--config", str(cfg),
                                 "--estimate-anchors", "A7"])
    assert r.exit_code == 0, r.output
    tab = pd.read_csv(out / "anchors_estimated.csv", dtype={"anchor": str})
    assert list(tab.columns[:4]) == ["anchor", "x", "y", "z"] and {"sd_x", "sd_y", "sd_z", "estimated"} <= set(tab)
    assert tab.set_index("anchor")["estimated"].to_dict() == {a: a == "A7" for a in tab["anchor"]}
    assert (tab.loc[tab.anchor == "A7", ["sd_x", "sd_y", "sd_z"]].to_numpy() > 0).all()
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    assert cal["anchors"]["estimated"] == ["A7"] and "anchor_x_A7" in cal["correlations"]["names"]
    assert "Anchor self-survey" in r.output


@pytest.mark.parametrize("value, code", [("Q9", 1), (" , ", 2)])
def test_estimate_anchors_refusals(dataset_dir, tmp_path, value, code):
    out = tmp_path / "o"
    r = CliRunner().invoke(app, ["calibrate", str(dataset_dir), "--out", str(out), "--estimate-anchors", value])
    assert r.exit_code == code, r.output
    assert not out.exists()


def test_repeatability_with_the_batch_method(dataset_dir, tmp_path):
    """``uwbimu repeatability --method batch``: every window calibrated by the batch (none fails), lever arm
    and t_d tested; the method is recorded in repeatability.json."""
    import json

    cfg = tmp_path / "calibrate.yaml"
    cfg.write_text(yaml.safe_dump({"td_profile": {"enabled": False}, "max_iterations": 10}))
    out = tmp_path / "rep"
    r = CliRunner().invoke(app, ["repeatability", str(dataset_dir), "--out", str(out), "--windows", "2",
                                 "--method", "batch", "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    rep = json.loads((out / "repeatability.json").read_text())
    assert rep["method"] == "batch" and rep["n_failed"] == 0
    n_lx = sum("lever_arm_x" in w["sigma_widened_by_blocks"] for w in rep["windows"])
    assert f"lx {n_lx}," in " ".join(r.output.split())  # the console line counts the windows per parameter
    assert set(rep["parameters"]) == {"lx", "ly", "lz", "time_offset"}
    # every window tested, or left out of the test because the batch held the parameter at its prior there
    assert all(p["n"] + p["held_windows"] == 2 for p in rep["parameters"].values())
    assert all(w["imu_noise_scale"] > 0 for w in rep["windows"])  # each window's estimated IMU noise scale
    # and which sigma its block check widened: names of calibration.yaml's parameters
    assert all(set(w["sigma_widened_by_blocks"]) <= {"lever_arm_x", "lever_arm_y", "lever_arm_z", "time_offset"}
               | {f"anchor_bias_{a}" for a in ("A0", "A1", "A2", "A3", "A4", "A5", "A6", "A7")}
               for w in rep["windows"])
    bad = CliRunner().invoke(app, ["repeatability", str(dataset_dir), "--out", str(tmp_path / "x"),
                                   "--method", "nope"])
    assert bad.exit_code != 0 and "--method" in bad.output


@pytest.fixture
def eskf_options_seen(monkeypatch):
    """The options of every initialising ESKF the batch runs (a spy on ``frames.to_graph_frame``)."""
    from uwbimu.calibration import frames

    seen = []
    orig = frames.to_graph_frame

    def spy(dataset, eskf_options, eskf):
        seen.append(eskf_options)
        return orig(dataset, eskf_options, eskf)

    monkeypatch.setattr(frames, "to_graph_frame", spy)
    return seen


def test_repeatability_batch_takes_the_initialising_eskf_preset(dataset_dir, tmp_path, eskf_options_seen):
    """``--preset`` with ``--method batch`` is the initialising ESKF's options (``init_eskf``): every window's
    filter runs with the preset (its white range sd 0.05 m), the batch options still come from --config."""
    import json

    seen = eskf_options_seen
    cfg = tmp_path / "calibrate.yaml"
    cfg.write_text(yaml.safe_dump({"td_profile": {"enabled": False}, "max_iterations": 10}))
    out = tmp_path / "rep"
    r = CliRunner().invoke(app, ["repeatability", str(dataset_dir), "--out", str(out), "--windows", "2",
                                 "--method", "batch", "--config", str(cfg), "--preset", "real"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "repeatability.json").read_text())["n_failed"] == 0
    assert len(seen) == 2 and all(o.range_sigma == 0.05 and o.anchor_bias.mode == "estimate" for o in seen)


def test_example_calibrate_yaml_is_the_defaults():
    """examples/calibrate.yaml lists the defaults it claims (a changed default must change the example)."""
    from pathlib import Path

    from uwbimu.calibration import CalibrationOptions

    ex = Path(__file__).resolve().parents[1] / "examples" / "calibrate.yaml"
    assert CalibrationOptions.from_yaml(ex) == CalibrationOptions()


def test_summary_says_what_set_each_sigma_and_the_verdict():
    """The console table: per lever-arm axis, t_d and range bias, whether the block check set its sigma or the
    sandwich did, and the identifiability verdict of calibration.yaml."""
    from rich.console import Console

    from uwbimu.cli.calibrate import calibration_summary

    par = {"lever_arm_x": {"variance_ratio": 4.0, "widened": True}, "lever_arm_y": {"variance_ratio": 0.5,
                                                                                    "widened": False},
           "lever_arm_z": {"variance_ratio": 0.9, "widened": False}, "time_offset": {"variance_ratio": 1.0,
                                                                                     "widened": False},
           "anchor_bias_A0": {"variance_ratio": 2.25, "widened": True}}
    cal = {"lever_arm": [0.1, 0.2, 0.3], "lever_arm_sd": [0.02, 0.01, 0.01],
           "time_offset": {"value": 0.01, "sd": 0.002, "sd_curvature": None, "held_at_prior": False,
                           "verdict": "identified"},
           "anchor_bias": {"A0": 0.05}, "anchor_bias_sd": {"A0": 0.01},
           "covariance": {"block_check": {"parameters": par}},
           "identifiability": {"lever_arm": {"x": {"verdict": "identified"}, "y": {"verdict": "weakly identified"},
                                             "z": {"verdict": "identified"}},
                               "anchor_bias": {"A0": {"verdict": "identified"}}}}
    con = Console(record=True, width=200)
    con.print(calibration_summary(cal))
    lines = {ln.split("│")[1].strip(): [c.strip() for c in ln.split("│")[2:-1]] for ln in con.export_text().splitlines()
             if ln.count("│") >= 5}
    assert lines["lever arm x (cm)"][2:] == ["blocks", "identified"]
    assert lines["lever arm y (cm)"][2:] == ["sandwich", "weakly identified"]
    assert lines["time offset (ms)"][2:] == ["sandwich", "identified"]
    assert lines["range bias A0 (cm)"][2:] == ["blocks", "identified"]


def test_calibrate_starts_from_the_eskf_run_uwbimu_estimate_makes(dataset_dir, tmp_path, eskf_options_seen):
    """The initialising ESKF is smoothed forward-backward as `uwbimu estimate`'s (one ESKF answer to start from
    and compare with) unless its options say otherwise; calibrate.yaml's init_eskf is used when no
    --eskf-config is given (the CLI passed the defaults over it before)."""
    seen = eskf_options_seen
    base = {"td_profile": {"enabled": False}, "max_iterations": 10, "second_start": False}
    cfg = tmp_path / "calibrate.yaml"
    cfg.write_text(yaml.safe_dump(base))
    init = tmp_path / "init.yaml"
    init.write_text(yaml.safe_dump(base | {"init_eskf": {"range_sigma": 0.07}}))
    causal = tmp_path / "eskf.yaml"
    causal.write_text(yaml.safe_dump({"smoother": "off"}))
    for i, extra in enumerate((["--config", str(cfg)], ["--config", str(init)],
                               ["--config", str(cfg), "--eskf-config", str(causal)])):
        r = CliRunner().invoke(app, ["calibrate", str(dataset_dir), "--out", str(tmp_path / f"o{i}"), *extra])
        assert r.exit_code == 0, r.output
    assert [o.smoother for o in seen] == ["forward_backward", "forward_backward", "off"]
    assert seen[1].range_sigma == 0.07 and seen[0].range_sigma != 0.07
