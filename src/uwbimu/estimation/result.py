"""What every estimator returns: one result type behind one interface.

Both the 19-state ESKF and the 6-state point-mass EKF fill an
:class:`EstimationResult`; writers, metrics, reports and the Monte Carlo
runner only ever see this type.  Estimators are looked up by name in
:mod:`uwbimu.estimation.registry`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
import pandas as pd

from uwbimu.typed import MappingResult


@dataclass(eq=False)
class CalibrationEstimate(MappingResult):
    """Calibration estimated by a filter run (final value and 1-sigma); reads like the former dict.

    Attributes
    ----------
    lever_arm, lever_arm_sd : tag antenna position in the IMU body frame and its sd [m], (3,).
    time_offset, time_offset_sd : UWB-IMU clock offset ``t_d`` and its sd [s].
    accel_bias, accel_bias_sd : accelerometer bias in the body frame [m/s^2], (3,).
    gyro_bias, gyro_bias_sd : gyroscope bias in the body frame [rad/s], (3,).
    extra : every other key of the estimator (``anchor_bias``, ``tags``, modes, verdicts...).

    ``cal.lever_arm`` and ``cal["lever_arm"]`` are the same value; :meth:`to_dict` gives the
    plain dictionary written to ``calibration.yaml``.
    """

    lever_arm: Optional[list[float]] = None
    lever_arm_sd: Optional[list[float]] = None
    time_offset: Optional[float] = None
    time_offset_sd: Optional[float] = None
    accel_bias: Optional[list[float]] = None
    accel_bias_sd: Optional[list[float]] = None
    gyro_bias: Optional[list[float]] = None
    gyro_bias_sd: Optional[list[float]] = None
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(eq=False)
class Event(MappingResult):
    """One entry of a run's event log; reads like the former dict.

    Attributes
    ----------
    t : time of the event on the UWB clock [s] (None for events without a time).
    kind : what happened (``initialised``, ``divergence``, ``reinitialised``, ``gate_reopened``,
        ``time_offset_verdict``, ``anchor_frame_override``, ...).
    extra : the event's other fields (``reason``, ``verdict``, ...).
    """

    t: Optional[float] = None
    kind: str = ""
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass
class EstimationResult:
    """Output of an estimator run over a dataset.

    Attributes
    ----------
    t : (K,) output stamps on the UWB clock [s].
    states : (K, 20) nominal states (layout of :mod:`uwbimu.models.state`); an
        estimator that does not estimate a block fills it with its fixed value
        (e.g. identity attitude, zero lever arm) and NaN standard deviations.
    covariances : (K, 19, 19) error-state covariances, or None when only the
        diagonal is kept (then ``sd`` must be given).
    sd : (K, 19) error-state standard deviations (NaN where not estimated).
    residuals : DataFrame ``t, anchor, range, predicted, innovation, nis, accepted``.
    calibration : :class:`CalibrationEstimate` (given as a dict, converted): ``lever_arm``,
        ``lever_arm_sd``, ``time_offset``, ``time_offset_sd``, ``accel_bias``(+``_sd``),
        ``gyro_bias``(+``_sd``), ``anchor_bias`` (optional), as plain floats/lists; read as
        attributes or as dict keys.
    warnings : human-readable warnings raised during the run (excitation,
        outages, re-initialisations...).
    events : machine-readable event log (dicts with ``t``, ``kind``, ...; typed: :meth:`event_log`).
    estimator : name of the estimator (``"eskf"``, ``"pointmass"``).
    config : the options used, as a plain dict (for provenance).
    runtime_s : wall time of the run [s].
    t_imu : (K,) the same output instants on the IMU clock [s] (optional).
    extra : estimator-specific arrays (e.g. ``anchor_bias_states`` (K, M)).
    """

    t: np.ndarray
    states: np.ndarray
    sd: np.ndarray
    residuals: pd.DataFrame
    calibration: CalibrationEstimate
    covariances: Optional[np.ndarray] = None
    warnings: list[str] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    estimator: str = "eskf"
    config: dict[str, Any] = field(default_factory=dict)
    runtime_s: float = float("nan")
    t_imu: Optional[np.ndarray] = None
    extra: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if isinstance(self.calibration, Mapping) and not isinstance(self.calibration, CalibrationEstimate):
            self.calibration = CalibrationEstimate.from_dict(self.calibration)

    def event_log(self) -> list[Event]:
        """The events as typed :class:`Event` records (``events`` keeps the plain dicts)."""
        return [e if isinstance(e, Event) else Event.from_dict(e) for e in self.events]

