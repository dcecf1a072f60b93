"""The UWB range factor of the batch calibrator: residual, Jacobians, GTSAM wrapper.

A range ``rho`` stamped ``t`` on the UWB clock observes the antenna at IMU time
``s = t + t_d`` (:func:`uwbimu.models.reference.imu_time_of_range`).  The graph
holds keyframe states at IMU stamps ``t_k``; the range is attached to the last
keyframe ``k`` with ``t_k <= s0 = t + t_d0`` (``t_d0``: the time offset about
which the association was made) through the IMU-propagated short delta from
``t_k`` to ``s0`` (body frame of ``k``, gravity-free, bias fixed at the
initial estimate) and a second-order extrapolation in ``delta = t_d - t_d0``::

    R_s0 = R_k dR                p_s0 = p_k + v_k tau - g tau^2 / 2 + R_k dp
    v_s0 = v_k - g tau + R_k dv  a_s0 = R_s0 (a_m - b_a) - g
    R(s) = R_s0 Exp(w delta)     p(s) = p_s0 + v_s0 delta + a_s0 delta^2 / 2
    e    = || p(s) + R(s) p_IU - p_anchor || + b_anchor - rho

with ``tau = s0 - t_k`` and ``w = w_m - b_g`` at ``s0``.  The residual equals
:func:`uwbimu.models.reference.range_measurement` of the reference-propagated
state plus the anchor bias (pinned by ``tests/test_calibrate_factor.py``).

Optionally (:class:`RangeGroup` with ``direction``) a direction-dependent bias
``F(w_b) . c`` is added, ``w_b = R(s)^T (p_anchor - p(s) - R(s) p_IU)`` the line
of sight in the body frame (:func:`direction_features`; exact Jacobians pinned by
``tests/test_calibrate_direction.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from uwbimu.models.reference import G_WORLD


def skew(v: np.ndarray) -> np.ndarray:
    """``[v]x`` with ``skew(a) @ b = a x b``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def so3_exp(w: np.ndarray) -> np.ndarray:
    """Rotation matrix ``Exp(w)`` (Rodrigues), ``w`` in rad."""
    th = float(np.linalg.norm(w))
    K = skew(w)
    if th < 1e-8:
        return np.eye(3) + K + 0.5 * K @ K
    return np.eye(3) + np.sin(th) / th * K + (1.0 - np.cos(th)) / th**2 * K @ K


@dataclass(frozen=True)
class RangeDelta:
    """IMU delta from a keyframe at ``t_k`` to the range instant ``s0`` (IMU clock).

    Attributes
    ----------
    tau : s0 - t_k [s].
    dR : (3, 3) rotation body(s0) -> body(t_k).
    dv, dp : (3,) gravity-free velocity / position increments in the body frame of ``t_k`` [m/s, m].
    acc, omega : (3,) bias-corrected specific force [m/s^2] and rate [rad/s] at ``s0`` (body).
    """

    tau: float
    dR: np.ndarray
    dv: np.ndarray
    dp: np.ndarray
    acc: np.ndarray
    omega: np.ndarray


def imu_cumulative(t_imu: np.ndarray, u_imu: np.ndarray, b_a: np.ndarray, b_g: np.ndarray,
                   t_key: np.ndarray) -> dict:
    """IMU delta from its keyframe to every IMU sample (the walk :func:`imu_deltas` needs, done once).

    Midpoint integration of the bias-corrected readings, reset at every keyframe (keyframes lie on
    IMU samples).  Returns a dict of arrays: ``dR`` (n, 3, 3), ``dv``, ``dp`` (n, 3) at every sample
    ``i`` from the keyframe ``k`` with ``t_key[k] <= t_imu[i]`` (the last one), and ``acc``, ``gyr``
    (n, 3) the bias-corrected readings, ``key_idx`` the keyframes' sample indices.
    """
    t_imu = np.asarray(t_imu, float)
    acc = np.asarray(u_imu[:, :3], float) - b_a
    gyr = np.asarray(u_imu[:, 3:6], float) - b_g
    key_idx = np.searchsorted(t_imu, t_key)
    n = len(t_imu)
    is_key = np.zeros(n, bool)
    is_key[key_idx] = True
    h = np.diff(t_imu)
    a_mid = 0.5 * (acc[:-1] + acc[1:])
    w_mid = 0.5 * (gyr[:-1] + gyr[1:])
    E_half = so3_exp_batch(0.5 * h[:, None] * w_mid)
    E_full = so3_exp_batch(h[:, None] * w_mid)
    dR = np.empty((n, 3, 3))
    dv = np.empty((n, 3))
    dp = np.empty((n, 3))
    R, v, p = np.eye(3), np.zeros(3), np.zeros(3)
    for i in range(n):
        if is_key[i]:
            R, v, p = np.eye(3), np.zeros(3), np.zeros(3)
        dR[i], dv[i], dp[i] = R, v, p
        if i + 1 < n:
            Ra = (R @ E_half[i]) @ a_mid[i]
            p = p + v * h[i] + 0.5 * Ra * h[i] * h[i]
            v = v + Ra * h[i]
            R = R @ E_full[i]
    return {"t": t_imu, "acc": acc, "gyr": gyr, "dR": dR, "dv": dv, "dp": dp, "key_idx": key_idx,
            "t_key": np.asarray(t_key, float)}


def imu_deltas(t_imu: np.ndarray, u_imu: np.ndarray, b_a: np.ndarray, b_g: np.ndarray,
               t_key: np.ndarray, s0: np.ndarray, cum: dict | None = None) -> tuple[np.ndarray, list[RangeDelta]]:
    """Keyframe index and IMU delta for every instant ``s0`` (IMU clock).

    Midpoint integration of the bias-corrected readings between the IMU samples,
    a partial step to ``s0``.  ``s0`` must lie in ``[t_key[0], t_imu[-1])``.
    ``cum``: :func:`imu_cumulative` of the same inputs, to reuse (it does not depend on ``s0``).

    Returns
    -------
    k : (M,) keyframe index of every instant.
    deltas : list of :class:`RangeDelta`.
    """
    if cum is None:
        cum = imu_cumulative(t_imu, u_imu, b_a, b_g, t_key)
    t, acc, gyr = cum["t"], cum["acc"], cum["gyr"]
    s0 = np.asarray(s0, float)
    k_of = np.searchsorted(cum["t_key"], s0, side="right") - 1
    i = np.maximum(np.searchsorted(t, s0, side="right") - 1, cum["key_idx"][k_of])
    j = np.minimum(i + 1, len(t) - 1)
    h = s0 - t[i]
    span = t[j] - t[i]
    frac = np.where(j > i, h / np.where(span > 0, span, 1.0), 0.0)[:, None]
    a_s = acc[i] + frac * (acc[j] - acc[i])
    w_s = gyr[i] + frac * (gyr[j] - gyr[i])
    a_mid, w_mid = 0.5 * (acc[i] + a_s), 0.5 * (gyr[i] + w_s)
    dR, dv, dp = cum["dR"][i], cum["dv"][i], cum["dp"][i]
    hh = h[:, None]
    Ra = np.einsum("nij,nj->ni", dR @ so3_exp_batch(0.5 * hh * w_mid), a_mid)
    dR_s = dR @ so3_exp_batch(w_mid * hh)
    dv_s = dv + Ra * hh
    dp_s = dp + dv * hh + 0.5 * Ra * hh * hh
    tau = s0 - cum["t_key"][k_of]
    out = [RangeDelta(tau=float(tau[m]), dR=dR_s[m], dv=dv_s[m], dp=dp_s[m], acc=a_s[m], omega=w_s[m])
           for m in range(len(s0))]
    return k_of, out


def range_error(R_k, p_k, v_k, lever, td, bias, anchor, rho, d: RangeDelta, td0: float,
                jacobians: bool = False, with_anchor: bool = False):
    """Whitening-free residual ``e`` [m] of one range and, on request, its Jacobians.

    Jacobians (rows of ``de/dx``) are with respect to the GTSAM tangents: pose
    ``[theta, p]`` with ``R_k Exp(theta)``, ``p_k + R_k dp``; velocity, lever arm
    (IMU frame), ``t_d`` and the anchor bias in their own coordinates.  With
    ``with_anchor`` a sixth Jacobian, with respect to the anchor position (world,
    m; a ``Point3`` variable of the self-survey), is appended.
    """
    delta = td - td0
    tau = d.tau
    R_s0 = R_k @ d.dR
    v_s0 = v_k - G_WORLD * tau + R_k @ d.dv
    a_s0 = R_s0 @ d.acc - G_WORLD
    p_s0 = p_k + v_k * tau - 0.5 * G_WORLD * tau**2 + R_k @ d.dp
    M = d.dR @ so3_exp(d.omega * delta)
    R_s = R_k @ M
    p_U = p_s0 + v_s0 * delta + 0.5 * a_s0 * delta**2 + R_s @ lever
    u = p_U - anchor
    r = float(np.linalg.norm(u))
    e = r + bias - rho
    if not jacobians:
        return e
    n = u / r
    body = d.dp + delta * d.dv + 0.5 * delta**2 * (d.dR @ d.acc) + M @ lever
    J_pose = np.concatenate([n @ (-R_k @ skew(body)), n @ R_k])
    J_vel = n * (tau + delta)
    J_lever = n @ R_s
    J_td = float(n @ (v_s0 + a_s0 * delta + R_s @ np.cross(d.omega, lever)))
    if with_anchor:
        return e, J_pose, J_vel, J_lever, J_td, -n
    return e, J_pose, J_vel, J_lever, J_td


def make_gtsam_factor(keys, anchor, rho, d: RangeDelta, td0: float, noise, td_fixed: float | None = None,
                      anchor_variable: bool = False):
    """A ``gtsam.CustomFactor`` on ``[pose, velocity, lever arm, (t_d), anchor bias, (anchor position)]``.

    With ``td_fixed`` the time offset is a constant (profile points) and ``keys``
    has no t_d key.  With ``anchor_variable`` the last key is the anchor's
    ``Point3`` (self-survey) and ``anchor`` is ignored.
    """
    import gtsam

    anchor = np.asarray(anchor, float)
    has_td = td_fixed is None
    ib = -2 if anchor_variable else -1  # position of the bias key

    def error(this, values, H):
        ks = this.keys()
        pose = values.atPose3(ks[0])
        td = values.atVector(ks[3])[0] if has_td else td_fixed
        bias = values.atVector(ks[ib])[0]
        a = values.atPoint3(ks[-1]) if anchor_variable else anchor
        res = range_error(pose.rotation().matrix(), pose.translation(), values.atVector(ks[1]),
                          values.atVector(ks[2]), td, bias, a, rho, d, td0, jacobians=H is not None,
                          with_anchor=anchor_variable)
        if H is None:
            return np.array([res])
        e, Jp, Jv, Jl, Jt = res[:5]
        H[0] = Jp.reshape(1, 6)
        H[1] = Jv.reshape(1, 3)
        H[2] = Jl.reshape(1, 3)
        if has_td:
            H[3] = np.array([[Jt]])
        H[len(ks) + ib] = np.ones((1, 1))
        if anchor_variable:
            H[len(ks) - 1] = res[5].reshape(1, 3)
        return np.array([e])

    return gtsam.CustomFactor(noise, gtsam.KeyVector(keys), error)


def so3_exp_batch(w: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotation matrices ``Exp(w_i)`` (Rodrigues) of (N, 3) rotation vectors [rad]."""
    w = np.asarray(w, float)
    th = np.linalg.norm(w, axis=1)
    K = np.zeros((len(w), 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = w[:, 2], -w[:, 1], w[:, 0]
    small = th < 1e-8
    ths = np.where(small, 1.0, th)
    a = np.where(small, 1.0, np.sin(ths) / ths)
    b = np.where(small, 0.5, (1.0 - np.cos(ths)) / ths**2)
    return np.eye(3)[None] + a[:, None, None] * K + b[:, None, None] * (K @ K)


#: Evaluate groups without an anchor-side direction model with the numba row loop
#: (:mod:`uwbimu.calibration.range_kernel`; the tag-side direction term vectorised on its geometry);
#: False: the NumPy implementation (the kernel's reference in ``tests/test_calibrate_speed.py``).
USE_KERNEL = True
#: The attributes of a RangeGroup the kernel knows; a group with any other (a model term added later) takes the
#: NumPy path until the kernel learns it.
_KERNEL_ATTRS = frozenset({"tau", "dR", "dv", "dp", "acc", "omega", "dRacc", "anchor", "rho", "bias_col", "td0",
                           "bias_matrix", "kf", "n_kf", "kf_mask", "direction", "dir_col", "n_dir", "dir_mask",
                           "anchor_direction", "anchor_rot", "adir_col", "n_adir", "adir_mask",
                           "anchor_var", "n_apos", "apos_mask"})


class RangeGroup:
    """The ranges attached to a few consecutive keyframes, evaluated together (vectorised :func:`range_error`).

    Same model, residual and Jacobians as :func:`range_error` for every row (pinned by
    ``tests/test_calibrate_factor.py``), plus the optional direction-dependent term; one GTSAM
    callback per group instead of one per range.

    Parameters
    ----------
    deltas : the rows' :class:`RangeDelta` (each from its own keyframe).
    anchors : (N, 3) anchor positions [m] (world).
    rho : (N,) measured ranges [m].
    bias_col : (N,) index of each row's anchor-bias key among the group's bias keys.
    td0 : the association's time offset [s].
    bias_matrix : optional (N, nb) 0/1 matrix: row m's bias is ``bias_matrix[m] @ biases`` (a constant
        bias plus a slowly varying one); default the one-hot matrix of ``bias_col``.
    kf : optional (N,) index of each row's keyframe among the group's keyframes (default all 0).
    direction : optional ``(orders, elevation)`` of the direction-dependent bias (:func:`direction_features`):
        each row's range gains ``direction_features(w_b) @ c`` with ``c`` its coefficient vector.
    dir_col : (N,) index of each row's coefficient vector among the group's direction keys (with ``direction``).
    anchor_direction : optional ``(orders, elevation_order)`` of the anchor-side direction-dependent bias: each
        row's range gains ``direction_features(w_a) @ c_a``, ``w_a = R_a^T (p_U - anchor)`` the line of sight
        from the anchor to the tag antenna in the anchor's antenna frame.
    anchor_rot : (N, 3, 3) each row's anchor antenna orientation ``R_a`` (antenna frame -> world).
    adir_col : (N,) index of each row's anchor-side coefficient vector among the group's anchor-side keys.
    anchor_var : optional (N,) index of each row's anchor among the group's anchor-position variables
        (``Point3``, world [m]; self-survey), -1 for a row whose anchor is fixed at ``anchors``.  Those rows'
        anchors are then the ``anchor_pos`` given to :meth:`evaluate` (``anchors`` ignored for them).
    """

    def __init__(self, deltas, anchors, rho, bias_col, td0: float, bias_matrix=None, kf=None,
                 direction=None, dir_col=None, anchor_direction=None, anchor_rot=None, adir_col=None,
                 anchor_var=None):
        self.tau = np.array([d.tau for d in deltas])
        self.dR = np.array([d.dR for d in deltas])
        self.dv = np.array([d.dv for d in deltas])
        self.dp = np.array([d.dp for d in deltas])
        self.acc = np.array([d.acc for d in deltas])
        self.omega = np.array([d.omega for d in deltas])
        self.dRacc = np.einsum("nij,nj->ni", self.dR, self.acc)
        self.anchor = np.asarray(anchors, float).reshape(-1, 3)
        self.rho = np.asarray(rho, float)
        self.bias_col = np.asarray(bias_col, np.int64)
        self.td0 = float(td0)
        if bias_matrix is None:
            bias_matrix = np.zeros((len(self.rho), int(self.bias_col.max()) + 1))
            bias_matrix[np.arange(len(self.rho)), self.bias_col] = 1.0
        self.bias_matrix = np.asarray(bias_matrix, float)
        self.kf = np.zeros(len(self.rho), np.int64) if kf is None else np.asarray(kf, np.int64)
        self.n_kf = int(self.kf.max()) + 1
        self.kf_mask = [(self.kf == i)[:, None].astype(float) for i in range(self.n_kf)]
        self.direction = direction
        if direction is not None:
            self.dir_col = np.zeros(len(self.rho), np.int64) if dir_col is None else np.asarray(dir_col, np.int64)
            self.n_dir = int(self.dir_col.max()) + 1
            self.dir_mask = [(self.dir_col == i)[:, None].astype(float) for i in range(self.n_dir)]
        else:
            self.dir_col, self.n_dir, self.dir_mask = None, 0, []
        self.anchor_direction = anchor_direction
        if anchor_direction is not None:
            self.anchor_rot = np.asarray(anchor_rot, float).reshape(-1, 3, 3)
            self.adir_col = np.zeros(len(self.rho), np.int64) if adir_col is None else np.asarray(adir_col, np.int64)
            self.n_adir = int(self.adir_col.max()) + 1
            self.adir_mask = [(self.adir_col == i)[:, None].astype(float) for i in range(self.n_adir)]
        else:
            self.anchor_rot, self.adir_col, self.n_adir, self.adir_mask = None, None, 0, []
        av = None if anchor_var is None else np.asarray(anchor_var, np.int64)
        if av is not None and np.any(av >= 0):
            self.anchor_var = av
            self.n_apos = int(av.max()) + 1
            self.apos_mask = [(av == i)[:, None].astype(float) for i in range(self.n_apos)]
        else:
            self.anchor_var, self.n_apos, self.apos_mask = None, 0, []

    def row_anchors(self, anchor_pos=None) -> np.ndarray:
        """(N, 3) each row's anchor position [m] (world): fixed ones from ``anchors``, estimated ones from
        ``anchor_pos`` (n_apos, 3), the current values of the group's anchor-position variables."""
        if self.anchor_var is None:
            return self.anchor
        if anchor_pos is None:
            raise TypeError("RangeGroup: this group has estimated anchors; pass anchor_pos")  # a caller's bug
        ap = np.asarray(anchor_pos, float).reshape(self.n_apos, 3)
        est = self.anchor_var >= 0
        return np.where(est[:, None], ap[np.maximum(self.anchor_var, 0)], self.anchor)

    @property
    def n_bias(self) -> int:
        """Number of bias keys of the group."""
        return int(self.bias_matrix.shape[1])

    def __len__(self) -> int:
        return len(self.rho)

    def line_of_sight_body(self, R_k, p_k, v_k, lever, td: float, anchor_pos=None) -> np.ndarray:
        """(N, 3) vector from the tag antenna to the anchor in the body (IMU) frame at the range instant [m]."""
        return self._geometry(R_k, p_k, v_k, lever, td, anchor_pos)["wb"]

    def line_of_sight_anchor(self, R_k, p_k, v_k, lever, td: float, anchor_pos=None) -> np.ndarray:
        """(N, 3) vector from the anchor to the tag antenna in the anchor's antenna frame [m]."""
        return np.einsum("nji,nj->ni", self.anchor_rot, self._geometry(R_k, p_k, v_k, lever, td, anchor_pos)["u"])

    def anchor_term(self, u, adir_coefs, jacobian: bool = False):
        """Anchor-side direction bias (N,) [m] of the world lines of sight ``u = p_U - anchor`` (N, 3) and, on
        request, its features (N, P) and its gradient with respect to ``u`` (N, 3, world)."""
        C = np.asarray(adir_coefs, float).reshape(self.n_adir, -1)[self.adir_col]
        wa = np.einsum("nji,nj->ni", self.anchor_rot, u)  # R_a^T u
        F, dF = direction_features(wa, *self.anchor_direction, jacobian=jacobian)
        term = np.einsum("np,np->n", F, C)
        if not jacobian:
            return term
        return term, F, np.einsum("nij,nj->ni", self.anchor_rot, np.einsum("np,npi->ni", C, dF))

    def _geometry(self, R_k, p_k, v_k, lever, td, anchor_pos=None):
        g = G_WORLD
        R_k = np.asarray(R_k, float).reshape(-1, 3, 3)[self.kf]
        p_k = np.asarray(p_k, float).reshape(-1, 3)[self.kf]
        v_k = np.asarray(v_k, float).reshape(-1, 3)[self.kf]
        delta = td - self.td0
        tau = self.tau[:, None]
        R_s0 = R_k @ self.dR
        v_s0 = v_k - g * tau + np.einsum("nij,nj->ni", R_k, self.dv)
        a_s0 = np.einsum("nij,nj->ni", R_s0, self.acc) - g
        p_s0 = p_k + v_k * tau - 0.5 * g * tau**2 + np.einsum("nij,nj->ni", R_k, self.dp)
        M = self.dR @ so3_exp_batch(self.omega * delta)
        R_s = R_k @ M
        p_U = p_s0 + v_s0 * delta + 0.5 * a_s0 * delta**2 + R_s @ lever
        u = p_U - self.row_anchors(anchor_pos)
        wb = -np.einsum("nij,ni->nj", R_s, u)  # R_s^T (anchor - p_U)
        return {"R_k": R_k, "delta": delta, "tau": tau, "v_s0": v_s0, "a_s0": a_s0, "M": M, "R_s": R_s,
                "u": u, "wb": wb}

    def _evaluate_kernel(self, R_k, p_k, v_k, lever, td: float, biases, jacobians: bool, anchor_pos=None,
                         dir_coefs=None):
        """:meth:`evaluate` without an anchor-side direction model, by the compiled row loop (:mod:`.range_kernel`).

        With estimated anchors the rows' current anchor positions go to the kernel and the anchor Jacobian
        ``-n`` is recovered exactly from the pose Jacobian's position block ``R_k^T n``.  With the tag-side
        direction model the kernel also returns the rows' geometry, on which the compiled direction term
        (:func:`.range_kernel.direction_rows`) adds itself and its derivatives."""
        from uwbimu.calibration.range_kernel import direction_rows, group_rows

        n = len(self.rho)
        R_k = np.ascontiguousarray(R_k, dtype=float).reshape(-1, 3, 3)
        p_k = np.ascontiguousarray(p_k, dtype=float).reshape(-1, 3)
        v_k = np.ascontiguousarray(v_k, dtype=float).reshape(-1, 3)
        lever = np.ascontiguousarray(lever, dtype=float).reshape(3)
        delta = float(td - self.td0)
        r = np.empty(n)
        if jacobians:
            Jp, Jv, Jl, Jt = np.empty((n, 6)), np.empty((n, 3)), np.empty((n, 3)), np.empty(n)
        else:
            Jp = Jv = Jl = np.empty((0, 6))
            Jt = np.empty(0)
        geo = self.direction is not None
        m = n if geo else 0
        u, R_s, M = np.empty((m, 3)), np.empty((m, 3, 3)), np.empty((m, 3, 3))
        v_s0, a_s0, body = np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3))
        group_rows(R_k, p_k, v_k, self.kf, self.tau, self.dR, self.dv, self.dp, self.acc, self.omega, self.dRacc,
                   np.ascontiguousarray(self.row_anchors(anchor_pos)), lever, delta,
                   float(G_WORLD[2]), jacobians, r, Jp, Jv, Jl, Jt, geo, u, R_s, M, v_s0, a_s0, body)
        e = r + self.bias_matrix @ np.asarray(biases, float) - self.rho
        if not geo:
            if not jacobians:
                return e
            J_anc = None if self.anchor_var is None else \
                -np.einsum("nij,nj->ni", R_k[self.kf], Jp[:, 3:6]) * (self.anchor_var >= 0)[:, None]
            return (e, Jp, Jv, Jl, Jt) + (() if J_anc is None else (J_anc,))
        orders, elevation = self.direction
        powers = tuple(elevation) if isinstance(elevation, (tuple, list)) else tuple(range(1, int(elevation) + 1))
        C = np.ascontiguousarray(np.asarray(dir_coefs, float).reshape(self.n_dir, -1)[self.dir_col])
        J_anc = None if not jacobians or self.anchor_var is None else \
            -np.einsum("nij,nj->ni", R_k[self.kf], Jp[:, 3:6]) * (self.anchor_var >= 0)[:, None]
        F, Rg = np.empty(C.shape), np.empty((n, 3))
        direction_rows(np.array(orders, np.int64).reshape(-1), np.array(powers, np.int64).reshape(-1), C, u, R_s, M,
                       v_s0, a_s0, body, self.omega, self.tau, lever, delta, jacobians, e, F, Jp, Jv, Jl, Jt, Rg)
        if not jacobians:
            return e
        if J_anc is not None:
            J_anc = J_anc + Rg * (self.anchor_var >= 0)[:, None]  # dw_b/danchor = R_s^T
        return (e, Jp, Jv, Jl, Jt, F) + (() if J_anc is None else (J_anc,))

    def evaluate(self, R_k, p_k, v_k, lever, td: float, biases, jacobians: bool = False, dir_coefs=None,
                 adir_coefs=None, anchor_pos=None):
        """Residuals ``e`` (N,) [m] and, on request, Jacobians ``(J_pose (N, 6), J_vel (N, 3),
        J_lever (N, 3), J_td (N,))`` on the GTSAM tangents (see :func:`range_error`); each row's
        pose and velocity Jacobians are with respect to its own keyframe.

        With a direction model, ``dir_coefs`` (n_dir, P) are the coefficient vectors, the direction term
        is added to ``e`` and its exact derivatives to every Jacobian, and a fifth Jacobian ``F`` (N, P)
        (the features: each row's derivative with respect to its own coefficient vector) is appended.
        With an anchor-side model, ``adir_coefs`` (n_adir, P_a) likewise: its term is added to ``e``; it is
        a function of ``u = p_U - anchor`` only, so its derivatives are the range's own with ``n = u / |u|``
        replaced by ``n + R_a dg/dw_a``; its features ``F_a`` (N, P_a) follow.
        With estimated anchors (``anchor_var``), ``anchor_pos`` (n_apos, 3) are their current positions
        [m] (world) and the Jacobian of every row with respect to its own anchor's position, (N, 3),
        comes last: ``-(n + R_a dg/dw_a) + R_s dF/dw_b c`` (range, anchor-side and tag-side terms; zero for
        the rows whose anchor is fixed).

        ``R_k, p_k, v_k``: the keyframes' states, (K, 3, 3), (K, 3), (K, 3) with K = ``n_kf``
        (or (3, 3), (3,), (3,) for one keyframe).
        """
        if USE_KERNEL and self.anchor_direction is None \
                and set(vars(self)) <= _KERNEL_ATTRS and np.size(lever) == 3:
            return self._evaluate_kernel(R_k, p_k, v_k, lever, td, biases, jacobians, anchor_pos, dir_coefs)
        geo = self._geometry(R_k, p_k, v_k, lever, td, anchor_pos)
        R_k, delta, tau, v_s0, a_s0, M, R_s, u = (geo[k] for k in ("R_k", "delta", "tau", "v_s0", "a_s0", "M",
                                                                    "R_s", "u"))
        r = np.sqrt(np.einsum("ni,ni->n", u, u))
        e = r + self.bias_matrix @ np.asarray(biases, float) - self.rho
        if self.direction is not None:
            C = np.asarray(dir_coefs, float).reshape(self.n_dir, -1)[self.dir_col]
            F, dF = direction_features(geo["wb"], *self.direction, jacobian=jacobians)
            e = e + np.einsum("np,np->n", F, C)
        if self.anchor_direction is not None:
            at = self.anchor_term(u, adir_coefs, jacobian=jacobians)
            e = e + (at[0] if jacobians else at)
        if not jacobians:
            return e
        n = u / r[:, None]
        if self.anchor_direction is not None:
            n = n + at[2]  # d(|u| + g(R_a^T u) c)/du: every Jacobian below is linear in it
        m = np.einsum("nij,ni->nj", R_k, n)  # R_k^T n
        body = self.dp + delta * self.dv + 0.5 * delta**2 * self.dRacc + M @ lever
        J_pose = np.hstack([np.cross(body, m), m])
        J_vel = n * (tau + delta)
        J_lever = np.einsum("nij,ni->nj", R_s, n)
        J_td = np.einsum("ni,ni->n", n, v_s0 + a_s0 * delta
                         + np.einsum("nij,nj->ni", R_s, np.cross(self.omega, lever)))
        extra = (at[1],) if self.anchor_direction is not None else ()
        est = None if self.anchor_var is None else (self.anchor_var >= 0)[:, None]
        J_anc = None if est is None else -n * est
        if self.direction is None:
            return (e, J_pose, J_vel, J_lever, J_td) + extra + (() if est is None else (J_anc,))
        # direction term F(w_b) c with w_b = R_s^T (anchor - p_U) = M^T R_k^T q - M^T b1 - lever, where
        # q = anchor - p_k - v_k (tau + delta) + g (tau + delta)^2 / 2 (world) and b1 = body - M lever:
        # dw_b/dtheta = M^T [R_k^T q]x = M^T [M w_b + body]x, dw_b/dp = -M^T, dw_b/dv = -(tau + delta) R_s^T,
        # dw_b/dlever = -I, dw_b/dt_d = -omega x (w_b + lever) - R_s^T (v_s0 + a_s0 delta)
        gv = np.einsum("np,npi->ni", C, dF)  # d(term)/d(w_b)
        Mg = np.einsum("nij,nj->ni", M, gv)
        Rg = np.einsum("nij,nj->ni", R_s, gv)
        z = np.einsum("nij,nj->ni", M, geo["wb"]) + body
        J_pose = J_pose + np.hstack([np.cross(Mg, z), -Mg])
        J_vel = J_vel - Rg * (tau + delta)
        J_lever = J_lever - gv
        J_td = J_td - np.einsum("ni,ni->n", gv, np.cross(self.omega, geo["wb"] + lever)) \
            - np.einsum("ni,ni->n", Rg, v_s0 + a_s0 * delta)
        if est is not None:
            J_anc = J_anc + Rg * est  # dw_b/danchor = R_s^T
        return (e, J_pose, J_vel, J_lever, J_td, F) + extra + (() if est is None else (J_anc,))


def direction_features(wb: np.ndarray, orders, elevation, jacobian: bool = False):
    """Features of the direction-dependent bias and, on request, their derivatives.

    Parameters
    ----------
    wb : (N, 3) line of sight from the tag antenna to the anchor, body (IMU) frame [m] (any length).
    orders : Fourier orders ``n`` in body azimuth ``az = atan2(w_y, w_x)``: columns ``cos(n az), sin(n az)``.
    elevation : append ``el = atan2(w_z, hypot(w_x, w_y))`` [rad] (``True`` or 1); an int ``q`` appends
        ``el, el^2, .., el^q``, a tuple of powers ``el^q`` for each ``q`` in it.

    Returns
    -------
    F : (N, P) features; dF : (N, P, 3) their derivatives with respect to ``wb`` [1/m] (None unless asked).

    A line of sight along the body z axis has no azimuth: ``hypot(w_x, w_y)`` is floored at 1 um there.
    """
    wb = np.asarray(wb, float)
    x, y, zz = wb[:, 0], wb[:, 1], wb[:, 2]
    h2 = np.maximum(x * x + y * y, 1e-12)
    az = np.arctan2(y, x)
    cols, dcols = [], []
    daz = np.stack([-y / h2, x / h2, np.zeros_like(x)], axis=1) if jacobian else None
    for n in orders:
        c, s_ = np.cos(n * az), np.sin(n * az)
        cols += [c, s_]
        if jacobian:
            dcols += [(-n * s_)[:, None] * daz, (n * c)[:, None] * daz]
    powers = tuple(elevation) if isinstance(elevation, (tuple, list)) else tuple(range(1, int(elevation) + 1))
    if powers:
        h = np.sqrt(h2)
        el = np.arctan2(zz, h)
        if jacobian:
            r2 = h2 + zz * zz
            del_ = np.stack([-x * zz / (r2 * h), -y * zz / (r2 * h), h / r2], axis=1)
        for q in powers:
            cols.append(el**q)
            if jacobian:
                dcols.append((q * el ** (q - 1))[:, None] * del_)
    F = np.stack(cols, axis=1)
    return F, (np.stack(dcols, axis=1) if jacobian else None)


def huber_sqrt(z: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """``s = sign(z) sqrt(2 rho(z))`` of the Huber loss (``rho = z^2/2`` for ``|z| <= k``, else
    ``k|z| - k^2/2``) and ``ds/dz``: ``s^2 / 2`` is GTSAM's Huber loss exactly, and so is its gradient."""
    a = np.abs(z)
    out = a > k
    s = np.where(out, np.sign(z) * np.sqrt(np.maximum(2.0 * k * a - k * k, 0.0)), z)
    ds = np.where(out, k / np.where(out, np.abs(s), 1.0), 1.0)
    return s, ds


def make_gtsam_group_factor(keys, group: RangeGroup, sigma: float, huber_k: float, td_fixed: float | None = None):
    """A ``gtsam.CustomFactor`` of a group's ranges.

    Keys: ``[pose_0, velocity_0, ..., pose_{K-1}, velocity_{K-1}, lever arm, (t_d), bias_0, bias_1, ...,
    (dir_0, dir_1, ...), (adir_0, ...), (anchor_0, ...)]`` (K = ``group.n_kf`` keyframes; the
    direction-coefficient vectors, one per ``group.n_dir``, with a direction model, then the anchor-side ones,
    one per ``group.n_adir``, then the estimated anchors' ``Point3`` positions, one per ``group.n_apos``).
    The robust loss is applied per range inside the factor: the returned residual
    is ``huber_sqrt(e / sigma)`` with a unit noise model, so the factor's error is
    the sum of the rows' Huber losses (equal to one ``Robust(Huber(k), Isotropic(sigma))`` factor per
    range) with the same gradient; its Gauss-Newton weight of a down-weighted row is ``k / (2|z| - k)``
    where GTSAM's iteratively reweighted one is ``k / |z|`` (equal at the threshold).
    """
    import gtsam

    has_td = td_fixed is None
    K = group.n_kf
    il = 2 * K  # index of the lever-arm key
    off = il + (2 if has_td else 1)
    nd, nad, nap = group.n_dir, group.n_adir, group.n_apos
    nb = len(keys) - off - nd - nad - nap
    ia = off + nb + nd + nad  # index of the first anchor-position key
    n = len(group)
    onehot = group.bias_matrix
    assert onehot.shape[1] == nb, "one key per column of the group's bias matrix"

    def error(this, values, H):
        ks = this.keys()
        R = np.empty((K, 3, 3))
        P = np.empty((K, 3))
        Vv = np.empty((K, 3))
        for i in range(K):
            pose = values.atPose3(ks[2 * i])
            R[i], P[i], Vv[i] = pose.rotation().matrix(), pose.translation(), values.atVector(ks[2 * i + 1])
        td = values.atVector(ks[il + 1])[0] if has_td else td_fixed
        biases = np.array([values.atVector(ks[off + i])[0] for i in range(nb)])
        coefs = np.array([values.atVector(ks[off + nb + i]) for i in range(nd)]) if nd else None
        acoefs = np.array([values.atVector(ks[off + nb + nd + i]) for i in range(nad)]) if nad else None
        apos = np.array([values.atPoint3(ks[ia + i]) for i in range(nap)]) if nap else None
        res = group.evaluate(R, P, Vv, values.atVector(ks[il]), td, biases, jacobians=H is not None,
                             dir_coefs=coefs, adir_coefs=acoefs, anchor_pos=apos)
        if H is None:
            return huber_sqrt(res / sigma, huber_k)[0]
        e, Jp, Jv, Jl, Jt = res[:5]
        s, ds = huber_sqrt(e / sigma, huber_k)
        w = (ds / sigma)[:, None]
        Jp, Jv = w * Jp, w * Jv
        if K == 1:
            H[0], H[1] = Jp, Jv
        else:
            for i in range(K):
                H[2 * i] = Jp * group.kf_mask[i]
                H[2 * i + 1] = Jv * group.kf_mask[i]
        H[il] = w * Jl
        if has_td:
            H[il + 1] = w * Jt[:, None]
        for i in range(nb):
            H[off + i] = w * onehot[:, i:i + 1]
        for i in range(nd):
            H[off + nb + i] = w * res[5] * group.dir_mask[i]
        ja = len(res) - 1 if nap else len(res)  # the anchor Jacobian is last
        for i in range(nad):
            H[off + nb + nd + i] = w * res[ja - 1] * group.adir_mask[i]
        for i in range(nap):
            H[ia + i] = w * res[ja] * group.apos_mask[i]
        return s

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(n), gtsam.KeyVector(keys), error)
