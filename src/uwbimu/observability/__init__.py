"""Observability and identifiability of UWB-IMU systems (seed 001 section 3, seed 002 V-VIII).

* :func:`structural_verdict` — Lie-derivative rank test of a configuration;
* :func:`delay_verdict` — time-offset identifiability (Theorem 1, T1-T3);
* :func:`window_observability` — per-window information / CRLB of a log;
* :class:`ControlAffineModel`, :class:`LieObservability` — the general engine.

Names are imported lazily so that ``structural_verdict`` does not pay for
numba (used only by the per-window analysis).
"""

from importlib import import_module

_EXPORTS = {
    "ConfigError": "config",
    "ObservabilityConfig": "config",
    "load_config": "config",
    "delay_verdict": "delay",
    "ControlAffineModel": "engine",
    "LieObservability": "engine",
    "ObservabilityCache": "engine",
    "RankResult": "engine",
    "structural_verdict": "structural",
    "WindowOptions": "window",
    "window_observability": "window",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name):
    if name in _EXPORTS:
        return getattr(import_module(f"uwbimu.observability.{_EXPORTS[name]}"), name)
    raise AttributeError(f"module 'uwbimu.observability' has no attribute {name!r}")
