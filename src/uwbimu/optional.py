"""Optional dependencies: a clear refusal naming the extra to install.

``pip install uwbimu`` installs what the demo and the core verbs need; Dask (distributed
studies), rosbags (ROS bag import) and pyarrow (Parquet tables) come with the extras
``[dask]``, ``[ros]``, ``[parquet]`` (or ``[all]``).
"""

from __future__ import annotations

from importlib import import_module
from types import ModuleType

from uwbimu.errors import UsageError


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module`` or raise :class:`UsageError` saying which extra provides it.

    Parameters
    ----------
    module : importable name, e.g. ``"distributed"``.
    extra : the uwbimu extra that installs it, e.g. ``"dask"``.
    purpose : what needs it, for the message (e.g. ``"a Dask study"``).
    """
    try:
        return import_module(module)
    except ImportError:
        raise UsageError(
            f"{purpose} needs the optional package {module!r}, which is not installed",
            hint=f'pip install "uwbimu[{extra}]"',
        ) from None
