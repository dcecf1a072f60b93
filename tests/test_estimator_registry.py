"""The estimator registry: one lookup for the CLI, the studies and repeatability."""

from __future__ import annotations

import pytest

from uwbimu.estimation.registry import get_estimator
from uwbimu.eval.estimators import estimator_names
from uwbimu.estimation import EskfOptions, PointMassOptions


def test_names_and_options_models():
    assert estimator_names()[:2] == ["eskf", "pointmass"]
    assert "batch" in estimator_names()
    assert get_estimator("eskf").options_model is EskfOptions
    assert get_estimator("pointmass").options({"attitude": "identity"}).attitude == "identity"
    assert get_estimator("batch").returns == "CalibrationResult"


def test_unknown_name_lists_known_ones():
    with pytest.raises(KeyError, match="pointmass"):
        get_estimator("ukf")


def test_strict_options_refuse_unknown_field():
    with pytest.raises(ValueError, match="no_such"):
        get_estimator("pointmass").options({"no_such": 1})
