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
    assert d["rank"] == 18 and d["dimension"] == 18 and d["observable"] is True and d["lie_order"] == 3
    assert d["conditions"]["theorem2"] is True and len(d["singular_values"]) == 18


def test_structural_rich_output_names_directions():
    res = runner.invoke(app, ["observability", "structural", str(EXAMPLES / "single_anchor.yaml")])
    assert res.exit_code == 0, res.output
    assert "NOT observable" in res.output and "global yaw" in res.output


def test_delay_json():
    res = runner.invoke(app, ["observability", "delay", str(EXAMPLES / "delay_gyro_only.yaml"), "--json"])
    assert res.exit_code == 0, res.output
    d = json.loads(res.output)
    assert d["identifiable"] is True and d["conditions"] == {"T1": True, "T2": False, "T3": True}
    res = runner.invoke(app, ["observability", "delay", str(EXAMPLES / "delay_no_excitation.yaml"), "--json"])
    assert json.loads(res.output)["identifiable"] is False


def test_bad_config_is_a_readable_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("anchors: [[0, 0], [1, 1, 1]]\nlie_order: 9\n")
    res = runner.invoke(app, ["observability", "structural", str(bad)])
    assert res.exit_code == 2
    assert "bad.yaml" in res.output and "anchors" in res.output and "lie_order" in res.output
    assert "Traceback" not in res.output
    with pytest.raises(ConfigError, match="no such configuration file"):
        load_config(tmp_path / "missing.yaml")
    res = runner.invoke(app, ["observability", "delay", str(EXAMPLES / "pointmass_4_beacons.yaml")])
    assert res.exit_code == 2 and "uwb_imu" in res.output


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
    assert list(table.columns[:5]) == ["t_start", "t_end", "min_eigenvalue", "condition_number", "weakest_direction"]
    assert [c for c in table.columns if c.startswith("sd_")] == [f"sd_{n}" for n in ERROR_STATE_NAMES]
    assert len(table) == 3
    assert (out / "observability.png").stat().st_size > 1000
    # refuses to overwrite its outputs without --force
    res = runner.invoke(app, ["observability", "log", str(folder), "--window", "10", "--out", str(out)])
    assert res.exit_code == 2 and "--force" in res.output
