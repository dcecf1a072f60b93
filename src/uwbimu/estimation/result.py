"""What every estimator returns: one result type behind one interface.

Both the 19-state ESKF and the 6-state point-mass EKF fill an
:class:`EstimationResult`; writers, metrics, reports and the Monte Carlo
runner only ever see this type.  Estimators are looked up by name in
:mod:`uwbimu.estimation.registry`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
import pandas as pd


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
    calibration : dict with ``lever_arm``, ``lever_arm_sd``, ``time_offset``,
        ``time_offset_sd``, ``accel_bias``(+``_sd``), ``gyro_bias``(+``_sd``),
        ``anchor_bias`` (optional), as plain floats/lists.
    warnings : human-readable warnings raised during the run (excitation,
        outages, re-initialisations...).
    events : machine-readable event log (dicts with ``t``, ``kind``, ...).
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
    calibration: dict[str, Any]
    covariances: Optional[np.ndarray] = None
    warnings: list[str] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    estimator: str = "eskf"
    config: dict[str, Any] = field(default_factory=dict)
    runtime_s: float = float("nan")
    t_imu: Optional[np.ndarray] = None
    extra: dict[str, Any] = field(default_factory=dict)

