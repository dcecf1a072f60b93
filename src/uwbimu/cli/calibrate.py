"""``uwbimu calibrate``: full-batch MAP calibration (GTSAM) of lever arm, time offset and anchor range biases."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import math

import typer

from uwbimu.cli.conventions import FORCE_HELP, measurement_counts, value_sd
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from uwbimu.cli.dataset_options import with_load_options
from uwbimu.formatting import format_number, format_value_sigma


def calibration_summary(cal: dict, truth=None) -> Table:
    """Rich table "value ± σ" (and the truth when the dataset documents it); one lever arm per tag when
    the calibration has several (``cal["tags"]``)."""
    t = Table(title="Batch calibration (value ± 1σ, marginal)")
    for c in ("parameter", "estimate ± σ", "truth", "σ from", "verdict"):
        t.add_column(c, justify="left" if c == "parameter" else "right")
    per = ((cal.get("covariance") or {}).get("block_check") or {}).get("parameters") or {}
    idf = (cal.get("identifiability") or {}).get("lever_arm") or {}

    def source(name: str) -> str:  # what set this sigma: the blocks (widened) or the sandwich / model
        b = per.get(name)
        if b is None:
            return "-"
        return "blocks" if b["widened"] else "sandwich"

    tags = cal.get("tags") or {}
    blocks = list(tags.items()) if len(tags) > 1 else [(None, cal)]  # several tags: one lever arm each
    for k, (name, blk) in enumerate(blocks):
        t_lever = truth.lever_arm if truth is not None else None
        if name is not None:
            t_lever = (truth.tags or {}).get(name) if truth is not None else None
        verdicts = idf.get(name, {}) if name is not None else idf
        for i, c in enumerate("xyz"):
            tv = t_lever[i] if t_lever is not None else None
            label = f"lever arm {c} (cm)" if name is None else f"lever arm {c}, {name} (cm)"
            pname = f"lever_arm_{c}" if k == 0 else f"lever_arm_{name}_{c}"
            t.add_row(escape(label), value_sd(blk["lever_arm"][i], blk["lever_arm_sd"][i], 100),
                      "-" if tv is None else f"{100 * tv:.2f}", source(pname),
                      (verdicts.get(c) or {}).get("verdict", "-"))
    td = cal["time_offset"]
    tv = truth.time_offset if truth is not None else None
    if td["held_at_prior"]:
        val = f"{1000 * td['value']:.1f} (held at prior: {td['verdict']})"
    elif td["sd_curvature"] is not None and math.isfinite(td["sd_curvature"]):
        val = (f"{value_sd(td['value'], td['sd'], 1000, '.1f')} marginal, ± {1000 * td['sd_curvature']:.1f} "
               f"profile curvature")
    else:
        val = f"{value_sd(td['value'], td['sd'], 1000, '.1f')} marginal ({td['verdict']})"
    t.add_row("time offset (ms)", val, "-" if tv is None else f"{1000 * tv:.1f}",
              "-" if td["held_at_prior"] else source("time_offset"), td["verdict"])
    bias_v = (cal.get("identifiability") or {}).get("anchor_bias") or {}
    for a, b in cal["anchor_bias"].items():
        t.add_row(escape(f"range bias {a} (cm)"), value_sd(b, cal["anchor_bias_sd"][a], 100), "-",
                  source(f"anchor_bias_{a}"), (bias_v.get(a) or bias_v.get(str(a)) or {}).get("verdict", "-"))
    return t


def anchor_summary(anchors: dict) -> Table:
    """Rich table of the anchor self-survey: position ± σ (cm) of every estimated anchor and the gauge."""
    t = Table(title=f"Anchor self-survey (gauge: {anchors['gauge']['kind']})")
    for c in ("anchor", "x ± σ (m)", "y ± σ (m)", "z ± σ (m)", "prior"):
        t.add_column(c, justify="left" if c == "anchor" else "right")
    for a in anchors["estimated"]:
        e = anchors["positions"][a]
        t.add_row(escape(str(a)), *[value_sd(v, s, fmt=".3f") for v, s in zip(e["position"], e["sd"])],
                  "none" if e["prior_sd"] is None else f"{e['prior_sd']:g} m")
    return t


def print_agreement(console: Console, event: Optional[dict]) -> None:
    """The batch against its initialising ESKF (calibration.yaml ``estimators``): one warning line with
    :func:`uwbimu.calibration.agreement.agreement_message` when they disagree, else one short line."""
    from uwbimu.calibration.agreement import agreement_message

    if not isinstance(event, dict) or "kind" not in event:
        return
    rows = [dict(r, z=math.inf if r.get("z") is None else float(r["z"])) for r in event.get("parameters") or []]
    msg = agreement_message(dict(event, parameters=rows))
    if msg is not None:
        console.print(f"[yellow]warning (estimators_disagree):[/] {escape(msg)}", highlight=False)
    elif rows:
        console.print(escape(f"the batch agrees with the initialising ESKF (largest distance "
                             f"{format_number(max(r['z'] for r in rows))} combined σ)"), highlight=False)


class StageBars:
    """Progress of :func:`uwbimu.calibration.calibrate` from its ``on_stage`` reports
    (:class:`uwbimu.calibration.stages.StageProgress`): on a terminal, a bar over the stages and one over the
    t_d profile points; elsewhere (a pipe, a log file), one line per stage started.  Written to ``console``
    (``uwbimu calibrate`` gives it stderr, so stdout keeps only the results)."""

    def __init__(self, console: Console):
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.console = console
        self.live = console.is_terminal
        # refreshed on each report, no auto-refresh thread: with one thread the t_d profile's pool is forked
        # from this process (parallel._can_fork), the start that makes --workers 2 pay
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                                 TimeElapsedColumn(), console=console, transient=True, disable=not self.live,
                                 auto_refresh=False)
        self.stages = None
        self.points = None
        self.t0 = None

    def __enter__(self) -> "StageBars":
        import time

        self.t0 = time.perf_counter()
        self.progress.__enter__()
        return self

    def __exit__(self, *exc) -> None:
        self.progress.__exit__(*exc)

    def update(self, ev) -> None:
        """The ``on_stage`` callback."""
        import time

        if self.stages is None:
            self.stages = self.progress.add_task("calibrate", total=ev.total)
        if ev.status == "started":
            self.progress.update(self.stages, description=f"calibrate: {ev.stage}", completed=ev.index, refresh=True)
            if not self.live:
                self.console.print(escape(f"calibrate: {ev.stage} ({ev.index + 1}/{ev.total}, "
                                          f"{time.perf_counter() - self.t0:.0f} s)"), highlight=False)
        elif ev.status in ("done", "skipped"):
            self.progress.update(self.stages, completed=ev.index + 1, refresh=True)
        elif ev.status == "point":
            if self.points is None:
                self.points = self.progress.add_task("t_d profile points", total=ev.total_points)
            self.progress.update(self.points, completed=ev.done, total=ev.total_points, refresh=True)


def register(app: typer.Typer) -> None:
    @app.command("calibrate")
    @with_load_options
    def calibrate_cmd(
        dataset: Path = typer.Argument(..., help="Dataset folder (imu.csv, uwb.csv and/or tdoa.csv, anchors.csv)"),
        out: Path = typer.Option(..., "--out", "-o", help="Output folder"),
        config: Optional[Path] = typer.Option(None, "--config", "-c", help="Calibration options YAML (see docs/calibrate.md)."),
        eskf_config: Optional[Path] = typer.Option(None, "--eskf-config", help="Options of the initialising ESKF"),
        estimate_anchors: Optional[str] = typer.Option(
            None, "--estimate-anchors",
            help="Comma-separated anchor ids whose positions are estimated (self-survey; weak prior around "
                 "anchors.csv, none for rows marked surveyed: false); adds to the config's estimate_anchors"),
        plots: bool = typer.Option(True, "--plots/--no-plots", help="Write the plots (td_profile.png, ...)."),
        workers: int = typer.Option(
            1, "--workers", min=1,
            help="Processes for the t_d profile (its upward and downward walks run in parallel on the Monte Carlo "
                 "process pool; more than 2 gain nothing). 1: in this process. Same result either way."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        load_options=None,
    ) -> None:
        """Batch MAP calibration over the whole log: lever arm, time offset (profile + verdict), anchor biases."""
        from uwbimu.calibration import CalibrationOptions, calibrate, write_calibration
        from types import SimpleNamespace

        from uwbimu.calibration.outputs import OUTPUT_FILES
        from uwbimu.cli.estimate import print_run_warnings
        from uwbimu.cli.dataset_options import (apply_dataset_properties, estimator_options, load,
                                                offline_smoothing, print_load_warnings)
        import numpy as np

        from uwbimu.errors import EstimationError, UsageError, UwbimuError
        from uwbimu.io.atomic import check_output_target, output_folder

        console = Console()
        # a bad --config: ConfigError naming file, line and field (exit 2)
        opts = CalibrationOptions.from_yaml(config) if config is not None else CalibrationOptions()
        if estimate_anchors is not None:
            ids = [a.strip() for a in estimate_anchors.split(",") if a.strip()]
            if not ids:
                raise UsageError("--estimate-anchors: expected comma-separated anchor ids, e.g. --estimate-anchors 6,7,8")
            opts = opts.model_copy(update={"estimate_anchors": list(dict.fromkeys(opts.estimate_anchors + ids))})
        # the initialising ESKF: --eskf-config, else calibrate.yaml's init_eskf, else the defaults; smoothed
        # forward-backward unless that file sets smoother (the run uwbimu estimate makes: one ESKF answer)
        eskf_opts = (estimator_options("eskf", eskf_config, None) if eskf_config is not None
                     else opts.init_eskf if opts.init_eskf is not None else estimator_options("eskf", None, None))
        check_output_target(out, sorted(OUTPUT_FILES), force, protect=[dataset])
        ds = load(dataset, load_options)
        print_load_warnings(console, ds)
        eskf_opts = offline_smoothing(apply_dataset_properties(eskf_opts, ds, console), None)
        from uwbimu.cli.compile_notice import ensure_compiled

        # the initialising ESKF's kernels: a cold cache compiles them now, announced and timed, not in silence
        compiled = ensure_compiled(console)
        try:
            with StageBars(Console(stderr=True)) as bars:
                res = calibrate(ds, opts, eskf_options=eskf_opts, workers=workers, on_stage=bars.update)
        except UwbimuError:
            raise  # refusals (input exit 1, config 2) and EstimationError / InitialisationError (5) keep their code
        except (RuntimeError, np.linalg.LinAlgError) as exc:
            # GTSAM's solver failures (indeterminant system: RuntimeError) and singular matrices: the estimation
            # failed (exit 5).  Any other exception is a bug and reaches the wrapper as one (exit 70).
            raise EstimationError(f"{type(exc).__name__}: {exc}") from None
        with output_folder(out, force, protect=[dataset], names=sorted(OUTPUT_FILES)) as tmp:
            written = write_calibration(res, tmp, plots=plots)
        cal = res.calibration
        console.print(calibration_summary(cal, ds.meta.truth))
        td = cal["time_offset"]
        if td.get("held_at_prior"):
            console.print(escape(f"the other values and sigmas are conditional on t_d = "
                                 f"{format_number(1000 * td['value'], 'ms')} (held at the prior; its uncertainty is "
                                 "not in them)"), highlight=False)
        if "anchors" in cal and cal["anchors"]["estimated"]:
            console.print(anchor_summary(cal["anchors"]))
        sc = cal.get("imu_noise", {}).get("scale", {})
        if sc.get("method") == "variance_component":
            sd = sc.get("scale_sd")
            fig = (format_value_sigma(sc["scale"], sd) if sd is not None and math.isfinite(sd) and sd > 0
                   else format_number(sc["scale"]))
            console.print(escape(f"IMU noise model scaled by {fig} (estimated from the log; imu_noise_scale: fixed "
                                 "to keep the stated one)"), highlight=False)
        st = cal.get("start") or {}
        if st.get("source") == "eskf":  # the fallback is a warning event, printed with the others below
            console.print(escape(f"batch started from the ESKF (health check: {st.get('reason')})"), highlight=False)
        print_agreement(console, cal.get("estimators"))
        # every warning and event the report lists (run_warning_items), each once; the disagreement is printed above
        print_run_warnings(console, SimpleNamespace(
            warnings=list(cal.get("warnings") or []),
            events=[ev for ev in res.events if ev.get("kind") != "estimators_disagree"]))
        r = cal["ranges"]
        hub = cal["range_model"].get("huber", {})
        # cal["ranges"] counts every measurement row of the solve (ranges and TDoA)
        used = "ranges" if getattr(ds, "tdoa", None) is None else "measurements"
        console.print(escape(
            f"{measurement_counts(ds)}: {r['used']} {used} in the solve ({r['downweighted']} down-weighted by Huber "
            f"at {r['huber_k']:.2f} sigma{' (adaptive)' if hub.get('selection') == 'adaptive' else ''}, "
            f"{format_number(int(round(r['expected_downweighted'])))} expected from Gaussian noise), {len(written)} "
            f"files in {out}, {format_number(res.runtime_s, 's')}"
            + (f" (the ESKF's kernels compiled once before it, {format_number(compiled.seconds, 's')})"
               if compiled.cold else "")), highlight=False)
