"""Seed 002 sec. XI-XII optimal control: det(O), adjoint, indirect vs direct, PD, CLI."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uwbimu.design.trajectory.seed_ocp import (
    SeedOcpConfig,
    _cost_total,
    det_observability,
    det_observability_grad,
    hamiltonian_gradient,
    pd_rollout,
    rollout,
    seed_cost,
    solve_direct,
    solve_indirect,
)

COARSE = dict(n_steps=58)  # h = 40 ms: same problem, coarser grid, fast


def test_det_matches_seed_closed_form():
    """det(a) = -(1 - p^T P^-1 1) det P (seed) and det(O) = det(a)/(r1 r2 r3)."""
    cfg = SeedOcpConfig()
    P = np.asarray(cfg.beacons)
    rng = np.random.default_rng(1)
    p = rng.uniform(-5, 25, size=(50, 3))
    det_a = -(1.0 - p @ np.linalg.solve(P, np.ones(3))) * np.linalg.det(P)
    r = np.linalg.norm(p[:, None, :] - P[None], axis=2)
    np.testing.assert_allclose(det_observability(p, P), det_a / r.prod(axis=1), rtol=1e-10)
    # start of the seed problem: both beacon-plane side and magnitude
    assert det_observability(np.array([8.0, 9, 11]), P) == pytest.approx(2250.0 / np.sqrt(206 * 221 * 146), rel=1e-12)


def test_det_gradient_finite_difference():
    cfg = SeedOcpConfig()
    P = np.asarray(cfg.beacons)
    rng = np.random.default_rng(2)
    for p in rng.uniform(2, 20, size=(10, 3)):
        D, dD = det_observability_grad(p, P)
        fd = np.array([(det_observability(p + e, P) - det_observability(p - e, P)) / 2e-6 for e in 1e-6 * np.eye(3)])
        np.testing.assert_allclose(dD, fd, rtol=1e-6, atol=1e-9)
        assert D == pytest.approx(det_observability(p, P))


@pytest.mark.parametrize("track_velocity", [False, True])
def test_costate_sweep_is_exact_gradient(track_velocity):
    """h * H_u from the backward costate sweep = dJ_h/du (finite differences)."""
    cfg = SeedOcpConfig(track_velocity=track_velocity, **COARSE)
    _, u = pd_rollout(cfg)
    rng = np.random.default_rng(3)
    u = u + rng.normal(0, 0.5, u.shape)
    x = rollout(cfg.x0, u, cfg.h)
    _, Hu = hamiltonian_gradient(x, u, cfg)
    for _ in range(3):
        d = rng.normal(size=u.shape)
        eps = 1e-6
        jp = _cost_total(rollout(cfg.x0, u + eps * d, cfg.h), u + eps * d, cfg)
        jm = _cost_total(rollout(cfg.x0, u - eps * d, cfg.h), u - eps * d, cfg)
        assert (jp - jm) / (2 * eps) == pytest.approx(cfg.h * np.sum(Hu * d), rel=1e-6)


def test_rollout_is_exact_double_integrator():
    u = np.tile([1.0, -2.0, 0.5], (10, 1))
    x = rollout(np.array([1.0, 2, 3, 0.1, 0, -0.1]), u, 0.1)
    t = 1.0
    np.testing.assert_allclose(x[-1, :3], [1 + 0.1 * t + 0.5 * t * t, 2 - t * t, 3 - 0.1 * t + 0.25 * t * t])
    np.testing.assert_allclose(x[-1, 3:], [0.1 + t, -2 * t, -0.1 + 0.5 * t])


def test_pd_baseline_settles_at_goal():
    cfg = SeedOcpConfig()
    x, u = pd_rollout(cfg)
    # critically damped, 2 % settling in t_f: within 2.5 % of the 6 m step, slow at the end
    assert np.all(np.abs(x[-1, :3] - cfg.goal) < 0.025 * 6.0)
    assert np.linalg.norm(x[-1, 3:]) < 0.5
    c = seed_cost(x, u, cfg)
    assert c["total"] == pytest.approx(c["det_term"] + c["track_term"] + c["control_term"])


def test_indirect_and_direct_agree_and_beat_pd():
    cfg = SeedOcpConfig(hu_tol=1e-7, **COARSE)
    xpd, upd = pd_rollout(cfg)
    ind = solve_indirect(cfg)
    dire = solve_direct(cfg)
    assert ind.converged and dire.converged
    # the seed's stopping rule: |H_u| decreased below threshold from the PD start
    h = ind.history["hu_max"]
    assert h[0] > 1.0 and h[-1] < cfg.hu_tol
    assert np.all(np.diff(ind.history["cost"]) <= 1e-12)  # monotone descent
    # same optimum
    assert ind.cost["total"] == pytest.approx(dire.cost["total"], rel=1e-9)
    np.testing.assert_allclose(ind.u, dire.u, atol=1e-5)
    assert dire.hu_max < 1e-6  # direct solution satisfies the PMP condition H_u = 0
    pd_cost = seed_cost(xpd, upd, cfg)
    assert dire.cost["total"] < pd_cost["total"]
    # seed fig. 8: the optimal trajectory keeps det(O) higher on average than the PD
    assert dire.cost["det_mean"] > pd_cost["det_mean"]


def test_indirect_limited_iterations_reports_not_converged():
    cfg = SeedOcpConfig(max_iter=5, **COARSE)
    ind = solve_indirect(cfg)
    assert not ind.converged and ind.iterations == 5
    assert ind.history["hu_max"][-1] < ind.history["hu_max"][0]


def test_config_rejects_bad_beacons():
    with pytest.raises(ValueError):
        SeedOcpConfig(beacons=[[0, 0, 0], [1, 0, 0]])


def test_cli_seed_ocp(tmp_path):
    from typer.testing import CliRunner

    from uwbimu.cli.main import app

    cfgfile = tmp_path / "c.yaml"
    cfgfile.write_text("n_steps: 58\n")
    res = CliRunner().invoke(app, ["plan", "seed-ocp", "--out", str(tmp_path / "out"), "--config", str(cfgfile)])
    assert res.exit_code == 0, res.output
    data = json.loads((tmp_path / "out" / "plan.json").read_text())
    for k in ("cost_pd", "cost_indirect", "cost_direct", "det_mean_pd", "det_mean_opt", "solve_time_direct_s"):
        assert np.isfinite(data[k])
    assert data["cost_indirect"] == pytest.approx(data["cost_direct"], rel=1e-6)
    assert (tmp_path / "out" / "fig8_det_observability.png").stat().st_size > 1000
    bad = tmp_path / "bad.yaml"
    bad.write_text("n_stepz: 10\n")
    res = CliRunner().invoke(app, ["plan", "seed-ocp", "--out", str(tmp_path / "o2"), "--config", str(bad)])
    assert res.exit_code == 2 and "n_stepz" in res.output


def test_example_configs_validate():
    from pathlib import Path

    import yaml

    from uwbimu.design.trajectory.calibration import CalibrationDesignConfig
    from uwbimu.design.trajectory.pointmass import PointMassPlanConfig

    ex = Path(__file__).resolve().parents[1] / "examples" / "plan"
    cfg = SeedOcpConfig.model_validate(yaml.safe_load((ex / "seed_ocp.yaml").read_text()))
    assert cfg == SeedOcpConfig(kp=cfg.kp, kd=cfg.kd) and cfg.kp == pytest.approx(SeedOcpConfig().kp, rel=1e-5)
    PointMassPlanConfig.model_validate(yaml.safe_load((ex / "pointmass.yaml").read_text()))
    assert CalibrationDesignConfig.model_validate(yaml.safe_load((ex / "calibration.yaml").read_text())) == CalibrationDesignConfig(
        name="room8-calibration"
    )


def test_fixed_final_state_variant_trades_observability_for_rest():
    """Seed: fixing the final state (at rest) is possible but costs observability."""
    cfg = SeedOcpConfig(**COARSE)
    free = solve_direct(cfg)
    ff = solve_direct(cfg, fixed_final=True)
    assert ff.converged
    np.testing.assert_allclose(ff.x[-1], list(cfg.goal) + [0, 0, 0], atol=1e-8)
    assert ff.cost["total"] > free.cost["total"]
    assert ff.cost["det_mean"] < free.cost["det_mean"]


def test_continuous_costate_method_matches_direct_to_discretisation_order():
    """The seed's literal method (costate ODE by RK4) reaches the grid optimum up to O(h^2)."""
    from uwbimu.design.trajectory.seed_ocp import continuous_cost, continuous_costate, solve_indirect_continuous

    cfg = SeedOcpConfig(**COARSE)
    x, u = pd_rollout(cfg)
    rng = np.random.default_rng(5)
    u = u + rng.normal(0, 0.5, u.shape)
    x = rollout(cfg.x0, u, cfg.h)
    _, Hu = continuous_costate(x, u, cfg)
    d = rng.normal(size=u.shape)
    eps = 1e-6
    fd = (continuous_cost(rollout(cfg.x0, u + eps * d, cfg.h), u + eps * d, cfg)
          - continuous_cost(rollout(cfg.x0, u - eps * d, cfg.h), u - eps * d, cfg)) / (2 * eps)  # fmt: skip
    assert fd == pytest.approx(cfg.h * np.sum(Hu * d), rel=1e-5)  # H_u is the gradient of the ODE-integrated cost
    diffs = []
    for n in (29, 58):
        c = SeedOcpConfig(n_steps=n)
        ic = solve_indirect_continuous(c)
        assert ic.converged and ic.hu_max < c.hu_tol
        diffs.append(np.abs(ic.u - solve_direct(c).u).max())
    assert diffs[1] < 1e-3 and 3.0 < diffs[0] / diffs[1] < 5.0  # second order in h


def test_cli_refuses_a_folder_with_other_files(tmp_path):
    """The output rule: a file of the verb's name that uwbimu did not write is refused (exit 4, nothing written)."""
    from typer.testing import CliRunner

    from uwbimu.cli.main import app

    out = tmp_path / "o"
    out.mkdir()
    (out / "plan.json").write_text("mine")
    (out / "design.json").write_text("mine too")
    for args, name in ((["plan", "seed-ocp", "--out", str(out)], "plan.json"),
                       (["plan", "calibration", "--out", str(out), str(tmp_path / "c.yaml")], "design.json")):
        if args[1] == "calibration":
            (tmp_path / "c.yaml").write_text("duration: 12.0\nramp: 1.5\n")
        res = CliRunner().invoke(app, args)
        assert res.exit_code == 4 and name in res.output, res.output
    assert sorted(p.name for p in out.iterdir()) == ["design.json", "plan.json"]
    assert (out / "plan.json").read_text() == "mine"
