"""The range-error oracle of ``benchmarks/check_range_error_oracle.py`` (docs/calibrate.md, "What limits INRoL's ATE").

On a simulated log with known per-anchor biases and a known slowly varying error, each oracle must
recover what was simulated, and removing it must bring the smoothed trajectory closer to the truth."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from uwbimu.io.check import range_residuals
from uwbimu.sim import builtin_scenario, simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from check_range_error_oracle import oracle_correction, run  # noqa: E402

BIAS = {"A0": 0.15, "A1": -0.10, "A2": 0.08, "A3": 0.0, "A4": -0.12, "A5": 0.05, "A6": 0.0, "A7": 0.10}


@pytest.fixture(scope="module")
def biased():
    sc = builtin_scenario("calibration-flight")
    sc = sc.model_copy(update={"duration": 20.0, "uwb": sc.uwb.model_copy(update={"anchor_bias": BIAS})})
    return simulate(sc)


def test_constant_oracle_recovers_the_simulated_biases(biased):
    res = range_residuals(biased)
    corr = oracle_correction("constant", res, biased)
    sigma = biased.meta.range_sigma if getattr(biased.meta, "range_sigma", None) else 0.05
    for a, b in BIAS.items():
        m = (res["anchor"] == a).to_numpy()
        got = corr[m]
        assert np.ptp(got) == 0.0
        # 4 sd of a median of m.sum() white ranges (efficiency 2/pi)
        assert abs(got[0] - b) < 4 * 1.2533 * sigma / np.sqrt(m.sum()), (a, got[0], b)
    left = res["residual"].to_numpy() - corr
    assert abs(np.median(left)) < 0.005


def test_smooth_oracle_follows_a_slow_error(biased):
    res = range_residuals(biased)
    t = res["t"].to_numpy()
    slow = 0.1 * np.sin(2 * np.pi * t / 10.0)  # a 10 s period error on top of the biases
    res2 = res.assign(residual=res["residual"] + slow)
    corr = oracle_correction("smooth:2", res2, biased)
    truth = np.array([BIAS[a] for a in res["anchor"]]) + slow
    # a 2 s running median of ~12 ranges of 0.05 m white noise: sd ~0.018 m, plus its lag on the sine
    assert np.sqrt(np.mean((corr - truth) ** 2)) < 0.03
    # a constant per anchor cannot follow it: it leaves the sine's RMS (0.071 m)
    const = oracle_correction("constant", res2, biased)
    assert np.sqrt(np.mean((const - truth) ** 2)) > 0.06


def test_removing_the_biases_improves_the_smoothed_trajectory(biased):
    rows = run(biased, ["none", "constant"], progress=lambda s: None)
    by = {r["model"]: r for r in rows}
    assert by["constant"]["ate_batch"] < 0.6 * by["none"]["ate_batch"]
    assert by["constant"]["residual_mad_cm"] < by["none"]["residual_mad_cm"]
    assert all(np.isfinite(r["ate_multilateration"]) for r in rows)


def test_refuses_a_ground_truth_in_another_frame(biased):
    import copy

    ds = copy.deepcopy(biased)
    ds.groundtruth["px"] = ds.groundtruth["px"] + 5.0
    with pytest.raises(SystemExit, match="anchors' frame"):
        run(ds, ["none"], progress=lambda s: None)


@pytest.mark.parametrize("bad", ["foo", "smooth:", "smooth:-1", "smooth:x"])
def test_unknown_model_is_refused(biased, bad):
    with pytest.raises(ValueError, match="unknown oracle model"):
        oracle_correction(bad, range_residuals(biased), biased)
