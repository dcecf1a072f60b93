"""Flight segments (uwbimu.estimation.segments): take-off/landing from the IMU, the floor's ranges left
out only where they contradict the airborne ones; start/end options; the real Crazyflie log (shared,
skipped when absent)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from uwbimu.errors import UsageError
from uwbimu.estimation.segments import detect_flight, ground_ranges_shadowed, select_segment
from uwbimu.io.dataset import Dataset, DatasetMeta

G = 9.81
ANCHORS = np.array([[-4, -4, 0.2], [-4, 4, 3.0], [4, 4, 0.2], [4, -4, 3.0],
                    [-4, -4, 3.0], [4, -4, 0.2], [4, 4, 3.0], [-4, 4, 0.2]], dtype=float)


def _smooth_step(t, t0, dur):
    """0 -> 1 with zero velocity and acceleration at both ends (quintic)."""
    s = np.clip((t - t0) / dur, 0.0, 1.0)
    return 10 * s**3 - 15 * s**4 + 6 * s**5


def _flight(seed=0, climb=1.2, t_up=2.5, t_down=12.0, rate=500.0, vib=1.0):
    """Rest 0.5 s (motors off), motors on, climb `climb` m from t_up over 2 s, hover, descend from t_down,
    motors idle 1 s, rest 0.5 s.  Returns t, imu (N, 6), height z(t)."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, t_down + 4.0, 1.0 / rate)
    z = 0.05 + climb * (_smooth_step(t, t_up, 2.0) - _smooth_step(t, t_down, 2.0))
    az = np.gradient(np.gradient(z, t), t)
    motors = (t > 0.5) & (t < t_down + 3.0)
    imu = np.zeros((len(t), 6))
    imu[:, 2] = G + az
    imu[:, :3] += rng.normal(0, 0.01, (len(t), 3)) + motors[:, None] * rng.normal(0, vib, (len(t), 3))
    imu[:, 3:] = rng.normal(0, 0.002, (len(t), 3)) + motors[:, None] * rng.normal(0, 0.05, (len(t), 3))
    return t, imu, z


def test_takeoff_and_landing_found_where_the_height_says():
    t, imu, z = _flight()
    seg = detect_flight(t, imu)
    assert seg is not None
    # take-off while the climb has started, before 0.3 m; start once the vehicle is ~0.3 m up
    assert 2.5 < seg.takeoff < float(np.interp(0.3 + 0.05, z[: len(z) // 2], t[: len(z) // 2]))
    # the IMU's height is an estimate: the start lies between a third of and twice airborne_height up
    z_start = float(np.interp(seg.start, t, z)) - 0.05
    assert 0.1 < z_start < 0.6
    assert seg.landing is not None and 12.0 < seg.landing < 14.0
    z_end = float(np.interp(seg.end, t, z)) - 0.05
    assert 0.1 < z_end < 0.6 and seg.end < seg.landing


@pytest.mark.parametrize("case", ["no_initial_rest", "no_climb"])
def test_no_flight_no_segment(case):
    t, imu, z = _flight(climb=0.1 if case == "no_climb" else 1.2)
    if case == "no_initial_rest":
        imu = imu.copy()
        imu[:, 3] += 0.3 * np.sin(2 * np.pi * 0.5 * t)  # rotating from the first sample
    assert detect_flight(t, imu) is None


def _dataset(t, imu, z, floor_offset):
    """TDoA of all anchor pairs at 50 Hz from the true position, the floor rows (z < 0.1) computed from a
    point `floor_offset` away (a shadowed radio)."""
    ti = np.arange(0.0, t[-1], 0.02)
    zi = np.interp(ti, t, z)
    p = np.column_stack([np.zeros_like(ti), np.zeros_like(ti), zi])
    p[zi < 0.1] += floor_offset
    rows = []
    rng = np.random.default_rng(5)
    for a in range(8):
        for b in range(a + 1, 8):
            d = np.linalg.norm(p - ANCHORS[b], axis=1) - np.linalg.norm(p - ANCHORS[a], axis=1)
            rows.append(pd.DataFrame({"t": ti, "anchor_a": str(a), "anchor_b": str(b),
                                      "tdoa": d + rng.normal(0, 0.05, len(ti))}))
    tdoa = pd.concat(rows).sort_values("t", kind="stable").reset_index(drop=True)
    anchors = pd.DataFrame({"anchor": [str(i) for i in range(8)], "x": ANCHORS[:, 0], "y": ANCHORS[:, 1],
                            "z": ANCHORS[:, 2]})
    imu_df = pd.DataFrame(imu, columns=["ax", "ay", "az", "wx", "wy", "wz"])
    imu_df.insert(0, "t", t)
    return Dataset(imu=imu_df, uwb=pd.DataFrame({"t": [], "anchor": [], "range": []}), anchors=anchors,
                   tdoa=tdoa, meta=DatasetMeta(name="synthetic-flight"))


@pytest.mark.parametrize("offset,shadowed", [((0.5, 0.3, 6.0), True), ((0.0, 0.0, 0.0), False)])
def test_floor_ranges_left_out_only_when_they_contradict_the_air(offset, shadowed):
    t, imu, z = _flight()
    ds = _dataset(t, imu, z, np.array(offset))
    seg = detect_flight(t, imu)
    sh = ground_ranges_shadowed(ds, seg)
    assert sh["before"] is shadowed and sh["after"] is shadowed
    cropped, ev = select_segment(ds, "auto")
    assert ev["kind"] == "flight_segment" and ev["detected"]
    if shadowed:
        assert ev["used"] == [seg.start, seg.end]
        assert cropped.tdoa["t"].min() >= seg.start and cropped.imu["t"].max() <= seg.end
    else:
        assert ev["used"] == [float(t[0]), float(t[-1])]
        assert len(cropped.tdoa) == len(ds.tdoa)
    # the whole log on request, and explicit start/end win over the detection
    assert select_segment(ds, "whole")[1]["used"] == [float(t[0]), float(t[-1])]
    part, ev2 = select_segment(ds, "auto", start=3.0, end=8.0)
    assert ev2["source"] == "options" and part.imu["t"].min() >= 3.0 and part.imu["t"].max() <= 8.0
    with pytest.raises(UsageError):
        select_segment(ds, "auto", start=8.0, end=3.0)


UTIL_0425 = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "util_0425"


@pytest.mark.skipif(not (UTIL_0425 / "raw" / "TDOA2" / "0425-traj3").exists(),
                    reason="UTIL 2021 logs not present (shared data, not in the repo)")
# the take-off is dated while the vehicle is below z_takeoff [m]: measured 0.07 m (TDoA2) and 0.25 m (TDoA3,
# whose vibrating IMU on the floor dates it about 0.4 s late)
@pytest.mark.parametrize("log,z_takeoff", [("TDOA2/0425-traj3", 0.2), ("TDOA3/0425-traj16", 0.3)])
def test_crazyflie_log_starts_in_the_air(log, z_takeoff):
    from uwbimu.io.importers.cf_usdlog import convert

    ds = convert(UTIL_0425 / "raw" / log, UTIL_0425 / "survey" / "anchors_0425.csv").dataset
    cropped, ev = select_segment(ds, "auto")
    gt = ds.groundtruth
    z = lambda s: float(np.interp(s, gt["t"], gt["pz"]))  # noqa: E731
    assert ev["shadowed_before"] and ev["shadowed_after"]
    # the floor is at 0.03 m in the Vicon frame; the used span starts and ends in the air
    assert 0.15 < z(ev["used"][0]) < 0.6 and 0.15 < z(ev["used"][1]) < 0.6
    assert z(ev["takeoff"]) < z_takeoff and ev["landing"] is not None and z(ev["landing"]) < 0.2


def test_loader_start_end_cut_every_stream_but_the_ground_truth(tmp_path):
    from uwbimu.io.dataset import write_dataset
    from uwbimu.io.loader import DatasetError, load_dataset

    t, imu, z = _flight()
    ds = _dataset(t, imu, z, np.zeros(3))
    ds.groundtruth = pd.DataFrame({"t": t[::10], "px": 0.0, "py": 0.0, "pz": z[::10], "qw": 1.0, "qx": 0.0,
                                   "qy": 0.0, "qz": 0.0})
    path = write_dataset(ds, tmp_path / "ds")
    cut = load_dataset(path, start=3.0, end=8.0)
    for name in ("imu", "tdoa"):
        tt = getattr(cut, name)["t"]
        assert tt.min() >= 3.0 and tt.max() <= 8.0
        assert len(tt) < len(getattr(ds, name))
    assert len(cut.groundtruth) == len(ds.groundtruth)
    assert any("--start/--end" in a for a in cut.report.actions)
    with pytest.raises(DatasetError):
        load_dataset(path, start=8.0, end=3.0)
    with pytest.raises(DatasetError):
        load_dataset(path, start=1e6)
