"""Noise from the data (uwbimu.estimation.noise_from_data): the three stated rules, and run_eskf using them.

Rule 1: the IMU densities from the 5-25 Hz spectrum (never below the preset); rule 2: range/TDoA sd by
covariance matching of the innovations; rule 3: the calibration sds grow with the residuals' long-run
variance when it is significantly above 1.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.estimation.noise_from_data import (
    imu_noise_from_log, measurement_noise_from_innovations, residual_variance_factor)
from uwbimu.models.imu import imu_preset
from uwbimu.sim import builtin_scenario, simulate

PRESET = imu_preset("bmi088")


def _imu(seed: int, acc_density: float, gyr_density: float, rate: float = 200.0, seconds: float = 60.0):
    """White sensor noise of the given densities on top of a slow (0.3 Hz) motion of 3 m/s^2 and 1 rad/s."""
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * rate)) / rate
    motion = np.column_stack([3.0 * np.sin(2 * np.pi * 0.3 * t + k) for k in range(3)]
                             + [1.0 * np.sin(2 * np.pi * 0.2 * t + k) for k in range(3)])
    noise = rng.normal(size=(t.size, 6)) * np.r_[[acc_density] * 3, [gyr_density] * 3] * math.sqrt(rate)
    return t, motion + noise


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_imu_density_recovered_from_the_spectrum_under_motion(seed):
    acc, gyr = 20 * PRESET.accel_noise_density, 5 * PRESET.gyro_noise_density
    t, u = _imu(seed, acc, gyr)
    noise, rep = imu_noise_from_log(t, u, PRESET)
    assert rep["status"] == "measured"
    assert noise.accel_noise_density == pytest.approx(acc, rel=0.05)
    assert noise.gyro_noise_density == pytest.approx(gyr, rel=0.05)
    # the bias random walks follow the density ratio
    assert noise.accel_bias_rw / PRESET.accel_bias_rw == pytest.approx(rep["accel"]["ratio"], rel=1e-9)


def test_imu_density_never_below_the_preset_and_short_logs_keep_it():
    t, u = _imu(3, 0.2 * PRESET.accel_noise_density, 0.2 * PRESET.gyro_noise_density)
    noise, rep = imu_noise_from_log(t, u, PRESET)
    assert noise.accel_noise_density == PRESET.accel_noise_density
    assert noise.gyro_noise_density == PRESET.gyro_noise_density
    assert rep["accel"]["log"] < PRESET.accel_noise_density
    t, u = _imu(3, PRESET.accel_noise_density, PRESET.gyro_noise_density, seconds=4.0)
    noise, rep = imu_noise_from_log(t, u, PRESET)
    assert noise is PRESET and rep["status"] == "too short"


@pytest.mark.parametrize("true_scale", [1.0, 3.0, 0.5])
def test_covariance_matching_recovers_the_measurement_sd(true_scale):
    rng = np.random.default_rng(7)
    sigma, hph = 0.1, 0.002**2
    n = 4000
    innov = rng.normal(size=n) * math.sqrt(hph + (true_scale * sigma) ** 2)
    S = np.full(n, hph + sigma**2)
    r = measurement_noise_from_innovations(innov, S, sigma)
    if true_scale == 1.0:
        assert not r["changed"] and r["sigma_new"] == sigma
    else:
        assert r["changed"]
        assert r["sigma_new"] == pytest.approx(true_scale * sigma, rel=0.1)


def test_variance_factor_false_alarms_on_white_residuals_and_detects_correlation():
    rng = np.random.default_rng(11)
    n_ch, n = 6, 3000
    channel = np.repeat(np.arange(n_ch), n)
    applied = 0
    for _ in range(100):
        e = rng.normal(size=n_ch * n)
        applied += residual_variance_factor(e, np.ones_like(e), channel)["applied"]
    assert applied <= 4  # one-sided 1 % test: 1 expected in 100
    # AR(1) residuals, rho 0.8: long-run variance (1 + rho) / (1 - rho) = 9
    rho = 0.8
    x = np.zeros((n_ch, n))
    w = rng.normal(size=(n_ch, n)) * math.sqrt(1 - rho**2)
    for k in range(1, n):
        x[:, k] = rho * x[:, k - 1] + w[:, k]
    r = residual_variance_factor(x.ravel(), np.ones(n_ch * n), channel)
    assert r["applied"]
    assert r["factor"] ** 2 == pytest.approx(9.0, rel=0.3)


@pytest.fixture(scope="module")
def sim_flight():
    sc = builtin_scenario("calibration-flight")
    return sc.model_copy(update={"duration": 40.0})


def test_run_eskf_with_matched_noise_changes_nothing(sim_flight):
    ds = simulate(sim_flight)
    r = run_eskf(ds, EskfOptions())
    n = r.extra["noise"]
    assert n["mode"] == "data"
    assert 0.95 <= n["imu"]["accel"]["ratio"] <= 1.15 and 0.95 <= n["imu"]["gyro"]["ratio"] <= 1.15
    assert not n["measurements"]["range"]["changed"]
    assert r.calibration["sigma_scale"] == 1.0
    assert any(e["kind"] == "noise_from_data" for e in r.events)
    assert any(e["kind"] == "sigma_from_residuals" for e in r.events)
    # what was used is in calibration.yaml
    from uwbimu.estimation.outputs import calibration_document

    doc = calibration_document(r)
    assert doc["imu_noise"]["source"] == "log"
    assert doc["imu_noise"]["accel_noise_density"] == pytest.approx(n["imu"]["accel"]["used"])
    assert doc["measurement_noise"]["range"]["source"] == "preset"
    assert doc["measurement_noise"]["range"]["sigma"] == r.config["resolved"]["range_sigma"]
    p = run_eskf(ds, EskfOptions(noise="preset"))
    assert "measurements" not in p.extra["noise"]
    # the same log, the same answer to well within a sigma
    for a, b, s in zip(r.calibration["lever_arm"], p.calibration["lever_arm"], p.calibration["lever_arm_sd"]):
        assert abs(a - b) < 0.2 * s


def test_run_eskf_finds_range_noise_larger_than_declared(sim_flight):
    sc = sim_flight.model_copy(update={"uwb": sim_flight.uwb.model_copy(update={"sigma": 0.15})})
    ds = simulate(sc)
    ds.meta.range_sigma = 0.05  # declared three times too small
    r = run_eskf(ds, EskfOptions())
    m = r.extra["noise"]["measurements"]["range"]
    assert m["changed"] and m["sigma_new"] == pytest.approx(0.15, rel=0.15)
    assert r.config["resolved"]["range_sigma"] == pytest.approx(m["sigma_new"])
    # an explicit option is used as given
    g = run_eskf(ds, EskfOptions(range_sigma=0.05))
    assert g.extra["noise"]["measurements"]["range"]["given"]
    assert g.config["resolved"]["range_sigma"] == 0.05


def _with_correlated_range_errors(ds, sd=0.15, tau=5.0, seed=5):
    """Each anchor's ranges get a slowly varying error (first-order Gauss-Markov, sd ``sd``, ``tau`` s)."""
    rng = np.random.default_rng(seed)
    uwb = ds.uwb.copy()
    for a in uwb["anchor"].unique():
        rows = np.flatnonzero((uwb["anchor"] == a).to_numpy())
        t = uwb["t"].to_numpy(float)[rows]
        e = np.zeros(rows.size)
        for k in range(1, rows.size):
            phi = math.exp(-(t[k] - t[k - 1]) / tau)
            e[k] = phi * e[k - 1] + sd * math.sqrt(1 - phi**2) * rng.normal()
        uwb.loc[uwb.index[rows], "range"] += e
    ds.uwb = uwb
    return ds


def test_unidentified_lever_arm_is_held_when_the_residuals_refute_the_model(sim_flight):
    clean = run_eskf(simulate(sim_flight))
    # a log that agrees with its model keeps its estimate
    assert clean.calibration["sigma_scale"] == 1.0
    assert not any(e["kind"] == "calibration_held" for e in clean.events)
    assert clean.config["resolved"]["modes"]["lever_arm"] == "estimate"
    # translation only (the lever arm not identified) and slowly varying range errors (the model refuted)
    sc = builtin_scenario("translation").model_copy(update={"duration": 40.0})
    bad = run_eskf(_with_correlated_range_errors(simulate(sc)))
    assert bad.calibration["sigma_scale"] > 1.0
    held = [e for e in bad.events if e["kind"] == "calibration_held"]
    assert held and held[0]["blocks"] == ["lever_arm"]
    assert not any(v == "identified" for v in held[0]["first_pass"]["lever_arm_verdict"].values())
    assert bad.config["resolved"]["modes"]["lever_arm"] == "consider"
    # held at its prior with the prior's sd (the data's information is shrunk, never the prior's)
    prior_sd = EskfOptions().lever_arm.prior_sd
    assert np.allclose(bad.calibration["lever_arm_sd"], prior_sd, rtol=0.05)
    err = np.array(bad.calibration["lever_arm"]) - np.array(sc.lever_arm)
    assert np.all(np.abs(err) <= 3 * np.array(bad.calibration["lever_arm_sd"]))
    assert bad.calibration["time_offset_sd"] >= bad.calibration["time_offset_sd_filter"]
