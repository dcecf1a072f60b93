"""Rule 2 of uwbimu.estimation.noise_from_data with ``statistic="mean_square"``: the level of the whole error
distribution (tails included, each square capped), next to the robust statistic that fits the core.

Why: on the Crazyflie TDoA logs the errors are heavy-tailed (multipath, NLOS); the robust (MAD) sigma fits
their core and the gate then rejects 8-20 % of the measurements.  The mean-square statistic over every
processed measurement gives the level of all of them; these tests pin what each statistic measures.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from uwbimu.errors import UsageError
from uwbimu.estimation import EskfOptions
from uwbimu.estimation import kernels as K
from uwbimu.estimation.filterpass import REC_ACC, REC_INNOV, REC_S, REC_STATUS
from uwbimu.estimation.noise_from_data import WINSOR_SIGMAS, measurement_noise_from_innovations
from uwbimu.estimation.noise_passes import match_measurement_noise

SIGMA = 0.1


def _mixture(seed: int, n: int = 20000, tail_fraction: float = 0.15, tail_scale: float = 4.0):
    """Innovations with a core of sd SIGMA and a fraction ``tail_fraction`` of sd ``tail_scale`` SIGMA."""
    rng = np.random.default_rng(seed)
    e = rng.normal(size=n)
    tail = rng.random(n) < tail_fraction
    e[tail] *= tail_scale
    return e * SIGMA, np.full(n, SIGMA**2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_mean_square_measures_the_tails_the_robust_statistic_leaves_out(seed):
    innov, S = _mixture(seed)
    robust = measurement_noise_from_innovations(innov, S, SIGMA)
    ms = measurement_noise_from_innovations(innov, S, SIGMA, statistic="mean_square")
    assert robust["statistic"] == "robust" and ms["statistic"] == "mean_square"
    # the whole distribution's variance: 0.85 * 1 + 0.15 * 16 = 3.25 sigma^2 (no square reaches the cap)
    assert ms["changed"]
    assert ms["sigma_new"] == pytest.approx(math.sqrt(3.25) * SIGMA, rel=0.05)
    # the robust statistic sees the core: well below the total
    assert robust["sigma_new"] < 1.3 * SIGMA


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_mean_square_keeps_a_sigma_that_fits_gaussian_innovations(seed):
    rng = np.random.default_rng(seed)
    hph = 0.02**2
    innov = rng.normal(size=5000) * math.sqrt(hph + SIGMA**2)
    r = measurement_noise_from_innovations(innov, np.full(innov.size, hph + SIGMA**2), SIGMA, statistic="mean_square")
    assert r["band"][0] < r["k"] < r["band"][1]
    assert not r["changed"] and r["sigma_new"] == SIGMA


def test_gross_spikes_count_at_most_the_cap():
    rng = np.random.default_rng(6)
    n = 10000
    innov = rng.normal(size=n) * SIGMA
    innov[: n // 100] = 1000.0 * SIGMA  # 1 % of +1000-sigma spikes (e.g. +100 m ranges)
    r = measurement_noise_from_innovations(innov, np.full(n, SIGMA**2), SIGMA, statistic="mean_square")
    # uncapped the spikes alone would give k = 1e4; capped: about 0.99 + 0.01 * WINSOR_SIGMAS^2
    assert r["k"] == pytest.approx(0.99 + 0.01 * WINSOR_SIGMAS**2, rel=0.05)


def test_unknown_statistic_is_refused():
    innov, S = _mixture(7, n=100)
    with pytest.raises(UsageError):
        measurement_noise_from_innovations(innov, S, SIGMA, statistic="median")


def _pass_records(seed: int, n: int = 4000, rejected_fraction: float = 0.2):
    """One pass over ``n`` TDoA rows: accepted rows with innovations of sd SIGMA, gate-rejected rows of 5 SIGMA."""
    rng = np.random.default_rng(seed)
    rec = np.zeros((n, 7))
    rej = rng.random(n) < rejected_fraction
    rec[:, REC_INNOV] = rng.normal(size=n) * SIGMA
    rec[rej, REC_INNOV] = 5.0 * SIGMA * np.sign(rng.normal(size=int(rej.sum())))
    rec[:, REC_S] = SIGMA**2
    rec[:, REC_ACC] = np.where(rej, 0.0, 1.0)
    rec[:, REC_STATUS] = K.UPD_OK
    prob = SimpleNamespace(uwb_t=np.arange(n) * 0.01, uwb_b=np.ones(n, dtype=np.int64))
    passes = [SimpleNamespace(j0=0, j_end=n, rec=rec)]
    return prob, passes, rej


def test_match_counts_the_gate_rejected_measurements_only_for_mean_square():
    prob, passes, rej = _pass_records(8)
    info = {"range_sigma": SIGMA / math.sqrt(2.0), "tdoa_sigma": SIGMA}
    robust = match_measurement_noise(prob, passes, info, EskfOptions())["tdoa"]
    ms = match_measurement_noise(prob, passes, info, EskfOptions(), statistic="mean_square")["tdoa"]
    assert robust["n"] == int((~rej).sum()) and ms["n"] == rej.size
    assert robust["rejected_fraction"] == pytest.approx(rej.mean()) == ms["rejected_fraction"]
    # accepted core of sd SIGMA: the robust step keeps it; with the rejected rows (25 sigma^2 each) the
    # mean square is about 0.8 + 0.2 * 25 = 5.8
    assert not robust["changed"]
    assert ms["changed"] and ms["k"] == pytest.approx(1.0 - rej.mean() + 25.0 * rej.mean(), rel=0.05)
    # an explicitly given sigma is kept by either statistic
    given = match_measurement_noise(prob, passes, info, EskfOptions(tdoa_sigma=SIGMA), statistic="mean_square")
    assert given["tdoa"]["given"] and given["tdoa"]["sigma_new"] == SIGMA
