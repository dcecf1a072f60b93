"""``uwbimu import inrol`` on the committed excerpt (and the full sequence when present)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.io.check import check_dataset
from uwbimu.io.importers import inrol
from uwbimu.io.loader import DatasetError, load_dataset

EXCERPT = Path(__file__).parent / "data" / "inrol_excerpt"
FULL = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "inrol_uwb_imu"
ENV = {"COLUMNS": "200"}


def n_rows(path: Path) -> int:
    return len(path.read_text().splitlines()) - 1  # minus the '#' header


@pytest.fixture(scope="module")
def imported(tmp_path_factory) -> Path:
    dst = tmp_path_factory.mktemp("inrol") / "ds"
    res = CliRunner().invoke(app, ["import", "inrol", str(EXCERPT), str(dst)], env=ENV)
    assert res.exit_code == 0, res.output
    assert "wrote" in res.output
    return dst


def test_excerpt_conversion_values(imported):
    ds = load_dataset(imported)
    assert len(ds.imu) == n_rows(EXCERPT / "imu.txt")
    assert len(ds.uwb) == n_rows(EXCERPT / "uwb.txt")
    assert len(ds.groundtruth) == n_rows(EXCERPT / "imu_pose.txt")
    assert len(ds.anchors) == 8
    # First source rows: imu "0 0.039346218109 wx wy wz ax ay az" -> t, ax..az, wx..wz.
    np.testing.assert_allclose(ds.imu.iloc[0].to_numpy(float),
                               [0.039346218109, 0.147045422914, -0.451711661741, 9.832836885452,
                                -0.000685630042, 0.003896188550, 0.001393836747], rtol=1e-8, atol=1e-11)
    # imu_pose "t tx ty tz qx qy qz qw" -> t, px, py, pz, qw, qx, qy, qz.
    np.testing.assert_allclose(ds.groundtruth.iloc[0].to_numpy(float),
                               [0.029132366180, -0.027788741803, -0.023224520897, 0.696705395230,
                                0.723518271051, -0.010143029001, -0.025207981371, 0.689770242975], rtol=1e-8, atol=1e-11)
    assert ds.uwb["anchor"].iloc[:2].tolist() == ["4", "6"]
    np.testing.assert_allclose(ds.anchor_positions()["2"], [-1.521325623594, -1.871297644138, 0.293390671208])
    # anchor.txt "id tx ty tz qx qy qz qw": the documented antenna orientation -> anchors.csv qw, qx, qy, qz
    a2 = ds.anchors.set_index("anchor").loc["2", ["qw", "qx", "qy", "qz"]].to_numpy(float)
    np.testing.assert_allclose(a2, [0.513857791475, -0.483663161110, -0.509068408645, -0.492817889332])
    # At rest the specific force rotated into the world points up (z-up world, IMU-frame pose).
    from uwbimu.models.quaternion import quat_rotate

    f_w = quat_rotate(ds.groundtruth[["qw", "qx", "qy", "qz"]].to_numpy()[:200],
                      np.tile(ds.imu_u[0, :3], (200, 1)))
    assert abs(np.median(f_w[:, 2]) - 9.83) < 0.05


def test_excerpt_metadata_license_and_attribution(imported):
    meta = yaml.safe_load((imported / "dataset.yaml").read_text())
    assert meta["tags"] == [{"name": "tag0", "lever_arm": [0.0, 0.0, 0.01]}]
    assert meta["truth"]["lever_arm"] == [0.0, 0.0, 0.01]
    assert "time_offset" not in meta["truth"]
    # range_sigma, IMU noise and glitches are measured on the sequence read (here the excerpt)
    sd = meta["extra"]["range_residuals"]["robust_sigma_m"]
    assert meta["range_sigma"] == pytest.approx(np.ceil(sd * 100) / 100) and "GPL-3.0" in meta["license"]
    assert meta["extra"]["groundtruth_glitches"]["count"] == 0 and "one clock" in meta["description"]
    assert meta["imu_noise"]["gyro_noise_density"] == 3.0e-4  # max per-axis sd*sqrt(dt) 2.93e-4 at rest, rounded up
    assert set(meta["extra"]["anchor_orientation_xyzw"]) == {str(i) for i in range(1, 9)}
    assert meta["extra"]["source_sensor_noise_tuning"]["accel"] == 0.10
    assert (imported / "LICENSE").read_bytes() == (EXCERPT / "LICENSE").read_bytes()
    att = (imported / "ATTRIBUTION.md").read_text()
    assert "INRoL/inrol_uwb_localization" in att and "GPL-3.0" in att and "IROS 2024" in att


def test_cli_check_on_imported_excerpt_prints_residual_table(imported):
    res = CliRunner().invoke(app, ["check", str(imported)], env=ENV)
    assert res.exit_code == 0, res.output
    assert "Range residuals per anchor" in res.output and "truth.lever_arm" in res.output
    table = res.output.split("Range residuals per anchor")[1]
    for a in range(1, 9):
        assert f"│      {a} │" in table
    # The medians printed are the ones computed (3 decimals, signed).
    rt = check_dataset(load_dataset(imported)).residual_table
    for a, med in rt["median"].items():
        assert f"│      {a} │" in table and f"{med:+.3f}" in table


def test_cli_check_tables_fit_an_80_column_terminal(imported):
    # A plain terminal is 80 columns wide: no number may be cut to "-0.0…" or cropped.
    res = CliRunner().invoke(app, ["check", str(imported)], env={"COLUMNS": "80"})
    assert res.exit_code == 0, res.output
    assert "…" not in res.output
    # Table lines must fit (flag messages are soft-wrapped by the terminal itself).
    table_lines = [ln for ln in res.output.splitlines() if ln[:1] in "┏┃┡│└"]
    assert len(table_lines) > 20 and max(len(ln) for ln in table_lines) <= 80
    rt = check_dataset(load_dataset(imported)).residual_table
    table = res.output.split("Range residuals per anchor")[1]
    for med, mad in zip(rt["median"], rt["mad"]):
        assert f"{med:+.3f}" in table and f"{mad:.3f}" in table


def test_refuses_non_empty_destination_without_force(imported, tmp_path):
    dst = tmp_path / "out"
    dst.mkdir()
    (dst / "mine.txt").write_text("keep me")
    runner = CliRunner()
    res = runner.invoke(app, ["import", "inrol", str(EXCERPT), str(dst)], env=ENV)
    assert res.exit_code == 4 and "--force" in res.output
    assert (dst / "mine.txt").read_text() == "keep me"
    res = runner.invoke(app, ["import", "inrol", str(EXCERPT), str(dst), "--force"], env=ENV)
    assert res.exit_code == 0, res.output
    assert not (dst / "mine.txt").exists() and (dst / "imu.csv").is_file()
    # Never into (or over) the source itself.
    with pytest.raises(FileExistsError):
        inrol.import_dataset(EXCERPT, EXCERPT, force=True)
    assert (EXCERPT / "imu.txt").is_file()


def test_missing_source_file_is_named(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(EXCERPT, src)
    (src / "imu_pose.txt").unlink()
    res = CliRunner().invoke(app, ["import", "inrol", str(src), str(tmp_path / "o")], env=ENV)
    assert res.exit_code == 1 and "imu_pose.txt" in res.output and "Traceback" not in res.output
    assert not (tmp_path / "o").exists()


def test_malformed_source_line_is_located(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(EXCERPT, src)
    lines = (src / "uwb.txt").read_text().splitlines()
    cells = lines[9].split()
    cells[3] = "oops"
    lines[9] = " ".join(cells)
    (src / "uwb.txt").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError) as info:
        inrol.convert(src)
    err = info.value
    assert (err.file, err.row, err.column) == ("uwb.txt", 10, "r")
    assert "uwb.txt, line 10, column 'r'" in str(err)


def test_out_of_order_source_rows_are_sorted_and_reported(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(EXCERPT, src)
    lines = (src / "uwb.txt").read_text().splitlines()
    lines[20], lines[22] = lines[22], lines[20]  # file lines 21 and 23 (header = line 1)
    (src / "uwb.txt").write_text("\n".join(lines) + "\n")
    result = inrol.import_dataset(src, tmp_path / "o")
    assert len(result.changes) == 1 and "uwb.txt" in result.changes[0] and "line 23" in result.changes[0]
    assert "line 23" in (tmp_path / "o" / "ATTRIBUTION.md").read_text()
    assert load_dataset(tmp_path / "o").uwb["t"].is_monotonic_increasing


@pytest.mark.skipif(not (FULL / "imu.txt").is_file(),
                    reason=f"full INRoL sequence not present at {FULL} (the excerpt tests still run)")
def test_full_sequence_import_and_residuals(tmp_path):
    result = inrol.import_dataset(FULL, tmp_path / "full")
    assert result.changes and "uwb.txt" in result.changes[0]  # one row out of order at t = 149.84 s
    ds = load_dataset(tmp_path / "full")
    assert (len(ds.imu), len(ds.uwb), len(ds.groundtruth)) == (19139, 32422, 22496)
    r = check_dataset(ds)
    tab = r.residual_table
    assert sorted(tab.index) == [str(i) for i in range(1, 9)]
    # Dataset README: per-anchor median residual -0.05..+0.08 m, sd 0.08-0.16 m.
    assert tab["median"].between(-0.07, 0.10).all()
    assert tab["robust_sigma"].between(0.04, 0.17).all()
    assert r.flags == []
    # The facts of this sequence, measured by the importer (not constants): the mocap glitch near 172.63 s.
    assert ds.meta.extra["groundtruth_glitches"]["count"] == 2
    assert ds.meta.extra["groundtruth_glitches"]["t"][0] == pytest.approx(172.63, abs=0.01)
    assert ds.meta.range_sigma == 0.10 and ds.meta.imu_noise.accel_noise_density == 1.5e-3


def test_import_reports_progress_in_order(tmp_path):
    seen = []
    inrol.import_dataset(EXCERPT, tmp_path / "p", progress=lambda stage, frac: seen.append((stage, frac)))
    fracs = [f for _, f in seen]
    assert fracs == sorted(fracs) and fracs[0] == 0.0 and seen[-1] == ("done", 1.0)
    assert [s for s, _ in seen][:3] == ["reading imu.txt", "reading uwb.txt", "reading imu_pose.txt"]
    assert any(s.startswith("writing and validating") for s, _ in seen)
    stages = []
    check_dataset(load_dataset(tmp_path / "p"), progress=lambda s, f: stages.append((s, f)))
    assert [s for s, _ in stages] == ["stream statistics", "range residuals", "anchor refit and id cross-check",
                                      "done"]
    assert [f for _, f in stages] == sorted(f for _, f in stages)
