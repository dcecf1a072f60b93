"""Rule 2 of uwbimu.estimation.noise_from_data, second step: the range / TDoA sd chosen by the filter's own
predictive likelihood (uwbimu.estimation.noise_search), searched from the covariance-matched level.

Why: on real logs (heavy-tailed, correlated errors) the matched level fits the core of the innovations and
the filter then follows the tails; the predictive likelihood scores every processed measurement under the
pass that used the level.  These tests pin the score (it peaks at the true level, with and without
outliers), the search (it finds the maximum of a known curve, returns the pass it ran there, stays within
its step budget) and the filter's use of it (a configured sd 3 x too small is corrected to the truth; a log
whose configured noise is right runs no search).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.estimation.noise_from_data import outlier_width, predictive_loglik
from uwbimu.estimation.noise_search import MAX_STEPS, STEP, search_level
from uwbimu.sim import builtin_scenario, simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from check_noise_search import nlos_runs  # noqa: E402  (the benchmark's controlled case, one definition)

SIGMA = 0.2
WIDTH = 20.0


def _innovations(seed: int, n: int = 6000, outliers: float = 0.0):
    rng = np.random.default_rng(seed)
    nu = rng.normal(size=n) * SIGMA
    bad = rng.random(n) < outliers
    nu[bad] = rng.uniform(-WIDTH / 2, WIDTH / 2, size=int(bad.sum()))
    return nu


@pytest.mark.parametrize("outliers", [0.0, 0.1])
def test_score_peaks_at_the_true_level_and_fits_the_outlier_fraction(outliers):
    nu = _innovations(1, outliers=outliers)
    scale = STEP ** np.linspace(-2, 2, 17)  # the level tried, relative to the truth
    scores = [predictive_loglik(nu, np.full(nu.size, (c * SIGMA) ** 2), WIDTH) for c in scale]
    best = scale[int(np.argmax([s["ll"] for s in scores]))]
    assert abs(math.log(best)) <= math.log(STEP) / 4 + 1e-12  # within one grid point of the truth
    at_truth = scores[8]
    assert at_truth["n"] == nu.size
    assert at_truth["eps"] == pytest.approx(outliers, abs=0.015)


def test_score_counts_a_gross_spike_at_the_outlier_density_not_as_minus_infinity():
    nu = _innovations(2, n=2000)
    nu[0] = 1e6  # far outside the width: scored at eps / width, finite
    s = predictive_loglik(nu, np.full(nu.size, SIGMA**2), WIDTH)
    assert np.isfinite(s["ll"]) and s["eps"] > 0


def test_outlier_width_scales_with_the_anchors():
    a = np.array([[0, 0, 0], [4, 0, 0], [0, 3, 0], [4, 3, 2.0]])
    assert outlier_width(a) == pytest.approx(2 * math.sqrt(16 + 9 + 4))
    assert outlier_width(10 * a) == pytest.approx(10 * outlier_width(a))


@pytest.mark.parametrize("sigma0", [0.05, 0.3, 1.2])
def test_search_finds_the_maximum_of_a_known_curve(sigma0):
    peak = 0.3
    calls = []

    def evaluate(sig):
        calls.append(sig)
        return {"ll": -(math.log(sig / peak)) ** 2, "eps": 0.01}, ("pass at", sig)

    score0 = {"ll": -(math.log(sigma0 / peak)) ** 2, "eps": 0.01}
    sig, payload, rep = search_level(sigma0, score0, evaluate, payload0=("pass at", sigma0))
    assert sig == pytest.approx(peak, rel=0.06)           # the parabola refines within a fraction of a step
    assert payload == ("pass at", sig)                     # the pass run at the chosen level, not a rerun
    assert len(calls) <= MAX_STEPS + 2
    assert rep["sigma"] == sig and rep["levels"][0][0] == sigma0
    assert rep["ll"] == max(level[1] for level in rep["levels"])


def test_search_keeps_the_start_when_it_is_the_best():
    def evaluate(sig):
        return {"ll": -abs(math.log(sig / 0.1)), "eps": 0.0}, sig

    sig, payload, rep = search_level(0.1, {"ll": 0.0, "eps": 0.0}, evaluate, payload0="start")
    assert sig == 0.1 and payload == "start"
    assert [round(s, 6) for s, *_ in rep["levels"]] == [0.1, round(0.1 * STEP, 6), round(0.1 / STEP, 6)]


def _flight(true_sigma: float, configured: float):
    sc = builtin_scenario("calibration-flight")
    sc = sc.updated(uwb={**sc.uwb.model_dump(), "sigma": true_sigma}, duration=40.0)
    ds = simulate(sc)
    ds.meta.range_sigma = configured
    return ds


def test_filter_corrects_an_understated_range_sd_to_the_truth():
    ds = _flight(0.15, 0.05)
    r = run_eskf(ds, EskfOptions())
    m = r.extra["noise"]["measurements"]["range"]
    assert m["changed"] and "likelihood" in m
    used = r.calibration["measurement_noise"]["range"]["sigma"]
    assert used == pytest.approx(0.15, rel=0.2)
    assert used == m["likelihood"]["sigma"] == m["sigma_new"]
    assert r.calibration["measurement_noise"]["range"]["method"] == "predictive_likelihood"


def test_a_log_whose_configured_noise_is_right_runs_no_search():
    ds = _flight(0.05, 0.05)
    r = run_eskf(ds, EskfOptions())
    m = r.extra["noise"]["measurements"]["range"]
    assert not m["changed"] and "likelihood" not in m


def test_on_nlos_ranges_the_search_improves_the_trajectory_and_the_time_offset_sd():
    """Ranges with 10 % NLOS errors (positive, scale 0.3 m) and a configured sd 2.5 x too small: covariance
    matching fits the core; the likelihood's level gives a better trajectory and a t_d sd its error agrees
    with (seeds 1-3; measured: RMSE 0.176 vs 0.202 m, rms t_d error / sd 2.05 vs 3.40)."""
    runs = [nlos_runs(seed) for seed in (1, 2, 3)]
    rmse = {k: [r[k][0] for r in runs] for k in (True, False)}
    z_td = {k: [r[k][1] for r in runs] for k in (True, False)}
    assert np.mean(rmse[True]) < 0.9 * np.mean(rmse[False])
    assert np.sqrt(np.mean(np.square(z_td[True]))) < np.sqrt(np.mean(np.square(z_td[False])))
