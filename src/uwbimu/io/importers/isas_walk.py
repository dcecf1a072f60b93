"""Importer for the KIT-ISAS ISAS-Walk sequences (SFUISE, CSV conversion of the ROS1 bag).

Source folder (see ``shared/datasets/isas_walk/README.md``)::

    imu.csv               t_header_s, t_bag_s, ax_mps2.., gx_radps.., q*_ahrs
    uwb_ranges.csv        t_header_s, t_bag_s, t_module_ms, anchor_id, range_m, ra_valid, ...
    anchors.csv           anchor_id, x_m, y_m, z_m           (UWB frame)
    groundtruth_vive.csv  t_header_s, t_bag_s, x_m, y_m, z_m, qx, qy, qz, qw   (optional; Vive frame)
    LICENSE               GPL-3.0 (copied next to the imported data)

What the conversion does (every choice is recorded in ``dataset.yaml``):

* Time: ROS header stamps of all streams (host clock), shifted by one common
  origin ``t0`` (the earliest stamp of the three streams; stored in
  ``extra.time_origin_unix_s``) so that times are small numbers.
* Ranges: only fresh ranges (``ra_valid == 1``) are kept, as SFUISE does; the
  count of dropped stale/failed rows is recorded.  Ranges are kept as
  measured.  The documented per-anchor offsets ``toa_offset`` enter SFUISE as
  ``range ≈ true_distance − toa_offset``; we store them as
  ``known_anchor_bias`` with our sign convention ``measured = true + bias``,
  i.e. ``bias = −toa_offset`` (+0.070, −0.154, +0.075, −0.141, +0.025 m for
  anchors 7475, 9524, 10548, 15155, 20276).  An estimator subtracts them.
* Lever arm: SFUISE's fixed setting ``offset = [0.10, −0.025, 0.0]`` m (tag in
  the IMU frame) → ``tags[0].lever_arm`` and ``truth.lever_arm``.  It is a
  configured value, not a measured truth.
* Ground truth: the Vive tracker pose in the Vive reference frame.  Neither
  the Vive→UWB-frame transform nor the tracker→IMU transform is documented,
  so the ``groundtruth.csv`` written here is **not** the IMU pose in the
  anchors' frame: evaluate with ``uwbimu evaluate OUT --groundtruth
  DST/groundtruth.csv --align se3`` and read the result as an upper bound
  (it includes the unknown tracker↔IMU lever arm).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Optional, Union

import numpy as np
import pandas as pd

from uwbimu.io.dataset import ANCHOR_COLUMNS, GT_COLUMNS, IMU_COLUMNS, Dataset, DatasetMeta, TagMeta, TruthMeta
from uwbimu.io.importers import ImportResult, read_csv_source, require_files, write_import
from uwbimu.io.importers.imu_noise import imu_noise_at_rest
from uwbimu.io.loader import DatasetError
from uwbimu.models.imu import ICM20948

__all__ = ["convert", "import_dataset", "TOA_OFFSET", "LEVER_ARM", "SOURCE_FILES", "RECOMMENDED_CONFIG"]

#: SFUISE ``toa_offset`` (config_test_isas-walk1.yaml; the walk2/3 configs hold the same values), by anchor id
#: (ascending-id order), m.
TOA_OFFSET = {"7475": -0.0700, "9524": 0.1539, "10548": -0.0751, "15155": 0.1409, "20276": -0.0247}
#: SFUISE ``offset``: tag position in the IMU/body frame, m (a fixed setting).
LEVER_ARM = [0.10, -0.025, 0.0]

SOURCE_FILES = {
    "imu": ("imu.csv", ["t_header_s", "ax_mps2", "ay_mps2", "az_mps2", "gx_radps", "gy_radps", "gz_radps"]),
    "uwb": ("uwb_ranges.csv", ["t_header_s", "anchor_id", "range_m", "ra_valid"]),
    "anchors": ("anchors.csv", ["anchor_id", "x_m", "y_m", "z_m"]),
    "groundtruth": ("groundtruth_vive.csv", ["t_header_s", "x_m", "y_m", "z_m", "qx", "qy", "qz", "qw"]),
}

_DESCRIPTION = (
    "ISAS-Walk (KIT-ISAS, SFUISE): walking sequence, UWB TWR to 5 anchors + Waveshare Sense HAT (B) IMU, "
    "HTC Vive ground truth. Ranges: only fresh (ra_valid==1), raw values; documented per-anchor offsets in "
    "known_anchor_bias (measured = true + bias). GROUND TRUTH IS THE VIVE TRACKER POSE IN THE VIVE FRAME, "
    "not the IMU pose in the anchors' frame: evaluate with --align se3 (tracker-to-IMU offset undocumented). "
    "Lever arm [0.10, -0.025, 0.0] m is SFUISE's fixed setting, not a measured truth. "
    "THE ANCHORS' FRAME OF THE ISAS RTLS SET-UP IS Z-DOWN (found on ISAS-Walk1, whose at-rest specific force "
    "mapped into it is about (0.46, 0.76, -9.94) m/s^2; the source documents no transform): estimate with "
    "anchor_frame_up: -z, e.g. --config examples/estimator_isas.yaml."
)
#: Where the estimator preset for this sequence lives (repository-relative).
RECOMMENDED_CONFIG = "examples/estimator_isas.yaml"


def sequence_number(src: Path) -> tuple[Optional[int], str]:
    """``(N, where)`` of ISAS-Walk N named by the input (None when the input names none).

    Looks at the first line of the folder's ``README.md`` / ``ATTRIBUTION.md``
    (``# ISAS-Walk2 ...``), then at the folder name (``isas_walk2``, ``ISAS-Walk-2``).
    """
    for doc in ("README.md", "ATTRIBUTION.md"):
        f = src / doc
        if f.is_file():
            first = f.read_bytes()[:200].decode("utf-8", errors="replace").split("\n", 1)[0]
            m = re.search(r"ISAS[-_ ]?Walk[-_ ]?(\d+)", first, re.IGNORECASE)
            if m:
                return int(m.group(1)), f"{doc}'s title"
    m = re.search(r"walk[-_ ]?(\d+)", src.resolve().name, re.IGNORECASE)
    if m:
        return int(m.group(1)), "the folder name"
    return None, "not named by the input (no ISAS-WalkN in README.md / ATTRIBUTION.md or the folder name)"


def _read_csv(path: Path, required: list[str]) -> pd.DataFrame:
    """Read one source CSV; errors name the file, line and column."""
    df = read_csv_source(path)  # UTF-8, every line complete (a cut-short last line is refused)
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DatasetError(
            f"{path.name}, line 1: missing column(s) {', '.join(missing)}; the header has {', '.join(map(str, df.columns))}",
            file=path.name, row=1, column=missing[0],
        )
    if len(df) == 0:
        raise DatasetError(f"{path.name}: header but no data rows", file=path.name)
    out = pd.DataFrame(index=df.index)
    for c in required:
        if c == "anchor_id":
            out[c] = df[c].str.strip()
            empty = out[c].isna() | (out[c] == "")
            if empty.any():
                i = int(np.argmax(empty.to_numpy()))
                raise DatasetError(f"{path.name}, line {i + 2}, column '{c}': empty anchor id", file=path.name,
                                   row=i + 2, column=c)
            continue
        vals = pd.to_numeric(df[c], errors="coerce")
        bad = vals.isna() | ~np.isfinite(vals.to_numpy(float))
        if bad.any():
            i = int(np.argmax(bad.to_numpy()))
            raise DatasetError(f"{path.name}, line {i + 2}, column '{c}': not a finite number ('{df[c].iloc[i]}')",
                               file=path.name, row=i + 2, column=c)
        out[c] = vals.astype(float)
    return out


#: Length of the stationary start used to measure the IMU white noise [s].
REST_S = 3.0


def _imu_noise_at_rest(imu: pd.DataFrame) -> tuple:
    """White-noise densities measured over the stationary start (Welch, 0.5-5 Hz); bias terms of the ICM-20948.

    The board low-pass filters, so ``sd * sqrt(dt)`` would understate the
    in-band density ~3x (:func:`uwbimu.io.importers.imu_noise.density_welch`).
    """
    return imu_noise_at_rest(imu, ICM20948, REST_S, method="welch", preset_name="ICM-20948")


def convert(src: Union[str, os.PathLike], with_groundtruth: bool = True) -> ImportResult:
    """Convert an ISAS-Walk CSV folder to a :class:`Dataset` (not written).

    Parameters
    ----------
    src : folder with ``imu.csv``, ``uwb_ranges.csv``, ``anchors.csv`` and
        optionally ``groundtruth_vive.csv`` (+ ``LICENSE``, ``README.md``).
    with_groundtruth : include the Vive ground truth when present.

    Returns
    -------
    ImportResult with the dataset, the licence/readme to copy and the list of changes.
    """
    src = Path(src)
    require_files(src, [SOURCE_FILES[k][0] for k in ("imu", "uwb", "anchors")])
    changes: list[str] = []
    imu_raw = _read_csv(src / SOURCE_FILES["imu"][0], SOURCE_FILES["imu"][1])
    uwb_raw = _read_csv(src / SOURCE_FILES["uwb"][0], SOURCE_FILES["uwb"][1])
    anc_raw = _read_csv(src / SOURCE_FILES["anchors"][0], SOURCE_FILES["anchors"][1])
    gt_file = src / SOURCE_FILES["groundtruth"][0]
    gt_raw = _read_csv(gt_file, SOURCE_FILES["groundtruth"][1]) if (with_groundtruth and gt_file.is_file()) else None
    if with_groundtruth and gt_raw is None:
        changes.append(f"{gt_file.name} not found: imported without ground truth")

    # -- ranges: fresh only, as SFUISE does
    valid = uwb_raw["ra_valid"].to_numpy() == 1
    n_stale = int((~valid).sum())
    changes.append(
        f"uwb_ranges.csv: kept {int(valid.sum())} fresh ranges (ra_valid==1), dropped {n_stale} stale/failed "
        f"(ra_valid!=1) of {len(uwb_raw)}"
    )
    uwb_raw = uwb_raw[valid]

    streams = [imu_raw["t_header_s"], uwb_raw["t_header_s"]] + ([gt_raw["t_header_s"]] if gt_raw is not None else [])
    t0 = float(min(s.min() for s in streams))
    t0 = float(np.floor(t0))  # whole second: keeps the µs digits of every stamp exact

    imu = pd.DataFrame(
        {
            "t": imu_raw["t_header_s"].to_numpy() - t0,
            "ax": imu_raw["ax_mps2"].to_numpy(),
            "ay": imu_raw["ay_mps2"].to_numpy(),
            "az": imu_raw["az_mps2"].to_numpy(),
            "wx": imu_raw["gx_radps"].to_numpy(),
            "wy": imu_raw["gy_radps"].to_numpy(),
            "wz": imu_raw["gz_radps"].to_numpy(),
        }
    )[IMU_COLUMNS]
    uwb = pd.DataFrame(
        {
            "t": uwb_raw["t_header_s"].to_numpy() - t0,
            "anchor": uwb_raw["anchor_id"].astype(str).to_numpy(),
            "range": uwb_raw["range_m"].to_numpy(),
        }
    )
    # stable order: time, then anchor id, so that one epoch's ranges stay together
    uwb = uwb.sort_values(["t", "anchor"], kind="stable").reset_index(drop=True)
    imu = imu.sort_values("t", kind="stable").reset_index(drop=True)
    anchors = pd.DataFrame(
        {"anchor": anc_raw["anchor_id"].astype(str), "x": anc_raw["x_m"], "y": anc_raw["y_m"], "z": anc_raw["z_m"]}
    )[ANCHOR_COLUMNS]

    unknown = sorted(set(uwb["anchor"]) - set(anchors["anchor"]))
    if unknown:
        raise DatasetError(f"uwb_ranges.csv, column 'anchor_id': anchors {unknown} are not in anchors.csv "
                           f"({', '.join(map(str, sorted(anchors['anchor'])))})", file="uwb_ranges.csv", column="anchor_id")
    missing_bias = sorted(set(anchors["anchor"]) - set(TOA_OFFSET))
    if missing_bias:
        changes.append(f"anchors without a documented toa_offset (no known bias): {missing_bias}")
    known_bias = {a: -TOA_OFFSET[a] for a in sorted(anchors["anchor"], key=lambda a: (len(a), a)) if a in TOA_OFFSET}

    gt = None
    if gt_raw is not None:
        gt = pd.DataFrame(
            {
                "t": gt_raw["t_header_s"].to_numpy() - t0,
                "px": gt_raw["x_m"].to_numpy(),
                "py": gt_raw["y_m"].to_numpy(),
                "pz": gt_raw["z_m"].to_numpy(),
                "qw": gt_raw["qw"].to_numpy(),
                "qx": gt_raw["qx"].to_numpy(),
                "qy": gt_raw["qy"].to_numpy(),
                "qz": gt_raw["qz"].to_numpy(),
            }
        )[GT_COLUMNS].sort_values("t", kind="stable").reset_index(drop=True)
        changes.append("groundtruth_vive.csv: Vive tracker pose in the Vive frame written as groundtruth.csv "
                       "(not the IMU pose in the anchors' frame; evaluate with --align se3)")

    seq, seq_where = sequence_number(src)
    label = f"ISAS-Walk{seq}" if seq is not None else "ISAS-Walk (sequence unknown)"
    changes.append(f"sequence: {label} ({seq_where})")
    dt = np.diff(imu["t"].to_numpy())
    rate = float(1.0 / np.median(dt)) if len(dt) else None
    imu_noise, noise_note = _imu_noise_at_rest(imu)
    changes.append(f"imu noise: {noise_note}")
    changes.append(f"the anchors' frame is z-down (recorded as anchor_frame_up: -z in dataset.yaml): estimate with "
                   f"--config {RECOMMENDED_CONFIG}")
    meta = DatasetMeta(
        name=f"isas-walk:{src.name}",
        description=_DESCRIPTION,
        imu_noise=imu_noise,
        imu_rate_hz=rate,
        range_sigma=0.10,
        tags=[TagMeta(name="tag0", lever_arm=list(LEVER_ARM))],
        truth=TruthMeta(lever_arm=list(LEVER_ARM)),
        known_anchor_bias=known_bias,
        source="https://github.com/KIT-ISAS/SFUISE @ 75bf5a32f1a8e5c3046a5bd1a1ddf659fa996f7d, "
        + (f"dataset/ISAS-Walk{seq}.bag" if seq is not None else "an ISAS-Walk bag (sequence not named by the input)")
        + " (CSV conversion); calibration from sfuise/config/config_test_isas-walk"
        + (f"{seq}.yaml" if seq is not None else "N.yaml (identical for walk1-3)"),
        license="GPL-3.0 (see LICENSE next to this file; K. Li, Z. Cao, U. D. Hanebeck, 'Continuous-Time "
        "Ultra-Wideband-Inertial Fusion', IEEE RA-L 8(7), 2023)",
        extra={
            "importer": "uwbimu.io.importers.isas_walk",
            "sequence": label,
            "sequence_named_by": seq_where,
            "time_origin_unix_s": t0,
            "time_source": "ROS header stamps (host clock) of every stream, minus time_origin_unix_s",
            "known_anchor_bias_convention": "measured = true + bias; bias = -toa_offset of SFUISE",
            "sfuise_toa_offset": dict(TOA_OFFSET),
            "lever_arm_note": "SFUISE fixed setting 'offset' (tag in IMU frame), not estimated or measured by the "
            "source; truth.lever_arm repeats it for comparison only",
            "groundtruth_frame": "vive/reference (no documented transform to the UWB/anchor frame)",
            "groundtruth_body": "vive/tracker_1 (tracker-to-IMU transform undocumented)",
            "groundtruth_align": "se3",
            "groundtruth_attitude_comparable": False,
            "imu_noise_note": noise_note + "; range_sigma 0.10 m is our choice, not documented",
            "sfuise_imu_weights": {"accel": 7.85, "gyro": 27.6, "accel_bias": 515, "gyro_bias": 2951,
                                   "note": "inverse variances of SFUISE's spline residuals (not sensor densities)"},
            "ranges_dropped_stale": n_stale,
            "uwb_time_offset_note": "not documented (all stamps from the recording host)",
            "anchor_frame_note": "the ISAS RTLS anchors' frame has z pointing down (found on ISAS-Walk1: the "
            "at-rest specific force mapped into it is about (0.46, 0.76, -9.94) m/s^2); the source documents no "
            "transform; the ESKF option anchor_frame_up: -z handles it",
            "recommended_config": RECOMMENDED_CONFIG,
        },
        anchor_frame_up="-z",
    )
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors, groundtruth=gt, meta=meta)
    extra_files: dict = {}
    if (src / "LICENSE").is_file():
        extra_files["LICENSE"] = src / "LICENSE"
    else:
        changes.append("no LICENSE file in the source folder: the GPL-3.0 text must be kept with the data")
    if (src / "README.md").is_file():
        extra_files["SOURCE_README.md"] = src / "README.md"
    return ImportResult(dataset=ds, extra_files=extra_files, changes=changes)


def import_dataset(
    src: Union[str, os.PathLike],
    dst: Union[str, os.PathLike],
    force: bool = False,
    with_groundtruth: bool = True,
) -> ImportResult:
    """Convert ``src`` and write it to ``dst`` (refuses a non-empty ``dst`` unless ``force``)."""
    res = convert(src, with_groundtruth=with_groundtruth)
    write_import(res, dst, force=force, src=src)
    return res
