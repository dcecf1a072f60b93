"""``uwbimu observability``: structural rank test, time-offset identifiability, per-window log analysis."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from uwbimu.cli.conventions import FORCE_HELP, fit_table
from uwbimu.cli.dataset_options import with_load_options

obs_app = typer.Typer(
    name="observability",
    help="Observability and identifiability: Lie-derivative rank test, time offset, per-window analysis of logs.",
    no_args_is_help=True,
    add_completion=False,
)


def _fail(msg: str) -> None:
    """A bad option value: one stderr line through the CLI wrapper, exit code 2."""
    from uwbimu.errors import UsageError

    raise UsageError(msg)


def _jsonable(obj):
    from uwbimu.io.atomic import to_plain

    return to_plain(obj, nonfinite=str)  # --json: NaN / inf as "nan" / "inf" text


@obs_app.command("structural")
def structural(
    config: Path = typer.Argument(..., help="Configuration YAML (see examples/observability/)"),
    as_json: bool = typer.Option(False, "--json", help="Print the verdict as JSON"),
) -> None:
    """Lie-derivative observability rank test of a configuration."""
    from uwbimu.observability.structural import structural_verdict

    console = Console()
    v = structural_verdict(config)  # a bad configuration: ConfigError, exit 2 (cli.main wrapper)
    if as_json:
        keys = ["rank", "dimension", "observable", "verdict", "lie_order", "singular_values", "unobservable_directions", "conditions"]
        extra = ["name", "model", "measurement", "search_verdict", "search_rank", "lie_order_setting", "order_search", "stop_reason",
                 "cross_check", "null_dimension_at_order", "removed_by_higher_orders", "tolerance", "cut",
                 "gap_decades", "margin_decades", "scale", "raw_rank", "raw_dimension", "words", "rows",
                 "state_names", "excitation", "n_points"]  # fmt: skip
        typer.echo(json.dumps(_jsonable({k: v[k] for k in keys + extra}), indent=2))
        return
    print_structural(console, v)


def print_structural(console: Console, v: dict) -> None:
    """Rich rendering of a :func:`structural_verdict` result."""
    ok = "[green]observable[/green]" if v["observable"] else f"[yellow]{v['verdict']}[/yellow]"
    order = f"Lie order {v['lie_order']}" + (" (auto)" if v["lie_order_setting"] == "auto" else "")
    console.print(
        f"[bold]{v['name']}[/bold] ({v['model']}{', TDoA' if v.get('measurement') == 'tdoa' else ''}, {order}, "
        f"{v['n_points']} point(s)): {ok} - "
        f"rank {v['rank']} / {v['dimension']} tangent dims"
        + (
            f" (quaternion as 4-vector: {v['raw_rank']} / {v['raw_dimension']})"
            if v["raw_rank"] is not None and v["model"] == "uwb_imu"
            else ""
        )
    )
    tol = "rounding-noise floor" if v["tolerance"] is None else f"relative tol {v['tolerance']:g}"
    margin = v["margin_decades"]
    console.print(
        f"evidence: gap {v['gap_decades']:.1f} decades; weakest kept singular value "
        f"{'n/a' if margin is None else f'{margin:.1f} decades'} above the cut ({tol}); states scaled by "
        f"L = {v['scale']['length_m']:.3g} m, T = {v['scale']['time_s']:g} s; order search "
        + ", ".join(f"{h['order']}:{h['rank']}" for h in v["order_search"])
        + f" ({v['stop_reason']})"
    )
    if margin is not None and margin < 3:
        console.print(
            "note: the weakest direction is less than 3 decades above the cut: the point is nearly degenerate "
            "(observable in theory, practically weak); see `uwbimu observability log` for the bound on a real log."
        )
    cc = v.get("cross_check")
    if cc is not None:
        console.print(
            f"trajectory test ({cc['horizon_s']:g} s, generic inputs): rank {cc['rank']} (gap {cc['gap_decades']:.1f} decades)"
            + ("" if cc["agree"] else " - higher than the Lie rank at the last order; the verdict uses it")
        )
    if v["lie_order_setting"] != "auto" and not v["observable"]:
        console.print(
            f"note: explicit Lie order {v['lie_order']}: the automatic search finds rank {v['search_rank']} / "
            f"{v['dimension']} ({v['search_verdict']}); {v['removed_by_higher_orders']} of the order-{v['lie_order']} "
            "null directions are removed by higher orders and not named."
        )
    t = Table(title="seed conditions (sufficient)")
    t.add_column("condition")
    t.add_column("holds")
    for k, c in v["conditions"].items():
        t.add_row(escape(k), ("yes" if c else "no") if isinstance(c, bool) else escape(str(c)))
    console.print(t)
    if v["unobservable_directions"]:
        t = Table(title="unobservable directions (weakest point)")
        t.add_column("#")
        t.add_column("direction")
        for i, d in enumerate(v["unobservable_directions"]):
            t.add_row(str(i), escape(d["name"]))
        console.print(t)


@obs_app.command("delay")
def delay(
    config: Path = typer.Argument(..., help="Configuration YAML (model uwb_imu)"),
    as_json: bool = typer.Option(False, "--json", help="Print the verdict as JSON"),
) -> None:
    """Time-offset identifiability (seed 001 Theorem 1, T1-T3) with a numeric check."""
    from uwbimu.observability.delay import delay_verdict

    console = Console()
    v = delay_verdict(config)  # a bad configuration: ConfigError, exit 2 (cli.main wrapper)
    if as_json:
        keys = ["identifiable", "conditions", "theorem1", "numeric", "first_order", "explanation", "basis", "agree",
                "n_points", "name", "measurement"]  # fmt: skip
        typer.echo(json.dumps(_jsonable({k: v[k] for k in keys}), indent=2))
        return
    ok = "[green]identifiable[/green]" if v["identifiable"] else "[yellow]NOT identifiable[/yellow]"
    console.print(f"[bold]{escape(str(v['name']))}[/bold]: t_d {ok} (basis: {escape(str(v['basis']))})")
    t = Table(title="Theorem 1")
    t.add_column("condition")
    t.add_column("holds")
    for k, c in v["conditions"].items():
        t.add_row(escape(k), "yes" if c else "no")
    t.add_row("T1 and (T2 or T3)", "yes" if v["theorem1"] else "no")
    console.print(t)
    t = Table(title=f"max |d range / d u(t_r - t_d)| at t_d = {v['numeric']['time_offset']:g} s")
    t.add_column("excited input")
    t.add_column("sensitivity", justify="right")
    for k, s in v["numeric"]["sensitivity"].items():
        t.add_row(escape(k), f"{s:.3e}")
    console.print(t)
    num = v["numeric"]
    power = "" if num["td_power"] is None else f", growing like t_d^{num['td_power']:g}"
    console.print(
        f"numeric check: the largest sensitivity over t_d in "
        f"{', '.join(f'{x:g}' for x in num['probe_time_offsets'])} s is "
        f"{num['probe_over_noise']:.3g} x the rounding noise of the range ({num['tolerance']:.2e} m per unit input)"
        f"{power}: the verdict does not depend on the configured t_d"
    )
    if v["explanation"]:
        console.print(f"note: {escape(str(v['explanation']))}.")
    if v["identifiable"] and not v["theorem1"]:
        # identifiable only through an effect the seed's first-order argument drops:
        # say how large it is so that nobody mistakes "identifiable" for "well determined"
        smax = max(v["numeric"]["sensitivity"].values(), default=0.0)
        console.print(
            f"note: Theorem 1's sufficient conditions do not hold; t_d is identifiable only through the "
            f"input-output sensitivity above (at most {smax:.2e} m per unit input at the weakest point). "
            "Compare it with the range noise; `uwbimu observability log` gives the Cramer-Rao bound on a real log."
        )


@obs_app.command("log")
@with_load_options
def log(
    dataset: Path = typer.Argument(..., help="Dataset folder"),
    window: float = typer.Option(20.0, "--window", help="Window length [s]"),
    out: Path = typer.Option(..., "--out", "-o", help="Output folder (observability.csv, observability.png)"),
    range_sigma: Optional[float] = typer.Option(None, "--range-sigma", help="Range sd [m] (default: dataset meta, else 0.1)"),
    no_imu_noise: bool = typer.Option(False, "--no-imu-noise", help="Ignore IMU noise (noise-free IMU)"),
    bound: str = typer.Option("pcrb", "--bound", help="Bound: pcrb (posterior CRB from the window-start prior, IMU noise as "
                              "process noise) or gramian (former approximate Gramian, no prior)"),
    excited_ratio: float = typer.Option(0.5, "--excited-sd-ratio", help="Excited when the window brings the bound to "
                                        "at most this fraction of the prior sd"),
    lever_sd: Optional[float] = typer.Option(None, "--lever-sd-threshold", help="Also require this lever-arm bound [m]"),
    td_sd: Optional[float] = typer.Option(None, "--td-sd-threshold", help="Also require this time-offset bound [s]"),
    trajectory: Optional[Path] = typer.Option(
        None, "--trajectory", help="Linearise about an estimator's states.csv (or its output folder) instead of the ground truth"
    ),
    force: bool = typer.Option(False, "--force", help=FORCE_HELP),
    load_options=None,
) -> None:
    """Per-window posterior Cramer-Rao bound, information gained and excitation flags of a log."""
    from uwbimu.io.atomic import write_csv, write_json
    from uwbimu.observability.window import (
        WindowOptions,
        plot_timeline,
        trajectory_from_states_csv,
        window_observability,
    )

    console = Console()
    if window <= 0:
        _fail(f"--window must be positive, got {window}")
    if bound not in ("pcrb", "gramian"):
        _fail(f"--bound must be pcrb or gramian, got {bound}")
    if not 0 < excited_ratio < 1:
        _fail(f"--excited-sd-ratio must be in (0, 1), got {excited_ratio}")
    csv_path, png_path = out / "observability.csv", out / "observability.png"
    from uwbimu.cli.dataset_options import load, print_load_warnings
    from uwbimu.errors import InputError

    ds = load(dataset, load_options)  # a refused dataset is an InputError (exit 1, file / line / column named)
    print_load_warnings(console, ds)
    traj = None
    if trajectory is not None:
        try:
            traj = trajectory_from_states_csv(trajectory)
        except InputError as e:
            raise InputError(str(e), hint="pass the states.csv of `uwbimu estimate` (or its output folder)") from None
    elif ds.groundtruth is None:
        raise InputError(
            f"{dataset}: no groundtruth table; pass --trajectory (an estimator's states.csv) to linearise about"
        )
    opts = WindowOptions(
        window=window, range_sigma=range_sigma, include_imu_noise=not no_imu_noise, bound=bound,
        excited_sd_ratio=excited_ratio, lever_sd_threshold=lever_sd, td_sd_threshold=td_sd,
    )  # fmt: skip
    from uwbimu.io.atomic import check_output_target, output_folder

    names = [csv_path.name, png_path.name, "observability_meta.json"]
    check_output_target(out, names, force=force, protect=[dataset])  # refused before any work (OutputError)
    from uwbimu.cli.compile_notice import ensure_compiled

    ensure_compiled(console, "window")  # a cold cache: one line, then its measured cost
    with console.status("computing per-window information"):
        table, meta = window_observability(ds, traj, options=opts)
    # outputs whole or not at all; sd columns may hold inf (--bound gramian: unbounded direction)
    with output_folder(out, force, protect=[dataset], names=names, finite=False) as tmp:
        write_csv(tmp / csv_path.name, table)
        write_json(tmp / "observability_meta.json", meta)
        plot_timeline(table, tmp / png_path.name, lever_sd, td_sd)  # dashed: absolute thresholds, if given
    if bound == "pcrb":
        need = 1.0 / excited_ratio**2 - 1.0
        console.print(
            "posterior Cramer-Rao bound at each window's end, windows chained from the prior sd "
            + ", ".join(f"{k} {v:g}" for k, v in opts.prior_sd.items())
            + f" (SI); excited = the window adds >= {need:g} x the prior's precision"
        )
    t = Table(title=escape(f"{dataset} - {len(table)} window(s) of {window:g} s"))
    for c in ("t_start", "t_end", "min eig", "cond", "weakest", "sd lever max (m)", "sd t_d (s)", "lever", "t_d"):
        t.add_column(c)
    for r in table.itertuples(index=False):
        sdl = max(r.sd_lx, r.sd_ly, r.sd_lz)
        t.add_row(
            f"{r.t_start:.1f}", f"{r.t_end:.1f}", f"{r.min_eigenvalue:.3g}", f"{r.condition_number:.3g}",
            escape(str(r.weakest_direction)[:40]), f"{sdl:.3g}", f"{r.sd_time_offset:.3g}",
            "ok" if r.lever_arm_excited else "[yellow]weak[/yellow]", "ok" if r.time_offset_excited else "[yellow]weak[/yellow]",
        )  # fmt: skip
    console.print(fit_table(console, t, fold=("weakest",)))
    dropped = meta["ranges_unknown_anchor"] + meta["ranges_outside_imu_span"] + meta["ranges_other_tags"]
    if dropped:
        console.print(
            f"[yellow]not used: {meta['ranges_unknown_anchor']} range(s) with an unknown anchor, "
            f"{meta['ranges_outside_imu_span']} outside the IMU span, "
            f"{meta['ranges_other_tags']} from other tags than the first[/yellow]"
        )
    res_med = meta["range_residual_median"]
    if res_med is not None and res_med > max(5 * meta["range_sigma"], 0.3):
        console.print(
            f"[yellow]warning: median |range - predicted range| along the trajectory is {res_med:.2f} m: "
            "the trajectory may not be in the anchors' frame (or the lever arm / anchors are off); "
            "the Jacobians are only as good as the trajectory[/yellow]"
        )
    console.print(escape(f"wrote {csv_path}, {png_path}"))


def register(app: typer.Typer) -> None:
    """Attach the ``observability`` sub-app to the main CLI."""
    app.add_typer(obs_app, name="observability")
