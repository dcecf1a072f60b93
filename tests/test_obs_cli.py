"""``uwbimu observability structural|delay|log`` and the config files of examples/observability."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.models.state import ERROR_STATE_NAMES
from uwbimu.observability import structural_verdict
from uwbimu.observability.config import ConfigError, load_config

EXAMPLES = Path(__file__).resolve().parents[1] / "examples" / "observability"
runner = CliRunner()


def test_structural_json_keys():
    res = runner.invoke(app, ["observability", "structural", str(EXAMPLES / "theorem2_generic.yaml"), "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.output)
    for k in ("rank", "dimension", "observable", "lie_order", "singular_values", "unobservable_directions", "conditions"):
        assert k in d
    assert d["rank"] == 18 and d["dimension"] == 18 and d["observable"] is True
    # lie_order: auto stops at the first order with full rank (2 for 3 anchors, full excitation)
    assert d["lie_order"] == 2 and d["verdict"] == "observable" and d["order_search"][-1]["rank"] == 18
    assert d["conditions"]["theorem2"] is True and len(d["singular_values"]) == 18


def test_structural_json_directions_are_name_vector_pairs():
    res = runner.invoke(app, ["observability", "structural", str(EXAMPLES / "single_anchor.yaml"), "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.output)
    assert d["rank"] == 17 and d["observable"] is False and d["conditions"]["C1"] is False
    assert d["verdict"] == "not observable" and d["cross_check"]["rank"] == 17
    (u,) = d["unobservable_directions"]
    assert set(u) == {"name", "vector"} and u["name"].startswith("global yaw about the vertical line")
    assert len(u["vector"]) == d["dimension"] == 18


def test_structural_rich_output_names_directions():
    res = runner.invoke(app, ["observability", "structural", str(EXAMPLES / "single_anchor.yaml")])
    assert res.exit_code == 0, res.output
    assert "not observable" in res.output and "global yaw" in res.output


def test_delay_json():
    res = runner.invoke(app, ["observability", "delay", str(EXAMPLES / "delay_gyro_only.yaml"), "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.output)
    assert d["identifiable"] is True and d["conditions"] == {"T1": True, "T2": False, "T3": True}
    res = runner.invoke(app, ["observability", "delay", str(EXAMPLES / "delay_no_excitation.yaml"), "--json"])
    assert json.loads(res.output)["identifiable"] is False


def test_delay_warns_when_only_a_higher_order_effect_identifies_td(tmp_path):
    cfg = tmp_path / "zero_lever_gyro.yaml"
    cfg.write_text(
        "anchors: [[0, 0, 0], [5, 0, 0.5], [0, 5, 1.0]]\nlever_arm: [0, 0, 0]\n"
        "excitation: {accel: [], gyro: [x, y, z]}\ntime_offset: 0.02\nrandom_points: 3\n"
    )
    res = runner.invoke(app, ["observability", "delay", str(cfg)])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "T1 and (T2 or T3) │ no" in text and "conditions do not hold" in text
    # the sensitivity is a third-order effect of t_d: far below a range noise of centimetres
    d = json.loads(runner.invoke(app, ["observability", "delay", str(cfg), "--json"]).output)
    assert d["identifiable"] and not d["theorem1"] and max(d["numeric"]["sensitivity"].values()) < 1e-4
    res = runner.invoke(app, ["observability", "delay", str(EXAMPLES / "delay_gyro_only.yaml")])
    assert "conditions do not hold" not in " ".join(res.output.split())


def test_bad_config_is_a_readable_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("anchors: [[0, 0], [1, 1, 1]]\nlie_order: 9\n")
    res = runner.invoke(app, ["observability", "structural", str(bad)])
    assert res.exit_code == 2
    assert "bad.yaml" in res.output and "anchors" in res.output and "lie_order" in res.output
    assert "Traceback" not in res.output
    with pytest.raises(ConfigError, match="configuration file not found"):
        load_config(tmp_path / "missing.yaml")
    res = runner.invoke(app, ["observability", "delay", str(EXAMPLES / "pointmass_4_beacons.yaml")])
    assert res.exit_code == 2 and "uwb_imu" in res.output
    with pytest.raises(ConfigError, match="lever_arm"):
        load_config({"model": "point_mass", "anchors": [[0, 0, 0]], "lever_arm": [0, 0, 0.1]})
    with pytest.raises(ConfigError, match="nominal_input"):
        load_config({"anchors": [[0, 0, 0]], "nominal_input": [0, 0, 9.81]})


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.yaml")), ids=lambda p: p.name)
def test_every_example_config_loads(path):
    cfg = load_config(path)
    assert cfg.anchors


def test_demo_verdict_for_eight_anchors():
    v = structural_verdict(EXAMPLES / "demo_8_anchors.yaml")
    assert v["observable"] and v["rank"] == 18 and v["unobservable_directions"] == []
    assert v["elapsed_s"] < 30


def test_log_command_writes_csv_and_png(tmp_path):
    sim = pytest.importorskip("uwbimu.sim")
    pytest.importorskip("uwbimu.io.loader")
    from uwbimu.io.dataset import write_dataset

    ds = sim.simulate(sim.builtin_scenario("calibration-flight").model_copy(update={"duration": 30.0}))
    folder = write_dataset(ds, tmp_path / "ds")
    out = tmp_path / "out"
    res = runner.invoke(app, ["observability", "log", str(folder), "--window", "10", "--out", str(out)])
    assert res.exit_code == 0, res.output
    table = pd.read_csv(out / "observability.csv")
    head = ["t_start", "t_end", "min_eigenvalue", "condition_number", "weakest_direction"]
    sd_cols = [f"sd_{n}" for n in ERROR_STATE_NAMES]
    # exactly the columns first, in order; extra columns (n_ranges, flags) only after
    assert list(table.columns[: 5 + len(sd_cols)]) == head + sd_cols
    assert [c for c in table.columns if c.startswith("sd_")] == sd_cols
    assert {"lever_arm_excited", "time_offset_excited"} <= set(table.columns)
    assert len(table) == 3
    assert (out / "observability.png").stat().st_size > 1000
    # the output rule: a rerun replaces its own unchanged outputs; an edited one needs --force (exit 4)
    res = runner.invoke(app, ["observability", "log", str(folder), "--window", "10", "--out", str(out)])
    assert res.exit_code == 0, res.output
    (out / "observability.csv").write_text((out / "observability.csv").read_text() + "\n")
    res = runner.invoke(app, ["observability", "log", str(folder), "--window", "10", "--out", str(out)])
    assert res.exit_code == 4 and "--force" in res.output
    # --trajectory: an estimator's states.csv (here the truth in that format)
    import numpy as np

    from uwbimu.models.state import NOMINAL_STATE_NAMES

    gt = ds.groundtruth
    X = np.zeros((len(gt), 20))
    X[:, 0:3] = gt[["px", "py", "pz"]].to_numpy()
    X[:, 3:6] = gt[["vx", "vy", "vz"]].to_numpy()
    X[:, 6:10] = gt[["qw", "qx", "qy", "qz"]].to_numpy()
    X[:, 16:19] = ds.meta.truth.lever_arm
    X[:, 19] = ds.meta.truth.time_offset
    states = pd.DataFrame(X, columns=list(NOMINAL_STATE_NAMES))
    states.insert(0, "t", gt["t"].to_numpy())
    states.to_csv(tmp_path / "states.csv", index=False)
    res = runner.invoke(
        app, ["observability", "log", str(folder), "--window", "10", "--out", str(out), "--force", "--trajectory", str(tmp_path / "states.csv")]
    )
    assert res.exit_code == 0, res.output
    assert np.allclose(pd.read_csv(out / "observability.csv")["sd_lx"], table["sd_lx"], rtol=1e-6)
    res = runner.invoke(app, ["observability", "log", str(folder), "--out", str(out), "--force", "--trajectory", str(tmp_path / "nope")])
    # a refused input is exit 1 (uwbimu.errors.InputError), not a usage error
    assert res.exit_code == 1 and "estimator states file" in " ".join(res.output.split())


def test_dataset_helpers_for_the_demo():
    sim = pytest.importorskip("uwbimu.sim")
    from uwbimu.observability.structural import config_for_dataset, format_verdict

    ds = sim.simulate(sim.builtin_scenario("calibration-flight").model_copy(update={"duration": 5.0}))
    cfg = config_for_dataset(ds, random_points=2)
    assert len(cfg.anchors) == len(ds.anchors) and cfg.lever_arm == list(ds.meta.truth.lever_arm)
    v = structural_verdict(cfg)
    line = format_verdict(v)
    assert v["observable"] and line.startswith("observable: rank 18/18")


def test_window_on_an_estimator_trajectory(tmp_path):
    """An EstimationResult (here: the truth written as estimator states) drives the analysis too."""
    sim = pytest.importorskip("uwbimu.sim")
    import numpy as np

    from uwbimu.estimation.result import EstimationResult
    from uwbimu.observability.window import WindowOptions, trajectory_from_groundtruth, trajectory_from_result, window_observability

    ds = sim.simulate(sim.builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0}))
    gt = ds.groundtruth
    X = np.zeros((len(gt), 20))
    X[:, 0:3] = gt[["px", "py", "pz"]].to_numpy()
    X[:, 3:6] = gt[["vx", "vy", "vz"]].to_numpy()
    X[:, 6:10] = gt[["qw", "qx", "qy", "qz"]].to_numpy()
    X[:, 16:19] = ds.meta.truth.lever_arm
    X[:, 19] = ds.meta.truth.time_offset
    res = EstimationResult(t=gt["t"].to_numpy(), states=X, sd=np.full((len(gt), 19), np.nan), residuals=None, calibration={})
    opts = WindowOptions(window=20.0)
    a, _ = window_observability(ds, trajectory_from_result(res), opts)
    b, _ = window_observability(ds, trajectory_from_groundtruth(ds), opts)
    assert np.allclose(a["sd_lx"], b["sd_lx"], rtol=1e-9) and np.allclose(a["sd_time_offset"], b["sd_time_offset"], rtol=1e-9)
    # the same through a states.csv file and the CLI's --trajectory
    from uwbimu.models.state import NOMINAL_STATE_NAMES
    from uwbimu.observability.window import trajectory_from_states_csv

    states = pd.DataFrame(X, columns=list(NOMINAL_STATE_NAMES))
    states.insert(0, "t", gt["t"].to_numpy())
    states.to_csv(tmp_path / "states.csv", index=False)
    c, _ = window_observability(ds, trajectory_from_states_csv(tmp_path), opts)
    assert np.allclose(c["sd_lx"], b["sd_lx"], rtol=1e-6)
    lines = (tmp_path / "states.csv").read_text().splitlines()
    cells = lines[4].split(",")
    cells[2] = "oops"
    lines[4] = ",".join(cells)
    (tmp_path / "bad.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match="row 5"):
        trajectory_from_states_csv(tmp_path / "bad.csv")
