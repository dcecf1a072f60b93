"""Moved: the registry with every estimator is :mod:`uwbimu.estimators` (above calibration, below eval and
studies).  This module re-exports it for code that still imports ``uwbimu.eval.estimators``."""

from __future__ import annotations

from uwbimu.estimators import EstimatorEntry, estimator_names, get_estimator, register_estimator  # noqa: F401

__all__ = ["EstimatorEntry", "get_estimator", "estimator_names", "register_estimator"]
