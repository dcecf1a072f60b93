"""``uwbimu report`` and ``uwbimu repeatability``: the one-file HTML report and the window test."""

from __future__ import annotations

import math

from pathlib import Path
from typing import Optional

import typer

from uwbimu.cli.conventions import FORCE_HELP
from uwbimu.cli.dataset_options import SMOOTH_HELP
from uwbimu.cli.dataset_options import with_load_options

#: Files of an estimator output folder the report reads; a folder with none of them is refused.
REPORT_INPUTS = ("calibration.yaml", "trajectory.csv", "residuals.csv")


def register(app: typer.Typer) -> None:
    @app.command("report")
    @with_load_options
    def report(
        out: Path = typer.Argument(..., help="Estimator output folder (calibration.yaml, trajectory.csv, residuals.csv)."),
        dataset: Optional[Path] = typer.Option(None, "--dataset", "-d",
                                               help="Dataset folder: adds anchors, documented/true calibration, ground truth."),
        folder: Optional[Path] = typer.Option(None, "--out", "-o",
                                              help="Output folder for report.html (default: the estimator output folder)."),
        html: Optional[Path] = typer.Option(None, "--html", help="Write the report to this HTML file instead."),
        output: Optional[Path] = typer.Option(None, "--output", hidden=True, help="Old name of --html."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        load_options=None,
    ) -> None:
        """Write one self-contained HTML calibration report (plots embedded, opens offline)."""
        from rich.console import Console
        from rich.markup import escape

        from uwbimu.cli.dataset_options import load, print_load_warnings
        from uwbimu.eval.report import write_report
        from uwbimu.errors import UsageError
        from uwbimu.io.atomic import check_output_target, is_dataset_folder, output_folder

        console = Console()
        if not out.is_dir():
            raise UsageError(f"{out}: estimator output folder not found",
                             hint="give the folder `uwbimu estimate` or `uwbimu calibrate` wrote (-o)")
        if not any((out / n).is_file() for n in REPORT_INPUTS):
            # e.g. a dataset folder: --force would not help (there is nothing to report on)
            raise UsageError(f"{out} holds no estimator output ({', '.join(REPORT_INPUTS)})",
                             hint=(f"run `uwbimu estimate {out} -o OUT` first, then `uwbimu report OUT --dataset {out}`"
                                   if is_dataset_folder(out) else "give the folder `uwbimu estimate` wrote (-o)"))
        if html is not None and output is not None:
            raise UsageError("give --html FILE once (--output is its old name)")
        html = html if html is not None else output
        if html is not None and folder is not None:
            raise UsageError("give --out FOLDER or --html FILE, not both")
        target = html if html is not None else (folder if folder is not None else out) / "report.html"
        folder = target.parent if str(target.parent) else Path(".")
        protect = [dataset] if dataset is not None else []
        # Never over a file uwbimu did not write, never into (or over) a dataset.
        check_output_target(folder, [target.name], force, protect)
        ds = None
        if dataset is not None:
            ds = load(dataset, load_options)
            print_load_warnings(console, ds)
        with output_folder(folder, force, protect, names=[target.name], finite=False) as tmp:
            write_report(out, dataset=ds, path=tmp / target.name)  # EvalInputError: an InputError (exit 1)
        console.print(escape(f"wrote {target}"))

    @app.command("repeatability")
    @with_load_options
    def repeatability_cmd(
        dataset: Path = typer.Argument(..., help="Dataset folder."),
        out: Path = typer.Option(..., "--out", "-o", help="Folder for repeatability.json (e.g. the estimator output folder)."),
        windows: int = typer.Option(4, "--windows", "-k", help="Number of windows (at least 2)."),
        method: str = typer.Option("eskf", "--method", help="Estimator: eskf (the filter) or batch (uwbimu calibrate, GTSAM)."),
        config: Optional[Path] = typer.Option(None, "--config", help="Estimator options YAML."),
        preset: Optional[str] = typer.Option(
            None, "--preset", help="Shipped ESKF options: default, real, isas-walk (with --method batch: the "
                                   "initialising ESKF's)."),
        level: float = typer.Option(0.01, "--level", help="Significance level of the chi-square test."),
        workers: int = typer.Option(1, "--workers", help="Windows calibrated in parallel (process pool, at least 1)."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        smooth: Optional[bool] = typer.Option(None, "--smooth/--no-smooth", help="With --method eskf: " + SMOOTH_HELP),
        load_options=None,
    ) -> None:
        """Calibrate K windows of a log and compare the spread of lever arm / time offset with the filter's sigma."""
        from rich.console import Console
        from rich.progress import Progress
        from rich.markup import escape
        from rich.table import Table

        from uwbimu.cli.conventions import fit_table
        from uwbimu.cli.dataset_options import (apply_dataset_properties, estimator_options, load,
                                                offline_smoothing, print_load_warnings)
        from uwbimu.eval.repeatability import repeatability
        from uwbimu.io.atomic import check_output_target, output_folder, write_json
        from uwbimu.models.blocks import calibration_components

        from uwbimu.errors import UsageError

        console = Console()
        if windows < 2:
            raise UsageError(f"--windows must be at least 2, got {windows}")
        if workers < 1:
            raise UsageError(f"--workers must be at least 1, got {workers}")
        if not 0 < level < 1:
            raise UsageError(f"--level must be in (0, 1), got {level:g}")
        check_output_target(out, ["repeatability.json"], force, protect=[dataset])
        if method not in ("eskf", "batch"):
            raise UsageError(f"--method {method}: expected eskf or batch")
        if method == "batch":
            from uwbimu.calibration import CalibrationOptions

            try:
                opts = CalibrationOptions.from_yaml(config) if config is not None else CalibrationOptions()
            except (OSError, ValueError) as exc:
                raise UsageError(f"--config {config}: {exc}") from None
            if preset is not None:  # the initialising ESKF's options (the batch options come from --config)
                opts = opts.model_copy(update={"init_eskf": estimator_options("eskf", None, preset)})
        else:
            opts = estimator_options("eskf", config, preset)
        ds = load(dataset, load_options)
        print_load_warnings(console, ds)
        if method == "eskf":
            opts = offline_smoothing(apply_dataset_properties(opts, ds, console), smooth)
        elif smooth is not None:
            raise UsageError("--smooth/--no-smooth apply to --method eskf only")
        elif opts.init_eskf is not None:  # the initialising ESKF smoothed as uwbimu estimate's unless it says
            opts = opts.model_copy(update={"init_eskf": offline_smoothing(
                apply_dataset_properties(opts.init_eskf, ds, console), None)})
        if method == "eskf":
            from uwbimu.cli.compile_notice import ensure_compiled

            ensure_compiled(console)  # before the workers: they load the compiled kernels from the cache
        # no auto-refresh: its thread would stop repeatability from forking its pool from this warm process
        # (parallel._can_fork: one thread), the fast start that makes 2 workers pay on short windows
        with Progress(console=console, auto_refresh=False) as prog:
            task = prog.add_task("calibrating windows", total=windows)
            rep = repeatability(ds, windows, method, options=opts, level=level, workers=workers,
                                progress=lambda d, n: prog.update(task, completed=d, refresh=True))
        rep["method"] = method
        rep["dataset"] = str(dataset)
        with output_folder(out, force, protect=[dataset], names=["repeatability.json"], finite=False) as tmp:
            write_json(tmp / "repeatability.json", rep)
        t = Table(title=f"Repeatability over {windows} windows of {rep['window_s']:.1f} s")
        for c in ("parameter", "mean", "spread sd", "predicted sigma", "ratio", "chi2/dof", "p", "verdict"):
            t.add_column(c, justify="right")
        comp = calibration_components()  # lx, ly, lz, time_offset -> (block, component)

        def cell(v, fmt, scale=1.0):  # "-" where the test does not apply (a parameter held in every window)
            return "-" if v is None or not math.isfinite(v) else format(v * scale, fmt)

        for name, p in rep["parameters"].items():
            sc, u = comp[name][0].table if name in comp else (100.0, "cm")
            # a scalar block by its state name (t_d), a vector's component by its output name (lx)
            shown = comp[name][0].name if name in comp and comp[name][0].size == 1 else name
            t.add_row(escape(f"{shown} [{u}]"), cell(p["mean"], ".2f", sc), cell(p["std"], ".2f", sc),
                      cell(p["rms_sd"], ".2f", sc), cell(p["ratio"], ".2f"),
                      "-" if not math.isfinite(p["chi2"]) else f"{p['chi2']:.1f}/{p['dof']}",
                      cell(p["p_value"], ".3f"), p["verdict"])
        console.print(fit_table(console, t))
        for w in rep["windows"]:
            if "error" in w:
                console.print(f"[yellow]window {w['i'] + 1} failed:[/yellow] {escape(str(w['error']))}")
        # the names the batch's block check gives the parameters: <output_key>[_<axis>]
        pname = {n: "_".join(filter(None, (b.output_key, b.axes[i]))) for n, (b, i) in comp.items()}
        wid = {k: sum(pname[k] in (w.get("sigma_widened_by_blocks") or []) for w in rep["windows"])
               for k in rep["parameters"] if k in pname}
        if any("sigma_widened_by_blocks" in w for w in rep["windows"]):  # batch: each window's block check
            console.print("sigma set by the block check (windows of " + str(len(rep["windows"])) + "): "
                          + ", ".join(f"{k} {n}" for k, n in wid.items()))
        console.print(escape(f"wrote {out / 'repeatability.json'}"))
