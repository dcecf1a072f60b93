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

from uwbimu.calibration.range_factor import RangeDelta, range_error


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
