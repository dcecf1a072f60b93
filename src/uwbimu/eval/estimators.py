"""The estimator registry with every estimator, the batch calibrator included.

:mod:`uwbimu.estimation.registry` holds ``eskf`` and ``pointmass``; the GTSAM batch
calibrator (:mod:`uwbimu.calibration`) sits one layer above, so it is registered here.
The CLI, the Monte Carlo studies and the repeatability test import :func:`get_estimator`
from this module.  ``batch`` returns a :class:`uwbimu.calibration.CalibrationResult`
(``calibration`` dict, ``trajectory`` DataFrame, ``residuals``), not an
:class:`~uwbimu.estimation.result.EstimationResult`; its ``calibration`` dict is what
repeatability reads.
"""

from __future__ import annotations

from uwbimu.estimation.registry import EstimatorEntry, estimator_names, get_estimator, register_estimator

__all__ = ["EstimatorEntry", "get_estimator", "estimator_names", "register_estimator"]


def _run_batch(dataset, options, progress=None):
    from uwbimu.calibration import calibrate

    return calibrate(dataset, options, progress=progress)


def _register_batch() -> None:
    try:
        from uwbimu.calibration.options import CalibrationOptions
    except ImportError:  # pragma: no cover - options are pure pydantic; GTSAM is imported by calibrate
        return
    register_estimator(EstimatorEntry("batch", _run_batch, CalibrationOptions,
                                      "full-log MAP calibration with a GTSAM factor graph (needs gtsam)",
                                      returns="CalibrationResult"))


_register_batch()
