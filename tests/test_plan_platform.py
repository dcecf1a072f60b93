"""Platform models of trajectory design: multirotor (differential flatness, limits) vs handheld."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from uwbimu.design.trajectory.calibration import CalibrationDesignConfig, design_and_write, sim_trajectory_kinematics
from uwbimu.design.trajectory.maneuver import fit_flat_to_bounds, fourier_maneuver
from uwbimu.design.trajectory.platform import MultirotorLimits, check_multirotor, platform_usage
from uwbimu.design.trajectory.pointmass import PointMassPlanConfig, flight_trajectory, plan_point_mass
from uwbimu.models.reference import GRAVITY
from uwbimu.sim.flat import flat_attitude

TINY = dict(
    duration=12.0,
    ramp=1.5,
    design={"n_harmonics": 1, "period": 4.0, "dt": 0.05},
    optimizer={"seed": 0, "n_random": 3, "max_evals": 6},
)
PM = dict(
    beacons=[[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0.5]],
    x0=[1, 1, 1, 0, 0, 0],
    goal=[9, 9, 2],
    goal_velocity=[0, 0, 0],
    tf=8.0,
    n_steps=32,
    box_min=[0, 0, 0.5],
    box_max=[10, 10, 5],
    v_max=3.0,
)


def _flat_maneuver(seed, cfg):
    rng = np.random.default_rng(seed)
    K = 2
    m = fourier_maneuver(rng.standard_normal(4 * K * 2), cfg.start_point() + [0, 0, 0], cfg.duration, cfg.ramp, 4.0, K, flat=True)
    return fit_flat_to_bounds(m, cfg.motion_bounds(), cfg.multirotor)


def test_flat_attitude_rates_are_the_derivative_of_the_angles():
    rng = np.random.default_rng(0)
    n = 7
    a = rng.normal(0, 3, (n, 3))
    j = rng.normal(0, 5, (n, 3))
    yaw, dyaw = rng.uniform(-3, 3, n), rng.normal(0, 1, n)
    e, ed, T = flat_attitude(a, j, yaw, dyaw)
    h = 1e-6
    ep = flat_attitude(a + h * j, j, yaw + h * dyaw, dyaw)[0]
    em = flat_attitude(a - h * j, j, yaw - h * dyaw, dyaw)[0]
    np.testing.assert_allclose(ed, (ep - em) / (2 * h), rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(T, np.linalg.norm(a + [0, 0, GRAVITY], axis=1))
    with pytest.raises(ValueError, match="not upward"):
        flat_attitude(np.array([[0.0, 0.0, -1.5 * GRAVITY]]), np.zeros((1, 3)), [0.0], [0.0])


def test_simulated_imu_along_a_multirotor_plan_agrees_with_the_flat_attitude(tmp_path):
    """Noise-free IMU of the flown designed scenario: specific force along body z only (drag-free
    model: thrust is the only non-gravitational force) and gyro = rate of the attitude."""
    from uwbimu.sim import load_scenario, simulate

    cfg = CalibrationDesignConfig(**TINY)
    design_and_write(cfg, tmp_path)
    d = yaml.safe_load((tmp_path / "designed_scenario.yaml").read_text())
    assert d["trajectory"]["attitude"] == "flat"
    sc = load_scenario(tmp_path / "designed_scenario.yaml")
    sc = sc.model_copy(update={"imu": sc.imu.model_copy(update={"noise_scale": 0.0}), "time_offset": 0.0})
    ds = simulate(sc)
    acc = ds.imu[["ax", "ay", "az"]].to_numpy()
    gyr = ds.imu[["wx", "wy", "wz"]].to_numpy()
    # the body x/y specific force vanishes relative to the thrust (rounding only)
    assert np.max(np.abs(acc[:, :2])) <= 1e-9 * np.max(np.abs(acc[:, 2]))
    assert np.min(acc[:, 2]) > 0
    # and the vehicle does tilt, so this is not trivially level flight
    gt = ds.groundtruth
    q = gt[["qw", "qx", "qy", "qz"]].to_numpy()
    tilt = np.arccos(np.clip(1 - 2 * (q[:, 1] ** 2 + q[:, 2] ** 2), -1, 1))
    assert np.rad2deg(tilt.max()) > 2.0
    # gyro = body rate of the recorded attitude: 2 vec(q_k^* q_k+1) / dt vs the midpoint mean
    from uwbimu.models.quaternion import quat_conjugate as quat_conj, quat_multiply as quat_mul

    dt = float(np.median(np.diff(ds.imu["t"])))
    dq = quat_mul(quat_conj(q[:-1]), q[1:])
    w_fd = 2.0 * dq[:, 1:] * np.sign(dq[:, :1]) / dt
    w_mid = 0.5 * (gyr[:-1] + gyr[1:])
    assert np.max(np.abs(w_fd - w_mid)) <= 1e-3 * np.max(np.abs(gyr)) + 1e-9


def test_fit_flat_to_bounds_respects_every_limit_on_a_fine_grid():
    cfg = CalibrationDesignConfig(duration=12.0, ramp=1.5, bounds={"speed": 2.5, "accel": 6.0},
                                  multirotor={"tilt_max_deg": 20.0, "rate_max": 1.2, "yaw_rate_max": 0.8})
    for seed in range(3):
        m = _flat_maneuver(seed, cfg)
        kin = m.kinematics(np.arange(0.0, m.duration, 0.005))
        u = cfg.usage(kin)
        assert max(u.values()) <= 1.005, u
        # scaled up to a limit, not shrunk to nothing
        assert max(u["speed"], u["accel"], u["box"], u["tilt"], u["rate"], u["thrust_max"]) > 0.95, u
        assert check_multirotor(kin | {"t": np.arange(0.0, m.duration, 0.005)}, cfg.multirotor) == []


def test_designed_multirotor_plan_is_flyable_and_flat(tmp_path):
    cfg = CalibrationDesignConfig(**TINY)
    assert cfg.platform == "multirotor"
    rep = design_and_write(cfg, tmp_path)
    for key in ("designed", "figure8", "figure8_excited"):
        fl = rep[f"{key}_flown"]  # on the splines the simulator flies, 10 ms grid
        assert fl["limit_violations"] == [], (key, fl["limit_violations"])
        assert max(fl["bound_usage"].values()) <= 1.01, (key, fl["bound_usage"])
    # the excited figure-8 uses the yaw-rate budget the naive one leaves
    assert rep["figure8_excited_flown"]["bound_usage"]["yaw_rate"] > 0.95
    assert rep["figure8_flown"]["bound_usage"]["yaw_rate"] < 0.5


def test_check_names_the_violated_limit():
    cfg = CalibrationDesignConfig(duration=12.0, ramp=1.5, bounds={"speed": 3.0, "accel": 8.0})
    m = _flat_maneuver(1, cfg)
    t = np.arange(0.0, m.duration, 0.01)
    kin = m.kinematics(t) | {"t": t}
    u = platform_usage(kin, cfg.multirotor)
    for name in ("tilt", "rate", "yaw_rate", "thrust_max"):
        # a limit set to half the plan's peak is violated, and named with its peak and time
        field = {"tilt": "tilt_max_deg", "rate": "rate_max", "yaw_rate": "yaw_rate_max", "thrust_max": "thrust_max_g"}[name]
        cur = getattr(cfg.multirotor, field)
        new = cur * u[name] * 0.5 if name != "thrust_max" else max(1.0 + 1e-3, cur * u[name] * 0.999)
        lim = MultirotorLimits.model_validate({**cfg.multirotor.model_dump(), field: new})
        v = check_multirotor(kin, lim)
        names = [x.limit for x in v]
        assert name in names, (name, names)
        hit = v[names.index(name)]
        assert hit.usage > 1 and 0.0 <= hit.t <= m.duration and name in hit.message()
    # thrust_min: a plan that ever accelerates downwards needs less than 1 g of thrust
    assert kin["thrust"].min() < 0.99 * GRAVITY
    v = check_multirotor(kin, MultirotorLimits(thrust_min_g=0.995))
    assert [x.limit for x in v] == ["thrust_min"] and "below the limit" in v[0].message()
    # a handheld-style attitude (roll not following the thrust) is named too
    from dataclasses import replace

    hand = replace(m, flat=False, amp=m.amp.copy())
    hand.amp[3, 0] = 0.2
    v = check_multirotor(hand.kinematics(t) | {"t": t}, cfg.multirotor)
    assert "thrust_direction" in [x.limit for x in v]


def test_config_defaults_and_errors():
    assert CalibrationDesignConfig().platform == "multirotor"
    assert PointMassPlanConfig(**PM).platform == "multirotor"
    assert CalibrationDesignConfig(platform="handheld", bounds={"tilt_deg": 20}).motion_bounds().tilt == pytest.approx(np.deg2rad(20))
    with pytest.raises(ValueError, match="multirotor.tilt_max_deg"):
        CalibrationDesignConfig(bounds={"tilt_deg": 20})
    with pytest.raises(ValueError, match="thrust_max_g"):  # a multirotor must be able to hover
        MultirotorLimits(thrust_max_g=0.95)
    with pytest.raises(ValueError):
        CalibrationDesignConfig(platform="plane")


def test_point_mass_multirotor_limits_are_constraints():
    lim = {"tilt_max_deg": 5.0, "rate_max": 1.5}
    hand = plan_point_mass(PointMassPlanConfig(**PM, platform="handheld", objective="none"))
    # h = 0.1 s: the grid the margin (limit_margin) is made for; coarser grids are checked by the CLI
    cfg = PointMassPlanConfig(**{**PM, "n_steps": 80}, multirotor=lim, objective="none")
    res = plan_point_mass(cfg)
    assert res.success
    # the unconstrained (handheld) plan would violate the tilt limit; the multirotor plan does not
    T = hand.u + [0, 0, GRAVITY]
    assert np.rad2deg(np.arccos(T[:, 2] / np.linalg.norm(T, axis=1))).max() > 5.0 * 1.05
    assert max(res.constraint_violation.values()) <= 1e-6 * GRAVITY
    # flown by the simulator with the flat attitude (spline through the nodes): within the limits
    t = np.arange(0.0, cfg.tf, 0.005)
    kin = sim_trajectory_kinematics(flight_trajectory(res, cfg), t) | {"t": t}
    assert check_multirotor(kin, cfg.multirotor) == []
    # and the tilt limit binds (the grid constraint sits at limit_margin of it)
    assert platform_usage(kin, cfg.multirotor)["tilt"] > 0.9 * cfg.limit_margin


def test_cli_default_is_multirotor(tmp_path):
    from typer.testing import CliRunner

    from uwbimu.cli.main import app

    c = tmp_path / "c.yaml"
    c.write_text(yaml.safe_dump({**TINY, "optimizer": {"seed": 0, "n_random": 2, "max_evals": 2}}))
    res = CliRunner().invoke(app, ["plan", "calibration", str(c), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "o" / "design.json").read_text())
    assert data["config"]["platform"] == "multirotor"
    sc = yaml.safe_load((tmp_path / "o" / "designed_scenario.yaml").read_text())
    assert sc["trajectory"]["attitude"] == "flat"
    c.write_text(yaml.safe_dump({**PM, "n_steps": 20, "objective": "none"}))
    res = CliRunner().invoke(app, ["plan", "point-mass", str(c), "--out", str(tmp_path / "p")])
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "p" / "plan.json").read_text())
    assert data["config"]["platform"] == "multirotor" and data["platform"]["flown_limit_violations"] == []
    assert (tmp_path / "p" / "flight_trajectory.csv").is_file()
    # a coarse grid without margin: the flown spline overshoots the tilt limit between the nodes;
    # the files are written, the verb names the limit and exits 3 (check flagged)
    c.write_text(yaml.safe_dump({**PM, "objective": "none", "multirotor": {"tilt_max_deg": 5.0, "rate_max": 1.5}, "limit_margin": 1.0}))
    res = CliRunner().invoke(app, ["plan", "point-mass", str(c), "--out", str(tmp_path / "p2")])
    assert res.exit_code == 3, res.output
    assert "tilt" in res.output and "limit exceeded" in res.output
    data = json.loads((tmp_path / "p2" / "plan.json").read_text())
    assert data["platform"]["flown_limit_violations"][0].startswith("tilt")
    # an infeasible limit is refused with its name
    c.write_text(yaml.safe_dump({**TINY, "multirotor": {"thrust_max_g": 0.8}}))
    res = CliRunner().invoke(app, ["plan", "calibration", str(c), "--out", str(tmp_path / "o3")])
    assert res.exit_code == 2 and "multirotor.thrust_max_g" in res.output
