"""``uwbimu check``: validate a dataset folder and print its diagnostics."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer
from rich.markup import escape

from uwbimu.cli.conventions import FORCE_HELP, natural_key

from uwbimu.cli.dataset_options import ACCEL_UNITS, GYRO_UNITS, with_load_options  # noqa: F401 (re-export)


def register(app: typer.Typer) -> None:
    @app.command("check")
    @with_load_options
    def check(
        dataset: Path = typer.Argument(..., help="Dataset folder (imu, uwb and/or tdoa, anchors[, groundtruth] "
                                      ".csv/.parquet)."),
        move_threshold: float = typer.Option(0.3, "--move-threshold",
                                             help="Flag anchors whose refitted position moves more than this, in m."),
        strict: bool = typer.Option(False, "--strict", help="Exit with code 3 when an anchor or a TDoA pair is "
                                    "flagged."),
        csv: Optional[Path] = typer.Option(None, "--csv", help="Also write the per-anchor residual table here "
                                           "(and the per-pair TDoA residual table next to it, NAME_tdoa.csv)."),
        fix: Optional[Path] = typer.Option(None, "--fix", help="Write a repaired copy of the dataset (the repairs "
                                           "asked for with --sort, --drop-duplicates, units, ...) to this folder."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        load_options=None,
    ) -> None:
        """Validate a dataset (refusing bad input) and print rates, gaps, anchors, range and TDoA residuals."""
        from rich.console import Console

        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        from uwbimu.cli.dataset_options import load
        from uwbimu.errors import CheckFlagged, UsageError
        from uwbimu.io.atomic import check_output_target, output_folder, write_csv
        from uwbimu.io.check import CheckOptions, check_dataset
        from uwbimu.io.dataset import write_dataset
        from uwbimu.io.loader import DatasetError

        console = Console()
        protect = [dataset]
        if csv is not None:
            # Never overwrite a user's file by accident, and never a dataset's own input.
            check_output_target(csv.parent if str(csv.parent) else Path("."), _csv_names(csv), force, protect)
        if fix is not None:
            check_output_target(fix, force=force, protect=protect, replace=True)
        try:
            chk = CheckOptions(move_threshold=move_threshold)
        except ValueError:
            raise UsageError(f"--move-threshold must be > 0 m, got {move_threshold:g}") from None
        with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                      console=console, transient=True) as bar:
            task = bar.add_task(f"loading {dataset}", total=1.0)
            try:
                ds = load(dataset, load_options)
            except DatasetError:
                bar.stop()
                raise

            def progress(stage: str, frac: float) -> None:
                # Loading is the first 30 % of the bar, the diagnostics the rest.
                bar.update(task, completed=0.3 + 0.7 * frac, description=f"checking: {stage}")

            progress("validated", 0.0)
            result = check_dataset(ds, chk, progress=progress)
        print_check(console, ds, result)
        tables = [] if csv is None else [(n, tab) for n, tab in zip(_csv_names(csv), (result.residual_table,
                                                                                     result.tdoa_table))
                                         if tab is not None]
        if tables:
            with output_folder(csv.parent if str(csv.parent) else Path("."), force, protect,
                               names=[n for n, _ in tables], finite=False) as tmp:
                for name, tab in tables:
                    write_csv(tmp / name, tab.reset_index())
            console.print(escape("wrote " + ", ".join(str(csv.parent / n) for n, _ in tables)))
        elif csv is not None:
            console.print(escape(f"note: {csv} not written: no residuals to write (no ground truth, or ground "
                                 "truth in another frame)"))
        if fix is not None:
            with output_folder(fix, force, protect, replace=True, finite=False) as tmp:
                write_dataset(ds, tmp, overwrite=True, fmt=_table_format(ds))
            rep = ds.report
            console.print(escape(f"wrote the repaired copy {fix} ({len(rep.actions)} repair(s))" if rep.actions
                                 else f"wrote {fix} (an unchanged copy: no repair was asked for or needed)"))
            for a in rep.actions:
                console.print(f"  repaired: {escape(a)}", soft_wrap=True)
        if strict and result.flags:
            raise CheckFlagged(f"{len(result.flags)} flag(s) on anchor(s) / TDoA pair(s): "
                               + ", ".join(sorted({str(f.anchor) for f in result.flags}, key=natural_key)))


def _csv_names(csv: Path) -> list[str]:
    """``--csv`` file names: the per-anchor range residual table and the per-pair TDoA table."""
    return [csv.name, f"{csv.stem}_tdoa{csv.suffix or '.csv'}"]


def _table_format(ds) -> str:
    files = getattr(ds.report, "files", {}) if ds.report is not None else {}
    return "parquet" if files.get("imu", "").endswith(".parquet") else "csv"


def _f(x, fmt: str = ".3f") -> str:
    try:
        if x is None or (isinstance(x, float) and math.isnan(x)):
            return "-"
        return format(x, fmt)
    except (TypeError, ValueError):
        return str(x)


def print_check(console, ds, result, path=None) -> None:
    """Rich tables for a :class:`uwbimu.io.check.CheckResult`; ``path`` is the folder shown (default: the one
    the dataset was read from; ``demo`` shows where its staging folder ends up)."""
    from rich.table import Table

    from uwbimu.cli.conventions import fit_table

    rep = ds.report
    console.print(f"[bold]{escape(ds.meta.name)}[/bold] ({escape(str(path if path is not None else ds.path))}): "
                  f"[green]valid[/green]")
    if rep is not None:
        console.print(escape("files: " + ", ".join(rep.files.values())))
        for a in rep.actions:
            console.print(f"[yellow]repair:[/yellow] {escape(a)}")
        for n in rep.notes:
            console.print(f"note: {escape(n)}")
        for w in rep.warnings:
            console.print(f"[yellow]warning ({escape(w['code'])}):[/yellow] {escape(w['file'])}: "
                          f"{escape(w['message'])}", soft_wrap=True)

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
    console.print(fit_table(console, t))

    console.print(fit_table(console, _anchor_table(ds, result)))

    if result.residual_table is not None:
        lev = _lever_text(result)
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
        from uwbimu.cli.conventions import natural_key

        for aid, r in sorted(result.residual_table.iterrows(), key=lambda ar: natural_key(ar[0])):
            style = "red" if aid in flagged else None
            other, other_score = (str(r["best_other"]), _f(r["other_score"])) if r["best_other"] else ("-", "-")
            rt.add_row(escape(str(aid)), str(int(r["n"])), _f(r["median"], "+.3f"), _f(r["mad"]),
                       _f(r["rms"]), _f(r["p95_abs"]), _f(r["fit_shift"]), _f(r["fit_score"]), other, other_score,
                       style=style)
        console.print(rt)
    if result.tdoa_pairs is not None:
        console.print(fit_table(console, _tdoa_table(result)))
    if result.tdoa_offsets is not None and result.tdoa_offsets.notna().any():
        offs = ", ".join(f"{a} {v:+.3f}" for a, v in result.tdoa_offsets.items() if math.isfinite(v))
        console.print(escape(f"TDoA: per-anchor range offsets that explain the pair medians [m] (mean zero): {offs}"))
    for n in result.notes:
        console.print(f"note: {escape(n)}")
    if result.flags:
        for fl in result.flags:
            console.print(f"[red]flag ({fl.kind}):[/red] {escape(fl.message)}", soft_wrap=True)
    elif result.residual_table is not None or result.tdoa_table is not None:
        what = ("no anchor or TDoA pair flagged" if result.tdoa_table is not None else "no anchor flagged")
        how = ", ".join(x for x in ("position refit and id cross-check" if result.residual_table is not None else "",
                                    "TDoA pair medians and outliers" if result.tdoa_table is not None else "") if x)
        console.print(f"[green]{what}[/green] ({how} agree with the survey)")


def _lever_text(result) -> str:
    if result.lever_arm is None:
        return f"lever arms {result.lever_arm_source}"
    return "lever arm (" + ", ".join(f"{v:.3f}" for v in result.lever_arm) + f") m from {result.lever_arm_source}"


def _anchor_table(ds, result):
    """Anchors with their ranges and, with ``tdoa.csv``, the TDoA rows each takes part in
    (a TDoA-only dataset shows no empty range columns)."""
    from rich.table import Table

    has_ranges = len(ds.uwb) > 0 or ds.tdoa is None
    has_tdoa = ds.tdoa is not None
    what = {(True, False): "and ranges", (False, True): "and TDoA rows", (True, True): ", ranges and TDoA rows"}
    a = Table(title=f"Anchors (world frame, m) {what[has_ranges, has_tdoa]}".replace(") ,", "),"),
              collapse_padding=True)
    a.add_column("id", justify="right", overflow="fold")
    cols = [("x", 6), ("y", 6), ("z", 6)]
    if has_ranges:
        cols += [("ranges", 5), ("rate [Hz]", 5), ("min [m]", 5), ("median [m]", 6), ("max [m]", 6),
                 ("max gap [s]", 5)]
    if has_tdoa:
        cols += [("TDoA rows", 5)]
    for c, w in cols:
        a.add_column(escape(c), justify="right", min_width=w)
    from uwbimu.cli.conventions import natural_key

    for aid, r in sorted(result.anchors.iterrows(), key=lambda ar: natural_key(ar[0])):
        row = [escape(str(aid)), _f(r["x"]), _f(r["y"]), _f(r["z"])]
        if has_ranges:
            row += [str(int(r["ranges"])), _f(r["rate_hz"], ".1f"), _f(r["range_min"]), _f(r["range_median"]),
                    _f(r["range_max"]), _f(r["max_gap"])]
        if has_tdoa:
            row += [str(int(r["tdoa"]))]
        a.add_row(*row, style="dim" if r["ranges"] == 0 and r["tdoa"] == 0 else None)
    return a


def _tdoa_table(result):
    """Per TDoA pair: rows, rate, gaps and, with ground truth, the residual statistics."""
    from rich.table import Table

    tab = result.tdoa_table
    title = "TDoA pairs (a-b: |p - b| - |p - a|): rows and rates"
    if tab is not None:
        title += (f"; residuals measured - predicted from ground truth [m] ({_lever_text(result)}; "
                  f"{result.n_tdoa_compared} rows)")
    t = Table(title=escape(title), collapse_padding=True)
    t.add_column("pair", justify="right", overflow="fold")
    cols = [("rows", 5), ("rate [Hz]", 5), ("max gap [s]", 5), ("gaps", 4)]
    if tab is not None:
        cols += [("n", 4), ("median", 6), ("robust sd", 5), ("outliers [%]", 5), ("p95 |r|", 5)]
    for c, w in cols:
        t.add_column(escape(c), justify="right", min_width=w)
    flagged = {f.anchor for f in result.flags}
    from uwbimu.cli.conventions import natural_key

    for pair, r in sorted(result.tdoa_pairs.iterrows(), key=lambda pr: natural_key(pr[0])):
        row = [escape(str(pair)), str(int(r["samples"])), _f(r["rate_hz"], ".1f"), _f(r["max_gap"]), str(int(r["n_gaps"]))]
        if tab is not None:
            if pair in tab.index:
                s = tab.loc[pair]
                row += [str(int(s["n"])), _f(s["median"], "+.3f"), _f(s["robust_sigma"]),
                        _f(100 * s["outlier_frac"], ".1f"), _f(s["p95_abs"])]
            else:
                row += ["0", "-", "-", "-", "-"]
        t.add_row(*row, style="red" if pair in flagged else None)
    return t
