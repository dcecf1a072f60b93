"""Sensor models: vectorised kernels pinned to the reference, noise statistics, UWB effects, seeds."""

import numpy as np
import pytest

from uwbimu.models import reference as M
from uwbimu.models import state as S
from uwbimu.models.imu import BMI088
from uwbimu.models.quaternion import quat_normalize
from uwbimu.sim import Scenario, builtin_scenario, simulate, simulate_full
from uwbimu.sim.ranging import schedule
from uwbimu.sim.sensors import antenna_positions, imu_measurements, ranges


def with_uwb(sc: Scenario, **uwb) -> Scenario:
    return sc.updated(uwb=uwb)


def ideal_imu(sc: Scenario) -> Scenario:
    return sc.updated(imu={"noise": "ideal", "accel_bias": (0, 0, 0), "gyro_bias": (0, 0, 0)})


# --- pinned to the reference model ------------------------------------------------------


def test_vectorised_imu_equals_reference():
    rng = np.random.default_rng(0)
    n = 50
    q = quat_normalize(rng.normal(size=(n, 4)))
    acc, w, ba, bg, na, ng = (rng.normal(size=(n, 3)) for _ in range(6))
    a_m, w_m = imu_measurements(q, acc, w, ba, bg, na, ng)
    for k in range(n):
        ra, rw = M.imu_measurement(q[k], acc[k], w[k], ba[k], bg[k], na[k], ng[k])
        np.testing.assert_allclose(a_m[k], ra, atol=1e-12)
        np.testing.assert_allclose(w_m[k], rw, atol=1e-12)


def test_vectorised_range_equals_reference():
    rng = np.random.default_rng(1)
    n = 50
    p, anchors = rng.normal(size=(n, 3)), 5 * rng.normal(size=(n, 3))
    q = quat_normalize(rng.normal(size=(n, 4)))
    lever = np.array([0.12, -0.08, 0.14])
    r = ranges(p, q, lever, anchors)
    ant = antenna_positions(p, q, lever)
    for k in range(n):
        x = S.make_state(p=p[k], q=q[k], p_IU=lever)
        np.testing.assert_allclose(ant[k], M.antenna_position(x), atol=1e-12)
        assert r[k] == pytest.approx(M.range_measurement(x, anchors[k]), abs=1e-12)


def test_simulated_ranges_use_the_reference_relation():
    res = simulate_full(with_uwb(builtin_scenario("two-tags"), sigma=0.0))
    ds = res.dataset
    A = ds.anchor_positions()
    tags = ds.meta.truth.tags
    p, q = res.trajectory.pose(res.range_t_nominal)
    for k in range(0, len(ds.uwb), 97):
        row = ds.uwb.iloc[k]
        x = S.make_state(p=p[k], q=q[k], p_IU=tags[row["tag"]])
        assert row["range"] == pytest.approx(M.range_measurement(x, A[row["anchor"]]), abs=1e-12)
        assert res.range_true[k] == row["range"]


# --- IMU noise ---------------------------------------------------------------------------


def test_imu_noise_and_bias_statistics_match_densities():
    sc = builtin_scenario("calibration-flight")
    res = simulate_full(sc)
    clean = simulate(ideal_imu(sc))
    ds = res.dataset
    dt = 1.0 / ds.meta.imu_rate_hz
    sig = BMI088.discrete_sigmas(dt)
    u, u0 = ds.imu_u, clean.imu_u
    n_a = u[:, :3] - u0[:, :3] - res.accel_bias
    n_g = u[:, 3:] - u0[:, 3:] - res.gyro_bias
    # 36,003 draws each: the sample sd is within ~0.4 % (1 sigma) of the truth
    assert n_a.std() == pytest.approx(sig["accel"], rel=0.02)
    assert n_g.std() == pytest.approx(sig["gyro"], rel=0.02)
    assert abs(n_a.mean()) < 4 * sig["accel"] / np.sqrt(n_a.size)
    db_a, db_g = np.diff(res.accel_bias, axis=0), np.diff(res.gyro_bias, axis=0)
    assert db_a.std() == pytest.approx(sig["accel_bias_step"], rel=0.02)
    assert db_g.std() == pytest.approx(sig["gyro_bias_step"], rel=0.02)
    # initial biases drawn from sigma0 and reported
    np.testing.assert_allclose(ds.meta.extra["imu_bias"]["accel_initial"], res.accel_bias[0])
    np.testing.assert_allclose(ds.meta.extra["imu_bias"]["gyro_final"], res.gyro_bias[-1])
    assert np.abs(res.accel_bias[0]).max() < 5 * BMI088.accel_bias_sigma0


def test_initial_bias_given_and_noise_scale():
    sc = builtin_scenario("hover")
    res = simulate_full(sc.updated(imu={"accel_bias": (0.1, -0.2, 0.3), "gyro_bias": (0.01, 0.0, -0.01), "noise_scale": 0.0}))
    np.testing.assert_allclose(res.accel_bias, np.tile([0.1, -0.2, 0.3], (len(res.accel_bias), 1)))
    clean = simulate(ideal_imu(sc))
    np.testing.assert_allclose(res.dataset.imu_u - clean.imu_u, np.c_[res.accel_bias, res.gyro_bias], atol=1e-12)


def test_saturation_clips_and_counts():
    sc = builtin_scenario("calibration-flight")
    ds = simulate(sc.updated(imu={"gyro_limit": 0.5, "accel_limit": 10.0}))
    u = ds.imu_u
    assert np.abs(u[:, 3:]).max() <= 0.5 and np.abs(u[:, :3]).max() <= 10.0
    sat = ds.meta.extra["imu_saturation"]
    assert sat["gyro_clipped_values"] == int((np.abs(u[:, 3:]) == 0.5).sum()) > 0
    assert sat["accel_clipped_samples"] > 0


# --- UWB effects -------------------------------------------------------------------------


def test_range_noise_statistics_and_anchor_bias():
    sc = with_uwb(builtin_scenario("calibration-flight"), sigma=0.05, anchor_bias={"A3": 0.25})
    res = simulate_full(sc)
    ds = res.dataset
    e = ds.uwb["range"].to_numpy() - res.range_true
    a3 = (ds.uwb["anchor"] == "A3").to_numpy()
    assert e[~a3].std() == pytest.approx(0.05, rel=0.06)
    assert e[a3].mean() == pytest.approx(0.25, abs=4 * 0.05 / np.sqrt(a3.sum()))
    assert abs(e[~a3].mean()) < 4 * 0.05 / np.sqrt((~a3).sum())
    assert ds.meta.truth.anchor_bias["A3"] == 0.25 and ds.meta.truth.anchor_bias["A0"] == 0.0


def test_nlos_is_positive_only_with_the_given_rate_and_mean():
    sc = with_uwb(builtin_scenario("calibration-flight"), sigma=0.0, nlos_prob=0.3, nlos_scale=0.4)
    res = simulate_full(sc)
    e = res.dataset.uwb["range"].to_numpy() - res.range_true
    assert (e >= 0).all()
    np.testing.assert_array_equal(e > 0, res.range_nlos)
    n = len(e)
    assert res.range_nlos.mean() == pytest.approx(0.3, abs=4 * np.sqrt(0.3 * 0.7 / n))
    assert e[res.range_nlos].mean() == pytest.approx(0.4, rel=0.1)
    assert res.dataset.meta.extra["uwb_counts"]["nlos"] == res.range_nlos.sum()


def test_nlos_bursts_concentrate_on_their_window_and_anchor():
    res = simulate_full(with_uwb(builtin_scenario("nlos"), sigma=0.0))
    uwb = res.dataset.uwb
    t = res.range_t_nominal
    in_burst = ((t >= 15) & (t < 25) & (uwb["anchor"] == "A1")).to_numpy()
    assert res.range_nlos[in_burst].mean() > 0.6
    assert res.range_nlos[~in_burst].mean() < 0.06


def test_dropouts_max_range_and_outages_are_counted():
    sc = with_uwb(
        builtin_scenario("calibration-flight"), dropout_prob=0.2, max_range=7.0, outages=[[20.0, 30.0, "A2"], [40.0, 41.0, None]]
    )
    res = simulate_full(sc)
    c = res.dataset.meta.extra["uwb_counts"]
    assert c["emitted"] == len(res.dataset.uwb)
    assert c["scheduled"] == c["emitted"] + c["dropped_outage"] + c["dropped_max_range"] + c["dropped_dropout"] + c["dropped_nonpositive"]
    assert (res.range_true <= 7.0).all() and c["dropped_max_range"] > 0
    assert c["dropped_dropout"] / (c["scheduled"] - c["dropped_outage"] - c["dropped_max_range"]) == pytest.approx(0.2, abs=0.03)
    t, a = res.range_t_nominal, res.dataset.uwb["anchor"].to_numpy()
    assert not ((t >= 20) & (t < 30) & (a == "A2")).any()
    assert not ((t >= 40) & (t < 41)).any()
    # round robin 50 Hz over 8 anchors: 6.25 Hz per anchor -> 62-63 A2 ranges in 10 s, 50 slots in 1 s
    assert 62 + 50 <= c["dropped_outage"] <= 63 + 50


def test_jitter_moves_stamps_not_ranges():
    res = simulate_full(with_uwb(builtin_scenario("calibration-flight"), sigma=0.0, jitter_sd=0.002))
    uwb = res.dataset.uwb
    d = uwb["t"].to_numpy() - res.range_t_nominal
    assert d.std() == pytest.approx(0.002, rel=0.08)
    assert np.all(np.diff(uwb["t"].to_numpy()) >= 0)  # logged in stamp order
    p, q = res.trajectory.pose(res.range_t_nominal)
    lever = res.dataset.meta.truth.lever_arm
    A = res.dataset.anchor_array(uwb["anchor"])
    np.testing.assert_allclose(uwb["range"].to_numpy(), ranges(p, q, lever, A), atol=1e-12)


def test_schedules():
    sc = builtin_scenario("calibration-flight")
    t, ai, ti = schedule(sc, 0.0, 1.0)
    np.testing.assert_allclose(t, np.arange(51) / 50.0)
    np.testing.assert_array_equal(ai, np.arange(51) % 8)
    assert (ti == 0).all()
    t, ai, ti = schedule(sc.updated(uwb={"schedule": "all"}), 0.0, 1.0)
    assert len(t) == 51 * 8 and set(np.bincount(ai)) == {51}
    t, ai, ti = schedule(builtin_scenario("two-tags"), 0.0, 1.0)
    assert list(zip(ai[:4], ti[:4])) == [(0, 0), (0, 1), (1, 0), (1, 1)]


def test_uwb_window_is_covered_by_the_imu_stream():
    for t_d in (0.03, -0.04):
        ds = simulate(builtin_scenario("hover").updated(time_offset=t_d, duration=10.0))
        imu_time_of_ranges = ds.uwb["t"].to_numpy() + t_d
        assert imu_time_of_ranges.min() >= ds.imu_t[0] - 1e-12
        assert imu_time_of_ranges.max() <= ds.imu_t[-1] + 1e-12
        assert ds.uwb["t"].min() >= 0.0


# --- seeds -------------------------------------------------------------------------------


def test_same_seeds_give_identical_output_and_streams_are_separate():
    sc = builtin_scenario("random").updated(duration=20.0, uwb={"nlos_prob": 0.1, "dropout_prob": 0.05, "jitter_sd": 0.001})
    a, b = simulate(sc), simulate(sc)
    for name in ("imu", "uwb", "anchors", "groundtruth"):
        assert getattr(a, name).equals(getattr(b, name)), name
    assert a.meta == b.meta

    c = simulate(sc.updated(seeds={"noise": 99}))
    assert c.groundtruth.equals(a.groundtruth)  # truth untouched
    assert not np.allclose(c.imu_u, a.imu_u)  # noise changed
    assert not np.allclose(c.uwb["range"].to_numpy()[:100], a.uwb["range"].to_numpy()[:100])

    d = simulate(sc.updated(seeds={"truth": 99}))
    assert not np.allclose(d.groundtruth[["px", "py", "pz"]].to_numpy(), a.groundtruth[["px", "py", "pz"]].to_numpy())

    e = simulate(sc.updated(seeds={"init": 99}))
    # model_copy(update=...) is not validated by pydantic; simulate re-validates it
    f = simulate(sc.model_copy(update={"uwb": {"sigma": 0.0}}))
    assert f.meta.range_sigma is None and f.groundtruth.equals(a.groundtruth)
    assert e.imu.equals(a.imu) and e.uwb.equals(a.uwb) and e.meta.extra["seeds"]["init"] == 99


def test_meta_carries_truth_and_sensor_settings():
    ds = simulate(builtin_scenario("calibration-flight"))
    m = ds.meta
    assert m.truth.lever_arm == [0.12, -0.08, 0.14] and m.truth.time_offset == 0.03
    assert m.truth.tags == {"tag0": [0.12, -0.08, 0.14]}
    assert m.imu_noise == BMI088 and m.imu_rate_hz == 200.0 and m.range_sigma == 0.05
    assert [t.name for t in m.tags] == ["tag0"]
    assert m.extra["seeds"] == {"truth": 0, "noise": 1, "init": 2}
    assert Scenario.model_validate(m.extra["scenario"]) == builtin_scenario("calibration-flight")
    assert len(ds.imu) == 12001 and len(ds.uwb) == 2999 and list(ds.uwb.columns) == ["t", "anchor", "range"]
