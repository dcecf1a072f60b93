"""Dataset extensions: tdoa.csv, anchor_ranges.csv, anchor antenna orientation, anchor_frame_up."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import yaml

from uwbimu.errors import InputError, UwbimuError
from uwbimu.io.dataset import Dataset, DatasetMeta, write_dataset
from uwbimu.io.loader import DatasetError, load_dataset

ANCHORS = pd.DataFrame({"anchor": ["A", "B", "C", "D"], "x": [0.0, 4.0, 4.0, 0.0],
                        "y": [0.0, 0.0, 3.0, 3.0], "z": [2.0, 2.5, 2.0, 2.5]})


def _dataset(tmp_path, with_uwb=True, **tables):
    t = np.arange(0, 2, 0.01)
    imu = pd.DataFrame({"t": t, "ax": 0.0, "ay": 0.0, "az": 9.81, "wx": 0.0, "wy": 0.0, "wz": 0.0})
    p = np.array([2.0, 1.5, 1.0])
    pos = ANCHORS[["x", "y", "z"]].to_numpy()
    d = np.linalg.norm(pos - p, axis=1)
    tu = np.arange(0, 2, 0.1)
    uwb = pd.DataFrame({"t": np.repeat(tu, 4), "anchor": list("ABCD") * len(tu), "range": np.tile(d, len(tu))})
    tdoa = pd.DataFrame({"t": tu, "anchor_a": "A", "anchor_b": "B", "tdoa": d[1] - d[0]})
    ds = Dataset(imu=imu, uwb=uwb if with_uwb else uwb.iloc[:0], anchors=ANCHORS.copy(), tdoa=tdoa,
                 anchor_ranges=pd.DataFrame({"anchor_a": ["A"], "anchor_b": ["B"], "range": [4.05]}),
                 meta=DatasetMeta(anchor_frame_up="-z"))
    for k, v in tables.items():
        setattr(ds, k, v)
    return write_dataset(ds, tmp_path / "ds")


def test_round_trip_tdoa_only(tmp_path):
    folder = _dataset(tmp_path, with_uwb=False)
    assert not (folder / "uwb.csv").exists() and (folder / "tdoa.csv").exists()
    ds = load_dataset(folder)
    assert len(ds.uwb) == 0 and list(ds.uwb.columns)[:3] == ["t", "anchor", "range"]
    assert len(ds.tdoa) == 20 and set(ds.tdoa.columns) == {"t", "anchor_a", "anchor_b", "tdoa"}
    assert ds.anchor_ranges["range"].iloc[0] == pytest.approx(4.05)
    assert ds.meta.anchor_frame_up == "-z" == ds.anchor_frame_up


def test_anchor_orientation_round_trip(tmp_path):
    anchors = ANCHORS.assign(qw=1.0, qx=0.0, qy=0.0, qz=0.0)
    ds = load_dataset(_dataset(tmp_path, anchors=anchors))
    assert list(ds.anchors.columns) == ["anchor", "x", "y", "z", "qw", "qx", "qy", "qz"]


@pytest.mark.parametrize("edit, column", [
    (lambda df: df.assign(anchor_b=["Z"] + list(df.anchor_b[1:])), "anchor_b"),
    (lambda df: df.assign(anchor_b=["A"] + list(df.anchor_b[1:])), "anchor_b"),
    (lambda df: df.assign(tdoa=[np.nan] + list(df.tdoa[1:])), "tdoa"),
    (lambda df: df.assign(tdoa=[7.0] + list(df.tdoa[1:])), "tdoa"),  # separation A-B is 4.03 m
])
def test_tdoa_refusals_name_file_line_column(tmp_path, edit, column):
    folder = _dataset(tmp_path)
    df = pd.read_csv(folder / "tdoa.csv", dtype={"anchor_a": str, "anchor_b": str})
    edit(df).to_csv(folder / "tdoa.csv", index=False)
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert exc.value.file == "tdoa.csv" and exc.value.row == 2 and exc.value.column == column
    assert isinstance(exc.value, InputError) and exc.value.exit_code == 1


def test_bad_anchor_quaternion_and_partial_columns(tmp_path):
    folder = _dataset(tmp_path, anchors=ANCHORS.assign(qw=[1.0, 1.0, 2.0, 1.0], qx=0.0, qy=0.0, qz=0.0))
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert (exc.value.file, exc.value.row, exc.value.column) == ("anchors.csv", 4, "qw")
    ANCHORS.assign(qw=1.0).to_csv(folder / "anchors.csv", index=False)
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert exc.value.column == "qx"


def test_anchor_ranges_refuse_unknown_anchor(tmp_path):
    folder = _dataset(tmp_path)
    pd.DataFrame({"anchor_a": ["A"], "anchor_b": ["Q"], "range": [3.0]}).to_csv(folder / "anchor_ranges.csv",
                                                                                 index=False)
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert (exc.value.file, exc.value.column) == ("anchor_ranges.csv", "anchor_b")


def test_uwb_required_without_tdoa(tmp_path):
    folder = _dataset(tmp_path, with_uwb=False)
    (folder / "tdoa.csv").unlink()
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert exc.value.file == "uwb.csv"


def test_legacy_extra_anchor_frame_up_still_read(tmp_path):
    folder = _dataset(tmp_path)
    (folder / "dataset.yaml").write_text(yaml.safe_dump({"name": "x", "extra": {"anchor_frame_up": "-z"}}))
    assert load_dataset(folder).meta.anchor_frame_up == "-z"
    (folder / "dataset.yaml").write_text(yaml.safe_dump({"anchor_frame_up": "+z",
                                                         "extra": {"anchor_frame_up": "-z"}}))
    with pytest.raises(DatasetError):
        load_dataset(folder)


def test_error_hierarchy_keeps_old_names():
    from uwbimu.errors import CheckFlagged, EstimationError, OutputError, UsageError

    assert issubclass(DatasetError, ValueError) and issubclass(DatasetError, UwbimuError)
    codes = [c.exit_code for c in (InputError, UsageError, CheckFlagged, OutputError, EstimationError)]
    assert codes == [1, 2, 3, 4, 5]
