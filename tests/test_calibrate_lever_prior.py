"""The batch's lever-arm prior mean for one tag: the configured one, else the tag's nominal lever arm in
dataset.yaml (the ESKF's default ``lever_arm.prior: dataset``), else zero."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

pytest.importorskip("gtsam")

from uwbimu.calibration.graph import _tag_levers  # noqa: E402
from uwbimu.calibration.options import CalibrationOptions  # noqa: E402
from uwbimu.io.dataset import TagMeta  # noqa: E402

NOMINAL = [-0.012, 0.001, 0.091]
ESKF = SimpleNamespace(calibration={"lever_arm": [0.1, 0.2, 0.3]})


def _ds(tags):
    return SimpleNamespace(meta=SimpleNamespace(tags=tags))


@pytest.mark.parametrize("name", ["tag0", "cf"])
def test_one_tag_prior_is_the_documented_lever_arm(name):
    init, prior = _tag_levers(_ds([TagMeta(name=name, lever_arm=NOMINAL)]), ESKF, CalibrationOptions(), [name])
    np.testing.assert_array_equal(prior, [NOMINAL])
    np.testing.assert_array_equal(init, [ESKF.calibration["lever_arm"]])


def test_configured_prior_wins_and_no_nominal_is_zero():
    ds = _ds([TagMeta(name="tag0", lever_arm=NOMINAL)])
    _, prior = _tag_levers(ds, ESKF, CalibrationOptions(lever_arm_prior=[0.0, 0.0, 0.0]), ["tag0"])
    np.testing.assert_array_equal(prior, [[0.0, 0.0, 0.0]])
    for tags in ([], [TagMeta(name="tag0")]):
        _, prior = _tag_levers(_ds(tags), ESKF, CalibrationOptions(), ["tag0"])
        np.testing.assert_array_equal(prior, [[0.0, 0.0, 0.0]])
