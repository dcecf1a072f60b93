"""``uwbimu import``: convert third-party recordings into the dataset format.

Each importer is one subcommand of :data:`import_app`, added by a small
``_register_<name>(app)`` function below.  A new importer (say
``uwbimu.io.importers.rosbag``) needs one such function, or can register
itself from its own CLI module::

    from uwbimu.cli.import_cmd import import_app, run_import

    @import_app.command("rosbag")
    def rosbag(src: Path, dst: Path, force: bool = False) -> None:
        \"\"\"Convert a ROS bag ...\"\"\"
        from uwbimu.io.importers import rosbag as imp
        run_import(lambda: imp.import_dataset(src, dst, force=force))
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Optional

import typer

from uwbimu.cli.conventions import FORCE_HELP

import_app = typer.Typer(
    name="import",
    help="Convert third-party recordings (INRoL, ...) into the uwbimu dataset format.",
    no_args_is_help=True,
)


def _destination(dst: Optional[Path], out: Optional[Path]) -> Path:
    """The output folder, given as DST or as -o/--out (exactly one)."""
    from uwbimu.errors import UsageError

    if (dst is None) == (out is None):
        raise UsageError("give the output dataset folder once: as DST or with -o/--out")
    return dst if dst is not None else out


def run_import(do_import: Callable[..., object], with_progress: bool = False, dst: Optional[Path] = None,
               src: Optional[Path] = None, force: bool = False) -> None:
    """Run an importer call, print what it changed and where it wrote; exit 1 on a refusal.

    With ``dst`` (and ``src``, ``force``) the destination is checked before any work
    (writable, not the source, not a non-empty folder unless ``force``).

    ``do_import`` returns an :class:`uwbimu.io.importers.ImportResult`.  With
    ``with_progress`` it is called as ``do_import(progress)`` where
    ``progress(stage, fraction)`` drives a progress bar; otherwise as
    ``do_import()`` under a spinner.
    """
    from rich.console import Console
    from rich.markup import escape
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from uwbimu.errors import OutputError
    from uwbimu.io.atomic import check_output_target

    console = Console()
    if dst is not None:
        check_output_target(dst, force=force, protect=[src] if src is not None else [], replace=True)
    try:
        if with_progress:
            with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(),
                          console=console, transient=True) as bar:
                task = bar.add_task("converting", total=1.0)
                result = do_import(lambda stage, frac: bar.update(task, completed=frac,
                                                                  description=f"converting: {escape(stage)}"))
        else:
            with console.status("converting..."):
                result = do_import()
    except FileExistsError as exc:
        raise OutputError(str(exc), hint="use --force or another destination") from None
    ds = result.dataset
    for c in result.changes:
        # messages hold units in brackets ("[ms]", "[deg/s]") that rich would take for markup
        console.print(f"[yellow]changed:[/yellow] {escape(c)}", soft_wrap=True)
    n = {k: len(getattr(ds, k)) for k in ("imu", "uwb", "anchors")}
    if ds.groundtruth is not None:
        n["groundtruth"] = len(ds.groundtruth)
    if getattr(ds, "tdoa", None) is not None:
        n["tdoa"] = len(ds.tdoa)
    console.print(escape(f"wrote {result.path}: " + ", ".join(f"{k} {v} rows" for k, v in n.items())
                         + f"; run `uwbimu check {result.path}` to inspect it"), soft_wrap=True)


_TDOA_MARGIN_HELP = ("TDoA rows whose |tdoa| exceeds the two anchors' separation by more than this [m] are "
                     "dropped and counted per anchor pair (default 1.0, the loader's bound).")
_QUAT_ORDER_HELP = ("Order of an_quat in an anchor survey: auto (by the file's version: anchor_MMDD of 2021 "
                    "holds qw,qx,qy,qz; the released anchor_constN holds qx,qy,qz,qw), wxyz or xyzw.")


def _check_import_options(tdoa_margin: float, quat_order: str) -> str:
    """Refuse a negative margin or an unknown quaternion order (UsageError); the order in lower case."""
    from uwbimu.errors import UsageError
    from uwbimu.io.importers.anchors import QUAT_ORDERS

    if not tdoa_margin >= 0:
        raise UsageError(f"--tdoa-margin must be >= 0 m, got '{tdoa_margin}'")
    if quat_order.lower() not in QUAT_ORDERS:
        raise UsageError(f"--survey-quat-order must be one of {', '.join(QUAT_ORDERS)}, got '{quat_order}'")
    return quat_order.lower()


def _register_inrol(app: typer.Typer) -> None:
    @app.command("inrol")
    def inrol(
        src: Path = typer.Argument(..., help="INRoL parsed_dataset folder (imu.txt, uwb.txt, anchor.txt, "
                                             "imu_pose.txt, LICENSE)."),
        dst: Optional[Path] = typer.Argument(None, help="Output dataset folder (or give it with -o/--out)."),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output dataset folder (instead of DST)."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        name: Optional[str] = typer.Option(None, "--name", help="Dataset name (default from SRC)."),
    ) -> None:
        """Convert an INRoL UWB-IMU sequence (GPL-3.0 data; LICENSE and attribution are copied)."""
        dst = _destination(dst, out)
        from uwbimu.io.importers import inrol as imp

        run_import(lambda progress: imp.import_dataset(src, dst, force=force, name=name, progress=progress),
                   with_progress=True, dst=dst, src=src, force=force)


def _register_isas_walk(app: typer.Typer) -> None:
    @app.command("isas-walk")
    def isas_walk(
        src: Path = typer.Argument(..., help="ISAS-Walk CSV folder (imu.csv, uwb_ranges.csv, anchors.csv, "
                                             "groundtruth_vive.csv, LICENSE)."),
        dst: Optional[Path] = typer.Argument(None, help="Output dataset folder (or give it with -o/--out)."),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output dataset folder (instead of DST)."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        no_groundtruth: bool = typer.Option(False, "--no-groundtruth", help="Do not import the Vive ground truth."),
    ) -> None:
        """Convert an ISAS-Walk (SFUISE) sequence: fresh ranges only, documented anchor offsets as known biases."""
        dst = _destination(dst, out)
        from uwbimu.io.importers import isas_walk as imp

        run_import(lambda: imp.import_dataset(src, dst, force=force, with_groundtruth=not no_groundtruth),
                   dst=dst, src=src, force=force)


def _register_rosbag(app: typer.Typer) -> None:
    @app.command("rosbag")
    def rosbag(
        bag: Path = typer.Argument(..., help="ROS 1 .bag file or ROS 2 bag folder."),
        dst: Optional[Path] = typer.Argument(None, help="Output dataset folder (or give it with -o/--out)."),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output dataset folder (instead of DST)."),
        topics: Path = typer.Option(..., "--topics", help="Mapping YAML: imu/ranges topics, fields, anchors file."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
    ) -> None:
        """Convert a ROS 1 or ROS 2 bag (sensor_msgs/Imu + a configurable range message) with a mapping YAML."""
        dst = _destination(dst, out)
        from uwbimu.io.importers import rosbag as imp

        run_import(lambda: imp.import_dataset(bag, dst, topics, force=force), dst=dst, src=bag, force=force)


def _register_util(app: typer.Typer) -> None:
    @app.command("util")
    def util(
        src: Path = typer.Argument(..., help="UTIL flight CSV, e.g. csv-data/const1/const1-trial1-tdoa2.csv."),
        dst: Optional[Path] = typer.Argument(None, help="Output dataset folder (or give it with -o/--out)."),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output dataset folder (instead of DST)."),
        anchors: Optional[Path] = typer.Option(None, "--anchors", help="Anchor survey (anchor_constN.npz or "
                                               "_survey.txt); default: survey-results/anchor_constN.* found "
                                               "next to or above SRC."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        name: Optional[str] = typer.Option(None, "--name", help="Dataset name (default from SRC)."),
        tdoa_margin: float = typer.Option(1.0, "--tdoa-margin", help=_TDOA_MARGIN_HELP),
        quat_order: str = typer.Option("auto", "--survey-quat-order", help=_QUAT_ORDER_HELP),
    ) -> None:
        """Convert a UTIL (Zhao et al.) TDoA flight: TDoA, IMU (g, deg/s converted), Vicon pose, anchor survey."""
        dst = _destination(dst, out)
        order = _check_import_options(tdoa_margin, quat_order)
        from uwbimu.io.importers import util as imp

        run_import(lambda: imp.import_dataset(src, dst, anchors, force=force, name=name, tdoa_margin=tdoa_margin,
                                              quat_order=order), dst=dst, src=src, force=force)


def _register_cf_usdlog(app: typer.Typer) -> None:
    @app.command("cf-usdlog")
    def cf_usdlog(
        log: Path = typer.Argument(..., help="Crazyflie uSD-card event log (binary, e.g. log00)."),
        dst: Optional[Path] = typer.Argument(None, help="Output dataset folder (or give it with -o/--out)."),
        out: Optional[Path] = typer.Option(None, "--out", "-o", help="Output dataset folder (instead of DST)."),
        anchors: Path = typer.Option(..., "--anchors", help="Anchor positions: anchors.csv (anchor, x, y, z [, qw, qx, "
                                                            "qy, qz]; ids as the Loco nodes', 0-7) or a UTIL survey "
                                                            "(.npz with an_pos/an_quat, or _survey.txt)."),
        force: bool = typer.Option(False, "--force", help=FORCE_HELP),
        ignore_crc: bool = typer.Option(False, "--ignore-crc", help="Decode a log whose CRC does not match "
                                                                    "(e.g. cut by a power loss); recorded."),
        name: Optional[str] = typer.Option(None, "--name", help="Dataset name (default from LOG)."),
        tdoa_margin: float = typer.Option(1.0, "--tdoa-margin", help=_TDOA_MARGIN_HELP),
        quat_order: str = typer.Option("auto", "--survey-quat-order", help=_QUAT_ORDER_HELP),
        lever_arm: Optional[tuple[float, float, float]] = typer.Option(
            None, "--lever-arm", help="The tag's nominal lever arm X Y Z [m, IMU frame] written to dataset.yaml "
                                      "(default: the UTIL platform's documented offset, -0.01245 0.00127 0.0908)."),
        no_lever_arm: bool = typer.Option(False, "--no-lever-arm", help="Write no nominal lever arm (another "
                                                                        "vehicle whose offset is not known)."),
    ) -> None:
        """Convert a Crazyflie uSD event log (estTDOA, estAcceleration in g, estGyroscope in deg/s) to a TDoA dataset."""
        dst = _destination(dst, out)
        order = _check_import_options(tdoa_margin, quat_order)
        from uwbimu.io.importers import cf_usdlog as imp

        from uwbimu.errors import UsageError

        if no_lever_arm and lever_arm is not None:
            raise UsageError("give --lever-arm or --no-lever-arm, not both")
        lever = None if no_lever_arm else (list(lever_arm) if lever_arm is not None else imp.UTIL_T_UV)
        run_import(lambda: imp.import_dataset(log, dst, anchors, force=force, ignore_crc=ignore_crc, name=name,
                                              tdoa_margin=tdoa_margin, quat_order=order, lever_arm=lever),
                   dst=dst, src=log, force=force)


# One line per importer.
_register_inrol(import_app)
_register_isas_walk(import_app)
_register_rosbag(import_app)
_register_util(import_app)
_register_cf_usdlog(import_app)


def register(app: typer.Typer) -> None:
    app.add_typer(import_app, name="import")
