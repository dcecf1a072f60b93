"""Variable keys of the batch calibration graph: one public scheme, in the style of GTSAM's ``symbol_shorthand``.

Every GTSAM variable of :mod:`uwbimu.calibration.graph` is named by a character and an index, encoded as
GTSAM's ``Symbol(char, index).key()`` (the character in the top 8 bits, the index in the low 56).  The
functions below are the only place that spells the characters; every module of the calibrator names its
variables through them::

    from uwbimu.calibration import keys

    values.atPose3(keys.pose(k))            # keyframe k's pose
    values.atVector(keys.time_offset())[0]  # t_d [s]

==========  ======================================  ==========================  =====================
character   variable                                 function                    type, unit
==========  ======================================  ==========================  =====================
``x``       pose of keyframe ``k`` (IMU clock)       :func:`pose`                ``Pose3`` [rad, m]
``v``       velocity of keyframe ``k``               :func:`velocity`            3-vector [m/s]
``b``       IMU bias of keyframe ``k``               :func:`imu_bias`            ``imuBias`` [m/s^2, rad/s]
``l``       lever arm p_IU of tag ``i``              :func:`lever_arm`           3-vector [m, IMU frame]
``t``       time offset t_d (one, index 0)           :func:`time_offset`         1-vector [s]
``a``       constant range bias of anchor ``j``      :func:`anchor_bias`         1-vector [m]
``p``       position of estimated anchor ``j``       :func:`anchor_position`     ``Point3`` [m, world]
``d``       knot ``n`` of anchor ``j``'s drift       :func:`bias_drift`          1-vector [m]
``h``       direction-bias coefficients ``i``        :func:`direction_bias`      vector [m, m/rad]
``g``       anchor-side direction coefficients       :func:`anchor_direction_bias`  vector [m, m/rad^q]
==========  ======================================  ==========================  =====================

The encoding is GTSAM's own (``tests/test_calibration_keys.py`` pins every function to
``gtsam.symbol``), so keys printed by GTSAM (``x3``, ``t0``) read as these names.  Pure Python: importing
this module does not import GTSAM.
"""

from __future__ import annotations

__all__ = ["POSE", "VELOCITY", "IMU_BIAS", "LEVER_ARM", "TIME_OFFSET", "ANCHOR_BIAS", "ANCHOR_POSITION",
           "BIAS_DRIFT", "DIRECTION_BIAS", "ANCHOR_DIRECTION_BIAS", "symbol", "pose", "velocity", "imu_bias",
           "lever_arm", "time_offset", "anchor_bias", "anchor_position", "bias_drift", "direction_bias",
           "anchor_direction_bias", "DRIFT_KNOTS_PER_ANCHOR"]

#: The characters of the scheme (GTSAM ``Symbol`` characters).
POSE, VELOCITY, IMU_BIAS, LEVER_ARM, TIME_OFFSET = "x", "v", "b", "l", "t"
ANCHOR_BIAS, ANCHOR_POSITION, BIAS_DRIFT, DIRECTION_BIAS, ANCHOR_DIRECTION_BIAS = "a", "p", "d", "h", "g"

#: Index stride of :func:`bias_drift`: knot ``n`` of anchor ``j`` has index ``j * DRIFT_KNOTS_PER_ANCHOR + n``.
DRIFT_KNOTS_PER_ANCHOR = 1_000_000

_CHR_SHIFT = 56  # GTSAM Symbol: 8 bits of character above 56 bits of index
_INDEX_MASK = (1 << _CHR_SHIFT) - 1


def symbol(char: str, index: int) -> int:
    """GTSAM key of ``Symbol(char, index)``: ``ord(char) << 56 | index`` (``gtsam.symbol(char, index)``)."""
    i = int(index)
    if not 0 <= i <= _INDEX_MASK:
        raise IndexError(f"key index {i} outside [0, 2^56)")  # a bug in the caller, not an input problem
    return (ord(char) << _CHR_SHIFT) | i


def pose(k: int) -> int:
    """Key of keyframe ``k``'s pose ``x(k)`` (``Pose3``, world from IMU body)."""
    return symbol(POSE, k)


def velocity(k: int) -> int:
    """Key of keyframe ``k``'s velocity ``v(k)`` [m/s, world]."""
    return symbol(VELOCITY, k)


def imu_bias(k: int) -> int:
    """Key of keyframe ``k``'s IMU bias ``b(k)`` (``imuBias.ConstantBias``: accelerometer, gyroscope)."""
    return symbol(IMU_BIAS, k)


def lever_arm(i: int = 0) -> int:
    """Key of tag ``i``'s lever arm ``l(i)`` p_IU [m, IMU frame]; ``l(0)`` with one tag."""
    return symbol(LEVER_ARM, i)


def time_offset() -> int:
    """Key of the time offset ``t(0)`` t_d [s] (UWB clock + t_d = IMU clock)."""
    return symbol(TIME_OFFSET, 0)


def anchor_bias(j: int) -> int:
    """Key of anchor ``j``'s constant range bias ``a(j)`` [m] (``j`` the index in the problem's anchor order)."""
    return symbol(ANCHOR_BIAS, j)


def anchor_position(j: int) -> int:
    """Key of estimated anchor ``j``'s position ``p(j)`` (``Point3`` [m], world frame)."""
    return symbol(ANCHOR_POSITION, j)


def bias_drift(j: int, n: int) -> int:
    """Key of knot ``n`` of anchor ``j``'s slowly varying range bias ``d(j * 10^6 + n)`` [m]."""
    return symbol(BIAS_DRIFT, int(j) * DRIFT_KNOTS_PER_ANCHOR + int(n))


def direction_bias(i: int) -> int:
    """Key of direction-bias coefficient vector ``h(i)``: ``i = tag * n + a``, ``a`` the anchor index
    (``per_anchor``, ``n`` anchors) or 0 (shared, ``n = 1``); one tag: ``i`` = anchor index or 0."""
    return symbol(DIRECTION_BIAS, i)


def anchor_direction_bias(j: int) -> int:
    """Key of anchor ``j``'s anchor-side direction-bias coefficients ``g(j)`` (``range_model.anchor_direction``)."""
    return symbol(ANCHOR_DIRECTION_BIAS, j)
