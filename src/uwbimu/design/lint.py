"""Practitioner lint: vendor rules of thumb (Sewio, CUWB, Bitcraze, Pozyx) as checks.

* anchors not collinear and not coplanar (the seed: a coplanar set loses the height
  when the tag is in, or near, the anchors' plane);
* layout not flat: the anchors' horizontal extent (length or width) over their height
  spread <= 3;
* the flight volume inside the anchors' convex hull;
* anchors at least 0.15 m from walls, floor and ceiling (multipath / antenna detuning);
* the worst single-anchor failure (N-1): how much coverage / PDOP is lost.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

__all__ = ["LintWarning", "lint_layout", "hull_outside_fraction", "hull_outside_mask", "planarity"]


@dataclass
class LintWarning:
    code: str
    severity: str  # "warning" or "info"
    message: str
    value: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


def planarity(anchors) -> tuple[float, float]:
    """Ratios of the singular values of the centred anchor set, ``(s2/s1, s3/s1)``.

    ``s2/s1 ~ 0``: collinear; ``s3/s1 ~ 0``: coplanar (the RMS distance of the anchors to
    their best-fit plane is ``s3 / sqrt(N)`` [m]).
    """
    a = np.asarray(anchors, float)
    c = a - a.mean(axis=0)
    s = np.linalg.svd(c, compute_uv=False)
    s = np.concatenate([s, np.zeros(3 - len(s))])
    if s[0] <= 0:
        return 0.0, 0.0
    return float(s[1] / s[0]), float(s[2] / s[0])


def hull_outside_mask(anchors, points, tol: float = 1e-9) -> np.ndarray:
    """Boolean mask of ``points`` (P, 3) outside the convex hull of ``anchors`` (all True if the hull is flat)."""
    from scipy.spatial import ConvexHull, QhullError

    a = np.asarray(anchors, float)
    p = np.atleast_2d(np.asarray(points, float))
    if len(a) < 4:
        return np.ones(len(p), dtype=bool)
    try:
        eq = ConvexHull(a).equations  # outward facet normals n and offsets b: inside iff n.x + b <= 0
    except QhullError:
        return np.ones(len(p), dtype=bool)
    return np.any(p @ eq[:, :3].T + eq[:, 3] > tol, axis=1)


def hull_outside_fraction(anchors, points) -> float:
    """Fraction of ``points`` outside the convex hull of ``anchors`` (1.0 if the hull is flat)."""
    return float(np.mean(hull_outside_mask(anchors, points)))


def _space_note(space_extent, flat_ratio: float) -> str:
    if space_extent is None:
        return ""
    e = np.asarray(space_extent, float)
    r = float(max(e[0], e[1]) / e[2]) if e[2] > 0 else float("inf")
    if r > flat_ratio:
        return (f" (the space itself is {e[0]:g} x {e[1]:g} x {e[2]:g} m, ratio {r:.1f} > {flat_ratio:g}: "
                "anchors spread over the whole space cannot pass this rule)")
    return ""


def lint_layout(
    anchors,
    flight_points=None,
    surface_distance=None,
    min_wall_distance: float = 0.15,
    flat_ratio: float = 3.0,
    collinear_tol: float = 0.02,
    coplanar_tol: float = 0.05,
    single_failure: dict | None = None,
    single_failure_pdop_limit: float = 5.0,
    ids=None,
    space_extent=None,
) -> list[LintWarning]:
    """Check a layout against the rules of thumb.

    Parameters
    ----------
    anchors : (N, 3) positions [m]
    flight_points : (P, 3) samples of the flight volume (for the hull check)
    surface_distance : callable ``(N, 3) -> (N,)`` distance to the nearest wall/floor/
        ceiling [m] (room mode); skipped when None
    single_failure : ``{"anchor", "coverage", "pdop_p95", "coverage_all"}`` from the N-1
        analysis; reported as info, or as a warning when coverage drops or PDOP exceeds
        ``single_failure_pdop_limit``
    ids : anchor names for messages (default A1..AN)
    space_extent : (3,) size of the room/space [m]; when given, the flat-layout message
        says whether the space itself already exceeds the ratio
    """
    a = np.asarray(anchors, float)
    ids = list(ids) if ids is not None else [f"A{i + 1}" for i in range(len(a))]
    out: list[LintWarning] = []
    if len(a) < 4:
        out.append(LintWarning("too-few", "warning", f"{len(a)} anchors: 3-D positioning needs >= 4 non-coplanar anchors", len(a)))
    r2, r3 = planarity(a)
    if r2 < collinear_tol:
        out.append(LintWarning("collinear", "warning", f"anchors are (nearly) collinear: s2/s1 = {r2:.3f}", r2))
    elif r3 < coplanar_tol:
        out.append(LintWarning("coplanar", "warning",
                               f"anchors are (nearly) coplanar: s3/s1 = {r3:.3f}; the coordinate normal to "
                               "their plane is poorly observed near it (seed, Sec. VI)", r3))
    ext = a.max(axis=0) - a.min(axis=0)
    h = ext[2]
    ratio = float(max(ext[0], ext[1]) / h) if h > 1e-9 else float("inf")
    if ratio > flat_ratio:
        out.append(LintWarning("flat", "warning",
                               f"flat layout: max(length, width)/height = {ratio:.1f} > {flat_ratio:g} "
                               f"(extent {ext[0]:.1f} x {ext[1]:.1f} x {h:.2f} m); z will be poor"
                               + _space_note(space_extent, flat_ratio), ratio))
    if flight_points is not None and len(flight_points):
        f = hull_outside_fraction(a, flight_points)
        if f > 0:
            out.append(LintWarning("outside-hull", "warning" if f > 0.05 else "info",
                                   f"{100 * f:.1f} % of the flight volume is outside the anchors' convex hull", f))
    if surface_distance is not None:
        d = np.asarray(surface_distance(a), float)
        for i in np.flatnonzero(d < min_wall_distance):
            out.append(LintWarning("near-wall", "warning",
                                   f"anchor {ids[i]} is {d[i]:.2f} m from a wall/floor/ceiling (< {min_wall_distance} m)",
                                   float(d[i])))
    if single_failure:
        sf = single_failure
        sev = "info"
        if sf.get("coverage", 1.0) < sf.get("coverage_all", 1.0) - 1e-9 or sf.get("pdop_p95", 0.0) > single_failure_pdop_limit:
            sev = "warning"
        out.append(LintWarning("single-failure", sev,
                               f"worst single-anchor failure: losing {sf.get('anchor')} leaves coverage "
                               f"{100 * sf.get('coverage', float('nan')):.1f} % and PDOP p95 {sf.get('pdop_p95', float('nan')):.2f}",
                               sf.get("pdop_p95")))
    return out
