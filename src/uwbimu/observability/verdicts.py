"""Typed verdicts of the observability analyses; each reads like the dict it used to be.

``v.observable`` and ``v["observable"]`` are the same value; the analysis-specific details
(order search, singular values, per-point results, ...) are in ``extra`` and readable as keys;
:meth:`~uwbimu.typed.MappingResult.to_dict` gives the plain dictionary (``--json``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

from uwbimu.typed import MappingResult


@dataclass(eq=False)
class StructuralVerdict(MappingResult):
    """Result of :func:`uwbimu.observability.structural.structural_verdict`.

    Attributes
    ----------
    name, model, measurement : of the configuration analysed.
    observable : the rank equals the state dimension at every point.
    rank, dimension : rank of the observability codistribution (worst point) and state dimension.
    verdict : the sentence the CLI prints ("observable", "not shown observable at order k", ...).
    lie_order : Lie-derivative order used.
    unobservable_directions : named directions of the null space (``{"name", "vector", ...}``).
    conditions : the seed's sufficient conditions at the weakest point (name -> holds).
    extra : everything else (``singular_values``, ``order_search``, ``points``, ``elapsed_s``...).
    """

    name: str = ""
    model: str = ""
    measurement: str = ""
    observable: bool = False
    rank: int = 0
    dimension: int = 0
    verdict: str = ""
    lie_order: Optional[int] = None
    unobservable_directions: list[dict[str, Any]] = field(default_factory=list)
    conditions: dict[str, Any] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


@dataclass(eq=False)
class DelayVerdict(MappingResult):
    """Result of :func:`uwbimu.observability.delay.delay_verdict` (time-offset identifiability).

    Attributes
    ----------
    name, measurement : of the configuration analysed.
    identifiable : Theorem 1 holds, or the numeric input-output sensitivity is non-zero, at every point.
    theorem1 : T1 and (T2 or T3) at every point.
    conditions : ``{T1, T2, T3}`` at the weakest point.
    numeric : the numeric check (``sensitivity`` [m per unit input], ``tolerance``, ``nonzero``, ``td_power``...).
    basis : which test decided (``theorem`` / ``numeric``).
    agree : the theorem and the numeric check agree.
    extra : everything else (``first_order``, ``explanation``, ``points``, ``n_points``...).
    """

    name: str = ""
    measurement: str = ""
    identifiable: bool = False
    theorem1: bool = False
    conditions: dict[str, Any] = field(default_factory=dict)
    numeric: dict[str, Any] = field(default_factory=dict)
    basis: str = ""
    agree: bool = True
    extra: dict[str, Any] = field(default_factory=dict)
