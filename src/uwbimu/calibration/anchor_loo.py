"""The self-survey's systematic error, measured on the surveyed anchors (linearised leave-one-out).

The marginal sigma of an estimated anchor assumes white range errors.  Real range errors depend on the
line of sight (antenna pattern, multipath); a range error that varies with the direction of the line of
sight at the anchor moves the anchor's estimate, and one linear in that direction is *exactly* a shift of
the anchor (``d range / d anchor = -u``, the unit line of sight): no residual, no sandwich can see it in the
estimated anchor's own ranges.  On INRoL the self-surveyed anchors were off by 7-71 cm with sigma of 2-4 cm.

The surveyed anchors measure it.  For each one, :func:`surveyed_anchor_displacements` asks: had this anchor
been estimated as well, where would the log have put it?  One Gauss-Newton step from the solution with its
position freed (the Schur complement of the three new columns in the solved, whitened and IRLS-weighted
linear system) gives its displacement ``d_j`` and the white model's covariance ``C_j`` of that displacement.
Under the white model ``E d_j d_j^T = C_j``; what ``d_j`` has beyond it is the range model's systematic error,
as an estimated anchor would take it.  :func:`systematic_variance` pools the surveyed anchors (isotropic, per
axis)::

    s^2 = max(0, sum_j (|d_j|^2 - tr C_j) / (3 n))

and the calibrator adds ``s^2 I`` to every estimated anchor's covariance (``calibration.yaml``
``anchors.systematic``).  Assumption (stated in the report): the estimated anchors' range errors are like the
surveyed ones'.  On INRoL (all 8 anchors surveyed) the displacements were 8-54 cm, of the order of the errors of
the same anchors when actually self-surveyed (docs/calibrate.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from uwbimu.calibration import keys
from uwbimu.calibration.graph import _group_chunks
from uwbimu.calibration.covariance import _SymmetricFactor, linear_system
from uwbimu.calibration.range_factor import RangeGroup


@dataclass
class AnchorDisplacement:
    """The linearised leave-one-out of one surveyed anchor: ``displacement`` (3,) [m, world] of its position had
    it been estimated, ``cov_white`` (3, 3) [m^2] that displacement's covariance under the white range model,
    ``rows``: the ranges it rests on."""

    anchor: str
    displacement: np.ndarray
    cov_white: np.ndarray
    rows: int

    @property
    def mahalanobis(self) -> float:
        d = self.displacement
        return float(np.sqrt(d @ np.linalg.solve(self.cov_white, d)))


def lines_of_sight(pb, assoc, values, td: float, rows: np.ndarray) -> np.ndarray:
    """(n, 3) unit vectors from the anchor to the tag antenna [world] of the used range rows ``rows`` (indices into
    ``assoc.used``), at the solution ``values`` and time offset ``td`` (the range factors' own kinematics, in the
    graph's blocks of keyframes)."""
    K = len(pb.key_idx)
    poses = [values.atPose3(keys.pose(k)) for k in range(K)]
    R_k = np.array([q.rotation().matrix() for q in poses])
    p_k = np.array([q.translation() for q in poses])
    v_k = np.array([values.atVector(keys.velocity(k)) for k in range(K)])
    rows = np.asarray(rows, np.int64)
    pos = np.full(len(assoc.used), -1, np.int64)
    pos[rows] = np.arange(len(rows))
    out = np.zeros((len(rows), 3))
    for chunk in _group_chunks(pb, assoc, rows):
        used = assoc.used[chunk]
        kfs, kf = np.unique(np.asarray(assoc.key)[chunk], return_inverse=True)
        grp = RangeGroup([assoc.deltas[r] for r in chunk], pb.anchor_pos[pb.anchor_j[used]], pb.rho[used],
                         np.zeros(len(chunk), np.int64), assoc.td0, kf=kf)
        lever = values.atVector(keys.lever_arm(pb.tag_of(int(used[0]))))
        u = grp._geometry(R_k[kfs], p_k[kfs], v_k[kfs], lever, td)["u"]
        out[pos[chunk]] = u / np.linalg.norm(u, axis=1)[:, None]
    return out


def surveyed_anchor_displacements(pb, graph, values, assoc, td: float) -> tuple[list[AnchorDisplacement], dict]:
    """Linearised leave-one-out displacement of every surveyed (fixed) anchor with ranges (module docstring).

    Each range row of anchor ``j`` gains the column block ``s_i (-u_i^T)``, ``s_i`` the row's whitening and IRLS
    weight as linearised (read off its anchor-bias column, ``d e / d bias = 1``); with ``J``, ``b`` the solved
    system, ``S = A^T A - A^T J H^-1 J^T A`` and ``d = S^-1 (A^T b - A^T J H^-1 J^T b)``, ``C = S^-1``.
    TDoA rows are not used (their anchor enters twice); an anchor with fewer than 10 range rows, or whose ranges do
    not define its position (a singular ``S``), is skipped; returns the displacements and ``{anchor: reason}`` of
    the surveyed anchors skipped.
    """
    J, b, row0, cols = linear_system(graph, values)
    slots = np.asarray(assoc.slots, np.int64)
    row_index = row0[slots[:, 0]] + slots[:, 1]
    is_range = np.ones(len(assoc.used), bool) if pb.anchor_b is None else pb.anchor_b[assoc.used] < 0
    aj = pb.anchor_j[assoc.used]
    fixed = np.array([not pb.estimated(j) for j in range(len(pb.anchor_ids))], bool)
    cand = np.flatnonzero(is_range & fixed[aj])  # every range row of a surveyed anchor: lines of sight at once
    U = lines_of_sight(pb, assoc, values, td, cand) if len(cand) else np.zeros((0, 3))
    at = np.full(len(assoc.used), -1, np.int64)
    at[cand] = np.arange(len(cand))
    lu = None
    out, skipped = [], {}
    Jc = J.tocsc()
    for j, aid in enumerate(pb.anchor_ids):
        if pb.estimated(j):
            continue
        m = np.flatnonzero(is_range & (aj == j))
        if len(m) < 10:
            skipped[str(aid)] = f"{len(m)} range rows (TDoA rows are not used)"
            continue
        if lu is None:
            lu = _SymmetricFactor((J.T @ J).tocsc())
            hb = lu.solve(np.asarray(J.T @ b).ravel())
        s = np.asarray(Jc[row_index[m]][:, cols[int(keys.anchor_bias(j))]].todense()).ravel()
        if not np.any(s):  # no bias column to read the rows' weights from: nothing to free
            skipped[str(aid)] = "its range rows carry no weight"
            continue
        u = U[at[m]]
        vals = (-u * s[:, None]).ravel()
        Aj = sp.csr_matrix((vals, (np.repeat(row_index[m], 3), np.tile(np.arange(3), len(m)))), shape=(J.shape[0], 3))
        JA = np.asarray((J.T @ Aj).todense())
        S = np.asarray((Aj.T @ Aj).todense()) - JA.T @ lu.solve(JA)
        g = np.asarray(Aj.T @ b).ravel() - JA.T @ hb
        try:
            C = np.linalg.inv(0.5 * (S + S.T))
        except np.linalg.LinAlgError:  # seen from one direction only: its position is not defined by its ranges
            C = np.full((3, 3), np.nan)
        if not np.all(np.isfinite(C)):
            skipped[str(aid)] = "its ranges do not define its position"
            continue
        out.append(AnchorDisplacement(anchor=str(aid), displacement=C @ g, cov_white=0.5 * (C + C.T), rows=len(m)))
    return out, skipped


def systematic_variance(disp: list[AnchorDisplacement]) -> tuple[float | None, float]:
    """Pooled per-axis variance ``s^2`` [m^2] of the surveyed anchors' displacements beyond the white model
    (``None`` without any), and the raw estimate before the clip at 0 (``sum (|d|^2 - tr C) / 3n``)."""
    if not disp:
        return None, float("nan")
    raw = float(np.mean([d.displacement @ d.displacement - np.trace(d.cov_white) for d in disp]) / 3.0)
    return max(0.0, raw), raw


def report(disp: list[AnchorDisplacement], s2: float | None, raw: float, applied: bool, skipped: dict) -> dict:
    """``calibration.yaml`` ``anchors.systematic``."""
    return {
        "method": "linearised leave-one-out of the surveyed anchors",
        "applied": bool(applied and s2 is not None),
        "sd": None if s2 is None else float(np.sqrt(s2)),
        "variance_raw": raw if np.isfinite(raw) else None,
        "surveyed_anchors_used": len(disp),
        "surveyed_anchors_skipped": dict(skipped),
        "displacements": {d.anchor: {"displacement": [float(x) for x in d.displacement],
                                     "sd_white": [float(x) for x in np.sqrt(np.diag(d.cov_white))],
                                     "mahalanobis": d.mahalanobis, "rows": d.rows} for d in disp},
        "assumption": "the estimated anchors' direction-dependent range errors are like the surveyed anchors'",
    }
