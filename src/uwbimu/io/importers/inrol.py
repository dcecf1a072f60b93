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
IMU->tag lever arm is (0, 0, 0.01) m (one rig for every sequence).  Rows that
are out of time order are sorted, and the change is reported.

Everything ``dataset.yaml`` says about the sequence is measured on the
sequence read, never carried over from another one: the IMU white-noise
densities (at rest over the first :data:`REST_S` s), the range error against
ground truth (``range_sigma``: overall robust sd, per-anchor medians and sds in
``extra.range_residuals``) and motion-capture glitches (``extra.groundtruth_glitches``).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Callable, Optional, Union

import numpy as np
import pandas as pd
import yaml

from uwbimu.io.check import MAD_TO_SIGMA, range_residuals, residual_stats
from uwbimu.io.dataset import Dataset, DatasetMeta, TagMeta, TruthMeta
from uwbimu.io.importers import ImportResult, read_text_table, require_files, sort_by_time, source_text, write_import
from uwbimu.io.importers.imu_noise import imu_noise_at_rest
from uwbimu.io.loader import DatasetError
from uwbimu.models.imu import ICM20948

NAME = "inrol"
SOURCE_FILES = ["imu.txt", "uwb.txt", "anchor.txt", "imu_pose.txt", "LICENSE"]
REPOSITORY = "https://github.com/INRoL/inrol_uwb_localization"
COMMIT = "40562b6fee3c72920b6f6972524990612a7f58b9"
PAPER = ('T. Kim, B. Yoon, D. J. Lee, "UWB-Based Localization System Considering Antenna Anisotropy '
         'and NLOS/Multipath Conditions", IROS 2024')

#: Documented IMU->tag lever arm (source filter: inv(T_cam_imu) inv(T_mocap_cam) T_mocap_tag), m.
#: One rig for every sequence of the repository.
LEVER_ARM = [0.0, 0.0, 0.01]

#: Seconds at the start over which the IMU white noise is measured (the rig stands still first).
REST_S = 4.0
#: Initial bias sd of the rig's IMU (our setting, not a measurement): gyro rad/s, accel m/s^2.
#: The source's filter values (accel 0.10, gyro 0.20) are tuning numbers, not densities.
BIAS_SIGMA0 = {"gyro_bias_sigma0": 0.005, "accel_bias_sigma0": 0.1}
#: A ground-truth sample farther than this [m] from the running median of
#: GLITCH_WINDOW samples is reported as a motion-capture glitch.
GLITCH_M = 0.05
GLITCH_WINDOW = 7

_DESCRIPTION = """\
INRoL UWB-IMU filtering sequence converted by `uwbimu import inrol`. Real UWB two-way ranging to
{n_anchors} fixed anchors and a ~{imu_hz:.0f} Hz IMU, with motion-capture ground truth of the IMU frame.
Clock: the source gives all streams one clock and documents no UWB/IMU time offset, so imu.csv,
uwb.csv and groundtruth.csv carry the source timestamps unchanged. Lever arm: the source's
documented IMU->tag lever arm (0, 0, 0.01) m is given both as the nominal tag lever arm and as
truth.lever_arm (the documented value the evaluation compares against, not an independent
measurement). Ground truth: {glitch} Ranges (measured by the importer against ground truth with that
lever arm): {ranges}; the source models direction-dependent bias and NLOS tails.
IMU noise: {imu_note}. Data license: GPL-3.0 (see LICENSE and ATTRIBUTION.md in this folder)."""


def gt_glitches(gt: pd.DataFrame) -> dict:
    """Ground-truth samples farther than :data:`GLITCH_M` from the running median of their neighbours.

    Returns ``{"threshold_m", "window", "count", "t", "offset_m"}`` (times and
    offsets of the flagged samples; a motion-capture glitch moves one or two
    samples by 0.1 m while the running median of 7 follows the motion).
    """
    p = gt[["px", "py", "pz"]]
    med = p.rolling(GLITCH_WINDOW, center=True, min_periods=1).median()
    d = np.linalg.norm((p - med).to_numpy(float), axis=1)
    k = np.flatnonzero(d > GLITCH_M)
    return {"threshold_m": GLITCH_M, "window": GLITCH_WINDOW, "count": int(len(k)),
            "t": [round(float(x), 6) for x in gt["t"].to_numpy()[k]], "offset_m": [round(float(x), 4) for x in d[k]]}


def _range_facts(ds: Dataset) -> tuple[Optional[float], dict, str]:
    """``(range_sigma, record, sentence)`` from this sequence's range residuals against ground truth."""
    res = range_residuals(ds, np.asarray(LEVER_ARM))
    if len(res) < 20:
        return None, {"n": int(len(res))}, "too few ranges covered by ground truth to measure their error"
    r = res["residual"].to_numpy(float)
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(r - np.median(r))))
    cm = math.ceil(round(sigma * 100.0, 6)) / 100.0
    st = residual_stats(res)
    record = {"n": int(len(r)), "robust_sigma_m": round(sigma, 4),
              "per_anchor_median_m": {a: round(float(v), 4) for a, v in st["median"].items()},
              "per_anchor_robust_sigma_m": {a: round(float(v), 4) for a, v in st["robust_sigma"].items()}}
    sentence = (f"per-anchor median residual {st['median'].min():+.2f}..{st['median'].max():+.2f} m, per-anchor "
                f"robust sd {st['robust_sigma'].min():.2f}-{st['robust_sigma'].max():.2f} m, overall robust sd "
                f"{sigma:.3f} m over {len(r)} ranges (range_sigma: rounded up to the centimetre, {cm:.2f} m)")
    return cm, record, sentence


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
    uwb = pd.DataFrame({"t": raw["timestamp"], "anchor": _ids(raw["anchor_id"], "uwb.txt"), "range": raw["r"]})

    raw = read_text_table(src / "anchor.txt", ["anchor_id", "tx", "ty", "tz", "qx", "qy", "qz", "qw"])
    # the documented antenna orientations (antenna frame -> world) go into anchors.csv's optional qw..qz
    anchors = pd.DataFrame({"anchor": _ids(raw["anchor_id"], "anchor.txt"), "x": raw["tx"], "y": raw["ty"], "z": raw["tz"],
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
    }
    param = src / "parameter.yaml"
    if param.is_file():
        try:
            pdoc = yaml.safe_load(source_text(param, what="parameter file")) or {}
            if isinstance(pdoc, dict) and isinstance(pdoc.get("sensor_noise"), dict):
                extra["source_sensor_noise_tuning"] = pdoc["sensor_noise"]
        except (yaml.YAMLError, DatasetError) as exc:
            changes.append(f"parameter.yaml could not be read ({str(exc).splitlines()[0]}); its tuning values "
                           "were not copied")

    dt = float(np.median(np.diff(imu["t"].to_numpy())))
    imu_noise, imu_note = imu_noise_at_rest(imu, ICM20948, REST_S, method="sd", preset_name="ICM-20948 class",
                                            **BIAS_SIGMA0)
    glitches = gt_glitches(gt)
    if glitches["count"]:
        ts = glitches["t"]
        glitch = (f"{glitches['count']} sample(s) lie more than {GLITCH_M * 100:g} cm off the running median of "
                  f"{GLITCH_WINDOW} (t = {', '.join(f'{x:.2f}' for x in ts[:5])}{' ...' if len(ts) > 5 else ''} s; "
                  f"up to {max(glitches['offset_m']):.2f} m; a motion-capture glitch): interpolate robustly.")
    else:
        glitch = f"no sample lies more than {GLITCH_M * 100:g} cm off the running median of {GLITCH_WINDOW}."
    meta = DatasetMeta(
        name=name or (src.name if src.name.lower().startswith("inrol") else f"inrol_{src.name}"),
        imu_noise=imu_noise,
        imu_rate_hz=round(1.0 / dt, 2),
        tags=[TagMeta(name="tag0", lever_arm=list(LEVER_ARM))],
        truth=TruthMeta(lever_arm=list(LEVER_ARM)),
        source=f"{REPOSITORY} (commit {COMMIT}); {PAPER}",
        license="GPL-3.0 (data from the INRoL repository; see LICENSE and ATTRIBUTION.md)",
        extra=extra,
    )
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors, groundtruth=gt, meta=meta)
    range_sigma, range_record, range_sentence = _range_facts(ds)
    extra.update(imu_noise_note=imu_note, groundtruth_glitches=glitches, range_residuals=range_record,
                 import_changes=list(changes))
    ds.meta = meta.model_copy(update={
        "range_sigma": range_sigma,
        "extra": extra,
        "description": " ".join(_DESCRIPTION.format(n_anchors=len(anchors), imu_hz=1.0 / dt, glitch=glitch,
                                                    ranges=range_sentence, imu_note=imu_note).split())})
    return ImportResult(dataset=ds, changes=changes,
                        extra_files={"LICENSE": src / "LICENSE", "ATTRIBUTION.md": _attribution(src, changes)})


def _ids(col: pd.Series, fname: str) -> list[str]:
    """Integer-valued ids as text ("3", not "3.0"); a fractional id is refused (file, line, column)."""
    v = col.to_numpy(float)
    frac = v != np.round(v)
    if frac.any():
        i = int(np.argmax(frac))
        raise DatasetError(f"{fname}, line {i + 2}, column 'anchor_id': anchor id '{v[i]}' is not an integer",
                           file=fname, row=i + 2, column="anchor_id")
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
