"""Anchor self-survey on a simulated walk-around: 3 surveyed and 5 unknown anchors located within 5 cm."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("gtsam")

from uwbimu.calibration import CalibrationOptions, calibrate, write_calibration  # noqa: E402
from uwbimu.io.loader import load_dataset  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402

SURVEYED = ("A0", "A2", "A5")  # two low corners and one high anchor of room8


def walk_around(duration=45.0, seed=1):
    """room8, 8 anchors: a 3-D Lissajous over most of the room (7 x 6.4 m, 2.2 m of height change)."""
    sc = builtin_scenario("calibration-flight")
    traj = sc.trajectory.model_copy(update={"amplitude": (3.5, 3.2, 1.1)})
    return simulate(sc.model_copy(update={"duration": duration, "trajectory": traj,
                                          "seeds": sc.seeds.model_copy(update={"noise": seed})}))


@pytest.fixture(scope="module")
def survey():
    ds = walk_around()
    truth = ds.anchors.copy()
    an = ds.anchors.copy()
    an["surveyed"] = an["anchor"].isin(SURVEYED)
    # Unsurveyed anchors carry only a rough guess (0.5 m sd per axis): with 3 surveyed anchors the
    # initialising ESKF needs 4 for its first fix; the calibrator uses no prior from it.
    m = ~an["surveyed"].to_numpy()
    guess = an.loc[m, ["x", "y", "z"]].to_numpy() + np.random.default_rng(0).normal(0, 0.5, (m.sum(), 3))
    an.loc[m, ["x", "y", "z"]] = guess
    opts = CalibrationOptions.model_validate({"td_profile": {"enabled": False}, "estimate_anchor_bias": False})
    return truth, calibrate(dataclasses.replace(ds, anchors=an), opts)


def test_unknown_anchors_within_5_cm(survey):
    truth, res = survey
    tab = res.anchors.set_index("anchor")
    tru = truth.set_index("anchor")[["x", "y", "z"]]
    unknown = [a for a in tru.index if a not in SURVEYED]
    assert tab.loc[unknown, "estimated"].all() and not tab.loc[list(SURVEYED), "estimated"].any()
    err = tab.loc[unknown, ["x", "y", "z"]].to_numpy() - tru.loc[unknown].to_numpy()
    sd = tab.loc[unknown, ["sd_x", "sd_y", "sd_z"]].to_numpy()
    assert np.all(np.linalg.norm(err, axis=1) < 0.05), err
    # Honest sigma: every axis within 3 sd, and RMS(error / sd) neither tiny nor large over 15 numbers.
    assert np.all(np.abs(err) < 3 * sd), (err, sd)
    assert 0.3 < float(np.sqrt(np.mean((err / sd) ** 2))) < 2.0
    np.testing.assert_array_equal(tab.loc[list(SURVEYED), ["x", "y", "z"]].to_numpy(), tru.loc[list(SURVEYED)].to_numpy())
    assert not [e for e in res.events if e["kind"] in ("anchor_few_directions", "anchor_mirror_ambiguity")]


def test_anchors_estimated_csv_is_a_dataset_anchor_table(survey, tmp_path):
    _truth, res = survey
    names = {p.name for p in write_calibration(res, tmp_path, plots=False)}
    assert "anchors_estimated.csv" in names
    cal = res.calibration["anchors"]
    assert cal["gauge"]["kind"] == "surveyed" and len(cal["estimated"]) == 5
    assert all(len(cal["positions"][a]["sd"]) == 3 for a in cal["estimated"])
    # The file reads back as an anchors.csv (extra columns sd_x, sd_y, sd_z, estimated are ignored).
    ds = walk_around(duration=2.0)
    folder = tmp_path / "ds"
    from uwbimu.io.dataset import write_dataset

    write_dataset(ds, folder)
    (folder / "anchors.csv").write_text((tmp_path / "anchors_estimated.csv").read_text())
    back = load_dataset(folder)
    np.testing.assert_allclose(back.anchors[["x", "y", "z"]].to_numpy(), res.anchors[["x", "y", "z"]].to_numpy(),
                               atol=1e-8)


def test_bias_confounding_is_named_as_a_warning():
    """An estimated anchor whose bias is estimated too and that sees the motion in a narrow cone is named
    (event ``anchor_bias_confounded``, a warning with its inflation), solved, not refused; none without
    the bias."""
    from uwbimu.calibration import anchors as AN

    ds = walk_around(duration=20.0, seed=2)
    base = {"td_profile": {"enabled": False}, "estimate_anchors": ["A0", "A4"]}
    res = calibrate(ds, CalibrationOptions.model_validate(base))
    ev = {e["anchor"]: e for e in res.events if e["kind"] == "anchor_bias_confounded"}
    tab = ds.anchors.set_index("anchor")
    P = res.trajectory[["px", "py", "pz"]].to_numpy()  # IMU positions: the cone is the same to a few cm
    for a in ("A0", "A4"):  # inflation about 18 and 4 (threshold 10)
        infl = AN.bias_confounding(a, tab.loc[a, ["x", "y", "z"]].to_numpy(float), P)["inflation"]
        assert (a in ev) == (infl > AN.BIAS_INFLATION), (a, infl, sorted(ev))
    assert ev and all(e["severity"] == "warning" and e["inflation"] > AN.BIAS_INFLATION for e in ev.values())
    res0 = calibrate(ds, CalibrationOptions.model_validate(base | {"estimate_anchor_bias": False}), eskf=res.eskf)
    assert not [e for e in res0.events if e["kind"] == "anchor_bias_confounded"]
