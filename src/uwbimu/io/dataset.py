"""In-memory dataset and its folder format (the public interface).

A dataset is a folder::

    imu.csv          t, ax, ay, az, wx, wy, wz     (IMU clock s; m/s^2; rad/s; IMU frame)
    uwb.csv          t, anchor, range [, tag]      (UWB clock s; anchor id text; m)
                     optional when tdoa.csv exists
    tdoa.csv         t, anchor_a, anchor_b, tdoa [, tag]  (optional; UWB clock s; m,
                     tdoa = |p_U - p_b| - |p_U - p_a|)
    anchors.csv      anchor, x, y, z [, qw, qx, qy, qz]  (world frame, m; optional
                     antenna orientation, antenna frame -> world)
    anchor_ranges.csv  anchor_a, anchor_b, range   (optional; measured inter-anchor ranges, m)
    groundtruth.csv  t, px, py, pz, qw, qx, qy, qz [, vx, vy, vz]   (optional; UWB clock,
                     pose of the IMU frame in the world)
    dataset.yaml     optional metadata (:class:`DatasetMeta`)

Each table may be given as ``.parquet`` instead of ``.csv``.  Reading (with
validation) is :func:`uwbimu.io.loader.load_dataset`; writing is
:func:`write_dataset`, which writes atomically and never overwrites a folder
that already holds a dataset unless asked to.
"""

from __future__ import annotations

from uwbimu.errors import UsageError
import os
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
import pandas as pd
import yaml
from pydantic import BaseModel, ConfigDict, Field, model_validator

from uwbimu.models.imu import ImuNoise

IMU_COLUMNS = ["t", "ax", "ay", "az", "wx", "wy", "wz"]
UWB_COLUMNS = ["t", "anchor", "range"]
ANCHOR_COLUMNS = ["anchor", "x", "y", "z"]
ANCHOR_QUAT_COLUMNS = ["qw", "qx", "qy", "qz"]
TDOA_COLUMNS = ["t", "anchor_a", "anchor_b", "tdoa"]
ANCHOR_RANGE_COLUMNS = ["anchor_a", "anchor_b", "range"]
GT_COLUMNS = ["t", "px", "py", "pz", "qw", "qx", "qy", "qz"]
GT_VEL_COLUMNS = ["vx", "vy", "vz"]
TABLES = ("imu", "uwb", "tdoa", "anchors", "anchor_ranges", "groundtruth")


#: dataset.yaml holds finite numbers only (a NaN lever arm would silently disable every range).
_META_CONFIG = ConfigDict(extra="forbid", allow_inf_nan=False)


class TagMeta(BaseModel):
    """A UWB tag on the vehicle with its nominal lever arm (IMU frame, m)."""

    model_config = _META_CONFIG
    name: str = "tag0"
    lever_arm: Optional[list[float]] = Field(default=None, min_length=3, max_length=3)


class TruthMeta(BaseModel):
    """True calibration, when known (simulation), used only for evaluation."""

    model_config = _META_CONFIG
    lever_arm: Optional[list[float]] = Field(default=None, min_length=3, max_length=3)
    time_offset: Optional[float] = None
    anchor_bias: Optional[dict[str, float]] = None
    tags: Optional[dict[str, list[float]]] = None  # per-tag true lever arms


class DatasetMeta(BaseModel):
    """Contents of ``dataset.yaml``.

    ``tags``: when the file lists them, every ``tag`` of uwb.csv / tdoa.csv must be one of their names
    (checked by :func:`uwbimu.io.loader.load_dataset`, as are the ids of ``known_anchor_bias`` against
    anchors.csv).
    """

    model_config = _META_CONFIG
    name: str = "unnamed"
    description: str = ""
    imu_noise: Optional[ImuNoise] = None
    imu_rate_hz: Optional[float] = None
    range_sigma: Optional[float] = Field(default=None, gt=0, description="UWB range noise sd, m")
    tags: list[TagMeta] = Field(default_factory=lambda: [TagMeta()])
    truth: Optional[TruthMeta] = None
    known_anchor_bias: Optional[dict[str, float]] = None  # documented constant biases (subtract)
    source: Optional[str] = None
    license: Optional[str] = None
    anchor_frame_up: Optional[Literal["+z", "-z"]] = Field(
        default=None,
        description="which way the anchors' frame z axis points: '+z' (up, the convention) or '-z' "
        "(z down, e.g. ISAS-Walk's RTLS frame); None = '+z'. Every verb applies it.",
    )
    single_clock: Optional[bool] = Field(
        default=None,
        description="true when every stream (IMU, UWB, ground truth) was stamped by one clock "
        "(e.g. a Crazyflie uSD log): there is no UWB-IMU clock to drift or jump, so the clock-fault "
        "check reports nothing and corrects nothing. None = not known.",
    )
    extra: dict = Field(default_factory=dict)

    @model_validator(mode="after")
    def _unique_tags(self) -> "DatasetMeta":
        names = [t.name for t in self.tags]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"tag name(s) {', '.join(repr(n) for n in dup)} appear more than once in tags")
        return self

    @model_validator(mode="after")
    def _legacy_anchor_frame_up(self) -> "DatasetMeta":
        # Datasets written before anchor_frame_up was a field keep it under extra.
        legacy = self.extra.get("anchor_frame_up")
        if legacy is not None:
            if legacy not in ("+z", "-z"):
                raise ValueError(f"extra.anchor_frame_up must be '+z' or '-z', got {legacy!r}")
            if self.anchor_frame_up is None:
                self.anchor_frame_up = legacy
            elif self.anchor_frame_up != legacy:
                raise ValueError(f"anchor_frame_up {self.anchor_frame_up!r} contradicts "
                                 f"extra.anchor_frame_up {legacy!r}")
        return self


@dataclass
class Dataset:
    """One recorded or simulated sequence.

    Attributes
    ----------
    imu : DataFrame with columns ``IMU_COLUMNS`` (IMU clock).
    uwb : DataFrame with ``t, anchor, range`` and optionally ``tag`` (UWB clock); empty
        (same columns) when the dataset holds only TDoA.
    anchors : DataFrame ``anchor, x, y, z`` (world frame), plus ``qw, qx, qy, qz``
        (antenna frame -> world, unit Hamilton quaternion) when the file gives them.
    groundtruth : optional DataFrame ``GT_COLUMNS`` (+ velocity) on the UWB clock.
    tdoa : optional DataFrame ``t, anchor_a, anchor_b, tdoa`` (+ ``tag``), UWB clock,
        ``tdoa = |p_U - p_b| - |p_U - p_a|`` in m.
    anchor_ranges : optional DataFrame ``anchor_a, anchor_b, range`` (m), measured
        anchor-to-anchor ranges.
    meta : :class:`DatasetMeta`.
    path : folder it was read from, if any.
    report : load report (rows read/kept, repairs) when read by ``load_dataset``.
    """

    imu: pd.DataFrame
    uwb: pd.DataFrame
    anchors: pd.DataFrame
    groundtruth: Optional[pd.DataFrame] = None
    meta: DatasetMeta = field(default_factory=DatasetMeta)
    path: Optional[Path] = None
    #: :class:`uwbimu.io.loader.LoadReport` when read by ``load_dataset`` (rows, repairs).
    report: Optional[Any] = field(default=None, repr=False, compare=False)
    tdoa: Optional[pd.DataFrame] = None
    anchor_ranges: Optional[pd.DataFrame] = None

    # --- convenient array views -------------------------------------------
    @property
    def imu_t(self) -> np.ndarray:
        return self.imu["t"].to_numpy(float)

    @property
    def imu_u(self) -> np.ndarray:
        """(N, 6) ``[ax, ay, az, wx, wy, wz]``."""
        return self.imu[IMU_COLUMNS[1:]].to_numpy(float)

    def anchor_positions(self) -> dict[str, np.ndarray]:
        """Map anchor id -> (3,) world position."""
        return {
            str(r.anchor): np.array([r.x, r.y, r.z], dtype=float)
            for r in self.anchors.itertuples(index=False)
        }

    def anchor_array(self, ids) -> np.ndarray:
        """(M, 3) positions for a sequence of anchor ids."""
        pos = self.anchor_positions()
        return np.array([pos[str(i)] for i in ids])

    @property
    def anchor_frame_up(self) -> str:
        """``"+z"`` or ``"-z"``: the anchors' frame up axis (``meta.anchor_frame_up``, default +z)."""
        return self.meta.anchor_frame_up or "+z"

    @property
    def duration(self) -> float:
        return float(self.imu_t[-1] - self.imu_t[0]) if len(self.imu) else 0.0


def _write_table(df: pd.DataFrame, path: Path) -> None:
    if path.suffix == ".parquet":
        from uwbimu.optional import require

        require("pyarrow", "parquet", f"writing {path.name}")
        df.to_parquet(path, index=False)
    else:
        df.to_csv(path, index=False)


def write_dataset(ds: Dataset, folder: str | os.PathLike, overwrite: bool = False, fmt: str = "csv") -> Path:
    """Write ``ds`` to ``folder`` in the dataset format, atomically.

    Tables go to a temporary sibling folder that is renamed into place, so a
    crash never leaves a half-written dataset.  An existing non-empty folder is
    refused unless ``overwrite`` is true (it is then replaced as a whole).
    """
    folder = Path(folder)
    if fmt not in ("csv", "parquet"):
        raise UsageError(f"fmt must be 'csv' or 'parquet', got {fmt!r}")
    if folder.exists() and any(folder.iterdir()):
        if not overwrite:
            raise FileExistsError(
                f"{folder} exists and is not empty; refusing to overwrite (pass overwrite=True / --force)"
            )
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", dir=folder.parent))
    try:
        _write_table(ds.imu[IMU_COLUMNS], tmp / f"imu.{fmt}")
        uwb_cols = UWB_COLUMNS + (["tag"] if "tag" in ds.uwb.columns else [])
        if len(ds.uwb) or ds.tdoa is None:
            _write_table(ds.uwb[uwb_cols], tmp / f"uwb.{fmt}")
        if ds.tdoa is not None:
            tdoa_cols = TDOA_COLUMNS + (["tag"] if "tag" in ds.tdoa.columns else [])
            _write_table(ds.tdoa[tdoa_cols], tmp / f"tdoa.{fmt}")
        anchor_cols = ANCHOR_COLUMNS + (ANCHOR_QUAT_COLUMNS if set(ANCHOR_QUAT_COLUMNS) <= set(ds.anchors.columns)
                                        else []) + [c for c in ("surveyed",) if c in ds.anchors.columns]
        _write_table(ds.anchors[anchor_cols], tmp / f"anchors.{fmt}")
        if ds.anchor_ranges is not None:
            _write_table(ds.anchor_ranges[ANCHOR_RANGE_COLUMNS + [c for c in ("sd",) if c in ds.anchor_ranges.columns]],
                         tmp / f"anchor_ranges.{fmt}")
        if ds.groundtruth is not None:
            cols = [c for c in GT_COLUMNS if c in ds.groundtruth.columns]  # attitude optional (position-only)
            cols += [c for c in GT_VEL_COLUMNS if c in ds.groundtruth.columns]
            _write_table(ds.groundtruth[cols], tmp / f"groundtruth.{fmt}")
        with open(tmp / "dataset.yaml", "w") as fh:
            yaml.safe_dump(ds.meta.model_dump(exclude_none=True), fh, sort_keys=False)
        if folder.exists():
            backup = folder.with_name(f".{folder.name}.old")
            if backup.exists():
                shutil.rmtree(backup)
            folder.rename(backup)
            tmp.rename(folder)
            shutil.rmtree(backup)
        else:
            tmp.rename(folder)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return folder
