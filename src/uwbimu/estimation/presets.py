"""Estimator presets shipped with the package (``src/uwbimu/data/presets/NAME.yaml``).

``default``   the defaults of :class:`EskfOptions`.
``real``      real two-way ranging: a per-anchor Gauss-Markov range bias for the correlated, direction-
              dependent part of the range error (examples/estimator_real.yaml; docs/estimator.md, "Real data").
``isas-walk`` ``real`` plus the walking, low-cost-IMU settings measured on ISAS-Walk
              (examples/estimator_isas.yaml; docs/estimator.md, "ISAS-Walk").

Dataset properties (``anchor_frame_up``, known anchor biases, tags) are not part of a preset:
:func:`uwbimu.estimation.run_eskf` reads them from the dataset.
"""

from __future__ import annotations

from importlib import resources

from uwbimu.errors import UsageError
from uwbimu.estimation.options import EskfOptions

_PACKAGE = "uwbimu.data"


def preset_names() -> list[str]:
    """Names of the shipped presets, sorted."""
    folder = resources.files(_PACKAGE).joinpath("presets")
    return sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml"))


def load_preset(name: str) -> EskfOptions:
    """Options of the shipped preset ``name`` (see :func:`preset_names`).

    Raises
    ------
    ValueError
        Unknown name (the message lists the known ones).
    """
    names = preset_names()
    if name not in names:
        raise UsageError(f"unknown estimator preset {name!r}; known presets: {', '.join(names)}")
    with resources.as_file(resources.files(_PACKAGE).joinpath("presets", f"{name}.yaml")) as path:
        return EskfOptions.from_yaml(path)


def _deep_merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _deep_merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def load_options(preset: str | None = None, config=None) -> EskfOptions:
    """Options from a preset and/or a YAML file; the file's keys override the preset's (deep merge).

    Parameters
    ----------
    preset : name of a shipped preset, or None (the defaults).
    config : path of an options YAML (see examples/estimator.yaml), or None.
    """
    base = load_preset(preset) if preset else EskfOptions()
    if config is None:
        return base
    user = EskfOptions.from_yaml(config)  # validates the file alone first (errors name the file)
    merged = _deep_merge(base.model_dump(exclude_unset=True), user.model_dump(exclude_unset=True))
    return EskfOptions.model_validate(merged)
