"""``uwbimu estimate --estimator pointmass`` runs the seed's 6-state EKF behind the same CLI."""

import pandas as pd
import yaml
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.io.dataset import write_dataset
from uwbimu.sim import builtin_scenario, simulate


def test_pointmass_through_estimate_cli(tmp_path):
    ds = simulate(builtin_scenario("circle").updated(duration=20.0))
    data = write_dataset(ds, tmp_path / "data")
    out = tmp_path / "out"
    res = CliRunner().invoke(app, ["estimate", str(data), "--out", str(out), "--estimator", "pointmass", "--no-plots"])
    assert res.exit_code == 0, res.output
    traj = pd.read_csv(out / "trajectory.csv")
    assert {"t", "px", "py", "pz", "sd_px"} <= set(traj.columns)
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    assert "lever_arm" in cal
    metrics = yaml.safe_load((out / "metrics.yaml").read_text())
    assert metrics["estimator"] == "pointmass"
    assert metrics["position_rmse"] < 0.5


def test_unknown_estimator_refused(tmp_path):
    res = CliRunner().invoke(app, ["estimate", str(tmp_path), "--out", str(tmp_path / "o"), "--estimator", "ukf"])
    assert res.exit_code == 2
    assert "--estimator must be" in res.output
