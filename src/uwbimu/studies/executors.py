"""Moved: the generic executor is :mod:`uwbimu.parallel` (a low-level module every layer may import).

This name stays an alias of that module (the same module object, so ``monkeypatch`` on either reaches
both) for code that still imports ``uwbimu.studies.executors``.
"""

import sys

from uwbimu import parallel

sys.modules[__name__] = parallel
