"""One estimator registry: name -> how to run it, its options model, one line of help.

The CLI (``uwbimu estimate --estimator NAME``), the Monte Carlo studies (``kind: NAME``) and
the repeatability test all look estimators up here, so a new estimator is added once::

    from uwbimu.estimators import get_estimator  # every estimator, the batch calibrator included

    entry = get_estimator("pointmass")
    res = entry.run(dataset, entry.options({"attitude": "gyro"}), progress=None)

``eskf`` and ``pointmass`` live in this layer.  ``batch`` (the GTSAM calibrator of
:mod:`uwbimu.calibration`) sits one layer up, so it is registered by :mod:`uwbimu.estimators`,
a module above both (imports only go down): import the whole registry from there.  ``batch``
returns a :class:`uwbimu.calibration.CalibrationResult`, not an :class:`EstimationResult`
(``entry.returns`` says which).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional

__all__ = ["EstimatorEntry", "register_estimator", "get_estimator", "estimator_names"]


@dataclass(frozen=True)
class EstimatorEntry:
    """One registered estimator.

    Attributes
    ----------
    name : registry key (``--estimator`` value, study ``kind``).
    run : ``run(dataset, options, progress) -> result``; ``progress`` is ``None`` or a
        callable taking the completed fraction in [0, 1].
    options_model : strict pydantic model of the options (``options_model()`` = defaults).
    description : one line for help texts.
    returns : ``"EstimationResult"`` or the name of the result type when it differs.
    """

    name: str
    run: Callable[[Any, Any, Optional[Callable[[float], None]]], Any]
    options_model: type
    description: str
    returns: str = "EstimationResult"

    def options(self, value: Any = None):
        """Validate ``value`` (None, dict or an instance) into the options model.

        Raises
        ------
        uwbimu.errors.ConfigError
            ``value`` does not validate (names the field; exit code 2 on the command line).
        """
        if value is None:
            return self.options_model()
        if isinstance(value, self.options_model):
            return value
        from uwbimu.io.yamlconfig import validate_model

        return validate_model(value, self.options_model, source=f"{self.name} options",
                              what=f"{self.name} estimator options")


_REGISTRY: dict[str, EstimatorEntry] = {}


def register_estimator(entry: EstimatorEntry) -> EstimatorEntry:
    """Add (or replace) ``entry`` under ``entry.name``; returns it."""
    _REGISTRY[entry.name] = entry
    return entry


def estimator_names() -> list[str]:
    """Registered names, in registration order."""
    return list(_REGISTRY)


def get_estimator(name: str) -> EstimatorEntry:
    """The entry registered as ``name``; ``KeyError`` naming the known ones otherwise."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown estimator {name!r}; known: {', '.join(_REGISTRY)}") from None


def _run_eskf(dataset, options, progress=None):
    from uwbimu.estimation.eskf import run_eskf

    return run_eskf(dataset, options, progress=progress)


def _run_pointmass(dataset, options, progress=None):
    from uwbimu.estimation.pointmass import run_pointmass

    return run_pointmass(dataset, options, progress)


def _register_builtin() -> None:
    from uwbimu.estimation.options import EskfOptions
    from uwbimu.estimation.pointmass import PointMassOptions

    register_estimator(EstimatorEntry("eskf", _run_eskf, EskfOptions,
                                      "19-state UWB-IMU error-state EKF (lever arm, time offset, biases)"))
    register_estimator(EstimatorEntry("pointmass", _run_pointmass, PointMassOptions,
                                      "6-state point-mass EKF driven by world accelerations (seed 002)"))


_register_builtin()
