"""``uwbimu check``: validate a dataset folder and print its diagnostics."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

GYRO_UNITS = {"rad": "rad/s", "rad/s": "rad/s", "deg": "deg/s", "deg/s": "deg/s"}
ACCEL_UNITS = {"m/s2": "m/s^2", "m/s^2": "m/s^2", "ms2": "m/s^2", "si": "m/s^2", "g": "g"}


def register(app: typer.Typer) -> None:
    @app.command("check")
    def check(
        dataset: Path = typer.Argument(..., help="Dataset folder (imu, uwb, anchors[, groundtruth] .csv/.parquet)."),
        drop_duplicates: bool = typer.Option(False, "--drop-duplicates",
                                             help="Drop rows that exactly repeat an earlier row (counted)."),
        sort: bool = typer.Option(False, "--sort", help="Sort rows by time when out of order (counted)."),
        gyro_units: str = typer.Option("rad", "--gyro-units", help="Unit of wx,wy,wz in the file: rad | deg."),
        accel_units: str = typer.Option("m/s2", "--accel-units", help="Unit of ax,ay,az in the file: m/s2 | g."),
        no_unit_check: bool = typer.Option(False, "--no-unit-check",
                                           help="Skip the deg/s and g plausibility checks."),
        move_threshold: float = typer.Option(0.3, "--move-threshold",
                                             help="Flag anchors whose refitted position moves more than this [m]."),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when an anchor is flagged."),
        csv: Optional[Path] = typer.Option(None, "--csv", help="Also write the per-anchor residual table here."),
    ) -> None:
        """Validate a dataset (refusing bad input) and print rates, gaps, anchors and range residuals."""
        from rich.console import Console

        from uwbimu.io.check import CheckOptions, check_dataset
        from uwbimu.io.loader import DatasetError, LoadOptions, load_dataset

        console = Console()
        if gyro_units.lower() not in GYRO_UNITS:
            console.print(f"[red]error:[/red] --gyro-units must be rad or deg, got {gyro_units!r}")
            raise typer.Exit(code=2)
        if accel_units.lower() not in ACCEL_UNITS:
            console.print(f"[red]error:[/red] --accel-units must be m/s2 or g, got {accel_units!r}")
            raise typer.Exit(code=2)
        opts = LoadOptions(drop_duplicate_rows=drop_duplicates, sort=sort,
                           gyro_units=GYRO_UNITS[gyro_units.lower()], accel_units=ACCEL_UNITS[accel_units.lower()],
                           check_units=not no_unit_check)
        import warnings

        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")  # repairs are printed from the report below
                ds = load_dataset(dataset, opts)
        except DatasetError as exc:
            console.print(f"[red]refused:[/red] {exc}", soft_wrap=True)
            raise typer.Exit(code=1)
        try:
            chk = CheckOptions(move_threshold=move_threshold)
        except ValueError as exc:
            console.print(f"[red]error:[/red] {exc}")
            raise typer.Exit(code=2)
        with console.status("computing range residuals..."):
            result = check_dataset(ds, chk)
        print_check(console, ds, result)
        if csv is not None and result.residual_table is not None:
            from uwbimu.io.atomic import write_csv

            write_csv(csv, result.residual_table.reset_index())
            console.print(f"wrote {csv}")
        if strict and result.flags:
            raise typer.Exit(code=3)


def _f(x, fmt: str = ".3f") -> str:
    try:
        if x is None or (isinstance(x, float) and math.isnan(x)):
            return "-"
        return format(x, fmt)
    except (TypeError, ValueError):
        return str(x)


def print_check(console, ds, result) -> None:
    """Rich tables for a :class:`uwbimu.io.check.CheckResult`."""
    from rich.table import Table

    rep = ds.report
    console.print(f"[bold]{ds.meta.name}[/bold] ({ds.path}): [green]valid[/green]")
    if rep is not None:
        console.print("files: " + ", ".join(rep.files.values()))
        for a in rep.actions:
            console.print(f"[yellow]repair:[/yellow] {a}")
        for n in rep.notes:
            console.print(f"note: {n}")

    t = Table(title="Streams")
    for c in ("stream", "samples", "start [s]", "end [s]", "duration [s]", "rate [Hz]", "median dt [s]",
              "max gap [s]", "gaps"):
        t.add_column(c, justify="right")
    for name, r in result.streams.iterrows():
        t.add_row(name, str(int(r["samples"])), _f(r["t_start"]), _f(r["t_end"]), _f(r["duration"], ".2f"),
                  _f(r["rate_hz"], ".1f"), _f(r["median_dt"], ".4f"), _f(r["max_gap"]), str(int(r["n_gaps"])))
    console.print(t)

    a = Table(title="Anchors (world frame, m) and ranges")
    for c in ("anchor", "x", "y", "z", "ranges", "rate [Hz]", "min [m]", "median [m]", "max [m]", "max gap [s]"):
        a.add_column(c, justify="right")
    for aid, r in result.anchors.iterrows():
        a.add_row(str(aid), _f(r["x"]), _f(r["y"]), _f(r["z"]), str(int(r["ranges"])), _f(r["rate_hz"], ".1f"),
                  _f(r["range_min"]), _f(r["range_median"]), _f(r["range_max"]), _f(r["max_gap"]))
    console.print(a)

    if result.residual_table is not None:
        lev = "per tag" if result.lever_arm is None else "(" + ", ".join(f"{v:.3f}" for v in result.lever_arm) + ")"
        rt = Table(title=f"Range residuals per anchor: measured - predicted from ground truth [m] "
                         f"(lever arm {lev} m from {result.lever_arm_source}; {result.n_compared} ranges)")
        for c in ("anchor", "n", "median", "MAD", "robust sd", "RMS", "p95 |r|", "refit shift", "refit score",
                  "best other"):
            rt.add_column(c, justify="right")
        flagged = {f.anchor for f in result.flags}
        for aid, r in result.residual_table.iterrows():
            style = "red" if aid in flagged else None
            other = f"{r['best_other']} ({_f(r['other_score'])})" if r["best_other"] else "-"
            rt.add_row(str(aid), str(int(r["n"])), _f(r["median"], "+.3f"), _f(r["mad"]), _f(r["robust_sigma"]),
                       _f(r["rms"]), _f(r["p95_abs"]), _f(r["fit_shift"]), _f(r["fit_score"]), other, style=style)
        console.print(rt)
    for n in result.notes:
        console.print(f"note: {n}")
    if result.flags:
        for fl in result.flags:
            console.print(f"[red]flag ({fl.kind}):[/red] {fl.message}", soft_wrap=True)
    elif result.residual_table is not None:
        console.print("[green]no anchor flagged[/green] (position refit and id cross-check agree with the survey)")
