"""The ``uwbimu`` command line.

Each verb lives in its own module under :mod:`uwbimu.cli` and registers
itself on :data:`app` through a ``register(app)`` function; this file only
lists them, so ``uwbimu --help`` shows every verb with a one-line summary.
"""

from __future__ import annotations

import typer

app = typer.Typer(
    name="uwbimu",
    help="UWB-aided inertial localization: simulate, check, estimate, analyse observability, design.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_show_locals=False,
)

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


def main() -> None:  # pragma: no cover - entry point
    app()
