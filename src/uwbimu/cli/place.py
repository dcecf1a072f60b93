"""``uwbimu place``: anchor placement designer (room or structure)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from uwbimu.cli.conventions import FORCE_HELP


def _print_result(console: Console, res: dict) -> None:
    # numbers never break (one word each); headers wrap, so the table fits 80 columns
    meas = " (TDoA PDOP)" if res.get("measurement") == "tdoa" else ""
    t = Table(title="layouts compared" + meas if res["mode"] == "room" else f"{res.get('structure')}: coverage",
              collapse_padding=True)
    if res["mode"] == "room":
        t.add_column("layout", overflow="fold", min_width=21)
        for c in ("N", "cov. %", "PDOP p50", "PDOP p95", "N-1 p95", "out of hull %"):
            t.add_column(c)
        for r in res["table"]:
            n1 = r.get("n1_pdop_p95")
            hull = r.get("hull_outside")
            t.add_row(escape(r["layout"]), str(r["anchors"]), f"{100 * r['coverage']:.1f}", f"{r['pdop_p50']:.3f}",
                      f"{r['pdop_p95']:.3f}", "-" if n1 is None else f"{n1:.3f}",
                      "-" if hull is None else f"{100 * hull:.1f}")
    else:
        t.add_column("layout", overflow="fold")
        for c in ("N", "vars", "cov. %", "geo. %", "s"):
            t.add_column(c, no_wrap=True)
        for r in res["table"]:
            geo = r.get("geometric_coverage")
            t.add_row(escape(r["layout"]), str(r["anchors"]), str(r.get("variables", "-")), f"{100 * r['coverage']:.2f}",
                      "-" if geo is None else f"{100 * geo:.2f}", f"{r['seconds']:.1f}" if "seconds" in r else "-")
    console.print(t)
    if res["mode"] == "room":
        console.print(f"objective: {escape(res.get('objective_name', ''))}")
    elif "note" in res.get("radio", {}):
        console.print(escape(res["radio"]["note"]))
    wsf = res["worst_single_failure"]
    console.print(f"coverage {100 * res['coverage']:.2f} % (geometric, also PDOP <= 5: {100 * res['geometric_coverage']:.2f} %), "
                  f"PDOP p50 {res['pdop_p50']:.3f}, p95 {res['pdop_p95']:.3f}; "
                  f"worst single failure: {wsf.get('anchor')} -> coverage {100 * wsf.get('coverage', float('nan')):.2f} %, "
                  f"PDOP p95 {wsf.get('pdop_p95', float('nan')):.3f}")
    for w in res["lint"]:
        colour = "yellow" if w["severity"] == "warning" else "cyan"
        console.print(f"[{colour}]{w['severity']}[/{colour}] {escape('[' + w['code'] + ']')} {escape(w['message'])}")


def register(app: typer.Typer) -> None:
    @app.command("place")
    def place(
        config: Optional[Path] = typer.Argument(None, help="Placement YAML (see docs/placement.md)."),
        out: Path = typer.Option(..., "--out", "-o", help="Output folder."),
        example: Optional[str] = typer.Option(None, "--example", help="Built-in example: room, crane or bridge."),
        seed: Optional[int] = typer.Option(None, "--seed", help="Override the config's random seed."),
        workers: Optional[int] = typer.Option(None, "--workers", help="Processes for differential evolution."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        no_plots: bool = typer.Option(False, "--no-plots", help="Skip the PNG plots."),
    ) -> None:
        """Design UWB anchor positions (room or structure) for coverage, PDOP and N-1 robustness."""
        from uwbimu.design.config import load_config
        from uwbimu.design.run import EXAMPLES, builtin_example, run_placement, write_outputs
        from pydantic import ValidationError

        from uwbimu import errors

        console = Console()
        if (config is None) == (example is None):
            raise errors.UsageError("give either CONFIG.yaml or --example room|crane|bridge (exactly one)")
        names = ("placement.json", "anchors.csv", "anchors_scenario.yaml", "anchors_3d.png", "coverage_map.png",
                 "pdop_slices.png", "marginal_value.png", "seed_layout.png")
        from uwbimu.io.atomic import check_output_target, record_outputs

        # the output rule: our own unchanged earlier outputs are replaced, anything else needs --force
        # (e.g. --out pointing at a dataset folder with its own anchors.csv)
        check_output_target(out, names, force)
        try:
            if example is not None:
                if example not in EXAMPLES:
                    raise errors.UsageError(f"unknown example '{example}'; choose one of {', '.join(sorted(EXAMPLES))}")
                cfg = builtin_example(example)
            else:
                cfg = load_config(config)
            upd = {}
            if seed is not None:
                upd["seed"] = seed
            if upd:
                cfg = cfg.model_copy(update=upd)
            if workers is not None:
                cfg.optimizer.workers = workers
            res = run_placement(cfg, progress=True)
            record_outputs(out, write_outputs(res, out, plots=not no_plots))
        except errors.UwbimuError:
            raise
        except ValidationError as exc:
            # a value set on the loaded configuration (--seed, --workers) that it refuses
            where = "" if config is None else f"{config}: "
            raise errors.ConfigError(where + " ".join(str(exc).split())) from None
        _print_result(console, res)
        console.print(escape(f"wrote {out / 'placement.json'}, {out / 'anchors.csv'}" + ("" if no_plots else " and plots")))
