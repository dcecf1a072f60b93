"""Run a :class:`~uwbimu.sim.scenario.Scenario` into a :class:`~uwbimu.io.dataset.Dataset`.

Clocks (see DEVELOPERS.md): the UWB clock is the reference.  The IMU is
sampled on its own clock at stamps ``s_k = k / rate`` (``k = 0..N-1``,
``N = floor(duration * rate) + 1``); sample ``s_k`` describes the motion at
UWB time ``s_k - t_d``.  The ground truth is given at those instants, i.e.
row ``k`` of ``groundtruth`` (stamp ``s_k - t_d``, UWB clock) is the true
state of IMU row ``k``.

Ranges are scheduled on the UWB clock at slots ``j / uwb.rate_hz`` inside
the window where the IMU stream covers them (``[max(0, -t_d),
min(duration, duration - t_d)]``), so that every range's IMU time
``t + t_d`` lies within the IMU stamps.  A range is taken at the nominal
instant; its logged stamp is nominal plus jitter.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import pandas as pd

from uwbimu.io.dataset import GT_COLUMNS, GT_VEL_COLUMNS, IMU_COLUMNS, Dataset, DatasetMeta, TagMeta, TruthMeta
from uwbimu.sim.scenario import Scenario
from uwbimu.sim.sensors import imu_measurements, imu_noise_streams
from uwbimu.sim.trajectory import MotionSample, Trajectory

Progress = Callable[[str, float], None]

# Streams spawned from seeds.noise (fixed order: never reorder, append only).
_IMU_STREAM, _UWB_STREAM = 0, 1


@dataclass
class SimResult:
    """Everything :func:`simulate_full` knows, beyond what fits in a :class:`Dataset`.

    Attributes
    ----------
    dataset : the simulated :class:`Dataset`.
    trajectory : the truth :class:`Trajectory` (callable at any UWB time).
    motion : truth at the IMU instants (UWB times ``imu_t - t_d``).
    accel_bias, gyro_bias : (N, 3) true IMU biases at each IMU sample.
    range_t_nominal : (R,) true instant of each emitted range (UWB clock), rows of ``dataset.uwb``.
    range_true : (R,) noise-free range of each emitted range [m].
    range_nlos : (R,) bool, whether an NLOS excess was added.
    tdoa_t_nominal, tdoa_true, tdoa_nlos : the same per row of ``dataset.tdoa`` (TDoA modes;
        empty otherwise); ``tdoa_true`` takes each distance at its packet's arrival;
        ``tdoa_packets`` (T, 2) the indices ``(j, k)`` of the two packets of each row (rows sharing an
        index share that packet's error); ``tdoa_t_a`` the arrival instant of packet ``j`` (anchor_a).
    """

    dataset: Dataset
    trajectory: Trajectory
    motion: MotionSample
    accel_bias: np.ndarray
    gyro_bias: np.ndarray
    range_t_nominal: np.ndarray
    range_true: np.ndarray
    range_nlos: np.ndarray
    tdoa_t_nominal: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tdoa_true: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tdoa_nlos: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    tdoa_packets: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), int))
    tdoa_t_a: np.ndarray = field(default_factory=lambda: np.zeros(0))


def _noop(stage: str, frac: float) -> None:
    pass


def flight_duration(scenario: Scenario, traj: Trajectory) -> float:
    if scenario.duration is not None:
        return float(scenario.duration)
    return float(traj.natural_duration)


def simulate(scenario: Scenario, progress: Optional[Progress] = None) -> Dataset:
    """Simulate ``scenario``: IMU, UWB ranges, ground truth and true calibration.

    Returns a :class:`~uwbimu.io.dataset.Dataset` (``meta.truth`` holds lever
    arm, time offset, anchor biases and per-tag lever arms).  Deterministic
    given ``scenario.seeds``.
    """
    return simulate_full(scenario, progress).dataset


def simulate_full(scenario: Scenario, progress: Optional[Progress] = None) -> SimResult:
    """Like :func:`simulate` but also returns the truth that a dataset cannot hold."""
    progress = progress or _noop
    # Re-validate: a scenario edited with model_copy(update=...) is not validated by pydantic.
    scenario = Scenario.model_validate(scenario.model_dump(mode="python", warnings=False))
    progress("trajectory", 0.0)
    traj = scenario.trajectory.build(scenario.seeds.truth)
    duration = flight_duration(scenario, traj)
    t_d = float(scenario.time_offset)

    # ---- IMU --------------------------------------------------------------
    rate = float(scenario.imu.rate_hz)
    dt = 1.0 / rate
    n = int(math.floor(duration * rate + 1e-9)) + 1
    s = np.arange(n) * dt  # IMU clock
    motion = traj.sample(s - t_d)  # UWB time of each IMU sample
    progress("imu", 0.3)
    noise = scenario.imu.noise_model()
    ss = np.random.SeedSequence(scenario.seeds.noise).spawn(2)
    rng_imu = np.random.default_rng(ss[_IMU_STREAM])
    rng_uwb = np.random.default_rng(ss[_UWB_STREAM])
    # Draw the initial biases even when given, so that the later streams do not shift.
    b_a0 = rng_imu.standard_normal(3) * noise.accel_bias_sigma0
    b_g0 = rng_imu.standard_normal(3) * noise.gyro_bias_sigma0
    if scenario.imu.accel_bias is not None:
        b_a0 = np.asarray(scenario.imu.accel_bias, dtype=float)
    if scenario.imu.gyro_bias is not None:
        b_g0 = np.asarray(scenario.imu.gyro_bias, dtype=float)
    n_a, n_g, b_a, b_g = imu_noise_streams(noise, dt, n, b_a0, b_g0, rng_imu)
    a_m, w_m = imu_measurements(motion.q, motion.a, motion.w, b_a, b_g, n_a, n_g)
    saturation = {}
    for key, arr, lim in (("accel", a_m, scenario.imu.accel_limit), ("gyro", w_m, scenario.imu.gyro_limit)):
        if lim is not None:
            over = np.abs(arr) > lim
            saturation[f"{key}_clipped_samples"] = int(over.any(axis=1).sum())
            saturation[f"{key}_clipped_values"] = int(over.sum())
            np.clip(arr, -lim, lim, out=arr)
    imu = pd.DataFrame(np.column_stack([s, a_m, w_m]), columns=IMU_COLUMNS)
    gt = pd.DataFrame(
        np.column_stack([motion.t, motion.p, motion.q, motion.v]), columns=GT_COLUMNS + GT_VEL_COLUMNS
    )

    # ---- UWB --------------------------------------------------------------
    progress("uwb", 0.6)
    lo = max(0.0, s[0] - t_d)
    hi = min(duration, s[-1] - t_d)
    tdoa = None
    tinfo: dict = {"t_nominal": np.zeros(0), "true": np.zeros(0), "nlos": np.zeros(0, bool),
                   "packets": np.zeros((0, 2), int), "t_a_nominal": np.zeros(0)}
    if scenario.uwb.mode == "twr":
        from uwbimu.sim.ranging import simulate_ranges

        uwb, rinfo = simulate_ranges(scenario, traj, lo, hi, rng_uwb)
    else:
        from uwbimu.sim.tdoa import simulate_tdoa, tdoa_sigma

        tdoa, tinfo = simulate_tdoa(scenario, traj, lo, hi, rng_uwb)
        uwb = pd.DataFrame({"t": np.zeros(0), "anchor": np.zeros(0, dtype=str), "range": np.zeros(0)})
        rinfo = {"counts": tinfo["counts"], "t_nominal": np.zeros(0), "true": np.zeros(0),
                 "nlos": np.zeros(0, bool)}

    # ---- metadata ---------------------------------------------------------
    tags = scenario.tag_list()
    ids = scenario.anchor_ids()
    anchors = pd.DataFrame(
        {"anchor": ids, **{c: scenario.anchor_positions()[:, i] for i, c in enumerate("xyz")}}
    )
    truth = TruthMeta(
        lever_arm=[float(x) for x in tags[0].lever_arm],
        time_offset=t_d,
        anchor_bias={a: float(scenario.uwb.anchor_bias.get(a, 0.0)) for a in ids},
        tags={t.name: [float(x) for x in t.lever_arm] for t in tags},
    )
    meta = DatasetMeta(
        name=scenario.name,
        description=scenario.description or f"simulated by uwbimu.sim ({scenario.trajectory.type})",
        imu_noise=noise,
        imu_rate_hz=rate,
        range_sigma=float(scenario.uwb.sigma) if scenario.uwb.sigma > 0 and tdoa is None else None,
        tags=[TagMeta(name=t.name, lever_arm=None if t.nominal_lever_arm is None else [float(x) for x in t.nominal_lever_arm]) for t in tags],
        truth=truth,
        source="uwbimu.sim",
        extra={
            "simulated": True,
            "duration": duration,
            "seeds": scenario.seeds.model_dump(),
            "imu_bias": {
                "accel_initial": b_a[0].tolist(),
                "gyro_initial": b_g[0].tolist(),
                "accel_final": b_a[-1].tolist(),
                "gyro_final": b_g[-1].tolist(),
            },
            "imu_saturation": saturation,
            "uwb_counts": rinfo["counts"],
            "uwb_window": [float(lo), float(hi)],
            "range_sigma": float(scenario.uwb.sigma),
            "uwb_mode": scenario.uwb.mode,
            **({"tdoa_sigma": tdoa_sigma(scenario)} if tdoa is not None else {}),
            "scenario": scenario.model_dump(mode="json", exclude_none=True),
        },
    )
    ds = Dataset(imu=imu, uwb=uwb, anchors=anchors, groundtruth=gt, meta=meta, tdoa=tdoa)
    progress("done", 1.0)
    return SimResult(
        dataset=ds,
        trajectory=traj,
        motion=motion,
        accel_bias=b_a,
        gyro_bias=b_g,
        range_t_nominal=rinfo["t_nominal"],
        range_true=rinfo["true"],
        range_nlos=rinfo["nlos"],
        tdoa_t_nominal=tinfo["t_nominal"],
        tdoa_true=tinfo["true"],
        tdoa_nlos=tinfo["nlos"],
        tdoa_packets=tinfo["packets"],
        tdoa_t_a=tinfo["t_a_nominal"],
    )
