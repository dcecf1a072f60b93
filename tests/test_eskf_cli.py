"""``uwbimu estimate``: files, columns, refusals; options YAML; calibration modes; anchor biases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.estimation import EskfOptions, compute_metrics, run_eskf, write_outputs
from uwbimu.io.dataset import write_dataset
from uwbimu.sim import builtin_scenario, simulate

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def short_ds():
    sc = builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0})
    return simulate(sc)


def test_example_options_file_is_the_defaults_and_bad_keys_are_named(tmp_path):
    assert EskfOptions.from_yaml(ROOT / "examples" / "estimator.yaml") == EskfOptions()
    bad = tmp_path / "bad.yaml"
    bad.write_text("gating:\n  probabilty: 0.99\n")
    with pytest.raises(ValueError, match="probabilty"):
        EskfOptions.from_yaml(bad)


def test_cli_estimate_writes_every_output(tmp_path, short_ds):
    data = write_dataset(short_ds, tmp_path / "ds")
    cfg = tmp_path / "est.yaml"
    cfg.write_text("output_rate_hz: 10\ninit:\n  bank_window_s: 6\n")
    out = tmp_path / "out"
    r = CliRunner().invoke(app, ["estimate", str(data), "--out", str(out), "--config", str(cfg)])
    assert r.exit_code == 0, r.output
    for f in ("trajectory.csv", "calibration.yaml", "residuals.csv", "metrics.yaml", "trajectory.png",
              "position_error.png", "calibration.png", "nis.png", "states.csv", "events.yaml", "run.json"):
        assert (out / f).is_file(), f
    import json
    run = json.loads((out / "run.json").read_text())
    assert run["imu_samples"] == len(short_ds.imu) and run["ranges"] == len(short_ds.uwb)
    assert 0 < run["filter_cpu_seconds"] <= run["total_cpu_seconds"]
    traj = pd.read_csv(out / "trajectory.csv")
    assert list(traj.columns[:11]) == ["t", "px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz"]
    assert {"sd_px", "sd_py", "sd_pz", "sd_vx", "sd_thz"} <= set(traj.columns)
    assert np.all(np.diff(traj.t) > 0) and abs(np.diff(traj.t).mean() - 0.1) < 0.01
    res = pd.read_csv(out / "residuals.csv")
    assert list(res.columns) == ["t", "anchor", "range", "predicted", "innovation", "nis", "accepted"]
    assert len(res) == len(short_ds.uwb)
    cal = yaml.safe_load((out / "calibration.yaml").read_text())
    for k in ("schema_version", "lever_arm", "lever_arm_sd", "time_offset", "accel_bias", "accel_bias_sd",
              "gyro_bias", "gyro_bias_sd", "uwbimu_version", "config"):
        assert k in cal
    assert cal["tags"][next(iter(cal["tags"]))]["lever_arm"] == cal["lever_arm"]
    # the one schema (uwbimu.io.calibration_file): the time offset is a mapping, as `uwbimu calibrate` writes it
    td = cal["time_offset"]
    assert cal["schema_version"] == 2 and "time_offset_sd" not in cal
    assert td["unit"] == "s" and td["mode"] in ("estimate", "consider") and td["sd"] > 0
    assert td["verdict"] in ("identified", "weakly identified", "not identified")
    assert cal["config"]["output_rate_hz"] == 10 and cal["config"]["init"]["bank_window_s"] == 6
    met = yaml.safe_load((out / "metrics.yaml").read_text())
    for k in ("position_rmse", "orientation_rmse_deg", "nees_mean", "lever_arm_error", "time_offset_error"):
        assert k in met
    assert "Range residuals per anchor" in r.output and "lever arm x" in r.output
    # the input is never overwritten; a folder with foreign files is refused
    r2 = CliRunner().invoke(app, ["estimate", str(data), "--out", str(data)])
    assert r2.exit_code != 0
    r3 = CliRunner().invoke(app, ["estimate", str(tmp_path / "missing"), "--out", str(tmp_path / "o2")])
    assert r3.exit_code != 0 and "Traceback" not in r3.output


def test_consider_and_fixed_modes(short_ds):
    lever = [0.1, -0.1, 0.1]
    opts = EskfOptions.model_validate({"lever_arm": {"mode": "consider", "prior": lever, "prior_sd": 0.05},
                                       "time_offset": {"mode": "fixed", "prior": 0.03}})
    res = run_eskf(short_ds, opts)
    # consider: value never corrected, its sd stays at the prior, but is still in the covariance
    np.testing.assert_allclose(res.states[:, 16:19], np.tile(lever, (len(res.t), 1)))
    np.testing.assert_allclose(res.sd[-1, 15:18], 0.05, rtol=1e-6)
    assert np.any(np.abs(res.covariances[-1][0:3, 15:18]) > 1e-6)
    # fixed: exactly the prior, no uncertainty reported
    assert np.all(res.states[:, 19] == 0.03) and np.all(np.isnan(res.sd[:, 18]))
    assert res.calibration["time_offset_sd"] == 0.0


def test_anchor_biases_are_estimated():
    sc = builtin_scenario("calibration-flight")
    biases = {"A1": 0.15, "A4": -0.10}
    sc = sc.model_copy(update={"duration": 40.0, "uwb": sc.uwb.model_copy(update={"anchor_bias": biases})})
    ds = simulate(sc)
    res = run_eskf(ds, EskfOptions.model_validate({"anchor_bias": {"mode": "estimate", "prior_sd": 0.2}}))
    est, sd = res.calibration["anchor_bias"], res.calibration["anchor_bias_sd"]
    for a in ds.anchors["anchor"]:
        true = biases.get(a, 0.0)
        assert abs(est[a] - true) < max(3 * sd[a], 0.01), (a, est[a], sd[a])
    assert sd["A1"] < 0.1
    m = compute_metrics(res, ds)
    assert m["position_rmse_after"] < 0.1


def test_preintegrated_covariance_keeps_accuracy(short_ds):
    r1 = run_eskf(short_ds, EskfOptions(init={"yaw": 0.0, "search_time_offset": False},
                                        time_offset={"prior": 0.03, "prior_sd": 0.02}))
    r5 = run_eskf(short_ds, EskfOptions(cov_every=5, init={"yaw": 0.0, "search_time_offset": False},
                                        time_offset={"prior": 0.03, "prior_sd": 0.02}))
    d = np.abs(r5.states[-1, 16:20] - r1.states[-1, 16:20])
    assert np.all(d < 0.1 * r1.sd[-1, 15:19]), d / r1.sd[-1, 15:19]
    np.testing.assert_allclose(r5.sd[-1], r1.sd[-1], rtol=0.05)


def test_write_outputs_without_ground_truth(tmp_path, short_ds):
    res = run_eskf(short_ds)
    ds = short_ds
    ds_nogt = type(ds)(imu=ds.imu, uwb=ds.uwb, anchors=ds.anchors, groundtruth=None, meta=ds.meta)
    w = write_outputs(res, ds_nogt, tmp_path)
    assert w["metrics"] is None and not (tmp_path / "metrics.yaml").exists()
    assert (tmp_path / "trajectory.csv").is_file() and len(w["residual_table"]) == len(ds.anchors)


def test_metrics_and_outputs_for_a_result_without_attitude(tmp_path, short_ds):
    """compute_metrics / write_outputs accept any EstimationResult, e.g. a position-only estimator."""
    from uwbimu.estimation import EstimationResult
    from uwbimu.metrics.filter import truth_at

    gt = short_ds.groundtruth
    t = gt["t"].to_numpy()[::20]
    p, q, v, _ = truth_at(short_ds, t)
    X = np.zeros((len(t), 20))
    X[:, :3] = p + 0.05
    X[:, 3:6] = v
    X[:, 6] = 1.0
    sd = np.full((len(t), 19), np.nan)
    sd[:, :6] = 0.05
    res = EstimationResult(t=t, states=X, sd=sd, residuals=pd.DataFrame(columns=["t", "anchor", "range", "predicted",
                           "innovation", "nis", "accepted"]), calibration={}, estimator="pointmass")
    m = compute_metrics(res, short_ds)
    assert m["position_rmse"] == pytest.approx(0.05 * np.sqrt(3), rel=1e-6)
    assert m["orientation_rmse_deg"] is None and m["nees_dof"] == 6
    assert "lever_arm_error" not in m
    assert m["nees_mean"] == pytest.approx(3.0, rel=0.05)  # position 3 x (0.05/0.05)^2, velocity exact
    w = write_outputs(res, short_ds, tmp_path)
    assert (tmp_path / "metrics.yaml").is_file() and (tmp_path / "position_error.png").is_file()
    assert w["residual_table"].empty


def test_real_data_preset_gauss_markov_biases_stay_honest():
    """examples/estimator_real.yaml: Gauss-Markov per-anchor biases.  With a constant true bias the
    bias sd cannot collapse (the model lets it drift), it stays bounded by its stationary sd, and the
    estimate covers the truth; the position estimate remains usable."""
    opts = EskfOptions.from_yaml(ROOT / "examples" / "estimator_real.yaml")
    assert opts.anchor_bias.mode == "estimate" and opts.anchor_bias.correlation_time == 2.0
    sc = builtin_scenario("calibration-flight")
    biases = {"A1": 0.08}
    sc = sc.model_copy(update={"duration": 30.0, "uwb": sc.uwb.model_copy(update={"anchor_bias": biases})})
    ds = simulate(sc)
    res = run_eskf(ds, opts)
    const = run_eskf(ds, opts.model_copy(update={"anchor_bias": opts.anchor_bias.model_copy(
        update={"correlation_time": None})}))
    est, sd = res.calibration["anchor_bias"], res.calibration["anchor_bias_sd"]
    for a in ds.anchors["anchor"]:
        assert abs(est[a] - biases.get(a, 0.0)) < 3 * sd[a], (a, est[a], sd[a])
        assert sd[a] <= 0.10 + 1e-9
        assert sd[a] > 2 * const.calibration["anchor_bias_sd"][a]  # a drifting bias is never pinned down
    m = compute_metrics(res, ds)
    assert m["position_rmse_after"] < 0.1
    assert m["lever_arm_within_3sigma"] and m["time_offset_within_3sigma"]


def test_truth_velocity_without_velocity_columns_ignores_stamp_jitter(short_ds):
    """Ground truth without vx/vy/vz (e.g. motion capture): the truth velocity is a central
    difference over +/-0.05 s, so sub-millisecond stamp jitter does not blow it up."""
    from uwbimu.metrics.filter import truth_at

    gt = short_ds.groundtruth.copy()
    rng = np.random.default_rng(3)
    ds_j = type(short_ds)(imu=short_ds.imu, uwb=short_ds.uwb, anchors=short_ds.anchors,
                          groundtruth=gt.drop(columns=["vx", "vy", "vz"]).assign(
                              t=gt["t"] + rng.uniform(-2e-4, 2e-4, len(gt))), meta=short_ds.meta)
    t = np.linspace(3.0, 17.0, 200)
    _, _, v_true, _ = truth_at(short_ds, t)
    _, _, v_fd, _ = truth_at(ds_j, t)
    assert np.sqrt(np.mean(np.sum((v_fd - v_true) ** 2, axis=1))) < 0.05
