"""Typed options for ``uwbimu place`` (pydantic, loadable from YAML).

A minimal room config::

    mode: room
    seed: 0
    n_anchors: 6
    measurement: twr                  # or tdoa (differences to a reference anchor)
    radio: {preset: dw1000-indoor, antenna: {type: omni}, range_sigma: 0.1, k: 3}
    room:
      box: [10, 8, 3]                 # or polygon: [[x, y], ...] + height
      mount: {surfaces: [walls, ceiling, floor], standoff: 0.2, spacing: 0.5}
      flight_volume: {lo: [0.5, 0.5, 0.3], hi: [9.5, 7.5, 2.5]}
    objective: {weights: {coverage: 10, pdop: 1, n1_pdop: 0.25}, percentile: 95}

See ``docs/placement.md`` for every field.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, model_validator

from uwbimu import errors
from uwbimu.io.yamlconfig import load_yaml_model

__all__ = [
    "AntennaConfig",
    "RadioConfig",
    "ObstacleConfig",
    "MountConfig",
    "VolumeConfig",
    "RoomConfig",
    "ObjectiveConfig",
    "OptimizerConfig",
    "StructureConfig",
    "PlacementConfig",
    "ConfigError",
    "load_config",
]


class _M(BaseModel):
    model_config = ConfigDict(extra="forbid")


class AntennaConfig(_M):
    """Anchor antenna: ``omni``, ``cosn`` (beamwidth) or ``table`` (CSV pattern)."""

    type: Literal["omni", "cosn", "table"] = "omni"
    gain_dbi: float = 0.0  # omni gain
    beamwidth_deg: float = Field(90.0, gt=0, lt=180)
    peak_gain_dbi: Optional[float] = None
    front_to_back_db: float = Field(20.0, ge=0)
    csv: Optional[str] = None  # table pattern file (azimuth_deg, elevation_deg, gain_dbi)

    @model_validator(mode="after")
    def _need_csv(self):
        if self.type == "table" and not self.csv:
            raise ValueError("antenna.type 'table' needs antenna.csv (a CSV of azimuth_deg, elevation_deg, gain_dbi)")
        return self


class RadioConfig(_M):
    """Link budget: preset or explicit 0 dBi LOS range, antennas, NLOS loss, noise, k.

    ``range_sigma`` is the sd of one two-way range; ``tdoa_sigma`` the sd of one TDoA
    (one difference ``r_i - r_ref``), default ``sqrt(2) range_sigma`` (the same per-anchor
    timing noise as the ranges, as in the filter's ``tdoa_sigma``).  ``k`` defaults to 3
    links for ``measurement: twr`` and 4 for ``tdoa`` (3 differences for a 3-D fix).
    """

    preset: Literal["dw1000-indoor", "dw1000-long-range", "outdoor-high-power"] = "dw1000-indoor"
    max_range: Optional[float] = Field(None, gt=0, description="overrides the preset's 0 dBi LOS range, m")
    antenna: AntennaConfig = Field(default_factory=AntennaConfig)
    tag_gain_dbi: float = 0.0
    nlos_loss_db: float = Field(10.0, ge=0)
    range_sigma: float = Field(0.1, gt=0, description="range noise sd, m")
    tdoa_sigma: Optional[float] = Field(
        None, gt=0, description="sd of one TDoA measurement (r_i - r_ref), m; None: sqrt(2) range_sigma")
    k: Optional[int] = Field(
        None, ge=1, description="links needed for a point to count as covered; None: 3 (twr), 4 (tdoa)")

    @property
    def tdoa_sigma_m(self) -> float:
        """The TDoA sd in use [m]: ``tdoa_sigma``, else ``sqrt(2) range_sigma``."""
        return float(self.tdoa_sigma) if self.tdoa_sigma is not None else math.sqrt(2.0) * self.range_sigma


class ObstacleConfig(_M):
    """A box ``{box: {lo, hi}}`` or a bar ``{bar: {p0, p1, radius}}`` with optional loss."""

    box: Optional[dict[str, list[float]]] = None
    bar: Optional[dict[str, object]] = None
    loss_db: Optional[float] = Field(None, ge=0)

    @model_validator(mode="after")
    def _one(self):
        if (self.box is None) == (self.bar is None):
            raise ValueError("an obstacle needs exactly one of 'box' or 'bar'")
        if self.box is not None:
            if set(self.box) != {"lo", "hi"} or any(len(v) != 3 for v in self.box.values()):
                raise ValueError("box needs lo: [x, y, z] and hi: [x, y, z]")
            if any(a > b for a, b in zip(self.box["lo"], self.box["hi"])):
                raise ValueError(f"box lo {self.box['lo']} must be <= hi {self.box['hi']}")
        if self.bar is not None:
            if not {"p0", "p1"} <= set(self.bar) or not set(self.bar) <= {"p0", "p1", "radius"}:
                raise ValueError("bar needs p0: [x, y, z], p1: [x, y, z] and optional radius")
        return self


class MountConfig(_M):
    """Where anchors may go: surfaces with a stand-off, sampled every ``spacing`` m."""

    surfaces: list[Literal["walls", "ceiling", "floor"]] = Field(default_factory=lambda: ["walls", "ceiling", "floor"])
    standoff: float = Field(0.2, ge=0, description="distance from the surface, m")
    spacing: float = Field(0.5, gt=0, description="candidate spacing, m")
    z_min: Optional[float] = None  # lowest wall mounting height, m (default standoff)
    z_max: Optional[float] = None  # highest wall mounting height, m (default height - standoff)


class VolumeConfig(_M):
    lo: list[float] = Field(min_length=3, max_length=3)
    hi: list[float] = Field(min_length=3, max_length=3)


class RoomConfig(_M):
    """Room: a box ``[L, W, H]`` (corner at the origin) or an extruded polygon."""

    box: Optional[list[float]] = Field(None, min_length=3, max_length=3)
    polygon: Optional[list[list[float]]] = None
    height: Optional[float] = Field(None, gt=0)
    obstacles: list[ObstacleConfig] = Field(default_factory=list)
    mount: MountConfig = Field(default_factory=MountConfig)
    candidates: Optional[list[list[float]]] = None  # explicit candidate anchor points, m
    flight_volume: Optional[VolumeConfig] = None  # default: room inset by 0.5 m, z 0.3..H-0.5
    grid_step: float = Field(0.5, gt=0, description="tag sample spacing, m")

    @model_validator(mode="after")
    def _shape(self):
        if (self.box is None) == (self.polygon is None):
            raise ValueError("room needs exactly one of 'box: [L, W, H]' or 'polygon' + 'height'")
        if self.polygon is not None:
            if self.height is None:
                raise ValueError("room.polygon needs room.height")
            if len(self.polygon) < 3 or any(len(p) != 2 for p in self.polygon):
                raise ValueError("room.polygon must be a list of >= 3 [x, y] vertices")
        if self.box is not None and any(v <= 0 for v in self.box):
            raise ValueError(f"room.box sizes must be > 0, got {self.box}")
        if self.candidates is not None and any(len(c) != 3 for c in self.candidates):
            raise ValueError("room.candidates must be [x, y, z] triples")
        return self


class ObjectiveConfig(_M):
    """Weighted objective (minimised).

    ``w_coverage 100 (1 - coverage) + w_pdop PDOP_q + w_n1_pdop max_i PDOP_q(-i)
    + w_n1_coverage 100 (1 - min_i coverage(-i)) - w_info logdetJ_(100-q)
    + w_hull 100 (fraction of the flight volume outside the anchors' convex hull)``, with
    ``q`` the percentile (PDOP upper tail, information lower tail).
    """

    weights: dict[Literal["coverage", "pdop", "n1_pdop", "n1_coverage", "info", "hull"], float] = Field(
        default_factory=lambda: {"coverage": 10.0, "pdop": 1.0, "n1_pdop": 0.25}
    )
    percentile: float = Field(95.0, gt=0, le=100)
    pdop_cap: float = Field(20.0, gt=1, description="PDOP used for points that are not observable")
    pareto: bool = False


class OptimizerConfig(_M):
    greedy: bool = True
    swaps: bool = True
    swap_rounds: int = Field(4, ge=0)
    refine: bool = True  # scipy differential evolution on the mounting surfaces
    maxiter: int = Field(40, ge=1)
    popsize: int = Field(8, ge=2)
    workers: int = Field(1, ge=1)


class StructureConfig(_M):
    """Structure mode (jib crane of the seed, or a girder bridge)."""

    name: Literal["jib-crane", "bridge"] = "jib-crane"
    range_m: float = Field(30.0, gt=0, description="0 dBi LOS range R0, m")
    beamwidth_deg: float = Field(90.0, gt=0, lt=180)
    # How the 4 anchors of a crane station face (the seed does not say): corner diagonals or face
    # normals.  Each reading has its own fitted R0 (docs/placement.md); ignored for the bridge.
    reading: Literal["diagonal", "axis-aligned"] = "diagonal"
    stations_per_rail: Optional[list[int]] = None
    freedom: Literal["seed", "rotate", "rotate-tilt"] = "rotate-tilt"
    reproduce_seed: bool = True  # also run the seed's set-up (10 variables, PSO)
    pso_particles: int = Field(24, ge=2)
    pso_iters: int = Field(40, ge=1)
    grid_step: Optional[float] = Field(None, gt=0)
    local_search: bool = True
    objective: Literal["coverage", "geometric"] = "coverage"  # geometric: k links AND PDOP <= pdop_max
    pdop_max: float = Field(5.0, gt=1)


class PlacementConfig(_M):
    mode: Literal["room", "structure"] = "room"
    seed: int = 0
    n_anchors: int = Field(6, ge=1)
    measurement: Literal["twr", "tdoa"] = "twr"  # two-way ranges, or TDoA to a reference anchor (room mode)
    radio: RadioConfig = Field(default_factory=RadioConfig)
    room: Optional[RoomConfig] = None
    structure: Optional[StructureConfig] = None
    objective: ObjectiveConfig = Field(default_factory=ObjectiveConfig)
    optimizer: OptimizerConfig = Field(default_factory=OptimizerConfig)
    compare: dict[str, list[list[float]]] = Field(default_factory=dict)  # named reference layouts

    @model_validator(mode="after")
    def _mode(self):
        for name, lay in self.compare.items():
            for i, p in enumerate(lay):
                if len(p) != 3:
                    raise ValueError(f"compare.{name}[{i}] must be [x, y, z], got {p}")
        if self.mode == "room" and self.room is None:
            raise ValueError("mode 'room' needs a 'room' section")
        if self.mode == "structure" and self.structure is None:
            raise ValueError("mode 'structure' needs a 'structure' section")
        if self.measurement == "tdoa" and self.mode != "room":
            raise ValueError("measurement 'tdoa' is supported in room mode only (structure mode evaluates "
                             "two-way ranges); use measurement: twr")
        if self.radio.k is None:
            self.radio.k = 4 if self.measurement == "tdoa" else 3
        elif self.measurement == "tdoa" and self.radio.k < 4:
            raise ValueError(f"radio.k = {self.radio.k} with measurement 'tdoa': a 3-D TDoA fix needs >= 4 anchors "
                             "in range (3 differences); set radio.k >= 4 or leave it out (default 4 for tdoa)")
        return self


class ConfigError(errors.ConfigError):
    """A placement config file is missing or invalid (message names file, line and field; exit 2)."""


def _resolve_antenna_csv(path: Path):
    def prepare(data: dict) -> dict:
        # relative antenna CSV paths are relative to the config's folder
        ant = (data.get("radio") or {}).get("antenna") if isinstance(data.get("radio"), dict) else None
        if isinstance(ant, dict) and isinstance(ant.get("csv"), str) and not Path(ant["csv"]).is_absolute():
            ant["csv"] = str((path.parent / ant["csv"]).resolve())
        return data

    return prepare


def load_config(path: str | Path) -> PlacementConfig:
    """Read and validate a placement YAML (:func:`uwbimu.io.yamlconfig.load_yaml_model`); errors name the
    file, line and field."""
    path = Path(path)
    return load_yaml_model(path, PlacementConfig, what="placement config", error=ConfigError,
                           prepare=_resolve_antenna_csv(path))
