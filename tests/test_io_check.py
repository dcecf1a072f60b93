"""Dataset diagnostics: residuals against ground truth and anchor flags."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

sys.path.insert(0, str(Path(__file__).parent))  # shared builders, whatever pytest's import mode

from test_io_support import ANCHORS, LEVER, edit_line, make_dataset, truth, write_valid
from uwbimu.cli.main import app
from uwbimu.io.check import (
    CheckOptions,
    check_dataset,
    interpolate_pose,
    lever_arm_for,
    range_residuals,
    residual_score,
    stream_summary,
)
from uwbimu.io.dataset import DatasetMeta, TagMeta, TruthMeta, write_dataset
from uwbimu.models.reference import range_measurement


def test_exact_ranges_have_zero_residual():
    ds = make_dataset(duration=20.0)
    res = range_residuals(ds)
    assert len(res) == len(ds.uwb) and res.attrs["n_outside"] == 0
    # Only the linear/slerp interpolation between 100 Hz truth samples remains.
    assert np.max(np.abs(res["residual"])) < 2e-4
    # Wrong lever arm -> visible residuals: the lever arm is really used.
    res0 = range_residuals(ds, lever_arm=np.zeros(3))
    assert np.max(np.abs(res0["residual"])) > 0.05


def test_prediction_matches_reference_range_model():
    ds = make_dataset(duration=5.0)
    res = range_residuals(ds)
    anchors = ds.anchor_positions()
    for k in (0, 57, 123):
        t = res["t"].iloc[k]
        p, q, _, _ = truth(np.array([t]))
        x = np.zeros(20)
        x[0:3], x[6:10], x[16:19] = p[0], q[0], LEVER
        ref = range_measurement(x, anchors[res["anchor"].iloc[k]])
        assert abs(ref - res["predicted"].iloc[k]) < 2e-4


def test_interpolate_pose_outside_and_gaps():
    ds = make_dataset(duration=2.0)
    gt = ds.groundtruth.drop(index=range(50, 120)).reset_index(drop=True)  # 0.7 s hole
    p, q, valid = interpolate_pose(gt, np.array([-0.1, 0.205, 0.8, 1.5, 5.0]), max_gap=0.5)
    assert valid.tolist() == [False, True, False, True, False]
    pt, qt, _, _ = truth(np.array([0.205, 1.5]))
    np.testing.assert_allclose(p[[1, 3]], pt, atol=1e-4)
    np.testing.assert_allclose(np.abs(np.sum(q[[1, 3]] * qt, axis=1)), 1.0, atol=1e-9)
    assert np.isnan(p[0]).all()


def test_lever_arm_lookup_order():
    m = DatasetMeta(tags=[TagMeta(name="t0", lever_arm=[1, 2, 3]), TagMeta(name="t1", lever_arm=[4, 5, 6])])
    assert lever_arm_for(m)[0].tolist() == [1, 2, 3]
    assert lever_arm_for(m, "t1")[0].tolist() == [4, 5, 6]
    m.truth = TruthMeta(lever_arm=[0.1, 0.2, 0.3], tags={"t1": [7, 8, 9]})
    assert lever_arm_for(m)[0].tolist() == [0.1, 0.2, 0.3]
    assert lever_arm_for(m, "t1")[0].tolist() == [7, 8, 9]
    assert lever_arm_for(DatasetMeta(tags=[]))[0].tolist() == [0, 0, 0]


def test_clean_noisy_data_is_not_flagged():
    ds = make_dataset(duration=40.0, sigma=0.08, seed=3)
    # A few NLOS-like outliers must not trigger flags either.
    rng = np.random.default_rng(4)
    k = rng.choice(len(ds.uwb), 40, replace=False)
    ds.uwb.loc[k, "range"] += rng.exponential(0.8, 40)
    r = check_dataset(ds)
    assert r.flags == []
    tab = r.residual_table
    assert list(tab.index) == list("ABCDEF")
    assert (tab["n"] > 300).all()
    assert np.all(np.abs(tab["median"]) < 0.03)
    assert np.all(np.abs(tab["robust_sigma"] - 0.08) < 0.02)


def test_moved_anchor_is_flagged_with_its_true_position():
    ds = make_dataset(duration=40.0, sigma=0.05, seed=1)
    true_c = ds.anchor_positions()["C"]
    ds.anchors.loc[ds.anchors["anchor"] == "C", ["x", "y", "z"]] = true_c + np.array([0.5, -0.4, 0.3])
    r = check_dataset(ds)
    assert [(f.anchor, f.kind) for f in r.flags] == [("C", "moved")]
    fitted = np.array(r.flags[0].details["fitted"])
    assert np.linalg.norm(fitted - true_c) < 0.1
    assert not r.flags[0].details["bias_explains_too"]
    assert "C" in r.flags[0].message and "misplaced" in r.flags[0].message


def test_small_survey_error_is_not_flagged():
    ds = make_dataset(duration=40.0, sigma=0.05, seed=1)
    ds.anchors.loc[ds.anchors["anchor"] == "C", "x"] += 0.1
    assert check_dataset(ds).flags == []


def test_swapped_anchor_ids_are_flagged():
    ds = make_dataset(duration=40.0, sigma=0.05, seed=2)
    a = ds.anchors.set_index("anchor")
    a.loc[["B", "E"]] = a.loc[["E", "B"]].to_numpy()
    ds.anchors = a.reset_index()
    r = check_dataset(ds)
    kinds = sorted((f.anchor, f.kind, f.details["other"]) for f in r.flags)
    assert kinds == [("B", "swapped", "E"), ("E", "swapped", "B")]
    assert r.residual_table.loc["B", "best_other"] == "E"


def test_constant_range_bias_is_flagged_on_that_anchor_only():
    ds = make_dataset(duration=40.0, sigma=0.05, seed=5)
    ds.uwb.loc[ds.uwb["anchor"] == "D", "range"] += 0.6
    r = check_dataset(ds)
    assert {f.anchor for f in r.flags} == {"D"}
    # Seen from inside the room a range offset looks like a radial anchor
    # shift; the flag must say that a bias explains it too.
    f = r.flags[0]
    assert f.kind == "bias" or (f.kind == "moved" and f.details["bias_explains_too"] and "+0.6" in f.message)


def test_stream_summary_rates_and_gaps():
    ds = make_dataset(duration=10.0)
    ds.imu = ds.imu.drop(index=range(300, 330)).reset_index(drop=True)
    s = stream_summary(ds)
    assert s.loc["imu", "n_gaps"] == 1 and abs(s.loc["imu", "max_gap"] - 0.31) < 1e-9
    assert abs(s.loc["uwb", "rate_hz"] - 50.0) < 0.2
    assert s.loc["groundtruth", "n_gaps"] == 0


def test_check_without_ground_truth():
    ds = make_dataset(duration=5.0)
    ds.groundtruth = None
    r = check_dataset(ds)
    assert r.residual_table is None and "no ground truth" in r.notes[0]


# --- against the simulator (its own truth and calibration) --------------------
def test_check_agrees_with_simulator_truth():
    sim = pytest.importorskip("uwbimu.sim", reason="uwbimu.sim not available")
    sc = sim.builtin_scenario("ideal").model_copy(update={"duration": 8.0})
    ds = sim.simulate(sc)
    assert ds.meta.truth.time_offset != 0  # the offset must not enter: truth is on the UWB clock
    r = check_dataset(ds)
    assert np.max(np.abs(r.residuals["residual"])) < 5e-3
    assert r.flags == []


def test_check_per_tag_lever_arms_from_simulator():
    sim = pytest.importorskip("uwbimu.sim", reason="uwbimu.sim not available")
    sc = sim.builtin_scenario("two-tags").model_copy(update={"duration": 8.0})
    ds = sim.simulate(sc)
    assert "tag" in ds.uwb.columns and ds.uwb["tag"].nunique() == 2
    r = check_dataset(ds)
    sigma = ds.meta.range_sigma or 0.1
    assert r.lever_arm is None
    assert np.all(np.abs(r.residual_table["median"]) < sigma)
    # Per-tag lever arms matter: one lever arm for both tags fits the other tag worse.
    back = r.residuals["tag"] != r.residuals["tag"].iloc[0]
    one = range_residuals(ds, lever_arm=lever_arm_for(ds.meta, str(r.residuals["tag"].iloc[0]))[0])
    assert residual_score(one["residual"][back.to_numpy()]) > 1.2 * residual_score(r.residuals["residual"][back])


# --- CLI ----------------------------------------------------------------------
def test_cli_check_prints_tables_and_flags(tmp_path):
    ds = make_dataset(duration=30.0, sigma=0.05, seed=1)
    a = ds.anchors.set_index("anchor")
    a.loc[["A", "C"]] = a.loc[["C", "A"]].to_numpy()
    ds.anchors = a.reset_index()
    write_dataset(ds, tmp_path / "d")
    runner = CliRunner()
    res = runner.invoke(app, ["check", str(tmp_path / "d"), "--csv", str(tmp_path / "res.csv")],
                        env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    for text in ("Streams", "Range residuals per anchor", "flag (swapped)", "anchors A and C look swapped"):
        assert text in res.output
    assert (tmp_path / "res.csv").read_text().startswith("anchor,n,median,mad")
    res = runner.invoke(app, ["check", str(tmp_path / "d"), "--strict"], env={"COLUMNS": "200"})
    assert res.exit_code == 3
    # An existing --csv file is kept unless --force; a dataset's own file never is replaced.
    (tmp_path / "res.csv").write_text("mine")
    res = runner.invoke(app, ["check", str(tmp_path / "d"), "--csv", str(tmp_path / "res.csv")])
    assert res.exit_code == 4 and "--force" in res.output and (tmp_path / "res.csv").read_text() == "mine"
    res = runner.invoke(app, ["check", str(tmp_path / "d"), "--csv", str(tmp_path / "res.csv"), "--force"])
    assert res.exit_code == 0 and (tmp_path / "res.csv").read_text().startswith("anchor,n,median")
    before = (tmp_path / "d" / "uwb.csv").read_bytes()
    res = runner.invoke(app, ["check", str(tmp_path / "d"), "--csv", str(tmp_path / "d" / "uwb.csv"), "--force"])
    assert res.exit_code == 4 and (tmp_path / "d" / "uwb.csv").read_bytes() == before


def test_cli_check_refusal_exit_code_without_traceback(tmp_path):
    d = write_valid(tmp_path / "d")
    edit_line(d / "uwb.csv", 5, "range", "-2")
    res = CliRunner().invoke(app, ["check", str(d)], env={"COLUMNS": "200"})
    assert res.exit_code == 1
    assert "refused" in res.output and "uwb.csv" in res.output and "line 5" in res.output
    assert "Traceback" not in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit)


def test_cli_check_unit_repair_option(tmp_path):
    ds = make_dataset(duration=5.0)
    ds.imu[["ax", "ay", "az"]] /= 9.81
    write_dataset(ds, tmp_path / "d")
    runner = CliRunner()
    assert runner.invoke(app, ["check", str(tmp_path / "d")]).exit_code == 1
    res = runner.invoke(app, ["check", str(tmp_path / "d"), "--accel-units", "g"], env={"COLUMNS": "200"})
    assert res.exit_code == 0, res.output
    assert "repair:" in res.output and "from g to m/s^2" in res.output


def test_anchor_table_keeps_survey_positions():
    ds = make_dataset(duration=5.0)
    r = check_dataset(ds, CheckOptions())
    np.testing.assert_allclose(r.anchors.loc[list("ABCDEF"), ["x", "y", "z"]].to_numpy(),
                               ANCHORS[["x", "y", "z"]].to_numpy())


def test_groundtruth_in_another_frame_is_not_compared(tmp_path):
    """ISAS-Walk-like data: ground truth in another frame must not produce anchor flags."""
    from uwbimu.io.check import check_dataset
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("circle").updated(duration=10.0))
    gt = ds.groundtruth.copy()
    gt[["px", "py"]] += 5.0  # another frame
    ds.groundtruth = gt
    ds.meta.extra["groundtruth_align"] = "se3"
    result = check_dataset(ds)
    assert result.flags == []
    assert any("another frame" in n for n in result.notes)


def test_outputs_get_normal_file_permissions(tmp_path):
    import os
    import stat

    from uwbimu.io.atomic import write_text

    umask = os.umask(0o022)
    try:
        p = write_text(tmp_path / "out.txt", "x")
    finally:
        os.umask(umask)
    assert stat.S_IMODE(p.stat().st_mode) == 0o644
