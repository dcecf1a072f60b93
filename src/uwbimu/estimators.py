"""The estimator registry with every estimator: ``eskf``, ``pointmass`` and the batch calibrator ``batch``.

:mod:`uwbimu.estimation.registry` defines the registry and holds the filters of its own layer (``eskf``,
``pointmass``); the GTSAM batch calibrator (:mod:`uwbimu.calibration`) sits one layer above it, so it is
registered here, in a module above both.  Whoever needs the whole registry imports it from this module: the
CLI, the Monte Carlo studies (:mod:`uwbimu.studies.worker`) and the repeatability test
(:mod:`uwbimu.eval.repeatability`); nothing below imports it (``tests/test_layering.py``)::

    from uwbimu.estimators import get_estimator

    entry = get_estimator("batch")
    res = entry.run(dataset, entry.options({"td_profile": {"enabled": False}}), None)

``batch`` returns a :class:`uwbimu.calibration.CalibrationResult` (``calibration`` dict, ``trajectory``
DataFrame, ``residuals``), not an :class:`~uwbimu.estimation.result.EstimationResult`; its ``calibration``
dict is what repeatability reads (``entry.returns`` says which).
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
