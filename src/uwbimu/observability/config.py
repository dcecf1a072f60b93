"""Options of the observability analyses (one typed place, loadable from YAML).

A configuration describes *what* is analysed: the model, the anchors, the
excitation and the points at which the rank test is evaluated.  Example
(``examples/observability/theorem2_generic.yaml``)::

    model: uwb_imu            # or point_mass
    anchors: [[0, 0, 0], [5, 0, 0.5], [0, 5, 1.0]]
    lever_arm: [0.1, 0.05, 0.2]
    lie_order: auto           # raise until full rank or stalled (cap lie_order_cap)
    excitation: {accel: [x, y, z], gyro: [x, y, z]}
    random_points: 20
    seed: 0
"""

from __future__ import annotations

import os
from typing import Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, field_validator

from uwbimu.errors import ConfigError  # re-exported here: a configuration that cannot be used
from uwbimu.io.yamlconfig import load_yaml_model, validate_model

Axis = Literal["x", "y", "z"]
Vec3 = list[float]


class Excitation(BaseModel):
    """Which input channels are excited (their input fields enter the words).

    A channel that is not excited is held at its constant ``nominal_input``
    value, which enters the drift.  ``None`` = model default: all six IMU axes
    for ``uwb_imu``, none for ``point_mass`` (seed 002 analyses the drift only).
    """

    model_config = ConfigDict(extra="forbid")
    accel: Optional[list[Axis]] = None
    gyro: Optional[list[Axis]] = None

    @field_validator("accel", "gyro")
    @classmethod
    def _unique(cls, v):
        if v is not None and len(set(v)) != len(v):
            raise ValueError("axes must not repeat")
        return v


class PointSpec(BaseModel):
    """An evaluation point; omitted blocks are drawn at random (seeded)."""

    model_config = ConfigDict(extra="forbid")
    p: Optional[Vec3] = Field(default=None, min_length=3, max_length=3)
    v: Optional[Vec3] = Field(default=None, min_length=3, max_length=3)
    q: Optional[list[float]] = Field(default=None, min_length=4, max_length=4)
    b_a: Optional[Vec3] = Field(default=None, min_length=3, max_length=3)
    b_g: Optional[Vec3] = Field(default=None, min_length=3, max_length=3)
    #: put the *antenna* (p + R p_IU) at this world position (overrides ``p``)
    antenna: Optional[Vec3] = Field(default=None, min_length=3, max_length=3)


class ObservabilityConfig(BaseModel):
    """Configuration of ``uwbimu observability structural|delay``.

    Attributes
    ----------
    model : ``uwb_imu`` (seed 001, 19 numbers / 18 tangent dims without t_d) or
        ``point_mass`` (seed 002, 6 states).
    measurement : ``range`` (two-way ranges to every anchor) or ``tdoa``
        (uwb_imu only: time differences of arrival ``|p_U - p_i| - |p_U - p_0|``,
        i = 1..N-1, which span the codistribution of every pair's difference).
    anchors : anchor (beacon) positions, world frame [m].
    lever_arm : ``p_IU`` [m, IMU frame]; None = random per point (uwb_imu).
    altimeter : add a height measurement ``z`` (point_mass only).
    lie_order : ``"auto"`` (default): raise the Lie order from 0 until the
        rank is full or has not grown for two orders, up to ``lie_order_cap``
        (and a budget of Lie rows); at the cap the verdict is cross-checked by
        the trajectory sensitivity test.  An integer: that order only; a rank
        deficit is then reported as "not shown observable at order k".
    lie_order_cap : highest order the automatic search tries (0..6).
    excitation : excited input axes (see :class:`Excitation`).
    nominal_input : constant input of the non-excited channels, ``[a_m, w_m]``
        (6, uwb_imu) or world acceleration (3, point_mass); None = random.
    points : explicit evaluation points; with none, ``random_points`` random ones.
    random_points : number of random points when ``points`` is empty.
    seed : RNG seed of every random draw.
    tolerance : relative singular-value tolerance of the rank decision;
        ``None`` (default) = adaptive: the rounding-noise floor of the
        nondimensionalised matrix (see ``engine.noise_floor``).
    time_offset : ``t_d`` [s] used by the numeric check of Theorem 1.
    all_words : always use every Lie word up to ``lie_order`` (slower; gives
        the 4-vector ``raw_rank`` too), instead of words selected at a generic
        point with the all-words fallback on rank deficiency.
    """

    model_config = ConfigDict(extra="forbid")
    name: str = "unnamed"
    description: str = ""
    model: Literal["uwb_imu", "point_mass"] = "uwb_imu"
    measurement: Literal["range", "tdoa"] = "range"
    anchors: list[Vec3] = Field(min_length=1)
    lever_arm: Optional[Vec3] = Field(default=None, min_length=3, max_length=3)
    altimeter: bool = False
    lie_order: Union[Literal["auto"], int] = "auto"
    lie_order_cap: int = Field(default=6, ge=0, le=6)
    excitation: Excitation = Field(default_factory=Excitation)
    nominal_input: Optional[list[float]] = None
    points: list[PointSpec] = Field(default_factory=list)
    random_points: int = Field(default=1, ge=1, le=1000)
    seed: int = 0
    tolerance: Optional[float] = Field(default=None, gt=0, lt=1)
    time_offset: float = Field(default=0.01, gt=0)
    all_words: bool = False

    @field_validator("anchors")
    @classmethod
    def _three(cls, v):
        for i, a in enumerate(v):
            if len(a) != 3:
                raise ValueError(f"anchor {i} must have 3 coordinates, got {len(a)}")
        return v

    @field_validator("lie_order")
    @classmethod
    def _order(cls, v):
        if v != "auto" and not 0 <= int(v) <= 6:
            raise ValueError("must be 'auto' or an integer 0..6")
        return v

    def accel_axes(self) -> tuple[str, ...]:
        if self.excitation.accel is not None:
            return tuple(sorted(self.excitation.accel))
        return ("x", "y", "z") if self.model == "uwb_imu" else ()

    def gyro_axes(self) -> tuple[str, ...]:
        if self.model != "uwb_imu":
            return ()
        return tuple(sorted(self.excitation.gyro)) if self.excitation.gyro is not None else ("x", "y", "z")


def load_config(source: Union[str, os.PathLike, dict, ObservabilityConfig]) -> ObservabilityConfig:
    """Read and validate a configuration (path to YAML, dict or config)."""
    if isinstance(source, ObservabilityConfig):
        return source
    if isinstance(source, (str, os.PathLike)):
        where = str(source)
        cfg = load_yaml_model(source, ObservabilityConfig, what="configuration")
    else:
        where = "<dict>"
        if not isinstance(source, dict):
            raise ConfigError(f"{where}: expected a mapping at the top level")
        cfg = validate_model(source, ObservabilityConfig, source=where, what="configuration")
    n_in = 6 if cfg.model == "uwb_imu" else 3
    if cfg.nominal_input is not None and len(cfg.nominal_input) != n_in:
        raise ConfigError(f"{where}: field 'nominal_input' must have {n_in} numbers for model {cfg.model}")
    if cfg.model == "point_mass" and cfg.excitation.gyro:
        raise ConfigError(f"{where}: field 'excitation.gyro' is not defined for model point_mass")
    if cfg.model == "point_mass" and cfg.lever_arm is not None:
        raise ConfigError(f"{where}: field 'lever_arm' is only available for model uwb_imu")
    if cfg.model == "point_mass" and any(sp.q or sp.b_a or sp.b_g for sp in cfg.points):
        raise ConfigError(f"{where}: field 'points': q, b_a, b_g are only available for model uwb_imu")
    if cfg.measurement == "tdoa" and cfg.model != "uwb_imu":
        raise ConfigError(f"{where}: field 'measurement': tdoa is only available for model uwb_imu")
    if cfg.measurement == "tdoa" and len(cfg.anchors) < 2:
        raise ConfigError(f"{where}: field 'anchors': measurement tdoa needs at least 2 anchors")
    if cfg.model == "uwb_imu" and cfg.altimeter:
        raise ConfigError(f"{where}: field 'altimeter' is only available for model point_mass")
    return cfg
