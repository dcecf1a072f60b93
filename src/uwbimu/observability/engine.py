"""Lie-derivative observability rank test for control-affine systems.

A model is ``x' = f0(x, p) + sum_i f_i(x, p) u_i``, ``y = h(x, p)`` given as
CasADi ``SX`` expressions (``p`` are numeric parameters such as anchor
positions, so one compiled function serves every configuration of the same
structure).  The observability codistribution is spanned by the gradients of
the Lie derivatives ``L_w h`` along all words ``w`` of the fields up to a
chosen length (Hermann & Krener; seed 001 eq. 17-19).

Why two word sets
-----------------
All words of length <= 3 over the 7 fields of the UWB-IMU model give ~360 rows
whose symbolic gradients take ~0.5 s to build and ~4 ms to evaluate.  Most of
them are redundant: if ``dL_w h`` lies in the span of the other gradients on an
open set, so do the gradients of all its Lie derivatives (``L_f`` of a
combination is a combination of ``L_f`` of the terms plus terms already in the
span).  The engine therefore first selects, at random *generic* points, the
words that raise the rank ("pruned" set, ~20 rows, built in ~0.1 s, evaluated in
~0.1 ms).  The pruned rows are a subset of all rows, so a full rank found with
them is a proof of full rank; a rank deficiency found with them may be an
artefact of pruning at a special point, so the engine then re-evaluates with
*all* words (compiled lazily, once) and decides on those.

Manifold states (the unit quaternion) are handled by a tangent basis
``T(x)`` (n x d): the reported matrix is ``O T`` and its rank is compared with
``d`` (18 for the 19-number UWB-IMU state without ``t_d``), not with ``n``.
"""

from __future__ import annotations

from uwbimu.errors import UsageError
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence

import numpy as np

#: Legacy fixed relative tolerance (``tol=RANK_TOL``); the default decision is
#: adaptive (:func:`noise_floor`), so that a genuinely small singular value
#: (a geometry 1e-8 rad off a degenerate one) is not cut by a fixed threshold.
RANK_TOL = 1e-8

#: Multiple of the rounding level ``eps sqrt(rows) sigma_max`` below which a
#: singular value of the row-normalised matrix is rounding noise.  Measured on
#: every boundary case of docs/observability.md (orders 1-4, up to 1914 rows):
#: the singular values of exact null directions are <= 2e-15, i.e. < 1e-2 of
#: this floor, while genuine ones go down to what the geometry makes them.
NOISE_FACTOR = 100.0


def noise_floor(sigma_max: float, rows: int) -> float:
    """Rounding-noise level of the singular values of a row-normalised matrix."""
    return NOISE_FACTOR * np.finfo(float).eps * np.sqrt(max(rows, 1)) * max(sigma_max, 1e-300)


#: Tolerance of the greedy word selection at generic points (residual of a new
#: unit row after projection on the kept rows).  Generic dependence leaves
#: ~1e-13; independence leaves >1e-4 in all models we ship.
_SELECT_TOL = 1e-7

#: Rows whose norm is below this fraction of the largest row norm are treated
#: as zero.  Some Lie derivatives vanish identically but CasADi does not
#: simplify them to a structural zero (e.g. ``a*b - b*a`` after expansion);
#: they evaluate to rounding noise (~1e-16 relative) and, once normalised, would
#: fake extra rank.  Genuine rows of the shipped models are > 1e-7 relative.
ZERO_ROW_TOL = 1e-10

#: The pruned words hold only ~dim rows, so a point where they are nearly
#: dependent gives a weak (if formally full-rank) verdict.  Below this ratio
#: sigma_min / sigma_max the decision is re-taken with all words.
PRUNED_MARGIN = 1e-4


@dataclass
class ControlAffineModel:
    """A control-affine system with symbolic (CasADi ``SX``) fields and outputs.

    Attributes
    ----------
    name : label used in reports.
    x : (n, 1) SX state symbols.
    params : (m, 1) SX parameter symbols (may be empty, ``SX(0, 1)``).
    drift : (n, 1) SX drift field ``f0(x, p)`` (include any constant input here).
    fields : input fields ``f_i(x, p)`` (each (n, 1) SX) of the *excited* inputs.
    field_names : a name per input field (for reports).
    outputs : (k, 1) SX measurement function ``h(x, p)``.
    state_names : n names of the state coordinates.
    tangent : (n, d) SX tangent basis ``T(x)``; identity when ``None``.
    tangent_names : d names of the tangent coordinates (defaults to ``state_names``).
    sampler : ``rng -> (x, p)`` drawing a *generic* point (used to select words).
    """

    name: str
    x: object
    params: object
    drift: object
    fields: Sequence[object]
    field_names: Sequence[str]
    outputs: object
    state_names: Sequence[str]
    tangent: Optional[object] = None
    tangent_names: Optional[Sequence[str]] = None
    sampler: Optional[Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray]]] = None

    @property
    def n(self) -> int:
        return int(self.x.numel())

    @property
    def dim(self) -> int:
        """Dimension the rank is compared with (tangent dimension)."""
        return self.n if self.tangent is None else int(self.tangent.shape[1])

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self.tangent_names or self.state_names)


@dataclass
class RankResult:
    """Outcome of one rank test at one point.

    Attributes
    ----------
    rank, dim : numerical rank of the tangent-projected matrix and the
        dimension it is compared with.
    singular_values : (dim,) singular values of the row-normalised matrix,
        descending (zeros appended when there are fewer rows than ``dim``).
    null_space : (dim, dim - rank) orthonormal basis of the unobservable
        tangent directions (right singular vectors of the dropped values).
    tol : relative tolerance used (``sigma_i > tol * sigma_max`` is kept);
        ``None`` = adaptive (rounding-noise floor, :func:`noise_floor`).
    cut : the absolute threshold the decision used.
    margin_decades : ``log10(smallest_kept / cut)``: how far the weakest kept
        direction is above the threshold (small = the verdict rests on a
        nearly degenerate geometry).
    col_scale : the characteristic scales the tangent columns were multiplied
        by (nondimensionalised states), or None.
    smallest_kept, largest_dropped : the two singular values around the cut
        (``largest_dropped`` is None when nothing was dropped).
    gap_decades : ``log10(smallest_kept / max(largest_dropped, eps sigma_max))``,
        the evidence of the decision (many decades = clear-cut).
    rows : number of Lie-derivative rows used.
    words : ``"pruned"`` or ``"all"`` (see module docstring).
    raw_rank, raw_dim : rank of the matrix before tangent projection and its
        column count (the seed's count, 19 for the UWB-IMU model).
    """

    rank: int
    dim: int
    singular_values: np.ndarray
    null_space: np.ndarray
    tol: Optional[float]
    smallest_kept: float
    largest_dropped: Optional[float]
    gap_decades: float
    rows: int
    words: str
    raw_rank: int
    raw_dim: int
    cut: float = 0.0
    margin_decades: float = float("inf")
    col_scale: Optional[np.ndarray] = None

    @property
    def full_rank(self) -> bool:
        return self.rank == self.dim


def numerical_rank(M: np.ndarray, tol: Optional[float] = None, row_ref: Optional[np.ndarray] = None):
    """Rank of ``M`` after normalising its rows, with the singular-value gap.

    Rows are scaled to unit norm first: rank is invariant to it, and it keeps
    high-order Lie derivatives (which carry powers of g and of the rates) from
    drowning the low-order ones.  Rows below ``ZERO_ROW_TOL`` times the largest
    row norm are rounding noise of identically-zero Lie derivatives and are
    dropped (see :data:`ZERO_ROW_TOL`).

    Parameters
    ----------
    tol : relative tolerance (``sigma_i > tol * sigma_max`` counts); ``None``
        (default) = the rounding-noise floor :func:`noise_floor` of the matrix.
    row_ref : (rows,) typical norm of each row (e.g. at a generic point); a row
        below ``ZERO_ROW_TOL`` of it is zero too.  Without it a matrix whose
        rows are *all* rounding noise (a lone vanishing gradient) would be
        normalised into rank.

    Returns
    -------
    rank, s (min(rows, cols),) singular values, Vt (cols, cols) right singular
    vectors, cut (the absolute threshold used).
    """
    M = np.asarray(M, dtype=float)
    ncol = M.shape[1]
    norms = np.linalg.norm(M, axis=1)
    keep = norms > max(ZERO_ROW_TOL * (norms.max() if norms.size else 0.0), 1e-300)
    if row_ref is not None:
        keep &= norms > ZERO_ROW_TOL * np.asarray(row_ref, float)
    if not np.any(keep):
        return 0, np.zeros(ncol), np.eye(ncol), 0.0
    Mn = M[keep] / norms[keep, None]
    rows = Mn.shape[0]
    if Mn.shape[0] < ncol:  # pad so that Vt is square (null space complete)
        Mn = np.vstack([Mn, np.zeros((ncol - Mn.shape[0], ncol))])
    # thin SVD: the U factor of a tall matrix is never needed
    _, s, Vt = np.linalg.svd(Mn, full_matrices=False)
    cut = noise_floor(s[0], rows) if tol is None else tol * s[0]
    rank = int(np.sum(s > cut))
    return rank, s, Vt, cut


def _as_dm(v):
    return np.asarray(v, dtype=float).reshape(-1)


class LieObservability:
    """Compiled observability matrix of a model up to a Lie order.

    Build once (per model structure and order) and evaluate at many points:
    ``matrix(x, p)`` and ``rank_test(x, p)``.

    Parameters
    ----------
    model : the :class:`ControlAffineModel`.
    order : maximal word length (Lie order), >= 0.
    prune : select words at generic points first (see module docstring).
    seed : RNG seed of the generic points used for word selection.
    """

    def __init__(self, model: ControlAffineModel, order: int, prune: bool = True, seed: int = 12345):
        import casadi as ca

        if order < 0:
            raise UsageError(f"Lie order must be >= 0, got {order}")
        self.model = model
        self.order = int(order)
        self._ca = ca
        x, p = model.x, model.params
        self._T = ca.Function("T", [x, p], [model.tangent if model.tangent is not None else ca.SX.eye(model.n)])
        self._all_fn = None
        self._all_rows = None
        self.pruned_words: list[tuple[str, ...]] = []
        self._pruned_fn = None
        if prune and model.sampler is not None:
            self._select_words(np.random.default_rng(seed))

    # ------------------------------------------------------------------
    def _alphabet(self):
        m = self.model
        return [("f0", m.drift)] + list(zip(m.field_names, m.fields))

    def _select_words(self, rng: np.random.Generator) -> None:
        """Greedy word selection at a generic point (see module docstring)."""
        ca = self._ca
        m = self.model
        # one generic point suffices (dependence at a generic point holds on a
        # neighbourhood); special points are covered by the all-words fallback.
        pts = [m.sampler(rng)]
        Ts = [np.asarray(self._T(xv, pv)) for xv, pv in pts]
        basis: list[np.ndarray] = []  # orthonormal rows (concatenated over points)
        kept_exprs, kept_words = [], []
        frontier = [((f"h{i}",), m.outputs[i]) for i in range(m.outputs.numel())]
        alphabet = self._alphabet()
        row_scale = 0.0
        for k in range(self.order + 1):
            if k == 0:
                cands = frontier
            else:
                cands = []
                for word, e in frontier:
                    for fname, f in alphabet:
                        le = ca.jtimes(e, m.x, f)
                        if not le.is_zero():
                            cands.append(((fname,) + word, le))
            if not cands:
                break
            G = ca.Function("g", [m.x, m.params], [ca.jacobian(ca.vertcat(*[c[1] for c in cands]), m.x)])
            rows = np.hstack([np.asarray(G(xv, pv)) @ T for (xv, pv), T in zip(pts, Ts)])
            frontier = []
            row_scale = max(row_scale, float(np.linalg.norm(rows, axis=1).max()))
            for (word, e), r in zip(cands, rows):
                nr = np.linalg.norm(r)
                if nr <= ZERO_ROW_TOL * row_scale:
                    continue
                v = r / nr
                for _ in range(2):  # re-orthogonalise for stability
                    for b in basis:
                        v = v - (b @ v) * b
                res = np.linalg.norm(v)
                if res > _SELECT_TOL:
                    basis.append(v / res)
                    kept_exprs.append(e)
                    kept_words.append(word)
                    frontier.append((word, e))
            if len(basis) >= m.dim:
                break
        self.pruned_words = kept_words
        self._pruned_fn = ca.Function(
            "O_pruned", [m.x, m.params], [ca.jacobian(ca.vertcat(*kept_exprs), m.x)]
        )

    def _build_all(self) -> None:
        """All words up to ``order`` (structural zeros removed); compiled lazily."""
        ca = self._ca
        m = self.model
        alphabet = self._alphabet()
        level = [m.outputs[i] for i in range(m.outputs.numel())]
        allL = list(level)
        for _ in range(self.order):
            nxt = []
            cur = ca.vertcat(*level)
            for _, f in alphabet:
                L = ca.jtimes(cur, m.x, f)
                nxt.extend(L[i] for i in range(L.numel()) if not L[i].is_zero())
            level = nxt
            allL.extend(level)
            if not level:
                break
        self._all_rows = len(allL)
        self._all_fn = ca.Function("O_all", [m.x, m.params], [ca.jacobian(ca.vertcat(*allL), m.x)])

    # ------------------------------------------------------------------
    def _row_floor(self, kind: str, OT: np.ndarray, D: np.ndarray) -> Optional[np.ndarray]:
        """Typical norm of each row of ``O T diag(D)`` (reference: a generic point of the
        model's sampler, unscaled), or None without a sampler."""
        if self.model.sampler is None:
            return None
        cache = self.__dict__.setdefault("_row_refs", {})
        if kind not in cache:
            xg, pg = self.model.sampler(np.random.default_rng(2024))
            fn = self._pruned_fn if kind == "pruned" else self._all_fn
            Og = np.asarray(fn(_as_dm(xg), _as_dm(pg))) @ self.tangent_basis(xg, pg)
            cache[kind] = np.linalg.norm(Og, axis=1)
        # column scaling changes every row norm by at most max(D) / min(D)
        return cache[kind] * float(np.min(D)) if len(cache[kind]) == OT.shape[0] else None

    def tangent_basis(self, x, p) -> np.ndarray:
        """(n, d) tangent basis at ``x``."""
        return np.asarray(self._T(_as_dm(x), _as_dm(p)))

    def matrix(self, x, p=(), words: str = "all", tangent: bool = True) -> np.ndarray:
        """Observability matrix (stacked Lie-derivative gradients) at ``(x, p)``.

        Parameters
        ----------
        words : ``"all"`` (every word up to the order) or ``"pruned"``.
        tangent : multiply by the tangent basis (columns = tangent coordinates).
        """
        x, p = _as_dm(x), _as_dm(p)
        if words == "pruned" and self._pruned_fn is not None:
            O = np.asarray(self._pruned_fn(x, p))
        else:
            if self._all_fn is None:
                self._build_all()
            O = np.asarray(self._all_fn(x, p))
        return O @ self.tangent_basis(x, p) if tangent else O

    def rank_test(
        self, x, p=(), tol: Optional[float] = None, words: str = "auto", col_scale: Optional[np.ndarray] = None
    ) -> RankResult:
        """Decide the rank at ``(x, p)``.

        ``words="auto"`` uses the pruned words and falls back to all words when
        they do not give full rank, or give it with ``sigma_min / sigma_max <
        PRUNED_MARGIN`` (see module docstring).  ``tol=None`` decides at the
        rounding-noise floor (:func:`noise_floor`).  ``col_scale`` (d,) are
        characteristic scales of the tangent coordinates: the columns are
        multiplied by them before the decision (nondimensionalised states), and
        the null space is mapped back to physical tangent coordinates.
        """
        x, p = _as_dm(x), _as_dm(p)
        T = self.tangent_basis(x, p)
        D = np.ones(T.shape[1]) if col_scale is None else np.asarray(col_scale, float)
        Ts = T * D[None, :]
        used = "pruned"
        if words in ("auto", "pruned") and self._pruned_fn is not None:
            O_raw = np.asarray(self._pruned_fn(x, p))
            rank, s, Vt, cut = numerical_rank(O_raw @ Ts, tol, self._row_floor("pruned", O_raw @ T, D))
            weak = rank == T.shape[1] and s[rank - 1] < PRUNED_MARGIN * s[0]
            if (rank < T.shape[1] or weak) and words == "auto":
                used = "all"
        else:
            used = "all"
        if used == "all":
            if self._all_fn is None:
                self._build_all()
            O_raw = np.asarray(self._all_fn(x, p))
            rank, s, Vt, cut = numerical_rank(O_raw @ Ts, tol, self._row_floor("all", O_raw @ T, D))
        d = T.shape[1]
        s_full = np.zeros(d)
        s_full[: min(d, len(s))] = s[:d]
        null = Vt[rank:].T * D[:, None]  # scaled null vectors -> physical tangent coordinates
        if null.shape[1]:
            null = np.linalg.qr(null)[0]
        eps_floor = np.finfo(float).eps * (s_full[0] if s_full[0] > 0 else 1.0)
        kept = float(s_full[rank - 1]) if rank > 0 else 0.0
        dropped = float(s_full[rank]) if rank < d else None
        denom = max(dropped if dropped is not None else 0.0, eps_floor)
        gap = float(np.log10(kept / denom)) if kept > 0 else 0.0
        margin = float(np.log10(kept / cut)) if kept > 0 and cut > 0 else (float("inf") if kept > 0 else 0.0)
        raw_rank = numerical_rank(O_raw, tol)[0]
        return RankResult(
            rank=rank,
            dim=d,
            singular_values=s_full,
            null_space=null,
            tol=tol,
            smallest_kept=kept,
            largest_dropped=dropped,
            gap_decades=gap,
            rows=int(O_raw.shape[0]),
            words=used,
            raw_rank=raw_rank,
            raw_dim=int(O_raw.shape[1]),
            cut=float(cut),
            margin_decades=margin,
            col_scale=None if col_scale is None else D,
        )


@dataclass
class ObservabilityCache:
    """Explicit per-process cache of compiled :class:`LieObservability` objects.

    Keys are hashable model specifications (e.g. a frozen dataclass) plus the
    Lie order; ``builder(spec)`` makes the :class:`ControlAffineModel`.
    """

    entries: dict = field(default_factory=dict)

    def get(self, spec, order: int, builder: Callable[[object], ControlAffineModel]) -> LieObservability:
        key = (spec, int(order))
        if key not in self.entries:
            self.entries[key] = LieObservability(builder(spec), order)
        return self.entries[key]

    def clear(self) -> None:
        self.entries.clear()
