"""One metrics package: ATE/RPE, alignment, NEES and calibration errors.

Used by ``uwbimu estimate`` (:func:`compute_metrics`), ``uwbimu evaluate`` / the report
(:func:`evaluate_trajectory`, :func:`relative_pose_error`) and the Monte Carlo studies
(:func:`run_metrics`).  It sits in the layer of ``sim``/``estimation`` (it needs only
``models`` and ``io``), so the estimator's own output writer can score a run too.

* ``align.py``: Umeyama / SE(3) / yaw-only alignment of two trajectories;
* ``trajectory.py``: association, ground-truth glitch masks, ATE, RPE (estimator outputs
  against a reference trajectory, any source);
* ``filter.py``: errors of an :class:`~uwbimu.estimation.result.EstimationResult` against
  the dataset's truth: position/attitude RMSE, NEES, calibration errors.
"""

from uwbimu.metrics.align import Alignment, align_trajectories  # noqa: F401
from uwbimu.metrics.filter import attitude_error, compute_metrics, nees_series, run_metrics, truth_at  # noqa: F401
from uwbimu.metrics.trajectory import (  # noqa: F401
    Evaluation, associate, detect_glitches, error_stats, evaluate_trajectory, relative_pose_error,
)

__all__ = [
    "Alignment", "align_trajectories", "attitude_error", "compute_metrics", "nees_series", "run_metrics",
    "truth_at", "Evaluation", "associate", "detect_glitches", "error_stats", "evaluate_trajectory",
    "relative_pose_error",
]
