"""Repeatability: window splitting and the chi-square consistency of window estimates."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from uwbimu.eval.repeatability import consistency, repeatability, split_windows
from uwbimu.io.dataset import Dataset, DatasetMeta, TruthMeta


def _dataset(duration=40.0):
    t = np.arange(0, duration, 0.01)
    imu = pd.DataFrame({"t": t, "ax": 0.0, "ay": 0.0, "az": 9.81, "wx": 0.0, "wy": 0.0, "wz": 0.0})
    tu = np.arange(0, duration, 0.05)
    uwb = pd.DataFrame({"t": tu, "anchor": "1", "range": 2.0})
    gt = pd.DataFrame({"t": t, "px": 0.0, "py": 0.0, "pz": 0.0, "qw": 1.0, "qx": 0.0, "qy": 0.0, "qz": 0.0})
    an = pd.DataFrame({"anchor": ["1"], "x": [1.0], "y": [0.0], "z": [0.0]})
    meta = DatasetMeta(name="stub", truth=TruthMeta(lever_arm=[0.1, 0.0, 0.05], time_offset=0.02))
    return Dataset(imu=imu, uwb=uwb, anchors=an, groundtruth=gt, meta=meta)


def test_split_windows_partition_without_overlap():
    ds = _dataset()
    wins = split_windows(ds, 4)
    assert len(wins) == 4
    assert sum(len(w.imu) for w in wins) == len(ds.imu)
    assert sum(len(w.uwb) for w in wins) == len(ds.uwb)
    assert sum(len(w.groundtruth) for w in wins) == len(ds.groundtruth)
    for a, b in zip(wins[:-1], wins[1:]):
        assert a.imu["t"].max() < b.imu["t"].min()
    with pytest.raises(ValueError):
        split_windows(ds, 1)


class StubEstimator:
    """Returns truth + Gaussian noise of ``true_sd`` while reporting ``claimed_sd``."""

    def __init__(self, true_sd, claimed_sd, seed=0, fail_on=None):
        self.rng = np.random.default_rng(seed)
        self.true_sd, self.claimed_sd, self.calls, self.fail_on = true_sd, claimed_sd, 0, fail_on

    def __call__(self, w: Dataset):
        self.calls += 1
        if self.fail_on == self.calls:
            raise RuntimeError("diverged")
        la = np.array(w.meta.truth.lever_arm) + self.rng.normal(0, self.true_sd, 3)
        return {"lever_arm": la.tolist(), "lever_arm_sd": [self.claimed_sd] * 3,
                "time_offset": 0.02 + self.rng.normal(0, self.true_sd / 10), "time_offset_sd": self.claimed_sd / 10}


def test_honest_sigmas_are_consistent_and_overconfident_ones_are_flagged():
    ds = _dataset()
    good = repeatability(ds, 8, StubEstimator(0.01, 0.01, seed=1))
    for p in ("lx", "ly", "lz", "time_offset"):
        assert good["parameters"][p]["verdict"] == "consistent", good["parameters"][p]
        assert 0.4 < good["parameters"][p]["ratio"] < 1.8
    assert abs(good["parameters"]["lx"]["mean_error"]) < 0.02
    over = repeatability(ds, 8, StubEstimator(0.05, 0.005, seed=2))
    for p in ("lx", "ly", "lz", "time_offset"):
        assert over["parameters"][p]["verdict"] == "over-confident"
        assert over["parameters"][p]["ratio"] > 4
    under = repeatability(ds, 8, StubEstimator(0.001, 0.05, seed=3))
    assert under["parameters"]["lx"]["verdict"] == "under-confident"


def test_failed_window_is_reported_not_fatal():
    rep = repeatability(_dataset(), 4, StubEstimator(0.01, 0.01, fail_on=2))
    assert rep["n_failed"] == 1
    assert "diverged" in rep["windows"][1]["error"]
    assert rep["parameters"]["lx"]["n"] == 3


def test_consistency_chi_square_calibration():
    # under honest sigmas the p-value is uniform: about 1 % of trials fall below 0.01
    rng = np.random.default_rng(7)
    p = np.array([consistency(rng.normal(0, 1, 6), np.ones(6))["p_value"] for _ in range(2000)])
    assert 0.005 < np.mean(p < 0.01) < 0.02
    assert 0.45 < np.mean(p < 0.5) < 0.55
    assert consistency(np.array([1.0, 1.1]), np.array([0.0, 0.0]))["verdict"].startswith("not estimated")


def test_repeatability_cli_with_stub_estimator(tmp_path, monkeypatch):
    import json
    from pathlib import Path

    from typer.testing import CliRunner

    from uwbimu.estimation import EskfOptions, registry
    from uwbimu.cli.main import app
    from uwbimu.io.importers.isas_walk import import_dataset

    import_dataset(Path(__file__).parent / "data" / "isas_walk_excerpt", tmp_path / "ds")
    stub = StubEstimator(0.01, 0.01, seed=4)
    monkeypatch.setitem(registry._REGISTRY, "eskf",
                        registry.EstimatorEntry("eskf", lambda ds, opts, progress: stub(ds), EskfOptions, "stub"))
    r = CliRunner().invoke(app, ["repeatability", str(tmp_path / "ds"), "--out", str(tmp_path / "out"), "--windows", "3"])
    assert r.exit_code == 0, r.output
    rep = json.loads((tmp_path / "out" / "repeatability.json").read_text())
    assert stub.calls == 3 and rep["k"] == 3 and set(rep["parameters"]) == {"lx", "ly", "lz", "time_offset"}
    assert rep["parameters"]["lx"]["truth"] == 0.10  # ISAS documented lever arm


def test_windows_on_the_executors_match_the_serial_run():
    """``workers=2`` runs the windows through uwbimu.studies.executors: same records, in window order."""
    from uwbimu.sim import builtin_scenario, simulate

    sc = builtin_scenario("calibration-flight").model_copy(update={"duration": 24.0})
    ds = simulate(sc)
    serial = repeatability(ds, 2, "eskf")
    pooled = repeatability(ds, 2, "eskf", workers=2)
    assert [r["i"] for r in pooled["windows"]] == [0, 1]
    for a, b in zip(serial["windows"], pooled["windows"]):
        assert "error" not in a and "error" not in b, (a, b)  # the ESKF's typed calibration is read
        assert a["values"] == b["values"] and a["sd"] == b["sd"]
    assert pooled["parameters"].keys() == serial["parameters"].keys()
    with pytest.raises(ValueError):
        repeatability(ds, 2, lambda w: None, workers=2)


@pytest.mark.parametrize("with_truth", [True, False])
def test_report_table_shows_the_truth_when_the_dataset_has_it(tmp_path, with_truth):
    """The demo's repeatability table (report section) carries the truth, mean - truth and z columns
    exactly when the dataset has a truth (issue 27): from repeatability.json's ``truth`` per parameter."""
    import json

    from uwbimu.eval.report.inputs import ReportInputs
    from uwbimu.eval.report.sections import _repeatability_section

    ds = _dataset()
    if not with_truth:
        ds.meta.truth = None
    stub = StubEstimator(0.01, 0.01, seed=5)
    truth = TruthMeta(lever_arm=[0.1, 0.0, 0.05], time_offset=0.02)
    # the stub needs a truth to draw from: give it one on the windows only
    rep = repeatability(ds, 4, lambda w: stub(Dataset(imu=w.imu, uwb=w.uwb, anchors=w.anchors, groundtruth=None,
                                                      meta=w.meta.model_copy(update={"truth": truth}))))
    (tmp_path / "repeatability.json").write_text(json.dumps(rep))
    for p, v in zip(("lx", "ly", "lz", "time_offset"), (0.1, 0.0, 0.05, 0.02)):
        if with_truth:
            assert rep["parameters"][p]["truth"] == v
            assert rep["parameters"][p]["mean_error"] == pytest.approx(rep["parameters"][p]["mean"] - v)
        else:
            assert "truth" not in rep["parameters"][p]
    _, attrs = _repeatability_section(ReportInputs(tmp_path, None))
    assert attrs == {"truth-shown": "yes" if with_truth else "no", "parameters": 4}


def test_a_parameter_held_at_its_prior_is_reported_held_not_under_confident():
    """A window whose estimator held the lever arm at its prior (the ESKF's consider mode, the batch's
    held_at_prior) returns the prior with the prior's sigma: no spread by construction.  Those windows are left
    out of the sigma test; held in every window, the verdict says so (was: "under-confident", p = 1)."""
    from types import SimpleNamespace

    ds = _dataset()
    held_eskf = StubEstimator(0.01, 0.01, seed=4)

    def eskf_like(w):
        cal = held_eskf(w)
        cal["lever_arm"], cal["lever_arm_sd"] = [0.0, 0.0, 0.01], [0.3, 0.3, 0.3]
        return SimpleNamespace(calibration=cal, config={"resolved": {"modes": {"lever_arm": "consider",
                                                                               "time_offset": "estimate"}}})

    rep = repeatability(ds, 4, eskf_like)
    for p in ("lx", "ly", "lz"):
        assert rep["parameters"][p]["verdict"] == "held at its prior"
        assert rep["parameters"][p]["held_windows"] == 4 and rep["parameters"][p]["n"] == 0
    assert rep["parameters"]["time_offset"]["verdict"] == "consistent"
    assert rep["parameters"]["time_offset"]["held_windows"] == 0

    # the batch's record: held in two windows of four, the other two tested
    calls = {"n": 0}
    stub = StubEstimator(0.01, 0.01, seed=5)

    def batch_like(w):
        calls["n"] += 1
        cal = stub(w)
        if calls["n"] <= 2:
            cal["held_at_prior"] = {"blocks": ["lever_arm"]}
        return cal

    rep = repeatability(ds, 4, batch_like)
    assert rep["parameters"]["lx"]["held_windows"] == 2 and rep["parameters"]["lx"]["n"] == 2
    assert rep["parameters"]["lx"]["verdict"] in ("consistent", "over-confident", "under-confident")
