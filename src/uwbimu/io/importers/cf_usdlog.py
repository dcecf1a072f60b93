"""Importer for the Crazyflie uSD-card event log (``uwbimu import cf-usdlog LOG DST --anchors A``).

The decoder is written from the format description (Bitcraze
``crazyflie-firmware/tools/usdlog/cfusdlog.py``; the UTIL devkit ships the
same file).  A log file is, little-endian throughout::

    uint8   0xBC                        magic
    uint16  version                     1 or 2
    uint16  n_event_types
    n_event_types x {                   header
        uint16  event id
        char[]  event name, NUL-terminated         e.g. "estTDOA"
        uint16  n_variables
        n_variables x char[] "name(T)", NUL-terminated, T a struct type code (e.g. "acc.x(f)")
    }
    records until the last 4 bytes {
        uint16  event id
        uint32  timestamp [ms]   (version 1)  |  uint64 timestamp [us]  (version 2)
        packed payload of the event's variables (struct format "<" + type codes)
    }
    uint32  CRC-32 (zlib) of every byte before it

Events used (names as the firmware's ``EVENTTRIGGER`` and the uSD config give them):

* ``estTDOA`` (``idA``, ``idB``, ``distanceDiff``): ``distanceDiff`` is, as in
  the firmware's TDoA model, ``|p - p_B| - |p - p_A|`` [m] -> ``tdoa.csv``
  (``anchor_a = idA``, ``anchor_b = idB``) unchanged;
* ``estAcceleration`` (``acc.x/y/z`` [g]) -> m/s^2 (x 9.81, the value the
  Crazyflie firmware and the UTIL devkit use);
* ``estGyroscope`` (``gyro.x/y/z`` [deg/s]) -> rad/s;
* ``estPose`` with ``locSrv.x/y/z/qx/qy/qz/qw`` (motion-capture pose sent to
  the Crazyflie, the UTIL set-up), if present -> ``groundtruth.csv``.

All events carry the Crazyflie's own clock, so IMU and TDoA share a clock
(the UWB clock of the dataset); times are shifted by the earliest stamp.
The accelerometer is linearly interpolated to the gyro stamps (the two
streams are logged separately), and gyro samples outside the accelerometer's
span are dropped; both are recorded in ``extra.import_changes``.

Nominal lever arm: the importer reads the UTIL set-up's logs (its uSD configuration and
``estPose``/``locSrv`` ground truth), so the tag's nominal lever arm in ``dataset.yaml`` is the
UTIL platform's documented vehicle-centre -> UWB-tag offset, :data:`UTIL_T_UV` (the dataset page:
"the manually measured translation vectors from the center of the vehicle to onboard sensors
(UWB tag and flow deck) in the dataset paper and the data parsing scripts"; the devkit's
``t_uv = [-0.01245, 0.00127, 0.0908]`` m, "external calibration: translation vector from the
quadcopter to UWB tag", in its ESKF and plotting scripts).  It is a prior mean for the estimators
(``lever_arm.prior: dataset``), never a measured truth; ``lever_arm=None`` writes none (another
vehicle), a 3-vector writes that one.  The choice is recorded in ``extra.import_changes`` and
``extra.nominal_lever_arm_source``.

TDoA rows whose ``|tdoa|`` exceeds the two anchors' separation plus
``tdoa_margin`` (``--tdoa-margin``, 1 m) are dropped and counted per anchor
pair (:mod:`uwbimu.io.importers.tdoa`); ``dataset.yaml`` says
``single_clock: true``.  ``--anchors`` takes an ``anchors.csv`` or a UTIL
survey (``.npz``, ``_survey.txt``; :mod:`uwbimu.io.importers.anchors`).

Refused (``DatasetError`` naming the file and the record or header entry):
bad magic, unsupported version, CRC mismatch (unless ``ignore_crc``), a
record with an unknown event id, a truncated record, a header type code
that is not a struct code, missing events or variables, and TDoA rows whose
anchor ids are not in the anchors file.
"""

from __future__ import annotations

import math
import os
import struct
import zlib
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np
import pandas as pd

from uwbimu.io.dataset import GT_COLUMNS, IMU_COLUMNS, UWB_COLUMNS, Dataset, DatasetMeta, TagMeta
from uwbimu.io.importers import ImportResult, write_import
from uwbimu.io.importers.anchors import QuatOrder, read_anchors, read_anchors_csv
from uwbimu.io.importers.tdoa import TDOA_MARGIN_M, drop_tdoa_outliers, tdoa_load_options, tdoa_table
from uwbimu.errors import UsageError
from uwbimu.io.loader import DatasetError
from uwbimu.models.imu import imu_preset

__all__ = ["decode", "convert", "import_dataset", "combine_imu", "read_anchors_csv", "tdoa_table", "G_CRAZYFLIE",
           "encode", "EVENT_TYPES", "UTIL_T_UV"]

#: The UTIL platform's vehicle-centre -> UWB-tag offset [m] in the body (IMU) frame: the devkit's ``t_uv``
#: (utiasDSL/util-uwb-dataset, scripts/estimation/eskf_class.py and the visualisation scripts).
UTIL_T_UV = (-0.01245, 0.00127, 0.0908)
_UTIL_SOURCE = ("UTIL devkit t_uv (utiasDSL/util-uwb-dataset scripts: 'translation vector from the quadcopter to "
                "UWB tag'), the offset the dataset page says is manually measured")

#: The events and variables this importer reads, with the struct type codes the firmware logs them
#: with (``encode(EVENT_TYPES, ...)`` builds a log like the UTIL set-up's for tests and fixtures).
EVENT_TYPES = [
    ("estTDOA", [("idA", "B"), ("idB", "B"), ("distanceDiff", "f")]),
    ("estAcceleration", [("acc.x", "f"), ("acc.y", "f"), ("acc.z", "f")]),
    ("estGyroscope", [("gyro.x", "f"), ("gyro.y", "f"), ("gyro.z", "f")]),
    ("estPose", [("locSrv.x", "f"), ("locSrv.y", "f"), ("locSrv.z", "f"), ("locSrv.qx", "f"), ("locSrv.qy", "f"),
                 ("locSrv.qz", "f"), ("locSrv.qw", "f")]),
]

#: Standard gravity used by the Crazyflie firmware to convert g to m/s^2.
G_CRAZYFLIE = 9.81
_STRUCT_CODES = set("bBhHiIqQfd?")


def _name(data: bytes, idx: int, path: Path, what: str) -> tuple[str, int]:
    end = data.find(b"\x00", idx)
    if end < 0:
        raise DatasetError(f"{path.name}: header {what} at byte {idx} is not NUL-terminated", file=path.name)
    try:
        return data[idx:end].decode("utf-8"), end + 1
    except UnicodeDecodeError:
        raise DatasetError(f"{path.name}: header {what} at byte {idx} is not UTF-8 text", file=path.name) from None


def decode(path: Union[str, os.PathLike], ignore_crc: bool = False) -> tuple[dict, dict]:
    """Decode a uSD event log.

    Returns ``(events, info)``: ``events[name]`` maps ``"timestamp"`` (ms, float)
    and each variable name to a NumPy array; ``info`` holds ``version``,
    ``records`` and ``crc_ok``.
    """
    path = Path(path)
    data = path.read_bytes()
    if len(data) < 9 or data[0] != 0xBC:
        raise DatasetError(f"{path.name}: not a Crazyflie uSD log (first byte must be 0xBC, file has "
                           f"{len(data)} bytes)", file=path.name)
    crc_ok = zlib.crc32(data[:-4]) == struct.unpack("<I", data[-4:])[0]
    if not crc_ok and not ignore_crc:
        raise DatasetError(f"{path.name}: CRC-32 of the log does not match its last 4 bytes (truncated or "
                           "corrupted file)", file=path.name, hint="--ignore-crc decodes the complete records anyway")
    version, n_types = struct.unpack("<HH", data[1:5])
    if version not in (1, 2):
        raise DatasetError(f"{path.name}: unsupported log version {version} (1 and 2 are known)", file=path.name)
    idx = 5
    types: dict[int, dict] = {}
    for k in range(n_types):
        if idx + 2 > len(data) - 4:
            raise DatasetError(f"{path.name}: header ends inside event type {k}", file=path.name)
        (eid,) = struct.unpack("<H", data[idx:idx + 2])
        name, idx = _name(data, idx + 2, path, f"event type {k} name")
        (n_var,) = struct.unpack("<H", data[idx:idx + 2])
        idx += 2
        fmt, variables = "<", []
        for v in range(n_var):
            spec, idx = _name(data, idx, path, f"variable {v} of event {name!r}")
            if len(spec) < 4 or spec[-3] != "(" or spec[-1] != ")" or spec[-2] not in _STRUCT_CODES:
                raise DatasetError(f"{path.name}: header variable {spec!r} of event {name!r} is not 'name(T)' "
                                   f"with a type code T in {''.join(sorted(_STRUCT_CODES))}", file=path.name,
                                   column=name)
            fmt += spec[-2]
            variables.append(spec[:-3])
        types[eid] = {"name": name, "fmt": fmt, "size": struct.calcsize(fmt), "vars": variables}
    rows: dict[int, list] = {eid: [] for eid in types}
    stamps: dict[int, list] = {eid: [] for eid in types}
    head_fmt, head_size = ("<HI", 6) if version == 1 else ("<HQ", 10)
    end = len(data) - 4
    n = 0
    while idx < end:
        if idx + head_size > end:
            raise DatasetError(f"{path.name}: record {n} at byte {idx} is truncated (header)", file=path.name, row=n)
        eid, stamp = struct.unpack(head_fmt, data[idx:idx + head_size])
        if eid not in types:
            raise DatasetError(f"{path.name}: record {n} at byte {idx} has unknown event id {eid} (known: "
                               f"{', '.join(map(str, sorted(types)))})", file=path.name, row=n)
        ev = types[eid]
        start = idx + head_size
        if start + ev["size"] > end:
            raise DatasetError(f"{path.name}: record {n} ({ev['name']}) at byte {idx} is truncated", file=path.name,
                               row=n, column=ev["name"])
        rows[eid].append(struct.unpack(ev["fmt"], data[start:start + ev["size"]]))
        stamps[eid].append(stamp if version == 1 else stamp / 1000.0)
        idx = start + ev["size"]
        n += 1
    events = {}
    for eid, ev in types.items():
        if not rows[eid]:
            continue
        arr = list(zip(*rows[eid]))
        out = {"timestamp": np.asarray(stamps[eid], dtype=float)}
        out.update({v: np.asarray(col) for v, col in zip(ev["vars"], arr)})
        events[ev["name"]] = out
    return events, {"version": version, "records": n, "crc_ok": crc_ok}


def encode(events: list[tuple[str, list[tuple[str, str]]]], records: list[tuple[int, float, tuple]],
           version: int = 2) -> bytes:
    """Build a uSD log (the inverse of :func:`decode`; used by the tests and for fixtures).

    ``events``: ``[(name, [(variable, type code), ...]), ...]`` with ids 0, 1, ...;
    ``records``: ``[(event id, timestamp in ms, values), ...]``.
    """
    out = bytearray(b"\xbc") + struct.pack("<HH", version, len(events))
    fmts = []
    for eid, (name, variables) in enumerate(events):
        out += struct.pack("<H", eid) + name.encode() + b"\x00" + struct.pack("<H", len(variables))
        for v, code in variables:
            out += f"{v}({code})".encode() + b"\x00"
        fmts.append("<" + "".join(c for _, c in variables))
    for eid, t_ms, values in records:
        stamp = struct.pack("<HI", eid, int(round(t_ms))) if version == 1 else struct.pack("<HQ", eid, int(round(t_ms * 1000)))
        out += stamp + struct.pack(fmts[eid], *values)
    out += struct.pack("<I", zlib.crc32(bytes(out)))
    return bytes(out)


def combine_imu(t_acc: np.ndarray, acc_g: np.ndarray, t_gyro: np.ndarray, gyro_dps: np.ndarray, source: str,
                changes: list[str]) -> pd.DataFrame:
    """IMU table on the gyro stamps: accelerometer [g] interpolated, converted to m/s^2 and rad/s.

    Gyro samples outside the accelerometer's span are dropped (counted in ``changes``).
    """
    inside = (t_gyro >= t_acc[0]) & (t_gyro <= t_acc[-1])
    if inside.sum() < 2:
        raise DatasetError(f"{source}: the gyro and accelerometer streams do not overlap", file=source)
    if not inside.all():
        changes.append(f"{source}: {int((~inside).sum())} gyro sample(s) outside the accelerometer's time span "
                       "dropped")
    t = t_gyro[inside]
    acc = np.column_stack([np.interp(t, t_acc, acc_g[:, i]) for i in range(3)]) * G_CRAZYFLIE
    gyro = np.radians(gyro_dps[inside])
    changes.append(f"{source}: accelerometer [g] interpolated linearly to the gyro stamps and multiplied by "
                   f"{G_CRAZYFLIE}; gyro [deg/s] converted to rad/s")
    return pd.DataFrame(np.column_stack([t, acc, gyro]), columns=IMU_COLUMNS)


def _need(events: dict, name: str, variables: list[str], path: Path) -> dict:
    if name not in events:
        raise DatasetError(f"{path.name}: no {name!r} events in the log (it holds: {', '.join(sorted(events))})",
                           file=path.name, column=name)
    ev = events[name]
    missing = [v for v in variables if v not in ev]
    if missing:
        raise DatasetError(f"{path.name}: event '{name}' lacks variable(s) {', '.join(missing)} (it has "
                           f"{', '.join(k for k in ev if k != 'timestamp')})", file=path.name, column=name)
    return ev


def convert(log: Union[str, os.PathLike], anchors: Union[str, os.PathLike], ignore_crc: bool = False,
            name: Optional[str] = None, tdoa_margin: float = TDOA_MARGIN_M,
            quat_order: QuatOrder = "auto",
            lever_arm: Optional[Sequence[float]] = UTIL_T_UV) -> ImportResult:
    """Convert a uSD event log plus an anchors file into a :class:`Dataset` (not written).

    Parameters
    ----------
    log : the binary event log.
    anchors : ``anchors.csv``, a UTIL survey ``.npz`` or ``_survey.txt``
        (:func:`uwbimu.io.importers.anchors.read_anchors`).
    ignore_crc : decode the complete records of a log whose CRC does not match.
    name : dataset name (default ``cf-usdlog:<log name>``).
    tdoa_margin : TDoA rows with ``|tdoa|`` beyond the anchors' separation plus
        this (m) are dropped and counted (:func:`~uwbimu.io.importers.tdoa.drop_tdoa_outliers`).
    quat_order : ``an_quat`` order of a survey file (``auto``: by the file's version).
    lever_arm : (3,) nominal lever arm of the tag [m], IMU (body) frame, written to ``dataset.yaml``
        (default: the UTIL platform's documented offset :data:`UTIL_T_UV`); None: none written.
    """
    log = Path(log)
    if lever_arm is not None:
        lever = np.asarray(lever_arm, dtype=float).reshape(-1)
        if lever.shape != (3,) or not np.all(np.isfinite(lever)):
            raise UsageError(f"lever_arm must be 3 finite numbers [m] (x, y, z in the IMU frame); got {lever.size} "
                             "value(s)" + ("" if lever.shape != (3,) else ", not all finite"))
    if not log.is_file():
        raise DatasetError(f"{log}: log file not found", file=log.name)
    changes: list[str] = []
    anchors_df = read_anchors(anchors, quat_order, changes)
    events, info = decode(log, ignore_crc=ignore_crc)
    if not info["crc_ok"]:
        changes.append(f"{log.name}: CRC mismatch ignored (--ignore-crc); {info['records']} complete records decoded")
    td = _need(events, "estTDOA", ["idA", "idB", "distanceDiff"], log)
    acc = _need(events, "estAcceleration", ["acc.x", "acc.y", "acc.z"], log)
    gyr = _need(events, "estGyroscope", ["gyro.x", "gyro.y", "gyro.z"], log)
    t0 = min(float(e["timestamp"][0]) for e in events.values())
    sec = lambda e: (e["timestamp"] - t0) / 1000.0  # noqa: E731
    changes.append(f"{log.name}: Crazyflie clock [ms] -> s, origin at the first record (t0 = {t0} ms); IMU, TDoA "
                   "and the pose sent to the Crazyflie share that clock (single_clock: true)")
    imu = combine_imu(sec(acc), np.column_stack([acc[f"acc.{a}"] for a in "xyz"]).astype(float), sec(gyr),
                      np.column_stack([gyr[f"gyro.{a}"] for a in "xyz"]).astype(float), log.name, changes)
    tdoa = tdoa_table(sec(td), td["idA"], td["idB"], td["distanceDiff"], anchors_df, log.name, "estTDOA event")
    tdoa, outliers = drop_tdoa_outliers(tdoa, anchors_df, tdoa_margin, log.name, changes)
    gt = None
    pose_vars = ["locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qx", "locSrv.qy", "locSrv.qz", "locSrv.qw"]
    if "estPose" in events and all(v in events["estPose"] for v in pose_vars):
        ev = events["estPose"]
        gt = pd.DataFrame(np.column_stack([sec(ev)] + [ev[v].astype(float) for v in
                                          ("locSrv.x", "locSrv.y", "locSrv.z", "locSrv.qw", "locSrv.qx",
                                           "locSrv.qy", "locSrv.qz")]), columns=GT_COLUMNS)
        changes.append(f"{log.name}: estPose locSrv.* (external pose sent to the Crazyflie) -> groundtruth.csv")
    if lever_arm is not None:
        source = _UTIL_SOURCE if tuple(lever) == UTIL_T_UV else "given (lever_arm)"
        changes.append(f"{log.name}: nominal lever arm of tag0 = ({', '.join(f'{v:g}' for v in lever)}) m, IMU frame: "
                       f"{source}; a prior mean for the estimators, not a measured truth")
    dt = float(np.median(np.diff(imu["t"].to_numpy()))) if len(imu) > 1 else math.nan
    meta = DatasetMeta(
        name=name or f"cf-usdlog:{log.name}",
        description="Crazyflie uSD-card event log (estTDOA, estAcceleration, estGyroscope); every stream is "
                    "stamped by the Crazyflie's clock",
        imu_noise=imu_preset("bmi088"),
        imu_rate_hz=1.0 / dt if dt > 0 else None,
        tags=[TagMeta(name="tag0", lever_arm=None if lever_arm is None else [float(v) for v in lever])],
        source=f"Crazyflie uSD event log {log.name} (format version {info['version']})",
        single_clock=True,
        extra={"import_changes": list(changes), "uwb_mode": "tdoa", "usd_events": sorted(events),
               "tdoa_outliers": outliers},
    )
    if lever_arm is not None:
        meta.extra["nominal_lever_arm_source"] = _UTIL_SOURCE if tuple(lever) == UTIL_T_UV else "given"
    uwb = pd.DataFrame({"t": np.zeros(0), "anchor": np.zeros(0, dtype=str), "range": np.zeros(0)},
                       columns=UWB_COLUMNS)
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors_df, groundtruth=gt, meta=meta, tdoa=tdoa)
    return ImportResult(dataset=ds, changes=changes)


def import_dataset(log, dst, anchors, force: bool = False, ignore_crc: bool = False,
                   name: Optional[str] = None, tdoa_margin: float = TDOA_MARGIN_M,
                   quat_order: QuatOrder = "auto", lever_arm: Optional[Sequence[float]] = UTIL_T_UV) -> ImportResult:
    """Convert ``log`` and write it to ``dst`` (refuses a non-empty ``dst`` unless ``force``)."""
    res = convert(log, anchors, ignore_crc=ignore_crc, name=name, tdoa_margin=tdoa_margin, quat_order=quat_order,
                  lever_arm=lever_arm)
    write_import(res, dst, force=force, src=log, load_options=tdoa_load_options(tdoa_margin))
    return res
