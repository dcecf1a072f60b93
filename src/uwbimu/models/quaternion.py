"""Hamilton unit quaternions and SO(3) utilities (NumPy, batched).

Conventions
-----------
* Quaternions are Hamilton, stored ``[qw, qx, qy, qz]``.
* A quaternion ``q`` of the state rotates IMU-body vectors into the world
  frame: ``v_world = R(q) @ v_body``.
* Rotation vectors (``so(3)`` tangent vectors) are in radians.
* Attitude perturbations are *right* (body-frame) perturbations:
  ``q_true = q_nominal ⊗ Exp(dtheta)``; this is the convention of the ESKF.

All functions accept a single element (``(4,)``, ``(3,)``, ``(3, 3)``) or a
batch with leading dimensions (``(..., 4)`` etc.) and return arrays of the
matching shape.  The symbolic (CasADi) counterparts used by the observability
engine live in :mod:`uwbimu.models.reference` and are pinned to these by tests.
"""

from __future__ import annotations

from uwbimu.errors import InputError
import numpy as np

__all__ = [
    "skew",
    "quat_normalize",
    "quat_multiply",
    "quat_conjugate",
    "quat_to_rotmat",
    "rotmat_to_quat",
    "so3_exp",
    "so3_log",
    "quat_exp",
    "quat_log",
    "quat_rotate",
    "quat_identity",
    "quat_slerp",
    "omega_matrix",
]

_SMALL_ANGLE = 1e-8


def quat_identity() -> np.ndarray:
    """Identity quaternion ``[1, 0, 0, 0]``."""
    return np.array([1.0, 0.0, 0.0, 0.0])


def skew(v: np.ndarray) -> np.ndarray:
    """Skew-symmetric cross-product matrix ``[v]x`` so that ``[v]x @ w = v x w``."""
    v = np.asarray(v, dtype=float)
    out = np.zeros(v.shape[:-1] + (3, 3))
    out[..., 0, 1] = -v[..., 2]
    out[..., 0, 2] = v[..., 1]
    out[..., 1, 0] = v[..., 2]
    out[..., 1, 2] = -v[..., 0]
    out[..., 2, 0] = -v[..., 1]
    out[..., 2, 1] = v[..., 0]
    return out


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with non-negative scalar part (canonical sign)."""
    q = np.asarray(q, dtype=float)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(n == 0):
        raise InputError("cannot normalise a zero quaternion")
    q = q / n
    sign = np.where(q[..., :1] < 0, -1.0, 1.0)
    return q * sign


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p ⊗ q`` (apply ``q`` first, then ``p``)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """Conjugate (inverse for unit quaternions)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix ``R(q)`` (body to world) of a unit quaternion."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    out = np.empty(q.shape[:-1] + (3, 3))
    out[..., 0, 0] = 1 - 2 * (y * y + z * z)
    out[..., 0, 1] = 2 * (x * y - w * z)
    out[..., 0, 2] = 2 * (x * z + w * y)
    out[..., 1, 0] = 2 * (x * y + w * z)
    out[..., 1, 1] = 1 - 2 * (x * x + z * z)
    out[..., 1, 2] = 2 * (y * z - w * x)
    out[..., 2, 0] = 2 * (x * z - w * y)
    out[..., 2, 1] = 2 * (y * z + w * x)
    out[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return out


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (``qw >= 0``) of a rotation matrix.

    Uses the numerically robust branch selection of Shepperd's method,
    vectorised over any batch shape.
    """
    R = np.asarray(R, dtype=float)
    batch = R.shape[:-2]
    m = R.reshape(-1, 3, 3)
    m00, m01, m02 = m[:, 0, 0], m[:, 0, 1], m[:, 0, 2]
    m10, m11, m12 = m[:, 1, 0], m[:, 1, 1], m[:, 1, 2]
    m20, m21, m22 = m[:, 2, 0], m[:, 2, 1], m[:, 2, 2]
    # 4 w^2, 4 x^2, 4 y^2, 4 z^2: the largest (>= 1 for a rotation) is taken
    # from the diagonal, the other components from off-diagonal sums.
    args = np.stack([1.0 + m00 + m11 + m22, 1.0 + m00 - m11 - m22,
                     1.0 - m00 + m11 - m22, 1.0 - m00 - m11 + m22], axis=1)
    choice = np.argmax(args, axis=1)
    s = 2.0 * np.sqrt(np.take_along_axis(args, choice[:, None], axis=1)[:, 0])
    a, b, c = (m21 - m12) / s, (m02 - m20) / s, (m10 - m01) / s
    d, e, f = (m01 + m10) / s, (m02 + m20) / s, (m12 + m21) / s
    h = 0.25 * s
    cand = np.stack([
        np.stack([h, a, b, c], axis=1),
        np.stack([a, h, d, e], axis=1),
        np.stack([b, d, h, f], axis=1),
        np.stack([c, e, f, h], axis=1),
    ], axis=1)  # (N, branch, 4)
    q = np.take_along_axis(cand, choice[:, None, None], axis=1)[:, 0]
    return quat_normalize(q).reshape(batch + (4,))


def quat_exp(rotvec: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation vector: ``Exp(phi) = [cos(|phi|/2), sin(|phi|/2) phi/|phi|]``."""
    phi = np.asarray(rotvec, dtype=float)
    angle = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * angle
    small = angle < _SMALL_ANGLE
    # sin(a/2)/a with its Taylor series near zero keeps the map smooth at 0.
    safe = np.where(small, 1.0, angle)
    k = np.where(small, 0.5 - angle**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([np.cos(half), k * phi], axis=-1)


def quat_log(q: np.ndarray) -> np.ndarray:
    """Rotation vector of a unit quaternion, angle in ``[0, pi]``."""
    q = quat_normalize(q)
    w = np.clip(q[..., :1], -1.0, 1.0)
    v = q[..., 1:]
    vn = np.linalg.norm(v, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(vn, w)
    small = vn < _SMALL_ANGLE
    # np.where evaluates both branches for every element, so each divisor is
    # made safe for the elements that take the *other* branch.  In the small
    # branch the quaternion is unit with w >= 0 (canonical sign), so w ~ 1 and
    # 2 atan2(|v|, w) / |v| = 2 / w up to O(|v|^2) < 1e-16 relative.
    safe_vn = np.where(small, 1.0, vn)
    safe_w = np.where(small, w, 1.0)
    k = np.where(small, 2.0 / safe_w, angle / safe_vn)
    return k * v


def so3_exp(rotvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (Rodrigues)."""
    return quat_to_rotmat(quat_exp(rotvec))


def so3_log(R: np.ndarray) -> np.ndarray:
    """Rotation vector of a rotation matrix."""
    return quat_log(rotmat_to_quat(R))


def quat_rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Rotate body vectors ``v`` into the world: ``R(q) @ v``."""
    R = quat_to_rotmat(q)
    return np.einsum("...ij,...j->...i", R, np.asarray(v, dtype=float))


def quat_slerp(q0: np.ndarray, q1: np.ndarray, alpha: np.ndarray | float) -> np.ndarray:
    """Spherical interpolation from ``q0`` (alpha=0) to ``q1`` (alpha=1)."""
    q0 = np.asarray(q0, dtype=float)
    q1 = np.asarray(q1, dtype=float)
    # Take the short way round: q and -q are the same rotation.
    dot = np.sum(q0 * q1, axis=-1, keepdims=True)
    q1 = np.where(dot < 0, -q1, q1)
    delta = quat_log(quat_multiply(quat_conjugate(q0), q1))
    a = np.asarray(alpha, dtype=float)[..., None] if np.ndim(alpha) else float(alpha)
    return quat_multiply(q0, quat_exp(a * delta))


def omega_matrix(w: np.ndarray) -> np.ndarray:
    """``Omega(w)`` of seed eq. (4): ``q_dot = 0.5 * Omega(w) @ q`` for body rate ``w``.

    ``Omega(w) = [[0, -w^T], [w, -[w]x]]`` with ``q = [qw, qx, qy, qz]``.
    """
    w = np.asarray(w, dtype=float)
    out = np.zeros(w.shape[:-1] + (4, 4))
    out[..., 0, 1:] = -w
    out[..., 1:, 0] = w
    out[..., 1:, 1:] = -skew(w)
    return out


def quat_from_euler(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """``q = Rz(yaw) Ry(pitch) Rx(roll)`` (body -> world, ZYX Euler angles [rad]), Hamilton ``[w, x, y, z]``."""
    qz = np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])
    qy = np.array([np.cos(pitch / 2), 0.0, np.sin(pitch / 2), 0.0])
    qx = np.array([np.cos(roll / 2), np.sin(roll / 2), 0.0, 0.0])
    return quat_multiply(qz, quat_multiply(qy, qx))
