"""ROS 1 / ROS 2 bag import with a custom range message, written in tmp_path with rosbags."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from uwbimu.io.importers.rosbag import RosbagImportError, convert, import_dataset, load_mapping
from uwbimu.io.loader import load_dataset

ARRAY_MSG = """std_msgs/Header header
string[] anchor_ids
float64[] ranges
uint8[] valid
"""
SCALAR_MSG = """std_msgs/Header header
uint16 anchor
float32 distance_mm
"""
T0 = 1_700_000_000.0


def _write_bag(path: Path, ros: int, n_imu: int = 60, scalar: bool = False) -> None:
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros == 1 else Stores.ROS2_HUMBLE)
    rtype = "test_msgs/msg/UwbScalar" if scalar else "test_msgs/msg/UwbRanges"
    store.register(get_types_from_msg(SCALAR_MSG if scalar else ARRAY_MSG, rtype))
    T = store.types
    Imu, Header, Time = T["sensor_msgs/msg/Imu"], T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]
    V3, Q, R = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"], T[rtype]
    Pose, Point, PoseStamped = T["geometry_msgs/msg/Pose"], T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/PoseStamped"]
    if ros == 1:
        from rosbags.rosbag1 import Writer

        writer, ser = Writer(path), store.serialize_ros1
    else:
        from rosbags.rosbag2 import Writer

        writer, ser = Writer(path, version=8), store.serialize_cdr

    def header(k, t):
        st = Time(sec=int(t), nanosec=int(round((t - int(t)) * 1e9)))
        return Header(seq=k, stamp=st, frame_id="imu") if ros == 1 else Header(stamp=st, frame_id="imu")

    with writer:
        ci = writer.add_connection("/imu/data", "sensor_msgs/msg/Imu", typestore=store)
        cr = writer.add_connection("/uwb", rtype, typestore=store)
        cg = writer.add_connection("/mocap/pose", "geometry_msgs/msg/PoseStamped", typestore=store)
        for k in range(n_imu):
            t = T0 + 0.5 + k * 0.01
            bag_ns = int((t + 0.004) * 1e9)  # received 4 ms after the stamp
            m = Imu(header=header(k, t), orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0), orientation_covariance=np.zeros(9),
                    angular_velocity=V3(x=0.01 * k, y=0.0, z=-0.02), angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=V3(x=0.1, y=0.0, z=9.81), linear_acceleration_covariance=np.zeros(9))
            writer.write(ci, bag_ns, ser(m, "sensor_msgs/msg/Imu"))
            if k % 5 == 0:
                if scalar:
                    # k == 10: a failed ranging published as 0 (dropped and counted by the importer)
                    r = R(header=header(k, t), anchor=7, distance_mm=np.float32(0.0 if k == 10 else 1500.0 + k))
                else:
                    r = R(header=header(k, t), anchor_ids=["A", "B", "C"], ranges=np.array([1.0, 2.0, 3.0]) + 0.001 * k,
                          valid=np.array([1, 1, 0], dtype=np.uint8))
                writer.write(cr, bag_ns, ser(r, rtype))
                ps = PoseStamped(header=header(k, t), pose=Pose(position=Point(x=0.01 * k, y=0.0, z=1.0),
                                                               orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0)))
                writer.write(cg, bag_ns, ser(ps, "geometry_msgs/msg/PoseStamped"))


def _mapping(tmp_path: Path, **over) -> Path:
    (tmp_path / "anchors.csv").write_text("anchor,x,y,z\nA,0,0,0\nB,4,0,1\nC,0,4,2\n7,1,1,1\n")
    m = {"imu": {"topic": "/imu/data"},
         "ranges": {"topic": "/uwb", "type": "test_msgs/msg/UwbRanges", "anchor_field": "anchor_ids",
                    "range_field": "ranges", "valid_field": "valid"},
         "groundtruth": {"topic": "/mocap/pose"},
         "anchors": "anchors.csv", "name": "bagtest", "lever_arm": [0.0, 0.0, 0.05]}
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(m.get(k), dict):
            m[k] = {**m[k], **v}
        else:
            m[k] = v
    p = tmp_path / "map.yaml"
    p.write_text(yaml.safe_dump(m))
    return p


@pytest.mark.parametrize("ros", [1, 2])
def test_import_ros1_and_ros2_bags(tmp_path, ros):
    bag = tmp_path / ("in.bag" if ros == 1 else "in_bag2")
    _write_bag(bag, ros)
    res = import_dataset(bag, tmp_path / "ds", _mapping(tmp_path))
    ds = load_dataset(tmp_path / "ds")
    assert len(ds.imu) == 60
    assert len(ds.uwb) == 12 * 2  # 12 messages x (A, B); C is marked invalid
    assert set(ds.uwb["anchor"]) == {"A", "B"}
    assert any("dropped 12" in c for c in res.changes)
    t0 = ds.meta.extra["time_origin_s"]
    assert t0 == T0
    np.testing.assert_allclose(ds.imu["t"].to_numpy()[:3], [0.5, 0.51, 0.52], atol=1e-6)  # header stamps
    np.testing.assert_allclose(ds.imu["wx"].to_numpy()[:3], [0.0, 0.01, 0.02])
    b = ds.uwb[ds.uwb.anchor == "B"]["range"].to_numpy()
    np.testing.assert_allclose(b[:2], [2.0, 2.005])
    assert len(ds.groundtruth) == 12 and ds.groundtruth["px"].iloc[1] == pytest.approx(0.05)
    assert ds.meta.tags[0].lever_arm == [0.0, 0.0, 0.05]


def test_scalar_fields_bag_time_and_scale(tmp_path):
    bag = tmp_path / "s.bag"
    _write_bag(bag, 1, scalar=True)
    mp = _mapping(tmp_path, ranges={"type": "test_msgs/msg/UwbScalar", "anchor_field": "anchor",
                                    "range_field": "distance_mm", "valid_field": None, "range_scale": 0.001,
                                    "time": "bag"}, groundtruth=None)
    res = convert(bag, mp)
    ds = res.dataset
    assert any("dropped 1 non-positive" in c for c in res.changes)
    assert len(ds.uwb) == 11
    assert list(ds.uwb["anchor"].unique()) == ["7"]
    np.testing.assert_allclose(ds.uwb["range"].to_numpy()[:2], [1.5, 1.505], rtol=1e-6)
    np.testing.assert_allclose(ds.uwb["t"].to_numpy()[0] - ds.imu["t"].to_numpy()[0], 0.004, atol=1e-6)


def test_clear_errors_list_topics_and_fields(tmp_path):
    bag = tmp_path / "in.bag"
    _write_bag(bag, 1, n_imu=10)
    with pytest.raises(RosbagImportError, match=r"'/uwb_missing' is not in the bag; topics in the bag: .*/imu/data"):
        convert(bag, _mapping(tmp_path, ranges={"topic": "/uwb_missing"}))
    with pytest.raises(RosbagImportError, match=r"field 'rangez' not found.*'anchor_ids', 'ranges', 'valid'"):
        convert(bag, _mapping(tmp_path, ranges={"range_field": "rangez"}))
    with pytest.raises(RosbagImportError, match="has type sensor_msgs/msg/Imu, expected|has type .*mapping says"):
        convert(bag, _mapping(tmp_path, ranges={"type": "other_msgs/msg/Range"}))
    with pytest.raises(RosbagImportError, match="imu topic '/uwb' has type"):
        convert(bag, _mapping(tmp_path, imu={"topic": "/uwb"}))
    with pytest.raises(RosbagImportError, match=r"(?s)invalid rosbag mapping.*line \d+, field .ranges.range_field."):
        bad = tmp_path / "bad.yaml"
        bad.write_text(yaml.safe_dump({"imu": {"topic": "/imu/data"}, "ranges": {"topic": "/uwb", "anchor_field": "a"},
                                       "anchors": "anchors.csv"}))
        load_mapping(bad)
    (tmp_path / "anchors.csv").write_text("anchor,x,y,z\nA,0,0,0\n")
    mp = tmp_path / "map2.yaml"
    mp.write_text(yaml.safe_dump({"imu": {"topic": "/imu/data"}, "anchors": "anchors.csv",
                                  "ranges": {"topic": "/uwb", "anchor_field": "anchor_ids", "range_field": "ranges"}}))
    with pytest.raises(RosbagImportError, match=r"anchor id\(s\) \['B', 'C'\]"):
        convert(bag, mp)


def test_cli_rosbag_refuses_overwrite(tmp_path):
    from uwbimu.cli.main import app

    bag = tmp_path / "in.bag"
    _write_bag(bag, 1, n_imu=10)
    mp = _mapping(tmp_path)
    dst = tmp_path / "ds"
    r = CliRunner().invoke(app, ["import", "rosbag", str(bag), str(dst), "--topics", str(mp)])
    assert r.exit_code == 0, r.output
    r = CliRunner().invoke(app, ["import", "rosbag", str(bag), str(dst), "--topics", str(mp)])
    assert r.exit_code == 0, r.output  # the output rule: its own unchanged import is replaced
    (dst / "imu.csv").write_text((dst / "imu.csv").read_text() + "\n")  # edited since: refused
    r = CliRunner().invoke(app, ["import", "rosbag", str(bag), str(dst), "--topics", str(mp)])
    assert r.exit_code == 4 and "imu.csv" in r.output
    r = CliRunner().invoke(app, ["import", "rosbag", str(bag), str(dst), "--topics", str(mp), "--force"])
    assert r.exit_code == 0, r.output
