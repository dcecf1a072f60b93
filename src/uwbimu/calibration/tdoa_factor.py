"""The TDoA factor of the batch calibrator: the difference of two range residuals.

A TDoA ``z = |p_U - p_b| - |p_U - p_a|`` [m] stamped ``t`` (UWB clock) observes the antenna at IMU time
``t + t_d`` exactly as a range does (:mod:`uwbimu.calibration.range_factor`: same keyframe, same IMU
delta, same time-offset extrapolation), so its residual is

    e = (|p_U(s) - p_b| + b_b) - (|p_U(s) - p_a| + b_a) - z

and its Jacobians are the difference of the two range rows (the anchor biases enter as ``b_b - b_a``).
Pinned to :func:`uwbimu.models.reference.tdoa_measurement` by ``tests/test_calibrate_factor.py``.
"""

from __future__ import annotations

import numpy as np

from uwbimu.calibration.range_factor import RangeDelta, RangeGroup, range_error


def tdoa_error(R_k, p_k, v_k, lever, td, bias_a, bias_b, anchor_a, anchor_b, z, d: RangeDelta, td0: float,
               jacobians: bool = False):
    """Residual ``e`` [m] of one TDoA and, on request, its Jacobians (pose (6,), velocity (3,), lever
    arm (3,), t_d, and ``-1`` / ``+1`` for the biases of anchors a and b)."""
    ra = range_error(R_k, p_k, v_k, lever, td, bias_a, anchor_a, 0.0, d, td0, jacobians)
    rb = range_error(R_k, p_k, v_k, lever, td, bias_b, anchor_b, 0.0, d, td0, jacobians)
    if not jacobians:
        return rb - ra - z
    ea, Jpa, Jva, Jla, Jta = ra
    eb, Jpb, Jvb, Jlb, Jtb = rb
    return eb - ea - z, Jpb - Jpa, Jvb - Jva, Jlb - Jla, Jtb - Jta


def make_gtsam_tdoa_factor(keys, anchor_a, anchor_b, z, d: RangeDelta, td0: float, noise,
                           td_fixed: float | None = None):
    """A ``gtsam.CustomFactor`` on ``[pose, velocity, lever arm, (t_d), bias_a, bias_b]``.

    With ``td_fixed`` the time offset is a constant (profile points) and ``keys`` has no t_d key.
    ``bias_a`` and ``bias_b`` may be the same key only when ``a == b``, which the loader refuses.
    """
    import gtsam

    anchor_a = np.asarray(anchor_a, float)
    anchor_b = np.asarray(anchor_b, float)
    has_td = td_fixed is None

    def error(this, values, H):
        ks = this.keys()
        pose = values.atPose3(ks[0])
        td = values.atVector(ks[3])[0] if has_td else td_fixed
        ba = values.atVector(ks[-2])[0]
        bb = values.atVector(ks[-1])[0]
        res = tdoa_error(pose.rotation().matrix(), pose.translation(), values.atVector(ks[1]),
                         values.atVector(ks[2]), td, ba, bb, anchor_a, anchor_b, z, d, td0,
                         jacobians=H is not None)
        if H is None:
            return np.array([res])
        e, Jp, Jv, Jl, Jt = res
        H[0] = Jp.reshape(1, 6)
        H[1] = Jv.reshape(1, 3)
        H[2] = Jl.reshape(1, 3)
        if has_td:
            H[3] = np.array([[Jt]])
        H[-2] = -np.ones((1, 1))
        H[-1] = np.ones((1, 1))
        return np.array([e])

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


class TdoaGroup:
    """The TDoA rows of a few consecutive keyframes, evaluated together: each row is :func:`tdoa_error`, i.e. the
    range to anchor b minus the range to anchor a at the same instant, computed by two
    :class:`~uwbimu.calibration.range_factor.RangeGroup` (compiled row loop) on the same IMU deltas.

    It offers what :func:`~uwbimu.calibration.range_factor.make_gtsam_group_factor` and the graph's residual
    helpers use of a ``RangeGroup`` (no direction model, no estimated anchors: those keep one factor per row).

    Parameters
    ----------
    deltas : the rows' :class:`RangeDelta`.
    anchors_a, anchors_b : (N, 3) positions of each row's anchors a and b [m] (world).
    z : (N,) measured TDoA [m].
    bias_matrix : (N, nb) signed: +1 in anchor b's bias column, -1 in anchor a's (``e`` gains ``b_b - b_a``).
    td0 : the association's time offset [s].
    kf : (N,) each row's keyframe among the group's keyframes.
    """

    direction = anchor_direction = anchor_var = None
    n_dir = n_adir = n_apos = 0
    dir_mask: list = []

    def __init__(self, deltas, anchors_a, anchors_b, z, bias_matrix, td0: float, kf=None):
        n = len(z)
        self.bias_matrix = np.asarray(bias_matrix, float)
        zero = np.zeros(n, np.int64)
        self._a = RangeGroup(deltas, anchors_a, np.zeros(n), zero, td0, bias_matrix=np.zeros_like(self.bias_matrix),
                             kf=kf)
        self._b = RangeGroup(deltas, anchors_b, z, zero, td0, bias_matrix=self.bias_matrix, kf=kf)
        self.n_kf, self.kf_mask = self._b.n_kf, self._b.kf_mask

    @property
    def n_bias(self) -> int:
        return int(self.bias_matrix.shape[1])

    def __len__(self) -> int:
        return len(self._b)

    def evaluate(self, R_k, p_k, v_k, lever, td: float, biases, jacobians: bool = False, dir_coefs=None,
                 adir_coefs=None, anchor_pos=None):
        """Residuals (N,) [m] and, on request, the Jacobians ``(J_pose, J_vel, J_lever, J_td)`` as
        :meth:`RangeGroup.evaluate` (each the b row's minus the a row's)."""
        rb = self._b.evaluate(R_k, p_k, v_k, lever, td, biases, jacobians)
        ra = self._a.evaluate(R_k, p_k, v_k, lever, td, np.zeros(self.n_bias), jacobians)
        if not jacobians:
            return rb - ra
        return tuple(b - a for b, a in zip(rb, ra))
