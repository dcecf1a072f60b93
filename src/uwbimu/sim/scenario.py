"""The simulation scenario: one typed, YAML-loadable description of a flight.

See ``docs/simulator.md`` for the YAML reference.  Units: SI (m, s, rad, Hz);
world frame z up; lever arms in the IMU frame.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from uwbimu.errors import ConfigError
from uwbimu.io.yamlconfig import load_yaml_model, validate_model
from uwbimu.models.imu import IMU_PRESETS, ImuNoise, imu_preset
from uwbimu.sim.trajspec import LissajousSpec, TrajectorySpec, Vec3

# --------------------------------------------------------------------------
# Anchors
# --------------------------------------------------------------------------
#: Named anchor layouts.  ``room8``: a 10 x 8 x 3 m room, four anchors low
#: (~0.3 m) near the corners and four high (~2.7 m) at mid-walls, staggered so
#: that no four are coplanar by construction and the heights differ.
ANCHOR_PRESETS: dict[str, dict[str, Vec3]] = {
    "room8": {
        "A0": (0.20, 0.30, 0.35),
        "A1": (9.70, 0.40, 0.25),
        "A2": (9.80, 7.70, 0.40),
        "A3": (0.30, 7.80, 0.30),
        "A4": (5.10, 0.15, 2.75),
        "A5": (9.85, 4.20, 2.65),
        "A6": (4.90, 7.85, 2.70),
        "A7": (0.15, 3.80, 2.80),
    },
    # Bitcraze Loco Positioning "box" layout: 8 anchors at the corners of a 4 x 4 x 2.4 m volume
    # (ids 0-7 as the Loco nodes are numbered; 0-3 at the floor, 4-7 at the ceiling, 4 above 0 ...).
    "bitcraze8": {
        "0": (0.0, 0.0, 0.1),
        "1": (4.0, 0.0, 0.1),
        "2": (4.0, 4.0, 0.1),
        "3": (0.0, 4.0, 0.1),
        "4": (0.0, 0.0, 2.5),
        "5": (4.0, 0.0, 2.5),
        "6": (4.0, 4.0, 2.5),
        "7": (0.0, 4.0, 2.5),
    },
    # Four anchors only (minimal 3-D set): two low, two high, on different walls.
    "room4": {
        "A0": (0.20, 0.30, 0.35),
        "A1": (9.70, 0.40, 2.70),
        "A2": (9.80, 7.70, 0.40),
        "A3": (0.30, 7.80, 2.75),
    },
}


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _str_id(v):
    return str(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else v


class AnchorSpec(_Spec):
    """One anchor: ``id`` (text) and world ``position`` [m]."""

    id: str
    position: Vec3

    @field_validator("id", mode="before")
    @classmethod
    def _id_as_text(cls, v):
        return _str_id(v)


class TagSpec(_Spec):
    """A UWB tag on the vehicle."""

    name: str
    lever_arm: Vec3 = Field(description="true antenna position in the IMU frame [m]")
    nominal_lever_arm: Optional[Vec3] = Field(
        default=None, description="nominal (e.g. CAD) value written to dataset.yaml tags; default none, so that nothing of the truth reaches an estimator [m]"
    )


# --------------------------------------------------------------------------
# Sensors
# --------------------------------------------------------------------------
class ImuSpec(_Spec):
    """IMU on its own clock: rate, noise model, initial biases, saturation."""

    rate_hz: float = Field(default=200.0, gt=0, le=10000, description="sample rate [Hz]")
    noise: Union[str, ImuNoise] = Field(
        default="bmi088", description=f"preset name {sorted(IMU_PRESETS)} or explicit ImuNoise densities"
    )
    noise_scale: float = Field(default=1.0, ge=0, description="multiplies every density and sigma0 (0: noise-free)")
    accel_bias: Optional[Vec3] = Field(
        default=None, description="initial accelerometer bias [m/s^2]; drawn from accel_bias_sigma0 (noise seed) if absent"
    )
    gyro_bias: Optional[Vec3] = Field(
        default=None, description="initial gyro bias [rad/s]; drawn from gyro_bias_sigma0 (noise seed) if absent"
    )
    accel_limit: Optional[float] = Field(default=None, gt=0, description="accelerometer saturation per axis [m/s^2]")
    gyro_limit: Optional[float] = Field(default=None, gt=0, description="gyro saturation per axis [rad/s]")

    @field_validator("noise")
    @classmethod
    def _known_preset(cls, v):
        if isinstance(v, str):
            try:
                imu_preset(v)
            except KeyError as exc:  # pydantic reports ValueErrors with the field path
                raise ValueError(exc.args[0]) from None
        return v

    def noise_model(self) -> ImuNoise:
        """The effective :class:`ImuNoise` (preset or explicit, times ``noise_scale``)."""
        base = imu_preset(self.noise) if isinstance(self.noise, str) else self.noise
        return base if self.noise_scale == 1.0 else base.scaled(self.noise_scale)


class NlosBurst(_Spec):
    """A time window in which ranges are NLOS with probability ``prob``."""

    t0: float = Field(description="start, UWB time [s]")
    t1: float = Field(description="end, UWB time [s]")
    anchor: Optional[str] = Field(default=None, description="anchor id, or null for all anchors")
    prob: float = Field(default=0.8, ge=0, le=1, description="NLOS probability inside the window")

    @field_validator("anchor", mode="before")
    @classmethod
    def _id_as_text(cls, v):
        return _str_id(v)

    @model_validator(mode="after")
    def _order(self):
        if self.t1 <= self.t0:
            raise ValueError(f"nlos burst t1 ({self.t1}) must be after t0 ({self.t0})")
        return self


class UwbSpec(_Spec):
    """UWB on the UWB clock: two-way ranging (``twr``) or time differences of arrival (``tdoa2`` / ``tdoa3``)."""

    mode: Literal["twr", "tdoa2", "tdoa3"] = Field(
        default="twr",
        description="twr: ranges (uwb.csv); tdoa2: slotted anchors, consecutive-slot differences; "
        "tdoa3: free-running anchors, random pairs (tdoa.csv); see uwbimu.sim.tdoa",
    )
    rate_hz: float = Field(
        default=50.0, gt=0, le=5000,
        description="twr: range slots per second; tdoa2: anchor slots (packets) per second; tdoa3: mean packets "
        "per second over all anchors [Hz]",
    )
    schedule: Literal["round_robin", "all"] = Field(
        default="round_robin", description="round_robin: one (tag, anchor) pair per slot; all: every pair each slot"
    )
    sigma: float = Field(
        default=0.05, ge=0,
        description="twr: white range noise sd; tdoa: tag receive-timestamp noise sd per packet (a difference "
        "has sqrt(2) times it) [m]",
    )
    clock_sigma: float = Field(default=0.0, ge=0, description="tdoa: anchor clock error sd per packet, white [m]")
    anchor_clock_sigma: dict[str, float] = Field(
        default_factory=dict, description="tdoa: clock_sigma per anchor id (overrides clock_sigma) [m]"
    )
    clock_rw: float = Field(
        default=0.0, ge=0, description="tdoa: anchor clock error random walk [m/sqrt(s)] (residual drift correction)"
    )
    tdoa3_max_age: float = Field(
        default=0.1, gt=0, description="tdoa3: a packet is differenced with another anchor's packet at most this old [s]"
    )
    tdoa3_interval_jitter: float = Field(
        default=0.5, ge=0, lt=1, description="tdoa3: relative spread of an anchor's transmit interval (uniform +-)"
    )
    nlos_prob: float = Field(default=0.0, ge=0, le=1, description="probability that a range is NLOS")
    nlos_scale: float = Field(default=0.3, gt=0, description="mean of the positive exponential NLOS excess [m]")
    nlos_bursts: list[NlosBurst] = Field(default_factory=list, description="windows of raised NLOS probability")
    anchor_bias: dict[str, float] = Field(default_factory=dict, description="constant range bias per anchor id [m]")
    dropout_prob: float = Field(default=0.0, ge=0, lt=1, description="probability that a range is lost")
    outages: list[tuple[float, float, Optional[str]]] = Field(
        default_factory=list, description="[t0, t1, anchor or null]: no ranges in [t0, t1) (UWB time, s)"
    )
    max_range: Optional[float] = Field(default=None, gt=0, description="ranges beyond this true distance are lost [m]")
    jitter_sd: float = Field(default=0.0, ge=0, description="timestamp jitter sd [s] (the range is at the nominal instant)")

    @field_validator("anchor_bias", "anchor_clock_sigma", mode="before")
    @classmethod
    def _keys_as_text(cls, v):
        return {str(k): val for k, val in v.items()} if isinstance(v, dict) else v

    @field_validator("outages", mode="before")
    @classmethod
    def _outage_ids(cls, v):
        if isinstance(v, list):
            return [[*o[:2], _str_id(o[2])] if isinstance(o, (list, tuple)) and len(o) == 3 else o for o in v]
        return v

    @field_validator("outages")
    @classmethod
    def _outage_order(cls, v):
        for i, (t0, t1, _) in enumerate(v):
            if t1 <= t0:
                raise ValueError(f"outage {i}: t1 ({t1}) must be after t0 ({t0})")
        return v


class Seeds(_Spec):
    """Independent random streams."""

    truth: int = Field(default=0, ge=0, description="trajectory randomness (type: random)")
    noise: int = Field(default=1, ge=0, description="sensor noise, biases, NLOS, dropouts, jitter")
    init: int = Field(default=2, ge=0, description="for the estimator's initial perturbation (carried in meta)")


# --------------------------------------------------------------------------
# Scenario
# --------------------------------------------------------------------------
class Scenario(_Spec):
    """A complete simulated flight (see ``docs/simulator.md``)."""

    name: str = Field(default="custom", description="dataset name")
    description: str = Field(default="", description="one line shown by 'uwbimu simulate --list'")
    duration: Optional[float] = Field(
        default=None, gt=0, le=36000, description="flight length [s]; default: the trajectory file's span"
    )
    trajectory: TrajectorySpec = Field(default_factory=LissajousSpec)
    imu: ImuSpec = Field(default_factory=ImuSpec)
    uwb: UwbSpec = Field(default_factory=UwbSpec)
    anchors: Union[str, list[AnchorSpec]] = Field(default="room8", description=f"preset {sorted(ANCHOR_PRESETS)} or list")
    lever_arm: Vec3 = Field(
        default=(0.0, 0.0, 0.0), description="UWB antenna in the IMU frame [m] (single tag; leave unset with tags)"
    )
    time_offset: float = Field(default=0.0, ge=-1.0, le=1.0, description="t_d [s]: IMU stamp s is UWB time s - t_d")
    tags: Optional[list[TagSpec]] = Field(default=None, description="several tags (replaces lever_arm)")
    seeds: Seeds = Field(default_factory=Seeds)

    @field_validator("anchors")
    @classmethod
    def _known_anchor_preset(cls, v):
        if isinstance(v, str) and v not in ANCHOR_PRESETS:
            raise ValueError(f"unknown anchor preset {v!r}; choose one of {', '.join(map(str, sorted(ANCHOR_PRESETS)))}")
        return v

    @model_validator(mode="after")
    def _consistent(self):
        if self.duration is None and self.trajectory.type != "file":
            raise ValueError("duration is required (only a trajectory file provides its own)")
        ids = self.anchor_ids()
        if len(ids) == 0:
            raise ValueError("at least one anchor is needed")
        if len(set(ids)) != len(ids):
            raise ValueError(f"duplicate anchor ids in {ids}")
        refs = [("uwb.anchor_bias", k) for k in self.uwb.anchor_bias]
        refs += [("uwb.outages", o[2]) for o in self.uwb.outages if o[2] is not None]
        refs += [("uwb.nlos_bursts", b.anchor) for b in self.uwb.nlos_bursts if b.anchor is not None]
        refs += [("uwb.anchor_clock_sigma", k) for k in self.uwb.anchor_clock_sigma]
        if self.uwb.mode != "twr":
            if len(ids) < 2:
                raise ValueError(f"uwb.mode {self.uwb.mode}: at least two anchors are needed")
            if self.tags is not None and len(self.tags) > 1:
                raise ValueError(f"uwb.mode {self.uwb.mode}: one tag only (TDoA is simulated for a single tag)")
            if any(v < 0 for v in self.uwb.anchor_clock_sigma.values()):
                raise ValueError("uwb.anchor_clock_sigma: values must be >= 0")
        for where, a in refs:
            if a not in ids:
                raise ValueError(f"{where}: unknown anchor {a!r}; anchors are {ids}")
        if self.tags is not None:
            # lever_arm belongs to the single-tag form; with tags it must stay at its default
            # (a full model_dump carries it) or repeat the first tag's.
            if tuple(self.lever_arm) not in ((0.0, 0.0, 0.0), tuple(self.tags[0].lever_arm)):
                raise ValueError("give either lever_arm (one tag) or tags (with their lever arms), not both")
            names = [t.name for t in self.tags]
            if not names or len(set(names)) != len(names):
                raise ValueError(f"tags need unique names, got {names}")
        return self

    # --- derived views -----------------------------------------------------
    def anchor_ids(self) -> list[str]:
        if isinstance(self.anchors, str):
            return list(ANCHOR_PRESETS[self.anchors])
        return [a.id for a in self.anchors]

    def anchor_positions(self) -> np.ndarray:
        """(M, 3) anchor positions in the order of :meth:`anchor_ids` [m]."""
        if isinstance(self.anchors, str):
            return np.array(list(ANCHOR_PRESETS[self.anchors].values()), dtype=float)
        return np.array([a.position for a in self.anchors], dtype=float)

    def tag_list(self) -> list[TagSpec]:
        """The tags (one ``tag0`` with ``lever_arm`` unless ``tags`` is given)."""
        if self.tags is None:
            return [TagSpec(name="tag0", lever_arm=self.lever_arm)]
        return list(self.tags)

    def updated(self, **changes) -> "Scenario":
        """A validated copy with ``changes`` deep-merged (nested dicts merge, lists replace).

        Prefer this to ``model_copy(update=...)``, which neither validates nor
        converts nested dicts.  A ``trajectory`` update with a different
        ``type`` replaces the trajectory block instead of merging into it.
        Example: ``sc.updated(time_offset=0.05, uwb={"sigma": 0.1})``.
        """
        data = self.model_dump(mode="python", warnings=False)
        traj = changes.get("trajectory")
        if isinstance(traj, dict) and traj.get("type", self.trajectory.type) != self.trajectory.type:
            data["trajectory"] = {}
        return validate_scenario(_deep_merge(data, changes), f"scenario {self.name!r} update")

    def to_yaml(self) -> str:
        """YAML text that :func:`load_scenario` reads back to an equal scenario."""
        return yaml.safe_dump(self.model_dump(mode="json", exclude_none=True), sort_keys=False)


def _deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, BaseModel):
            v = v.model_dump(mode="python", warnings=False)
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = v
    return out


class ScenarioError(ConfigError):
    """A scenario file that cannot be read (message names the file, line and field; exit code 1)."""


def validate_scenario(data: dict, source: str = "<scenario>") -> Scenario:
    """``Scenario.model_validate`` with errors re-raised as :class:`ScenarioError` naming ``source``."""
    return validate_model(data, Scenario, source=source, what="scenario", error=ScenarioError)


def load_scenario(path: str | os.PathLike) -> Scenario:
    """Read a scenario YAML file.

    A relative ``trajectory.path`` (type ``file``) is resolved against the
    folder of the scenario file.  Errors raise :class:`ScenarioError` naming
    the file, the line and the offending field.
    """
    path = Path(path)

    def prepare(data: dict) -> dict:
        traj = data.get("trajectory")
        if isinstance(traj, dict) and traj.get("type") == "file" and isinstance(traj.get("path"), str):
            p = Path(traj["path"]).expanduser()
            if not p.is_absolute():
                p = (path.parent / p).resolve()
            data = {**data, "trajectory": {**traj, "path": str(p)}}
        data.setdefault("name", path.stem)
        return data

    return load_yaml_model(path, Scenario, what="scenario", error=ScenarioError, prepare=prepare)
