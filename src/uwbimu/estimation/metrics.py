"""Moved to :mod:`uwbimu.metrics.filter` (one metrics package); kept for ``estimation/outputs.py``."""

from uwbimu.metrics.filter import attitude_error, compute_metrics, nees_series, truth_at  # noqa: F401

__all__ = ["attitude_error", "compute_metrics", "nees_series", "truth_at"]
