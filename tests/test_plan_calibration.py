"""Calibration manoeuvre design: kinematics, Jacobians, predictor, bounds, files, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from uwbimu.design.trajectory.calibration import (
    CalibrationDesignConfig,
    design_and_write,
    design_calibration,
    naive_figure8,
)
from uwbimu.design.trajectory.maneuver import bound_usage, envelope, fit_to_bounds, fourier_maneuver
from uwbimu.design.trajectory.predictor import _cov_run, range_jacobian
from uwbimu.models import reference as ref
from uwbimu.models import state as S

TINY = dict(
    duration=12.0,
    ramp=1.5,
    design={"n_harmonics": 1, "period": 4.0, "dt": 0.05},
    optimizer={"seed": 0, "n_random": 4, "max_evals": 10},
)


def _random_maneuver(seed=0, K=2, T=12.0):
    rng = np.random.default_rng(seed)
    cfg = CalibrationDesignConfig(duration=T, ramp=1.5)
    m = fourier_maneuver(rng.standard_normal(6 * K * 2), cfg.start_point() + [0, 0, 0], T, 1.5, 4.0, K)
    return fit_to_bounds(m, cfg.motion_bounds()), cfg


LEVER = np.array([0.12, -0.08, 0.14])
P0_DIAG = np.diag([0.3] * 3 + [0.5] * 3 + [0.1] * 3 + [0.05] * 3 + [0.01] * 3 + [0.3] * 3 + [0.03]) ** 2


def _short_run(seed: int, dt: float, t_end: float, first: int, every: int):
    """Truth on a grid over [0, t_end] [s] of a random manoeuvre, range steps (round-robin anchors), their Jacobians."""
    m, cfg = _random_maneuver(seed, T=6.0)
    tg = np.arange(0.0, t_end + 0.5 * dt, dt)
    kin = m.kinematics(tg)
    A = cfg.anchor_array()
    idx = np.arange(first, len(tg), every)
    km = {k: v[idx] for k, v in kin.items()}
    return tg, kin, idx, range_jacobian(km, A[np.arange(len(idx)) % len(A)], LEVER)


def test_envelope_and_channel_derivatives():
    T = 10.0
    w, w1, w2 = envelope(np.array([0.0, T]), T, 2.0)
    np.testing.assert_allclose([w, w1, w2], 0.0, atol=1e-15)
    m, _ = _random_maneuver()
    t = np.linspace(0.3, 11.7, 40)
    eps = 1e-5
    f, f1, f2 = m.channels(t)
    fp, f1p, _ = m.channels(t + eps)
    fm, f1m, _ = m.channels(t - eps)
    np.testing.assert_allclose(f1, (fp - fm) / (2 * eps), atol=1e-6)
    np.testing.assert_allclose(f2, (f1p - f1m) / (2 * eps), atol=1e-5)
    # at rest, level, at the centre at both ends
    k0 = m.kinematics(np.array([0.0, m.duration]))
    np.testing.assert_allclose(k0["v"], 0.0, atol=1e-12)
    np.testing.assert_allclose(k0["w"], 0.0, atol=1e-12)
    np.testing.assert_allclose(k0["p"], [m.center[:3]] * 2, atol=1e-12)


def test_kinematics_pinned_to_reference_imu_and_quaternion_rate():
    m, _ = _random_maneuver(1)
    t = np.linspace(1.0, 11.0, 15)
    kin = m.kinematics(t)
    for i in range(len(t)):
        a_m, w_m = ref.imu_measurement(kin["q"][i], kin["a"][i], kin["w"][i], np.zeros(3), np.zeros(3))
        np.testing.assert_allclose(kin["f"][i], a_m, atol=1e-12)
    # body rate consistent with q' = 0.5 Xi(q) w (reference)
    eps = 1e-6
    qp, qm = m.kinematics(t + eps)["q"], m.kinematics(t - eps)["q"]
    for i in range(len(t)):
        qdot = 0.5 * ref.quaternion_rate_matrix(kin["q"][i]) @ kin["w"][i]
        np.testing.assert_allclose((qp[i] - qm[i]) / (2 * eps), qdot, atol=1e-6)


def test_range_jacobian_matches_reference_model():
    """Rows of the predictor's H = derivatives of reference.range_measurement (boxplus) and of t_d."""
    m, _ = _random_maneuver(2)
    t = np.array([3.0, 6.5, 9.0])
    kin = m.kinematics(t)
    lever = np.array([0.12, -0.08, 0.14])
    anchors = np.array([[0.2, 0.3, 0.35], [9.7, 0.4, 0.25], [4.9, 7.85, 2.7]])
    H = range_jacobian(kin, anchors, lever)
    eps = 1e-6
    for i in range(len(t)):
        x = S.make_state(p=kin["p"][i], v=kin["v"][i], q=kin["q"][i], p_IU=lever)
        for j in range(18):
            dx = np.zeros(19)
            dx[j] = eps
            hp = ref.range_measurement(S.boxplus(x, dx), anchors[i])
            hm = ref.range_measurement(S.boxplus(x, -dx), anchors[i])
            assert (hp - hm) / (2 * eps) == pytest.approx(H[i, j], abs=1e-6)
        # t_d: the range observes the state at IMU time t + t_d
        kp, km = m.kinematics(t[i : i + 1] + eps), m.kinematics(t[i : i + 1] - eps)
        xp = S.make_state(p=kp["p"][0], q=kp["q"][0], p_IU=lever)
        xm = S.make_state(p=km["p"][0], q=km["q"][0], p_IU=lever)
        dh = (ref.range_measurement(xp, anchors[i]) - ref.range_measurement(xm, anchors[i])) / (2 * eps)
        assert dh == pytest.approx(H[i, 18], abs=1e-6)


def test_covariance_recursion_equals_batch_information_without_process_noise():
    """With no process noise the KF posterior is (P0^-1 + sum (H Phi)^T (H Phi) / s^2)^-1, Phi from the
    reference dynamics (RK4 on boxplus-perturbed states), so F is pinned to the reference model."""
    dt = 0.01
    tg, kin, idx, H = _short_run(3, dt, 3.0, 5, 5)
    lever = LEVER
    P0 = P0_DIAG
    sigma = 0.05
    P = _cov_run(P0, kin["R"], kin["f"], kin["w"], dt, 0.0, 0.0, 0.0, 0.0, idx.astype(np.int64), H, sigma**2)
    # transition of the error state by finite differences of the reference propagation
    u = np.column_stack([kin["f"], kin["w"]])
    x0 = S.make_state(p=kin["p"][0], v=kin["v"][0], q=kin["q"][0], p_IU=lever)
    nom = ref.integrate_imu(x0, tg, u)
    eps = 1e-6
    Phi = np.zeros((len(idx), 19, 19))
    for j in range(15):
        d = np.zeros(19)
        d[j] = eps
        xp = ref.integrate_imu(S.boxplus(x0, d), tg, u)
        for n, k in enumerate(idx):
            Phi[n, :, j] = S.boxminus(xp[k], nom[k]) / eps
    for n in range(len(idx)):
        Phi[n, 15:, 15:] = np.eye(4)
    info = np.linalg.inv(P0)
    for n in range(len(idx)):
        r = H[n] @ Phi[n]
        info += np.outer(r, r) / sigma**2
    # compare the calibration block (what the design uses) and the position block,
    # the batch covariance (initial state) mapped to the last range instant = end of the run
    assert idx[-1] == len(tg) - 1
    Pb = Phi[-1] @ np.linalg.inv(info) @ Phi[-1].T
    for blk in (slice(15, 19), slice(0, 3)):
        np.testing.assert_allclose(np.sqrt(np.diag(P[blk, blk])), np.sqrt(np.diag(Pb[blk, blk])), rtol=0.02)


def test_covariance_recursion_is_the_estimators_transition():
    """_cov_run's prediction is Phi P Phi^T + Q_d with Phi the estimator's dense
    models.kernels.error_transition (19x19), updates as the scalar Kalman update."""
    from uwbimu.models.kernels import error_transition

    dt = 0.02
    tg, kin, idx, H = _short_run(5, dt, 2.0, 3, 4)
    L = np.random.default_rng(7).standard_normal((19, 19)) * 0.1
    P0 = L @ L.T + P0_DIAG  # a full (correlated) prior
    qa, qg, qba, qbg, s2 = 2e-4, 3e-6, 1e-7, 1e-9, 0.05**2
    P = _cov_run(P0, kin["R"], kin["f"], kin["w"], dt, qa, qg, qba, qbg, idx.astype(np.int64), H, s2)
    Pe = P0.copy()
    Phi = np.zeros((19, 19))
    Qd = np.zeros((19, 19))
    for blk, q in ((S.EV, qa), (S.ETH, qg), (S.EBA, qba), (S.EBG, qbg)):
        Qd[blk, blk] = q * dt * np.eye(3)
    m_i = 0
    for k in range(len(tg)):
        while m_i < len(idx) and idx[m_i] == k:
            h = H[m_i]
            Ph = Pe @ h
            Pe = Pe - np.outer(Ph, Ph) / (h @ Ph + s2)
            m_i += 1
        if k == len(tg) - 1:
            break
        x = S.make_state(p=kin["p"][k], v=kin["v"][k], q=kin["q"][k], p_IU=LEVER)
        error_transition(x, np.concatenate([kin["f"][k], kin["w"][k]]), dt, Phi)
        Pe = Phi @ Pe @ Phi.T + Qd
        Pe = 0.5 * (Pe + Pe.T)
    np.testing.assert_allclose(P, Pe, rtol=1e-9, atol=1e-15)


def test_fit_to_bounds_holds_on_a_fine_grid():
    for seed in range(3):
        m, cfg = _random_maneuver(seed)
        u = bound_usage(m.kinematics(np.arange(0.0, m.duration, 0.005)), cfg.motion_bounds())
        assert max(u.values()) <= 1.005, u
        assert max(u["speed"], u["accel"], u["box"]) > 0.95  # grown to the bounds


def test_figure8_respects_bounds_and_ends_at_rest():
    cfg = CalibrationDesignConfig(duration=30.0)
    m = naive_figure8(cfg)
    t = np.arange(0.0, 30.0 + 1e-9, 0.005)
    kin = m.kinematics(t)
    u = bound_usage(kin, cfg.motion_bounds())
    assert max(u.values()) <= 1.005
    k = m.kinematics(np.array([0.0, 30.0]))
    np.testing.assert_allclose(k["v"], 0.0, atol=1e-12)
    np.testing.assert_allclose(k["w"], 0.0, atol=1e-12)
    # "same bounds": the baseline is not a slow one -- its speed or acceleration reaches
    # the bound, and in the cruise, not in the start/stop ramps
    assert max(u["speed"], u["accel"]) > 0.98, u
    cruise = (t > cfg.ramp) & (t < cfg.duration - cfg.ramp)
    sp = np.linalg.norm(kin["v"], axis=1)
    assert sp[cruise].max() > 0.98 * cfg.bounds.speed
    # it runs along the lemniscate itself (time warp), also in the ramps
    x = (kin["p"][:, 0] - m.center[0]) / m.amp[0, 0]
    y = (kin["p"][:, 1] - m.center[1]) / m.amp[1, 0]
    np.testing.assert_allclose((y / 2) ** 2, x**2 * (1 - x**2), atol=1e-12)


def test_warped_channel_derivatives():
    cfg = CalibrationDesignConfig(duration=30.0)
    m = naive_figure8(cfg)
    t = np.concatenate([np.linspace(0.05, 1.95, 20), np.linspace(2.1, 27.9, 20), np.linspace(28.05, 29.95, 20)])
    eps = 1e-5
    f, f1, f2 = m.channels(t)
    fp, f1p, _ = m.channels(t + eps)
    fm, f1m, _ = m.channels(t - eps)
    np.testing.assert_allclose(f1, (fp - fm) / (2 * eps), atol=1e-6)
    np.testing.assert_allclose(f2, (f1p - f1m) / (2 * eps), atol=1e-5)
    # the clock is continuous across the ramp ends and runs T - ramp in all
    from uwbimu.design.trajectory.maneuver import warped_clock

    s, s1, _ = warped_clock(np.array([0.0, 2.0 - 1e-9, 2.0 + 1e-9, 28.0 - 1e-9, 28.0 + 1e-9, 30.0]), 30.0, 2.0)
    np.testing.assert_allclose(s, [0.0, 1.0, 1.0, 27.0, 27.0, 28.0], atol=1e-8)
    np.testing.assert_allclose(s1, [0.0, 1.0, 1.0, 1.0, 1.0, 0.0], atol=1e-8)


def test_design_beats_figure8_and_writes_flyable_files(tmp_path):
    from uwbimu.sim import load_scenario, read_trajectory_file, simulate

    cfg = CalibrationDesignConfig(**TINY)
    rep = design_and_write(cfg, tmp_path)
    d, f8 = rep["designed_flown"], rep["figure8_flown"]
    # E-optimality: the designed manoeuvre carries more information on the worst calibration direction
    assert d["lambda_min_scaled"] > 1.5 * f8["lambda_min_scaled"]
    assert max(d["bound_usage"].values()) <= 1.01 and max(f8["bound_usage"].values()) <= 1.01
    # analytic and flown (spline through the written rows) predictions agree
    assert d["sigma_time_offset_s"] == pytest.approx(rep["designed"]["sigma_time_offset_s"], rel=0.02)
    t, p, e = read_trajectory_file(tmp_path / "designed_trajectory.csv")
    assert t[-1] == pytest.approx(cfg.duration) and p.shape[1] == 3
    sc = load_scenario(tmp_path / "designed_scenario.yaml")
    assert sc.duration == cfg.duration and list(sc.lever_arm) == cfg.truth.lever_arm
    ds = simulate(sc)
    assert len(ds.uwb) > 0.9 * cfg.duration * cfg.sensors.uwb_rate_hz
    assert (tmp_path / "calibration_design.png").stat().st_size > 1000
    data = json.loads((tmp_path / "design.json").read_text())
    o = cfg.optimizer  # the random shapes once, then max_evals - n_random per Powell start
    assert data["n_evals"] == o.n_random + o.starts * (o.max_evals - o.n_random)


def test_design_is_seeded():
    cfg = CalibrationDesignConfig(**{**TINY, "optimizer": {"seed": 3, "n_random": 3, "max_evals": 3}})
    a, b = design_calibration(cfg), design_calibration(cfg)
    np.testing.assert_array_equal(a["theta"], b["theta"])


def test_more_powell_starts_are_never_worse():
    """Several starts: the first search is the one-start search (same seeded shapes, same
    budget), so the best over all of them is at least as good; the budget is per start."""
    opt = {"seed": 1, "n_random": 4, "max_evals": 12}
    one = design_calibration(CalibrationDesignConfig(**{**TINY, "optimizer": {**opt, "starts": 1}}))
    three = design_calibration(CalibrationDesignConfig(**{**TINY, "optimizer": {**opt, "starts": 3}}))
    assert one["n_evals"] == 12 and three["n_evals"] == 4 + 3 * 8
    assert three["metrics_designed"]["lambda_min_scaled"] >= one["metrics_designed"]["lambda_min_scaled"]


def test_config_errors():
    with pytest.raises(ValueError):
        CalibrationDesignConfig(box_min=[1, 1, 3], box_max=[9, 7, 2.4])
    with pytest.raises(ValueError):
        CalibrationDesignConfig(anchors="nowhere")
    with pytest.raises(ValueError):
        CalibrationDesignConfig(duration=3.0)


def test_cli_calibration(tmp_path):
    from typer.testing import CliRunner

    from uwbimu.cli.main import app

    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump({**TINY, "optimizer": {"seed": 0, "n_random": 2, "max_evals": 2}}))
    res = CliRunner().invoke(app, ["plan", "calibration", str(c), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "designed_scenario.yaml").is_file()
    bad = tmp_path / "bad.yaml"
    bad.write_text("bounds: {speed: -1}\n")
    res = CliRunner().invoke(app, ["plan", "calibration", str(bad), "--out", str(tmp_path / "o2")])
    assert res.exit_code == 2 and "bounds.speed" in res.output


def test_range_jacobian_agrees_with_observability_engine():
    """Cross-check with uwbimu.observability.window (written independently)."""
    window = pytest.importorskip("uwbimu.observability.window")
    m, _ = _random_maneuver(4)
    kin = m.kinematics(np.linspace(1.0, 11.0, 20))
    lever = np.array([0.12, -0.08, 0.14])
    anchors = np.random.default_rng(0).uniform(0, 10, (20, 3))
    _, H_obs = window.range_jacobians(kin["p"], kin["v"], kin["R"], kin["w"], lever, anchors)
    np.testing.assert_allclose(range_jacobian(kin, anchors, lever), H_obs, atol=1e-12)


def test_custom_anchor_list_goes_into_the_scenario():
    from uwbimu.design.trajectory.calibration import scenario_dict
    from uwbimu.sim import validate_scenario

    anchors = [{"id": i, "position": p} for i, p in enumerate([[0, 0, 0.3], [10, 0, 2.7], [10, 8, 0.4], [0, 8, 2.8]])]
    cfg = CalibrationDesignConfig(anchors=anchors)
    assert cfg.anchor_ids() == ["0", "1", "2", "3"] and cfg.anchor_array().shape == (4, 3)
    d = scenario_dict(cfg, "x.csv", "n", "d")
    d["trajectory"] = {"type": "hover"}  # the file does not exist here; check the rest
    sc = validate_scenario(d)
    np.testing.assert_allclose(sc.anchor_positions(), cfg.anchor_array())
