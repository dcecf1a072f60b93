"""Evaluation of estimator outputs: alignment, ATE/RPE (from :mod:`uwbimu.metrics`), repeatability, the HTML report.

Public API::

    from uwbimu.eval import align_trajectories, evaluate_trajectory, evaluate_output
    from uwbimu.eval import repeatability, write_report

See ``docs/real_data.md`` and ``docs/report.md``.
"""

from uwbimu.metrics.align import Alignment, align_trajectories  # noqa: F401
from uwbimu.eval.evaluate import evaluate_output  # noqa: F401
from uwbimu.metrics.trajectory import associate, detect_glitches, evaluate_trajectory, relative_pose_error  # noqa: F401
from uwbimu.eval.repeatability import consistency, repeatability, split_windows  # noqa: F401
from uwbimu.eval.report import render_report, write_report  # noqa: F401

__all__ = [
    "Alignment",
    "align_trajectories",
    "associate",
    "detect_glitches",
    "evaluate_trajectory",
    "relative_pose_error",
    "evaluate_output",
    "consistency",
    "repeatability",
    "split_windows",
    "render_report",
    "write_report",
]
