"""Importer for the INRoL UWB-IMU filtering sequences (IROS 2024, GPL-3.0 data).

Source: https://github.com/INRoL/inrol_uwb_localization,
``example/filtering_state_estimation*/parsed_dataset/`` (see the README of
``shared/datasets/inrol_uwb_imu``).  Space-separated text files with a ``#``
header:

=================  ==========================================  ==========================
source file        source columns                              our table
=================  ==========================================  ==========================
``imu.txt``        ``index timestamp wx wy wz ax ay az``       ``imu``: t, ax..az, wx..wz
``uwb.txt``        ``index timestamp anchor_id r``             ``uwb``: t, anchor (text), range
``anchor.txt``     ``anchor_id tx ty tz qx qy qz qw``          ``anchors``: anchor, x, y, z
``imu_pose.txt``   ``timestamp tx ty tz qx qy qz qw``          ``groundtruth``: t, px..pz, qw..qz
=================  ==========================================  ==========================

All streams share one clock; the ground truth is the pose of the IMU frame
(quaternion reordered from x,y,z,w to w,x,y,z; no velocity).  The documented
IMU->tag lever arm is (0, 0, 0.01) m.  Rows of ``uwb.txt`` that are out of
time order (one in sequence 1) are sorted, and the change is reported.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np
import pandas as pd
import yaml

from uwbimu.io.dataset import Dataset, DatasetMeta, TagMeta, TruthMeta
from uwbimu.io.importers import ImportResult, read_text_table, require_files, sort_by_time, write_import
from uwbimu.models.imu import ImuNoise

NAME = "inrol"
SOURCE_FILES = ["imu.txt", "uwb.txt", "anchor.txt", "imu_pose.txt", "LICENSE"]
REPOSITORY = "https://github.com/INRoL/inrol_uwb_localization"
COMMIT = "40562b6fee3c72920b6f6972524990612a7f58b9"
PAPER = ('T. Kim, B. Yoon, D. J. Lee, "UWB-Based Localization System Considering Antenna Anisotropy '
         'and NLOS/Multipath Conditions", IROS 2024')

#: Documented IMU->tag lever arm (source filter: inv(T_cam_imu) inv(T_mocap_cam) T_mocap_tag), m.
LEVER_ARM = [0.0, 0.0, 0.01]
#: Overall robust range sigma against ground truth (dataset README: ~0.10 m).
RANGE_SIGMA = 0.10

#: IMU noise.  The source's filter values (accel 0.10, gyro 0.20) are tuning
#: numbers, not densities.  White-noise densities here come from the first 4 s,
#: where the rig stands still: per-axis sd 0.0019-0.0029 rad/s and
#: 0.011-0.014 m/s^2 at 100 Hz, i.e. 1.9-2.9e-4 rad/s/sqrt(Hz) and
#: 1.1-1.4e-3 m/s^2/sqrt(Hz); rounded up to 3e-4 and 1.5e-3.  Bias random
#: walks are those of the ICM-20948 class preset (no way to measure them from
#: 191 s); initial bias sd: gyro 0.005 rad/s, accel 0.1 m/s^2.
IMU_NOISE = ImuNoise(
    gyro_noise_density=3.0e-4,
    accel_noise_density=1.5e-3,
    gyro_bias_rw=4.0e-5,
    accel_bias_rw=6.0e-4,
    gyro_bias_sigma0=0.005,
    accel_bias_sigma0=0.1,
)

_DESCRIPTION = """\
INRoL UWB-IMU filtering sequence converted by `uwbimu import inrol`. Real UWB two-way ranging to
8 fixed anchors (~21 Hz per anchor) and a ~100 Hz IMU, with motion-capture ground truth of the IMU
frame. Clock: all streams share one clock (the source states no UWB/IMU time offset; a scan of the
range residuals puts it within about +-0.1 s, flattest near +0.02..+0.06 s), so imu.csv, uwb.csv and
groundtruth.csv carry the source timestamps unchanged. Lever arm: the source's documented IMU->tag
lever arm (0, 0, 0.01) m is given both as the nominal tag lever arm and as truth.lever_arm (it is the
documented value the evaluation compares against, not an independent measurement). Ground truth:
motion capture; sequence 1 has a mocap glitch (two samples near t = 172.63 s displaced by about
0.12-0.14 m): interpolate robustly. Ranges: per-anchor median residual -0.05..+0.08 m and sd
0.08-0.16 m against ground truth; the source models direction-dependent bias and NLOS tails.
IMU noise: white-noise densities measured at rest in the first 4 s; bias random walks of an
ICM-20948-class IMU (assumed, not measured). Data license: GPL-3.0 (see LICENSE and ATTRIBUTION.md
in this folder)."""


def _attribution(src: Path, changes: list[str]) -> str:
    lines = [
        "# Attribution",
        "",
        "These files are derived from the INRoL UWB localization example data.",
        "",
        f"* Repository: {REPOSITORY}",
        f"* Commit: `{COMMIT}`",
        "* Files: `example/filtering_state_estimation*/parsed_dataset/{anchor,imu,imu_pose,uwb}.txt`",
        f"* Paper: {PAPER}",
        "* License: GPL-3.0 (full text in `LICENSE` next to this file). The converted data stays under",
        "  GPL-3.0; keep this attribution and the license with it.",
        "",
        f"Converted with `uwbimu import inrol` from `{src.name}`: column reordering (IMU `ax..az, wx..wz`),",
        "quaternions reordered from (x, y, z, w) to (w, x, y, z), anchor ids as text, anchor antenna",
        "orientations moved to `dataset.yaml` (`extra.anchor_orientation_xyzw`). Values are unchanged.",
    ]
    if changes:
        lines += ["", "Changes reported by the importer:", ""] + [f"* {c}" for c in changes]
    return "\n".join(lines) + "\n"


ProgressFn = Callable[[str, float], None]


def convert(src: Union[str, os.PathLike], name: str | None = None,
            progress: Optional[ProgressFn] = None) -> ImportResult:
    """Read an INRoL ``parsed_dataset`` folder (plus ``LICENSE``) into a :class:`Dataset`.

    Parameters
    ----------
    src : folder holding ``imu.txt, uwb.txt, anchor.txt, imu_pose.txt, LICENSE``
        (``parameter.yaml`` optional: its ``sensor_noise`` is kept in ``extra``).
    name : dataset name (default: the folder name, prefixed with ``inrol_`` if it lacks it).
    progress : optional ``progress(stage, fraction)`` callback (fraction of the conversion, 0-1).

    Raises
    ------
    DatasetError : a missing source file, or a malformed line (file, line, column).
    """
    src = Path(src)
    require_files(src, SOURCE_FILES)
    changes: list[str] = []
    report = progress or (lambda stage, frac: None)

    report("reading imu.txt", 0.0)
    raw = read_text_table(src / "imu.txt", ["index", "timestamp", "wx", "wy", "wz", "ax", "ay", "az"])
    raw = sort_by_time(raw, "timestamp", "imu.txt", changes)
    imu = pd.DataFrame({"t": raw["timestamp"], "ax": raw["ax"], "ay": raw["ay"], "az": raw["az"],
                        "wx": raw["wx"], "wy": raw["wy"], "wz": raw["wz"]})

    report("reading uwb.txt", 0.3)
    raw = read_text_table(src / "uwb.txt", ["index", "timestamp", "anchor_id", "r"])
    raw = sort_by_time(raw, "timestamp", "uwb.txt", changes)
    uwb = pd.DataFrame({"t": raw["timestamp"], "anchor": _ids(raw["anchor_id"]), "range": raw["r"]})

    raw = read_text_table(src / "anchor.txt", ["anchor_id", "tx", "ty", "tz", "qx", "qy", "qz", "qw"])
    # the documented antenna orientations (antenna frame -> world) go into anchors.csv's optional qw..qz
    anchors = pd.DataFrame({"anchor": _ids(raw["anchor_id"]), "x": raw["tx"], "y": raw["ty"], "z": raw["tz"],
                            "qw": raw["qw"], "qx": raw["qx"], "qy": raw["qy"], "qz": raw["qz"]})
    orient = {a: [float(v) for v in row] for a, row in
              zip(anchors["anchor"], raw[["qx", "qy", "qz", "qw"]].to_numpy())}

    report("reading imu_pose.txt", 0.6)
    raw = read_text_table(src / "imu_pose.txt", ["timestamp", "tx", "ty", "tz", "qx", "qy", "qz", "qw"])
    raw = sort_by_time(raw, "timestamp", "imu_pose.txt", changes)
    gt = pd.DataFrame({"t": raw["timestamp"], "px": raw["tx"], "py": raw["ty"], "pz": raw["tz"],
                       "qw": raw["qw"], "qx": raw["qx"], "qy": raw["qy"], "qz": raw["qz"]})

    extra: dict = {
        "importer": "uwbimu import inrol",
        "source_repository": REPOSITORY,
        "source_commit": COMMIT,
        "anchor_orientation_xyzw": orient,
        "truth_note": "truth.lever_arm is the source's documented IMU->tag lever arm (0, 0, 0.01) m; "
                      "no documented time offset",
        "import_changes": list(changes),
    }
    param = src / "parameter.yaml"
    if param.is_file():
        try:
            pdoc = yaml.safe_load(param.read_text()) or {}
            if isinstance(pdoc, dict) and isinstance(pdoc.get("sensor_noise"), dict):
                extra["source_sensor_noise_tuning"] = pdoc["sensor_noise"]
        except yaml.YAMLError:
            changes.append("parameter.yaml could not be parsed; its tuning values were not copied")

    dt = float(np.median(np.diff(imu["t"].to_numpy())))
    meta = DatasetMeta(
        name=name or (src.name if src.name.lower().startswith("inrol") else f"inrol_{src.name}"),
        description=" ".join(_DESCRIPTION.split()),
        imu_noise=IMU_NOISE,
        imu_rate_hz=round(1.0 / dt, 2),
        range_sigma=RANGE_SIGMA,
        tags=[TagMeta(name="tag0", lever_arm=list(LEVER_ARM))],
        truth=TruthMeta(lever_arm=list(LEVER_ARM)),
        source=f"{REPOSITORY} (commit {COMMIT}); {PAPER}",
        license="GPL-3.0 (data from the INRoL repository; see LICENSE and ATTRIBUTION.md)",
        extra=extra,
    )
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors, groundtruth=gt, meta=meta)
    return ImportResult(dataset=ds, changes=changes,
                        extra_files={"LICENSE": src / "LICENSE", "ATTRIBUTION.md": _attribution(src, changes)})


def _ids(col: pd.Series) -> list[str]:
    """Integer-valued ids as text ("3", not "3.0")."""
    v = col.to_numpy(float)
    if not np.all(v == np.round(v)):
        raise ValueError("anchor ids must be integers in INRoL files")
    return [str(int(x)) for x in v]


def import_dataset(src: Union[str, os.PathLike], dst: Union[str, os.PathLike], force: bool = False,
                   name: str | None = None, progress: Optional[ProgressFn] = None) -> ImportResult:
    """Convert ``src`` and write it to ``dst`` (atomic; refuses a non-empty ``dst`` unless ``force``).

    ``progress(stage, fraction)``, when given, is told of each stage (reading
    takes the first 60 %, writing and re-validating the rest).
    """
    report = progress or (lambda stage, frac: None)
    result = convert(src, name=name, progress=lambda stage, frac: report(stage, 0.6 * frac))
    report(f"writing and validating {dst}", 0.6)
    write_import(result, dst, force=force, src=src)
    report("done", 1.0)
    return result
