"""Shipped presets, --preset on the CLI, and dataset properties applied by run_eskf."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from uwbimu.estimation import EskfOptions
from uwbimu.estimation.eskf import resolve_anchor_frame_up
from uwbimu.estimation.presets import load_options, load_preset, preset_names

ROOT = Path(__file__).resolve().parents[1]


def test_presets_ship_and_match_the_examples():
    assert {"default", "real", "isas-walk"} <= set(preset_names())
    assert load_preset("default") == EskfOptions()
    real = load_preset("real")
    assert real == EskfOptions.from_yaml(ROOT / "examples" / "estimator_real.yaml")
    isas = load_preset("isas-walk")
    ex = EskfOptions.from_yaml(ROOT / "examples" / "estimator_isas.yaml")
    # the preset leaves the anchors' frame to the dataset; everything else is the example's
    assert isas.anchor_frame_up is None and ex.anchor_frame_up == "-z"
    assert isas.model_copy(update={"anchor_frame_up": "-z"}) == ex
    with pytest.raises(ValueError, match="known presets"):
        load_preset("nope")


def test_config_overrides_preset(tmp_path):
    cfg = tmp_path / "o.yaml"
    cfg.write_text(yaml.safe_dump({"anchor_bias": {"prior_sd": 0.2}, "output_rate_hz": 5}))
    o = load_options("real", cfg)
    assert o.anchor_bias.prior_sd == 0.2 and o.output_rate_hz == 5
    assert o.anchor_bias.correlation_time == load_preset("real").anchor_bias.correlation_time


class _Meta:
    def __init__(self, up=None, extra=None):
        self.name = "m"
        self.extra = extra or {}
        if up is not None:
            self.anchor_frame_up = up


class _Ds:
    def __init__(self, meta):
        import pandas as pd
        self.meta = meta
        self.uwb = pd.DataFrame({"t": [1.0]})


@pytest.mark.parametrize("meta,opt,expect,warned", [
    (_Meta(), None, "+z", False),
    (_Meta(up="-z"), None, "-z", False),
    (_Meta(extra={"anchor_frame_up": "-z"}), None, "-z", False),   # legacy location
    (_Meta(up="-z"), "+z", "+z", True),                              # explicit option wins, reported
    (_Meta(up="+z"), "+z", "+z", False),
])
def test_anchor_frame_up_from_dataset(meta, opt, expect, warned):
    w, e = [], []
    got = resolve_anchor_frame_up(_Ds(meta), EskfOptions(anchor_frame_up=opt), w, e)
    assert got == expect
    assert bool(e) == warned and all(ev["kind"] == "anchor_frame_override" for ev in e)


def test_cli_preset_runs_and_unknown_preset_is_a_usage_error(tmp_path):
    from typer.testing import CliRunner

    from uwbimu.cli.main import app
    from uwbimu.io.dataset import write_dataset
    from uwbimu.sim import builtin_scenario, simulate

    data = tmp_path / "d"
    write_dataset(simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 15.0})), data)
    r = CliRunner().invoke(app, ["estimate", str(data), "--out", str(tmp_path / "o"), "--preset", "nope"])
    assert r.exit_code == 2 and "known presets" in r.output
    r = CliRunner().invoke(app, ["estimate", str(data), "--out", str(tmp_path / "o"), "--preset", "real",
                                 "--no-plots"])
    assert r.exit_code == 0, r.output
    cal = yaml.safe_load((tmp_path / "o" / "calibration.yaml").read_text())
    assert cal["config"]["anchor_bias"]["correlation_time"] == load_preset("real").anchor_bias.correlation_time
