"""Importers, round 29: TDoA outliers counted (not a refused flight), survey files as --anchors, the survey
quaternion order by file version, single_clock, facts measured on the sequence read, and bad inputs refused
(non-UTF-8, empty, cut short) with exit 1 naming the file and line.

The real-log tests read ``../shared/datasets/util_0425`` (no licence: never copied into the repository) and
skip when it is absent.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.io.importers import cf_usdlog, inrol, isas_walk, util
from uwbimu.io.importers.anchors import read_anchors, read_survey, survey_quat_order
from uwbimu.io.importers.imu_noise import round_up_half_step
from uwbimu.io.importers.tdoa import drop_tdoa_outliers
from uwbimu.io.loader import DatasetError, LoadOptions, load_dataset
from uwbimu.sim import builtin_scenario, simulate

DATA = Path(__file__).parent / "data"
INROL = DATA / "inrol_excerpt"
ISAS = DATA / "isas_walk_excerpt"
UTIL_0425 = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "util_0425"
needs_util = pytest.mark.skipif(not (UTIL_0425 / "raw").is_dir(),
                                reason=f"UTIL 2021 logs not present at {UTIL_0425} (shared data, not in the repo)")
ENV = {"COLUMNS": "200"}

EVENTS = cf_usdlog.EVENT_TYPES

#: A unit quaternion [qw, qx, qy, qz] that is not symmetric under the wxyz <-> xyzw mix-up.
Q_WXYZ = np.array([0.8, 0.2, -0.4, 0.4]) / np.linalg.norm([0.8, 0.2, -0.4, 0.4])


@pytest.fixture(scope="module")
def sim():
    return simulate(builtin_scenario("crazyflie-tdoa3").updated(duration=2.0, time_offset=0.0))


def write_log(folder: Path, ds, wild: dict[int, float] | None = None) -> Path:
    """A uSD log of ``ds``; ``wild`` replaces the TDoA value of the given rows (m)."""
    rec = []
    for i, (t, a, b, d) in enumerate(ds.tdoa[["t", "anchor_a", "anchor_b", "tdoa"]].itertuples(index=False)):
        rec.append((0, 5000.0 + t * 1e3, (int(a), int(b), (wild or {}).get(i, d))))
    for r in ds.imu.itertuples(index=False):
        rec.append((1, 5000.0 + r.t * 1e3, (r.ax / 9.81, r.ay / 9.81, r.az / 9.81)))
        rec.append((2, 5000.0 + r.t * 1e3, tuple(np.degrees([r.wx, r.wy, r.wz]))))
    for r in ds.groundtruth.iloc[::10].itertuples(index=False):
        rec.append((3, 5000.0 + r.t * 1e3, (r.px, r.py, r.pz, r.qx, r.qy, r.qz, r.qw)))
    rec.sort(key=lambda x: x[1])
    log = folder / "log00"
    log.write_bytes(cf_usdlog.encode(EVENTS, rec))
    return log


def write_anchors(folder: Path, ds) -> Path:
    path = folder / "anchors.csv"
    ds.anchors[["anchor", "x", "y", "z"]].to_csv(path, index=False)
    return path


# ---------------------------------------------------------------- TDoA outliers
def test_tdoa_outliers_dropped_counted_per_pair_and_recorded(tmp_path, sim):
    a, b = sim.tdoa["anchor_a"].iloc[3], sim.tdoa["anchor_b"].iloc[3]
    wild = {3: 150.0, 10: -120.0}
    log, anchors = write_log(tmp_path, sim, wild), write_anchors(tmp_path, sim)
    res = CliRunner().invoke(app, ["import", "cf-usdlog", str(log), str(tmp_path / "ds"), "--anchors", str(anchors)],
                             env=ENV)
    assert res.exit_code == 0, res.output
    ds = load_dataset(tmp_path / "ds")  # loads with the default margin: the impossible rows are gone
    assert len(ds.tdoa) == len(sim.tdoa) - 2
    rec = ds.meta.extra["tdoa_outliers"]
    assert rec["rows_dropped"] == 2 and rec["rows_read"] == len(sim.tdoa) and rec["margin_m"] == 1.0
    pairs = {f"{a}-{b}": 1}
    pairs[f"{sim.tdoa['anchor_a'].iloc[10]}-{sim.tdoa['anchor_b'].iloc[10]}"] = \
        pairs.get(f"{sim.tdoa['anchor_a'].iloc[10]}-{sim.tdoa['anchor_b'].iloc[10]}", 0) + 1
    assert rec["by_pair"] == pairs and rec["largest_abs_tdoa_m"] == pytest.approx(150.0)
    # the same count is in the import changes of dataset.yaml and in the console summary
    assert any("2 of" in c and "TDoA" in c for c in ds.meta.extra["import_changes"])
    assert "dropped 2 of" in res.output
    # the kept rows are the source's rows, unchanged
    keep = np.setdiff1d(np.arange(len(sim.tdoa)), list(wild))
    np.testing.assert_allclose(ds.tdoa["tdoa"].to_numpy(), sim.tdoa["tdoa"].to_numpy()[keep], atol=1e-6)


def test_tdoa_margin_option_keeps_rows_and_loading_needs_the_same_margin(tmp_path, sim):
    log, anchors = write_log(tmp_path, sim, {5: 30.0}), write_anchors(tmp_path, sim)
    res = CliRunner().invoke(app, ["import", "cf-usdlog", str(log), str(tmp_path / "ds"), "--anchors", str(anchors),
                                   "--tdoa-margin", "40"], env=ENV)
    assert res.exit_code == 0, res.output
    ds = load_dataset(tmp_path / "ds", LoadOptions(tdoa_margin=40.0))
    assert len(ds.tdoa) == len(sim.tdoa) and ds.meta.extra["tdoa_outliers"]["rows_dropped"] == 0
    with pytest.raises(DatasetError) as e:
        load_dataset(tmp_path / "ds")
    assert e.value.column == "tdoa"
    res = CliRunner().invoke(app, ["import", "cf-usdlog", str(log), str(tmp_path / "d2"), "--anchors", str(anchors),
                                   "--tdoa-margin", "-1"], env=ENV)
    assert res.exit_code == 2 and not (tmp_path / "d2").exists()


def test_tdoa_mostly_beyond_the_bound_is_refused_not_repaired(sim):
    td = sim.tdoa.copy()
    td["tdoa"] = td["tdoa"] * 1e3  # millimetres, not metres
    with pytest.raises(DatasetError) as e:
        drop_tdoa_outliers(td, sim.anchors, 1.0, "x.log", [])
    assert e.value.file == "x.log" and e.value.column == "tdoa"


def test_util_csv_drops_tdoa_outliers_and_says_single_clock(tmp_path, sim):
    path = tmp_path / "csv-data" / "const1" / "const1-trial1-tdoa3.csv"
    path.parent.mkdir(parents=True)
    imu, td = sim.imu, sim.tdoa
    n = max(len(imu), len(td))
    pad = lambda x: list(x) + [""] * (n - len(x))  # noqa: E731
    vals = td["tdoa"].to_numpy().copy()
    vals[7] = 99.0
    pd.DataFrame({"t_tdoa": pad(td["t"]), "idA": pad(td["anchor_a"]), "idB": pad(td["anchor_b"]),
                  "tdoa_meas": pad(vals), "t_acc": pad(imu["t"]),
                  **{f"acc_{c}": pad(imu[f"a{c}"] / 9.81) for c in "xyz"}, "t_gyro": pad(imu["t"]),
                  **{f"gyro_{c}": pad(np.degrees(imu[f"w{c}"])) for c in "xyz"}}).to_csv(path, index=False)
    survey = tmp_path / "survey-results"
    survey.mkdir()
    np.savez(survey / "anchor_const1.npz", an_pos=sim.anchors[["x", "y", "z"]].to_numpy())
    res = CliRunner().invoke(app, ["import", "util", str(path), str(tmp_path / "ds"), "--tdoa-margin", "0.5"], env=ENV)
    assert res.exit_code == 0, res.output
    ds = load_dataset(tmp_path / "ds")
    assert ds.meta.single_clock is True
    rec = ds.meta.extra["tdoa_outliers"]
    assert rec["rows_dropped"] == 1 and rec["margin_m"] == 0.5
    assert rec["by_pair"] == {f"{td['anchor_a'].iloc[7]}-{td['anchor_b'].iloc[7]}": 1}


# ---------------------------------------------------------------- anchors files and quaternion order
def _survey_files(folder: Path, sim, name: str, order: str) -> Path:
    pos = sim.anchors[["x", "y", "z"]].to_numpy()
    q = np.tile(Q_WXYZ if order == "wxyz" else Q_WXYZ[[1, 2, 3, 0]], (len(pos), 1))
    path = folder / name
    np.savez(path, an_pos=pos, an_quat=q)
    return path


@pytest.mark.parametrize("name, order", [("anchor_0425.npz", "wxyz"), ("anchor_const2.npz", "xyzw")])
def test_survey_quaternion_order_by_file_version(tmp_path, sim, name, order):
    path = _survey_files(tmp_path, sim, name, order)
    assert survey_quat_order(path)[0] == order
    changes: list[str] = []
    df = read_survey(path, changes=changes)
    np.testing.assert_allclose(df[["qw", "qx", "qy", "qz"]].to_numpy(), np.tile(Q_WXYZ, (len(df), 1)), atol=1e-12)
    assert len(changes) == 1
    # the wrong order, forced, gives a different rotation (the test can fail)
    wrong = read_survey(path, quat_order="xyzw" if order == "wxyz" else "wxyz")
    assert not np.allclose(np.abs(wrong[["qw", "qx", "qy", "qz"]].to_numpy() @ Q_WXYZ), 1.0)


def test_survey_txt_release_form_and_unknown_name(tmp_path, sim):
    pos = sim.anchors[["x", "y", "z"]].to_numpy()
    q = Q_WXYZ[[1, 2, 3, 0]]
    txt = tmp_path / "anchor_const3_survey.txt"
    txt.write_text("".join(f"an{i}_p,{p[0]},{p[1]},{p[2]}\n" for i, p in enumerate(pos))
                   + "".join(f"an{i}_quat,{q[0]},{q[1]},{q[2]},{q[3]}\n" for i in range(len(pos))))
    df = read_anchors(txt)
    np.testing.assert_allclose(df[["qw", "qx", "qy", "qz"]].to_numpy()[0], Q_WXYZ, atol=1e-12)
    other = tmp_path / "my_survey.txt"
    shutil.copy(txt, other)
    assert survey_quat_order(other) == ("xyzw", survey_quat_order(other)[1])
    assert "ASSUMED" in survey_quat_order(other)[1]


def test_cf_usdlog_anchors_from_npz_survey_and_refusals(tmp_path, sim):
    log = write_log(tmp_path, sim)
    npz = _survey_files(tmp_path, sim, "anchor_0425.npz", "wxyz")
    res = CliRunner().invoke(app, ["import", "cf-usdlog", str(log), str(tmp_path / "ds"), "--anchors", str(npz)],
                             env=ENV)
    assert res.exit_code == 0, res.output
    ds = load_dataset(tmp_path / "ds")
    assert ds.meta.single_clock is True
    np.testing.assert_allclose(ds.anchors[["qw", "qx", "qy", "qz"]].to_numpy()[0], Q_WXYZ, atol=1e-9)
    np.testing.assert_allclose(ds.anchors[["x", "y", "z"]].to_numpy(), sim.anchors[["x", "y", "z"]].to_numpy())
    # the raw total-station survey, a non-UTF-8 anchors.csv and an unknown type: exit 1, the file named
    raw = tmp_path / "anchor_0425.txt"
    raw.write_text("uwbDatasetFrame1,-0.0002,-0.0001,-0.0004\nanchor0_1,-3.1,-3.9,0.24\nanchorAnt0,-3.1,-4.0,0.18\n")
    bad = tmp_path / "bad.csv"
    bad.write_bytes(b"anchor,x,y,z\n0,1,2,3\n\xff1,1,2,3\n")
    odd = tmp_path / "anchors.json"
    odd.write_text("{}\n")
    cut = tmp_path / "anchor_0426.npz"
    cut.write_bytes(npz.read_bytes()[:200])
    for path, row in ((raw, None), (bad, 3), (odd, None), (cut, None)):
        with pytest.raises(DatasetError) as e:
            cf_usdlog.convert(log, path)
        assert e.value.file == path.name and e.value.row == row
        res = CliRunner().invoke(app, ["import", "cf-usdlog", str(log), str(tmp_path / "x"), "--anchors", str(path)],
                                 env=ENV)
        assert res.exit_code == 1 and "Traceback" not in res.output, res.output


# ---------------------------------------------------------------- real UTIL logs (shared, skipped when absent)
@needs_util
def test_real_tdoa3_log_imports_with_outliers_counted(tmp_path):
    log = UTIL_0425 / "raw" / "TDOA3" / "0425-traj16"
    res = CliRunner().invoke(app, ["import", "cf-usdlog", str(log), str(tmp_path / "ds"), "--anchors",
                                   str(UTIL_0425 / "survey" / "anchor_0425.npz")], env=ENV)
    assert res.exit_code == 0, res.output
    ds = load_dataset(tmp_path / "ds")
    rec = ds.meta.extra["tdoa_outliers"]
    assert 0 < rec["rows_dropped"] < 0.01 * rec["rows_read"] and sum(rec["by_pair"].values()) == rec["rows_dropped"]
    assert len(ds.tdoa) == rec["rows_read"] - rec["rows_dropped"]
    assert ds.meta.single_clock is True and ds.groundtruth is not None
    # the npz (2021: [qw, qx, qy, qz]) and the survey's anchors.csv give the same anchors
    csv = read_anchors(UTIL_0425 / "survey" / "anchors_0425.csv")
    cols = ["x", "y", "z", "qw", "qx", "qy", "qz"]
    np.testing.assert_allclose(ds.anchors[cols].to_numpy(), csv[cols].to_numpy(), atol=1e-6)
    raw = np.load(UTIL_0425 / "survey" / "anchor_0425.npz")["an_quat"]
    np.testing.assert_allclose(ds.anchors[["qw", "qx", "qy", "qz"]].to_numpy(),
                               raw / np.linalg.norm(raw, axis=1, keepdims=True), atol=1e-9)
    # the summary prints the units the rich console would have eaten as markup
    assert "[ms]" in res.output and "[g]" in res.output and "[deg/s]" in res.output


@needs_util
def test_real_tdoa2_log_keeps_every_row(tmp_path):
    res = cf_usdlog.import_dataset(UTIL_0425 / "raw" / "TDOA2" / "0425-traj3", tmp_path / "ds",
                                   UTIL_0425 / "survey" / "anchors_0425.csv")
    assert res.dataset.meta.extra["tdoa_outliers"]["rows_dropped"] == 0
    assert res.dataset.meta.single_clock is True


@needs_util
def test_real_raw_survey_txt_is_refused_clearly():
    with pytest.raises(DatasetError) as e:
        read_anchors(UTIL_0425 / "survey" / "anchor_0425.txt")
    assert e.value.file == "anchor_0425.txt" and e.value.hint


# ---------------------------------------------------------------- bad inputs: exit 1, file and line named
def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _cut_last_line(path: Path, keep_fields: int | None, sep: str | None) -> int:
    """Cut the file inside its last line; return that line's number."""
    lines = path.read_text().splitlines()
    last = lines[-1]
    if keep_fields is None:
        cut = last[:-3]  # the same fields, the last number shortened, no line end
    else:
        cut = (sep or " ").join(last.split(sep)[:keep_fields])
    path.write_text("\n".join(lines[:-1] + [cut]))
    return len(lines)


@pytest.mark.parametrize("keep_fields", [None, 3])
@pytest.mark.parametrize("which", ["isas imu.csv", "inrol imu.txt", "inrol uwb.txt"])
def test_cut_short_last_line_is_refused(tmp_path, which, keep_fields):
    kind, fname = which.split()
    src = _copy(ISAS if kind == "isas" else INROL, tmp_path / "src")
    line = _cut_last_line(src / fname, keep_fields, "," if kind == "isas" else None)
    with pytest.raises(DatasetError) as e:
        (isas_walk if kind == "isas" else inrol).convert(src)
    assert (e.value.file, e.value.row) == (fname, line)
    res = CliRunner().invoke(app, ["import", "isas-walk" if kind == "isas" else "inrol", str(src),
                                   str(tmp_path / "o")], env=ENV)
    assert res.exit_code == 1 and not (tmp_path / "o").exists(), res.output


def test_cut_short_util_csv_and_empty_csv_are_refused(tmp_path, sim):
    path = tmp_path / "const1-trial1-tdoa3.csv"
    np.savez(tmp_path / "anchor_const1.npz", an_pos=sim.anchors[["x", "y", "z"]].to_numpy())
    path.write_bytes(b"")
    res = CliRunner().invoke(app, ["import", "util", str(path), str(tmp_path / "o")], env=ENV)
    assert res.exit_code == 1 and "Traceback" not in res.output, res.output
    with pytest.raises(DatasetError) as e:
        util.convert(path)
    assert e.value.file == path.name
    path.write_text("t_tdoa,idA,idB,tdoa_meas,t_acc,acc_x,acc_y,acc_z,t_gyro,gyro_x,gyro_y,gyro_z\n"
                    "0.0,0,1,0.5,0.0,0,0,1,0.0,0,0,0\n0.1,0,1,0.5,0.1,0,0,1,0.1,0,0")
    with pytest.raises(DatasetError) as e:
        util.convert(path)
    assert (e.value.file, e.value.row) == (path.name, 3)


@pytest.mark.parametrize("fname", ["uwb.txt", "imu.txt"])
def test_inrol_non_utf8_is_refused_with_file_and_line(tmp_path, fname):
    src = _copy(INROL, tmp_path / "src")
    data = (src / fname).read_bytes().split(b"\n")
    data[4] = data[4] + b" \xe9"
    (src / fname).write_bytes(b"\n".join(data))
    with pytest.raises(DatasetError) as e:
        inrol.convert(src)
    assert (e.value.file, e.value.row) == (fname, 5)
    res = CliRunner().invoke(app, ["import", "inrol", str(src), str(tmp_path / "o")], env=ENV)
    assert res.exit_code == 1 and "Traceback" not in res.output, res.output


# ---------------------------------------------------------------- facts of the sequence read
def test_isas_sequence_named_from_the_input(tmp_path):
    walk2 = _copy(ISAS, tmp_path / "isas_walk2")
    (walk2 / "ATTRIBUTION.md").unlink()
    meta = isas_walk.convert(walk2).dataset.meta
    assert meta.extra["sequence"] == "ISAS-Walk2" and "Walk2" in meta.source and "Walk1.bag" not in meta.source
    meta = isas_walk.convert(ISAS).dataset.meta  # the excerpt's ATTRIBUTION.md: "# ISAS-Walk1 excerpt"
    assert meta.extra["sequence"] == "ISAS-Walk1"
    anon = _copy(ISAS, tmp_path / "recording")
    (anon / "ATTRIBUTION.md").unlink()
    meta = isas_walk.convert(anon).dataset.meta
    assert "Walk1" not in meta.source and meta.extra["sequence"].startswith("ISAS-Walk (")
    assert meta.single_clock is None  # host stamps of separate devices: not known to be one clock


def test_inrol_facts_are_measured_on_the_input(tmp_path):
    base = inrol.convert(INROL).dataset.meta
    assert base.extra["groundtruth_glitches"]["count"] == 0 and "172.6" not in base.description
    src = _copy(INROL, tmp_path / "src")
    # a 12 cm two-sample jump in the ground truth at line 1001, and ranges twice as noisy
    lines = (src / "imu_pose.txt").read_text().splitlines()
    for k in (1000, 1001):
        c = lines[k].split()
        c[1] = f"{float(c[1]) + 0.12:.12f}"
        lines[k] = " ".join(c)
    (src / "imu_pose.txt").write_text("\n".join(lines) + "\n")
    t_glitch = float(lines[1000].split()[0])
    uwb = (src / "uwb.txt").read_text().splitlines()
    rng = np.random.default_rng(0)
    for k in range(1, len(uwb)):
        c = uwb[k].split()
        c[3] = f"{float(c[3]) + rng.normal(0.0, 0.2):.12f}"
        uwb[k] = " ".join(c)
    (src / "uwb.txt").write_text("\n".join(uwb) + "\n")
    meta = inrol.convert(src).dataset.meta
    g = meta.extra["groundtruth_glitches"]
    assert g["count"] == 2 and g["t"][0] == pytest.approx(t_glitch, abs=1e-6)
    assert meta.range_sigma > base.range_sigma + 0.05
    assert meta.range_sigma == pytest.approx(np.ceil(meta.extra["range_residuals"]["robust_sigma_m"] * 100) / 100)
    assert meta.single_clock is None


def test_round_up_half_step():
    assert [round_up_half_step(x) for x in (2.93e-4, 1.39e-3, 3e-4, 0.97)] == pytest.approx([3e-4, 1.5e-3, 3e-4, 1.0])


def test_written_dataset_yaml_holds_single_clock(tmp_path, sim):
    log, anchors = write_log(tmp_path, sim), write_anchors(tmp_path, sim)
    cf_usdlog.import_dataset(log, tmp_path / "ds", anchors)
    assert yaml.safe_load((tmp_path / "ds" / "dataset.yaml").read_text())["single_clock"] is True
