"""Shared option texts of the ``uwbimu`` verbs (one wording, one meaning everywhere).

* ``-o/--out DIR``: the output folder of a verb (created if missing; outputs written whole or not
  at all through :func:`uwbimu.io.atomic.output_folder`).
* ``--force``: write where uwbimu would otherwise refuse -- over files in the output folder that
  uwbimu did not write (or that were edited since), into a non-empty folder a verb replaces as a
  whole (``simulate``, ``import``) -- never over a dataset's input files.
"""

from __future__ import annotations

#: Help of ``--force`` on every verb.
FORCE_HELP = ("Replace outputs uwbimu did not write (or a non-empty folder the verb replaces whole); "
              "never a dataset's input files.")
