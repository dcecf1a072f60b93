"""Batch calibration with several tags: one lever arm per tag (issue 12 item 1)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

pytest.importorskip("gtsam")

from uwbimu.calibration import CalibrationOptions, calibrate, write_calibration  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402

NOPROF = {"td_profile": {"enabled": False}}


def _two_tags(seed: int, duration: float = 20.0):
    sc = builtin_scenario("two-tags")
    return simulate(sc.model_copy(update={"duration": duration, "seeds": sc.seeds.model_copy(update={"noise": seed})}))


@pytest.fixture(scope="module")
def seeded_runs():
    return [(ds, calibrate(ds, CalibrationOptions(**NOPROF))) for ds in (_two_tags(s) for s in (1, 2, 3))]


def test_both_lever_arms_within_three_sigma(seeded_runs):
    """Each tag's lever arm within 3 sigma of its truth on every seed, and the two tags' estimates are
    distinct (each tag's ranges reach its own lever-arm key: mixing them would pull both to one value)."""
    zs = []
    for ds, res in seeded_runs:
        cal, truth = res.calibration, ds.meta.truth.tags
        assert list(cal["tags"]) == ["front", "back"]  # dataset.yaml's order
        for name, blk in cal["tags"].items():
            err = np.subtract(blk["lever_arm"], truth[name])
            sd = np.array(blk["lever_arm_sd"])
            assert np.all(sd > 0.002) and np.all(sd < 0.1), (name, sd)
            assert np.all(np.abs(err) < 3 * sd), (name, err, sd)
            zs.append(err / sd)
            assert blk["ranges"] > 200
        sep = np.subtract(cal["tags"]["front"]["lever_arm"], cal["tags"]["back"]["lever_arm"])
        true_sep = np.subtract(truth["front"], truth["back"])
        assert np.linalg.norm(sep - true_sep) < 0.03, (sep, true_sep)
    rms = float(np.sqrt(np.mean(np.square(zs))))
    assert 0.3 < rms < 1.6, rms


def test_layout_matches_the_eskf_and_the_files(seeded_runs, tmp_path):
    """calibration.yaml: top-level lever_arm = the first tag's, a ``tags`` block as the ESKF writes it, the
    other tags' lever arms in the correlations; residuals.csv has the tag column."""
    ds, res = seeded_runs[0]
    cal = res.calibration
    assert cal["lever_arm"] == cal["tags"]["front"]["lever_arm"]
    assert cal["lever_arm_sd"] == cal["tags"]["front"]["lever_arm_sd"]
    assert set(res.eskf.calibration["tags"]) == set(cal["tags"])
    for blk in cal["tags"].values():
        assert {"lever_arm", "lever_arm_sd"} <= set(blk)
    names = cal["correlations"]["names"]
    assert names[:3] == ["lever_arm_x", "lever_arm_y", "lever_arm_z"]
    i = names.index("lever_arm_back_x")
    assert np.sqrt(np.asarray(cal["correlations"]["matrix"])[i, i]) == pytest.approx(1.0)
    r = res.residuals
    assert list(r.columns[:3]) == ["t", "anchor", "tag"] and set(r["tag"]) == {"front", "back"}
    # each row kept its own tag: the rows of one tag at one stamp are that tag's ranges in uwb.csv
    u = ds.uwb.set_index(["t", "anchor", "tag"])["range"]
    np.testing.assert_allclose(u.loc[list(zip(r["t"], r["anchor"], r["tag"]))].to_numpy(), r["range"])
    write_calibration(res, tmp_path, plots=False)
    back = yaml.safe_load((tmp_path / "calibration.yaml").read_text())
    assert back["tags"]["back"]["lever_arm"] == cal["tags"]["back"]["lever_arm"]


def test_one_tag_outputs_unchanged_by_a_tag_column(seeded_runs):
    """A one-tag log gives the same calibration with or without a (constant) tag column, in the single-tag layout
    (no ``tags`` block); only residuals.csv gains the column.  A two-tag log calibrated with the ESKF's
    ``tag`` option uses that tag alone, as the log filtered to it does."""
    from uwbimu.estimation import EskfOptions

    ds2, _ = seeded_runs[0]
    front = dataclasses.replace(ds2, uwb=ds2.uwb[ds2.uwb["tag"] == "front"].drop(columns="tag").reset_index(drop=True))
    plain = calibrate(front, CalibrationOptions(**NOPROF))
    tagged = dataclasses.replace(front, uwb=front.uwb.assign(tag="front"))
    with_col = calibrate(tagged, CalibrationOptions(**NOPROF), eskf=plain.eskf)
    # the default start (the smoothed ESKF of uwbimu estimate) with the tag chosen
    picked = calibrate(ds2, CalibrationOptions(**NOPROF), eskf_options=EskfOptions(tag="front", smoother="forward_backward"))
    for res in (with_col, picked):
        assert "tags" not in res.calibration
        np.testing.assert_allclose(res.calibration["lever_arm"], plain.calibration["lever_arm"], atol=1e-6)
        np.testing.assert_allclose(res.calibration["lever_arm_sd"], plain.calibration["lever_arm_sd"], rtol=1e-4)
        assert list(res.calibration) == list(plain.calibration)
        assert list(res.residuals.columns) == [c for c in plain.residuals.columns[:2]] + ["tag"] + \
            list(plain.residuals.columns[2:])
        np.testing.assert_allclose(res.residuals["residual"], plain.residuals["residual"], atol=1e-6)
    assert "tag" not in plain.residuals.columns


def test_direction_model_per_tag():
    """With range_model.direction each tag's antenna has its own coefficients (per anchor and tag with
    per_anchor), reported per tag and named per tag in the correlations."""
    ds = _two_tags(4, duration=8.0)
    res = calibrate(ds, CalibrationOptions(**NOPROF, range_model={"direction": {"harmonics": 2, "per_anchor": True}}))
    d = res.calibration["range_model"]["direction"]
    anchors = sorted(ds.anchors["anchor"].astype(str))
    assert list(d["coefficients"]) == ["front", "back"]
    for tag in ("front", "back"):
        assert list(d["coefficients"][tag]) == anchors
    names = res.calibration["correlations"]["names"]
    assert f"direction_back_{anchors[0]}_sin2" in names and f"direction_front_{anchors[-1]}_cos1" in names
    # no coefficient is shared: the two tags' vectors of one anchor differ
    a = anchors[0]
    assert d["coefficients"]["front"][a]["cos1"]["value"] != d["coefficients"]["back"][a]["cos1"]["value"]
    assert "bias_direction" in res.residuals.columns


def test_several_tags_self_survey_runs_and_tdoa_refusal():
    """Self-survey with several tags now calibrates (one lever arm per tag, the named anchor estimated for all
    tags; tests/test_calibrate_survey_tags.py checks the values); a tdoa.csv without tag column next to a
    two-tag uwb.csv is still refused, naming what is not supported."""
    from uwbimu.errors import InputError

    ds = _two_tags(5, duration=4.0)
    a0 = str(ds.anchors["anchor"].iloc[0])
    res = calibrate(ds, CalibrationOptions(**NOPROF, estimate_anchors=[a0]))
    assert res.calibration["anchors"]["estimated"] == [a0] and list(res.calibration["tags"]) == ["front", "back"]
    assert set(res.residuals.loc[res.residuals["anchor"] == a0, "tag"]) == {"front", "back"}
    import pandas as pd

    u = ds.uwb
    a1 = str(ds.anchors["anchor"].iloc[1])
    tdoa = pd.DataFrame({"t": u["t"].iloc[:5].to_numpy(), "anchor_a": a0, "anchor_b": a1, "tdoa": 0.1})
    with pytest.raises(InputError, match="tdoa.csv has no tag column"):
        calibrate(dataclasses.replace(ds, tdoa=tdoa), CalibrationOptions(**NOPROF))


def test_cli_summary_prints_every_tag(seeded_runs):
    from rich.console import Console

    from uwbimu.cli.calibrate import calibration_summary

    ds, res = seeded_runs[0]
    con = Console(record=True, width=160)
    con.print(calibration_summary(res.calibration, ds.meta.truth))
    text = con.export_text()
    for tag in ("front", "back"):
        lev, truth = res.calibration["tags"][tag]["lever_arm"], ds.meta.truth.tags[tag]
        assert f"lever arm x, {tag} (cm)" in text
        assert f"{100 * lev[2]:.2f} ±" in text and f"{100 * truth[2]:.2f}" in text
