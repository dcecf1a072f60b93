"""Slowly varying per-anchor range bias (range_bias_drift): the Gauss-Markov chain and its recovery."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from uwbimu.calibration import CalibrationOptions, calibrate  # noqa: E402
from uwbimu.calibration import graph as G  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402


def test_drift_chain_is_stationary():
    """Without ranges, every knot's marginal sd is the option's sd and neighbours correlate by phi."""

    class _Pb:
        anchor_ids = ["a", "b"]
        n_knots = 12
        _drift_factors = None
        options = CalibrationOptions(range_bias_drift={"sd": 0.08, "correlation_time": 2.0, "knot_spacing": 0.5})

    pb = _Pb()
    g = gtsam.NonlinearFactorGraph()
    vals = gtsam.Values()
    for f in G.drift_factors(pb):
        g.add(f)
    for j in range(2):
        for n in range(pb.n_knots):
            vals.insert(G.drift_key(j, n), np.zeros(1))
    m = gtsam.Marginals(g, vals)
    phi = np.exp(-0.5 / 2.0)
    for n in (0, 5, 11):
        assert np.sqrt(m.marginalCovariance(G.drift_key(1, n))[0, 0]) == pytest.approx(0.08, rel=1e-9)
    c = m.jointMarginalCovariance(gtsam.KeyVector([G.drift_key(0, 4), G.drift_key(0, 5)])).fullMatrix()
    assert c[0, 1] / c[0, 0] == pytest.approx(phi, rel=1e-9)


def test_injected_slow_bias_is_tracked_and_sigma_grows():
    """A slow 8 cm sinusoidal error on one anchor's ranges: the drift model follows it (correlation > 0.8) and
    keeps the lever arm within 3 sigma; its sigmas are larger than the white model's."""
    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 12.0}))
    a0 = str(ds.anchors["anchor"].iloc[0])
    uwb = ds.uwb.copy()
    sel = uwb["anchor"].astype(str) == a0
    slow = 0.08 * np.sin(2 * np.pi * uwb.loc[sel, "t"].to_numpy() / 6.0)
    uwb.loc[sel, "range"] += slow
    ds = dataclasses.replace(ds, uwb=uwb)
    white = calibrate(ds, CalibrationOptions(td_profile={"enabled": False}))
    drift = calibrate(ds, CalibrationOptions(td_profile={"enabled": False},
                                             range_bias_drift={"sd": 0.08, "correlation_time": 3.0}),
                      eskf=white.eskf)
    r = drift.residuals
    mine = (r["anchor"].astype(str) == a0).to_numpy()
    est = r.loc[mine, "bias_drift"].to_numpy() + drift.calibration["anchor_bias"][a0]
    assert np.corrcoef(est, slow)[0, 1] > 0.8
    c = drift.calibration
    err = np.subtract(c["lever_arm"], ds.meta.truth.lever_arm)
    assert np.all(np.abs(err) < 3 * np.array(c["lever_arm_sd"]))
    assert np.all(np.array(c["lever_arm_sd"]) > np.array(white.calibration["lever_arm_sd"]))
    assert c["range_model"]["drift"]["knots_per_anchor"] == G.build_problem(
        ds, white.eskf, CalibrationOptions(range_bias_drift={"sd": 0.08, "correlation_time": 3.0})).n_knots


def test_drift_refused_without_grouped_factors():
    from uwbimu.errors import UsageError

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 4.0}))
    with pytest.raises(UsageError, match="range_bias_drift"):
        calibrate(ds, CalibrationOptions(td_profile={"enabled": False}, group_range_factors=False,
                                         range_bias_drift={"sd": 0.05}))
