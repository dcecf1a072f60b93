"""Anchor self-survey: dataset columns (surveyed, anchor_ranges sd), gauge, degenerate geometry, refusals."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pytest

from uwbimu.calibration import CalibrationOptions
from uwbimu.calibration.anchors import BIAS_INFLATION, bias_confounding, geometry_checks, multilaterate, plan_anchors
from uwbimu.errors import InputError
from uwbimu.io.dataset import Dataset, write_dataset
from uwbimu.io.loader import DatasetError, load_dataset

ANCHORS = pd.DataFrame({"anchor": ["A", "B", "C", "D"], "x": [0.0, 4.0, 4.0, 0.0],
                        "y": [0.0, 0.0, 3.0, 3.0], "z": [2.0, 2.5, 0.3, 2.5]})


def _folder(tmp_path, anchors=None, anchor_ranges=None):
    t = np.arange(0, 2, 0.01)
    imu = pd.DataFrame({"t": t, "ax": 0.0, "ay": 0.0, "az": 9.81, "wx": 0.0, "wy": 0.0, "wz": 0.0})
    an = ANCHORS if anchors is None else anchors
    d = np.linalg.norm(an[["x", "y", "z"]].to_numpy() - [2.0, 1.5, 1.0], axis=1)
    tu = np.arange(0, 2, 0.1)
    uwb = pd.DataFrame({"t": np.repeat(tu, 4), "anchor": list("ABCD") * len(tu), "range": np.tile(d, len(tu))})
    ds = Dataset(imu=imu, uwb=uwb, anchors=an.copy(), anchor_ranges=anchor_ranges)
    return write_dataset(ds, tmp_path / "ds")


# --- dataset columns -------------------------------------------------------------------------------

def test_surveyed_column_round_trip(tmp_path):
    folder = _folder(tmp_path)
    an = ANCHORS.assign(surveyed=["true", "false", "Yes", "0"])
    an.to_csv(folder / "anchors.csv", index=False)
    ds = load_dataset(folder)
    assert ds.anchors["surveyed"].tolist() == [True, False, True, False]
    again = load_dataset(write_dataset(ds, tmp_path / "copy"))
    assert again.anchors["surveyed"].tolist() == [True, False, True, False]


def test_surveyed_bad_value_names_line_and_column(tmp_path):
    folder = _folder(tmp_path)
    ANCHORS.assign(surveyed=["true", "maybe", "true", "true"]).to_csv(folder / "anchors.csv", index=False)
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert (exc.value.file, exc.value.row, exc.value.column) == ("anchors.csv", 3, "surveyed")
    assert "maybe" in str(exc.value)


@pytest.mark.parametrize("rows, column, line", [
    ({"anchor_a": ["A", "B"], "anchor_b": ["B", "Q"], "range": [4.0, 3.0]}, "anchor_b", 3),  # unknown anchor
    ({"anchor_a": ["A", "C"], "anchor_b": ["B", "C"], "range": [4.0, 3.0]}, "anchor_b", 3),  # a == b
    ({"anchor_a": ["A", "B"], "anchor_b": ["B", "C"], "range": [4.0, "nan"]}, "range", 3),  # non-finite
    ({"anchor_a": ["A", "B"], "anchor_b": ["B", "C"], "range": [4.0, "inf"]}, "range", 3),
    ({"anchor_a": ["A", "B"], "anchor_b": ["B", "C"], "range": [-4.0, 3.0]}, "range", 2),  # negative
    ({"anchor_a": ["A", "B"], "anchor_b": ["B", "C"], "range": [4.0, 3.0], "sd": [0.01, -0.02]}, "sd", 3),
    ({"anchor_a": ["A", "B"], "anchor_b": ["B", "C"], "range": [4.0, 3.0], "sd": [0.01, "inf"]}, "sd", 3),
    ({"anchor_a": ["A", "B"], "anchor_b": ["B", "C"], "range": [4.0, 3.0], "sd": ["x", 0.02]}, "sd", 2),
])
def test_anchor_ranges_refusals_name_file_line_column(tmp_path, rows, column, line):
    folder = _folder(tmp_path)
    pd.DataFrame(rows).to_csv(folder / "anchor_ranges.csv", index=False)
    with pytest.raises(DatasetError) as exc:
        load_dataset(folder)
    assert (exc.value.file, exc.value.row, exc.value.column) == ("anchor_ranges.csv", line, column)


def test_anchor_ranges_sd_column(tmp_path):
    ar = pd.DataFrame({"anchor_a": ["A", "B"], "anchor_b": ["B", "C"], "range": [4.0, 3.0], "sd": [0.01, 0.02]})
    ds = load_dataset(_folder(tmp_path, anchor_ranges=ar))
    np.testing.assert_allclose(ds.anchor_ranges["sd"], [0.01, 0.02])


# --- which anchors are variables, and the gauge -------------------------------------------------------

def _ds(anchors):
    return Dataset(imu=pd.DataFrame(), uwb=pd.DataFrame({"t": [], "anchor": [], "range": []}), anchors=anchors)


def test_unknown_id_in_estimate_anchors_is_refused():
    with pytest.raises(InputError, match="'Q'.*not in anchors.csv"):
        plan_anchors(_ds(ANCHORS), CalibrationOptions(estimate_anchors=["B", "Q"]))


def test_surveyed_anchors_fix_the_frame():
    s = plan_anchors(_ds(ANCHORS.assign(surveyed=[True, True, False, True])),
                     CalibrationOptions(estimate_anchors=["D"]))
    assert s.gauge["kind"] == "surveyed" and s.gauge["fixed_anchors"] == ["A", "B"]
    assert s.estimated.tolist() == [False, False, True, True]
    assert np.isinf(s.prior_sd[2]) and s.prior_sd[3] == 0.5  # unsurveyed: no prior; named surveyed: weak prior
    assert s.events[0]["kind"] == "anchor_unsurveyed_estimated" and s.events[0]["anchors"] == ["C"]
    np.testing.assert_allclose(s.pos, ANCHORS[["x", "y", "z"]].to_numpy())


@pytest.mark.parametrize("named, origin_moves", [(["A", "B", "C", "D"], True), (["B", "C", "D"], False)])
def test_gauge_convention(named, origin_moves):
    """Fewer than two fixed anchors: origin at the first (fixed) anchor, x axis horizontally towards the next."""
    s = plan_anchors(_ds(ANCHORS), CalibrationOptions(estimate_anchors=named))
    assert s.gauge["kind"] == "convention"
    assert (s.gauge["origin_anchor"], s.gauge["x_axis_anchor"]) == ("A", "B")
    assert not s.estimated[0] and s.yaw_fix[0] == 1
    np.testing.assert_allclose(s.pos[0], [0, 0, 0] if origin_moves else ANCHORS.iloc[0][["x", "y", "z"]].to_numpy(float),
                               atol=1e-12)
    assert s.pos[1][1] == pytest.approx(s.pos[0][1]) and s.pos[1][0] > s.pos[0][0]
    # A rigid motion about the vertical: distances and heights unchanged.
    P0 = ANCHORS[["x", "y", "z"]].to_numpy()
    np.testing.assert_allclose(np.linalg.norm(s.pos[:, None] - s.pos[None], axis=-1),
                               np.linalg.norm(P0[:, None] - P0[None], axis=-1), atol=1e-12)
    np.testing.assert_allclose(s.pos[:, 2] - s.pos[0, 2], P0[:, 2] - P0[0, 2], atol=1e-12)


# --- degenerate geometry ------------------------------------------------------------------------------

def _ranges(P, a, sigma, seed=0):
    return np.linalg.norm(P - a, axis=1) + np.random.default_rng(seed).normal(0, sigma, len(P))


@pytest.mark.parametrize("scale", [1.0, 10.0])
def test_geometry_checks(scale):
    """Straight line: too few directions; planar: mirror ambiguity; 3-D: neither.  Scale-free verdicts."""
    rng = np.random.default_rng(1)
    a, sigma = scale * np.array([1.0, 2.0, 2.5]), 0.05 * scale
    line = scale * np.column_stack([np.linspace(-3, 3, 400), np.full(400, -1.0), np.full(400, 1.0)])
    plane = scale * np.column_stack([rng.uniform(-3, 3, 400), rng.uniform(-3, 3, 400), np.full(400, 1.0)])
    solid = scale * rng.uniform([-3, -3, 0.2], [3, 3, 2.0], (400, 3))
    kinds = lambda P: {e["kind"] for e in geometry_checks("X", a, P, _ranges(P, a, sigma), sigma, 0.3 * scale)}
    assert "anchor_few_directions" in kinds(line)
    assert kinds(plane) == {"anchor_mirror_ambiguity"}
    assert kinds(solid) == set()
    # Multilateration finds the anchor from the 3-D positions.
    est, rms = multilaterate(solid, _ranges(solid, a, sigma))
    assert np.linalg.norm(est - a) < 0.05 * scale and rms < 2 * sigma


@pytest.mark.parametrize("scale", [1.0, 10.0])
def test_bias_confounding(scale):
    """Inflation = largest ratio of position variances with the range bias free against known (Fisher).

    A small flight volume far from the anchor (narrow cone, as for a room-corner anchor seen from a
    1-m box 3 m away) is flagged; a motion around the anchor is not.  Scale-free.
    """
    rng = np.random.default_rng(2)
    a = scale * np.array([0.0, 0.0, 2.0])
    box = scale * (np.array([3.0, 0.5, 1.0]) + rng.uniform(-0.5, 0.5, (500, 3)))
    ring = scale * np.column_stack([2.0 * np.cos(th := rng.uniform(0, 2 * np.pi, 500)), 2.0 * np.sin(th),
                                    rng.uniform(0.5, 3.5, 500)])

    def fisher_inflation(P):
        n = (a - P) / np.linalg.norm(a - P, axis=1)[:, None]
        J = np.column_stack([-n, np.ones(len(n))])
        cov_free = np.linalg.inv(J.T @ J)[:3, :3]  # bias estimated (no prior)
        cov_known = np.linalg.inv(n.T @ n)  # bias known
        return float(np.sqrt(np.max(np.linalg.eigvals(np.linalg.solve(cov_known, cov_free)).real)))

    narrow, wide = bias_confounding("X", a, box), bias_confounding("Y", a, ring)
    assert narrow["inflation"] == pytest.approx(fisher_inflation(box), rel=1e-6)
    assert wide["inflation"] == pytest.approx(fisher_inflation(ring), rel=1e-6)
    assert narrow["inflation"] > BIAS_INFLATION and narrow["event"]["kind"] == "anchor_bias_confounded"
    assert "X" in narrow["event"]["message"] and "estimate_anchor_bias" in narrow["event"]["message"]
    assert wide["inflation"] < 2.0 and wide["event"] is None
    # The mean line of sight of the box points from it to the anchor.
    d = a - box.mean(axis=0)
    assert np.dot(narrow["mean_los"], d / np.linalg.norm(d)) > 0.99


def test_coplanar_motion_is_refused_without_a_prior():
    """Horizontal circle (constant height): an unsurveyed anchor's height side is ambiguous -> InputError."""
    pytest.importorskip("gtsam")
    from uwbimu.calibration import calibrate
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("circle").model_copy(update={"duration": 10.0}))
    an = ds.anchors.assign(surveyed=[a != "A6" for a in ds.anchors["anchor"]])
    with pytest.raises(InputError, match="A6.*(height|directions)"):
        calibrate(dataclasses.replace(ds, anchors=an), CalibrationOptions(td_profile={"enabled": False}))


def test_gauge_convention_and_anchor_ranges_end_to_end():
    """Every anchor estimated (weak priors around 20 cm-off guesses) plus measured inter-anchor ranges.

    The gauge convention holds A0 at the origin and A1 on the x axis; the solution matches the truth
    expressed in that frame within 4 sd, and the anchor_ranges factors hold each measured pair to its
    1 cm sd although the guesses were off by tens of cm.
    """
    pytest.importorskip("gtsam")
    from uwbimu.calibration import calibrate
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 15.0}))
    truth = ds.anchors[["x", "y", "z"]].to_numpy()
    ids = list(ds.anchors["anchor"])
    rng = np.random.default_rng(5)
    guess = ds.anchors.copy()
    guess[["x", "y", "z"]] = truth + rng.normal(0, 0.2, truth.shape)
    pairs = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 6), (5, 7), (0, 4), (2, 6)]
    ar = pd.DataFrame({"anchor_a": [ids[a] for a, _ in pairs], "anchor_b": [ids[b] for _, b in pairs],
                       "range": [np.linalg.norm(truth[a] - truth[b]) + rng.normal(0, 0.01) for a, b in pairs],
                       "sd": 0.01})
    opts = CalibrationOptions.model_validate({"td_profile": {"enabled": False}, "estimate_anchors": ids,
                                              "estimate_anchor_bias": False})
    res = calibrate(dataclasses.replace(ds, anchors=guess, anchor_ranges=ar), opts)
    cal = res.calibration["anchors"]
    assert (cal["gauge"]["kind"], cal["gauge"]["origin_anchor"], cal["gauge"]["x_axis_anchor"]) == ("convention", "A0", "A1")
    assert any(e["kind"] == "anchor_gauge_convention" for e in res.events)
    est = res.anchors[["x", "y", "z"]].to_numpy()
    sd = res.anchors[["sd_x", "sd_y", "sd_z"]].to_numpy()
    np.testing.assert_allclose(est[0], 0.0, atol=1e-12)
    assert abs(est[1, 1]) < 1e-3 and est[1, 0] > 0
    d = truth[1] - truth[0]
    c, s = np.cos(-np.arctan2(d[1], d[0])), np.sin(-np.arctan2(d[1], d[0]))
    in_gauge = (truth - truth[0]) @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    err = (est - in_gauge)[1:]
    ok = np.abs(err) < 4 * sd[1:]
    ok[0, 1] = True  # A1's y is the gauge constraint (sd ~ 0)
    assert ok.all(), (err, sd)
    res_pairs = np.array([p["residual"] for p in cal["anchor_ranges"]])
    assert all(p["in_graph"] for p in cal["anchor_ranges"])
    assert np.all(np.abs(res_pairs) < 0.03), res_pairs
    guess_err = [abs(np.linalg.norm(guess[["x", "y", "z"]].to_numpy()[a] - guess[["x", "y", "z"]].to_numpy()[b])
                     - r) for (a, b), r in zip(pairs, ar["range"])]
    assert np.median(guess_err) > 0.1  # the guesses alone were far off: the factors did the work
