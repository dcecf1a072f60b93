"""State estimation: the tightly-coupled UWB-IMU error-state EKF and its outputs.

Public API::

    from uwbimu.estimation import EskfOptions, run_eskf, write_outputs, compute_metrics

    res = run_eskf(dataset, EskfOptions.from_yaml("estimator.yaml"))
    write_outputs(res, dataset, "out/")     # trajectory.csv, calibration.yaml, residuals.csv, ...
    compute_metrics(res, dataset)           # needs ground truth

Names are resolved on first use (PEP 562): ``from uwbimu.estimation import write_outputs`` imports the
output writer, not the point-mass EKF, the streaming filter's extras or the metrics as well (``uwbimu
estimate`` pays at start for what it runs).  See ``docs/estimator.md``.
"""

from __future__ import annotations

from importlib import import_module

#: public name -> defining module
_EXPORTS = {
    "EskfOptions": "uwbimu.estimation.options",
    "EstimationResult": "uwbimu.estimation.result",
    "InitialState": "uwbimu.estimation.init",
    "InitialisationError": "uwbimu.estimation.init",
    "run_eskf": "uwbimu.estimation.eskf",
    "Eskf": "uwbimu.estimation.streaming",
    "EskfState": "uwbimu.estimation.streaming",
    "compute_metrics": "uwbimu.estimation.metrics",
    "truth_at": "uwbimu.estimation.metrics",
    "write_outputs": "uwbimu.estimation.outputs",
    "residual_table": "uwbimu.estimation.outputs",
    "PointMassOptions": "uwbimu.estimation.pointmass",
    "run_pointmass": "uwbimu.estimation.pointmass",
}

__all__ = list(_EXPORTS)


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'uwbimu.estimation' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value  # cache: later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
