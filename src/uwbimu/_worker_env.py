"""Imported by the Monte Carlo forkserver only, never by the caller: one BLAS thread per worker.

:func:`uwbimu.parallel.execute` names this module first in the forkserver's preload
list, so the variables are set in the server before it imports NumPy and every worker it
forks inherits them; the caller's ``os.environ`` is never touched (issue 15: no environment
changes in the library).  Workers then compute with one BLAS thread each, as Dask workers do:
the same numerics and no oversubscription.  A variable the user set is kept.  It is a
top-level module so that importing it loads nothing else (no NumPy).
"""

from __future__ import annotations

import os

THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

for _k in THREAD_VARS:
    os.environ.setdefault(_k, "1")
