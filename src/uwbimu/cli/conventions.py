"""Shared option texts of the ``uwbimu`` verbs (one wording, one meaning everywhere).

* ``-o/--out DIR``: the output folder of a verb (created if missing; outputs written whole or not
  at all through :func:`uwbimu.io.atomic.output_folder`).

The output rule (the same for every verb that writes, documented here once)
---------------------------------------------------------------------------
uwbimu records what it writes into a folder in ``.uwbimu-outputs.json`` (file -> sha256).

* A verb may replace a file of its outputs only when uwbimu wrote it there and it is unchanged
  since; so rerunning a verb into its own output folder just works (``estimate``, ``evaluate``,
  ``report``, ``observability log``, ``plan``, ``place``, ``check --csv``, ``repeatability``,
  ``calibrate``).  Other files in the folder are left alone.
* A verb that replaces a folder as a whole (``simulate``, ``import``, ``demo``, ``check --fix``) may
  replace it only when every file in it is an unchanged uwbimu output (a previous run's).
* Anything else -- a file uwbimu did not write, one edited since -- needs ``--force`` (exit 4
  without it, naming the file, nothing written).
* Never, even with ``--force``: a dataset's input files, or an input of the command itself.
  Outputs go into a dataset folder only with ``--force``.
* ``montecarlo`` has no ``--force``: a rerun into its folder resumes the same study; a folder of
  another study, or not a study folder, is refused (exit 4).
"""

from __future__ import annotations

from uwbimu.formatting import natural_key  # noqa: F401 (the one natural order, re-exported for the verbs)

#: Help of ``--force`` on every verb.
FORCE_HELP = ("Replace files uwbimu did not write, or edited since (without it only the verb's own "
              "unchanged outputs are replaced); never a dataset's input files.")


def fit_table(console, table, fold=()):
    """Make a rich ``table`` fit ``console``'s width by wrapping headers, never by cutting numbers.

    When the table is wider than the console, every column gets a fixed width: its longest
    cell or its longest header word, whichever is larger (headers then wrap at spaces, cells
    are kept whole); the columns named in ``fold`` (free text) share what is left and wrap.
    Rich's own shrinking cuts numbers ("0.00…") or whole columns.  Returns the table
    (changed in place).
    """
    from rich.measure import Measurement
    from rich.text import Text

    if Measurement.get(console, console.options.update_width(10_000), table).maximum <= console.width:
        return table

    def plain(x) -> str:
        return x.plain if isinstance(x, Text) else Text.from_markup(str(x)).plain

    # one space between columns (rich miscounts fixed widths under collapse_padding)
    table.collapse_padding, table.padding, table.pad_edge = False, (0, 0, 0, 1), True
    cols = table.columns
    word = [max([len(w) for w in plain(c.header).split()] or [0]) for c in cols]
    cell = [max([len(line) for x in c._cells for line in plain(x).splitlines()] or [0]) for c in cols]
    free = [plain(c.header) in fold for c in cols]
    fixed = sum(max(w, n) for w, n, f in zip(word, cell, free) if not f)
    room = console.width - fixed - 2 * len(cols) - 1  # borders and one space per column
    n_free = sum(free)
    for c, w, n, f in zip(cols, word, cell, free):
        c.width = max(w, min(n, room // n_free)) if f else max(w, n)
        c.min_width = None
        if f:
            c.overflow = "fold"
    return table


def value_sd(value, sd, scale: float = 1.0, fmt: str = ".2f", sep: str = " ± ") -> str:
    """``"value ± sd"`` (both times ``scale``) for the console; never ``± nan``.

    A missing or non-finite ``sd`` (a parameter the estimator holds, or whose
    uncertainty it could not compute) prints as ``"value (σ not estimated)"``.
    """
    import math

    v = format(scale * value, fmt)
    if sd is None or not math.isfinite(float(sd)):
        return f"{v} (σ not estimated)"
    return f"{v}{sep}{format(scale * sd, fmt)}"


def measurement_counts(ds) -> str:
    """``"N IMU samples, M ranges[, K TDoA]"`` of a dataset (TDoA counted when it has ``tdoa``)."""
    text = f"{len(ds.imu)} IMU samples, {len(ds.uwb)} ranges"
    if getattr(ds, "tdoa", None) is not None:
        text += f", {len(ds.tdoa)} TDoA"
    return text
