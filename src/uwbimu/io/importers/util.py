"""Importer for the UTIL UWB TDoA dataset (``uwbimu import util CSV DST [--anchors SURVEY]``).

UTIL: W. Zhao, A. Goudar, X. Qiao, A. P. Schoellig, "UTIL: An Ultra-wideband
Time-difference-of-arrival Indoor Localization Dataset", IJRR 2024;
devkit https://github.com/utiasDSL/util-uwb-dataset.  Layout as the devkit
documents and reads it (``scripts/utility/praser.py``,
``scripts/flight-dataset/sdcard_scripts/log_to_csv.py``):

* one flight CSV per trial, e.g. ``flight-dataset/csv-data/const1/const1-trial1-tdoa2.csv``,
  with a header and column groups of different lengths (shorter groups are
  padded with empty cells at the end)::

      t_tdoa, idA, idB, tdoa_meas          TDoA [s, -, -, m]; tdoa_meas = |p - p_B| - |p - p_A|
      t_acc, acc_x, acc_y, acc_z           accelerometer [s, g]
      t_gyro, gyro_x, gyro_y, gyro_z       gyro [s, deg/s]
      t_tof, tof                           laser height [s, m]          (not imported)
      t_flow, deltaX, deltaY               optical flow [s, px]         (not imported)
      t_baro, baro                         barometer [s, asl]           (not imported)
      t_pose, pose_x, pose_y, pose_z, pose_qx, pose_qy, pose_qz, pose_qw   Vicon pose [s, m, -]

  All times are the Crazyflie's clock (s since the log's first record).
* the anchor survey of the constellation, ``flight-dataset/survey-results/anchor_constN.npz``
  (``an_pos`` (8, 3) m, ``an_quat`` (8, 4) anchor frame -> Vicon frame, ``[qx, qy, qz, qw]``
  in the release; the 2021 surveys named by date, ``anchor_0425.npz``, hold
  ``[qw, qx, qy, qz]``: :mod:`uwbimu.io.importers.anchors` picks the order by the
  file's version), or its text form ``anchor_constN_survey.txt`` (lines
  ``anI_p,x,y,z`` and ``anI_quat,qx,qy,qz,qw``).  Without ``--anchors`` the importer looks for
  ``survey-results/anchor_constN.npz`` (then ``..._survey.txt``) in the CSV's
  folder and its parents, N from ``constN`` in the CSV's name.

Conversion (every choice is listed in ``extra.import_changes``): anchor ids
``0..7`` as text; ``tdoa = tdoa_meas`` unchanged (same convention as ours,
``anchor_a = idA``, ``anchor_b = idB``); accelerometer x 9.81 (the devkit's
``GRAVITY_MAGNITUDE``) interpolated to the gyro stamps, gyro deg/s -> rad/s;
ground truth = the Vicon pose of the vehicle body frame, taken as the IMU
frame; the devkit's antenna offset ``t_uv = [-0.01245, 0.00127, 0.0908]`` m
becomes the tag's *nominal* lever arm (a fixed setting of the devkit, not a
measured truth).  TDoA rows beyond the anchors' separation plus
``tdoa_margin`` are dropped and counted per anchor pair; all streams come from
one Crazyflie log, so ``dataset.yaml`` says ``single_clock: true``.  Refusals
name the file, the line and the column (an empty or cut-short CSV included).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Optional, Union

import numpy as np
import pandas as pd

from uwbimu.io.dataset import GT_COLUMNS, UWB_COLUMNS, Dataset, DatasetMeta, TagMeta
from uwbimu.io.importers import ImportResult, read_csv_source, write_import
from uwbimu.io.importers.anchors import QuatOrder, read_survey
from uwbimu.io.importers.cf_usdlog import UTIL_T_UV, combine_imu
from uwbimu.io.importers.tdoa import TDOA_MARGIN_M, drop_tdoa_outliers, tdoa_load_options, tdoa_table
from uwbimu.io.loader import DatasetError
from uwbimu.models.imu import imu_preset

__all__ = ["convert", "import_dataset", "read_survey", "find_survey", "GROUPS", "T_UV"]

#: Devkit antenna offset: UWB tag in the quadrotor body frame [m] (visual_tdoa*_csv.py, main.py).
T_UV = list(UTIL_T_UV)

#: Column groups of a flight CSV; each group is one stream (same length within a group).
GROUPS: dict[str, list[str]] = {
    "tdoa": ["t_tdoa", "idA", "idB", "tdoa_meas"],
    "acc": ["t_acc", "acc_x", "acc_y", "acc_z"],
    "gyro": ["t_gyro", "gyro_x", "gyro_y", "gyro_z"],
    "pose": ["t_pose", "pose_x", "pose_y", "pose_z", "pose_qx", "pose_qy", "pose_qz", "pose_qw"],
}
_REQUIRED = ("tdoa", "acc", "gyro")


def find_survey(csv: Path) -> Optional[Path]:
    """``survey-results/anchor_constN.npz`` (or ``_survey.txt``) next to the CSV or in a parent folder."""
    m = re.search(r"const(\d+)", csv.name)
    if m is None:
        return None
    stem = f"anchor_const{m.group(1)}"
    for folder in [csv.parent, *csv.parent.parents][:5]:
        for cand in (folder / "survey-results" / f"{stem}.npz", folder / "survey-results" / f"{stem}_survey.txt",
                     folder / f"{stem}.npz", folder / f"{stem}_survey.txt"):
            if cand.is_file():
                return cand
    return None


def _stream(raw: pd.DataFrame, cols: list[str], fname: str) -> np.ndarray:
    """The rows of one column group: leading complete rows, then only empty cells (padding)."""
    block = raw[cols]
    filled = block.notna().to_numpy()
    any_f = filled.any(axis=1)
    n = int(np.argmin(any_f)) if not any_f.all() else len(any_f)  # first fully empty row
    partial = any_f & ~filled.all(axis=1)
    if partial[:n].any() or any_f[n:].any():
        i = int(np.argmax(partial)) if partial[:n].any() else n + int(np.argmax(any_f[n:]))
        col = cols[int(np.argmin(filled[i]))] if partial[i] else cols[int(np.argmax(filled[i]))]
        raise DatasetError(f"{fname}, line {i + 2}, column '{col}': the {cols[0][2:]} stream has a gap (empty cells "
                           "are allowed only as padding after a stream's last row)", file=fname, row=i + 2, column=col)
    out = np.empty((n, len(cols)))
    for j, c in enumerate(cols):
        vals = pd.to_numeric(block[c].iloc[:n], errors="coerce").to_numpy(float)
        bad = ~np.isfinite(vals)
        if bad.any():
            i = int(np.argmax(bad))
            raise DatasetError(f"{fname}, line {i + 2}, column '{c}': not a finite number ('{block[c].iloc[i]}')",
                               file=fname, row=i + 2, column=c)
        out[:, j] = vals
    return out


def convert(csv: Union[str, os.PathLike], anchors: Optional[Union[str, os.PathLike]] = None,
            name: Optional[str] = None, tdoa_margin: float = TDOA_MARGIN_M,
            quat_order: QuatOrder = "auto") -> ImportResult:
    """Convert one UTIL flight CSV (+ its anchor survey) into a :class:`Dataset` (not written).

    Parameters
    ----------
    csv : the flight CSV.
    anchors : the anchor survey (default: found next to or above ``csv``, :func:`find_survey`).
    name : dataset name (default ``util:<csv stem>``).
    tdoa_margin : TDoA rows with ``|tdoa|`` beyond the anchors' separation plus
        this (m) are dropped and counted.
    quat_order : ``an_quat`` order of the survey (``auto``: by the survey file's version,
        :func:`uwbimu.io.importers.anchors.survey_quat_order`).
    """
    csv = Path(csv)
    if not csv.is_file():
        raise DatasetError(f"{csv}: flight CSV not found", file=csv.name)
    survey = Path(anchors) if anchors is not None else find_survey(csv)
    if survey is None:
        raise DatasetError(f"{csv.name}: no anchor survey given and none found (survey-results/anchor_constN.npz "
                           "next to or above the CSV)", file=csv.name, hint="pass --anchors SURVEY.npz|_survey.txt")
    changes: list[str] = []
    anchors_df = read_survey(survey, quat_order, changes)
    raw = read_csv_source(csv, what="flight CSV")
    for g in _REQUIRED:
        missing = [c for c in GROUPS[g] if c not in raw.columns]
        if missing:
            raise DatasetError(f"{csv.name}, line 1: missing column(s) {missing} (a UTIL flight CSV has "
                               f"{sum(GROUPS.values(), [])} ...)", file=csv.name, row=1, column=missing[0])
    td = _stream(raw, GROUPS["tdoa"], csv.name)
    acc = _stream(raw, GROUPS["acc"], csv.name)
    gyr = _stream(raw, GROUPS["gyro"], csv.name)
    for what, arr in (("t_tdoa", td), ("t_acc", acc), ("t_gyro", gyr)):
        if len(arr) < 2:
            raise DatasetError(f"{csv.name}: the {what[2:]} stream has fewer than 2 rows", file=csv.name, column=what)
    ids = np.concatenate([td[:, 1], td[:, 2]])
    if not np.all(ids == np.round(ids)):
        i = int(np.argmax(ids != np.round(ids))) % len(td)
        raise DatasetError(f"{csv.name}, line {i + 2}: anchor id is not an integer", file=csv.name, row=i + 2,
                           column="idA")
    tdoa = tdoa_table(td[:, 0], td[:, 1].astype(int), td[:, 2].astype(int), td[:, 3], anchors_df, csv.name,
                      "line", first=2)
    tdoa, outliers = drop_tdoa_outliers(tdoa, anchors_df, tdoa_margin, csv.name, changes)
    imu = combine_imu(acc[:, 0], acc[:, 1:4], gyr[:, 0], gyr[:, 1:4], csv.name, changes)
    gt = None
    if all(c in raw.columns for c in GROUPS["pose"]):
        pose = _stream(raw, GROUPS["pose"], csv.name)
        if len(pose):
            q = pose[:, [7, 4, 5, 6]]
            q = q / np.linalg.norm(q, axis=1, keepdims=True)
            gt = pd.DataFrame(np.column_stack([pose[:, 0:4], q]), columns=GT_COLUMNS)
            changes.append(f"{csv.name}: Vicon pose of the vehicle body frame -> groundtruth.csv (taken as the IMU "
                           "frame; quaternion reordered to qw, qx, qy, qz)")
    changes.append(f"{csv.name}: tof, flow and baro columns not imported")
    changes.append(f"anchors from {survey.name}: ids 0..{len(anchors_df) - 1}")
    changes.append(f"{csv.name}: every stream on the Crazyflie's clock (one log): single_clock: true")
    mode = "tdoa3" if "tdoa3" in csv.name else ("tdoa2" if "tdoa2" in csv.name else "tdoa")
    rate = 1.0 / float(np.median(np.diff(imu["t"].to_numpy())))
    meta = DatasetMeta(
        name=name or f"util:{csv.stem}",
        description=f"UTIL flight {csv.stem} (Loco Positioning {mode.upper()}, Crazyflie-based quadrotor)",
        imu_noise=imu_preset("bmi088"),
        imu_rate_hz=rate,
        tags=[TagMeta(name="tag0", lever_arm=list(T_UV))],
        source="UTIL dataset (Zhao, Goudar, Qiao, Schoellig, IJRR 2024), https://utiasdsl.github.io/util-uwb-dataset/; "
               f"file {csv.name}, survey {survey.name}",
        license="see the UTIL dataset's website (cite the IJRR paper when using the data)",
        single_clock=True,
        extra={"import_changes": list(changes), "uwb_mode": mode, "nominal_lever_arm_source": "devkit t_uv",
               "tdoa_outliers": outliers},
    )
    uwb = pd.DataFrame({"t": np.zeros(0), "anchor": np.zeros(0, dtype=str), "range": np.zeros(0)},
                       columns=UWB_COLUMNS)
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors_df, groundtruth=gt, meta=meta, tdoa=tdoa)
    return ImportResult(dataset=ds, changes=changes)


def import_dataset(csv, dst, anchors=None, force: bool = False, name: Optional[str] = None,
                   tdoa_margin: float = TDOA_MARGIN_M, quat_order: QuatOrder = "auto") -> ImportResult:
    """Convert ``csv`` and write it to ``dst`` (refuses a non-empty ``dst`` unless ``force``)."""
    res = convert(csv, anchors, name=name, tdoa_margin=tdoa_margin, quat_order=quat_order)
    write_import(res, dst, force=force, src=csv, load_options=tdoa_load_options(tdoa_margin))
    return res
