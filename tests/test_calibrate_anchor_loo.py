"""The self-survey's systematic sigma from the surveyed anchors (calibration/anchor_loo.py).

A 30 s simulated walk-around in room8: 5 anchors surveyed, 3 estimated.  On the white log the surveyed
anchors' leave-one-out displacements are what the white model allows; with one surveyed anchor's documented
position 30 cm off (a survey error: a range-model error exactly linear in the line of sight) its
displacement recovers the error, agrees with an actual re-solve that frees it, and the estimated anchors'
sigma takes the measured systematic variance.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from pydantic import ValidationError
from scipy.stats import chi2

pytest.importorskip("gtsam")

from test_calibrate_survey_sim import walk_around  # noqa: E402

from uwbimu.calibration import CalibrationOptions, calibrate  # noqa: E402
from uwbimu.calibration.anchor_loo import AnchorDisplacement, systematic_variance  # noqa: E402

SURVEYED = ("A0", "A1", "A2", "A5", "A6")
OFF = np.array([-0.2, 0.2, -0.1])  # A6 documented this far from where it is [m]


def _run(ds, unknown_extra=(), off=False, systematic="surveyed"):
    an = ds.anchors.copy()
    an["surveyed"] = an["anchor"].isin(SURVEYED) & ~an["anchor"].isin(unknown_extra)
    m = ~an["surveyed"].to_numpy()
    an.loc[m, ["x", "y", "z"]] = an.loc[m, ["x", "y", "z"]].to_numpy() + \
        np.random.default_rng(0).normal(0, 0.5, (m.sum(), 3))
    if off:
        an.loc[an["anchor"] == "A6", ["x", "y", "z"]] -= OFF
    opts = CalibrationOptions.model_validate({"td_profile": {"enabled": False}, "estimate_anchor_bias": False,
                                              "anchor_systematic": systematic})
    return calibrate(dataclasses.replace(ds, anchors=an), opts)


@pytest.fixture(scope="module")
def log():
    ds = walk_around(duration=30.0)
    return ds, ds.anchors.set_index("anchor")[["x", "y", "z"]]


@pytest.fixture(scope="module")
def white(log):
    return _run(log[0])


@pytest.fixture(scope="module")
def off(log):
    return _run(log[0], off=True), _run(log[0], off=True, systematic="none")


def test_white_log_displacements_are_the_white_models(white):
    sy = white.calibration["anchors"]["systematic"]
    assert sy["applied"] and sy["surveyed_anchors_used"] == len(SURVEYED) and sy["surveyed_anchors_skipped"] == {}
    d = sy["displacements"]
    assert set(d) == set(SURVEYED)
    # sum of the squared Mahalanobis distances ~ chi2(3 n) under the white model
    stat = sum(v["mahalanobis"] ** 2 for v in d.values())
    assert chi2.sf(stat, 3 * len(d)) > 1e-3, stat
    # what it adds is small against the estimated anchors' own sigma
    sd = np.array([white.calibration["anchors"]["positions"][a]["sd"] for a in white.calibration["anchors"]["estimated"]])
    assert sy["sd"] < 0.5 * np.median(sd), (sy["sd"], sd)


def test_a_survey_error_is_seen_and_widens_the_estimated_anchors(off, log):
    res, res_none = off
    sy = res.calibration["anchors"]["systematic"]
    d6 = sy["displacements"]["A6"]
    # the displacement is where the log puts A6 against its documented position: the survey error
    np.testing.assert_array_less(np.abs(np.array(d6["displacement"]) - OFF), 3 * np.array(d6["sd_white"]) + 0.01)
    assert d6["mahalanobis"] == max(v["mahalanobis"] for v in sy["displacements"].values())
    assert sy["sd"] > 0.05
    # every estimated anchor's variance is the white one plus s^2 (per axis); option none keeps the white one
    assert not res_none.calibration["anchors"]["systematic"]["applied"]
    for a in res.calibration["anchors"]["estimated"]:
        v = np.square(res.calibration["anchors"]["positions"][a]["sd"])
        v0 = np.square(res_none.calibration["anchors"]["positions"][a]["sd"])
        np.testing.assert_allclose(v, v0 + sy["sd"] ** 2, rtol=1e-9)
    # and covers the estimated anchors' errors, which the survey error caused
    _ds, truth = log
    for a in res.calibration["anchors"]["estimated"]:
        e = np.asarray(res.calibration["anchors"]["positions"][a]["position"]) - truth.loc[a].to_numpy(float)
        assert np.all(np.abs(e) < 3 * np.asarray(res.calibration["anchors"]["positions"][a]["sd"])), (a, e)


def test_linearised_leave_one_out_matches_a_re_solve(off, log):
    """Freeing A6 for real (surveyed: false, no prior) moves it as the linearised leave-one-out said."""
    res, _ = off
    ds, truth = log
    pred = np.array(res.calibration["anchors"]["systematic"]["displacements"]["A6"]["displacement"])
    freed = _run(ds, unknown_extra=("A6",), off=True)
    moved = np.asarray(freed.calibration["anchors"]["positions"]["A6"]["position"]) - (truth.loc["A6"].to_numpy(float) - OFF)
    # one Gauss-Newton step from a solution that a 30 cm survey error distorted: within 15 % of the displacement
    assert np.linalg.norm(moved - pred) < 0.15 * np.linalg.norm(OFF), (moved, pred)


def test_systematic_variance_pools_the_excess_over_the_white_model():
    C = np.diag([1e-4, 4e-4, 9e-4])
    d = [AnchorDisplacement("a", np.array([0.1, 0.0, 0.0]), C, 100), AnchorDisplacement("b", np.array([0.0, 0.2, 0.0]), C, 100)]
    s2, raw = systematic_variance(d)
    assert raw == pytest.approx(((0.01 + 0.04) / 2 - 14e-4) / 3)
    assert s2 == raw
    s2, raw = systematic_variance([AnchorDisplacement("a", np.zeros(3), C, 100)])
    assert s2 == 0.0 and raw < 0
    assert systematic_variance([])[0] is None


def test_option_is_validated():
    with pytest.raises(ValidationError):
        CalibrationOptions.model_validate({"anchor_systematic": "bogus"})


def test_a_surveyed_anchor_with_few_ranges_is_reported_skipped(log):
    ds, _truth = log
    u = ds.uwb
    keep = (u["anchor"] != "A0").to_numpy() | (np.cumsum((u["anchor"] == "A0").to_numpy()) <= 5)
    res = _run(dataclasses.replace(ds, uwb=u[keep].reset_index(drop=True)))
    sy = res.calibration["anchors"]["systematic"]
    assert set(sy["surveyed_anchors_skipped"]) == {"A0"}
    assert sy["surveyed_anchors_used"] == len(SURVEYED) - 1 and "A0" not in sy["displacements"]
