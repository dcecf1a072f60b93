"""Calibration manoeuvre design for the 19-state UWB-IMU model.

Given anchors, a flight box and bounds on speed, acceleration, tilt and body
rate, find a smooth rest-to-rest 6-DoF manoeuvre (Fourier series of ``K``
harmonics per channel under a smooth envelope, :mod:`.maneuver`) that
maximises the information on the lever arm and the time offset:
E-optimality, i.e. the smallest eigenvalue of the Fisher information of the
calibration block (scaled by ``scale_lever_arm`` / ``scale_time_offset``,
navigation states marginalised, IMU process noise included), computed by
the linearised ESKF covariance along the candidate (:mod:`.predictor`).

Platform (``platform``, default ``multirotor``, :mod:`.platform`): a multirotor
manoeuvre chooses x, y, z and yaw only; roll and pitch follow the thrust
(differential flatness, :mod:`uwbimu.sim.flat`), the vehicle's thrust, tilt,
body-rate and yaw-rate limits hold (:func:`.maneuver.fit_flat_to_bounds`), the
scenarios fly it with ``attitude: flat`` and the flown splines are checked
(:func:`.platform.check_multirotor`).  ``handheld``: a free rigid body, six
channels, as below.

Bounds are enforced by construction: every candidate is scaled
(:func:`.maneuver.fit_to_bounds`) so that its peaks sit at 99 % of the
bounds, which leaves the optimiser (scipy Powell, seeded random starts) an
unconstrained problem over the *shape* of the motion.

Outputs (:func:`design_and_write`): trajectory files in the simulator's
format (CSV ``t, px, py, pz, qw, qx, qy, qz``) for the designed manoeuvre and
the naive figure-8 baseline, scenario YAMLs that ``uwbimu simulate`` flies,
``design.json`` with the predicted sigmas and the bound usage, and plots.
"""

from __future__ import annotations

from uwbimu.errors import ConfigError
import time
from pathlib import Path
from typing import Any, Callable, Literal, Optional, Union

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from uwbimu.design.trajectory.maneuver import (
    Maneuver,
    MotionBounds,
    bound_usage,
    figure8_maneuver,
    fit_flat_to_bounds,
    fit_to_bounds,
    fourier_maneuver,
)
from uwbimu.design.trajectory.platform import MultirotorLimits, Platform, check_multirotor, platform_usage
from uwbimu.design.trajectory.predictor import calibration_metrics, predict_covariance
from uwbimu.models.imu import ImuNoise, imu_preset


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class AnchorItem(_Strict):
    id: str
    position: list[float] = Field(min_length=3, max_length=3)

    @field_validator("id", mode="before")
    @classmethod
    def _id_as_text(cls, v):  # YAML `id: 3` is the anchor "3", as in the simulator
        return str(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v


class BoundsOptions(_Strict):
    speed: float = Field(1.5, gt=0, description="max speed [m/s]")
    accel: float = Field(2.0, gt=0, description="max acceleration (kinematic, world) [m/s^2]")
    tilt_deg: float = Field(30.0, gt=0, lt=80, description="handheld: max tilt of the body z axis from vertical [deg]")
    rate: float = Field(1.5, gt=0, description="handheld: max body angular rate [rad/s]")


class SensorOptions(_Strict):
    imu_noise: Union[str, ImuNoise] = Field("bmi088", description="preset name or densities")
    imu_rate_hz: float = Field(200.0, gt=0, description="IMU rate of the simulated flight [Hz]")
    uwb_rate_hz: float = Field(50.0, gt=0, description="range slots per second [Hz]")
    schedule: Literal["round_robin", "all"] = "round_robin"
    range_sigma: float = Field(0.05, gt=0, description="range noise sd [m]")

    def noise(self) -> ImuNoise:
        return imu_preset(self.imu_noise) if isinstance(self.imu_noise, str) else self.imu_noise


class TruthOptions(_Strict):
    lever_arm: list[float] = Field(default_factory=lambda: [0.12, -0.08, 0.14], min_length=3, max_length=3)
    time_offset: float = Field(0.03, ge=-1, le=1, description="[s]")


class PriorOptions(_Strict):
    """Initial 1-sigma of the predicted filter (defaults: the ESKF's defaults)."""

    position_sd: float = Field(0.3, gt=0)
    velocity_sd: float = Field(0.5, gt=0)
    roll_pitch_sd_deg: float = Field(5.0, gt=0)
    yaw_sd_deg: float = Field(15.0, gt=0)
    accel_bias_sd: Optional[float] = Field(None, gt=0, description="None: the IMU's accel_bias_sigma0")
    gyro_bias_sd: Optional[float] = Field(None, gt=0, description="None: the IMU's gyro_bias_sigma0")
    lever_arm_sd: float = Field(0.3, gt=0, description="[m]")
    time_offset_sd: float = Field(0.03, gt=0, description="[s] (ESKF: sd after its grid search)")


class ObjectiveOptions(_Strict):
    scale_lever_arm: float = Field(0.01, gt=0, description="[m] that counts as much as scale_time_offset")
    scale_time_offset: float = Field(0.001, gt=0, description="[s]")


class DesignOptions(_Strict):
    n_harmonics: int = Field(3, ge=1, le=8, description="harmonics per channel (2 coefficients each)")
    period: float = Field(10.0, gt=0, description="fundamental period [s]: harmonics k / period")
    dt: float = Field(0.04, gt=0, le=0.1, description="grid of the covariance prediction [s]")


class OptimizerOptions(_Strict):
    seed: int = Field(0, ge=0)
    n_random: int = Field(12, ge=1, description="random shapes tried before the local search")
    starts: int = Field(3, ge=1, description="Powell searches, one from each of the `starts` best random shapes (at most n_random)")
    max_evals: int = Field(
        800,
        ge=1,
        description=(
            "objective evaluations of ONE search: the n_random random shapes plus one Powell start; every "
            "Powell start gets max_evals - n_random, so the total is at most n_random + starts * (max_evals - n_random)"
        ),
    )

    @property
    def total_evals(self) -> int:
        """Evaluation budget of the whole design (the random shapes once, then every start's budget; a converged
        Powell search stops earlier)."""
        n_rand = min(self.n_random, self.max_evals)
        return n_rand + min(self.starts, n_rand) * (self.max_evals - n_rand)


class Figure8Options(_Strict):
    period: Optional[float] = Field(None, gt=0, description="[s]; None: the fastest the speed/accel bounds allow")
    fill: float = Field(0.95, gt=0, le=1, description="fraction of the box half-extents used in x, y")
    attitude_amplitude: list[float] = Field(default_factory=lambda: [0.15, 0.15, 0.4], min_length=3, max_length=3)
    attitude_frequency: list[float] = Field(default_factory=lambda: [0.3, 0.23, 0.07], min_length=3, max_length=3)


class CalibrationDesignConfig(_Strict):
    """Everything :func:`design_calibration` needs (YAML: see ``examples/plan/calibration.yaml``)."""

    name: str = "calibration-design"
    platform: Platform = Field("multirotor", description="multirotor: attitude follows the thrust (flat); handheld: free rigid body")
    multirotor: MultirotorLimits = Field(default_factory=MultirotorLimits, description="limits of the multirotor platform")
    duration: float = Field(40.0, gt=0, description="flight length [s] (both trajectories)")
    ramp: float = Field(2.0, ge=0, description="rest-to-motion ramp at both ends [s]")
    anchors: Union[str, list[AnchorItem]] = Field("room8", description="simulator preset name or list")
    box_min: list[float] = Field(default_factory=lambda: [1.0, 1.0, 0.8], min_length=3, max_length=3)
    box_max: list[float] = Field(default_factory=lambda: [9.0, 7.0, 2.4], min_length=3, max_length=3)
    center: Optional[list[float]] = Field(None, min_length=3, max_length=3, description="start/end point; None: box centre")
    bounds: BoundsOptions = Field(default_factory=BoundsOptions)
    sensors: SensorOptions = Field(default_factory=SensorOptions)
    truth: TruthOptions = Field(default_factory=TruthOptions)
    prior: PriorOptions = Field(default_factory=PriorOptions)
    objective: ObjectiveOptions = Field(default_factory=ObjectiveOptions)
    design: DesignOptions = Field(default_factory=DesignOptions)
    optimizer: OptimizerOptions = Field(default_factory=OptimizerOptions)
    figure8: Figure8Options = Field(default_factory=Figure8Options)
    waypoint_rate_hz: float = Field(20.0, gt=0, description="rows per second of the trajectory files")

    @model_validator(mode="after")
    def _check(self):
        if any(lo >= hi for lo, hi in zip(self.box_min, self.box_max)):
            raise ValueError("box_min must be below box_max on every axis")
        c = self.start_point()
        if any(not (lo < ci < hi) for lo, ci, hi in zip(self.box_min, c, self.box_max)):
            raise ValueError(f"center {c} must lie strictly inside the box")
        if self.duration <= 2 * self.ramp + 1.0:
            raise ValueError(f"duration ({self.duration}) must exceed 2 * ramp + 1 s")
        self.anchor_array()  # raises on an unknown preset
        if self.platform == "multirotor":
            both = sorted(self.bounds.model_fields_set & {"tilt_deg", "rate"})
            if both:
                fields = ", ".join(f"bounds.{k}" for k in both)
                raise ValueError(
                    f"{fields} apply to platform 'handheld'; the multirotor's are multirotor.tilt_max_deg and multirotor.rate_max"
                )
        return self

    @property
    def flat(self) -> bool:
        """True for the multirotor: roll and pitch follow the thrust."""
        return self.platform == "multirotor"

    def fit(self, m: Maneuver, dt: float = 0.02, grow: bool = True) -> Maneuver:
        """Scale a manoeuvre onto the bounds and the platform's limits (99 %)."""
        b = self.motion_bounds()
        if self.flat:
            return fit_flat_to_bounds(m, b, self.multirotor, dt=dt, grow=grow)
        return fit_to_bounds(m, b, dt=dt, grow=grow)

    def start_point(self) -> list[float]:
        return self.center if self.center is not None else [0.5 * (a + b) for a, b in zip(self.box_min, self.box_max)]

    def anchor_ids(self) -> list[str]:
        from uwbimu.sim.scenario import ANCHOR_PRESETS

        if isinstance(self.anchors, str):
            if self.anchors not in ANCHOR_PRESETS:
                raise ConfigError(f"unknown anchor preset {self.anchors!r}; choose one of {', '.join(map(str, sorted(ANCHOR_PRESETS)))}")
            return list(ANCHOR_PRESETS[self.anchors])
        return [a.id for a in self.anchors]

    def anchor_array(self) -> np.ndarray:
        from uwbimu.sim.scenario import ANCHOR_PRESETS

        if isinstance(self.anchors, str):
            if self.anchors not in ANCHOR_PRESETS:
                raise ConfigError(f"unknown anchor preset {self.anchors!r}; choose one of {', '.join(map(str, sorted(ANCHOR_PRESETS)))}")
            return np.array(list(ANCHOR_PRESETS[self.anchors].values()), dtype=float)
        return np.array([a.position for a in self.anchors], dtype=float)

    def motion_bounds(self) -> MotionBounds:
        """Box, speed, acceleration; tilt and body rate of the platform (multirotor: its limits)."""
        b = self.bounds
        if self.flat:
            tilt, rate = self.multirotor.tilt_max, self.multirotor.rate_max
        else:
            tilt, rate = np.deg2rad(b.tilt_deg), b.rate
        return MotionBounds(np.asarray(self.box_min, float), np.asarray(self.box_max, float), b.speed, b.accel, tilt, rate)

    def usage(self, kin: dict) -> dict[str, float]:
        """Peak / bound of every bound (and, multirotor, every vehicle limit) along ``kin``."""
        u = bound_usage(kin, self.motion_bounds())
        if self.flat:
            u |= platform_usage(kin, self.multirotor)
        return u

    def prior_covariance(self) -> np.ndarray:
        pr, n = self.prior, self.sensors.noise()
        sd = np.concatenate(
            [
                [pr.position_sd] * 3,
                [pr.velocity_sd] * 3,
                np.deg2rad([pr.roll_pitch_sd_deg, pr.roll_pitch_sd_deg, pr.yaw_sd_deg]),
                [pr.accel_bias_sd or max(n.accel_bias_sigma0, 1e-4)] * 3,
                [pr.gyro_bias_sd or max(n.gyro_bias_sigma0, 1e-5)] * 3,
                [pr.lever_arm_sd] * 3,
                [pr.time_offset_sd],
            ]
        )
        return np.diag(sd**2)


# --------------------------------------------------------------------------
# Evaluation of a candidate
# --------------------------------------------------------------------------
def range_schedule(cfg: CalibrationDesignConfig) -> tuple[np.ndarray, np.ndarray]:
    """Nominal range instants (UWB clock) and anchor indices, as the simulator schedules them."""
    rate, M = cfg.sensors.uwb_rate_hz, len(cfg.anchor_array())
    j = np.arange(0, int(np.floor(cfg.duration * rate + 1e-9)) + 1)
    t = j / rate
    if cfg.sensors.schedule == "round_robin":
        return t, j % M
    return np.repeat(t, M), np.tile(np.arange(M), len(j))


def evaluate_kinematics(kin_grid: dict, kin_meas: dict, meas_anchor_idx: np.ndarray, cfg: CalibrationDesignConfig) -> dict[str, Any]:
    """Predicted covariance and calibration metrics of a truth sampled on the grid and at the ranges."""
    A = cfg.anchor_array()
    P = predict_covariance(kin_grid, kin_meas, A[meas_anchor_idx], np.asarray(cfg.truth.lever_arm), cfg.prior_covariance(), cfg.sensors.noise(), cfg.sensors.range_sigma)
    out = calibration_metrics(P, cfg.objective.scale_lever_arm, cfg.objective.scale_time_offset)
    out["P"] = P
    return out


def evaluate_maneuver(m: Maneuver, cfg: CalibrationDesignConfig, sched=None) -> dict[str, Any]:
    """Predicted calibration metrics and bound usage of an analytic manoeuvre."""
    tm, ai = sched if sched is not None else range_schedule(cfg)
    tg = np.arange(0.0, cfg.duration + 0.5 * cfg.design.dt, cfg.design.dt)
    kin = m.kinematics(tg)
    out = evaluate_kinematics(kin, m.kinematics(tm), ai, cfg)
    out["bound_usage"] = cfg.usage(kin)
    return out


def sim_trajectory_kinematics(traj, t: np.ndarray) -> dict[str, np.ndarray]:
    """The same truth dictionary as :meth:`Maneuver.kinematics` from a simulator trajectory."""
    from uwbimu.models.quaternion import quat_to_rotmat
    from uwbimu.models.reference import G_WORLD

    s = traj.sample(np.asarray(t, dtype=float))
    R = quat_to_rotmat(s.q)
    return {
        "t": s.t, "p": s.p, "v": s.v, "a": s.a, "euler": s.euler, "q": s.q, "R": R, "w": s.w,
        "f": np.einsum("nji,nj->ni", R, s.a + G_WORLD), "tilt": np.arccos(np.clip(R[:, 2, 2], -1.0, 1.0)),
    }  # fmt: skip


def evaluate_sim_trajectory(traj, cfg: CalibrationDesignConfig) -> dict[str, Any]:
    """Predicted metrics and bound usage of a trajectory as the simulator flies it (e.g. a loaded file)."""
    tm, ai = range_schedule(cfg)
    tg = np.arange(0.0, cfg.duration + 0.5 * cfg.design.dt, cfg.design.dt)
    kin = sim_trajectory_kinematics(traj, tg)
    out = evaluate_kinematics(kin, sim_trajectory_kinematics(traj, tm), ai, cfg)
    fine = sim_trajectory_kinematics(traj, np.arange(0.0, cfg.duration, 0.01))
    out["bound_usage"] = cfg.usage(fine)
    if cfg.flat:
        out["limit_violations"] = [v.message() for v in check_multirotor(fine, cfg.multirotor)]
    return out


# --------------------------------------------------------------------------
# Baseline and design
# --------------------------------------------------------------------------
def naive_figure8(cfg: CalibrationDesignConfig) -> Maneuver:
    """The naive baseline: a horizontal figure-8 under the same duration, ramp and bounds.

    A lemniscate filling ``fill`` of the box half-extents around the start point,
    flown along the curve on the time-warped clock (rest to cruise to rest) at the
    fastest period for which the peak speed *or* acceleration reaches 99 % of its
    bound (or at ``figure8.period``), with the simulator's gentle attitude
    oscillation -- what one flies without an observability criterion.  Tilt and
    rate stay below their bounds (shrunk only if the attitude defaults exceed them).
    """
    f8 = cfg.figure8
    c = np.asarray(cfg.start_point() + [0.0, 0.0, 0.0])
    half = f8.fill * np.minimum(np.asarray(cfg.box_max) - c[:3], c[:3] - np.asarray(cfg.box_min))
    b = cfg.motion_bounds()

    def make(period):
        return figure8_maneuver(c, half[:2], period, cfg.duration, cfg.ramp, f8.attitude_amplitude, f8.attitude_frequency, flat=cfg.flat)

    tg = np.arange(0.0, cfg.duration + 0.01, 0.02)

    def usage(period):
        u = bound_usage(make(period).kinematics(tg), b)
        return max(u["speed"], u["accel"])

    if f8.period is not None:
        m = make(f8.period)
    else:
        # speed and acceleration fall monotonically with the period: bisect (log scale)
        # for the period at which the first of them reaches 99 % of its bound
        lo, hi = 1e-3 * cfg.duration, 1e3 * cfg.duration
        for _ in range(60):
            mid = np.sqrt(lo * hi)
            lo, hi = (mid, hi) if usage(mid) > 0.99 else (lo, mid)
        m = make(hi)
    # the attitude (and a user-given period) must respect the bounds (and the vehicle's limits) as well
    return cfg.fit(m, grow=False) if max(cfg.usage(m.kinematics(tg)).values()) > 1.0 else m


def _objective_factory(cfg: CalibrationDesignConfig, counter: list, progress: Optional[Callable[[int], None]]):
    sched = range_schedule(cfg)
    c = np.asarray(cfg.start_point() + [0.0, 0.0, 0.0])
    K = cfg.design.n_harmonics
    best = {"f": np.inf, "theta": None}

    def man(theta):
        raw = fourier_maneuver(theta, c, cfg.duration, cfg.ramp, cfg.design.period, K, flat=cfg.flat)
        return cfg.fit(raw, dt=0.05)

    def f(theta):
        counter[0] += 1
        try:
            r = evaluate_maneuver(man(theta), cfg, sched)
            val = -np.log(max(r["lambda_min_scaled"], 1e-300))
        except (FloatingPointError, np.linalg.LinAlgError, ValueError):
            val = 1e6
        if val < best["f"]:
            best.update(f=val, theta=np.array(theta, copy=True))
        if progress is not None:
            progress(counter[0])
        return val

    return f, man, best


def design_calibration(cfg: CalibrationDesignConfig, progress: Optional[Callable[[int], None]] = None) -> dict[str, Any]:
    """Optimise the manoeuvre; returns the designed and figure-8 manoeuvres with their metrics.

    Seeded: ``n_random`` random coefficient sets (standard normal) are scored, then
    a Powell search starts from each of the ``starts`` best of them, each with a
    budget of ``max_evals - n_random`` evaluations (so ``starts = 1`` is one search
    of ``max_evals`` evaluations in all); the best manoeuvre seen by any search is
    the design.  The objective is flat and the searches path-dependent, so several
    starts make the design both better and less sensitive to round-off.
    """
    from scipy.optimize import minimize

    t0 = time.perf_counter()
    opt = cfg.optimizer
    rng = np.random.default_rng(opt.seed)
    K = cfg.design.n_harmonics
    counter = [0]
    f, man, best = _objective_factory(cfg, counter, progress)
    n_rand = min(opt.n_random, opt.max_evals)
    n_chan = 4 if cfg.flat else 6  # multirotor: x, y, z, yaw
    cands = []
    for _ in range(n_rand):
        theta = rng.standard_normal(n_chan * K * 2)
        cands.append((f(theta), len(cands), theta))
    cands.sort(key=lambda c: (c[0], c[1]))  # stable: ties keep the draw order
    per_start = opt.max_evals - n_rand
    if per_start > 0:
        for _, _, theta in cands[: opt.starts]:
            minimize(f, theta, method="Powell", options={"maxfev": per_start, "xtol": 1e-3, "ftol": 1e-4})
    designed = man(best["theta"])
    fig8 = naive_figure8(cfg)
    # a stronger (non-naive) reference: the same figure-8 with its attitude
    # oscillation enlarged up to the tilt / rate bounds
    fig8x = cfg.fit(fig8)
    return {
        "designed": designed,
        "figure8": fig8,
        "figure8_excited": fig8x,
        "theta": best["theta"],
        "metrics_designed": evaluate_maneuver(designed, cfg),
        "metrics_figure8": evaluate_maneuver(fig8, cfg),
        "metrics_figure8_excited": evaluate_maneuver(fig8x, cfg),
        "n_evals": counter[0],
        "design_time_s": time.perf_counter() - t0,
    }


# --------------------------------------------------------------------------
# Files
# --------------------------------------------------------------------------
def write_maneuver_file(m: Maneuver, path: Path, rate_hz: float) -> Path:
    """Sample a manoeuvre into the simulator's trajectory file (``t, px, py, pz, qw, qx, qy, qz``)."""
    from uwbimu.sim.trajfile import write_trajectory_file

    t = np.linspace(0.0, m.duration, int(round(m.duration * rate_hz)) + 1)
    kin = m.kinematics(t)
    return write_trajectory_file(path, t, kin["p"], q=kin["q"])


def scenario_dict(cfg: CalibrationDesignConfig, traj_file: str, name: str, description: str, seeds: Optional[dict] = None) -> dict:
    """A scenario (``uwbimu.sim.Scenario`` fields) flying ``traj_file`` with the design's sensors."""
    s = cfg.sensors
    imu_noise = s.imu_noise if isinstance(s.imu_noise, str) else s.imu_noise.model_dump()
    anchors = cfg.anchors if isinstance(cfg.anchors, str) else [a.model_dump() for a in cfg.anchors]
    return {
        "name": name,
        "description": description,
        "duration": float(cfg.duration),
        # multirotor: the simulator recomputes roll/pitch from the position spline's thrust
        "trajectory": {"type": "file", "path": traj_file, "attitude": "flat" if cfg.flat else "file"},
        "imu": {"rate_hz": s.imu_rate_hz, "noise": imu_noise},
        "uwb": {"rate_hz": s.uwb_rate_hz, "schedule": s.schedule, "sigma": s.range_sigma},
        "anchors": anchors,
        "lever_arm": list(cfg.truth.lever_arm),
        "time_offset": float(cfg.truth.time_offset),
        "seeds": seeds or {"truth": 0, "noise": 1, "init": 2},
    }


def _plain_metrics(r: dict) -> dict:
    return {k: v for k, v in r.items() if k != "P"}


def design_and_write(cfg: CalibrationDesignConfig, out: str | Path, progress=None, config_path=None) -> dict[str, Any]:
    """Design, then write trajectory files, scenarios, ``design.json`` and plots into ``out``.

    The written files are read back through the simulator (``load_scenario`` and
    the trajectory-file loader) and the prediction is repeated on the flown
    splines (``*_flown`` entries), so the report describes what is simulated.
    """
    from uwbimu.design.trajectory.plots import save_calibration_figures
    from uwbimu.io.atomic import write_json, write_yaml
    from uwbimu.sim.scenario import load_scenario

    out = Path(out)
    res = design_calibration(cfg, progress=progress)
    files = []
    report: dict[str, Any] = {"name": cfg.name, "n_evals": res["n_evals"], "design_time_s": res["design_time_s"]}
    for key, m, desc in (
        ("designed", res["designed"], f"E-optimal calibration manoeuvre ({cfg.name})"),
        ("figure8", res["figure8"], f"naive figure-8 baseline, same duration and bounds ({cfg.name})"),
        ("figure8_excited", res["figure8_excited"], f"figure-8 with attitude excitation at the bounds ({cfg.name})"),
    ):
        tf = write_maneuver_file(m, out / f"{key}_trajectory.csv", cfg.waypoint_rate_hz)
        sf = write_yaml(out / f"{key}_scenario.yaml", scenario_dict(cfg, tf.name, f"{cfg.name}-{key}", desc))
        files += [tf, sf]
        sc = load_scenario(sf)  # read back exactly as `uwbimu simulate` will
        flown = evaluate_sim_trajectory(sc.trajectory.build(), cfg)
        report[key] = _plain_metrics(res[f"metrics_{key}"])
        report[f"{key}_flown"] = _plain_metrics(flown)
        report[f"{key}_maneuver"] = {
            "center": m.center.tolist(), "amplitude": m.amp.tolist(), "frequency_hz": m.freq.tolist(),
            "phase": m.phase.tolist(), "duration": m.duration, "ramp": m.ramp,
        }  # fmt: skip
    d = report["designed_flown"]
    for key in ("figure8", "figure8_excited"):
        f8 = report[f"{key}_flown"]
        report[f"predicted_ratio_{key}_over_designed"] = {
            "lever_arm_sigma_norm": float(np.linalg.norm(f8["sigma_lever_arm_m"]) / np.linalg.norm(d["sigma_lever_arm_m"])),
            "time_offset_sigma": float(f8["sigma_time_offset_s"] / d["sigma_time_offset_s"]),
        }
    report["config"] = cfg.model_dump(mode="json")
    if config_path is not None:
        report["config_file"] = str(config_path)
    files += save_calibration_figures(res, cfg, out)
    files.append(out / "design.json")
    report["files"] = [str(p) for p in files]
    write_json(out / "design.json", report)
    return report
