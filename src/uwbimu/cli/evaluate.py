"""``uwbimu evaluate``: score an estimator output against ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from uwbimu.cli.conventions import FORCE_HELP


#: Files ``uwbimu evaluate`` writes into the estimator output folder.
EVALUATION_FILES = ("evaluation.json", "evaluation_errors.csv", "evaluation_trajectory.png", "evaluation_errors.png")


def _parse_distances(text: str) -> list[float]:
    """``--distances`` as a list of positive path lengths [m]; a bad value is a UsageError (exit 2)."""
    from uwbimu.errors import UsageError

    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise UsageError(f"--distances must be comma-separated numbers, got '{text}'") from None
    if not vals or any(v <= 0 for v in vals):
        raise UsageError(f"--distances must be positive, got '{text}'")
    return vals


def register(app: typer.Typer) -> None:
    @app.command("evaluate")
    def evaluate(
        out: Path = typer.Argument(..., help="Estimator output folder (holds trajectory.csv)."),
        groundtruth: Path = typer.Option(..., "--groundtruth", "-g", help="Ground truth: groundtruth.csv (dataset format) or a dataset folder."),
        align: str = typer.Option("se3", "--align", help="Alignment to ground truth: none | position | se3."),
        distances: str = typer.Option("1,2,5", "--distances", help="RPE path lengths in m, comma-separated."),
        max_gap: float = typer.Option(0.5, "--max-gap", help="Longest ground-truth gap bridged by interpolation [s]."),
        skip_initial: float = typer.Option(0.0, "--skip-initial", help="Ignore the first seconds of the estimate (convergence)."),
        no_plots: bool = typer.Option(False, "--no-plots", help="Do not write PNG plots."),
        attitude: Optional[bool] = typer.Option(
            None, "--attitude/--no-attitude",
            help="Compare attitudes (default: yes, unless the dataset.yaml next to the ground truth marks its body "
                 "frame as not the IMU frame, as ISAS-Walk's)."),
        folder: Optional[Path] = typer.Option(None, "--out", "-o",
                                              help="Output folder for evaluation.json (default: the estimator output folder)."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
    ) -> None:
        """Score OUT/trajectory.csv against ground truth (ATE after alignment, RPE); writes OUT/evaluation.json."""
        from rich.console import Console
        from rich.markup import escape

        from uwbimu.metrics.align import ALIGN_MODES
        from uwbimu.eval.evaluate import evaluate_output

        from uwbimu.errors import UsageError
        from uwbimu.io.atomic import check_output_target, output_folder

        console = Console()
        if align not in ALIGN_MODES:
            raise UsageError(f"--align must be one of {', '.join(ALIGN_MODES)}, got '{align}'")
        dist = _parse_distances(distances)
        names = list(EVALUATION_FILES)
        gt_folder = groundtruth  # a file is protected itself, a dataset folder as a whole
        target = folder if folder is not None else out
        check_output_target(target, names, force, protect=[gt_folder])
        # Scores of empty sets are NaN by design (n/a); the finiteness rule guards estimates.
        with output_folder(target, force, protect=[gt_folder], names=names, finite=False) as tmp:
            s = evaluate_output(tmp, groundtruth, align=align, distances=dist, max_gap=max_gap,
                                skip_initial=skip_initial, plots=not no_plots, compare_attitude=attitude,
                                trajectory=out / "trajectory.csv")
        print_summary(console, s)
        console.print(escape(f"wrote {target / 'evaluation.json'}"))


def print_summary(console, s: dict) -> None:
    """Rich tables of an evaluation summary (units in brackets escaped: rich would read them as markup)."""
    from rich.markup import escape
    from rich.table import Table

    a = s["association"]
    al = s["align"]
    console.print(
        f"alignment [bold]{al['mode']}[/bold]: rotation {al['rotation_deg']:.2f} deg, "
        f"translation ({', '.join(f'{x:.3f}' for x in al['translation'])}) m; scored {a['n_scored']}/{a['n_estimate']} samples; "
        f"ground-truth glitches excluded: {a['n_groundtruth_glitches_excluded']} position, "
        f"{a['n_groundtruth_attitude_glitches_excluded']} attitude; "
        f"outside span {a['n_estimate_outside_groundtruth_span']}, in gaps {a['n_estimate_in_groundtruth_gaps']}"
    )
    t = Table(title="Absolute trajectory error")
    for c in ("metric", "RMSE", "mean", "median", "max", "n"):
        t.add_column(c, justify="right")
    ap = s["ate_position"]
    t.add_row(escape("position [m]"), *(f"{ap[k]:.3f}" for k in ("rmse", "mean", "median", "max")), str(ap["n"]))
    if "ate_rotation" in s:
        t.add_row(escape("attitude [deg]"), escape(str(s["ate_rotation"])), "", "", "", "")
    elif "ate_rotation_deg" in s:
        ar = s["ate_rotation_deg"]
        t.add_row(escape("attitude [deg]"), *(f"{ar[k]:.2f}" for k in ("rmse", "mean", "median", "max")), str(ar["n"]))
    console.print(t)
    r = Table(title="Relative pose error over travelled distance")
    for c in ("distance [m]", "pairs", "trans RMSE [m]", "trans median [m]", "drift [%]", "rot RMSE [deg]"):
        r.add_column(escape(c), justify="right")
    for d, v in s["rpe"].items():
        if v["n_pairs"] == 0:
            r.add_row(d, "0", "-", "-", "-", "-")
            continue
        rot = v["rotation_deg"]["rmse"]
        r.add_row(d, str(v["n_pairs"]), f"{v['translation']['rmse']:.3f}", f"{v['translation']['median']:.3f}",
                  f"{v['translation_percent']:.1f}", "-" if not rot == rot else f"{rot:.2f}")
    console.print(r)
    for w in s.get("warnings") or []:
        console.print(f"[yellow]warning ({escape(w['code'])}):[/yellow] {escape(w['file'])}: {escape(w['message'])}",
                      soft_wrap=True)
