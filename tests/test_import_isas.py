"""ISAS-Walk importer on the bundled excerpt (GPL-3.0 data, see tests/data/isas_walk_excerpt/ATTRIBUTION.md)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from uwbimu.io.importers.isas_walk import LEVER_ARM, TOA_OFFSET, convert, import_dataset
from uwbimu.io.loader import DatasetError, load_dataset

EXCERPT = Path(__file__).parent / "data" / "isas_walk_excerpt"


def test_import_excerpt_roundtrip(tmp_path):
    dst = tmp_path / "ds"
    res = import_dataset(EXCERPT, dst)
    ds = load_dataset(dst)
    raw_u = pd.read_csv(EXCERPT / "uwb_ranges.csv")
    raw_i = pd.read_csv(EXCERPT / "imu.csv")
    raw_g = pd.read_csv(EXCERPT / "groundtruth_vive.csv")
    # only fresh ranges, as SFUISE; the drop is counted
    fresh = raw_u[raw_u.ra_valid == 1]
    assert len(ds.uwb) == len(fresh)
    assert any(f"dropped {int((raw_u.ra_valid != 1).sum())} stale" in c for c in res.changes)
    assert len(ds.imu) == len(raw_i) and len(ds.groundtruth) == len(raw_g)
    # one common time origin (header stamps), microseconds kept
    t0 = ds.meta.extra["time_origin_unix_s"]
    np.testing.assert_allclose(ds.imu["t"].to_numpy() + t0, raw_i.t_header_s.to_numpy(), atol=2e-6, rtol=0)
    np.testing.assert_allclose(np.sort(ds.uwb["t"].to_numpy() + t0), np.sort(fresh.t_header_s.to_numpy()), atol=2e-6, rtol=0)
    # ranges unchanged, matched by (stamp, anchor)
    m = ds.uwb.assign(ts=np.round(ds.uwb.t + t0, 6)).merge(
        fresh.assign(ts=np.round(fresh.t_header_s, 6), anchor=fresh.anchor_id.astype(str)), on=["ts", "anchor"])
    assert len(m) == len(ds.uwb)
    np.testing.assert_allclose(m["range"], m["range_m"])
    # gyro/accel columns mapped in order
    np.testing.assert_allclose(ds.imu[["ax", "wz"]].to_numpy(), raw_i[["ax_mps2", "gz_radps"]].to_numpy())
    # ground truth quaternion reordered to [qw, qx, qy, qz]
    np.testing.assert_allclose(ds.groundtruth["qw"].to_numpy(), raw_g["qw"].to_numpy(), atol=1e-6)  # loader renormalises
    # documented calibration: known biases with measured = true + bias = true - toa_offset
    assert ds.meta.known_anchor_bias == {a: -v for a, v in TOA_OFFSET.items()}
    assert ds.meta.known_anchor_bias["9524"] == pytest.approx(-0.1539)
    assert ds.meta.tags[0].lever_arm == LEVER_ARM == ds.meta.truth.lever_arm
    assert ds.meta.extra["groundtruth_align"] == "se3"
    assert "VIVE" in ds.meta.description
    # white noise measured over the stationary start (the board is noisier than the ICM-20948 datasheet)
    assert "measured at rest" in ds.meta.extra["imu_noise_note"] and "Welch" in ds.meta.extra["imu_noise_note"]
    assert 5e-4 < ds.meta.imu_noise.gyro_noise_density < 1e-2
    # the anchors' frame is z-down: recorded for the estimator, with the preset that handles it
    assert ds.meta.anchor_frame_up == "-z" and ds.anchor_frame_up == "-z"
    assert ds.meta.extra["recommended_config"] == "examples/estimator_isas.yaml"
    assert (Path(__file__).parents[1] / ds.meta.extra["recommended_config"]).is_file()
    assert "Z-DOWN" in ds.meta.description and "anchor_frame_up: -z" in ds.meta.description
    assert ds.meta.imu_noise.accel_bias_sigma0 > 0.17  # covers |a| - g = 0.175 m/s^2 at rest
    # licence travels with the data
    assert (dst / "LICENSE").read_bytes() == (EXCERPT / "LICENSE").read_bytes()


def test_refuses_nonempty_destination_without_force(tmp_path):
    dst = tmp_path / "ds"
    dst.mkdir()
    (dst / "keep.txt").write_text("user file")
    with pytest.raises(FileExistsError, match="not empty"):
        import_dataset(EXCERPT, dst)
    assert (dst / "keep.txt").read_text() == "user file"
    import_dataset(EXCERPT, dst, force=True)
    assert (dst / "imu.csv").is_file()


def test_bad_source_errors_name_file_line_column(tmp_path):
    src = tmp_path / "src"
    shutil.copytree(EXCERPT, src)
    lines = (src / "imu.csv").read_text().splitlines()
    cells = lines[5].split(",")
    cells[2] = "abc"
    lines[5] = ",".join(cells)
    (src / "imu.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(DatasetError, match=r"imu.csv, line 6, column 'ax_mps2'"):
        convert(src)
    (src / "uwb_ranges.csv").unlink()
    with pytest.raises(DatasetError, match="uwb_ranges.csv"):
        convert(src)


def test_cli_isas_walk(tmp_path):
    from uwbimu.cli.main import app

    r = CliRunner().invoke(app, ["import", "isas-walk", str(EXCERPT), str(tmp_path / "ds"), "--no-groundtruth"])
    assert r.exit_code == 0, r.output
    assert "estimator_isas.yaml" in r.output and "z-down" in r.output
    assert not (tmp_path / "ds" / "groundtruth.csv").exists()
    # the output rule: its own unchanged import is replaced; an edited one needs --force
    r = CliRunner().invoke(app, ["import", "isas-walk", str(EXCERPT), str(tmp_path / "ds")])
    assert r.exit_code == 0, r.output
    (tmp_path / "ds" / "notes.txt").write_text("mine")
    r = CliRunner().invoke(app, ["import", "isas-walk", str(EXCERPT), str(tmp_path / "ds")])
    assert r.exit_code == 4 and "notes.txt" in r.output


def test_noise_density_from_low_frequency_spectrum():
    """A low-pass filtered white noise: the in-band density is recovered; sd*sqrt(dt) understates it."""
    from scipy.signal import butter, lfilter

    from uwbimu.io.importers.isas_walk import _imu_noise_at_rest

    fs, q_g, q_a = 82.0, 4e-3, 1e-2  # two-sided densities [unit/sqrt(Hz)]
    n = int(3.0 * fs) + 1
    rng = np.random.default_rng(3)
    b, a = butter(4, 8.0 / (fs / 2))  # the board's low-pass (in-band gain 1 up to ~5 Hz)
    w = lfilter(b, a, rng.normal(0, q_g * np.sqrt(fs), (n + 200, 3)), axis=0)[200:]
    acc = lfilter(b, a, rng.normal(0, q_a * np.sqrt(fs), (n + 200, 3)), axis=0)[200:] + [0.0, 0.0, 9.81]
    imu = pd.DataFrame({"t": np.arange(n) / fs, "ax": acc[:, 0], "ay": acc[:, 1], "az": acc[:, 2],
                        "wx": w[:, 0], "wy": w[:, 1], "wz": w[:, 2]})
    noise, note = _imu_noise_at_rest(imu)
    assert noise.gyro_noise_density == pytest.approx(q_g, rel=0.25)
    assert noise.accel_noise_density == pytest.approx(q_a, rel=0.25)
    naive = w.std(axis=0).mean() / np.sqrt(fs)
    assert naive < 0.6 * q_g  # what sd*sqrt(dt) would have reported
    assert "Welch" in note
