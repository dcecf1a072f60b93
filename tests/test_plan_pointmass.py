"""General observability-aware point-mass planner (CasADi + IPOPT)."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.design.trajectory.pointmass import (
    Obstacle,
    PointMassPlanConfig,
    information_matrix,
    initial_guess,
    plan_point_mass,
)

BASE = dict(
    beacons=[[0, 0, 0], [10, 0, 0], [0, 10, 0], [10, 10, 0.5]],
    platform="handheld",  # the information planner alone; the multirotor limits: tests/test_plan_platform.py
    x0=[1, 1, 1, 0, 0, 0],
    goal=[9, 9, 2],
    goal_velocity=[0, 0, 0],
    tf=10.0,
    n_steps=40,
    box_min=[0, 0, 0.5],
    box_max=[10, 10, 5],
    obstacles=[
        {"kind": "sphere", "center": [5, 5, 1.5], "radius": 1.5},
        {"kind": "box", "center": [3, 7, 2], "half_size": [1, 1, 2]},
    ],
    v_max=2.0,
    a_max=2.0,
)


def test_information_matches_per_range_sum():
    """I_0 = sum over ranges of (dh/dX_0)^T (dh/dX_0) / sigma^2 with dh/dX_0 = [e^T, t e^T]."""
    cfg = PointMassPlanConfig(**BASE)
    x, _ = initial_guess(cfg)
    rng = np.random.default_rng(0)
    x = x + rng.normal(0, 0.3, x.shape)
    info = information_matrix(x, cfg)
    ref = np.diag([1 / cfg.prior_sigma_p**2] * 3 + [1 / cfg.prior_sigma_v**2] * 3)
    w = np.ones(cfg.n_steps + 1)
    w[[0, -1]] = 0.5
    for k, t in enumerate(cfg.t):
        for b in cfg.beacons:
            d = x[k, :3] - b
            e = d / np.linalg.norm(d)
            J = np.concatenate([e, t * e])
            ref += w[k] * cfg.h * cfg.rate_hz / cfg.range_sigma**2 * np.outer(J, J)
    np.testing.assert_allclose(info, ref, rtol=1e-12)
    # final-state information: same determinant (det Phi = 1)
    cfg_f = cfg.model_copy(update={"info_at": "final"})
    assert np.linalg.slogdet(information_matrix(x, cfg_f))[1] == pytest.approx(np.linalg.slogdet(info)[1])


def test_box_obstacle_surrogate_contains_the_box():
    ob = Obstacle(kind="box", center=[1, 2, 3], half_size=[0.5, 1.0, 2.0])
    corners = np.array([[1 + sx * 0.5, 2 + sy * 1.0, 3 + sz * 2.0] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    assert np.all(ob.clearance(corners) <= 1e-12)  # every point of the box is infeasible
    assert np.all(ob.clearance(np.array([[1 + 0.5 * 1.16, 2, 3], [1, 2 + 1.16, 3]])) > 0)  # <= 15 % beyond a face: free
    with pytest.raises(ValueError):
        Obstacle(kind="box", center=[0, 0, 0])


@pytest.mark.parametrize("objective", ["logdet", "min_eig", "trace_inv"])
def test_planner_improves_its_criterion_under_constraints(objective):
    base = plan_point_mass(PointMassPlanConfig(objective="none", **BASE))
    cfg = PointMassPlanConfig(objective=objective, w_info=2.0, **BASE)
    r = plan_point_mass(cfg)
    assert base.success and r.success, r.status
    assert max(r.constraint_violation.values()) < 1e-6
    np.testing.assert_allclose(r.x[-1, :3], BASE["goal"], atol=1e-6)
    np.testing.assert_allclose(r.x[-1, 3:], 0.0, atol=1e-6)
    if objective == "trace_inv":
        assert r.metrics["trace_inv"] < 0.99 * base.metrics["trace_inv"]
    elif objective == "min_eig":
        assert r.metrics["min_eig"] > 1.05 * base.metrics["min_eig"]
    else:
        assert r.metrics["logdet"] > base.metrics["logdet"] + 0.05
    # more information costs control effort (the baseline is the minimum-effort path)
    assert r.metrics["control_effort"] >= base.metrics["control_effort"] - 1e-9


def test_position_information_and_tolerance_goal():
    cfg = PointMassPlanConfig(
        **{**BASE, "goal_velocity": None, "obstacles": []}, objective="logdet", info_model="position", goal_tolerance=0.5
    )
    r = plan_point_mass(cfg)
    assert r.success and r.info.shape == (3, 3)
    assert np.max(np.abs(r.x[-1, :3] - np.asarray(BASE["goal"]))) <= 0.5 + 1e-6


def test_config_validation():
    with pytest.raises(ValueError):
        PointMassPlanConfig(**{**BASE, "box_min": [0, 0, 6]})
    with pytest.raises(ValueError):
        PointMassPlanConfig(**{**BASE, "beacons": [[0, 0]]})


def test_cli_point_mass(tmp_path):
    import json

    import yaml
    from typer.testing import CliRunner

    from uwbimu.cli.main import app

    c = tmp_path / "pm.yaml"
    c.write_text(yaml.safe_dump({**BASE, "n_steps": 25, "objective": "trace_inv"}))
    res = CliRunner().invoke(app, ["plan", "point-mass", str(c), "--out", str(tmp_path / "o")])
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "o" / "plan.json").read_text())
    assert data["plan"]["metrics"]["trace_inv"] < data["min_effort"]["metrics"]["trace_inv"]
    assert (tmp_path / "o" / "pointmass.png").stat().st_size > 1000
    c.write_text("beacons: [[0, 0, 0]]\n")
    res = CliRunner().invoke(app, ["plan", "point-mass", str(c), "--out", str(tmp_path / "o2")])
    assert res.exit_code == 2 and "x0" in res.output
