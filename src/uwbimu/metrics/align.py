"""Rigid alignment of an estimated trajectory to ground truth in another frame.

The estimate lives in the anchors' (UWB) frame; ground truth may live in a
motion-capture or Vive frame with no documented transform between the two.
Before comparing positions we therefore fit the transform

    p_gt ≈ R @ p_est + t

by least squares (Horn / Umeyama without scale).  The rotation of the
centred point sets is found with :meth:`scipy.spatial.transform.Rotation.align_vectors`
(a maintained Kabsch/SVD implementation that always returns a proper rotation).

Modes
-----
``none``      R = I, t = 0 (estimate and truth share a frame, e.g. simulation).
``position``  R = I, t = mean(p_gt - p_est) (shared orientation, unknown origin).
``se3``       full rotation + translation (frames unrelated, e.g. ISAS-Walk).
"""

from __future__ import annotations

from uwbimu.errors import InputError, UsageError
from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np
from scipy.spatial.transform import Rotation

from uwbimu.models.quaternion import quat_multiply, rotmat_to_quat

AlignMode = Literal["none", "position", "se3"]
ALIGN_MODES = ("none", "position", "se3")


@dataclass(frozen=True)
class GroundTruthFrame:
    """How a dataset's ground truth relates to the estimate's (anchors') frame.

    Read from ``dataset.yaml`` ``extra`` by :func:`groundtruth_frame`: the one rule for every
    place that compares an estimate with the ground truth (console, metrics, report).

    Attributes
    ----------
    align : str
        Alignment mode the comparison needs (``extra.groundtruth_align``, default ``"none"``).
    attitude_comparable : bool
        The ground truth's body frame is the IMU frame (``extra.groundtruth_attitude_comparable``,
        default True); False: attitudes are not compared.
    """

    align: str = "none"
    attitude_comparable: bool = True

    @property
    def frames_agree(self) -> bool:
        """True when raw (unaligned) comparisons with the ground truth are meaningful."""
        return self.align == "none"


def groundtruth_frame(meta_extra: Optional[dict]) -> GroundTruthFrame:
    """The ground-truth frame rule of a dataset from its ``meta.extra`` mapping (None: same frame).

    Raises
    ------
    uwbimu.errors.InputError
        ``groundtruth_align`` is not one of :data:`ALIGN_MODES`.
    """
    from uwbimu.errors import InputError

    extra = meta_extra or {}
    align = str(extra.get("groundtruth_align", "none"))
    if align not in ALIGN_MODES:
        raise InputError(f"dataset.yaml extra.groundtruth_align must be one of {', '.join(ALIGN_MODES)}, "
                         f"got '{align}'")
    return GroundTruthFrame(align=align,
                            attitude_comparable=bool(extra.get("groundtruth_attitude_comparable", True)))


@dataclass
class Alignment:
    """Transform taking estimate-frame coordinates into the ground-truth frame.

    Attributes
    ----------
    mode : alignment mode used.
    R : (3, 3) rotation, estimate frame -> ground-truth frame.
    t : (3,) translation [m], ground-truth frame.
    n_points : number of point pairs the fit used.
    rms_fit : RMS position residual of the fit [m].
    """

    mode: str
    R: np.ndarray = field(default_factory=lambda: np.eye(3))
    t: np.ndarray = field(default_factory=lambda: np.zeros(3))
    n_points: int = 0
    rms_fit: float = float("nan")

    def apply_positions(self, p: np.ndarray) -> np.ndarray:
        """Map (N, 3) estimate-frame positions into the ground-truth frame."""
        return np.asarray(p, float) @ self.R.T + self.t

    def apply_quaternions(self, q: np.ndarray) -> np.ndarray:
        """Map (N, 4) body->estimate-frame quaternions to body->ground-truth-frame."""
        q_align = rotmat_to_quat(self.R)
        return quat_multiply(np.broadcast_to(q_align, np.shape(q)), np.asarray(q, float))

    def as_dict(self) -> dict:
        return {
            "mode": self.mode,
            "rotation_matrix": self.R.tolist(),
            "rotation_deg": float(np.degrees(np.linalg.norm(Rotation.from_matrix(self.R).as_rotvec()))),
            "translation": self.t.tolist(),
            "n_points": int(self.n_points),
            "rms_fit": float(self.rms_fit),
        }


def align_trajectories(
    p_est: np.ndarray,
    p_gt: np.ndarray,
    mode: AlignMode = "se3",
    weights: Optional[np.ndarray] = None,
) -> Alignment:
    """Fit the transform ``p_gt ≈ R p_est + t`` for matched point pairs.

    Parameters
    ----------
    p_est, p_gt : (N, 3) matched positions [m] (estimate frame, ground-truth frame).
    mode : ``"none" | "position" | "se3"``.
    weights : optional (N,) non-negative weights.

    Returns
    -------
    Alignment

    Raises
    ------
    ValueError
        Unknown mode, mismatched shapes, too few points, or (for ``se3``) points
        so degenerate (all on one line) that the rotation is undetermined.
    """
    if mode not in ALIGN_MODES:
        raise UsageError(f"align mode must be one of {ALIGN_MODES}, got {mode!r}")
    a = np.asarray(p_est, float)
    b = np.asarray(p_gt, float)
    if a.shape != b.shape or a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"need two (N, 3) arrays of equal shape, got {a.shape} and {b.shape}")
    n = a.shape[0]
    if n == 0:
        raise InputError("no matched points to align")
    w = np.ones(n) if weights is None else np.asarray(weights, float)
    w = w / w.sum()
    R = np.eye(3)
    if mode == "none":
        t = np.zeros(3)
    elif mode == "position":
        t = w @ (b - a)
    else:
        if n < 3:
            raise InputError(f"se3 alignment needs at least 3 points, got {n}")
        ca = w @ a
        cb = w @ b
        A = a - ca
        B = b - cb
        # A line (rank < 2) leaves the rotation about it undetermined.
        sv = np.linalg.svd(A, compute_uv=False)
        if sv[1] < 1e-6 * max(sv[0], 1e-12) or sv[0] < 1e-9:
            raise InputError("se3 alignment is undetermined: the trajectory is (nearly) a straight line or a point")
        rot, _ = Rotation.align_vectors(B, A, weights=w)
        R = rot.as_matrix()
        t = cb - R @ ca
    res = a @ R.T + t - b
    rms = float(np.sqrt(w @ np.sum(res**2, axis=1)))
    return Alignment(mode=mode, R=R, t=t, n_points=n, rms_fit=rms)
