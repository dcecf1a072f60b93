"""The ``uwbimu`` command line.

Each verb lives in its own module under :mod:`uwbimu.cli` and registers
itself on :data:`app` through a ``register(app)`` function; this file only
lists them, so ``uwbimu --help`` shows every verb with a one-line summary.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import gc
import os
import sys

import typer
from typer.core import TyperOption


def _flag_type_hidden(display_type_rich):
    """Typer >= 0.2x prints a ``<bool>`` type column for on/off flags; a flag takes no value."""

    @functools.wraps(display_type_rich)
    def wrapper(self, ctx):
        return None if self.is_flag else display_type_rich(self, ctx)

    return wrapper


def _help_is_plain_text(make_rich_text):
    """Help texts are plain text, not rich markup.

    In typer's "rich" markup mode every help text (command docstrings, option and argument
    help) goes through ``rich.Text.from_markup``, which reads a unit such as ``[s]``, ``[m]``
    or ``[deg/s]`` as a style tag and drops it ("Window length [s]" printed "Window length").
    No uwbimu help uses markup, so the text is escaped on its way in; the panels, the
    highlighting and the "[default: ...]" / "[required]" texts typer adds are unchanged.
    ``tests/test_cli_help_units.py`` renders every verb's help and checks every bracket.
    """
    from rich.markup import escape

    @functools.wraps(make_rich_text)
    def wrapper(*, text: str, markup_mode, **kwargs):
        if markup_mode == "rich":
            text = escape(text)
        return make_rich_text(text=text, markup_mode=markup_mode, **kwargs)

    return wrapper


def _patch_rich_utils(module) -> None:
    module._make_rich_text = _help_is_plain_text(module._make_rich_text)


class _OnRichUtilsImport:
    """Meta-path finder that applies :func:`_help_is_plain_text` when typer first imports ``typer.rich_utils``.

    typer imports its rich helpers only to print help or an error; importing them here costs about 0.2 s
    of CPU (rich.markdown, markdown_it, pygments) on every command, ``uwbimu estimate`` included.  So the
    patch waits for typer's own import of the module (the same patch, applied before any of its functions
    runs).
    """

    name = "typer.rich_utils"

    def find_spec(self, fullname, path=None, target=None):
        if fullname != self.name:
            return None
        from importlib.machinery import PathFinder

        spec = PathFinder.find_spec(fullname, path)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return None  # the usual finders import it; :func:`_patch_typer` saw no such module
        inner = spec.loader.exec_module

        def exec_module(module):
            inner(module)
            _patch_rich_utils(module)

        spec.loader.exec_module = exec_module
        return spec


def _patch_typer() -> None:
    """CLI-only presentation tweaks (the library never touches typer)."""
    TyperOption.display_type_rich = _flag_type_hidden(TyperOption.display_type_rich)
    if _OnRichUtilsImport.name in sys.modules:
        _patch_rich_utils(sys.modules[_OnRichUtilsImport.name])
    elif not any(isinstance(f, _OnRichUtilsImport) for f in sys.meta_path):
        sys.meta_path.insert(0, _OnRichUtilsImport())


_patch_typer()

app = typer.Typer(
    name="uwbimu",
    help="UWB-aided inertial localization: simulate, check, estimate, analyse observability, design.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)


def _print_version(value: bool) -> None:
    if value:
        from uwbimu import __version__

        print(f"uwbimu {__version__}")
        raise typer.Exit()


@app.callback()
def _root(
    version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                 help="Print the uwbimu version and exit."),
) -> None:
    """UWB-aided inertial localization: simulate, check, estimate, analyse observability, design."""

# One line per verb module (keep sorted by workflow order).
from uwbimu.cli import demo as _demo  # noqa: E402

_demo.register(app)
from uwbimu.cli import simulate as _simulate; _simulate.register(app)  # noqa: E402,E702
from uwbimu.cli import check as _check, import_cmd as _import_cmd  # noqa: E402

_check.register(app)
_import_cmd.register(app)
from uwbimu.cli import evaluate as _evaluate, report as _report  # noqa: E402

_evaluate.register(app)
_report.register(app)
from uwbimu.cli import plan as _plan  # noqa: E402

_plan.register(app)
from uwbimu.cli import observability as _observability; _observability.register(app)  # noqa: E402,E702
from uwbimu.cli import estimate as _estimate; _estimate.register(app)  # noqa: E402,E702
from uwbimu.cli import montecarlo as _montecarlo; _montecarlo.register(app)  # noqa: E402,E702
from uwbimu.cli import place as _place; _place.register(app)  # noqa: E402,E702
from uwbimu.cli import calibrate as _calibrate; _calibrate.register(app)  # noqa: E402,E702


#: Set to 1 to let unexpected exceptions show their traceback (for bug reports).
TRACEBACK_ENV = "UWBIMU_TRACEBACK"
#: Exit code of an unexpected internal error (a bug: please report it).
INTERNAL_ERROR_EXIT = 70


def report_error(exc: BaseException) -> int:
    """Print an error as one line on stderr (plus a hint line) and return its exit code."""
    from uwbimu.errors import ConfigError, UwbimuError

    text = " ".join(str(exc).split()) or type(exc).__name__
    if isinstance(exc, UwbimuError):
        label = {1: "refused", 2: "usage error", 3: "flagged", 4: "output refused", 5: "estimation failed"}
        what = "invalid configuration" if isinstance(exc, ConfigError) else label.get(exc.exit_code, "error")
        print(f"uwbimu: {what}: {text}", file=sys.stderr)
        if exc.hint:
            print(f"hint: {exc.hint}", file=sys.stderr)
        return exc.exit_code
    if isinstance(exc, PermissionError):
        print(f"uwbimu: output refused: {text}", file=sys.stderr)
        print("hint: choose a writable output folder", file=sys.stderr)
        return 4
    print(f"uwbimu: internal error ({type(exc).__name__}): {text}", file=sys.stderr)
    print(f"hint: this is a bug; rerun with {TRACEBACK_ENV}=1 and report the traceback", file=sys.stderr)
    return INTERNAL_ERROR_EXIT


#: Allocations between two young-generation collections of the cyclic garbage collector while a verb runs
#: (Python's default is 700).  A 10-minute ``uwbimu estimate`` made about 600 collections (0.4 s of CPU, most in
#: the numba dispatchers' cache loads and the option models); at 10 000 it makes about 40 (0.15 s).  Only when
#: collections happen changes, nothing else; the previous thresholds are restored after the verb.
GC_YOUNG_THRESHOLD = 10_000


@contextlib.contextmanager
def _fewer_collections():
    old = gc.get_threshold()
    gc.set_threshold(max(old[0], GC_YOUNG_THRESHOLD), *old[1:])
    try:
        yield
    finally:
        gc.set_threshold(*old)


def _freeze_at_exit() -> None:
    """At interpreter exit, move every object to the collector's permanent generation: the collections of
    Python's finalisation then skip them (0.5-0.6 s of CPU at the end of a 10-minute ``uwbimu estimate``, its
    ~200 000 tracked objects walked again for garbage that the exiting process frees anyway).  The outputs are
    written and closed before; ``atexit`` handlers registered after this one (thread pools, multiprocessing,
    weakref finalizers) still run first."""
    gc.freeze()


atexit.register(_freeze_at_exit)


def guarded(func):
    """Wrap a verb so that every error ends as one stderr line and its exit code, never a traceback; the verb runs
    with fewer garbage collections (:data:`GC_YOUNG_THRESHOLD`)."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        try:
            with _fewer_collections():
                return func(*args, **kwargs)
        except (typer.Exit, typer.Abort, SystemExit, KeyboardInterrupt):
            raise
        except Exception as exc:  # noqa: BLE001 - the one place that turns errors into exit codes
            import click

            if isinstance(exc, click.exceptions.ClickException):
                raise
            if os.environ.get(TRACEBACK_ENV) == "1":
                raise
            raise typer.Exit(code=report_error(exc)) from None

    wrapper._uwbimu_guarded = True
    return wrapper


def _guard_all(typer_app: typer.Typer) -> None:
    for cmd in typer_app.registered_commands:
        if cmd.callback is not None and not getattr(cmd.callback, "_uwbimu_guarded", False):
            cmd.callback = guarded(cmd.callback)
    for group in typer_app.registered_groups:
        if group.typer_instance is not None:
            _guard_all(group.typer_instance)


_guard_all(app)


def main() -> None:  # pragma: no cover - entry point
    app()
