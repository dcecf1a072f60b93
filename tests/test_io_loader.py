"""load_dataset: round trips, refusals (file, row, column named) and counted repairs."""

from __future__ import annotations

import sys
from pathlib import Path

import math
import warnings

import numpy as np
import pandas as pd
import pytest

sys.path.insert(0, str(Path(__file__).parent))  # shared builders, whatever pytest's import mode

from test_io_support import edit_line, get_line, make_dataset, write_valid
from uwbimu.io.dataset import write_dataset
from uwbimu.io.loader import DatasetError, LoadRepairWarning, load_dataset


def refused(folder, **kwargs) -> DatasetError:
    with pytest.raises(DatasetError) as info:
        load_dataset(folder, **kwargs)
    return info.value


def assert_names(err: DatasetError, file: str, row, column: str, line_text: str | None = None):
    msg = str(err)
    assert err.file == file and file in msg
    assert err.row == row
    if line_text is not None:
        assert line_text in msg
    assert err.column == column and f"'{column}'" in msg


# --- round trips -------------------------------------------------------------
def test_csv_round_trip(tmp_path):
    ds = make_dataset(duration=5.0)
    write_dataset(ds, tmp_path / "d")
    back = load_dataset(tmp_path / "d")
    for name in ("imu", "uwb", "anchors", "groundtruth"):
        a, b = getattr(ds, name), getattr(back, name)
        assert list(b.columns) == list(a.columns)
        pd.testing.assert_frame_equal(a.reset_index(drop=True), b, check_dtype=False, rtol=1e-8, atol=1e-9)
    assert back.meta == ds.meta
    assert back.uwb["anchor"].map(type).eq(str).all()
    assert back.report.rows_kept == {"imu": 500, "uwb": 249, "anchors": 6, "groundtruth": 500}
    assert not back.report.repaired


def test_parquet_round_trip_is_exact(tmp_path):
    ds = make_dataset(duration=5.0)
    write_dataset(ds, tmp_path / "p", fmt="parquet")
    back = load_dataset(tmp_path / "p")
    assert back.report.files["imu"] == "imu.parquet"
    for name in ("imu", "uwb", "anchors", "groundtruth"):
        pd.testing.assert_frame_equal(getattr(ds, name).reset_index(drop=True), getattr(back, name),
                                      check_dtype=False, rtol=0, atol=0)


def test_integer_anchor_ids_in_parquet_become_text(tmp_path):
    ds = make_dataset(duration=3.0)
    ids = {a: i + 1 for i, a in enumerate(ds.anchors["anchor"])}
    ds.anchors["anchor"] = ds.anchors["anchor"].map(ids)
    ds.uwb["anchor"] = ds.uwb["anchor"].map(ids)
    write_dataset(ds, tmp_path / "p", fmt="parquet")
    back = load_dataset(tmp_path / "p")
    assert sorted(back.anchor_positions()) == ["1", "2", "3", "4", "5", "6"]
    assert set(back.uwb["anchor"]) <= set(back.anchor_positions())


def test_groundtruth_and_yaml_are_optional(tmp_path):
    d = write_valid(tmp_path / "d")
    (d / "groundtruth.csv").unlink()
    (d / "dataset.yaml").unlink()
    ds = load_dataset(d)
    assert ds.groundtruth is None and ds.meta.name == "unnamed"


def test_mixed_formats_and_yaml_path(tmp_path):
    d = write_valid(tmp_path / "d")
    ds = load_dataset(d)
    ds.imu.to_parquet(d / "imu.parquet", index=False)
    err = refused(d)
    assert "imu.csv" in str(err) and "imu.parquet" in str(err)
    (d / "imu.csv").unlink()
    assert load_dataset(d / "dataset.yaml").report.files["imu"] == "imu.parquet"


# --- refusals: each names the file, the row and the column --------------------
def test_missing_column(tmp_path):
    d = write_valid(tmp_path / "d")
    df = pd.read_csv(d / "imu.csv").drop(columns=["wz"])
    df.to_csv(d / "imu.csv", index=False)
    err = refused(d)
    assert_names(err, "imu.csv", 1, "wz", "line 1 (header)")
    assert "found 't', 'ax', 'ay', 'az', 'wx', 'wy'" in str(err)


def test_duplicate_column_in_csv_header(tmp_path):
    # pandas would rename the second 'x' to 'x.1' and ignore it: refuse instead.
    d = write_valid(tmp_path / "d")
    lines = (d / "anchors.csv").read_text().splitlines()
    (d / "anchors.csv").write_text("\n".join([lines[0] + ",x"] + [ln + ",0" for ln in lines[1:]]) + "\n")
    err = refused(d)
    assert_names(err, "anchors.csv", 1, "x", "line 1 (header)")
    assert "more than once" in str(err)


def test_non_numeric_value(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "imu.csv", 6, "ay", "abc")
    err = refused(d)
    assert_names(err, "imu.csv", 6, "ay", "line 6 (data row 5)")
    assert "'abc'" in str(err)


@pytest.mark.parametrize("value, word", [("nan", "NaN"), ("", "missing"), ("inf", "infinite")])
def test_nan_empty_and_inf(tmp_path, value, word):
    d = write_valid(tmp_path / "d")
    edit_line(d / "uwb.csv", 8, "range", value)
    err = refused(d)
    assert_names(err, "uwb.csv", 8, "range", "line 8")
    assert word in str(err)


def test_inf_anchor_coordinate(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "anchors.csv", 3, "z", "-inf")
    assert_names(refused(d), "anchors.csv", 3, "z", "line 3")


def test_timestamp_backwards_says_where(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "imu.csv", 12, "t", "0.0805")  # line 11 holds t=0.09
    err = refused(d)
    assert_names(err, "imu.csv", 12, "t", "line 12")
    msg = str(err)
    assert "backwards" in msg and "0.0805" in msg and "0.09" in msg and "line 11" in msg
    assert "sort=True" in msg


def test_timestamp_backwards_in_groundtruth(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "groundtruth.csv", 30, "t", "0.1")
    assert_names(refused(d), "groundtruth.csv", 30, "t", "line 30")


def test_duplicate_imu_stamp(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "imu.csv", 21, "t", "0.18")  # same stamp as line 20 (t = (line - 2) / 100), other values
    err = refused(d)
    assert_names(err, "imu.csv", 21, "t", "line 21")
    assert "duplicate IMU timestamp" in str(err) and "line 20" in str(err)
    # Dropping exact duplicates does not resolve a conflict.
    err = refused(d, drop_duplicate_rows=True)
    assert "different values" in str(err) and err.row == 21


def test_nonpositive_and_absurd_ranges(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "uwb.csv", 9, "range", "0")
    err = refused(d)
    assert_names(err, "uwb.csv", 9, "range", "line 9")
    assert "not positive" in str(err)
    d = write_valid(tmp_path / "e")
    edit_line(d / "uwb.csv", 4, "range", "-1.5")
    assert_names(refused(d), "uwb.csv", 4, "range", "line 4")
    d = write_valid(tmp_path / "f")
    edit_line(d / "uwb.csv", 15, "range", "1500.0")
    err = refused(d)
    assert_names(err, "uwb.csv", 15, "range", "line 15")
    assert "1 km" not in str(err) and "> 1000 m" in str(err)


def test_anchor_missing_from_anchors_csv(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "uwb.csv", 12, "anchor", "Z9")
    edit_line(d / "uwb.csv", 20, "anchor", "Y")
    edit_line(d / "uwb.csv", 30, "anchor", "Z9")
    err = refused(d)
    assert_names(err, "uwb.csv", 12, "anchor")
    msg = str(err)
    assert "'Z9' (first at line 12" in msg and "'Y' (first at line 20" in msg
    assert "anchors.csv" in msg and "A, B, C, D, E, F" in msg


def test_empty_files(tmp_path):
    # An empty file has no offending cell: the message names line 1 (where the
    # header should be) or line 2 (where data should start) and the expected columns.
    d = write_valid(tmp_path / "d")
    (d / "anchors.csv").write_text("")
    err = refused(d)
    assert_names(err, "anchors.csv", 1, "anchor", "anchors.csv, line 1")
    assert "empty" in str(err) and "'anchor', 'x', 'y', 'z'" in str(err)
    d = write_valid(tmp_path / "e")
    (d / "uwb.csv").write_text("t,anchor,range\n")
    err = refused(d)
    assert_names(err, "uwb.csv", 2, "t", "uwb.csv, line 2")
    assert "no data rows" in str(err) and "'t', 'anchor', 'range'" in str(err)
    d = write_valid(tmp_path / "f")
    (d / "groundtruth.csv").write_text("t,px,py,pz,qw,qx,qy,qz\n")
    assert_names(refused(d), "groundtruth.csv", 2, "t", "line 2")
    d = write_valid(tmp_path / "g")
    (d / "imu.csv").write_text("\n\n")  # blank lines only: no header either
    err = refused(d)
    assert err.file == "imu.csv" and err.row == 1 and "empty" in str(err) and "'wz'" in str(err)
    d = write_valid(tmp_path / "h")
    pd.DataFrame({c: pd.Series([], dtype=float) for c in ("t", "ax", "ay", "az", "wx", "wy", "wz")}).to_parquet(
        d / "imu.parquet", index=False)
    (d / "imu.csv").unlink()
    assert_names(refused(d), "imu.parquet", 1, "t", "imu.parquet, data row 1")


def test_duplicate_and_empty_anchor_ids(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "anchors.csv", 5, "anchor", "B")
    err = refused(d)
    assert_names(err, "anchors.csv", 5, "anchor", "line 5")
    assert "duplicate anchor id" in str(err) and "line 3" in str(err)
    d = write_valid(tmp_path / "e")
    edit_line(d / "uwb.csv", 6, "anchor", "  ")
    err = refused(d)
    assert_names(err, "uwb.csv", 6, "anchor", "line 6")
    assert "empty id" in str(err)


def test_malformed_csv_line(tmp_path):
    d = write_valid(tmp_path / "d")
    lines = (d / "uwb.csv").read_text().splitlines()
    lines[6] += ",9,9"
    (d / "uwb.csv").write_text("\n".join(lines) + "\n")
    err = refused(d)
    assert err.file == "uwb.csv" and "malformed CSV" in str(err) and "line 7" in str(err)


def test_missing_required_file(tmp_path):
    d = write_valid(tmp_path / "d")
    (d / "uwb.csv").unlink()
    err = refused(d)
    assert err.file == "uwb.csv" and "missing" in str(err) and "imu.csv" in str(err)
    err = refused(tmp_path / "nope")
    assert "no such dataset folder" in str(err)


def test_blank_line_inside_data(tmp_path):
    d = write_valid(tmp_path / "d")
    lines = (d / "anchors.csv").read_text().splitlines()
    (d / "anchors.csv").write_text("\n".join(lines[:3] + [""] + lines[3:]) + "\n\n")
    err = refused(d)
    assert err.file == "anchors.csv" and err.row == 4 and "blank line" in str(err)
    # Trailing blank lines alone are harmless.
    (d / "anchors.csv").write_text("\n".join(lines) + "\n\n\n")
    assert len(load_dataset(d).anchors) == 6


def test_non_unit_quaternion(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "groundtruth.csv", 5, "qw", "2.0")
    err = refused(d)
    assert_names(err, "groundtruth.csv", 5, "qw", "line 5")
    assert "norm" in str(err)


def test_parquet_location_is_a_data_row(tmp_path):
    ds = make_dataset(duration=3.0)
    ds.uwb.loc[6, "range"] = np.nan
    write_dataset(ds, tmp_path / "p", fmt="parquet")
    err = refused(tmp_path / "p")
    assert_names(err, "uwb.parquet", 7, "range", "data row 7")


# --- unit plausibility -------------------------------------------------------
def test_gyro_in_deg_s_detected_from_ground_truth(tmp_path):
    ds = make_dataset(duration=10.0, yaw_rate=0.5)  # 28.6 deg/s: plausible as rad/s on its own
    ds.imu[["wx", "wy", "wz"]] *= 180.0 / math.pi
    d = write_dataset(ds, tmp_path / "d")
    err = refused(d)
    msg = str(err)
    assert err.file == "imu.csv" and err.row == 2 and err.column == "wx"
    assert "deg/s" in msg and "pi/180" in msg and "--gyro-units deg" in msg and "lines 2-1001" in msg
    with pytest.warns(LoadRepairWarning, match="deg/s to rad/s"):
        fixed = load_dataset(d, gyro_units="deg/s")
    np.testing.assert_allclose(fixed.imu["wz"], 0.5, rtol=1e-8)


def test_gyro_in_deg_s_detected_without_ground_truth(tmp_path):
    ds = make_dataset(duration=5.0, yaw_rate=1.2)
    ds.imu[["wx", "wy", "wz"]] *= 180.0 / math.pi
    ds.groundtruth = None
    d = write_dataset(ds, tmp_path / "d")
    err = refused(d)
    assert err.file == "imu.csv" and err.column == "wx" and "2000 deg/s" in str(err)
    assert "--gyro-units deg" in str(err)


def test_accelerometer_in_g(tmp_path):
    ds = make_dataset(duration=5.0)
    ds.imu[["ax", "ay", "az"]] /= 9.81
    d = write_dataset(ds, tmp_path / "d")
    err = refused(d)
    msg = str(err)
    assert err.file == "imu.csv" and err.row == 2 and err.column == "ax" and "'ax'" in msg
    assert "in g" in msg and "multiply ax, ay, az by 9.81" in msg
    with pytest.warns(LoadRepairWarning):
        ok = load_dataset(d, accel_units="g")
    assert abs(np.median(np.linalg.norm(ok.imu_u[:, :3], axis=1)) - 9.81) < 0.5


def test_accelerometer_without_gravity(tmp_path):
    ds = make_dataset(duration=5.0)
    ds.imu["az"] -= 9.81
    ds.imu[["ax", "ay"]] *= 0.0
    err = refused(write_dataset(ds, tmp_path / "d"))
    assert err.file == "imu.csv" and "gravity" in str(err)


# --- dataset.yaml -------------------------------------------------------------
def test_unknown_key_in_yaml(tmp_path):
    d = write_valid(tmp_path / "d")
    text = (d / "dataset.yaml").read_text()
    (d / "dataset.yaml").write_text(text + "range_sigmaa: 0.1\n")
    err = refused(d)
    msg = str(err)
    assert err.file == "dataset.yaml" and err.column == "range_sigmaa"
    assert "unknown key" in msg and f"line {err.row}" in msg
    assert err.row == len(text.splitlines()) + 1


def test_invalid_nested_value_in_yaml(tmp_path):
    d = write_valid(tmp_path / "d")
    (d / "dataset.yaml").write_text("name: x\ntruth:\n  lever_arm: [0.1, 0.2]\n  time_offsett: 0.1\n")
    err = refused(d)
    msg = str(err)
    assert err.file == "dataset.yaml" and err.column == "truth.lever_arm" and err.row == 3
    assert "truth.time_offsett" in msg and "line 4" in msg


def test_broken_yaml_syntax(tmp_path):
    d = write_valid(tmp_path / "d")
    (d / "dataset.yaml").write_text("name: x\ntags: [\n")
    err = refused(d)
    assert err.file == "dataset.yaml" and "invalid YAML" in str(err) and err.row is not None


# --- repairs are counted, never silent ----------------------------------------
def test_drop_duplicate_rows_counts_them(tmp_path):
    d = write_valid(tmp_path / "d")
    for name, lines in (("uwb.csv", (5, 9, 9)), ("imu.csv", (3, 40))):
        rows = (d / name).read_text().splitlines()
        for k in sorted(lines, reverse=True):
            rows.insert(k, rows[k - 1])  # repeat line k right after itself
        (d / name).write_text("\n".join(rows) + "\n")
    err = refused(d)
    assert err.file == "imu.csv" and err.row == 4 and "drop_duplicate_rows=True" in str(err)
    with pytest.warns(LoadRepairWarning) as rec:
        ds = load_dataset(d, drop_duplicate_rows=True)
    assert ds.report.dropped == {"imu: duplicate rows": 2, "uwb: duplicate rows": 3}
    assert ds.report.rows_read["uwb"] == ds.report.rows_kept["uwb"] + 3 == 502
    assert len(ds.imu) == 1000 and "dropped 3" in str(rec[0].message)
    assert ds.imu["t"].is_monotonic_increasing


def test_sort_counts_rows_out_of_order(tmp_path):
    d = write_valid(tmp_path / "d")
    rows = (d / "uwb.csv").read_text().splitlines()
    rows[10], rows[11] = rows[11], rows[10]
    (d / "uwb.csv").write_text("\n".join(rows) + "\n")
    assert refused(d).row == 12
    with warnings.catch_warnings(record=True) as rec:
        warnings.simplefilter("always")
        ds = load_dataset(d, sort=True)
    assert ds.report.reordered == {"uwb": 1}
    assert any("1 rows were out of order" in str(w.message) for w in rec)
    assert ds.uwb["t"].is_monotonic_increasing and len(ds.uwb) == 499


def test_extra_columns_are_noted(tmp_path):
    d = write_valid(tmp_path / "d")
    df = pd.read_csv(d / "anchors.csv")
    df["label"] = "x"
    df.to_csv(d / "anchors.csv", index=False)
    ds = load_dataset(d)
    assert any("label" in n for n in ds.report.notes)
    assert list(ds.anchors.columns) == ["anchor", "x", "y", "z"]


def test_line_helper_matches_file(tmp_path):
    # Guards the test helper itself: line 2 is the first data row.
    d = write_valid(tmp_path / "d")
    assert get_line(d / "imu.csv", 1).startswith("t,")
    assert get_line(d / "imu.csv", 2).split(",")[0] in ("0", "0.0")
