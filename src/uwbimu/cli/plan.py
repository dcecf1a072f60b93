"""``uwbimu plan``: observability-aware trajectory design."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from uwbimu.cli.conventions import FORCE_HELP

plan_app = typer.Typer(
    help="Observability-aware trajectory design (seed OCP, point-mass planning, calibration manoeuvres).",
    no_args_is_help=True,
)


def _load(path: Path, model, what: str):
    """The config YAML as ``model``; a bad file is a ConfigError naming file, line and field (exit 2)."""
    from uwbimu.io.yamlconfig import load_yaml_model

    return load_yaml_model(path, model, what=what)


SEED_FILES = {"plan.json", "trajectories.csv", "fig7_trajectories.png", "fig8_det_observability.png", "indirect_convergence.png", "controls.png"}
POINTMASS_FILES = {"plan.json", "trajectory.csv", "flight_trajectory.csv", "pointmass.png"}
CALIBRATION_FILES = {
    *(f"{k}_{s}" for k in ("designed", "figure8", "figure8_excited") for s in ("trajectory.csv", "scenario.yaml")),
    "design.json", "calibration_design.png", "proof",
}  # fmt: skip


def _check_out(out: Path, ours: set, force: bool) -> None:
    """The output rule before any work: refuse a file as ``out``, a dataset folder, or a file of ours in it
    that uwbimu did not write (or that changed since) unless ``force``; other files are left alone."""
    from uwbimu.io.atomic import check_output_target, existing_files

    check_output_target(out, existing_files(out, sorted(ours)) if out.is_dir() else sorted(ours), force)


def _record(out: Path, ours: set) -> None:
    """Record the outputs written (so a rerun may replace them while unchanged)."""
    from uwbimu.io.atomic import record_outputs

    record_outputs(out, [out / n for n in sorted(ours)])


@plan_app.command("seed-ocp")
def seed_ocp(
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (plots + plan.json)"),
    config: Optional[Path] = typer.Option(None, "--config", "-c", help="YAML overriding SeedOcpConfig fields"),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
) -> None:
    """Seed 002 sec. XI-XII: 1/det(O)^2 optimal control by PMP and by IPOPT, vs PD."""
    from uwbimu.design.trajectory.plots import save_seed_figures
    from uwbimu.design.trajectory.seed_ocp import SeedOcpConfig, solve_seed_ocp
    from uwbimu.io.atomic import write_csv, write_json

    console = Console()
    cfg = _load(config, SeedOcpConfig, "seed OCP config") if config else SeedOcpConfig()
    _check_out(out, SEED_FILES, force)
    with console.status("solving PD, indirect (PMP) and direct (IPOPT)..."):
        res = solve_seed_ocp(cfg)
    summary = res.summary()
    write_json(out / "plan.json", summary)
    import numpy as np
    import pandas as pd

    from uwbimu.design.trajectory.seed_ocp import det_observability

    rows = {"t": cfg.t}
    for m in (res.pd, res.indirect, res.direct, res.fixed_final):
        if m is None:
            continue
        for i, c in enumerate(("px", "py", "pz", "vx", "vy", "vz")):
            rows[f"{m.name}_{c}"] = m.x[:, i]
        rows[f"{m.name}_det"] = det_observability(m.x[:, :3], np.asarray(cfg.beacons))
    write_csv(out / "trajectories.csv", pd.DataFrame(rows), float_format="%.9g")
    figs = save_seed_figures(res, out)
    tab = Table(title="Seed OCP: J = int 1/det(O)^2 + |p-p_d|^2/2 + |u|^2/2 dt", collapse_padding=True)
    for col in ("method", "J", "1/det^2", "track", "control", "det mean", "ms", "iter", "max|H_u|"):
        tab.add_column(escape(col), justify="right", no_wrap=col in ("method", "J"))
    short = {"pd": "PD", "indirect": "indirect", "indirect_continuous": "ind. ODE", "direct": "direct", "direct_fixed_final": "fixed-end"}
    for m in (res.pd, res.indirect, res.indirect_continuous, res.direct, res.fixed_final):
        if m is None:
            continue
        c = m.cost
        tab.add_row(
            short[m.name], f"{c['total']:.4f}", f"{c['det_term']:.3f}", f"{c['track_term']:.2f}", f"{c['control_term']:.2f}",
            f"{c['det_mean']:.3f}", f"{1e3 * m.solve_time_s:.0f}", str(m.iterations), f"{m.hu_max:.0e}",
        )  # fmt: skip
    console.print(tab)
    ag = res.agreement()
    console.print(
        f"indirect vs direct: |dJ|/J = {ag['cost_rel_diff']:.2e}, max|du| = {ag['u_max_abs_diff']:.2e} m/s^2, "
        f"max|dp| = {ag['p_max_abs_diff']:.2e} m"
    )
    if res.indirect_continuous is not None:
        console.print(
            "continuous-costate (RK4) indirect vs direct grid optimum: max|du| = "
            f"{summary['u_max_abs_diff_continuous_vs_direct']:.2e} m/s^2 (O(h^2) discretisation difference)"
        )
    _record(out, SEED_FILES)
    console.print(escape(f"wrote {out / 'plan.json'}, {out / 'trajectories.csv'} and {len(figs)} figures"))
    if not (res.indirect.converged and res.direct.converged):
        from uwbimu.errors import EstimationError

        raise EstimationError("a method did not converge (see plan.json)")


@plan_app.command("point-mass")
def point_mass(
    config: Path = typer.Argument(..., help="PointMassPlanConfig YAML (see examples/plan/pointmass.yaml)"),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder"),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
) -> None:
    """Observability-aware point-mass path (log-det / E / A-optimal information, IPOPT) vs minimum effort."""
    import numpy as np
    import pandas as pd

    from uwbimu.design.trajectory.plots import save_pointmass_figure
    from uwbimu.design.trajectory.pointmass import PointMassPlanConfig, flight_trajectory, plan_point_mass
    from uwbimu.io.atomic import write_csv, write_json

    console = Console()
    cfg = _load(config, PointMassPlanConfig, "point-mass plan config")
    _check_out(out, POINTMASS_FILES, force)
    with console.status("solving (IPOPT)..."):
        base = plan_point_mass(cfg.model_copy(update={"objective": "none"}))
        res = plan_point_mass(cfg)
    tab = Table(title=f"point-mass plan, objective {cfg.objective} ({cfg.info_model} information at {cfg.info_at})")
    for col in ("plan", "status", "solve [s]", "log det", "min eig", "trace inv", "effort", "max violation"):
        tab.add_column(escape(col), justify="right")
    for name, r in (("min effort", base), (cfg.objective, res)):
        m = r.metrics
        tab.add_row(name, r.status, f"{r.solve_time_s:.2f}", f"{m['logdet']:.3f}", f"{m['min_eig']:.4g}", f"{m['trace_inv']:.4g}",
                    f"{m['control_effort']:.3f}", f"{max(r.constraint_violation.values(), default=0.0):.1e}")
    console.print(tab)
    cols = {"t": res.t}
    for i, c in enumerate(("px", "py", "pz", "vx", "vy", "vz")):
        cols[c] = res.x[:, i]
    for i, c in enumerate(("ux", "uy", "uz")):
        cols[c] = np.append(res.u[:, i], np.nan)
    write_csv(out / "trajectory.csv", pd.DataFrame(cols), float_format="%.9g")
    # the plan as the simulator flies it (trajectory file; multirotor: scenario `attitude: flat`)
    from uwbimu.design.trajectory.calibration import sim_trajectory_kinematics
    from uwbimu.design.trajectory.platform import check_multirotor
    from uwbimu.sim.trajfile import write_trajectory_file

    write_trajectory_file(out / "flight_trajectory.csv", res.t, res.x[:, :3], yaw=np.full(len(res.t), cfg.yaw))
    violations = []
    if cfg.platform == "multirotor":
        tf = np.arange(0.0, cfg.tf, min(0.005, cfg.h / 4))
        violations = [v.message() for v in check_multirotor(sim_trajectory_kinematics(flight_trajectory(res, cfg), tf), cfg.multirotor)]
    summary = {
        name: {"success": r.success, "status": r.status, "solve_time_s": r.solve_time_s, "metrics": r.metrics,
               "constraint_violation": r.constraint_violation, "information": r.info.tolist()}
        for name, r in (("min_effort", base), ("plan", res))
    }  # fmt: skip
    summary["platform"] = {"platform": cfg.platform, "flown_limit_violations": violations}
    summary["config"] = cfg.model_dump(mode="json")
    write_json(out / "plan.json", summary)
    save_pointmass_figure(base, res, cfg, out / "pointmass.png")
    _record(out, POINTMASS_FILES)
    console.print(escape(f"wrote {out / 'plan.json'}, {out / 'trajectory.csv'}, {out / 'flight_trajectory.csv'}, "
                         f"{out / 'pointmass.png'}"))
    if cfg.platform == "multirotor":
        console.print("platform multirotor: fly flight_trajectory.csv with `trajectory: {type: file, path: ..., attitude: flat}`")
    if not res.success:
        from uwbimu.errors import EstimationError

        raise EstimationError(f"IPOPT did not converge: {res.status}")
    _report_violations(console, violations)


def _report_violations(console: Console, violations: list) -> None:
    """Name every multirotor limit the flown trajectory exceeds; exit 3 (check flagged) if any."""
    if violations:
        for v in violations:
            console.print(f"[red]limit exceeded[/red] (multirotor, flown trajectory): {escape(v)}")
        raise typer.Exit(code=3)


@plan_app.command("calibration")
def calibration(
    config: Path = typer.Argument(..., help="Calibration design YAML (see docs/trajectory_design.md)"),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder"),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
) -> None:
    """Design a calibration manoeuvre (lever arm + time offset, E-optimal) for the 19-state model."""
    from uwbimu.design.trajectory.calibration import CalibrationDesignConfig, design_and_write
    from uwbimu.errors import ConfigError, InputError, UsageError

    console = Console()
    cfg = _load(config, CalibrationDesignConfig, "calibration design config")
    _check_out(out, CALIBRATION_FILES, force)
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    with Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"), TimeElapsedColumn(), console=console) as prog:
        task = prog.add_task("optimising manoeuvre", total=cfg.optimizer.total_evals)

        def cb(n_evals: int) -> None:
            prog.update(task, completed=min(n_evals, cfg.optimizer.total_evals))

        try:
            report = design_and_write(cfg, out, progress=cb, config_path=config)
        except (ConfigError, InputError, UsageError) as exc:  # typed by the library; name the file
            raise type(exc)(f"{config}: {exc}", hint=exc.hint) from None
    _record(out, CALIBRATION_FILES)
    tab = Table(title=f"Calibration manoeuvre ({cfg.platform}): predicted 1-sigma (linearised ESKF covariance)")
    tab.add_column("trajectory")
    for col in ("lever x [mm]", "lever y [mm]", "lever z [mm]", "t_d [ms]", "lambda_min (scaled info)"):
        tab.add_column(escape(col), justify="right")
    for name in ("designed", "figure8", "figure8_excited"):
        r = report[f"{name}_flown"]  # evaluated on the splines the simulator flies
        s = r["sigma_lever_arm_m"]
        tab.add_row(name, *(f"{1e3 * v:.2f}" for v in s), f"{1e3 * r['sigma_time_offset_s']:.3f}", f"{r['lambda_min_scaled']:.3g}")
    console.print(tab)
    for key in ("figure8", "figure8_excited"):
        r = report[f"predicted_ratio_{key}_over_designed"]
        console.print(
            f"predicted sigma ratio {key} / designed: lever arm (norm) {r['lever_arm_sigma_norm']:.2f}x, "
            f"time offset {r['time_offset_sigma']:.2f}x"
        )
    console.print(f"optimised in {report['design_time_s']:.1f} s ({report['n_evals']} evaluations)")
    console.print(escape(f"wrote {len(report['files'])} files into {out}; fly with: uwbimu simulate "
                         f"{out / 'designed_scenario.yaml'}"))
    _report_violations(console, [f"{name}: {v}" for name in ("designed", "figure8", "figure8_excited") for v in report[f"{name}_flown"].get("limit_violations", [])])


def register(app: typer.Typer) -> None:
    app.add_typer(plan_app, name="plan")
