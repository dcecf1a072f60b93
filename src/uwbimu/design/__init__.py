"""uwbimu.design: anchor placement (room and structure modes) and, in ``design.trajectory``,
trajectory design.  Placement entry points: :func:`run_placement`, :func:`builtin_example`,
:func:`load_config`; metrics in :mod:`uwbimu.design.metrics`, radio model in
:mod:`uwbimu.design.radio`.  Exports are lazy so importing ``design.trajectory`` stays light.
"""

_EXPORTS = {
    "PlacementConfig": "uwbimu.design.config",
    "load_config": "uwbimu.design.config",
    "builtin_example": "uwbimu.design.run",
    "run_placement": "uwbimu.design.run",
    "write_outputs": "uwbimu.design.run",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        import importlib

        return getattr(importlib.import_module(_EXPORTS[name]), name)
    raise AttributeError(f"module 'uwbimu.design' has no attribute {name!r}")
