"""``uwbimu report`` and ``uwbimu repeatability``: the one-file HTML report and the window test."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer


def register(app: typer.Typer) -> None:
    @app.command("report")
    def report(
        out: Path = typer.Argument(..., help="Estimator output folder (calibration.yaml, trajectory.csv, residuals.csv)."),
        dataset: Optional[Path] = typer.Option(None, "--dataset", "-d",
                                               help="Dataset folder: adds anchors, documented/true calibration, ground truth."),
        output: Optional[Path] = typer.Option(None, "--output", "-o", help="HTML file to write (default OUT/report.html)."),
    ) -> None:
        """Write one self-contained HTML calibration report (plots embedded, opens offline)."""
        from rich.console import Console

        from uwbimu.eval.files import EvalInputError
        from uwbimu.eval.report import write_report
        from uwbimu.io.loader import DatasetError

        console = Console()
        try:
            path = write_report(out, dataset=dataset, path=output)
        except (EvalInputError, DatasetError) as exc:
            console.print(f"[red]error:[/red] {exc}", soft_wrap=True)
            raise typer.Exit(code=1)
        console.print(f"wrote {path}")

    @app.command("repeatability")
    def repeatability_cmd(
        dataset: Path = typer.Argument(..., help="Dataset folder."),
        out: Path = typer.Option(..., "--out", help="Folder for repeatability.json (e.g. the estimator output folder)."),
        windows: int = typer.Option(4, "--windows", "-k", min=2, help="Number of windows."),
        config: Optional[Path] = typer.Option(None, "--config", help="Estimator options YAML."),
        level: float = typer.Option(0.01, "--level", help="Significance level of the chi-square test."),
    ) -> None:
        """Calibrate K windows of a log and compare the spread of lever arm / time offset with the filter's sigma."""
        from rich.console import Console
        from rich.progress import Progress
        from rich.table import Table

        from uwbimu.eval.repeatability import repeatability
        from uwbimu.io.atomic import write_json
        from uwbimu.io.loader import DatasetError, load_dataset

        console = Console()
        try:
            ds = load_dataset(dataset)
        except DatasetError as exc:
            console.print(f"[red]error:[/red] {exc}", soft_wrap=True)
            raise typer.Exit(code=1)
        from uwbimu.estimation import EskfOptions, run_eskf

        opts = EskfOptions.from_yaml(config) if config is not None else None
        with Progress(console=console) as prog:
            task = prog.add_task("calibrating windows", total=windows)
            rep = repeatability(ds, windows, lambda w: run_eskf(w, opts), level=level,
                                progress=lambda d, n: prog.update(task, completed=d))
        rep["dataset"] = str(dataset)
        write_json(out / "repeatability.json", rep)
        t = Table(title=f"Repeatability over {windows} windows of {rep['window_s']:.1f} s")
        for c in ("parameter", "mean", "spread sd", "predicted sigma", "ratio", "chi2/dof", "p", "verdict"):
            t.add_column(c, justify="right")
        for name, p in rep["parameters"].items():
            sc, u = (1000.0, "ms") if name == "td" else (100.0, "cm")
            t.add_row(f"{name} [{u}]", f"{p['mean'] * sc:.2f}", f"{p['std'] * sc:.2f}", f"{p['rms_sd'] * sc:.2f}",
                      f"{p['ratio']:.2f}", f"{p['chi2']:.1f}/{p['dof']}", f"{p['p_value']:.3f}", p["verdict"])
        console.print(t)
        for w in rep["windows"]:
            if "error" in w:
                console.print(f"[yellow]window {w['i'] + 1} failed:[/yellow] {w['error']}")
        console.print(f"wrote {out / 'repeatability.json'}")
