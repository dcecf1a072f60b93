"""The loader options every verb that reads a dataset offers (one definition, many verbs).

``@with_load_options`` adds ``--sort``, ``--drop-duplicates``, ``--gyro-units``,
``--accel-units``, ``--no-unit-check``, ``--lenient``, ``--split-clock-jumps``,
``--tdoa-margin``, ``--start`` and ``--end`` to a typer command and passes the verb one
:class:`uwbimu.io.loader.LoadOptions` as the keyword argument ``load_options``.
So a refusal's hint (``--sort`` ...) always names an option the verb has.
"""

from __future__ import annotations

import functools
import inspect
from typing import Any, Optional

import typer

GYRO_UNITS = {"rad": "rad/s", "rad/s": "rad/s", "deg": "deg/s", "deg/s": "deg/s"}
ACCEL_UNITS = {"m/s2": "m/s^2", "m/s^2": "m/s^2", "ms2": "m/s^2", "si": "m/s^2", "g": "g"}

_PARAMS = [
    ("drop_duplicates", bool, typer.Option(False, "--drop-duplicates",
                                           help="Drop rows that exactly repeat an earlier row (counted).")),
    ("sort", bool, typer.Option(False, "--sort", help="Sort rows by time when out of order (counted).")),
    ("gyro_units", str, typer.Option("rad", "--gyro-units", help="Unit of wx,wy,wz in the file: rad | deg.")),
    ("accel_units", str, typer.Option("m/s2", "--accel-units", help="Unit of ax,ay,az in the file: m/s2 | g.")),
    ("no_unit_check", bool, typer.Option(False, "--no-unit-check",
                                         help="Skip the deg/s and g plausibility checks.")),
    ("lenient", bool, typer.Option(False, "--lenient",
                                   help="Accept an IMU below 10 Hz and degenerate anchor geometry with a warning.")),
    ("split_clock_jumps", bool, typer.Option(False, "--split-clock-jumps",
                                             help="At a backward clock jump keep the longer monotonic part "
                                                  "(reported) instead of refusing.")),
    ("tdoa_margin", float, typer.Option(1.0, "--tdoa-margin",
                                        help="How far |tdoa| may exceed the anchors' separation [m].")),
    ("start", Optional[float], typer.Option(None, "--start",
                                            help="Use the log from this stamp [s] (IMU, UWB, TDoA; ground truth "
                                                 "kept whole); default: the estimators' flight detection.")),
    ("end", Optional[float], typer.Option(None, "--end", help="Use the log up to this stamp [s].")),
]
NAMES = [p[0] for p in _PARAMS]


def build_load_options(values: dict[str, Any]):
    """:class:`LoadOptions` from the CLI values; a bad unit is a :class:`uwbimu.errors.UsageError`."""
    from uwbimu.errors import UsageError
    from uwbimu.io.loader import LoadOptions

    gyro, accel = str(values["gyro_units"]).lower(), str(values["accel_units"]).lower()
    if gyro not in GYRO_UNITS:
        raise UsageError(f"--gyro-units must be rad or deg, got '{values['gyro_units']}'")
    if accel not in ACCEL_UNITS:
        raise UsageError(f"--accel-units must be m/s2 or g, got '{values['accel_units']}'")
    if not values["tdoa_margin"] >= 0:
        raise UsageError(f"--tdoa-margin must be >= 0 m, got '{values['tdoa_margin']}'")
    return LoadOptions(drop_duplicate_rows=values["drop_duplicates"], sort=values["sort"],
                       gyro_units=GYRO_UNITS[gyro], accel_units=ACCEL_UNITS[accel],
                       check_units=not values["no_unit_check"], lenient=values["lenient"],
                       clock_jumps="split" if values["split_clock_jumps"] else "refuse",
                       tdoa_margin=float(values["tdoa_margin"]), start=values["start"], end=values["end"])


def with_load_options(func):
    """Add the shared loader options to a typer command; it receives ``load_options=LoadOptions``."""
    sig = inspect.signature(func)
    params = [p for p in sig.parameters.values() if p.name != "load_options"]
    params += [inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=default, annotation=ann)
               for name, ann, default in _PARAMS]

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        values = {n: kwargs.pop(n) for n in NAMES}
        return func(*args, load_options=build_load_options(values), **kwargs)

    wrapper.__signature__ = sig.replace(parameters=params)
    return wrapper


def print_load_warnings(console, ds) -> None:
    """Print the loader's repairs and structured warnings (``ds.report``) on ``console``."""
    rep = getattr(ds, "report", None)
    if rep is None:
        return
    from rich.markup import escape  # messages carry units in brackets ("[s]", "[m]") that rich reads as markup

    for a in rep.actions:
        console.print(f"[yellow]repair:[/yellow] {escape(str(a))}", soft_wrap=True)
    for w in rep.warnings:
        console.print(f"[yellow]warning ({escape(str(w['code']))}):[/yellow] {escape(str(w['file']))}: "
                      f"{escape(str(w['message']))}", soft_wrap=True)


def load(path, load_options):
    """Load a dataset quietly (repairs and warnings are in ``ds.report``, printed by the verb)."""
    import warnings

    from uwbimu.io.loader import load_dataset

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_dataset(path, load_options)


SMOOTH_HELP = ("Forward-backward smoothing (default): a second filter pass over the time-reversed log fused with "
               "the first (trajectory from the data before and after each stamp; lever arm and t_d the mean of "
               "both passes, half their difference in the sd). --no-smooth: the causal filter alone, as a robot "
               "runs it online. A --config that sets smoother decides when neither is given.")


def offline_smoothing(opts, smooth: Optional[bool]):
    """ESKF options of a verb that reads a whole log: ``smoother = forward_backward`` unless ``smooth`` is
    False, or None with a config that set ``smoother`` itself (the library's default is the causal filter)."""
    if smooth is None:
        if "smoother" in opts.model_fields_set:
            return opts
        smooth = True
    return opts.model_copy(update={"smoother": "forward_backward" if smooth else "off"})


def estimator_options(estimator: str, config, preset):
    """Estimator options from ``--config`` YAML or ``--preset`` NAME (defaults when neither)."""
    from uwbimu.errors import UsageError, UwbimuError

    if config is not None and preset is not None:
        raise UsageError("give --config or --preset, not both (copy the preset into your YAML to change it)")
    try:
        if estimator == "pointmass":
            from uwbimu.estimation.pointmass import PointMassOptions
            from uwbimu.io.yamlconfig import load_yaml_model

            if preset is not None:
                raise UsageError("--preset applies to the eskf estimator only")
            return (load_yaml_model(config, PointMassOptions, what="point-mass options")
                    if config is not None else PointMassOptions())
        from uwbimu.estimation import EskfOptions

        if preset is not None:
            try:
                from uwbimu.estimation.presets import load_preset
            except ImportError:
                raise UsageError("--preset is not available in this installation (uwbimu.estimation.presets "
                                 "is missing); use --config examples/estimator*.yaml") from None
            try:
                return load_preset(preset)
            except (KeyError, ValueError, FileNotFoundError) as exc:
                raise UsageError(f"--preset {preset}: {' '.join(str(exc).split())}") from None
        return EskfOptions.from_yaml(config) if config is not None else EskfOptions()
    except UwbimuError:
        raise  # ConfigError (exit 2) names the file, line and field
    except (OSError, ValueError) as exc:
        raise UsageError(f"--config {config}: {exc}") from None


def apply_dataset_properties(opts, ds, console=None):
    """Apply the dataset's own properties to estimator options the user did not set explicitly.

    Today: ``dataset.yaml``'s ``anchor_frame_up`` (known anchor biases and tag lever arms are
    applied by the estimator itself).  Returns the (possibly updated) options.
    """
    frame = getattr(ds, "anchor_frame_up", "+z")
    if hasattr(opts, "anchor_frame_up") and "anchor_frame_up" not in opts.model_fields_set \
            and opts.anchor_frame_up != frame:
        opts = opts.model_copy(update={"anchor_frame_up": frame})
        if console is not None:
            console.print(f"note: anchor_frame_up {frame} from the dataset's dataset.yaml")
    return opts
