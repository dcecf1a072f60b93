"""Geometry and information metrics of an anchor layout over a region of tag positions.

All positions are in the world frame [m], arrays are batched over tag points
``points`` with shape ``(P, 3)`` and anchors ``anchors`` with shape ``(N, 3)``.
An optional boolean ``links`` array of shape ``(P, N)`` says which anchor–tag
links close (radio range, antenna gain, line of sight; see
:mod:`uwbimu.design.radio`); links that do not close contribute nothing.

Range Fisher information
------------------------
A two-way range ``r_i = |p - a_i| + n``, ``n ~ N(0, sigma^2)``, has the gradient
``d r_i / d p = u_i^T`` with the unit line-of-sight vector ``u_i = (p - a_i)/r_i``.
The Fisher information of the tag position from all closing links is::

    J(p) = (1 / sigma^2) * sum_i u_i u_i^T = H^T H / sigma^2,   H = [u_1; ...; u_N]

* PDOP (A-optimal) ``= sqrt(trace((H^T H)^-1))`` — the position error standard
  deviation per metre of range noise; GDOP adds a clock column ``[u_i^T, 1]``
  (pseudorange / TDoA systems);
* D-optimal: ``log det J``;  E-optimal: ``lambda_min(J)``.

TDoA Fisher information
-----------------------
A TDoA system measures differences to a reference anchor ``ref`` among the ``n``
anchors in range, ``d_i = r_i - r_ref + e_i - e_ref`` (``i != ref``), with independent
arrival noises ``e ~ N(0, s^2)``.  The ``n - 1`` differences share ``e_ref``, so
their covariance is ``R = s^2 (I + 1 1^T)`` (correlated through the reference anchor)
and the marginal sd of one TDoA is ``sigma_tdoa = sqrt(2) s``.  With ``H`` rows
``(u_i - u_ref)^T``, ``H = D U`` for the differencing matrix ``D = [-1 | I]`` (reference
column first), and ``D^T (D D^T)^-1 D = I - 1 1^T / n`` is the projector onto the
complement of ``1`` (it does not depend on which anchor is the reference), hence::

    J_tdoa = H^T R^-1 H = (1 / s^2) U^T (I - 1 1^T / n) U
           = (1 / s^2) (sum_i u_i u_i^T - n ubar ubar^T),   ubar = mean_i u_i

— the range information minus the rank-1 direction of a common offset: it is the
Schur complement of the clock in the GDOP information of ``[u_i^T, 1]``.  TDoA PDOP is
``sqrt(trace((U^T P U)^-1))``, the position sd per metre of *arrival* noise ``s`` (so it
is directly comparable with the two-way PDOP for the same per-anchor timing noise, and
never smaller); it needs ``n >= 4`` anchors in range.  Coplanar anchors (all on the
ceiling) are weak in the direction normal to their plane: the normal components
``u_i . nrm = h / r_i`` (``h`` the tag's distance from the plane) differ only through
the ranges, and the centred vectors have none when the tag is equidistant from all
anchors (on the axis of anchors on a circle) — singular under TDoA, while two-way ranges
still see ``h / r > 0``.

The seed's observability determinant and how it relates
--------------------------------------------------------
The seed (Balaji & Sreekar) uses squared ranges ``Y_i = |p - a_i|^2`` and drops the
factor 2 of the gradient, so its zeroth-order observability matrix has rows
``a_i = p - a_i`` (tag position *relative to* anchor ``i``), i.e. ``O = D U``
with ``D = diag(r_1..r_N)`` and ``U = H``.  Its measure is ``det(O^T O)``.

* For **three beacons** ``O`` is square, hence::

      det(O^T O) = det(O)^2 = (r_1 r_2 r_3)^2 det(U)^2 = (r_1 r_2 r_3)^2 sigma^6 det(J)

  The seed's determinant is the line-of-sight (Fisher) determinant weighted by the
  squared product of ranges: it *rewards distance*, whereas the information does
  not; the two agree on where the determinant vanishes (tag in the anchors' plane,
  collinear anchors) but not on what is "more observable".  The seed's own
  normalisation in its optimal-control section, ``det(O) -> det(a) / (r_1 r_2 r_3)``
  (each row divided by its range), gives ``det = det(U)``, whose square is
  ``sigma^6 det(J)`` — exactly the D-optimal (Fisher) criterion.
* For **N beacons**, Cauchy–Binet gives
  ``det(O^T O) = sum_{i<j<k} (r_i r_j r_k)^2 det(U_ijk)^2`` while
  ``det(H^T H) = sum_{i<j<k} det(U_ijk)^2``.
* With the first-order Lie derivative (point mass, state ``[p, v]``) the matrix
  ``O_6 = [[A, 0], [V, A]]`` (rows ``[v^T, a_i^T]``) is block triangular, so for three
  beacons ``det(O_6) = det(A)^2`` and ``det(O_6^T O_6) = det(O^T O)^2`` — the
  statement "the determinant of the 6x6 matrix is the square of the 3x3 one".
"""

from __future__ import annotations

from uwbimu.errors import UsageError
import numpy as np

__all__ = [
    "unit_los",
    "information_matrix",
    "dop",
    "pdop",
    "gdop",
    "tdoa_gram",
    "tdoa_information_matrix",
    "tdoa_information_explicit",
    "tdoa_pdop",
    "measurement_information",
    "logdet_information",
    "min_eig_information",
    "seed_observability_matrix",
    "seed_observability_det",
    "percentiles",
    "region_metrics",
]

_EPS_RANGE = 1e-9


def _as_points(points) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    if p.ndim == 1:
        p = p[None, :]
    if p.ndim != 2 or p.shape[1] != 3:
        raise UsageError(f"points must have shape (P, 3), got {p.shape}")
    return p


def _as_anchors(anchors) -> np.ndarray:
    a = np.asarray(anchors, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise UsageError(f"anchors must have shape (N, 3), got {a.shape}")
    return a


def unit_los(points, anchors) -> tuple[np.ndarray, np.ndarray]:
    """Unit line-of-sight vectors from each anchor to each tag point.

    Returns
    -------
    u : (P, N, 3) unit vectors ``(p - a_i) / |p - a_i|`` (world frame)
    r : (P, N) ranges [m]
    """
    p = _as_points(points)
    a = _as_anchors(anchors)
    d = p[:, None, :] - a[None, :, :]
    r = np.linalg.norm(d, axis=2)
    u = d / np.maximum(r, _EPS_RANGE)[..., None]
    return u, r


def information_matrix(points, anchors, sigma: float = 1.0, links=None, clock: bool = False) -> np.ndarray:
    """Range Fisher information per tag point, ``J = H^T W H / sigma^2``.

    Parameters
    ----------
    points : (P, 3) tag positions [m]
    anchors : (N, 3) anchor positions [m]
    sigma : range noise standard deviation [m]
    links : optional (P, N) bool, which links close (others give no information)
    clock : add a unit clock column (pseudorange/TDoA model) -> (P, 4, 4)

    Returns
    -------
    (P, 3, 3) or (P, 4, 4) information matrices [1/m^2]
    """
    u, _ = unit_los(points, anchors)
    if clock:
        u = np.concatenate([u, np.ones(u.shape[:2] + (1,))], axis=2)
    w = np.ones(u.shape[:2]) if links is None else np.asarray(links, dtype=float)
    if w.shape != u.shape[:2]:
        raise UsageError(f"links must have shape {u.shape[:2]}, got {w.shape}")
    return np.einsum("pn,pni,pnj->pij", w, u, u) / float(sigma) ** 2


def _dop_from(g: np.ndarray) -> np.ndarray:
    """``sqrt(trace(g^-1))`` per matrix of (P, d, d); ``inf`` where ``g`` is singular."""
    out = np.full(g.shape[0], np.inf)
    # Relative conditioning test: a geometry whose smallest eigenvalue is ~0 is unobservable.
    ev = np.linalg.eigvalsh(g)
    ok = ev[:, 0] > 1e-10 * np.maximum(ev[:, -1], 1e-300)
    if ok.any():
        out[ok] = np.sqrt(np.sum(1.0 / ev[ok], axis=1))
    return out


def dop(points, anchors, links=None, clock: bool = False) -> np.ndarray:
    """Dilution of precision ``sqrt(trace((H^T H)^-1))`` per point (A-optimality).

    ``clock=False`` gives PDOP for two-way ranging; ``clock=True`` gives GDOP with
    an unknown clock term.  Points with a singular geometry (fewer than 3 (4)
    closing links, coplanar/collinear geometry) get ``inf``.
    """
    return _dop_from(information_matrix(points, anchors, 1.0, links, clock))


def pdop(points, anchors, links=None) -> np.ndarray:
    """Position DOP for two-way ranging, ``(P,)``; ``inf`` where unobservable."""
    return dop(points, anchors, links, clock=False)


def gdop(points, anchors, links=None) -> np.ndarray:
    """Geometric DOP with a clock unknown (pseudorange / TDoA), ``(P,)``."""
    return dop(points, anchors, links, clock=True)


TDOA_MIN_LINKS = 4  # anchors in range for a 3-D TDoA fix (3 independent differences)


def tdoa_gram(points, anchors, links=None) -> np.ndarray:
    """Centred geometry matrix ``U^T (I - 1 1^T / n) U`` of the anchors in range, (P, 3, 3).

    ``= sum_i u_i u_i^T - n ubar ubar^T`` over the ``n`` closing links of each point
    (zero where ``n < 2``); the TDoA information for unit arrival noise (module docstring).
    """
    u, _ = unit_los(points, anchors)
    w = np.ones(u.shape[:2]) if links is None else np.asarray(links, dtype=float)
    if w.shape != u.shape[:2]:
        raise UsageError(f"links must have shape {u.shape[:2]}, got {w.shape}")
    g = np.einsum("pn,pni,pnj->pij", w, u, u)
    s = np.einsum("pn,pni->pi", w, u)
    n = w.sum(axis=1)
    return g - np.einsum("pi,pj->pij", s, s) / np.maximum(n, 1.0)[:, None, None]


def tdoa_information_matrix(points, anchors, sigma: float = 1.0, links=None) -> np.ndarray:
    """TDoA Fisher information per tag point [1/m^2], (P, 3, 3).

    Parameters
    ----------
    points : (P, 3) tag positions [m]
    anchors : (N, 3) anchor positions [m]
    sigma : sd of one TDoA measurement ``r_i - r_ref`` [m] (``sqrt(2)`` times the arrival
        noise ``s``; the differences' covariance is ``(sigma^2 / 2) (I + 1 1^T)``)
    links : optional (P, N) bool, which anchors are in range (the others give nothing)

    Returns ``J = (2 / sigma^2) U^T (I - 1 1^T / n) U`` — equal to the explicit
    ``H^T R^-1 H`` of :func:`tdoa_information_explicit` for any reference anchor.
    """
    return tdoa_gram(points, anchors, links) * (2.0 / float(sigma) ** 2)


def tdoa_information_explicit(point, anchors, sigma: float = 1.0, ref: int = 0) -> np.ndarray:
    """TDoA information ``H^T R^-1 H`` of one point from differences to anchor ``ref``, (3, 3).

    The plain formula (reference for :func:`tdoa_information_matrix`): rows of ``H`` are
    ``(u_i - u_ref)^T`` for every ``i != ref``, ``R = (sigma^2 / 2) (I + 1 1^T)`` with
    ``sigma`` the sd of one TDoA [m].  ``anchors`` (N, 3) are the anchors in range.
    """
    u, _ = unit_los(point, anchors)
    u = u[0]
    n = len(u)
    if not 0 <= ref < n:
        raise UsageError(f"ref must index one of the {n} anchors, got {ref}")
    others = [i for i in range(n) if i != ref]
    H = u[others] - u[ref][None, :]
    R = 0.5 * float(sigma) ** 2 * (np.eye(n - 1) + np.ones((n - 1, n - 1)))
    return H.T @ np.linalg.solve(R, H)


def tdoa_pdop(points, anchors, links=None) -> np.ndarray:
    """TDoA position DOP ``sqrt(trace((U^T P U)^-1))`` per point, ``(P,)``.

    The position sd per metre of arrival noise (``tdoa_sigma / sqrt(2)``); equals the
    position part of :func:`gdop`.  ``inf`` where fewer than 4 anchors are in range or the
    geometry is singular (relative test as :func:`dop`).
    """
    g = tdoa_gram(points, anchors, links)
    out = _dop_from(g)
    n = np.full(len(g), _as_anchors(anchors).shape[0]) if links is None else np.asarray(links).sum(axis=1)
    out[n < TDOA_MIN_LINKS] = np.inf
    return out


def measurement_information(points, anchors, measurement: str = "twr", sigma: float = 1.0, links=None) -> np.ndarray:
    """Fisher information (P, 3, 3) for ``measurement`` ``twr`` (range sd ``sigma``) or
    ``tdoa`` (sd of one TDoA ``sigma``), both [m]."""
    if measurement == "twr":
        return information_matrix(points, anchors, sigma, links)
    if measurement == "tdoa":
        return tdoa_information_matrix(points, anchors, sigma, links)
    raise UsageError(f"measurement must be 'twr' or 'tdoa', got {measurement!r}")


def logdet_information(points, anchors, sigma: float = 1.0, links=None, floor: float = 1e-12,
                       measurement: str = "twr") -> np.ndarray:
    """D-optimality ``log det J`` per point; ``-inf``-like ``log(floor)`` sums when singular."""
    g = measurement_information(points, anchors, measurement, sigma, links)
    ev = np.linalg.eigvalsh(g)
    return np.sum(np.log(np.maximum(ev, floor)), axis=1)


def min_eig_information(points, anchors, sigma: float = 1.0, links=None, measurement: str = "twr") -> np.ndarray:
    """E-optimality ``lambda_min(J)`` per point [1/m^2]."""
    g = measurement_information(points, anchors, measurement, sigma, links)
    return np.maximum(np.linalg.eigvalsh(g)[:, 0], 0.0)


def seed_observability_matrix(point, anchors, velocity=None, order: int = 0) -> np.ndarray:
    """The seed's Lie-derivative observability matrix for the point-mass model.

    State ``X = [p, v]``, dynamics ``p' = v, v' = u``, outputs ``Y_i = |p - a_i|^2``
    with the factor 2 dropped as in the seed.

    Parameters
    ----------
    point : (3,) tag position [m]
    anchors : (N, 3) anchor positions [m]
    velocity : (3,) tag velocity [m/s], needed for ``order=1``
    order : 0 -> ``(N, 3)`` matrix with rows ``(p - a_i)^T`` (position block only);
        1 -> ``(2N, 6)`` matrix ``[[A, 0], [V, A]]`` with rows ``[v^T, (p - a_i)^T]``.
    """
    p = np.asarray(point, dtype=float).reshape(3)
    a = _as_anchors(anchors)
    A = p[None, :] - a
    if order == 0:
        return A
    if order != 1:
        raise UsageError("order must be 0 or 1")
    if velocity is None:
        raise UsageError("order=1 needs the velocity")
    v = np.asarray(velocity, dtype=float).reshape(3)
    top = np.hstack([A, np.zeros_like(A)])
    bottom = np.hstack([np.tile(v, (len(a), 1)), A])
    return np.vstack([top, bottom])


def seed_observability_det(points, anchors, links=None) -> np.ndarray:
    """``det(O^T O)`` of the seed's zeroth-order matrix per tag point [m^6].

    Vectorised over ``points`` (P, 3); ``links`` masks anchors out per point.
    See the module docstring for its relation to the Fisher determinant.
    """
    p = _as_points(points)
    a = _as_anchors(anchors)
    d = p[:, None, :] - a[None, :, :]
    w = np.ones(d.shape[:2]) if links is None else np.asarray(links, dtype=float)
    g = np.einsum("pn,pni,pnj->pij", w, d, d)
    return np.linalg.det(g)


def percentiles(values, qs=(50, 95), cap: float | None = None) -> dict[str, float]:
    """Percentiles of a per-point metric over the region.

    ``inf`` values (unobservable points) are replaced by ``cap`` when given so that
    a percentile is a finite, comparable number; otherwise they propagate as ``inf``.
    """
    v = np.asarray(values, dtype=float).ravel()
    if cap is not None:
        v = np.minimum(np.where(np.isfinite(v), v, cap), cap)
    out = {}
    for q in qs:
        # method="higher" avoids inf - inf = nan interpolation between two inf values.
        out[f"p{int(q)}"] = float(np.percentile(v, q, method="higher")) if v.size else float("nan")
    return out


def region_metrics(points, anchors, sigma: float = 0.1, links=None, qs=(50, 95), pdop_cap: float = 100.0,
                   measurement: str = "twr") -> dict:
    """All metrics per point plus their percentiles over the region.

    Returns a dict with per-point arrays ``pdop``, ``logdet``, ``min_eig``,
    ``seed_det`` and a ``summary`` dict of percentiles (PDOP capped at ``pdop_cap``).
    ``measurement="tdoa"``: TDoA PDOP and information (``sigma`` = sd of one TDoA, m).
    """
    pd_ = tdoa_pdop(points, anchors, links) if measurement == "tdoa" else pdop(points, anchors, links)
    ld = logdet_information(points, anchors, sigma, links, measurement=measurement)
    me = min_eig_information(points, anchors, sigma, links, measurement=measurement)
    sd = seed_observability_det(points, anchors, links)
    summary = {
        "pdop": percentiles(pd_, qs, cap=pdop_cap),
        "logdet": percentiles(ld, qs),
        "min_eig": percentiles(me, qs),
        "seed_det": percentiles(sd, qs),
        "observable_fraction": float(np.mean(np.isfinite(pd_))),
    }
    return {"pdop": pd_, "logdet": ld, "min_eig": me, "seed_det": sd, "summary": summary}
