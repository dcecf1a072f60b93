"""``uwbimu simulate``: simulate a scenario (YAML file or built-in name) into a dataset folder."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

from rich.markup import escape
import typer

from uwbimu.cli.conventions import FORCE_HELP
from rich.console import Console
from rich.table import Table


def _scenario_table(console: Console) -> None:
    from uwbimu.sim import builtin_scenario, list_scenarios

    table = Table(title="Built-in scenarios (uwbimu simulate NAME --out DIR)")
    table.add_column("name", style="bold")
    table.add_column("trajectory")
    table.add_column(r"duration \[s]", justify="right")
    table.add_column("description")
    for name, desc in list_scenarios().items():
        sc = builtin_scenario(name)
        table.add_row(name, sc.trajectory.type, f"{sc.duration:g}", escape(desc))
    console.print(table)


def _summary(console: Console, ds, out: Path, seconds: float) -> None:
    table = Table(title=escape(f"Simulated {ds.meta.name} -> {out}"))
    table.add_column("quantity")
    table.add_column("value", justify="right")
    extra = ds.meta.extra
    counts = extra.get("uwb_counts", {})
    table.add_row(r"duration \[s]", f"{extra.get('duration', ds.duration):g}")
    table.add_row("IMU samples", f"{len(ds.imu)} @ {ds.meta.imu_rate_hz:g} Hz")
    lost = {k: v for k, v in counts.items() if k.startswith("dropped_") and v}
    if "packets_scheduled" in counts:  # TDoA (uwbimu.sim.tdoa): packets, then differences
        table.add_row("TDoA packets received / scheduled", f"{counts['packets_received']} / {counts['packets_scheduled']}")
        table.add_row("packets lost", ", ".join(f"{k[8:]} {v}" for k, v in lost.items()) or "0")
        table.add_row("NLOS packets", str(counts.get("packets_nlos", 0)))
        table.add_row("TDoA differences emitted", str(counts.get("emitted", 0)))
    else:
        table.add_row("ranges emitted / scheduled", f"{counts.get('emitted', len(ds.uwb))} / {counts.get('scheduled', '?')}")
        table.add_row("ranges lost", ", ".join(f"{k[8:]} {v}" for k, v in lost.items()) or "0")
        table.add_row("NLOS ranges", str(counts.get("nlos", 0)))
    for k, v in extra.get("imu_saturation", {}).items():
        table.add_row(f"IMU {k.replace('_', ' ')}", str(v))
    truth = ds.meta.truth
    table.add_row("anchors", str(len(ds.anchors)))
    table.add_row(r"true lever arm \[m]", str([round(x, 4) for x in truth.lever_arm]))
    table.add_row(r"true time offset \[s]", f"{truth.time_offset:g}")
    table.add_row(r"wall time \[s]", f"{seconds:.2f}")
    console.print(table)


def register(app: typer.Typer) -> None:
    @app.command("simulate")
    def simulate_cmd(
        scenario: Optional[str] = typer.Argument(None, help="Scenario YAML file, or a built-in name (see --list)"),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output dataset folder"),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        list_: bool = typer.Option(False, "--list", help="List the built-in scenarios and exit"),
        fmt: str = typer.Option("csv", "--format", help="Table format: csv or parquet"),
    ) -> None:
        """Simulate a UWB-IMU flight (scenario YAML or built-in) into a dataset folder."""
        from uwbimu.io.dataset import write_dataset
        from uwbimu.errors import UsageError
        from uwbimu.sim import builtin_scenario, list_scenarios, load_scenario
        from uwbimu.sim.simulate import simulate

        console = Console()
        err = Console(stderr=True)
        if list_:
            _scenario_table(console)
            return
        if scenario is None or out is None:
            raise UsageError("give a SCENARIO (YAML file or built-in name) and --out DIR, or --list")
        if fmt not in ("csv", "parquet"):
            raise UsageError(f"--format must be csv or parquet, got '{fmt}'")
        from uwbimu.io.atomic import check_output_target, output_folder

        path = Path(scenario)
        protect = [path] if path.is_file() else []
        check_output_target(out, force=force, protect=protect, replace=True)
        if path.suffix.lower() in (".yaml", ".yml") or path.is_file():
            sc = load_scenario(path)  # ScenarioError (exit 2) / TrajectoryFileError (exit 1) name file and field
        elif scenario in list_scenarios():
            sc = builtin_scenario(scenario)
        else:
            raise UsageError(f"'{scenario}' is neither a scenario file nor a built-in name; "
                             f"built-ins: {', '.join(list_scenarios())}")

        from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

        t0 = time.perf_counter()
        with Progress(
            TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=err, transient=True
        ) as bar:
            task = bar.add_task(f"simulating {sc.name}", total=1.0)

            def progress(stage: str, frac: float) -> None:
                bar.update(task, completed=frac, description=f"simulating {sc.name}: {stage}")

            ds = simulate(sc, progress=progress)
            bar.update(task, description=f"writing {out}")
            with output_folder(out, force=force, protect=protect, replace=True) as tmp:
                write_dataset(ds, tmp, overwrite=True, fmt=fmt)
        _summary(console, ds, out, time.perf_counter() - t0)
