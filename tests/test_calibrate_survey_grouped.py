"""Anchor self-survey through the grouped (vectorised) range factor: anchor-position Jacobians, kernel path,
and the same survey as one CustomFactor per range."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from test_calibrate_factor import GROUP_ANCHORS as ANCHORS  # noqa: E402
from test_calibrate_factor import group_inputs  # shared synthetic group

from uwbimu.calibration import range_factor as RF
from uwbimu.calibration.range_factor import RangeGroup, so3_exp



def _group(rng, n=12, **kw):
    """Rows to 3 anchors; anchors 0 and 2 estimated (variables 0 and 1), anchor 1 fixed."""
    deltas, col, rho = group_inputs(rng, n)
    avar = np.array([0, -1, 1])[col]
    return RangeGroup(deltas, ANCHORS[col], rho, col, 0.02, anchor_var=avar, **kw)


STATE = (so3_exp(np.array([0.3, 0.1, -0.7])), np.array([1.0, 2.0, 1.5]), np.array([0.4, -0.3, 0.2]),
         np.array([0.12, -0.08, 0.14]), 0.033, np.array([0.03, -0.05, 0.01]))
#: the estimated anchors' current values, away from their initial ``anchors`` (those must not be used)
APOS = ANCHORS[[0, 2]] + np.array([[0.3, -0.2, 0.1], [-0.1, 0.25, 0.4]])

MODELS = {
    "range": {},
    "tag_direction": {"direction": ((1, 2), True), "dir_col": np.arange(12) % 3},
    "anchor_direction": {"anchor_direction": ((1, 2), (1,)), "adir_col": np.arange(12) % 3,
                         "anchor_rot": np.array([so3_exp(np.array([0.2 * i, -0.3, 0.5])) for i in range(12)])},
}


def _coefs(grp, rng):
    kw = {}
    if grp.direction is not None:
        kw["dir_coefs"] = rng.normal(0, 0.05, (grp.n_dir, 5))
    if grp.anchor_direction is not None:
        kw["adir_coefs"] = rng.normal(0, 0.05, (grp.n_adir, 5))
    return kw


@pytest.mark.parametrize("model", list(MODELS))
@pytest.mark.parametrize("kernel", [True, False])
def test_anchor_jacobian_matches_finite_differences(model, kernel, monkeypatch):
    """d e / d anchor (last Jacobian) against central differences of the estimated anchors' positions, with the
    range alone (kernel or NumPy), the tag-side and the anchor-side direction terms; zero on fixed-anchor rows."""
    monkeypatch.setattr(RF, "USE_KERNEL", kernel)
    rng = np.random.default_rng(7)
    grp = _group(rng, **MODELS[model])
    kw = _coefs(grp, rng)
    R, p, v, lev, td, b = STATE
    calls = []
    if kernel and model == "range":
        real = RangeGroup._evaluate_kernel
        monkeypatch.setattr(RangeGroup, "_evaluate_kernel", lambda *a, **k: calls.append(1) or real(*a, **k))
    res = grp.evaluate(R, p, v, lev, td, b, jacobians=True, anchor_pos=APOS, **kw)
    assert calls == ([1] if kernel and model == "range" else [])
    e, Ja = res[0], res[-1]
    assert Ja.shape == (12, 3)
    np.testing.assert_allclose(e, grp.evaluate(R, p, v, lev, td, b, anchor_pos=APOS, **kw), atol=1e-12)
    # the estimated rows use anchor_pos, the fixed ones their own anchor
    ra = grp.row_anchors(APOS)
    np.testing.assert_array_equal(ra[1::3], ANCHORS[[1] * 4])
    np.testing.assert_array_equal(ra[0::3], APOS[[0] * 4])
    np.testing.assert_array_equal(Ja[1::3], 0.0)
    h = 1e-6
    for a in range(2):
        for i in range(3):
            d = np.zeros((2, 3))
            d[a, i] = h
            fd = (grp.evaluate(R, p, v, lev, td, b, anchor_pos=APOS + d, **kw)
                  - grp.evaluate(R, p, v, lev, td, b, anchor_pos=APOS - d, **kw)) / 2 / h
            np.testing.assert_allclose(np.where(grp.anchor_var == a, Ja[:, i], 0.0), fd, atol=1e-7)
    if model != "range":  # the direction term moves the anchor Jacobian off -n
        u = grp._geometry(R, p, v, lev, td, APOS)["u"]
        n = u / np.linalg.norm(u, axis=1)[:, None]
        assert np.max(np.abs(Ja[0::3] + n[0::3])) > 1e-4


def test_kernel_and_numpy_agree_with_estimated_anchors(monkeypatch):
    rng = np.random.default_rng(3)
    grp = _group(rng)
    R, p, v, lev, td, b = STATE
    monkeypatch.setattr(RF, "USE_KERNEL", True)
    a = grp.evaluate(R, p, v, lev, td, b, jacobians=True, anchor_pos=APOS)
    monkeypatch.setattr(RF, "USE_KERNEL", False)
    c = grp.evaluate(R, p, v, lev, td, b, jacobians=True, anchor_pos=APOS)
    assert len(a) == len(c) == 6
    for x, y in zip(a, c):
        np.testing.assert_allclose(x, y, atol=1e-12)


def test_group_with_estimated_anchors_needs_their_positions():
    grp = _group(np.random.default_rng(1))
    with pytest.raises(TypeError, match="anchor_pos"):
        grp.evaluate(*STATE)


def test_gtsam_group_factor_anchor_keys():
    """The factor's Jacobian blocks of the Point3 keys are the rows' anchor Jacobians (whitened), from the
    values of those keys."""
    gtsam = pytest.importorskip("gtsam")
    from gtsam.symbol_shorthand import A, L, P, T, V, X

    grp = _group(np.random.default_rng(2))
    R, p, v, lev, td, b = STATE
    keys = [X(0), V(0), L(0), T(0), A(0), A(1), A(2), P(0), P(2)]
    f = RF.make_gtsam_group_factor(keys, grp, 0.1, 100.0)
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(gtsam.Rot3(R), p))
    vals.insert(V(0), v)
    vals.insert(L(0), lev)
    vals.insert(T(0), np.array([td]))
    for j in range(3):
        vals.insert(A(j), np.array([b[j]]))
    vals.insert(P(0), APOS[0])
    vals.insert(P(2), APOS[1])
    lin = f.linearize(vals)
    Ab = lin.jacobian()[0]
    res = grp.evaluate(R, p, v, lev, td, b, jacobians=True, anchor_pos=APOS)
    np.testing.assert_allclose(-lin.jacobian()[1], res[0] / 0.1, atol=1e-9)  # b = -e/sigma (Huber off)
    Ja = res[-1] / 0.1
    np.testing.assert_allclose(Ab[:, -6:-3], Ja * (grp.anchor_var == 0)[:, None], atol=1e-9)
    np.testing.assert_allclose(Ab[:, -3:], Ja * (grp.anchor_var == 1)[:, None], atol=1e-9)


def _survey(duration: float, seed: int):
    """A walk-around log (room8) with the anchors but SURVEYED marked ``surveyed: false`` at 0.3-m-sd guesses."""
    from test_calibrate_survey_sim import SURVEYED, walk_around

    ds = walk_around(duration=duration, seed=seed)
    an = ds.anchors.copy()
    an["surveyed"] = an["anchor"].isin(SURVEYED)
    m = ~an["surveyed"].to_numpy()
    an.loc[m, ["x", "y", "z"]] = an.loc[m, ["x", "y", "z"]].to_numpy() \
        + np.random.default_rng(0).normal(0, 0.3, (m.sum(), 3))
    return dataclasses.replace(ds, anchors=an)


@pytest.mark.parametrize("huber_k, bias, atol", [(100.0, True, 1e-6), (1.345, False, 1e-4)])
def test_grouped_survey_matches_the_per_range_graph(huber_k, bias, atol):
    """A short walk-around self-survey (3 surveyed, 5 unknown anchors): grouped range factors and one CustomFactor
    per range reach the same anchors.  With the loss quadratic on every row (huber_k 100) the two graphs give the
    same linear systems, so the same iterates: within 1e-6 m after 12 iterations (measured 2e-10 m, anchor biases
    estimated; the anchors have then moved 0.87 of the 0.88 m they move by convergence at iteration 40, where
    the difference is the same 2e-10 m: the per-range graph's Python factors made those 28 more iterations 8 s).
    With the default Huber the Gauss-Newton weights of down-weighted rows differ by design
    (:func:`make_gtsam_group_factor`), so only the optimum is shared, reached to the LM stopping rule: 1e-4 m
    (measured ~2e-5 m, biases fixed; with biases estimated the flat bias/distance valley lets the per-range
    graph stop 5 cm short at a higher cost, so that case is not compared)."""
    from uwbimu.calibration import CalibrationOptions, calibrate

    ds = _survey(12.0, 3)
    iterations = 12 if huber_k == 100.0 else 200  # same iterates (capped) / same optimum (converges in 6)
    base = {"td_profile": {"enabled": False}, "max_iterations": iterations, "huber_k": huber_k,
            "estimate_anchor_bias": bias}
    grp = calibrate(ds, CalibrationOptions.model_validate(base))
    per = calibrate(ds, CalibrationOptions.model_validate(base | {"group_range_factors": False}), eskf=grp.eskf)
    assert grp.anchors["estimated"].sum() == 5
    pos = grp.anchors[["x", "y", "z"]].to_numpy()
    assert np.max(np.abs(pos - ds.anchors[["x", "y", "z"]].to_numpy())) > 0.1  # the survey moved them
    np.testing.assert_allclose(pos, per.anchors[["x", "y", "z"]].to_numpy(), atol=atol)
    assert grp.calibration["solver"]["final_cost"] == pytest.approx(per.calibration["solver"]["final_cost"],
                                                                    rel=1e-7)


def test_survey_with_drift_and_tag_direction_and_anchor_direction_refused():
    """range_bias_drift and the tag-side range_model.direction now run with estimated anchors (grouped factors);
    on a log without such errors they move the surveyed anchors little (measured <= 2.5 cm on this 20 s walk).
    The anchor-side model stays refused: to first order it is a shift of the anchor's position."""
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.errors import UsageError

    ds = _survey(20.0, 4)
    base = {"td_profile": {"enabled": False}, "estimate_anchor_bias": False}
    plain = calibrate(ds, CalibrationOptions.model_validate(base))
    pos0 = plain.anchors[["x", "y", "z"]].to_numpy()
    for extra, col in (({"range_bias_drift": {"sd": 0.03}}, "bias_drift"),
                       ({"range_model": {"direction": {"harmonics": 2}}}, "bias_direction")):
        r = calibrate(ds, CalibrationOptions.model_validate(base | extra), eskf=plain.eskf)
        assert col in r.residuals.columns and r.anchors["estimated"].sum() == 5
        pos = r.anchors[["x", "y", "z"]].to_numpy()
        assert np.all(np.linalg.norm(pos - pos0, axis=1) < 0.05), (extra, pos - pos0)
        assert np.max(np.abs(pos - pos0)) > 1e-5  # the term is in the survey's graph
    with pytest.raises(UsageError, match="anchor_direction.*estimate-anchors"):
        calibrate(ds, CalibrationOptions.model_validate(base | {"range_model": {"anchor_direction": {}}}),
                  eskf=plain.eskf)


def test_surveyed_only_bias_holds_the_estimated_anchors_bias():
    """``estimate_anchor_bias: surveyed_only``: a fixed anchor's constant bias (0.15 m injected on A0) is
    estimated, an estimated anchor's is held at 0; ``true`` estimates both, the default is unchanged."""
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.errors import ConfigError

    assert CalibrationOptions().estimate_anchor_bias is True
    with pytest.raises((ConfigError, ValueError)):
        CalibrationOptions.model_validate({"estimate_anchor_bias": "fixed_only"})
    ds = _survey(15.0, 5)
    uwb = ds.uwb.copy()
    uwb.loc[uwb["anchor"].astype(str) == "A0", "range"] += 0.15
    ds = dataclasses.replace(ds, uwb=uwb)
    unknown = list(ds.anchors.loc[~ds.anchors["surveyed"], "anchor"])
    base = {"td_profile": {"enabled": False}}
    so = calibrate(ds, CalibrationOptions.model_validate(base | {"estimate_anchor_bias": "surveyed_only"}))
    both = calibrate(ds, CalibrationOptions.model_validate(base), eskf=so.eskf)
    b, sd = so.calibration["anchor_bias"], so.calibration["anchor_bias_sd"]
    assert abs(b["A0"] - 0.15) < max(3 * sd["A0"], 0.03), (b["A0"], sd["A0"])
    assert all(abs(b[a]) < 1e-5 for a in unknown), b
    assert max(abs(both.calibration["anchor_bias"][a]) for a in unknown) > 1e-3  # estimated with `true`
