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
                                             help="Flag anchors whose refitted position moves more than this, in m."),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when an anchor is flagged."),
        csv: Optional[Path] = typer.Option(None, "--csv", help="Also write the per-anchor residual table here."),
        force: bool = typer.Option(False, "--force", help="Replace an existing --csv file."),
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

        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        if csv is not None and csv.exists():
            # Never overwrite a user's file by accident, and never a dataset's own input.
            inside = csv.resolve().parent == (dataset if dataset.is_dir() else dataset.parent).resolve()
            if inside or not force:
                why = "it is inside the dataset folder" if inside else "use --force to replace it"
                console.print(f"[red]error:[/red] --csv {csv} exists; {why}")
                raise typer.Exit(code=2)
        try:
            chk = CheckOptions(move_threshold=move_threshold)
        except ValueError:
            console.print(f"[red]error:[/red] --move-threshold must be > 0 m, got {move_threshold!r}")
            raise typer.Exit(code=2)
        with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                      console=console, transient=True) as bar:
            task = bar.add_task(f"loading {dataset}", total=1.0)
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")  # repairs are printed from the report below
                    ds = load_dataset(dataset, opts)
            except DatasetError as exc:
                bar.stop()
                console.print(f"[red]refused:[/red] {exc}", soft_wrap=True)
                raise typer.Exit(code=1)

            def progress(stage: str, frac: float) -> None:
                # Loading is the first 30 % of the bar, the diagnostics the rest.
                bar.update(task, completed=0.3 + 0.7 * frac, description=f"checking: {stage}")

            progress("validated", 0.0)
            result = check_dataset(ds, chk, progress=progress)
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
    from rich.markup import escape
    from rich.table import Table

    rep = ds.report
    console.print(f"[bold]{ds.meta.name}[/bold] ({ds.path}): [green]valid[/green]")
    if rep is not None:
        console.print("files: " + ", ".join(rep.files.values()))
        for a in rep.actions:
            console.print(f"[yellow]repair:[/yellow] {a}")
        for n in rep.notes:
            console.print(f"note: {n}")

    # Numbers are never cut short ("-0.0…"): min_width keeps a column as wide
    # as its numbers, headers wrap instead, ids fold, and collapsed padding
    # lets the widest table fit an 80-column console.
    t = Table(title="Streams", collapse_padding=True)
    t.add_column("stream", justify="right", overflow="fold")
    for c, w in (("samples", 5), ("start [s]", 6), ("end [s]", 6), ("duration [s]", 8),
                 ("rate [Hz]", 5), ("median dt [s]", 6), ("max gap [s]", 5), ("gaps", 4)):
        t.add_column(escape(c), justify="right", min_width=w)
    for name, r in result.streams.iterrows():
        t.add_row(name, str(int(r["samples"])), _f(r["t_start"]), _f(r["t_end"]), _f(r["duration"], ".2f"),
                  _f(r["rate_hz"], ".1f"), _f(r["median_dt"], ".4f"), _f(r["max_gap"]), str(int(r["n_gaps"])))
    console.print(t)

    a = Table(title="Anchors (world frame, m) and ranges", collapse_padding=True)
    a.add_column("id", justify="right", overflow="fold")
    for c, w in (("x", 6), ("y", 6), ("z", 6), ("ranges", 5), ("rate [Hz]", 5), ("min [m]", 5),
                 ("median [m]", 6), ("max [m]", 6), ("max gap [s]", 5)):
        a.add_column(escape(c), justify="right", min_width=w)
    for aid, r in result.anchors.iterrows():
        a.add_row(str(aid), _f(r["x"]), _f(r["y"]), _f(r["z"]), str(int(r["ranges"])), _f(r["rate_hz"], ".1f"),
                  _f(r["range_min"]), _f(r["range_median"]), _f(r["range_max"]), _f(r["max_gap"]))
    console.print(a)

    if result.residual_table is not None:
        if result.lever_arm is None:
            lev = f"lever arms {result.lever_arm_source}"
        else:
            lev = ("lever arm (" + ", ".join(f"{v:.3f}" for v in result.lever_arm)
                   + f") m from {result.lever_arm_source}")
        # escape(): "[m]" would otherwise be read as rich markup and vanish.
        rt = Table(title=escape(f"Range residuals per anchor: measured - predicted from ground truth [m] "
                                f"({lev}; {result.n_compared} ranges)"),
                   collapse_padding=True)
        rt.add_column("anchor", justify="right", overflow="fold", min_width=6)
        # robust sd = 1.4826 MAD is left to the --csv table, to fit 80 columns.
        for c, w in (("n", 4), ("median", 6), ("MAD", 5), ("RMS", 5),
                     ("p95 |r|", 5), ("refit shift", 5), ("refit score", 5)):
            rt.add_column(escape(c), justify="right", min_width=w)
        # The other surveyed anchor that explains these ranges best, and its score.
        rt.add_column("best other", justify="right", overflow="fold")
        rt.add_column("other score", justify="right", min_width=5)
        flagged = {f.anchor for f in result.flags}
        for aid, r in result.residual_table.iterrows():
            style = "red" if aid in flagged else None
            other, other_score = (str(r["best_other"]), _f(r["other_score"])) if r["best_other"] else ("-", "-")
            rt.add_row(str(aid), str(int(r["n"])), _f(r["median"], "+.3f"), _f(r["mad"]),
                       _f(r["rms"]), _f(r["p95_abs"]), _f(r["fit_shift"]), _f(r["fit_score"]), other, other_score,
                       style=style)
        console.print(rt)
    for n in result.notes:
        console.print(f"note: {n}")
    if result.flags:
        for fl in result.flags:
            console.print(f"[red]flag ({fl.kind}):[/red] {fl.message}", soft_wrap=True)
    elif result.residual_table is not None:
        console.print("[green]no anchor flagged[/green] (position refit and id cross-check agree with the survey)")
