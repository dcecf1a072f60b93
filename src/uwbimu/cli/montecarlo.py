"""``uwbimu montecarlo``: scenarios x seeds x estimators on a process pool or Dask."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table


def _fmt(cell: dict, key: str, stat: str = "median", scale: float = 1.0, digits: int = 3) -> str:
    v = cell.get(key) or {}
    if not v.get("n"):
        return "-"
    return f"{v[stat] * scale:.{digits}f}"


def _ms(cell: dict, key: str, scale: float, digits: int = 1) -> str:
    v = cell.get(key)
    return "-" if v is None else f"{v * scale:.{digits}f}"


def summary_table(summary: dict) -> Table:
    """Every estimated quantity per cell: RMS over runs of position RMSE per axis, of the lever-arm
    error per axis and of the time-offset error; runs that diverged and the fewest runs alive."""
    table = Table(title=escape(f"{summary['name']}: {summary['runs_per_scenario']} runs per scenario"))
    for col in ("scenario", "estimator", "ok/runs", "diverged", "RMSE x [m]", "RMSE y [m]", "RMSE z [m]", "NEES pos",
                "lever x/y/z RMS [mm]", "t_d RMS [ms]", "est. [s/run]"):
        table.add_column(escape(col), justify="left" if col in ("scenario", "estimator") else "right",
                         no_wrap=col in ("scenario", "estimator", "ok/runs"))
    for c in summary["cells"]:
        table.add_row(
            escape(c["scenario"]), escape(c["estimator"]),
            f"{c['runs'] - c['failed']}/{c['runs']}" + (f" ({c['runs_truncated']} cut)" if c.get("runs_truncated") else ""),
            str(c.get("runs_diverged", 0)),
            *(f"{c[f'rmse_{a}_all_runs']:.3f}" if c.get(f"rmse_{a}_all_runs") is not None else "-" for a in "xyz"),
            _fmt(c, "nees_pos_mean", "mean", digits=2),
            "/".join(_ms(c, f"lever_arm_err_{a}_rms_all_runs", 1e3) for a in "xyz"),
            _ms(c, "time_offset_err_rms_all_runs", 1e3, 2), _fmt(c, "est_s", "mean", digits=2),
        )
    return table


def crlb_table(summary: dict) -> Optional[Table]:
    """Cells against their posterior Cramer-Rao bound (None when the study has no bounds)."""
    cells = [c for c in summary["cells"] if c.get("crlb")]
    if not cells:
        return None
    table = Table(title="against the posterior Cramer-Rao bound (ratio = RMS over runs / bound ± its standard "
                        "error from the spread over runs)")
    for col in ("scenario", "estimator", "inside hull", "RMSE 3-D / bound [m]", "ratio", "lever x/y/z bound [mm]",
                "lever ratio x y z", "t_d bound [ms]", "t_d ratio"):
        table.add_column(escape(col), justify="left" if col in ("scenario", "estimator") else "right")
    for c in cells:
        b, r = c["crlb"], c.get("ratio_to_crlb", {})
        se = c.get("ratio_to_crlb_se", {})

        def ratio(k: str) -> str:
            return f"{r[k]:.2f}±{se[k]:.2f}" if k in r and k in se else (f"{r[k]:.2f}" if k in r else "-")

        rm3 = c.get("rmse_3d_all_runs")
        table.add_row(
            c["scenario"], c["estimator"], f"{100 * b['inside_hull_fraction']:.0f}%",
            f"{rm3:.4f} / {b['rmse_3d']:.4f}" if rm3 is not None else f"- / {b['rmse_3d']:.4f}", ratio("rmse_3d"),
            "/".join(f"{1e3 * b[f'lever_arm_sd_{a}']:.1f}" for a in "xyz"),
            " ".join(ratio(f"lever_arm_err_{a}") for a in "xyz"),
            f"{1e3 * b['time_offset_sd']:.2f}", ratio("time_offset_err"),
        )
    return table


def register(app: typer.Typer) -> None:
    @app.command("montecarlo")
    def montecarlo_cmd(
        config: Optional[Path] = typer.Argument(None, help="Study YAML (scenarios, estimators, seed_base)"),
        out: Path = typer.Option(..., "--out", "-o", help="Output folder (a rerun with the same folder resumes)"),
        runs: Optional[int] = typer.Option(None, "--runs", "-n", help="Seeds per scenario (default: the config's)"),
        workers: Optional[int] = typer.Option(None, "--workers", "-j", help="Processes / Dask workers (default: all cores)"),
        scheduler: Optional[str] = typer.Option(None, "--scheduler", help="Dask scheduler address, e.g. tcp://host:8786"),
        dask_local: bool = typer.Option(False, "--dask-local", help="Run on a loopback Dask LocalCluster"),
        example: Optional[str] = typer.Option(None, "--example", help="A built-in study instead of CONFIG (seed-anchor-planes)"),
        no_plots: bool = typer.Option(False, "--no-plots", help="Skip the figures"),
    ) -> None:
        """Monte Carlo study: scenarios x seeds x estimators -> montecarlo.csv, summary.json, plots."""
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        from uwbimu.errors import UsageError
        from uwbimu.studies import config_from_dict, load_config, run_study
        from uwbimu.studies.examples import EXAMPLES, example_config

        console = Console()
        if not console.is_terminal and "COLUMNS" not in os.environ:
            console = Console(width=140)  # a log file: do not squeeze the numbers (COLUMNS=80 still wraps)
        err = Console(stderr=True)
        if (config is None) == (example is None):
            raise UsageError(f"give a CONFIG file or --example NAME (examples: {', '.join(sorted(EXAMPLES))})")
        if scheduler and dask_local:
            raise UsageError("--scheduler and --dask-local are exclusive")
        if workers is not None and workers < 1:
            raise UsageError("--workers must be at least 1")
        if example is not None:
            try:
                cfg = config_from_dict(example_config(example), f"example {example}")
            except KeyError as exc:
                raise UsageError(str(exc.args[0])) from None
        else:
            cfg = load_config(config)
        n_runs = runs if runs is not None else cfg.runs
        if n_runs < 1:
            raise UsageError(f"--runs must be at least 1, got {n_runs}")
        if any(e.kind == "eskf" for e in cfg.estimators):
            from uwbimu.cli.compile_notice import ensure_compiled

            ensure_compiled(console)  # once here, before the workers load the compiled kernels from the cache
        with Progress(TextColumn("[bold]runs"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                      console=console, transient=False) as bar:
            task = bar.add_task("runs", total=n_runs * len(cfg.scenarios))

            def progress(done: int, total: int) -> None:
                bar.update(task, completed=done, total=total)

            summary = run_study(cfg, out, runs=runs, workers=workers, scheduler=scheduler,
                                dask_local=dask_local, progress=progress, plots=not no_plots)
        console.print(summary_table(summary))
        ct = crlb_table(summary)
        if ct is not None:
            console.print(ct)
        ex = summary["execution"]
        console.print(escape(
            f"{ex['backend']} x{ex['workers']}, chunks of {ex['chunk_size']} runs, "
            f"{ex['runs_resumed_from_disk']} runs resumed from disk, {ex['wall_s_this_call']:.1f} s. "
            f"Wrote {out / 'montecarlo.csv'}, {out / 'summary.json'}"
            + (f" and {len(summary.get('figures', []))} figures" if summary.get("figures") else "")
        ))
        failed = sum(c["failed"] for c in summary["cells"])
        if failed:
            err.print(f"[yellow]{failed} run(s) failed[/] (status=failed rows in montecarlo.csv carry the message)")
