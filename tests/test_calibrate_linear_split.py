"""The batch's error split at the truth (``benchmarks/check_calibrate_linear_split.py``) and the control-variate
efficiency estimate of ``benchmarks/check_calibrate_mc.py`` (docs/calibrate.md, "Against the Cramér-Rao bound").

The Gauss-Newton step of the plain least-squares graph linearised at the truth must be the calibrator's error to
first order, and its range part the exact linear map of the simulated range noise; the control variate must
estimate the same mean square error as the plain RMS, with a smaller spread.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from check_calibrate_linear_split import PLAIN, truth_step  # noqa: E402
from check_calibrate_mc import control_variate_rms  # noqa: E402

from uwbimu.calibration import CalibrationOptions, calibrate  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate_full  # noqa: E402
from uwbimu.studies.crlb import posterior_bound  # noqa: E402


@pytest.fixture(scope="module")
def flight():
    sc = builtin_scenario("calibration-flight")
    sc = sc.model_copy(update={"duration": 25.0, "seeds": sc.seeds.model_copy(update={"noise": 1007})})
    sim = simulate_full(sc)
    o = CalibrationOptions.model_validate(PLAIN)
    res = calibrate(sim.dataset, o)
    return sc, sim, res, truth_step(sim, sc, res.eskf, o)


def test_step_from_the_truth_is_the_calibrators_error(flight):
    sc, sim, res, st = flight
    truth = sim.dataset.meta.truth
    err = np.append(np.subtract(res.calibration["lever_arm"], truth.lever_arm),
                    res.calibration["time_offset"]["value"] - truth.time_offset)
    b = posterior_bound(sim, sc)
    crlb = np.append(b["lever_arm_sd"], b["time_offset_sd"])
    # the same cost minimised: the one-step linear estimate from the truth is the solution to a tenth of the bound
    np.testing.assert_array_less(np.abs(err - np.array(st["gn"])), 0.1 * crlb)
    # and the white model's sigma of that graph is the bound's (the two models are built independently)
    np.testing.assert_allclose(st["sd_model"], crlb, rtol=0.1)
    # the range part carries most of the lever arm's variance; its exact sd is below the model sigma
    assert np.all(np.array(st["pred_range"]) <= np.array(st["sd_model"]) * (1 + 1e-9))


def test_range_part_is_the_map_of_the_range_noise(flight):
    """Scaling the simulated range noise scales the range part exactly (a linear map of the draws)."""
    sc, sim, res, st = flight
    sc2 = sc.model_copy(update={"uwb": sc.uwb.model_copy(update={"sigma": 2 * sc.uwb.sigma})})
    sim2 = simulate_full(sc2)  # same seeds: the same standard normal draws, twice the noise
    o = CalibrationOptions.model_validate(PLAIN | {"range_sigma": sc.uwb.sigma})  # the same weights
    st2 = truth_step(sim2, sc2, res.eskf, o)
    # exactly linear up to the model's own discretisation at the truth (the range factors' kinematics between
    # keyframes against the simulator's exact trajectory: ~0.1 mm), here within 1 % of the part's sd
    np.testing.assert_array_less(np.abs(np.array(st2["gn_range"]) - 2 * np.array(st["gn_range"])),
                                 0.01 * np.array(st["pred_range"]))
    np.testing.assert_allclose(st2["pred_range"], st["pred_range"], rtol=1e-9)


def test_control_variate_estimates_the_same_error_with_less_spread():
    rng = np.random.default_rng(1)
    plain, cv = [], []
    for _ in range(300):
        n = 20
        G = rng.normal(0.0, 0.9, (n, 1))  # known part, exact sd 0.9
        E = G + rng.normal(0.0, np.sqrt(1 - 0.81), (n, 1))  # total RMS 1
        est, _sd = control_variate_rms(E, G, np.full((n, 1), 0.9), n_boot=10)
        cv.append(est[0])
        plain.append(np.sqrt(np.mean(E**2)))
    cv, plain = np.array(cv), np.array(plain)
    assert abs(np.mean(cv**2) - 1.0) < 0.03
    assert abs(np.mean(plain**2) - 1.0) < 0.06
    # var(E^2 - G^2) = var(H^2) + 4 var(G H): sd ratio sqrt((2 * 0.19^2 + 4 * 0.81 * 0.19) / 2) = 0.59
    assert np.std(cv) < 0.75 * np.std(plain), (np.std(cv), np.std(plain))
