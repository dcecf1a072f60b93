"""Direction-dependent range bias (range_model.direction): exact Jacobians, config refusal, recovery."""

from __future__ import annotations

import numpy as np
import pytest

from test_calibrate_factor import GROUP_ANCHORS, assert_state_jacobians, group_inputs, group_values, retraction_differences  # shared

from uwbimu.calibration.range_factor import RangeGroup, direction_features, so3_exp


def _group(rng, n=9, direction=((1, 2), True)):
    deltas, col, rho = group_inputs(rng, n)
    return RangeGroup(deltas, GROUP_ANCHORS[col], rho, col, 0.02, direction=direction, dir_col=col)


def test_features_derivative_matches_finite_differences():
    rng = np.random.default_rng(1)
    w = rng.normal(size=(6, 3)) * 3
    F, dF = direction_features(w, (1, 2, 3), True, jacobian=True)
    h = 1e-6
    for i in range(3):
        dw = np.zeros(3)
        dw[i] = h
        fd = (direction_features(w + dw, (1, 2, 3), True)[0] - direction_features(w - dw, (1, 2, 3), True)[0]) / 2 / h
        np.testing.assert_allclose(dF[:, :, i], fd, atol=1e-7)
    az = np.arctan2(w[:, 1], w[:, 0])
    np.testing.assert_allclose(F[:, 2], np.cos(2 * az))
    np.testing.assert_allclose(F[:, 6], np.arcsin(w[:, 2] / np.linalg.norm(w, axis=1)))


@pytest.mark.parametrize("direction", [((1, 2), True), ((2, 3), False)])
def test_direction_jacobians_match_finite_differences(direction):
    """Exact derivatives of the range plus direction term w.r.t. attitude, position, velocity, lever arm, t_d
    (the line of sight moves with all of them) and the coefficients, against central differences."""
    rng = np.random.default_rng(5)
    grp = _group(rng, direction=direction)
    P = 2 * len(direction[0]) + int(direction[1])
    C = rng.normal(0, 0.05, (3, P))
    R, p, v = so3_exp(np.array([0.3, 0.1, -0.7])), np.array([1.0, 2.0, 1.5]), np.array([0.4, -0.3, 0.2])
    lev, td, b = np.array([0.12, -0.08, 0.14]), 0.033, np.array([0.03, -0.05, 0.01])

    def f(R=R, p=p, v=v, lev=lev, td=td, C=C):
        return grp.evaluate(R, p, v, lev, td, b, dir_coefs=C)

    e, Jp, Jv, Jl, Jt, F = grp.evaluate(R, p, v, lev, td, b, jacobians=True, dir_coefs=C)
    e0 = RangeGroup.__new__(RangeGroup)
    e0.__dict__.update(grp.__dict__, direction=None)
    assert np.max(np.abs(e - e0.evaluate(R, p, v, lev, td, b))) > 1e-3  # the term is there
    _e, Jp0, *_ = e0.evaluate(R, p, v, lev, td, b, jacobians=True)
    assert np.max(np.abs(Jp - Jp0)) > 1e-4  # and moves the attitude Jacobian
    h = 1e-6
    assert_state_jacobians(f, (Jp, Jv, Jl, Jt), R, p, v, lev, td, h=h)
    for j in range(3):
        for q in range(P):
            dC = np.zeros_like(C)
            dC[j, q] = h
            fd = (f(C=C + dC) - f(C=C - dC)) / 2 / h
            np.testing.assert_allclose(np.where(grp.dir_col == j, F[:, q], 0.0), fd, atol=1e-7)


def _with_body_azimuth_bias(ds, c1: float, s2: float):
    """``ds`` with ``c1 cos(az) + s2 sin(2 az)`` [m] added to every range, ``az`` the true body azimuth of the
    line of sight tag antenna -> anchor (ground truth is on the UWB clock)."""
    import dataclasses

    from scipy.spatial.transform import Rotation

    gt, uwb = ds.groundtruth, ds.uwb.copy()
    t = uwb["t"].to_numpy(float)
    i = np.clip(np.searchsorted(gt["t"].to_numpy(float), t), 0, len(gt) - 1)
    p = np.stack([np.interp(t, gt["t"], gt[c]) for c in ("px", "py", "pz")], axis=1)
    R = Rotation.from_quat(gt[["qx", "qy", "qz", "qw"]].to_numpy(float)[i]).as_matrix()
    a = ds.anchors.set_index("anchor").loc[uwb["anchor"].astype(str), ["x", "y", "z"]].to_numpy(float)
    wb = np.einsum("nji,nj->ni", R, a - p - R @ np.asarray(ds.meta.truth.lever_arm, float))
    az = np.arctan2(wb[:, 1], wb[:, 0])
    inj = c1 * np.cos(az) + s2 * np.sin(2 * az)
    uwb["range"] += inj
    return dataclasses.replace(ds, uwb=uwb), inj


@pytest.mark.parametrize("per_anchor", [False, True])
def test_body_azimuth_bias_is_recovered_and_frees_the_lever_arm(per_anchor):
    """Simulated flight with a 5 cm cos(az) + 3 cm sin(2 az) range bias (body azimuth): every coefficient
    (shared, or each anchor's) within 3 sigma of its true value, the lever-arm error less than half the one
    without the model (which absorbs the order-1 term into the lever arm), and residuals.csv's
    bias_direction follows the injected bias."""
    pytest.importorskip("gtsam")
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0}))
    ds, inj = _with_body_azimuth_bias(ds, 0.05, 0.03)
    truth = np.asarray(ds.meta.truth.lever_arm, float)
    # "plain": the white model, configured (select: given); by default the range model is chosen on the log
    # (issue 27 item 7), which on this log picks a direction family (asserted below for the shared case)
    plain = calibrate(ds, CalibrationOptions(td_profile={"enabled": False}, range_model={"select": "given"}))
    model = calibrate(ds, CalibrationOptions(td_profile={"enabled": False},
                                             range_model={"direction": {"harmonics": 2, "per_anchor": per_anchor}}),
                      eskf=plain.eskf)
    d = model.calibration["range_model"]["direction"]
    assert d["coefficient_names"] == ["cos1", "sin1", "cos2", "sin2"]
    true_c = {"cos1": 0.05, "sin1": 0.0, "cos2": 0.0, "sin2": 0.03}
    assert list(d["coefficients"]) == (sorted(ds.anchors["anchor"].astype(str)) if per_anchor else ["all"])
    for lab, cs in d["coefficients"].items():
        for name, c in cs.items():
            assert abs(c["value"] - true_c[name]) < 3 * c["sd"], (lab, name, c)
    if not per_anchor:
        assert d["coefficients"]["all"]["sin2"]["sd"] < 0.01  # order 2 is well determined
    err_plain = np.linalg.norm(np.subtract(plain.calibration["lever_arm"], truth))
    err_model = np.linalg.norm(np.subtract(model.calibration["lever_arm"], truth))
    assert err_model < 0.5 * err_plain, (err_model, err_plain)
    err = np.subtract(model.calibration["lever_arm"], truth)
    assert np.all(np.abs(err) < 3 * np.array(model.calibration["lever_arm_sd"]))
    r = model.residuals
    assert list(plain.residuals.columns) == [c for c in r.columns if c != "bias_direction"]
    rows = np.searchsorted(ds.uwb["t"].to_numpy(), r["t"].to_numpy())  # residual rows keep the log's order
    # per anchor, the constant bias takes the mean of the pattern over the azimuths that anchor was seen from
    est = r["bias_direction"] + r["anchor"].astype(str).map(model.calibration["anchor_bias"])
    assert np.corrcoef(est, inj[rows])[0, 1] > (0.8 if per_anchor else 0.9)
    names = model.calibration["correlations"]["names"]
    assert (f"direction_{d['coefficients'].popitem()[0]}_sin2" if per_anchor else "direction_sin2") in names
    if not per_anchor:
        # the default (range_model.select: auto) finds the direction-dependent bias on the batch's free solve
        auto = calibrate(ds, CalibrationOptions(td_profile={"enabled": False}), eskf=plain.eskf).calibration
        assert "direction" in auto["range_model"]["selection"]["chosen"], auto["range_model"]["selection"]["reason"]
        assert auto["range_model"]["direction"] is not None


def test_direction_options_refused_naming_the_field(tmp_path):
    from uwbimu.calibration import CalibrationOptions
    from uwbimu.errors import ConfigError

    p = tmp_path / "c.yaml"
    p.write_text("range_model:\n  direction: {harmonics: 2, tag_harmonic: 3}\n")
    with pytest.raises(ConfigError, match="tag_harmonic"):
        CalibrationOptions.from_yaml(p)
    p.write_text("range_model:\n  direction: {harmonics: 1, lowest_order: 2}\n")
    with pytest.raises(ConfigError, match="lowest_order"):
        CalibrationOptions.from_yaml(p)
    p.write_text("range_model:\n  direction: {prior_sd: -0.05}\n")
    with pytest.raises(ConfigError, match="prior_sd"):
        CalibrationOptions.from_yaml(p)
    o = CalibrationOptions(range_model={"direction": {"harmonics": 3, "lowest_order": 2, "elevation": True}})
    assert o.range_model.direction.names() == ["cos2", "sin2", "cos3", "sin3", "elevation"]
    assert o.range_model.direction.n_coef == 5


def test_direction_refused_without_grouped_factors():
    pytest.importorskip("gtsam")
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.errors import UsageError
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 4.0}))
    with pytest.raises(UsageError, match="range_model.direction"):
        calibrate(ds, CalibrationOptions(td_profile={"enabled": False}, group_range_factors=False,
                                         range_model={"direction": {"harmonics": 2}}))


def test_direction_with_drift_keeps_both_terms():
    """With range_bias_drift too, every grouped factor carries bias, drift and direction keys: both columns
    are in residuals.csv and residual = range − predicted still holds."""
    pytest.importorskip("gtsam")
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 8.0}))
    ds, _ = _with_body_azimuth_bias(ds, 0.05, 0.03)
    r = calibrate(ds, CalibrationOptions(td_profile={"enabled": False}, range_bias_drift={"sd": 0.05},
                                         range_model={"direction": {"harmonics": 2, "per_anchor": True}}))
    res = r.residuals
    assert {"bias_drift", "bias_direction"} <= set(res.columns)
    assert res["bias_direction"].abs().max() > 0.01 and res["bias_drift"].abs().max() > 0.0
    np.testing.assert_allclose(res["range"] - res["predicted"], res["residual"], atol=1e-12)


@pytest.mark.parametrize("td_fixed", [None, 0.031])
def test_gtsam_group_factor_with_direction_keys(td_fixed):
    """The CustomFactor's whitened Jacobian, direction-coefficient keys included, equals central differences
    through GTSAM's own retraction of every key (pins the key order of the wrapper)."""
    pytest.importorskip("gtsam")
    from uwbimu.calibration.range_factor import make_gtsam_group_factor

    rng = np.random.default_rng(11)
    grp = _group(rng, direction=((1, 2), True))
    sigma = 0.1
    vals, keys, dims = group_values(rng, td_fixed)
    f = make_gtsam_group_factor(keys, grp, sigma, 1e6, td_fixed=td_fixed)  # Huber threshold out of reach
    Aj, _b = f.linearize(vals).jacobian()
    cols = retraction_differences(f, vals, keys, dims)
    # unit noise model: the factor returns e / sigma (Huber inactive), so both sides are whitened
    np.testing.assert_allclose(Aj, cols, atol=1e-5)
