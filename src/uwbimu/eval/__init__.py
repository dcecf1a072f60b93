"""Evaluation of estimator outputs: alignment, ATE/RPE (from :mod:`uwbimu.metrics`), repeatability, the HTML report.

Public API::

    from uwbimu.eval import align_trajectories, evaluate_trajectory, evaluate_output
    from uwbimu.eval import repeatability, write_report

See ``docs/real_data.md`` and ``docs/report.md``.
"""

from importlib import import_module

#: public name -> defining module (resolved on first use, PEP 562: ``uwbimu.eval.clock_faults`` imported by
#: ``uwbimu estimate`` does not pull the repeatability study's scipy.stats or the report's renderer)
_EXPORTS = {
    "Alignment": "uwbimu.metrics.align", "align_trajectories": "uwbimu.metrics.align",
    "evaluate_output": "uwbimu.eval.evaluate",
    "associate": "uwbimu.metrics.trajectory", "detect_glitches": "uwbimu.metrics.trajectory",
    "evaluate_trajectory": "uwbimu.metrics.trajectory", "relative_pose_error": "uwbimu.metrics.trajectory",
    "consistency": "uwbimu.eval.repeatability", "repeatability": "uwbimu.eval.repeatability",
    "split_windows": "uwbimu.eval.repeatability",
    "render_report": "uwbimu.eval.report", "write_report": "uwbimu.eval.report",
}

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


def __getattr__(name: str):
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'uwbimu.eval' has no attribute {name!r}")
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value
