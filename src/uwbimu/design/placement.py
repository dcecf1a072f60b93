"""Room mode: candidate generation, objectives, lazy-greedy log-det, swaps, DE refinement.

Pipeline (all seeded, reproducible):

1. **Candidates** on the mounting surfaces (walls, ceiling, floor, each with a stand-off)
   every ``spacing`` m, or an explicit list; candidates inside obstacles are dropped
   (and counted).
2. **Lazy greedy D-optimal** selection: maximise ``sum_p log det(eps I + G_p(S))`` over
   the tag samples ``p`` (``G_p = sum_{i in S, link closes} u_i u_i^T``).  The marginal
   gain of candidate ``c`` is ``sum_p log(1 + u_pc^T (eps I + G_p)^-1 u_pc)`` (matrix
   determinant lemma); log det is submodular so stale gains are upper bounds and the
   lazy evaluation (Minoux) is exact.
3. **Local swaps** on the weighted objective (coverage, PDOP percentile, N-1 worst case).
4. **Continuous refinement** with ``scipy.optimize.differential_evolution``: every
   anchor keeps its surface and moves continuously on it (2 parameters each).

The weighted objective (minimised) is::

    J = w_coverage * 100 (1 - coverage) + w_pdop * PDOP_q + w_n1_pdop * max_i PDOP_q(without i)
        + w_n1_coverage * 100 (1 - min_i coverage(without i)) - w_info * logdetJ_(100-q)
        + w_hull * 100 * (fraction of the tag samples outside the anchors' convex hull)

(``logdetJ_(100-q)``: the information percentile, the lower tail of ``log det J``; the
hull term turns the practitioner rule "tags inside the anchors' hull", which
:mod:`uwbimu.design.lint` checks, into a penalty)

with PDOP evaluated on the links that close and capped at ``pdop_cap`` where the
position is not observable (fewer than 3 links or a degenerate geometry).

**TDoA** (``LayoutEvaluator(measurement="tdoa")``): every PDOP, the N-1 worst case and the
information term use the TDoA information of :mod:`uwbimu.design.metrics` (differences to a
reference anchor, correlated through it): ``J = sum u u^T - s s^T / n`` with ``s = sum u``
over the ``n`` anchors in range, which needs >= 4 of them (the cap applies below 4).  The
per-anchor terms then carry ``u`` next to ``u u^T`` (9 packed columns) so that sums and
leave-one-out differences stay linear.  The greedy stage maximises
``sum_p log det(eps I + sum [u; 1] [u; 1]^T)`` (the clock-augmented 4x4 information,
still submodular), whose determinant is ``n det(J_tdoa)`` at ``eps -> 0`` (Schur
complement of the clock entry ``n``).
"""

from __future__ import annotations

from uwbimu.errors import ConfigError, UsageError
import heapq
from dataclasses import dataclass, field

import numpy as np

from uwbimu.design.lint import hull_outside_mask
from uwbimu.design.radio import Bar, Box, LinkModel

__all__ = [
    "Room",
    "Surface",
    "LayoutEvaluator",
    "CandidateSet",
    "lazy_greedy_logdet",
    "swap_search",
    "RoomObjective",
    "refine_de",
    "pareto_front",
    "pdop_from_g6",
    "info6_from_sums",
]


# --------------------------------------------------------------------------- geometry
def _points_in_polygon(xy, poly) -> np.ndarray:
    """Even–odd rule, vectorised over points ``xy`` (P, 2)."""
    x, y = xy[:, 0], xy[:, 1]
    inside = np.zeros(len(xy), dtype=bool)
    n = len(poly)
    for i in range(n):
        x1, y1 = poly[i]
        x2, y2 = poly[(i + 1) % n]
        cond = (y1 > y) != (y2 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xint = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
        inside ^= cond & (x < xint)
    return inside


def _dist_to_edges(xy, poly) -> np.ndarray:
    d = np.full(len(xy), np.inf)
    n = len(poly)
    for i in range(n):
        a = np.asarray(poly[i], float)
        b = np.asarray(poly[(i + 1) % n], float)
        ab = b - a
        t = np.clip(((xy - a) @ ab) / (ab @ ab), 0.0, 1.0)
        d = np.minimum(d, np.linalg.norm(xy - (a + t[:, None] * ab), axis=1))
    return d


@dataclass
class Surface:
    """A mounting surface with two parameters ``(s1, s2)`` in ``[lo, hi]``.

    ``kind`` is ``wall``, ``ceiling`` or ``floor``.  Walls: ``s1`` along the edge [m],
    ``s2`` height [m].  Ceiling/floor: ``(s1, s2) = (x, y)`` [m].
    """

    kind: str
    lo: np.ndarray
    hi: np.ndarray
    origin: np.ndarray  # wall: start vertex (x, y) shifted inward by the stand-off
    tangent: np.ndarray  # wall: unit direction along the edge (x, y)
    normal: np.ndarray  # unit inward normal (3,)
    z: float = 0.0  # ceiling / floor height of the mounting plane

    def position(self, s) -> np.ndarray:
        s = np.atleast_2d(np.asarray(s, dtype=float))
        if self.kind == "wall":
            xy = self.origin[None, :] + s[:, :1] * self.tangent[None, :]
            return np.column_stack([xy, s[:, 1]])
        return np.column_stack([s[:, 0], s[:, 1], np.full(len(s), self.z)])


@dataclass
class Room:
    """An extruded polygon room (CCW vertices, m), height [m], and obstacles."""

    polygon: np.ndarray
    height: float
    obstacles: list = field(default_factory=list)

    def __post_init__(self):
        p = np.asarray(self.polygon, dtype=float)
        area2 = np.sum(p[:, 0] * np.roll(p[:, 1], -1) - np.roll(p[:, 0], -1) * p[:, 1])
        if abs(area2) < 1e-9:
            raise ConfigError("room polygon has zero area")
        self.polygon = p if area2 > 0 else p[::-1].copy()  # make it counter-clockwise

    @classmethod
    def box(cls, L: float, W: float, H: float, obstacles=None) -> "Room":
        return cls(np.array([[0, 0], [L, 0], [L, W], [0, W]], float), float(H), list(obstacles or []))

    def contains(self, pts, margin: float = 0.0) -> np.ndarray:
        pts = np.atleast_2d(pts)
        ok = _points_in_polygon(pts[:, :2], self.polygon)
        ok &= (pts[:, 2] >= margin - 1e-9) & (pts[:, 2] <= self.height - margin + 1e-9)
        if margin > 0:
            ok &= _dist_to_edges(pts[:, :2], self.polygon) >= margin - 1e-9
        return ok

    def surface_distance(self, pts) -> np.ndarray:
        """Distance [m] from each point to the nearest wall, floor or ceiling."""
        pts = np.atleast_2d(pts)
        d = _dist_to_edges(pts[:, :2], self.polygon)
        return np.minimum(d, np.minimum(pts[:, 2], self.height - pts[:, 2]))

    def in_obstacle(self, pts) -> np.ndarray:
        pts = np.atleast_2d(pts)
        out = np.zeros(len(pts), dtype=bool)
        for ob in self.obstacles:
            out |= ob.contains(pts)
        return out

    def surfaces(self, kinds, standoff: float, z_min=None, z_max=None) -> list[Surface]:
        out = []
        P = self.polygon
        z0 = standoff if z_min is None else z_min
        z1 = self.height - standoff if z_max is None else z_max
        lo_xy, hi_xy = P.min(axis=0) + standoff, P.max(axis=0) - standoff
        if "walls" in kinds:
            for i in range(len(P)):
                a, b = P[i], P[(i + 1) % len(P)]
                L = float(np.linalg.norm(b - a))
                t = (b - a) / L
                n = np.array([-t[1], t[0]])  # inward for a CCW polygon
                if L <= 2 * standoff:
                    continue
                out.append(Surface("wall", np.array([standoff, z0]), np.array([L - standoff, z1]),
                                   a + standoff * n, t, np.array([n[0], n[1], 0.0])))
        if "ceiling" in kinds:
            out.append(Surface("ceiling", lo_xy, hi_xy, np.zeros(2), np.zeros(2), np.array([0, 0, -1.0]),
                               self.height - standoff))
        if "floor" in kinds:
            out.append(Surface("floor", lo_xy, hi_xy, np.zeros(2), np.zeros(2), np.array([0, 0, 1.0]), standoff))
        return out

    def valid_mount(self, pos, standoff: float) -> np.ndarray:
        """Inside the room at least ``standoff`` from every surface (minus 1 mm) and not in an obstacle."""
        return self.contains(pos, max(standoff - 1e-3, 0.0)) & ~self.in_obstacle(pos)

    def candidates(self, kinds, standoff: float, spacing: float, z_min=None, z_max=None):
        """Candidate anchor points on the surfaces.

        Returns ``(positions (C, 3), boresights (C, 3), surface_index (C,), params (C, 2),
        surfaces, n_dropped)`` — boresights are the inward surface normals; ``n_dropped``
        counts grid points dropped for lying outside the polygon or inside obstacles.
        """
        surfs = self.surfaces(kinds, standoff, z_min, z_max)
        pos, bor, sid, par = [], [], [], []
        dropped = 0
        for k, s in enumerate(surfs):
            g1 = np.arange(s.lo[0], s.hi[0] + 1e-9, spacing)
            g2 = np.arange(s.lo[1], s.hi[1] + 1e-9, spacing)
            S = np.stack(np.meshgrid(g1, g2, indexing="ij"), -1).reshape(-1, 2)
            X = s.position(S)
            ok = self.valid_mount(X, standoff)
            dropped += int((~ok).sum())
            pos.append(X[ok])
            par.append(S[ok])
            bor.append(np.tile(s.normal, (int(ok.sum()), 1)))
            sid.append(np.full(int(ok.sum()), k))
        return (np.vstack(pos), np.vstack(bor), np.concatenate(sid), np.vstack(par), surfs, dropped)

    def flight_points(self, lo=None, hi=None, step: float = 0.5) -> np.ndarray:
        """Tag samples on a grid (cell centres) in the flight volume, inside the room, outside obstacles."""
        P = self.polygon
        if lo is None:
            lo = [P[:, 0].min() + 0.5, P[:, 1].min() + 0.5, 0.3]
        if hi is None:
            hi = [P[:, 0].max() - 0.5, P[:, 1].max() - 0.5, self.height - 0.5]
        axes = [np.arange(a + step / 2, b, step) if b - a > step else np.array([(a + b) / 2]) for a, b in zip(lo, hi)]
        pts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
        ok = self.contains(pts) & ~self.in_obstacle(pts)
        return pts[ok]


# --------------------------------------------------------------------------- metrics core
def pdop_from_g6(g6, cap: float) -> np.ndarray:
    """PDOP from packed symmetric 3x3 matrices ``[xx, yy, zz, xy, xz, yz]`` (..., 6).

    Closed form ``sqrt(trace(adj G) / det G)``; ``cap`` where ``det`` is ~0 relative to
    ``trace^3`` (unobservable).  Pinned to :func:`uwbimu.design.metrics.pdop` by a test.
    """
    xx, yy, zz, xy, xz, yz = (g6[..., i] for i in range(6))
    a11 = yy * zz - yz * yz
    a22 = xx * zz - xz * xz
    a33 = xx * yy - xy * xy
    det = xx * a11 - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)
    tr = xx + yy + zz
    ok = det > 1e-9 * np.maximum(tr, 1e-12) ** 3
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.sqrt(np.where(ok, (a11 + a22 + a33) / np.where(ok, det, 1.0), np.inf))
    return np.minimum(np.where(np.isfinite(p), p, cap), cap)


def det_g6(g6) -> np.ndarray:
    """Determinant of packed symmetric 3x3 matrices ``[xx, yy, zz, xy, xz, yz]``."""
    xx, yy, zz, xy, xz, yz = (g6[..., i] for i in range(6))
    return xx * (yy * zz - yz * yz) - xy * (xy * zz - yz * xz) + xz * (xy * yz - yy * xz)


def _outer6(u) -> np.ndarray:
    return np.stack([u[..., 0] ** 2, u[..., 1] ** 2, u[..., 2] ** 2, u[..., 0] * u[..., 1],
                     u[..., 0] * u[..., 2], u[..., 1] * u[..., 2]], axis=-1)


def info6_from_sums(G, counts) -> np.ndarray:
    """Packed unit-noise information ``(..., 6)`` from summed per-anchor terms.

    ``G`` (..., 6): two-way ranges, returned as is (``sum u u^T``).  ``G`` (..., 9) with
    ``u`` in the last three columns: TDoA, ``sum u u^T - s s^T / n`` with ``s = sum u`` and
    ``n = counts`` (anchors in range); pinned to :func:`uwbimu.design.metrics.tdoa_gram`.
    """
    G = np.asarray(G)
    if G.shape[-1] == 6:
        return G
    if G.shape[-1] != 9:
        raise ValueError(f"packed terms must have 6 (twr) or 9 (tdoa) columns, got {G.shape[-1]}")
    n = np.maximum(np.asarray(counts, dtype=G.dtype), 1)
    return G[..., :6] - _outer6(G[..., 6:9]) / n[..., None]


def _pct(v, q) -> float:
    return float(np.percentile(v, q, method="higher"))


@dataclass
class LayoutEvaluator:
    """Objective components of a layout over fixed tag samples ``points`` (P, 3)."""

    points: np.ndarray
    link: LinkModel
    k: int = 3
    percentile: float = 95.0
    pdop_cap: float = 20.0
    weights: dict = field(default_factory=lambda: {"coverage": 10.0, "pdop": 1.0, "n1_pdop": 0.25})
    sigma: float = 0.1  # sd of one range (twr) or of one TDoA (tdoa) [m], scales the information term
    measurement: str = "twr"  # "twr" two-way ranges | "tdoa" differences to a reference anchor

    def __post_init__(self):
        if self.measurement not in ("twr", "tdoa"):
            raise UsageError(f"measurement must be 'twr' or 'tdoa', got {self.measurement!r}")

    @property
    def min_links(self) -> int:
        """Anchors in range needed for a 3-D fix: 3 (twr), 4 (tdoa)."""
        return 4 if self.measurement == "tdoa" else 3

    @property
    def arrival_sigma(self) -> float:
        """Noise sd per link [m]: the range sd (twr) or the arrival sd ``sigma / sqrt(2)`` (tdoa)."""
        return self.sigma / np.sqrt(2.0) if self.measurement == "tdoa" else self.sigma

    def per_anchor(self, anchors, boresights):
        """Per-anchor packed terms (N, P, 6) — ``u u^T`` — or (N, P, 9) — ``u u^T`` and ``u``
        (tdoa) — masked by closing links, and the links (N, P)."""
        a = np.atleast_2d(anchors)
        d = self.points[None, :, :] - a[:, None, :]
        u = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-9)
        links = self.link.links(self.points, a, boresights).T
        terms = _outer6(u)
        if self.measurement == "tdoa":
            terms = np.concatenate([terms, u], axis=-1)
        return terms * links[..., None], links

    def components(self, O, M, n1: bool | None = None, anchors=None) -> dict:
        """Coverage, PDOP percentiles and (optionally) the N-1 worst case from per-anchor terms.

        The full set and all N leave-one-out sets are evaluated in one vectorised pass.
        With ``anchors`` (N, 3) also ``hull_outside``: the fraction of the tag samples
        outside the anchors' convex hull.
        """
        if n1 is None:
            n1 = bool(self.weights.get("n1_pdop", 0) or self.weights.get("n1_coverage", 0))
        n1 = n1 and len(O) > 1
        cnt = M.sum(axis=0)
        G = O.sum(axis=0)
        if n1:
            Gs = np.concatenate([G[None], G[None] - O], axis=0)  # (N+1, P, 6)
            Cs = np.concatenate([cnt[None], cnt[None] - M], axis=0)
        else:
            Gs, Cs = G[None], cnt[None]
        Js = info6_from_sums(Gs, Cs)  # unit-noise information, full set first
        pd_ = pdop_from_g6(Js, self.pdop_cap)
        pd_[Cs < self.min_links] = self.pdop_cap
        n = pd_.shape[1]
        # "higher" percentile = the element of rank ceil(q/100 (n-1)) in sorted order
        ks = sorted({int(np.ceil(q / 100.0 * (n - 1))) for q in (50.0, 95.0, self.percentile)})
        part = np.partition(pd_, ks, axis=1)
        rank = {k: part[:, k] for k in ks}

        def at(q):
            return rank[int(np.ceil(q / 100.0 * (n - 1)))]

        out = {
            "coverage": float(np.mean(cnt >= self.k)),
            "pdop_p50": float(at(50.0)[0]),
            "pdop_q": float(at(self.percentile)[0]),
            "pdop_p95": float(at(95.0)[0]),
        }
        # Information percentile: the (100 - q) % lower tail of log det J, J = J_unit / s^2
        # (s: range sd, or arrival sd = TDoA sd / sqrt(2)).
        ld = np.log(np.maximum(det_g6(Js[0]), 1e-12)) - 6.0 * np.log(self.arrival_sigma)
        out["logdet_low"] = float(np.percentile(ld, 100.0 - self.percentile, method="lower"))
        if anchors is not None:
            out["hull_outside"] = float(np.mean(hull_outside_mask(anchors, self.points)))
        if n1:
            qs = at(self.percentile)[1:]
            covs = np.mean(Cs[1:] >= self.k, axis=1)
            out.update({"n1_pdop_q": float(qs.max()), "n1_coverage": float(covs.min()),
                        "n1_worst_anchor": int(np.argmax(qs))})
        return out

    def objective(self, comp: dict) -> float:
        w = self.weights
        j = w.get("coverage", 0.0) * 100.0 * (1.0 - comp["coverage"]) + w.get("pdop", 0.0) * comp["pdop_q"]
        j -= w.get("info", 0.0) * comp["logdet_low"]
        if w.get("hull", 0.0):
            if "hull_outside" not in comp:
                raise UsageError("the 'hull' weight needs the anchor positions (components(..., anchors=...))")
            j += w["hull"] * 100.0 * comp["hull_outside"]
        if "n1_pdop_q" in comp:
            j += w.get("n1_pdop", 0.0) * comp["n1_pdop_q"] + w.get("n1_coverage", 0.0) * 100.0 * (1.0 - comp["n1_coverage"])
        return float(j)

    def evaluate(self, anchors, boresights=None, n1: bool = True) -> dict:
        a = np.atleast_2d(np.asarray(anchors, float))
        if boresights is None:
            boresights = np.tile([0.0, 0.0, -1.0], (len(a), 1))
        O, M = self.per_anchor(a, boresights)
        comp = self.components(O, M, n1=n1, anchors=a)
        comp["objective"] = self.objective(comp)
        return comp


class CandidateSet:
    """Candidates with precomputed per-point link masks and packed outer products."""

    def __init__(self, evaluator: LayoutEvaluator, positions, boresights):
        self.ev = evaluator
        self.positions = np.asarray(positions, float)
        self.boresights = np.asarray(boresights, float)
        self.O, self.M = evaluator.per_anchor(self.positions, self.boresights)
        d = evaluator.points[None, :, :] - self.positions[:, None, :]
        self.U = d / np.maximum(np.linalg.norm(d, axis=2, keepdims=True), 1e-9)

    def __len__(self) -> int:
        return len(self.positions)

    def components(self, idx, n1=None) -> dict:
        idx = list(idx)
        return self.ev.components(self.O[idx], self.M[idx], n1=n1, anchors=self.positions[idx])

    def objective(self, idx) -> float:
        return self.ev.objective(self.components(idx))


def lazy_greedy_logdet(cs: CandidateSet, n: int, eps: float = 1e-3, callback=None) -> dict:
    """Lazy greedy maximisation of ``sum_p log det(eps I + G_p)`` over the candidates.

    ``G_p = sum u u^T`` (twr) or, for a TDoA evaluator, the clock-augmented
    ``sum [u; 1] [u; 1]^T`` (4x4; its Schur complement is the TDoA information).
    Returns ``{"idx": chosen indices in order, "gains": marginal log-det gains,
    "curve": components after each addition}``.
    """
    U = cs.U
    if cs.ev.measurement == "tdoa":
        U = np.concatenate([U, np.ones(U.shape[:2] + (1,))], axis=2)
    P, dim = U.shape[1], U.shape[2]
    Minv = np.tile(np.eye(dim) / eps, (P, 1, 1))

    def gain(c):
        u = U[c]
        q = np.einsum("pi,pij,pj->p", u, Minv, u)
        return float(np.sum(np.log1p(cs.M[c] * q)))

    heap = [(-gain(c), c) for c in range(len(cs))]
    heapq.heapify(heap)
    chosen, gains, curve = [], [], []
    while len(chosen) < min(n, len(cs)):
        _, c = heapq.heappop(heap)
        g = gain(c)
        if heap and g < -heap[0][0] - 1e-12:
            heapq.heappush(heap, (-g, c))  # stale bound: re-insert with its fresh gain
            continue
        chosen.append(c)
        gains.append(g)
        u = U[c] * cs.M[c][:, None]
        Mu = np.einsum("pij,pj->pi", Minv, u)
        Minv = Minv - np.einsum("pi,pj->pij", Mu, Mu) / (1.0 + np.einsum("pi,pi->p", u, Mu))[:, None, None]
        curve.append(cs.components(chosen, n1=False))
        if callback is not None:
            callback(len(chosen), g)
    return {"idx": chosen, "gains": gains, "curve": curve}


def swap_search(cs: CandidateSet, idx, rounds: int = 4, callback=None) -> dict:
    """Best-improvement single swaps (one chosen anchor for one unchosen candidate)."""
    idx = list(idx)
    best = cs.objective(idx)
    nfev = 1
    for r in range(rounds):
        improved = False
        for pos in range(len(idx)):
            cur = best
            best_c = None
            for c in range(len(cs)):
                if c in idx:
                    continue
                trial = idx.copy()
                trial[pos] = c
                f = cs.objective(trial)
                nfev += 1
                if f < cur - 1e-9:
                    cur, best_c = f, c
            if best_c is not None:
                idx[pos] = best_c
                best = cur
                improved = True
        if callback is not None:
            callback(r + 1, best)
        if not improved:
            break
    return {"idx": idx, "objective": best, "nfev": nfev}


class RoomObjective:
    """Picklable DE objective: each anchor moves on its own surface (2 parameters)."""

    def __init__(self, room: Room, surfaces: list[Surface], surface_idx, evaluator: LayoutEvaluator, standoff: float):
        self.room = room
        self.surfaces = surfaces
        self.sidx = [int(s) for s in surface_idx]
        self.ev = evaluator
        self.standoff = standoff

    @property
    def bounds(self) -> list[tuple[float, float]]:
        b = []
        for s in self.sidx:
            sf = self.surfaces[s]
            b += [(float(sf.lo[0]), float(sf.hi[0])), (float(sf.lo[1]), float(sf.hi[1]))]
        return b

    def decode(self, x) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, float).reshape(-1, 2)
        pos = np.vstack([self.surfaces[s].position(x[i]) for i, s in enumerate(self.sidx)])
        bor = np.vstack([self.surfaces[s].normal for s in self.sidx])
        return pos, bor

    def encode(self, params) -> np.ndarray:
        return np.asarray(params, float).reshape(-1)

    def __call__(self, x) -> float:
        pos, bor = self.decode(x)
        bad = ~self.room.valid_mount(pos, self.standoff)
        comp = self.ev.evaluate(pos, bor)
        # Invalid mounts (outside a non-convex polygon, inside obstacles): penalised, not dropped.
        return comp["objective"] + 1000.0 * float(bad.sum())


def refine_de(obj: RoomObjective, x0, seed: int, maxiter: int, popsize: int, workers: int = 1, callback=None,
              init_sigma: float = 0.5) -> dict:
    """Continuous DE refinement on the surfaces, starting from a cloud (sd ``init_sigma`` m) around ``x0``."""
    from uwbimu.design.optimize import differential_evolution_opt

    b = np.array(obj.bounds)
    x0 = np.clip(np.asarray(x0, float), b[:, 0], b[:, 1])
    return differential_evolution_opt(obj, obj.bounds, seed=seed, maxiter=maxiter, popsize=popsize,
                                      workers=workers, x0=x0, callback=callback, init_sigma=init_sigma)


def pareto_front(F) -> np.ndarray:
    """Indices of the non-dominated rows of ``F`` (all columns minimised)."""
    F = np.asarray(F, float)
    keep = []
    for i in range(len(F)):
        dom = np.all(F <= F[i], axis=1) & np.any(F < F[i], axis=1)
        if not dom.any():
            keep.append(i)
    return np.array(keep, dtype=int)


def obstacles_from_config(obstacles) -> list:
    """Build :class:`Box` / :class:`Bar` from :class:`ObstacleConfig` entries."""
    out = []
    for o in obstacles:
        if o.box is not None:
            out.append(Box(tuple(o.box["lo"]), tuple(o.box["hi"]), o.loss_db))
        else:
            b = o.bar
            out.append(Bar(tuple(b["p0"]), tuple(b["p1"]), float(b.get("radius", 0.1)), o.loss_db))
    return out
