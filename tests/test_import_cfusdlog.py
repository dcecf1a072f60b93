"""Crazyflie uSD event-log importer: logs encoded by the test from a simulated TDoA3 flight, and refusals."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from uwbimu.io.importers import cf_usdlog as imp
from uwbimu.io.loader import DatasetError, load_dataset
from uwbimu.sim import builtin_scenario, simulate

EVENTS = imp.EVENT_TYPES


@pytest.fixture(scope="module")
def sim():
    return simulate(builtin_scenario("crazyflie-tdoa3").updated(duration=3.0, time_offset=0.0))


def records(ds, t0_ms=5000.0):
    rec = []
    for t, a, b, d in ds.tdoa[["t", "anchor_a", "anchor_b", "tdoa"]].itertuples(index=False):
        rec.append((0, t0_ms + t * 1e3, (int(a), int(b), d)))
    for r in ds.imu.itertuples(index=False):
        ms = t0_ms + r.t * 1e3
        rec.append((1, ms, (r.ax / 9.81, r.ay / 9.81, r.az / 9.81)))
        rec.append((2, ms, tuple(np.degrees([r.wx, r.wy, r.wz]))))
    for r in ds.groundtruth.itertuples(index=False):
        rec.append((3, t0_ms + r.t * 1e3, (r.px, r.py, r.pz, r.qx, r.qy, r.qz, r.qw)))
    rec.sort(key=lambda x: x[1])
    return rec


def write_case(tmp_path, ds, version=2, data=None):
    log = tmp_path / "log00"
    log.write_bytes(data if data is not None else imp.encode(EVENTS, records(ds), version=version))
    anchors = tmp_path / "anchors.csv"
    ds.anchors.to_csv(anchors, index=False)
    return log, anchors


@pytest.mark.parametrize("version", [1, 2])
def test_round_trip(tmp_path, sim, version):
    log, anchors = write_case(tmp_path, sim, version)
    imp.import_dataset(log, tmp_path / "out", anchors)
    back = load_dataset(tmp_path / "out")
    # float32 on the card: TDoA to ~1e-7 relative; stamps to 1 ms (v1) or 1 us (v2)
    np.testing.assert_allclose(back.tdoa["tdoa"].to_numpy(), sim.tdoa["tdoa"].to_numpy(), atol=1e-6)
    assert list(back.tdoa["anchor_b"].astype(str)) == list(sim.tdoa["anchor_b"])
    tol = 1e-3 if version == 1 else 1e-6
    np.testing.assert_allclose(back.tdoa["t"].to_numpy(), sim.tdoa["t"].to_numpy() - sim.imu["t"].iloc[0],
                               atol=tol)
    np.testing.assert_allclose(back.imu[["ax", "ay", "az"]].to_numpy(), sim.imu[["ax", "ay", "az"]].to_numpy(),
                               atol=1e-4)
    np.testing.assert_allclose(back.imu[["wx", "wy", "wz"]].to_numpy(), sim.imu[["wx", "wy", "wz"]].to_numpy(),
                               atol=1e-5)
    assert back.groundtruth is not None and len(back.groundtruth) == len(sim.groundtruth)


def test_decoder_reads_what_encode_wrote(tmp_path, sim):
    log, _ = write_case(tmp_path, sim)
    events, info = imp.decode(log)
    assert info["crc_ok"] and info["version"] == 2
    assert set(events) == {e for e, _ in EVENTS}
    assert len(events["estTDOA"]["timestamp"]) == len(sim.tdoa)


def _refused(tmp_path, sim, data, **kw):
    log, anchors = write_case(tmp_path, sim, data=data)
    with pytest.raises(DatasetError) as e:
        imp.convert(log, anchors, **kw)
    assert e.value.file == "log00"
    return e.value


def test_refusals_name_file_and_record(tmp_path, sim):
    good = imp.encode(EVENTS, records(sim))
    assert "0xBC" in str(_refused(tmp_path, sim, b"\x00" + good[1:]))
    flipped = bytearray(good)
    flipped[-10] ^= 0xFF
    assert "CRC" in str(_refused(tmp_path, sim, bytes(flipped)))
    # an unknown event id in record 3 (valid CRC): named by record number
    rec = records(sim)
    rec[3] = (7, rec[3][1], ())
    body = imp.encode(EVENTS + [("x", [])] * 8, rec)  # encode knows id 7 ...
    hdr_end = imp.encode(EVENTS, [])[:-4]  # ... the file's header declares only 0-3
    hdr_full = imp.encode(EVENTS + [("x", [])] * 8, [])[:-4]
    data = hdr_end + body[len(hdr_full):-4]
    data += struct.pack("<I", zlib.crc32(data))
    err = _refused(tmp_path, sim, data)
    assert err.row == 3 and "unknown event id 7" in str(err)
    # truncated last record (CRC recomputed, so only the structure is wrong)
    cut = good[:-4][:-3]
    cut += struct.pack("<I", zlib.crc32(cut))
    err = _refused(tmp_path, sim, cut)
    assert "truncated" in str(err) and err.row == len(rec) - 1
    # a CRC mismatch can be overridden, and is recorded
    res = imp.convert(*write_case(tmp_path, sim, data=bytes(flipped)), ignore_crc=True)
    assert any("CRC" in c for c in res.changes)


def test_refuses_missing_event_and_unknown_anchor(tmp_path, sim):
    no_gyro = imp.encode(EVENTS[:2], [r for r in records(sim) if r[0] in (0, 1)])
    err = _refused(tmp_path, sim, no_gyro)
    assert err.column == "estGyroscope"
    rec = records(sim)
    i = next(k for k, r in enumerate(rec) if r[0] == 0 and k > 10)
    n_before = sum(1 for r in rec[:i] if r[0] == 0)
    rec[i] = (0, rec[i][1], (9, 1, 0.5))
    err = _refused(tmp_path, sim, imp.encode(EVENTS, rec))
    assert (err.row, err.column) == (n_before, "anchor_a")


def test_bad_type_code_in_header(tmp_path, sim):
    bad = imp.encode([("estTDOA", [("idA", "Z")])], [])
    err = _refused(tmp_path, sim, bad)
    assert "type code" in str(err) and err.column == "estTDOA"


def test_nominal_lever_arm_is_the_util_platforms_or_given_or_none(tmp_path, sim):
    """dataset.yaml carries the UTIL platform's documented tag offset by default (the prior mean of
    ``lever_arm.prior: dataset``); another vehicle's, or none, when asked."""
    from uwbimu.errors import UsageError
    from uwbimu.estimation.eskf import dataset_lever_prior
    from uwbimu.estimation.options import EskfOptions

    log, anchors = write_case(tmp_path, sim)
    imp.import_dataset(log, tmp_path / "util", anchors)
    back = load_dataset(tmp_path / "util")
    assert back.meta.tags[0].lever_arm == pytest.approx(list(imp.UTIL_T_UV))
    assert "nominal_lever_arm_source" in back.meta.extra
    # the ESKF's default prior is the dataset's nominal lever arm
    assert dataset_lever_prior(back, EskfOptions(), "tag0") == pytest.approx(list(imp.UTIL_T_UV))
    assert dataset_lever_prior(back, EskfOptions(lever_arm={"prior": None}), "tag0") == [0.0, 0.0, 0.0]

    other = imp.convert(log, anchors, lever_arm=[0.0, 0.0, 0.02]).dataset
    assert other.meta.tags[0].lever_arm == pytest.approx([0.0, 0.0, 0.02])
    assert other.meta.extra["nominal_lever_arm_source"] == "given"
    none = imp.convert(log, anchors, lever_arm=None).dataset
    assert none.meta.tags[0].lever_arm is None and "nominal_lever_arm_source" not in none.meta.extra
    assert dataset_lever_prior(none, EskfOptions(), "tag0") == [0.0, 0.0, 0.0]
    for bad in ([0.0, 0.1], [0.0, float("nan"), 0.1]):
        with pytest.raises(UsageError):
            imp.convert(log, anchors, lever_arm=bad)


def test_cli_lever_arm_options(tmp_path, sim):
    """`uwbimu import cf-usdlog --lever-arm X Y Z | --no-lever-arm`: the nominal lever arm written, or none;
    both at once is a usage error (exit 2) that writes nothing."""
    from typer.testing import CliRunner

    from uwbimu.cli.main import app

    log, anchors = write_case(tmp_path, sim)
    base = ["import", "cf-usdlog", str(log), "--anchors", str(anchors)]
    r = CliRunner().invoke(app, base + [str(tmp_path / "given"), "--lever-arm", "0.01", "0.02", "0.03"])
    assert r.exit_code == 0, r.output
    assert load_dataset(tmp_path / "given").meta.tags[0].lever_arm == pytest.approx([0.01, 0.02, 0.03])
    r = CliRunner().invoke(app, base + [str(tmp_path / "none"), "--no-lever-arm"])
    assert r.exit_code == 0, r.output
    assert load_dataset(tmp_path / "none").meta.tags[0].lever_arm is None
    r = CliRunner().invoke(app, base + [str(tmp_path / "both"), "--no-lever-arm", "--lever-arm", "0", "0", "0"])
    assert r.exit_code == 2 and not (tmp_path / "both").exists()
