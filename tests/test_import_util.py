"""UTIL flight CSV importer: a CSV written by the test from a simulated TDoA2 flight, and refusals."""

from __future__ import annotations

import csv
from itertools import zip_longest

import numpy as np
import pandas as pd
import pytest

from uwbimu.io.importers import util as imp
from uwbimu.io.loader import DatasetError, load_dataset
from uwbimu.sim import builtin_scenario, simulate

HEADER = ["t_tdoa", "idA", "idB", "tdoa_meas", "t_acc", "acc_x", "acc_y", "acc_z", "t_gyro", "gyro_x", "gyro_y",
          "gyro_z", "t_tof", "tof", "t_flow", "deltaX", "deltaY", "t_baro", "baro", "t_pose", "pose_x", "pose_y",
          "pose_z", "pose_qx", "pose_qy", "pose_qz", "pose_qw"]


@pytest.fixture(scope="module")
def sim():
    sc = builtin_scenario("crazyflie-tdoa2").updated(duration=4.0, time_offset=0.0)
    return simulate(sc)


def write_util(folder, ds, mutate=None):
    """A UTIL-layout tree: csv-data/const1/const1-trial1-tdoa2.csv + survey-results/anchor_const1.npz."""
    imu, td, gt = ds.imu, ds.tdoa, ds.groundtruth
    t_gyro = imu["t"].to_numpy()
    t_acc = t_gyro[::2] + 0.0005  # accelerometer on its own (slower) stamps, as on the Crazyflie
    acc_g = np.column_stack([np.interp(t_acc, t_gyro, imu[c]) for c in ("ax", "ay", "az")]) / 9.81
    gyro_dps = np.degrees(imu[["wx", "wy", "wz"]].to_numpy())
    cols = [td["t"], td["anchor_a"].astype(int), td["anchor_b"].astype(int), td["tdoa"],
            t_acc, *acc_g.T, t_gyro, *gyro_dps.T, [0.1], [1.0], [0.1], [0], [0], [0.1], [100.0],
            gt["t"], gt["px"], gt["py"], gt["pz"], gt["qx"], gt["qy"], gt["qz"], gt["qw"]]
    rows = [list(r) for r in zip_longest(*[list(c) for c in cols], fillvalue="")]
    if mutate:
        mutate(rows)
    path = folder / "csv-data" / "const1" / "const1-trial1-tdoa2.csv"
    path.parent.mkdir(parents=True)
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(HEADER)
        w.writerows(rows)
    survey = folder / "survey-results"
    survey.mkdir()
    A = ds.anchors[["x", "y", "z"]].to_numpy()
    np.savez(survey / "anchor_const1.npz", an_pos=A, an_quat=np.tile([0.0, 0.0, 0.0, 1.0], (len(A), 1)))
    return path


def test_round_trip_units_and_survey_lookup(tmp_path, sim):
    path = write_util(tmp_path, sim)
    res = imp.import_dataset(path, tmp_path / "out")
    back = load_dataset(tmp_path / "out")
    np.testing.assert_allclose(back.tdoa["tdoa"].to_numpy(), sim.tdoa["tdoa"].to_numpy(), rtol=1e-12)
    assert list(back.tdoa["anchor_a"].astype(str)) == list(sim.tdoa["anchor_a"])
    # gyro stamps kept; accelerometer interpolated back from every second sample (linear -> small error)
    inside = back.imu["t"].to_numpy()
    ref = sim.imu.set_index("t").loc[inside]
    np.testing.assert_allclose(back.imu[["wx", "wy", "wz"]].to_numpy(), ref[["wx", "wy", "wz"]].to_numpy(),
                               rtol=1e-9, atol=1e-12)
    assert np.max(np.abs(back.imu[["ax", "ay", "az"]].to_numpy() - ref[["ax", "ay", "az"]].to_numpy())) < 0.5
    assert abs(np.median(back.imu["az"]) - np.median(sim.imu["az"])) < 0.05  # g -> m/s^2
    np.testing.assert_allclose(back.groundtruth[["qw", "qx", "qy", "qz"]].to_numpy(),
                               sim.groundtruth[["qw", "qx", "qy", "qz"]].to_numpy(), atol=1e-9)
    assert back.meta.tags[0].lever_arm == imp.T_UV
    assert "qw" in back.anchors.columns and back.meta.extra["uwb_mode"] == "tdoa2"
    assert any("gyro sample" in c for c in res.changes)  # the gyro tail outside the accel span


def test_text_survey(tmp_path, sim):
    path = write_util(tmp_path, sim)
    A = sim.anchors[["x", "y", "z"]].to_numpy()
    txt = tmp_path / "s_survey.txt"
    txt.write_text("".join(f"an{i}_p,{a[0]},{a[1]},{a[2]}\n" for i, a in enumerate(A))
                   + "".join(f"an{i}_quat,0,0,0,1\n" for i in range(len(A))))
    res = imp.convert(path, anchors=txt)
    np.testing.assert_allclose(res.dataset.anchors[["x", "y", "z"]].to_numpy(), A)
    txt.write_text("an0_p,1,2\n")
    with pytest.raises(DatasetError) as e:
        imp.read_survey(txt)
    assert e.value.file == "s_survey.txt" and e.value.row == 1


def _refusal(tmp_path, sim, mutate):
    path = write_util(tmp_path, sim, mutate)
    with pytest.raises(DatasetError) as e:
        imp.convert(path)
    assert e.value.file == path.name
    return e.value


def test_refuses_non_number_naming_line_and_column(tmp_path, sim):
    def bad(rows):
        rows[9][3] = "abc"

    err = _refusal(tmp_path, sim, bad)
    assert (err.row, err.column) == (11, "tdoa_meas")


def test_refuses_gap_in_a_stream(tmp_path, sim):
    def gap(rows):
        rows[20][5] = ""

    err = _refusal(tmp_path, sim, gap)
    assert (err.row, err.column) == (22, "acc_x")


def test_refuses_unknown_anchor(tmp_path, sim):
    def unknown(rows):
        rows[4][2] = 9

    err = _refusal(tmp_path, sim, unknown)
    assert (err.row, err.column) == (6, "anchor_b")


def test_refuses_missing_survey_and_columns(tmp_path, sim):
    path = write_util(tmp_path, sim)
    (tmp_path / "survey-results" / "anchor_const1.npz").unlink()
    with pytest.raises(DatasetError, match="anchor survey"):
        imp.convert(path)
    df = pd.read_csv(path).drop(columns=["gyro_y"])
    df.to_csv(path, index=False)
    with pytest.raises(DatasetError) as e:
        imp.convert(path, anchors=tmp_path / "nowhere.npz")
    assert e.value.file == "nowhere.npz"


def test_cli(tmp_path, sim):
    from typer.testing import CliRunner

    from uwbimu.cli.main import app

    path = write_util(tmp_path, sim)
    r = CliRunner().invoke(app, ["import", "util", str(path), str(tmp_path / "o")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "o" / "tdoa.csv").is_file()
    r = CliRunner().invoke(app, ["import", "util", str(path), str(tmp_path / "o")])
    assert r.exit_code == 0, r.output  # the output rule: its own unchanged import is replaced
    (tmp_path / "o" / "notes.txt").write_text("mine")
    r = CliRunner().invoke(app, ["import", "util", str(path), str(tmp_path / "o")])
    assert r.exit_code == 4  # a folder holding a file uwbimu did not write is refused (OutputError)
