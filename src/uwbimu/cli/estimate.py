"""``uwbimu estimate``: run the error-state EKF on a dataset and write trajectory, calibration, residuals."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import numpy as np
import pandas as pd
import typer

from uwbimu.cli.conventions import FORCE_HELP, measurement_counts, natural_key, value_sd
from uwbimu.formatting import format_number, format_value_sigma
from rich.console import Console
from rich.markup import escape

from uwbimu.cli.dataset_options import SMOOTH_HELP, with_load_options
from rich.table import Table

#: Files ``uwbimu estimate`` writes; an output folder holding anything else is refused without --force.
OUTPUT_FILES = {
    "trajectory.csv", "states.csv", "calibration.yaml", "residuals.csv", "events.yaml", "residual_table.csv", "run.json",
    "metrics.yaml", "trajectory.png", "position_error.png", "calibration.png", "nis.png",
}
#: Outputs whose NaN cells are documented (residuals of rejected/unpredicted ranges, metrics "n/a",
#: sd of states an estimator does not estimate); trajectory.csv and calibration.yaml must be finite.
NAN_DOCUMENTED = ("residuals.csv", "residual_table.csv", "metrics.yaml", "states.csv", "events.yaml")


def calibration_table(result, dataset=None, title: str = "Calibration (value ± 1σ)") -> Table:
    """Rich table of the estimated calibration with 1-sigma and, when known, the truth."""
    cal = result.calibration
    truth = dataset.meta.truth if dataset is not None else None
    table = Table(title=title)
    table.add_column("parameter")
    table.add_column("estimate ± σ", justify="right")
    table.add_column("truth", justify="right")
    table.add_column("error / σ", justify="right")
    tags = cal.get("tags") or {}
    blocks = list(tags.items()) if len(tags) > 1 else [(None, cal)]
    for name, blk in blocks:
        t_lever = truth.lever_arm if truth is not None else None
        if name is not None and truth is not None and truth.tags:
            t_lever = truth.tags.get(name)
        for i, c in enumerate("xyz"):
            v, s = blk["lever_arm"][i], blk["lever_arm_sd"][i]
            tv = t_lever[i] if t_lever is not None else None
            label = f"lever arm {c} (cm)" if name is None else f"lever arm {c}, {name} (cm)"
            table.add_row(label, value_sd(v, s, 100), f"{100 * tv:.2f}" if tv is not None else "-", _z(v, s, tv))
    v, s = cal["time_offset"], cal["time_offset_sd"]
    tv = truth.time_offset if truth is not None else None
    table.add_row("time offset (ms)", value_sd(v, s, 1000), f"{1000 * tv:.2f}" if tv is not None else "-",
                  _z(v, s, tv))
    td = time_offset_document(result)
    if td.get("verdict") or td.get("mode"):
        # mode and verdict as calibration.yaml and the report carry them (one source: calibration_document)
        table.add_row("time offset mode, verdict", escape(f"{td.get('mode', '-')}, {td.get('verdict') or '-'}"),
                      "-", "-")
    for name, key, scale, unit in (("accel bias", "accel_bias", 1.0, "m/s²"), ("gyro bias", "gyro_bias", 180 / np.pi, "deg/s")):
        vals = ", ".join(value_sd(a, b, scale, ".4f", sep="±") for a, b in zip(cal[key], cal[key + "_sd"]))
        table.add_row(f"{name} ({unit})", vals, "-", "-")
    for a, b in sorted((cal.get("anchor_bias") or {}).items(), key=lambda kv: natural_key(kv[0])):
        s = cal["anchor_bias_sd"][a]
        tv = (truth.anchor_bias or {}).get(a) if truth is not None else None
        table.add_row(f"range bias {escape(str(a))} (cm)", value_sd(b, s, 100),
                      f"{100 * tv:.2f}" if tv is not None else "-", _z(b, s, tv))
    return table


def time_offset_document(result) -> dict:
    """The ``time_offset`` mapping of calibration.yaml for ``result`` (value, sd, mode, verdict, ...), from
    :func:`uwbimu.estimation.outputs.calibration_document`: the console, calibration.yaml and the report read the
    same one (a result without events reads as one with none)."""
    from types import SimpleNamespace

    from uwbimu.estimation.outputs import calibration_document

    view = SimpleNamespace(calibration=result.calibration, events=getattr(result, "events", None) or [])
    td = calibration_document(view).get("time_offset")
    return td if isinstance(td, dict) else {}


def nis_line(result) -> Optional[str]:
    """One line of the NIS summary of the run's range/TDoA updates, the report's
    (:func:`uwbimu.eval.report.inputs.nis_summary` of ``result.residuals``); None without NIS."""
    from uwbimu.eval.report.inputs import nis_summary

    s = nis_summary(getattr(result, "residuals", None))
    if s is None:
        return None
    return (f"NIS of {s.n} range/TDoA updates (1 dof each): mean {format_number(s.mean_accepted)} over the "
            f"{s.n_accepted} accepted (expected 1), median {format_number(s.median)}, "
            f"{format_number(s.above_95_pct)} % above the 95 % bound (expected 5 %): {s.verdict}")


def noise_line(result) -> Optional[str]:
    """One line of the noise the run used (``result.extra["noise"]``): the IMU noise densities used and their ratio
    to the preset, each measurement kind's sigma; None when the run reports none."""
    rep = (getattr(result, "extra", None) or {}).get("noise")
    if not isinstance(rep, dict):
        return None
    parts = []
    imu = rep.get("imu") or {}
    for key, unit in (("accel", "m/s²/√Hz"), ("gyro", "rad/s/√Hz")):
        e = imu.get(key)
        if isinstance(e, dict) and e.get("used") is not None:
            ratio = e.get("ratio")
            parts.append(f"{key} {format_number(e['used'], unit)}"
                         + (f" ({format_number(ratio)} × preset)" if ratio is not None else ""))
    if imu.get("status") == "given":
        parts.append("IMU noise as given")
    for kind, e in (rep.get("measurements") or {}).items():
        if isinstance(e, dict) and e.get("sigma_new") is not None:
            lk = e.get("likelihood") if isinstance(e.get("likelihood"), dict) else None
            how = (f"predictive likelihood, {format_number(100 * float(lk['outlier_fraction']))} % outliers; "
                   if lk and lk.get("outlier_fraction") is not None else "")
            parts.append(f"{kind} σ {format_number(100 * float(e['sigma_new']), 'cm')}"
                         + (f" ({how}configured {format_number(100 * float(e['sigma']), 'cm')})"
                            if e.get("sigma") is not None else ""))
    if not parts:
        return None
    return f"noise used ({rep.get('mode', 'given')}): " + ", ".join(parts)


def held_line(result) -> Optional[str]:
    """One line for a ``calibration_held`` event (the filter rerun with the blocks the log did not identify held at
    their prior in consider mode): which blocks, and the first pass's estimate; None without one."""
    ev = next((e for e in getattr(result, "events", None) or [] if e.get("kind") == "calibration_held"), None)
    if ev is None:
        return None
    first = ev.get("first_pass") or {}
    blocks = ", ".join(str(b).replace("_", " ") for b in ev.get("blocks") or []) or "calibration"
    out = f"{blocks} held at the prior (consider mode): the log did not identify it"
    lv, ls = first.get("lever_arm"), first.get("lever_arm_sd")
    if lv is not None and ls is not None and "lever_arm" in (ev.get("blocks") or []):
        out += "; first pass lever arm " + ", ".join(
            f"{c} {format_value_sigma(100 * v, 100 * s, 'cm')}" for c, v, s in zip("xyz", lv, ls))
    if first.get("time_offset") is not None and "time_offset" in (ev.get("blocks") or []):
        sd = first.get("time_offset_sd")
        out += (f"; first pass time offset "
                f"{format_value_sigma(1000 * first['time_offset'], None if sd is None else 1000 * sd, 'ms')}")
    return out


def print_run_summary(console: Console, result) -> None:
    """The NIS summary and the noise used, one line each (the report's figures; a held calibration is printed with
    the warnings, :func:`print_run_warnings`)."""
    for line in (nis_line(result), noise_line(result)):
        if line is not None:
            console.print(escape(line), highlight=False)


def _z(v, s, tv) -> str:
    """Normalised error ``(v - truth) / sd``; "-" without a truth or a finite positive sd."""
    return f"{(v - tv) / s:+.1f}" if tv is not None and s is not None and np.isfinite(s) and s > 0 else "-"


def _cm(x) -> str:
    return f"{100 * x:.2f}" if np.isfinite(x) else "-"


def residual_rich_table(table_df, title: str = "Range residuals per anchor", key: str = "anchor",
                        count: str = "ranges") -> Table:
    """Rich table of :func:`uwbimu.estimation.outputs.residual_table` (innovations, cm)."""
    t = Table(title=title)
    for c in (key, count, "accepted", "rejected %", "median (cm)", "MAD (cm)"):
        t.add_column(c, justify="right" if c != key else "left")
    for r in sorted(table_df.itertuples(index=False), key=lambda r: natural_key(r.anchor)):
        t.add_row(escape(str(r.anchor)), str(r.ranges), str(r.accepted), f"{r.rejected_pct:.1f}", _cm(r.median),
                  _cm(r.mad))
    return t


def print_residual_tables(console: Console, result, written_table=None) -> None:
    """Innovation tables of a run: per anchor for ranges, per anchor pair for TDoA; none for a kind
    the run has no rows of (a TDoA-only log prints no range table).

    ``written_table``: the run's residual_table.csv as :func:`uwbimu.estimation.outputs.write_outputs` returned
    it; a run with ranges only prints it instead of computing it again (the same function of the same rows).
    """
    from types import SimpleNamespace

    from uwbimu.estimation.outputs import residual_table
    from uwbimu.io.check_tdoa import tdoa_pairs

    r = result.residuals
    kind = r["kind"].astype(str).to_numpy() if "kind" in r.columns else np.full(len(r), "range")
    is_range = kind == "range"
    if is_range.any():
        if written_table is not None and is_range.all():
            console.print(residual_rich_table(written_table))
        else:
            console.print(residual_rich_table(residual_table(SimpleNamespace(residuals=r[is_range]))))
    td = r[kind == "tdoa"]
    if len(td):
        # one row per unordered pair: (b, a) rows read as (a, b) with the innovation's sign flipped
        pairs = td.rename(columns={"anchor": "anchor_a"})
        first, second, sign = tdoa_pairs(pairs)
        per_pair = pd.DataFrame({"anchor": [f"{a}-{b}" for a, b in zip(first, second)],
                                 "innovation": sign * td["innovation"].to_numpy(float),
                                 "accepted": td["accepted"].to_numpy(bool)})
        console.print(residual_rich_table(residual_table(SimpleNamespace(residuals=per_pair)),
                                          title="TDoA residuals per anchor pair (a-b: |p - b| - |p - a|)",
                                          key="pair", count="TDoA"))


def run_with_progress(dataset, options, console: Console):
    """Run the ESKF with a rich progress bar."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    # the estimation layer's registry holds eskf and pointmass; uwbimu.estimators would also import the batch
    # calibrator's package (scipy.stats, scipy.optimize, ...: over a second of `uwbimu estimate`'s start)
    from uwbimu.estimation.registry import get_estimator

    run_eskf = get_estimator("eskf").run
    with Progress(TextColumn("[bold]ESKF"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"),
                  TimeElapsedColumn(), console=console, transient=True) as prog:
        task = prog.add_task("eskf", total=1.0)
        return run_eskf(dataset, options, progress=lambda f: prog.update(task, completed=f))


#: Text of a comparison the frames do not allow (the report's wording).
OTHER_FRAME_NA = "n/a (ground truth in another frame)"


def truth_comparison(result, dataset, metrics: Optional[dict] = None) -> Optional[dict]:
    """What the console may say about a run against the dataset's ground truth (None without one).

    The raw (unaligned) figures of :func:`uwbimu.metrics.compute_metrics` are reported only when
    the dataset says the frames agree (:func:`uwbimu.metrics.align.groundtruth_frame`); otherwise
    the position ATE after the dataset's alignment, with the alignment named, and the attitude
    after it only when the ground truth's body frame is the IMU frame -- as the report does.

    Returns
    -------
    dict or None
        ``frames_agree`` (bool), ``align`` (mode); when the frames agree: ``position_rmse``,
        ``position_rmse_after`` [m], ``orientation_rmse_deg`` [deg], ``nees_mean``, ``nees_dof``;
        otherwise ``ate_position_rmse`` [m], ``ate_rotation_rmse_deg`` [deg] (None when the
        attitudes are not comparable), ``n_scored`` and ``error`` (why no aligned figure, or None).
    """
    from uwbimu.errors import InputError
    from uwbimu.metrics.align import groundtruth_frame

    if dataset.groundtruth is None:
        return None
    frame = groundtruth_frame(dataset.meta.extra)
    if frame.frames_agree:
        if metrics is None:
            from uwbimu.metrics import compute_metrics

            metrics = compute_metrics(result, dataset)
        return {"frames_agree": True, "align": frame.align,
                "position_rmse": metrics.get("position_rmse"),
                "position_rmse_after": metrics.get("position_rmse_after"),
                "orientation_rmse_deg": metrics.get("orientation_rmse_deg"),
                "nees_mean": metrics.get("nees_mean"), "nees_dof": metrics.get("nees_dof")}
    from uwbimu.estimation.outputs import trajectory_frame
    from uwbimu.metrics.trajectory import evaluate_trajectory

    out = {"frames_agree": False, "align": frame.align, "ate_position_rmse": None,
           "ate_rotation_rmse_deg": None, "n_scored": 0, "error": None}
    try:
        ev = evaluate_trajectory(trajectory_frame(result), dataset.groundtruth, align=frame.align,
                                 compare_attitude=frame.attitude_comparable)
    except InputError as exc:  # e.g. too little overlap with the ground truth
        out["error"] = " ".join(str(exc).split())
        return out
    summ = ev.summary
    out["ate_position_rmse"] = summ["ate_position"]["rmse"]
    out["n_scored"] = summ["association"]["n_scored"]
    if isinstance(summ.get("ate_rotation_deg"), dict):
        out["ate_rotation_rmse_deg"] = summ["ate_rotation_deg"]["rmse"]
    return out


def _num(v, scale: float = 1.0, fmt: str = ".1f") -> str:
    return "n/a" if v is None or not np.isfinite(v) else format(scale * v, fmt)


def print_run_warnings(console: Console, result) -> list:
    """Print a run's warnings as the report lists them (:func:`uwbimu.eval.report.inputs.run_warning_items` of
    ``result.warnings`` and ``result.events``: one list for both); a text printed once.  Returns the items."""
    import dataclasses

    from uwbimu.eval.report.inputs import run_warning_items

    seen, shown = set(), []
    held = held_line(result)
    for item in run_warning_items(result.warnings, getattr(result, "events", None) or []):
        if item.kind == "calibration_held" and held is not None:
            item = dataclasses.replace(item, text=held)  # the same event, in words
        if item.text in seen:
            continue
        seen.add(item.text)
        shown.append(item)
        label = "warning" if item.severity != "info" else "note"
        kind = "" if item.kind == "estimator_warning" else f" ({escape(item.kind)})"
        console.print(f"[yellow]{label}{kind}:[/] {escape(item.text)}")
    return shown


def print_truth_comparison(console: Console, cmp: Optional[dict]) -> None:
    """One line of :func:`truth_comparison` (nothing without ground truth)."""
    if cmp is None:
        return
    if cmp["frames_agree"]:
        ori = ("orientation n/a (no attitude in the ground truth or the estimate)"
               if cmp["orientation_rmse_deg"] is None else
               f"orientation RMSE {_num(cmp['orientation_rmse_deg'], 1, '.2f')} deg")
        line = (f"position RMSE {_num(cmp['position_rmse'], 100)} cm (after 10 s: "
                f"{_num(cmp['position_rmse_after'], 100)} cm), {ori}, NEES {_num(cmp['nees_mean'])} "
                f"(dof {cmp['nees_dof']})")
        console.print(f"[bold]vs ground truth:[/] {escape(line)}")
        return
    head = f"vs ground truth after {cmp['align']} alignment (ground truth in another frame):"
    if cmp["error"] is not None:
        line = f"not computed: {cmp['error']}"
    else:
        rot = (f"orientation ATE RMSE {_num(cmp['ate_rotation_rmse_deg'], 1, '.2f')} deg"
               if cmp["ate_rotation_rmse_deg"] is not None else "orientation n/a (body frames differ)")
        line = (f"position ATE RMSE {_num(cmp['ate_position_rmse'], 100)} cm over {cmp['n_scored']} samples, "
                f"{rot}; unaligned RMSE and NEES {OTHER_FRAME_NA}")
    console.print(f"[bold]{escape(head)}[/] {escape(line)}")


def register(app: typer.Typer) -> None:
    @app.command("estimate")
    @with_load_options
    def estimate_cmd(
        dataset: Path = typer.Argument(..., help="Dataset folder (imu.csv, uwb.csv and/or tdoa.csv, anchors.csv "
                                       "[, groundtruth.csv])"),
        out: Path = typer.Option(..., "--out", "-o", help="Output folder"),
        config: Optional[Path] = typer.Option(None, "--config", "-c", help="Estimator options YAML (see examples/estimator.yaml)"),
        preset: Optional[str] = typer.Option(None, "--preset", help="Shipped estimator options: default, real, isas-walk"),
        plots: bool = typer.Option(True, "--plots/--no-plots", help="PNG plots when ground truth exists"),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        estimator: str = typer.Option(
            "eskf", "--estimator", help="Estimator: eskf (19-state ESKF) or pointmass (seed 002's 6-state EKF)"
        ),
        clock_faults: bool = typer.Option(True, "--clock-faults/--no-clock-faults",
                                          help="Test the run's time offset for UWB clock jumps/drift (no re-run "
                                               "on a clean log); correct the UWB stamps and re-run when found"),
        smooth: Optional[bool] = typer.Option(None, "--smooth/--no-smooth", help=SMOOTH_HELP),
        load_options=None,
    ) -> None:
        """Estimate trajectory, lever arm and time offset with the UWB-IMU error-state EKF."""
        from uwbimu.cli.compile_notice import CompileNotice, ensure_compiled
        from uwbimu.cli.dataset_options import (apply_dataset_properties, estimator_options, load,
                                                offline_smoothing, print_load_warnings)
        from uwbimu.estimation import write_outputs
        from uwbimu.errors import UsageError
        from uwbimu.io.atomic import check_output_target, output_folder

        console = Console()
        # eskf and pointmass only (batch has its own verb): the estimation layer's registry, without the batch
        # calibrator's imports
        from uwbimu.estimation.registry import get_estimator

        if estimator not in ("eskf", "pointmass"):  # batch has its own verb (uwbimu calibrate)
            raise UsageError(f"--estimator must be eskf or pointmass, got '{estimator}'")
        entry = get_estimator(estimator)
        opts = estimator_options(estimator, config, preset)
        check_output_target(out, sorted(OUTPUT_FILES), force, protect=[dataset])
        ds = load(dataset, load_options)
        print_load_warnings(console, ds)
        opts = apply_dataset_properties(opts, ds, console)
        if estimator == "eskf":
            opts = offline_smoothing(opts, smooth)
        elif smooth:
            raise UsageError("--smooth applies to the eskf estimator only")
        compiled = CompileNotice(cold=False)
        # input problems raise InputError (exit 1), estimation failures EstimationError (exit 5):
        # nothing is relabelled here
        if estimator == "pointmass":
            with console.status(entry.description):
                res = entry.run(ds, opts, None)
        else:
            compiled = ensure_compiled(console)
            res = run_with_progress(ds, opts, console)
            if clock_faults:
                from uwbimu.eval.clock_faults import handle_clock_faults

                res, ds = handle_clock_faults(res, ds, lambda d: run_with_progress(d, opts, console), console)
        with output_folder(out, force, protect=[dataset], names=sorted(OUTPUT_FILES),
                           finite=NAN_DOCUMENTED) as tmp:
            written = write_outputs(res, ds, tmp, plots=plots)
        print_residual_tables(console, res, written["residual_table"])
        console.print(calibration_table(res, ds))
        comparison = truth_comparison(res, ds, written["metrics"])
        print_truth_comparison(console, comparison)
        print_run_summary(console, res)
        print_run_warnings(console, res)
        console.print(escape(f"{measurement_counts(ds)}: ESKF run {res.runtime_s:.2f} s"
                             + (f" (kernels compiled once before it, {compiled.seconds:.0f} s)" if compiled.cold else "")
                             + f"; wrote {len(written['files'])} files to {out}"))


def estimate_and_print(dataset, console: Console, out: Optional[Path] = None, options=None):
    """Run the ESKF on ``dataset``, print calibration "value ± σ" (vs truth when known) and warnings.

    For other verbs (``uwbimu demo``); writes the outputs to ``out`` when given.  Returns the result.
    """
    from uwbimu.estimation import EskfOptions, write_outputs

    from uwbimu.cli.compile_notice import ensure_compiled

    ensure_compiled(console)
    res = run_with_progress(dataset, options or EskfOptions(), console)
    if out is not None:
        write_outputs(res, dataset, out)
    console.print(calibration_table(res, dataset))
    print_truth_comparison(console, truth_comparison(res, dataset))
    print_run_summary(console, res)
    print_run_warnings(console, res)
    return res
