"""``uwbimu demo``: the main job on built-in defaults.

Simulates the default calibration flight (room with 8 anchors, 60 s),
validates it exactly as a user's dataset would be validated, prints the
structural observability verdict of the set-up, runs the ESKF with online
lever-arm and time-offset calibration, compares the calibration with the
truth, computes the per-window observability timeline and writes the HTML
report.  Everything lands in one output folder.
"""

from __future__ import annotations

from typing import Optional

import time
from pathlib import Path

import numpy as np
import typer

from uwbimu.cli.conventions import FORCE_HELP
from rich.console import Console
from rich.markup import escape
from rich.table import Table

#: A file the demo leaves in its output folder so that a rerun may replace the
#: folder; any other non-empty folder is a user's and is never overwritten.
DEMO_MARKER = ".uwbimu-demo"


def _check_out(out: Path, force: bool) -> None:
    """Refuse, before any work, an --out holding files uwbimu did not write or that changed since (unless
    --force): the output rule of every verb (a previous demo's folder is replaced)."""
    from uwbimu.io.atomic import check_output_target

    check_output_target(out, force=force, replace=True)


def _summary_table(ds, seconds: float) -> Table:
    t = Table(title="Simulated calibration flight", show_header=True)
    t.add_column("item")
    t.add_column("value", justify="right")
    imu_t = ds.imu_t
    t.add_row("duration", f"{imu_t[-1] - imu_t[0]:.1f} s")
    t.add_row("IMU samples", f"{len(ds.imu)} ({(len(imu_t) - 1) / (imu_t[-1] - imu_t[0]):.0f} Hz)")
    t.add_row("UWB ranges", f"{len(ds.uwb)} to {ds.uwb['anchor'].nunique()} anchors")
    truth = ds.meta.truth
    if truth is not None and truth.lever_arm is not None:
        t.add_row("true lever arm", "[" + ", ".join(f"{v:+.3f}" for v in truth.lever_arm) + "] m")
    if truth is not None and truth.time_offset is not None:
        t.add_row("true time offset", f"{1e3 * truth.time_offset:+.1f} ms")
    t.add_row("simulation time", f"{seconds:.2f} s")
    return t


def _structural_table(verdict: dict, delay: dict) -> Table:
    t = Table(title="Observability of this set-up (Lie-derivative rank test, seed 001 section 3)")
    t.add_column("question")
    t.add_column("answer")
    t.add_row(
        "state without t_d locally weakly observable?",
        f"{'yes' if verdict['observable'] else 'NO'}: rank {verdict['rank']} of {verdict['dimension']} "
        f"(Lie order {verdict['lie_order']})",
    )
    conds = verdict.get("conditions") or {}
    if conds:
        t.add_row("Theorem 2 conditions", ", ".join(f"{k}={'yes' if v else 'no'}" for k, v in conds.items()
                                                    if isinstance(v, bool)))
    dconds = delay.get("conditions") or {}
    t.add_row(
        "time offset identifiable (Theorem 1)?",
        f"{'yes' if delay['identifiable'] else 'NO'} ("
        + ", ".join(f"{k}={'yes' if v else 'no'}" for k, v in dconds.items() if isinstance(v, bool))
        + ")",
    )
    names = [d["name"] for d in verdict.get("unobservable_directions", [])]
    if names:
        t.add_row("unobservable directions", escape("; ".join(names)))
    return t


def _truth_comparison(result, ds) -> Table:
    cal = result.calibration
    truth = ds.meta.truth
    t = Table(title="Online calibration: estimate ± 1σ against the truth")
    for c, j in (("quantity", "left"), ("estimate ± 1σ", "right"), ("truth", "right"),
                 ("error", "right"), ("|error| / σ", "right")):
        t.add_column(c, justify=j)
    la = np.asarray(cal["lever_arm"], float)
    la_sd = np.asarray(cal["lever_arm_sd"], float)
    la_true = np.asarray(truth.lever_arm, float)
    for i, ax in enumerate("xyz"):
        err = la[i] - la_true[i]
        t.add_row(f"lever arm {ax}", f"{100 * la[i]:+.2f} ± {100 * la_sd[i]:.2f} cm", f"{100 * la_true[i]:+.2f} cm",
                  f"{100 * err:+.2f} cm", f"{abs(err) / la_sd[i]:.2f}")
    td, td_sd, td_true = float(cal["time_offset"]), float(cal["time_offset_sd"]), float(truth.time_offset)
    t.add_row("time offset", f"{1e3 * td:+.2f} ± {1e3 * td_sd:.2f} ms", f"{1e3 * td_true:+.2f} ms",
              f"{1e3 * (td - td_true):+.2f} ms", f"{abs(td - td_true) / td_sd:.2f}")
    return t


def run_demo(out: Path, console: Console, force: bool = False, duration: float | None = None) -> dict:
    """Run the whole demo into ``out``; returns the key figures (for tests).

    Everything is written into a temporary folder that replaces ``out`` at the end (the
    output rule): an interrupted demo leaves the previous ``out`` as it was.
    """
    from uwbimu.cli.estimate import NAN_DOCUMENTED
    from uwbimu.io.atomic import output_folder

    _check_out(out, force)
    with output_folder(out, force=True, replace=True,
                       finite=NAN_DOCUMENTED + ("observability.csv", "repeatability.json")) as work:
        (work / DEMO_MARKER).write_text("written by uwbimu demo; the folder is replaced on the next run\n")
        figures = _run_demo_into(work, console, duration, final=out)
    figures["report"] = str(out / Path(figures["report"]).relative_to(work))
    console.print(f"[bold green]report:[/bold green] {escape(figures['report'])}")
    return figures


def _run_demo_into(out: Path, console: Console, duration: float | None, final: Path | None = None) -> dict:
    """The demo's steps, writing into ``out`` (a staging folder that becomes ``final``; paths are shown as
    they will be once the demo ends)."""
    from uwbimu.cli.check import print_check
    from uwbimu.cli.compile_notice import ensure_compiled
    from uwbimu.cli.estimate import print_run_warnings, print_truth_comparison, run_with_progress, truth_comparison
    from uwbimu.estimation import EskfOptions, compute_metrics, write_outputs
    from uwbimu.estimation import run_eskf
    from uwbimu.eval.repeatability import repeatability
    from uwbimu.eval.report import write_report
    from uwbimu.io.atomic import write_json
    from uwbimu.io.atomic import write_csv
    from uwbimu.io.check import check_dataset
    from uwbimu.io.dataset import write_dataset
    from uwbimu.io.loader import load_dataset
    from uwbimu.observability.delay import delay_verdict
    from uwbimu.observability.structural import config_for_dataset, format_verdict, structural_verdict
    from uwbimu.observability.window import WindowOptions, trajectory_from_result, window_observability
    from uwbimu.sim import builtin_scenario, simulate

    figures: dict = {}

    # 1. simulate the default calibration flight and write it as a dataset
    t0 = time.perf_counter()
    scenario = builtin_scenario("calibration-flight")
    if duration is not None:
        scenario = scenario.updated(duration=duration)
    with console.status("simulating the calibration flight"):
        sim = simulate(scenario)
        data_dir = write_dataset(sim, out / "dataset")
    console.print(_summary_table(sim, time.perf_counter() - t0))

    # 2. validate it exactly as a user's dataset
    ds = load_dataset(data_dir)
    check = check_dataset(ds)
    print_check(console, ds, check, path=(final if final is not None else out) / "dataset")
    figures["flags"] = [f.anchor for f in check.flags]

    # 3. structural observability of this set-up
    with console.status("Lie-derivative rank test"):
        config = config_for_dataset(ds, lie_order=3, random_points=3)
        verdict = structural_verdict(config)
        delay = delay_verdict(config)
    console.print(_structural_table(verdict, delay))
    console.print(escape(format_verdict(verdict)))
    figures["observable"] = bool(verdict["observable"])
    figures["td_identifiable"] = bool(delay["identifiable"])

    # 4. estimate: ESKF with online lever arm and time offset (no ground truth used)
    est_dir = out / "estimate"
    compiled = ensure_compiled(console)
    figures["compile_s"] = compiled.seconds
    # what uwbimu estimate runs on a log: the filter and its forward-backward smoothing
    result = run_with_progress(ds, EskfOptions(smoother="forward_backward"), console)
    write_outputs(result, ds, est_dir)
    metrics = compute_metrics(result, ds)
    console.print(_truth_comparison(result, ds))
    print_truth_comparison(console, truth_comparison(result, ds, metrics))
    console.print(f"ESKF run time {result.runtime_s:.2f} s"
                  + (f" (the kernels were compiled once before it, {compiled.seconds:.0f} s)" if compiled.cold else ""))
    print_run_warnings(console, result)
    figures.update(metrics)
    figures["calibration"] = result.calibration

    # 5. observability timeline along the estimated trajectory
    figures["compile_s"] += ensure_compiled(console, "window").seconds
    with console.status("per-window observability"):
        obs, _info = window_observability(ds, trajectory_from_result(result), WindowOptions(window=5.0))
        write_csv(est_dir / "observability.csv", obs)
    figures["observability_windows"] = len(obs)

    # 6. repeatability: calibrate 4 windows of the flight and test their spread against the
    #    sigma the filter predicts (the "is my calibration good?" question on one log)
    with console.status("repeatability over 4 windows"):
        rep = repeatability(ds, 4, lambda w: run_eskf(w, EskfOptions(smoother="forward_backward")))
        write_json(est_dir / "repeatability.json", rep)
    figures["repeatability"] = {k: v.get("verdict") for k, v in rep.get("parameters", {}).items()}

    # 7. the report
    report = write_report(est_dir, dataset=ds)
    figures["report"] = str(report)
    return figures


def register(app: typer.Typer) -> None:
    @app.command("demo")
    def demo(
        out: Optional[Path] = typer.Option(
            None, "--out", "-o",
            help="Output folder (replaced if a previous demo wrote it); default: a new temporary folder, printed"),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        duration: float = typer.Option(None, "--duration", help="Flight duration [s] (default: the scenario's 60 s)"),
    ) -> None:
        """Simulate a calibration flight, validate it, analyse, estimate and write the report."""
        console = Console()
        if out is None:
            # never litter the current folder: a fresh folder the user is told about
            import tempfile

            out = Path(tempfile.mkdtemp(prefix="uwbimu-demo-"))
            console.print(escape(f"writing the demo into {out}/ (choose another folder with --out)"))
        t0 = time.perf_counter()
        figures = run_demo(out, console, force=force, duration=duration)
        compile_s = figures.get("compile_s") or 0.0
        console.print(escape(f"demo finished in {time.perf_counter() - t0:.1f} s"
                             + (f" ({compile_s:.0f} s of it the one-time kernel compilation)" if compile_s else "")
                             + f"; everything is in {out}/"))
