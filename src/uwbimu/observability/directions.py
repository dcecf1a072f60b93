"""Naming unobservable directions in physical terms.

A null-space basis of the observability matrix is arbitrary up to rotation, so
directions are named by intersecting the null space with *candidate subspaces*
of known generators, in order of physical meaning:

1. world translations ``dp = t`` (a translation along the normal of the
   anchors' plane at a tag in that plane is the first-order trace of the
   mirror-image ambiguity and is named so);
2. single state blocks (e.g. "accelerometer bias along body z");
3. infinitesimal rigid motions of the world, ``dp = w x p + t, dv = w x v,
   dtheta = R^T w`` (named by their screw axis: yaw about a vertical line
   through a point, rotation about the line through two anchors, ...);
4. lever-arm / position trade-off ``dp = R e_j, dp_IU = -e_j`` (UWB-IMU model);
5. pairs of blocks ("gyro bias / attitude trade-off", "lever arm / accelerometer
   bias trade-off", ...).

What is left is reported by its dominant components.  Vectors are in the
model's tangent coordinates (18 for the UWB-IMU model, attitude as a body-frame
rotation vector), unit norm, largest component positive.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Sequence

import numpy as np

from uwbimu.models import state as ST
from uwbimu.models.blocks import BLOCK, BLOCKS
from uwbimu.models.quaternion import quat_to_rotmat

_COS_TOL = 1e-6  # 1 - cos(principal angle) below which a direction is shared

#: label and frame of each block of the ESKF state by its component-name prefix (``p``, ``th``, ``l``, ``td``),
#: from the declarations of :mod:`uwbimu.models.blocks` (other models' prefixes are named by themselves)
_BASE_BLOCKS = tuple(b for b in BLOCKS if b.multiplicity == "one")
BLOCK_LABELS = {b.symbol: (b.label, b.frame) for b in _BASE_BLOCKS}
#: the scalar blocks' names (a coordinate that is a block of its own: ``td``)
_LEVER = BLOCK["lever"].symbol
_SCALARS = frozenset(b.symbol for b in _BASE_BLOCKS if b.size == 1)


@dataclass
class Candidate:
    """A subspace of known generators and a function naming a member of it."""

    basis: np.ndarray  # (d, m)
    namer: Callable[[np.ndarray, np.ndarray], str]  # (coeffs, vector) -> name


def _fmt_vec(u: np.ndarray) -> str:
    return "[" + ", ".join(f"{c:+.2f}" for c in u) + "]"


def _axis_name(u: np.ndarray, frame: str = "") -> str:
    u = u / np.linalg.norm(u)
    i = int(np.argmax(np.abs(u)))
    suffix = f" ({frame})" if frame else ""
    if abs(u[i]) > 0.999:
        return f"{frame + ' ' if frame else ''}{'xyz'[i]}".strip() if frame else "xyz"[i]
    return _fmt_vec(u) + suffix


def dominant_components(vec: np.ndarray, names: Sequence[str], k: int = 4) -> str:
    """``"0.71 px - 0.70 lz"`` from the largest components of a unit vector."""
    order = np.argsort(-np.abs(vec))[:k]
    parts = [f"{vec[i]:+.2f} {names[i]}" for i in order if abs(vec[i]) > 0.15]
    return " ".join(parts) if parts else "(no dominant component)"


def _blocks(names: Sequence[str]) -> dict[str, list[int]]:
    """Group tangent coordinates by prefix (px,py,pz -> p; a declared scalar block: itself, td -> td)."""
    out: dict[str, list[int]] = {}
    for i, n in enumerate(names):
        key = n if n in _SCALARS else n[:-1]
        out.setdefault(key, []).append(i)
    return out


def _rigid_candidates(names, x_tangent_info, anchors) -> list[Candidate]:
    """Translations and rigid world motions for a state with p, v (and th)."""
    blocks = _blocks(names)
    d = len(names)
    p, v, R = x_tangent_info["p"], x_tangent_info["v"], x_tangent_info.get("R")
    anchors = np.asarray(anchors, dtype=float).reshape(-1, 3)
    T = np.zeros((d, 3))
    Rg = np.zeros((d, 6))
    for i in range(3):
        e = np.eye(3)[i]
        T[blocks["p"][i], i] = 1.0
        Rg[blocks["p"], i] = np.cross(e, p)
        Rg[blocks["v"], i] = np.cross(e, v)
        if R is not None and "th" in blocks:
            Rg[blocks["th"], i] = R.T @ e
        Rg[blocks["p"][i], 3 + i] = 1.0

    plane_normal = _anchor_plane_normal(anchors)
    scale = max(1.0, float(np.ptp(anchors, axis=0).max()) if len(anchors) else 1.0)
    tag = x_tangent_info.get("tag", p)

    # two anchors not on a vertical line: the vertical plane through them (a
    # height measurement cannot tell the mirror images through that plane apart)
    vplane_normal = None
    if len(anchors) == 2:
        d = anchors[1] - anchors[0]
        if np.linalg.norm(d[:2]) > 1e-9 * scale:
            vplane_normal = np.array([-d[1], d[0], 0.0]) / np.linalg.norm(d[:2])

    def name_translation(c, vec):
        t = c / np.linalg.norm(c)
        if plane_normal is not None and abs(t @ plane_normal) > 0.999:
            if abs((tag - anchors[0]) @ plane_normal) < 1e-6 * scale:
                return "displacement normal to the anchors' plane at a tag in that plane (mirror-image ambiguity)"
        if vplane_normal is not None and abs(t @ vplane_normal) > 0.999:
            if abs((tag - anchors[0]) @ vplane_normal) < 1e-6 * scale:
                return (
                    "displacement normal to the vertical plane through anchors 0 and 1 at a tag in that plane "
                    "(mirror-image ambiguity)"
                )
        return f"translation along {_axis_name(t, 'world')}"

    # The rigid-motion columns can be dependent at a point (point mass: a
    # rotation about the velocity direction plus a translation moves nothing);
    # the coefficients are then fixed up to that kernel, resolved below by
    # preferring a pure rotation (zero pitch).
    _, sv, Vt = np.linalg.svd(Rg)
    kernel = Vt[int(np.sum(sv > 1e-9 * sv[0])) :]

    def name_rigid(c, vec):
        c = np.array(c, dtype=float)
        if len(kernel) == 1:
            k = kernel[0]
            w0, t0, kw, kt = c[:3], c[3:], k[:3], k[3:]
            roots = np.roots([kw @ kt, w0 @ kt + kw @ t0, w0 @ t0]) if abs(kw @ kt) + abs(w0 @ kt + kw @ t0) > 0 else []
            real = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12]
            if real:
                c = c + min(real, key=abs) * k
        w, t = c[:3], c[3:]
        nw = np.linalg.norm(w)
        if nw < 1e-9 * max(1.0, np.linalg.norm(t)):
            return name_translation(t, vec)
        n = w / nw
        cpt = np.cross(w, t) / nw**2  # point on the axis closest to the origin
        cpt[np.abs(cpt) < 1e-9 * scale] = 0.0
        pitch = float(w @ t) / nw**2
        on_axis = [
            k for k, a in enumerate(anchors) if np.linalg.norm(np.cross(a - cpt, n)) < 1e-6 * scale
        ]
        screw = f" with pitch {pitch:+.3g} m/rad" if abs(pitch) > 1e-6 * scale else ""
        if len(on_axis) >= 2:
            kind = "global yaw about the vertical line" if abs(n[2]) > 0.999 else "rotation about the line"
            return f"{kind} through anchors {on_axis[0]} and {on_axis[1]}{screw}"
        if abs(n[2]) > 0.999:
            where = f"through anchor {on_axis[0]}" if on_axis else f"through ({cpt[0]:.3g}, {cpt[1]:.3g})"
            return f"global yaw about the vertical line {where}{screw}"
        where = f"anchor {on_axis[0]}" if on_axis else "(" + ", ".join(f"{c_:.3g}" for c_ in cpt) + ")"
        return f"rotation about axis {_fmt_vec(n)} through {where}{screw}"

    return [Candidate(T, name_translation), Candidate(Rg, name_rigid)]


def _anchor_plane_normal(anchors: np.ndarray) -> Optional[np.ndarray]:
    """Unit normal of the plane holding all anchors (None if not coplanar / < 3)."""
    if len(anchors) < 3:
        return None
    c = anchors - anchors.mean(axis=0)
    _, s, Vt = np.linalg.svd(c)
    scale = max(s[0], 1e-12)
    if s[1] < 1e-9 * scale:  # collinear: no unique plane
        return None
    if len(s) < 3 or s[2] < 1e-9 * scale:
        return Vt[2]
    return None


def _block_candidates(names) -> tuple[list[Candidate], list[Candidate]]:
    """Single-block and pair-of-blocks candidates."""
    blocks = _blocks(names)
    d = len(names)
    cands = []
    pairs = []
    keys = list(blocks)
    for key in keys:
        label, frame = BLOCK_LABELS.get(key, (key, ""))
        B = np.zeros((d, len(blocks[key])))
        for j, i in enumerate(blocks[key]):
            B[i, j] = 1.0

        def namer(c, vec, label=label, frame=frame):
            if len(c) == 1:
                return label
            return f"{label} along {_axis_name(c, frame)}"

        cands.append(Candidate(B, namer))
    for a in range(len(keys)):
        for b in range(a + 1, len(keys)):
            ia, ib = blocks[keys[a]], blocks[keys[b]]
            B = np.zeros((d, len(ia) + len(ib)))
            for j, i in enumerate(ia + ib):
                B[i, j] = 1.0
            la, lb = BLOCK_LABELS.get(keys[a], (keys[a], ""))[0], BLOCK_LABELS.get(keys[b], (keys[b], ""))[0]

            def namer(c, vec, la=la, lb=lb):
                return f"{la} / {lb} trade-off: {dominant_components(vec, names)}"

            pairs.append(Candidate(B, namer))
    return cands, pairs


def candidates_for(
    model_kind: str, names: Sequence[str], x: np.ndarray, anchors, gyro_reading: Optional[np.ndarray] = None
) -> list[Candidate]:
    """Candidate generator subspaces at a state of a built-in model, in naming order.

    Order: translations, single state blocks, rigid motions, lever-arm /
    position trade-off (UWB-IMU), pairs of blocks.

    Parameters
    ----------
    model_kind : ``"uwb_imu"`` (x = 19 numbers ``p, v, q, b_a, b_g, p_IU``) or
        ``"point_mass"`` (x = ``p, v``).
    names : tangent coordinate names.
    anchors : (N, 3) anchor/beacon positions (world, m).
    gyro_reading : (3,) constant gyro reading ``w_m`` [rad/s, body] when the
        gyro is not excited (UWB-IMU model).  Adds the constant-rotation
        lever-arm generator: with ``w = w_m - b_g`` constant, moving the lever
        arm by ``e`` and the IMU by ``dp = -R e, dv = -R [w]x e`` with
        ``db_a = [w]x^2 e`` keeps the antenna's path and the IMU readings
        consistent, for every ``e``.
    """
    x = np.asarray(x, dtype=float)
    info = {"p": x[ST.P], "v": x[ST.V]}
    extra: list[Candidate] = []
    if model_kind == "uwb_imu":
        R = quat_to_rotmat(x[ST.Q])
        info["R"] = R
        info["tag"] = x[ST.P] + R @ x[ST.PIU]
        blocks = _blocks(names)
        L = np.zeros((len(names), 3))
        for j in range(3):
            L[blocks["p"], j] = R[:, j]
            L[blocks[_LEVER][j], j] = -1.0

        def name_lever(c, vec):
            return f"position / lever-arm trade-off along body {_axis_name(c)} (antenna fixed, IMU moves)"

        extra.append(Candidate(L, name_lever))
        if gyro_reading is not None:
            w = np.asarray(gyro_reading, float) - x[ST.BG]
            W = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
            C = np.zeros((len(names), 3))
            for j in range(3):
                e = np.eye(3)[j]
                C[blocks["p"], j] = -R @ e
                C[blocks["v"], j] = -R @ (W @ e)
                C[blocks[BLOCK["b_a"].symbol], j] = W @ (W @ e)
                C[blocks[_LEVER][j], j] = 1.0

            def name_rot_lever(c, vec):
                return (
                    f"lever arm / IMU position, velocity, accelerometer bias trade-off along body {_axis_name(c)} "
                    "under constant rotation (antenna path fixed)"
                )

            extra.append(Candidate(C, name_rot_lever))
    translation, rigid = _rigid_candidates(names, info, anchors)
    singles, pairs = _block_candidates(names)
    return [translation] + singles + [rigid] + extra + pairs


def _orth(B: np.ndarray) -> np.ndarray:
    U, s, _ = np.linalg.svd(B, full_matrices=False)
    if s.size == 0 or s[0] == 0:
        return np.zeros((B.shape[0], 0))
    return U[:, s > 1e-10 * s[0]]


def _canonical_sign(v: np.ndarray) -> np.ndarray:
    i = int(np.argmax(np.abs(v)))
    return v if v[i] >= 0 else -v


def name_directions(null_space: np.ndarray, candidates: Sequence[Candidate], names: Sequence[str]) -> list[dict]:
    """Name the columns of a null-space basis (see module docstring).

    Returns a list of ``{"name": str, "vector": list[float]}``, one per
    null-space dimension.
    """
    N = np.asarray(null_space, dtype=float)
    out: list[dict] = []
    if N.size == 0 or N.shape[1] == 0:
        return out
    N = _orth(N)
    for cand in candidates:
        if N.shape[1] == 0:
            break
        Q = _orth(cand.basis)
        if Q.shape[1] == 0:
            continue
        U, s, _ = np.linalg.svd(N.T @ Q, full_matrices=False)
        shared = [i for i in range(len(s)) if s[i] > 1 - _COS_TOL]
        if not shared:
            continue
        for i in shared:
            v = _canonical_sign(N @ U[:, i])
            v /= np.linalg.norm(v)
            coeffs, *_ = np.linalg.lstsq(cand.basis, v, rcond=None)
            out.append({"name": cand.namer(coeffs, v), "vector": v.tolist()})
        # deflate: keep the part of the null space orthogonal to the named
        # directions (principal vectors N U[:, i] are orthonormal)
        V = N @ U[:, shared]
        Nd = N - V @ (V.T @ N)
        Ud, sd, _ = np.linalg.svd(Nd, full_matrices=False)
        N = Ud[:, sd > 0.5]  # surviving directions keep unit singular values
    for j in range(N.shape[1]):
        v = _canonical_sign(N[:, j])
        out.append({"name": "unnamed: " + dominant_components(v, names), "vector": v.tolist()})
    return out
