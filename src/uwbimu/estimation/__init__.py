"""State estimation: the tightly-coupled UWB-IMU error-state EKF and its outputs.

Public API::

    from uwbimu.estimation import EskfOptions, run_eskf, write_outputs, compute_metrics

    res = run_eskf(dataset, EskfOptions.from_yaml("estimator.yaml"))
    write_outputs(res, dataset, "out/")     # trajectory.csv, calibration.yaml, residuals.csv, ...
    compute_metrics(res, dataset)           # needs ground truth

See ``docs/estimator.md``.
"""

from uwbimu.estimation.options import EskfOptions  # noqa: F401
from uwbimu.estimation.result import EstimationResult  # noqa: F401
from uwbimu.estimation.init import InitialState, InitialisationError  # noqa: F401
from uwbimu.estimation.eskf import run_eskf  # noqa: F401
from uwbimu.estimation.streaming import Eskf, EskfState  # noqa: F401
from uwbimu.estimation.metrics import compute_metrics, truth_at  # noqa: F401
from uwbimu.estimation.outputs import write_outputs, residual_table  # noqa: F401
from uwbimu.estimation.pointmass import PointMassOptions, run_pointmass  # noqa: F401

__all__ = [
    "EskfOptions",
    "EstimationResult",
    "InitialState",
    "InitialisationError",
    "run_eskf",
    "Eskf",
    "EskfState",
    "compute_metrics",
    "truth_at",
    "write_outputs",
    "residual_table",
    "PointMassOptions",
    "run_pointmass",
]
