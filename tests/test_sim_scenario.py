"""Scenario models, YAML loading with clear errors, built-ins, and the ``uwbimu simulate`` CLI."""

from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.io.dataset import DatasetMeta
from uwbimu.sim import Scenario, ScenarioError, builtin_scenario, list_scenarios, load_scenario, simulate
from uwbimu.sim import write_trajectory_file

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "scenarios" / "calibration_flight.yaml"
REQUIRED_BUILTINS = {
    "calibration-flight", "excited-90s", "hover", "circle", "figure8", "lissajous",
    "random", "translation", "rotation", "nlos", "outage",
}  # fmt: skip


def test_builtins_listed_and_valid():
    names = list_scenarios()
    assert REQUIRED_BUILTINS <= set(names)
    assert all(isinstance(d, str) and d for d in names.values())
    with pytest.raises(KeyError, match="unknown built-in scenario 'nope'"):
        builtin_scenario("nope")


def test_calibration_flight_is_the_documented_demo_default():
    sc = builtin_scenario("calibration-flight")
    assert sc.duration == 60.0 and sc.trajectory.type == "lissajous"
    assert sc.imu.noise == "bmi088" and sc.imu.rate_hz == 200.0
    assert sc.uwb.rate_hz == 50.0 and sc.uwb.schedule == "round_robin" and sc.uwb.sigma == 0.05
    assert sc.lever_arm == (0.12, -0.08, 0.14) and sc.time_offset == 0.03
    assert len(sc.anchor_ids()) == 8
    assert builtin_scenario("excited-90s").duration == 90.0
    assert builtin_scenario("outage").uwb.outages == [(20.0, 30.0, "A2")]


@pytest.mark.parametrize("name", sorted(list_scenarios()))
def test_yaml_round_trip_and_meta_record(name, tmp_path):
    sc = builtin_scenario(name)
    path = tmp_path / f"{name}.yaml"
    path.write_text(sc.to_yaml())
    assert load_scenario(path) == sc
    # the scenario recorded in dataset.yaml reproduces the run
    assert Scenario.model_validate(yaml.safe_load(sc.to_yaml())) == sc


def test_example_yaml_loads_and_equals_the_builtin_flight():
    sc = load_scenario(EXAMPLE)
    ref = builtin_scenario("calibration-flight")
    assert sc.model_dump(exclude={"name", "description"}) == ref.model_dump(exclude={"name", "description"})


@pytest.mark.parametrize("path", sorted(EXAMPLE.parent.glob("*.yaml")), ids=lambda p: p.stem)
def test_every_example_scenario_simulates_into_a_valid_dataset(path, tmp_path):
    from uwbimu.io.dataset import write_dataset
    from uwbimu.io.loader import load_dataset

    sc = load_scenario(path)
    ds = simulate(sc.updated(duration=20.0))  # shortened: the example's content, not its length, is tested
    back = load_dataset(write_dataset(ds, tmp_path / "d"))
    assert len(back.uwb) == len(ds.uwb) > 0 and back.meta.truth.time_offset == sc.time_offset


def test_harsh_example_exercises_every_ranging_imperfection():
    sc = load_scenario(EXAMPLE.parent / "harsh_two_tags.yaml")
    ds = simulate(sc)
    counts = ds.meta.extra["uwb_counts"]
    for k in ("nlos", "dropped_outage", "dropped_max_range", "dropped_dropout"):
        assert counts[k] > 0, k
    assert set(ds.uwb["tag"]) == {"front", "back"} and ds.meta.imu_rate_hz == 400.0
    assert ds.meta.truth.anchor_bias["A3"] == 0.15
    # the outage of A5 from 40 to 45 s leaves no A5 range in that window
    a5 = ds.uwb[(ds.uwb["anchor"] == "A5")]["t"]
    assert not ((a5 > 40.01) & (a5 < 44.99)).any()


def test_updated_merges_and_validates():
    sc = builtin_scenario("calibration-flight")
    s2 = sc.updated(time_offset=-0.02, uwb={"sigma": 0.1}, trajectory={"type": "circle", "radius": 1.5})
    assert s2.uwb.sigma == 0.1 and s2.uwb.rate_hz == 50.0 and s2.trajectory.radius == 1.5
    s3 = sc.updated(trajectory={"ramp": 0.5})
    assert s3.trajectory.type == "lissajous" and s3.trajectory.ramp == 0.5 and s3.trajectory.amplitude == sc.trajectory.amplitude
    with pytest.raises(ScenarioError, match="field 'uwb.sigma'"):
        sc.updated(uwb={"sigma": -1.0})


def write_yaml(tmp_path, data, name="s.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize(
    "data, field",
    [
        ({"duration": 10, "uwb": {"sigma": -0.1}}, "uwb.sigma"),
        ({"duration": 10, "uwb": {"sigmaa": 0.1}}, "uwb.sigmaa"),
        ({"duration": 10, "imu": {"noise": "bmi999"}}, "imu.noise"),
        ({"duration": 10, "trajectory": {"type": "spiral"}}, "trajectory"),
        ({"duration": 10, "trajectory": {"type": "circle", "radius": 0}}, "trajectory.circle.radius"),
        ({"duration": 10, "lever_arm": [1, 2]}, "lever_arm"),
        ({"duration": -1}, "duration"),
        ({"trajectory": {"type": "hover"}}, "duration is required"),
        ({"duration": 10, "anchors": "room9"}, "anchors"),
        ({"duration": 10, "uwb": {"anchor_bias": {"A9": 0.1}}}, "unknown anchor 'A9'"),
        ({"duration": 10, "uwb": {"outages": [[5, 4, None]]}}, "uwb.outages"),
        ({"duration": 10, "anchors": [{"id": 1, "position": [0, 0, 0]}, {"id": 1, "position": [1, 0, 0]}]}, "duplicate anchor ids"),
        ({"duration": 10, "lever_arm": [0.1, 0, 0], "tags": [{"name": "a", "lever_arm": [0, 0, 0.1]}]}, "either lever_arm"),
    ],
)
def test_load_errors_name_file_and_field(tmp_path, data, field):
    path = write_yaml(tmp_path, data)
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    msg = str(err.value)
    assert str(path) in msg and field in msg, msg


def test_load_errors_for_missing_and_malformed_files(tmp_path):
    with pytest.raises(ScenarioError, match="not found"):
        load_scenario(tmp_path / "none.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("duration: [1,\n")
    with pytest.raises(ScenarioError, match="not valid YAML"):
        load_scenario(bad)
    lst = tmp_path / "list.yaml"
    lst.write_text("- 1\n- 2\n")
    with pytest.raises(ScenarioError, match="expected a mapping"):
        load_scenario(lst)


def test_numeric_anchor_ids_become_text(tmp_path):
    data = {
        "duration": 5,
        "anchors": [{"id": 1, "position": [0, 0, 0.3]}, {"id": 2, "position": [9, 0, 2.7]}, {"id": 3, "position": [0, 8, 1.0]}],
        "uwb": {"anchor_bias": {2: 0.1}, "outages": [[1, 2, 3]]},
    }
    sc = load_scenario(write_yaml(tmp_path, data))
    assert sc.anchor_ids() == ["1", "2", "3"] and sc.uwb.anchor_bias == {"2": 0.1}
    ds = simulate(sc)
    assert set(ds.uwb["anchor"]) == {"1", "2", "3"} and ds.meta.truth.anchor_bias["2"] == 0.1


def test_explicit_noise_densities_room4_and_all_schedule(tmp_path):
    noise = {"gyro_noise_density": 1e-3, "accel_noise_density": 2e-2, "gyro_bias_rw": 0.0, "accel_bias_rw": 0.0}
    data = {"duration": 5, "imu": {"noise": noise}, "anchors": "room4", "uwb": {"schedule": "all", "rate_hz": 10}}
    sc = load_scenario(write_yaml(tmp_path, data))
    ds = simulate(sc)
    assert ds.meta.imu_noise.accel_noise_density == 2e-2 and ds.meta.imu_noise.accel_bias_sigma0 == 0.0
    assert len(ds.anchors) == 4 and len(ds.uwb) == 4 * 51
    assert (ds.uwb.groupby("t").size() == 4).all()


def test_trajectory_file_path_is_relative_to_the_scenario(tmp_path):
    sub = tmp_path / "flights"
    sub.mkdir()
    t = np.arange(0, 12.5, 0.5)
    write_trajectory_file(sub / "wp.csv", t, np.column_stack([5 + np.sin(0.3 * t), 4 + 0 * t, 1.5 + 0 * t]), yaw=0.1 * t)
    path = write_yaml(sub, {"trajectory": {"type": "file", "path": "wp.csv"}}, "fly.yaml")
    sc = load_scenario(path)
    assert Path(sc.trajectory.path) == (sub / "wp.csv").resolve()
    assert sc.name == "fly" and sc.duration is None
    ds = simulate(sc)
    assert ds.meta.extra["duration"] == pytest.approx(12.0) and len(ds.imu) == 2401
    # a missing file is reported with its path
    broken = write_yaml(sub, {"trajectory": {"type": "file", "path": "nope.csv"}}, "broken.yaml")
    with pytest.raises(ValueError, match="nope.csv"):
        simulate(load_scenario(broken))


# --- CLI ---------------------------------------------------------------------------------

runner = CliRunner()


def test_cli_list():
    res = runner.invoke(app, ["simulate", "--list"])
    assert res.exit_code == 0, res.output
    for name in REQUIRED_BUILTINS:
        assert name in res.output


def test_cli_builtin_to_folder_and_refuses_overwrite(tmp_path):
    out = tmp_path / "ds"
    res = runner.invoke(app, ["simulate", "hover", "--out", str(out)])
    assert res.exit_code == 0, res.output
    for f in ("imu.csv", "uwb.csv", "anchors.csv", "groundtruth.csv", "dataset.yaml"):
        assert (out / f).is_file(), f
    meta = DatasetMeta.model_validate(yaml.safe_load((out / "dataset.yaml").read_text()))
    assert meta.truth.time_offset == 0.03 and meta.name == "hover"
    header = (out / "imu.csv").read_text().splitlines()[0]
    assert header == "t,ax,ay,az,wx,wy,wz"
    assert (out / "groundtruth.csv").read_text().startswith("t,px,py,pz,qw,qx,qy,qz,vx,vy,vz")

    # the output rule: its own unchanged dataset may be replaced; a user's file in it needs --force
    (out / "notes.txt").write_text("mine")
    before = (out / "imu.csv").read_text()
    res = runner.invoke(app, ["simulate", "circle", "--out", str(out)])
    assert res.exit_code == 4 and "refusing" in res.output
    assert (out / "imu.csv").read_text() == before
    res = runner.invoke(app, ["simulate", "circle", "--out", str(out), "--force"])
    assert res.exit_code == 0, res.output
    assert yaml.safe_load((out / "dataset.yaml").read_text())["name"] == "circle"


def test_cli_yaml_file_and_errors(tmp_path):
    path = write_yaml(tmp_path, {"duration": 5, "trajectory": {"type": "rotation"}, "tags": [
        {"name": "a", "lever_arm": [0.1, 0, 0]}, {"name": "b", "lever_arm": [-0.1, 0, 0]}]}, "two.yaml")
    out = tmp_path / "two"
    res = runner.invoke(app, ["simulate", str(path), "--out", str(out)])
    assert res.exit_code == 0, res.output
    assert (out / "uwb.csv").read_text().splitlines()[0] == "t,anchor,range,tag"

    bad = write_yaml(tmp_path, {"duration": 5, "uwb": {"sigma": "x"}}, "bad.yaml")
    res = runner.invoke(app, ["simulate", str(bad), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "bad.yaml" in res.output and "uwb.sigma" in res.output
    assert "Traceback" not in res.output
    res = runner.invoke(app, ["simulate", "not-a-scenario", "--out", str(tmp_path / "o")])
    assert res.exit_code == 2 and "neither a scenario file nor a built-in" in res.output
    res = runner.invoke(app, ["simulate", "hover"])
    assert res.exit_code == 2
