"""Generator of corrupted datasets and output-folder cases for tests/test_fuzz_*.py (no committed data).

``base_dataset(folder)`` writes a small valid dataset (10 s, IMU 200 Hz, 4 anchors at
10 Hz, ground truth).  ``DATASET_CASES`` maps a case name to ``(corrupt(folder),
expected, detail)``: ``expected`` is ``"refused"`` (detail: the file the refusal must
name), or ``"warned"`` (detail: the structured warning code, or ``"repair"``), and
the case may add loader options as CLI flags (``flags``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd
import yaml

from uwbimu.io.dataset import Dataset, DatasetMeta, write_dataset

ANCHORS = np.array([[0.0, 0.0, 0.5], [6.0, 0.0, 2.5], [6.0, 5.0, 0.8], [0.0, 5.0, 2.8]])


def base_dataset(folder: Path, duration: float = 10.0, imu_rate: float = 200.0) -> Path:
    """A small valid dataset: a slow circle with a yaw rotation, ranges and ground truth."""
    t = np.arange(0.0, duration, 1.0 / imu_rate)
    w = 0.5
    rng = np.random.default_rng(0)
    imu = pd.DataFrame({"t": t, "ax": 0.02 * rng.standard_normal(len(t)), "ay": -0.5 * w * np.ones(len(t)) * 0.2,
                        "az": 9.81 + 0.02 * rng.standard_normal(len(t)), "wx": 0.0, "wy": 0.0,
                        "wz": w + 0.001 * rng.standard_normal(len(t))})
    tg = np.arange(0.0, duration, 0.01)
    p = np.c_[3 + np.cos(w * tg), 2.5 + np.sin(w * tg), 1.2 + 0 * tg]
    q = np.c_[np.cos(w * tg / 2), 0 * tg, 0 * tg, np.sin(w * tg / 2)]
    gt = pd.DataFrame(np.c_[tg, p, q], columns=["t", "px", "py", "pz", "qw", "qx", "qy", "qz"])
    tu = np.arange(0.05, duration - 0.05, 0.1)
    rows = []
    for ti in tu:
        pi = np.array([np.interp(ti, tg, p[:, k]) for k in range(3)])
        for j, a in enumerate(ANCHORS):
            rows.append((ti, f"A{j}", float(np.linalg.norm(a - pi) + 0.03 * rng.standard_normal())))
    uwb = pd.DataFrame(rows, columns=["t", "anchor", "range"])
    anchors = pd.DataFrame({"anchor": [f"A{j}" for j in range(4)], "x": ANCHORS[:, 0], "y": ANCHORS[:, 1],
                            "z": ANCHORS[:, 2]})
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors, groundtruth=gt, meta=DatasetMeta(name="fuzz-base"))
    return write_dataset(ds, folder)


# --- editing helpers ------------------------------------------------------------
def _edit(name: str, fn: Callable[[pd.DataFrame], pd.DataFrame]):
    def corrupt(folder: Path) -> None:
        df = pd.read_csv(folder / name, dtype={"anchor": str, "anchor_a": str, "anchor_b": str})
        fn(df).to_csv(folder / name, index=False)
    return corrupt


def _cell(name: str, row: int, col: str, value):
    def fn(df):
        df = df.copy()
        if isinstance(value, str):
            df[col] = df[col].astype(object)
        df.loc[row, col] = value
        return df
    return _edit(name, fn)


def _text(name: str, text: str):
    def corrupt(folder: Path) -> None:
        (folder / name).write_text(text)
    return corrupt


def _append_line(name: str, line: str, at: int):
    def corrupt(folder: Path) -> None:
        lines = (folder / name).read_text().splitlines()
        lines.insert(at, line)
        (folder / name).write_text("\n".join(lines) + "\n")
    return corrupt


def _remove(name: str):
    def corrupt(folder: Path) -> None:
        (folder / name).unlink()
    return corrupt


def _yaml(data):
    def corrupt(folder: Path) -> None:
        (folder / "dataset.yaml").write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return corrupt


def _anchors(pos):
    def corrupt(folder: Path) -> None:
        pos_ = np.asarray(pos, float)
        pd.DataFrame({"anchor": [f"A{j}" for j in range(len(pos_))], "x": pos_[:, 0], "y": pos_[:, 1],
                      "z": pos_[:, 2]}).to_csv(folder / "anchors.csv", index=False)
    return corrupt


def _tdoa(rows):
    def corrupt(folder: Path) -> None:
        pd.DataFrame(rows, columns=["t", "anchor_a", "anchor_b", "tdoa"]).to_csv(folder / "tdoa.csv", index=False)
    return corrupt


def _scale_t(name: str, factor: float = 1.0, offset: float = 0.0):
    return _edit(name, lambda df: df.assign(t=df["t"] * factor + offset))


def _subsample(name: str, step: int):
    return _edit(name, lambda df: df.iloc[::step].reset_index(drop=True))


def _swap_rows(name: str, i: int, j: int):
    def fn(df):
        idx = list(range(len(df)))
        idx[i], idx[j] = idx[j], idx[i]
        return df.iloc[idx].reset_index(drop=True)
    return _edit(name, fn)


def _clock_back(name: str, at: float, size: float):
    return _edit(name, lambda df: df.assign(t=np.where(df["t"] >= at, df["t"] - size, df["t"])))


def _dup_row(name: str, i: int):
    return _edit(name, lambda df: pd.concat([df.iloc[: i + 1], df.iloc[i: i + 1], df.iloc[i + 1:]])
                 .reset_index(drop=True))


def _both(*fns):
    def corrupt(folder: Path) -> None:
        for f in fns:
            f(folder)
    return corrupt


@dataclass
class Case:
    corrupt: Callable[[Path], None]
    expected: str  # "refused" | "warned"
    detail: str  # refused: file named by the error; warned: warning code or "repair"
    flags: list[str] = field(default_factory=list)


_coplanar = [[0, 0, 2.0], [6, 0, 2.0], [6, 5, 2.0], [0, 5, 2.0]]
DATASET_CASES: dict[str, Case] = {
    # time base and units
    "imu_t_ns": Case(_scale_t("imu.csv", 1e9), "refused", "imu.csv"),
    "imu_t_ms": Case(_scale_t("imu.csv", 1e3), "refused", "imu.csv"),
    "imu_t_us": Case(_scale_t("imu.csv", 1e6), "refused", "imu.csv"),
    "gt_t_ms": Case(_scale_t("groundtruth.csv", 1e3), "refused", "groundtruth.csv"),
    "uwb_t_ms": Case(_scale_t("uwb.csv", 1e3), "refused", "uwb.csv"),
    "uwb_t_epoch": Case(_scale_t("uwb.csv", 1.0, 1.6e9), "refused", "uwb.csv"),
    "gt_t_epoch": Case(_scale_t("groundtruth.csv", 1.0, 1.7e9), "refused", "groundtruth.csv"),
    "uwb_no_overlap": Case(_scale_t("uwb.csv", 1.0, 100.0), "refused", "uwb.csv"),
    "imu_5hz": Case(_subsample("imu.csv", 40), "refused", "imu.csv"),
    "imu_one_row": Case(_edit("imu.csv", lambda df: df.iloc[:1]), "refused", "imu.csv"),
    "imu_huge_gap": Case(_cell("imu.csv", 1999, "t", 5e7), "refused", "imu.csv"),
    "imu_backwards": Case(_swap_rows("imu.csv", 100, 101), "refused", "imu.csv"),
    "uwb_clock_jump_back": Case(_clock_back("uwb.csv", 6.0, 3.0), "refused", "uwb.csv"),
    "imu_duplicate_row": Case(_dup_row("imu.csv", 50), "refused", "imu.csv"),
    "uwb_duplicate_row": Case(_dup_row("uwb.csv", 50), "refused", "uwb.csv"),
    # physics and units of values
    "accel_1e30": Case(_cell("imu.csv", 500, "ax", 1e30), "refused", "imu.csv"),
    "gyro_1e3": Case(_cell("imu.csv", 500, "wz", 1e3), "refused", "imu.csv"),
    "accel_in_g": Case(_edit("imu.csv", lambda df: df.assign(ax=df.ax / 9.81, ay=df.ay / 9.81, az=df.az / 9.81)),
                       "refused", "imu.csv"),
    "gravity_removed": Case(_edit("imu.csv", lambda df: df.assign(az=df.az - 9.81)), "refused", "imu.csv"),
    "accel_in_mg": Case(_edit("imu.csv", lambda df: df.assign(ax=df.ax * 102, ay=df.ay * 102, az=df.az * 102)),
                        "refused", "imu.csv"),
    "gyro_in_deg_fast": Case(_edit("imu.csv", lambda df: df.assign(wz=df.wz * 57.3 * 10)), "refused", "imu.csv"),
    "gyro_in_deg_vs_truth": Case(_edit("imu.csv", lambda df: df.assign(wz=df.wz * 57.3)), "refused", "imu.csv"),
    "anchor_1e30": Case(_cell("anchors.csv", 2, "x", 1e30), "refused", "anchors.csv"),
    "anchor_in_mm": Case(_edit("anchors.csv", lambda df: df.assign(x=df.x * 1000, y=df.y * 1000)),
                         "refused", "anchors.csv"),
    "anchors_one_point": Case(_anchors([[1, 1, 1]] * 4), "refused", "anchors.csv"),
    "anchors_collinear": Case(_anchors([[0, 0, 1], [1, 1, 1], [2, 2, 1], [3, 3, 1]]), "refused", "anchors.csv"),
    "gt_far_away": Case(_cell("groundtruth.csv", 10, "px", 1e6), "refused", "groundtruth.csv"),
    "gt_quat_norm": Case(_cell("groundtruth.csv", 10, "qw", 2.0), "refused", "groundtruth.csv"),
    "gt_inf": Case(_cell("groundtruth.csv", 10, "py", "inf"), "refused", "groundtruth.csv"),
    "range_negative": Case(_cell("uwb.csv", 7, "range", -1.5), "refused", "uwb.csv"),
    "range_1e5": Case(_cell("uwb.csv", 7, "range", 1e5), "refused", "uwb.csv"),
    # malformed content
    "imu_nan": Case(_cell("imu.csv", 3, "ax", np.nan), "refused", "imu.csv"),
    "uwb_text_range": Case(_cell("uwb.csv", 3, "range", "abc"), "refused", "uwb.csv"),
    "uwb_unknown_anchor": Case(_cell("uwb.csv", 3, "anchor", "Z9"), "refused", "uwb.csv"),
    "anchor_duplicate_id": Case(_cell("anchors.csv", 1, "anchor", "A0"), "refused", "anchors.csv"),
    "anchor_empty_id": Case(_cell("anchors.csv", 1, "anchor", " "), "refused", "anchors.csv"),
    "imu_missing_column": Case(_edit("imu.csv", lambda df: df.drop(columns=["wy"])), "refused", "imu.csv"),
    "imu_empty_file": Case(_text("imu.csv", ""), "refused", "imu.csv"),
    "uwb_header_only": Case(_text("uwb.csv", "t,anchor,range\n"), "refused", "uwb.csv"),
    "imu_blank_line": Case(_append_line("imu.csv", "", 10), "refused", "imu.csv"),
    "uwb_extra_field": Case(_append_line("uwb.csv", "0.07,A1,3.0,9,9", 5), "refused", "uwb.csv"),
    "imu_binary": Case(lambda f: (f / "imu.csv").write_bytes(b"\xff\xfe\x00\x81" * 50), "refused", "imu.csv"),
    "imu_dup_header": Case(_text("imu.csv", "t,ax,ax,az,wx,wy,wz\n0,0,0,9.81,0,0,0\n"), "refused", "imu.csv"),
    "gt_velocity_partial": Case(_edit("groundtruth.csv", lambda df: df.assign(vx=0.0)), "refused",
                                "groundtruth.csv"),
    "missing_anchors": Case(_remove("anchors.csv"), "refused", "anchors.csv"),
    "missing_uwb": Case(_remove("uwb.csv"), "refused", "uwb.csv"),
    "yaml_invalid": Case(_yaml("name: [unclosed\n"), "refused", "dataset.yaml"),
    "yaml_unknown_key": Case(_yaml({"name": "x", "colour": "red"}), "refused", "dataset.yaml"),
    "yaml_negative_sigma": Case(_yaml({"range_sigma": -0.1}), "refused", "dataset.yaml"),
    "yaml_frame_up_bad": Case(_yaml({"anchor_frame_up": "up"}), "refused", "dataset.yaml"),
    "yaml_frame_up_conflict": Case(_yaml({"anchor_frame_up": "+z", "extra": {"anchor_frame_up": "-z"}}),
                                   "refused", "dataset.yaml"),
    "yaml_not_mapping": Case(_yaml("- a\n- b\n"), "refused", "dataset.yaml"),
    # TDoA and the other new tables
    "tdoa_same_anchor": Case(_tdoa([(1.0, "A0", "A0", 0.5)]), "refused", "tdoa.csv"),
    "tdoa_unknown_anchor": Case(_tdoa([(1.0, "A0", "Q", 0.5)]), "refused", "tdoa.csv"),
    "tdoa_too_large": Case(_tdoa([(1.0, "A0", "A1", 50.0)]), "refused", "tdoa.csv"),
    "tdoa_in_seconds_ticks": Case(_tdoa([(1.0, "A0", "A1", 1.5e6)]), "refused", "tdoa.csv"),
    "tdoa_nan": Case(_tdoa([(1.0, "A0", "A1", np.nan)]), "refused", "tdoa.csv"),
    "anchor_quat_norm": Case(_edit("anchors.csv", lambda df: df.assign(qw=2.0, qx=0.0, qy=0.0, qz=0.0)),
                             "refused", "anchors.csv"),
    "anchor_ranges_unknown": Case(lambda f: pd.DataFrame({"anchor_a": ["A0"], "anchor_b": ["B7"], "range": [3.0]})
                                  .to_csv(f / "anchor_ranges.csv", index=False), "refused", "anchor_ranges.csv"),
    # accepted with a documented warning or an asked-for repair
    "imu_30hz": Case(_both(_subsample("imu.csv", 7)), "warned", "imu_rate_low"),
    "anchors_coplanar": Case(_anchors(_coplanar), "warned", "anchors_coplanar"),
    "anchors_coincident": Case(_both(_anchors(list(ANCHORS) + [ANCHORS[0]])), "warned", "anchors_coincident"),
    "gt_partial_overlap": Case(_scale_t("groundtruth.csv", 1.0, 7.0), "warned", "span_overlap_partial"),
    "accel_spike_20g": Case(_cell("imu.csv", 500, "ax", 200.0), "warned", "accel_high"),
    "imu_5hz_lenient": Case(_subsample("imu.csv", 40), "warned", "lenient_accepted", ["--lenient"]),
    "collinear_lenient": Case(_anchors([[0, 0, 1], [1, 1, 1], [2, 2, 1], [3, 3, 1]]), "warned", "lenient_accepted",
                              ["--lenient"]),
    "uwb_clock_jump_split": Case(_clock_back("uwb.csv", 6.0, 3.0), "warned", "clock_jump", ["--split-clock-jumps"]),
    "imu_backwards_sorted": Case(_swap_rows("imu.csv", 100, 101), "warned", "repair", ["--sort"]),
    "imu_duplicate_dropped": Case(_dup_row("imu.csv", 50), "warned", "repair", ["--drop-duplicates"]),
    "accel_in_g_converted": Case(_edit("imu.csv", lambda df: df.assign(ax=df.ax / 9.81, ay=df.ay / 9.81,
                                                                        az=df.az / 9.81)),
                                 "warned", "repair", ["--accel-units", "g"]),
}
