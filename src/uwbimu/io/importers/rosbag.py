"""Importer for ROS 1 (``.bag``) and ROS 2 (folder with ``metadata.yaml``) bags.

Bags are read with ``rosbags.highlevel.AnyReader`` (pure Python, no ROS
installation).  What to read is described by a mapping YAML
(:class:`RosbagMapping`)::

    imu:
      topic: /imu/data              # sensor_msgs/msg/Imu
      time: header                  # header (header.stamp) | bag (receive time)
    ranges:
      topic: /uwb/ranges
      type: my_msgs/msg/UwbRange    # optional: checked against the bag
      anchor_field: anchor_id       # dotted path; may be an array (one message, many ranges)
      range_field: range            # dotted path, same length as anchor_field when arrays
      time: header                  # header | bag | dotted path to a stamp (Time) or seconds
      valid_field: null             # optional dotted path: keep entries where it is true / non-zero
      range_scale: 1.0              # multiply ranges by this (0.001 for mm)
    groundtruth:                    # optional: geometry_msgs PoseStamped / TransformStamped,
      topic: /vicon/body            #   nav_msgs/Odometry (pose of the IMU frame)
      time: header
    anchors: anchors.csv            # anchor, x, y, z (m); relative to this YAML file
    msg_definitions:                # optional: .msg files of custom types for ROS 2 bags
      my_msgs/msg/UwbRange: UwbRange.msg      #   that do not embed their definitions
    name: my-recording
    lever_arm: [0.0, 0.0, 0.0]      # optional nominal lever arm -> tags[0].lever_arm
    range_sigma: 0.1                # optional

Times become seconds relative to a common origin (the whole second before
the first IMU or range stamp, stored in ``dataset.yaml`` ``extra``).
Errors name the topic / field and list what is available.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any, Literal, Optional, Union

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field

from uwbimu.io.dataset import ANCHOR_COLUMNS, ANCHOR_QUAT_COLUMNS, GT_COLUMNS, IMU_COLUMNS, Dataset, DatasetMeta, TagMeta
from uwbimu.io.importers import ImportResult, source_text, write_import
from uwbimu.io.importers.anchors import read_anchors_csv
from uwbimu.io.loader import DatasetError

__all__ = ["RosbagMapping", "RosbagImportError", "load_mapping", "convert", "import_dataset"]

IMU_TYPE = "sensor_msgs/msg/Imu"
GT_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped", "nav_msgs/msg/Odometry",
            "geometry_msgs/msg/PoseWithCovarianceStamped")


class RosbagImportError(DatasetError):
    """A bag or mapping that does not match (missing topic, field, type...)."""


class ImuTopic(BaseModel):
    model_config = ConfigDict(extra="forbid")
    topic: str
    time: Literal["header", "bag"] = "header"


class RangeTopic(BaseModel):
    model_config = ConfigDict(extra="forbid")
    topic: str
    type: Optional[str] = None
    anchor_field: str
    range_field: str
    time: str = Field(default="header", description="header | bag | dotted field path")
    valid_field: Optional[str] = None
    range_scale: float = Field(default=1.0, gt=0)


class GroundTruthTopic(BaseModel):
    model_config = ConfigDict(extra="forbid")
    topic: str
    time: Literal["header", "bag"] = "header"


class RosbagMapping(BaseModel):
    """Which topics and fields of a bag make a dataset (see module docstring)."""

    model_config = ConfigDict(extra="forbid")
    imu: ImuTopic
    ranges: RangeTopic
    groundtruth: Optional[GroundTruthTopic] = None
    anchors: str
    msg_definitions: dict[str, str] = Field(default_factory=dict)
    name: Optional[str] = None
    lever_arm: Optional[list[float]] = Field(default=None, min_length=3, max_length=3)
    range_sigma: Optional[float] = Field(default=None, gt=0)
    base_dir: Optional[str] = Field(default=None, description="set by load_mapping: folder of the YAML file")

    def resolve(self, p: str) -> Path:
        path = Path(p)
        if not path.is_absolute() and self.base_dir:
            path = Path(self.base_dir) / path
        return path


def load_mapping(path: Union[str, os.PathLike]) -> RosbagMapping:
    """Read and validate a mapping YAML; errors name the file and the key."""
    from uwbimu.io.yamlconfig import load_yaml_model

    path = Path(path)

    def error(message: str) -> RosbagImportError:
        return RosbagImportError(message, file=path.name)

    def prepare(obj: dict) -> dict:
        obj.setdefault("base_dir", str(path.parent))
        return obj

    return load_yaml_model(path, RosbagMapping, what="rosbag mapping", error=error, prepare=prepare)


# --------------------------------------------------------------------------- field access
def _field_names(obj: Any) -> list[str]:
    if dataclasses.is_dataclass(obj):
        return [f.name for f in dataclasses.fields(obj) if not f.name.startswith("__")]
    return []


def _get_field(msg: Any, path: str, topic: str, msgtype: str) -> Any:
    """Follow a dotted path into a message; a clear error lists the fields available."""
    cur = msg
    done = []
    for part in path.split("."):
        if not dataclasses.is_dataclass(cur) or not hasattr(cur, part):
            avail = _field_names(cur)
            where = ".".join(done) or "(message)"
            raise RosbagImportError(
                f"topic {topic} ({msgtype}): field '{path}' not found: '{part}' is not a field of {where}; "
                f"available there: {avail if avail else '(not a message: ' + type(cur).__name__ + ')'}",
                column=path,
            )
        cur = getattr(cur, part)
        done.append(part)
    return cur


def _stamp_seconds(x: Any, what: str) -> float:
    """A Time message (sec/nanosec) or a number (seconds) as float seconds."""
    if hasattr(x, "sec") and hasattr(x, "nanosec"):
        return float(x.sec) + 1e-9 * float(x.nanosec)
    if isinstance(x, (int, float, np.integer, np.floating)):
        return float(x)
    raise RosbagImportError(f"{what} is neither a Time (sec, nanosec) nor a number: {type(x).__name__}")


def _as_list(x: Any) -> Optional[list]:
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (list, tuple)):
        return list(x)
    return None


def _topic_error(topic: str, what: str, conns_by_topic: dict) -> RosbagImportError:
    avail = ", ".join(f"{t} ({ty})" for t, ty in sorted(conns_by_topic.items())) or "(none)"
    return RosbagImportError(f"{what} topic '{topic}' is not in the bag; topics in the bag: {avail}", column=topic)


# --------------------------------------------------------------------------- conversion
def _typestore_with(mapping: RosbagMapping):
    from uwbimu.optional import require

    require("rosbags", "ros", "ROS bag import")
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.LATEST)
    add: dict = {}
    for name, file in mapping.msg_definitions.items():
        p = mapping.resolve(file)
        if not p.is_file():
            raise RosbagImportError(f"msg_definitions: file for {name} not found: {p}", file=str(p), column=name)
        add.update(get_types_from_msg(source_text(p, what="message definition"), name))
    if add:
        store.register(add)
    return store


def _read_anchors(path: Path) -> pd.DataFrame:
    """The mapping's anchors file (``anchor, x, y, z`` [+ ``qw, qx, qy, qz``]) through the shared reader."""
    df = read_anchors_csv(path)
    quat = [c for c in ANCHOR_QUAT_COLUMNS if c in df.columns]
    return df[ANCHOR_COLUMNS + (quat if len(quat) == 4 else [])]


def convert(bag: Union[str, os.PathLike], mapping: Union[RosbagMapping, str, os.PathLike]) -> ImportResult:
    """Read ``bag`` (ROS 1 file or ROS 2 folder) as described by ``mapping``.

    Returns
    -------
    ImportResult (dataset not yet written).

    Raises
    ------
    RosbagImportError
        Missing topic (lists the bag's topics), missing field (lists the
        message's fields), wrong message type, no data, unknown anchors.
    """
    from uwbimu.optional import require

    require("rosbags", "ros", "ROS bag import")
    from rosbags.highlevel import AnyReader

    if not isinstance(mapping, RosbagMapping):
        mapping = load_mapping(mapping)
    bag = Path(bag)
    if not bag.exists():
        raise RosbagImportError(f"{bag}: bag not found", file=str(bag))
    anchors = _read_anchors(mapping.resolve(mapping.anchors))
    store = _typestore_with(mapping)
    changes: list[str] = []
    imu_rows: list[tuple] = []
    rng_rows: list[tuple] = []
    gt_rows: list[tuple] = []
    n_invalid = 0
    reader = AnyReader([bag], default_typestore=store)
    try:
        reader.open()
    except Exception as exc:  # rosbags raises its own reader errors for non-bags
        raise RosbagImportError(f"{bag}: cannot open as a ROS 1 or ROS 2 bag: {exc}", file=str(bag)) from None
    try:
        by_topic = {c.topic: c.msgtype for c in reader.connections}
        if mapping.imu.topic not in by_topic:
            raise _topic_error(mapping.imu.topic, "imu", by_topic)
        if mapping.ranges.topic not in by_topic:
            raise _topic_error(mapping.ranges.topic, "ranges", by_topic)
        if by_topic[mapping.imu.topic] != IMU_TYPE:
            raise RosbagImportError(f"imu topic '{mapping.imu.topic}' has type {by_topic[mapping.imu.topic]}, "
                                    f"expected {IMU_TYPE}", column=mapping.imu.topic)
        rtype = by_topic[mapping.ranges.topic]
        if mapping.ranges.type is not None and rtype != mapping.ranges.type:
            raise RosbagImportError(f"ranges topic '{mapping.ranges.topic}' has type {rtype}, mapping says "
                                    f"{mapping.ranges.type}", column=mapping.ranges.topic)
        gt_topic = mapping.groundtruth.topic if mapping.groundtruth else None
        if gt_topic is not None:
            if gt_topic not in by_topic:
                raise _topic_error(gt_topic, "groundtruth", by_topic)
            if by_topic[gt_topic] not in GT_TYPES:
                raise RosbagImportError(f"groundtruth topic '{gt_topic}' has type {by_topic[gt_topic]}; supported: "
                                        f"{', '.join(GT_TYPES)}", column=gt_topic)
        wanted = [c for c in reader.connections if c.topic in {mapping.imu.topic, mapping.ranges.topic, gt_topic}]
        for conn, t_bag_ns, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, conn.msgtype)
            t_bag = t_bag_ns * 1e-9
            if conn.topic == mapping.imu.topic:
                t = _stamp_seconds(msg.header.stamp, "imu header.stamp") if mapping.imu.time == "header" else t_bag
                a, w = msg.linear_acceleration, msg.angular_velocity
                imu_rows.append((t, a.x, a.y, a.z, w.x, w.y, w.z))
            elif conn.topic == mapping.ranges.topic:
                rc = mapping.ranges
                if rc.time == "bag":
                    t = t_bag
                else:
                    tf = "header.stamp" if rc.time == "header" else rc.time
                    t = _stamp_seconds(_get_field(msg, tf, conn.topic, conn.msgtype), f"{conn.topic} {tf}")
                ids = _get_field(msg, rc.anchor_field, conn.topic, conn.msgtype)
                rs = _get_field(msg, rc.range_field, conn.topic, conn.msgtype)
                ok = _get_field(msg, rc.valid_field, conn.topic, conn.msgtype) if rc.valid_field else True
                ids_l, rs_l, ok_l = _as_list(ids), _as_list(rs), _as_list(ok)
                if ids_l is None and rs_l is None:
                    ids_l, rs_l, ok_l = [ids], [rs], [ok] if ok_l is None else ok_l
                if ids_l is None or rs_l is None or len(ids_l) != len(rs_l):
                    raise RosbagImportError(
                        f"topic {conn.topic}: '{rc.anchor_field}' and '{rc.range_field}' must both be scalars or "
                        f"arrays of equal length (got {type(ids).__name__} and {type(rs).__name__})",
                        column=rc.range_field)
                if ok_l is None:
                    ok_l = [ok] * len(ids_l)
                if len(ok_l) != len(ids_l):
                    raise RosbagImportError(f"topic {conn.topic}: '{rc.valid_field}' length {len(ok_l)} differs from "
                                            f"'{rc.anchor_field}' length {len(ids_l)}", column=rc.valid_field)
                for a_id, r, v in zip(ids_l, rs_l, ok_l):
                    if not bool(v):
                        n_invalid += 1
                        continue
                    rng_rows.append((t, str(a_id).strip(), float(r) * rc.range_scale))
            else:
                t = _stamp_seconds(msg.header.stamp, "groundtruth header.stamp") if mapping.groundtruth.time == "header" else t_bag
                if conn.msgtype.endswith("TransformStamped"):
                    p, q = msg.transform.translation, msg.transform.rotation
                elif conn.msgtype.endswith("PoseStamped"):
                    p, q = msg.pose.position, msg.pose.orientation
                else:  # Odometry, PoseWithCovarianceStamped
                    p, q = msg.pose.pose.position, msg.pose.pose.orientation
                gt_rows.append((t, p.x, p.y, p.z, q.w, q.x, q.y, q.z))
    finally:
        reader.close()
    if not imu_rows:
        raise RosbagImportError(f"imu topic '{mapping.imu.topic}' holds no messages", column=mapping.imu.topic)
    if not rng_rows:
        raise RosbagImportError(f"ranges topic '{mapping.ranges.topic}' holds no (valid) ranges "
                                f"({n_invalid} invalid)", column=mapping.ranges.topic)
    if n_invalid:
        changes.append(f"{mapping.ranges.topic}: dropped {n_invalid} range(s) with {mapping.ranges.valid_field} false")

    imu = pd.DataFrame(imu_rows, columns=IMU_COLUMNS)
    uwb = pd.DataFrame(rng_rows, columns=["t", "anchor", "range"])
    # drivers often publish 0 / NaN / inf for a failed ranging: drop and count them
    bad_r = ~np.isfinite(uwb["range"].to_numpy(float)) | (uwb["range"].to_numpy(float) <= 0)
    if bad_r.any():
        changes.append(f"{mapping.ranges.topic}: dropped {int(bad_r.sum())} non-positive or non-finite range(s)")
        uwb = uwb[~bad_r].reset_index(drop=True)
        if uwb.empty:
            raise RosbagImportError(f"ranges topic '{mapping.ranges.topic}' holds no positive finite range",
                                    column=mapping.ranges.range_field)
    gt = pd.DataFrame(gt_rows, columns=GT_COLUMNS) if gt_rows else None
    t0 = float(np.floor(min(imu["t"].min(), uwb["t"].min())))
    for df in (imu, uwb) + ((gt,) if gt is not None else ()):
        df["t"] = df["t"] - t0
    for name, df in (("imu", imu), ("ranges", uwb), ("groundtruth", gt)):
        if df is None:
            continue
        n_back = int((np.diff(df["t"].to_numpy()) < 0).sum())
        if n_back:
            changes.append(f"{name}: {n_back} message(s) out of time order; sorted by time")
    imu = imu.sort_values("t", kind="stable").reset_index(drop=True)
    uwb = uwb.sort_values(["t", "anchor"], kind="stable").reset_index(drop=True)
    n_dup = int(uwb.duplicated(["t", "anchor"]).sum())
    if n_dup:
        uwb = uwb.drop_duplicates(["t", "anchor"], keep="first").reset_index(drop=True)
        changes.append(f"ranges: dropped {n_dup} repeated range(s) of the same anchor at the same stamp (kept the first)")
    if gt is not None:
        gt = gt.sort_values("t", kind="stable").drop_duplicates("t").reset_index(drop=True)

    unknown = sorted(set(uwb["anchor"]) - set(anchors["anchor"]))
    if unknown:
        raise RosbagImportError(f"ranges use anchor id(s) {unknown} that are not in the anchors file "
                                f"{mapping.resolve(mapping.anchors)} (it has {', '.join(map(str, sorted(anchors['anchor'])))})",
                                file=mapping.anchors, column="anchor")
    dt = np.diff(imu["t"].to_numpy())
    meta = DatasetMeta(
        name=mapping.name or f"rosbag:{bag.name}",
        description=f"imported from {bag.name} (imu {mapping.imu.topic}, ranges {mapping.ranges.topic})",
        imu_rate_hz=float(1.0 / np.median(dt)) if len(dt) and np.median(dt) > 0 else None,
        range_sigma=mapping.range_sigma,
        tags=[TagMeta(name="tag0", lever_arm=mapping.lever_arm)],
        source=str(bag),
        extra={
            "importer": "uwbimu.io.importers.rosbag",
            "time_origin_s": t0,
            "imu_time": mapping.imu.time,
            "range_time": mapping.ranges.time,
            "mapping": mapping.model_dump(exclude={"base_dir"}),
        },
    )
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors, groundtruth=gt, meta=meta)
    return ImportResult(dataset=ds, extra_files={}, changes=changes)


def import_dataset(
    bag: Union[str, os.PathLike],
    dst: Union[str, os.PathLike],
    mapping: Union[RosbagMapping, str, os.PathLike],
    force: bool = False,
) -> ImportResult:
    """Convert ``bag`` with ``mapping`` and write to ``dst`` (non-empty ``dst`` refused unless ``force``)."""
    res = convert(bag, mapping)
    write_import(res, dst, force=force, src=bag)
    return res
