"""Layout of the 20-number nominal state and the 19-dimensional error state.

Nominal state (seed 001, eq. 1)::

    x = (p, v, q, b_a, b_g, p_IU, t_d)
         0:3 3:6 6:10 10:13 13:16 16:19 19

* ``p``    IMU position in the world frame [m]
* ``v``    IMU velocity in the world frame [m/s]
* ``q``    Hamilton quaternion ``[qw, qx, qy, qz]``, IMU body -> world
* ``b_a``  accelerometer bias, IMU frame [m/s^2]
* ``b_g``  gyroscope bias, IMU frame [rad/s]
* ``p_IU`` lever arm: UWB antenna position in the IMU frame [m]
* ``t_d``  time offset [s]: an IMU sample stamped ``s`` describes the motion
  at UWB time ``s - t_d``.

Error state (attitude error as a 3-vector, right/body perturbation
``q = q_hat ⊗ Exp(dtheta)``)::

    dx = (dp, dv, dtheta, db_a, db_g, dp_IU, dt_d)
          0:3 3:6  6:9    9:12  12:15 15:18  18
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from uwbimu.models.quaternion import quat_exp, quat_multiply, quat_normalize, quat_conjugate, quat_log

# nominal-state slices
P = slice(0, 3)
V = slice(3, 6)
Q = slice(6, 10)
BA = slice(10, 13)
BG = slice(13, 16)
PIU = slice(16, 19)
TD = 19
NOMINAL_DIM = 20

# error-state slices
EP = slice(0, 3)
EV = slice(3, 6)
ETH = slice(6, 9)
EBA = slice(9, 12)
EBG = slice(12, 15)
EPIU = slice(15, 18)
ETD = 18
ERROR_DIM = 19

# First indices of the blocks, for numba kernels (integer globals are compile-time constants there;
# slices are not): nominal ``N_*`` and error-state ``E_*`` offsets of the slices above.
N_P, N_V, N_Q, N_BA, N_BG, N_L, N_TD = P.start, V.start, Q.start, BA.start, BG.start, PIU.start, TD
E_P, E_V, E_TH, E_BA, E_BG, E_L, E_TD = EP.start, EV.start, ETH.start, EBA.start, EBG.start, EPIU.start, ETD

#: Names of the 19 error-state components, in order (used for CSV columns and reports).
ERROR_STATE_NAMES = (
    "px", "py", "pz",
    "vx", "vy", "vz",
    "thx", "thy", "thz",
    "bax", "bay", "baz",
    "bgx", "bgy", "bgz",
    "lx", "ly", "lz",
    "td",
)  # fmt: skip

#: Names of the 20 nominal-state components, in order.
NOMINAL_STATE_NAMES = (
    "px", "py", "pz",
    "vx", "vy", "vz",
    "qw", "qx", "qy", "qz",
    "bax", "bay", "baz",
    "bgx", "bgy", "bgz",
    "lx", "ly", "lz",
    "td",
)  # fmt: skip


def make_state(
    p=(0.0, 0.0, 0.0),
    v=(0.0, 0.0, 0.0),
    q=(1.0, 0.0, 0.0, 0.0),
    b_a=(0.0, 0.0, 0.0),
    b_g=(0.0, 0.0, 0.0),
    p_IU=(0.0, 0.0, 0.0),
    t_d: float = 0.0,
) -> np.ndarray:
    """Assemble a nominal state vector of length 20 (quaternion normalised)."""
    x = np.zeros(NOMINAL_DIM)
    x[P] = p
    x[V] = v
    x[Q] = quat_normalize(np.asarray(q, dtype=float))
    x[BA] = b_a
    x[BG] = b_g
    x[PIU] = p_IU
    x[TD] = t_d
    return x


def boxplus(x: np.ndarray, dx: np.ndarray) -> np.ndarray:
    """Inject an error-state vector into a nominal state: ``x ⊞ dx``."""
    x = np.asarray(x, dtype=float)
    dx = np.asarray(dx, dtype=float)
    out = x.copy()
    out[P] = x[P] + dx[EP]
    out[V] = x[V] + dx[EV]
    out[Q] = quat_normalize(quat_multiply(x[Q], quat_exp(dx[ETH])))
    out[BA] = x[BA] + dx[EBA]
    out[BG] = x[BG] + dx[EBG]
    out[PIU] = x[PIU] + dx[EPIU]
    out[TD] = x[TD] + dx[ETD]
    # extended state: further additive components (anchor biases, altimeter bias, ...)
    out[NOMINAL_DIM:] = x[NOMINAL_DIM:] + dx[ERROR_DIM:ERROR_DIM + len(x) - NOMINAL_DIM]
    return out


def boxminus(x: np.ndarray, x_ref: np.ndarray) -> np.ndarray:
    """Error-state difference ``x ⊟ x_ref`` so that ``x_ref ⊞ (x ⊟ x_ref) = x``."""
    x = np.asarray(x, dtype=float)
    x_ref = np.asarray(x_ref, dtype=float)
    dx = np.zeros(ERROR_DIM + len(x) - NOMINAL_DIM)
    dx[ERROR_DIM:] = x[NOMINAL_DIM:] - x_ref[NOMINAL_DIM:]
    dx[EP] = x[P] - x_ref[P]
    dx[EV] = x[V] - x_ref[V]
    dx[ETH] = quat_log(quat_multiply(quat_conjugate(x_ref[Q]), x[Q]))
    dx[EBA] = x[BA] - x_ref[BA]
    dx[EBG] = x[BG] - x_ref[BG]
    dx[EPIU] = x[PIU] - x_ref[PIU]
    dx[ETD] = x[TD] - x_ref[TD]
    return dx


class StateLayout:
    """Named blocks of the extended filter state, so that no code needs a literal index.

    The extended nominal state is the 20 numbers above followed by ``n_anchor_bias`` per-anchor range
    biases [m], ``n_pair_bias`` TDoA pair biases [m] (``pair_bias``), the lever arms of tags
    2..``n_tags`` [m] (``extra_levers``; the first tag's is ``lever``)
    and ``n_height_bias`` (0 or 1) altimeter biases [m]; the error state is the 19 above followed by the
    same additive components.  Blocks: ``p, v, q`` (nominal) / ``theta`` (error), ``b_a, b_g, lever,
    t_d, anchor_bias, pair_bias, extra_levers, height_bias``; ``lever_err(i)`` / ``lever_nom(i)`` per tag.  ``err(name)`` and ``nom(name)``
    give slices, ``cov(P, a, b)`` a covariance block (as OpenVINS addresses its covariance by the
    variable's id).

    >>> L = StateLayout(n_anchor_bias=8)
    >>> L.err("lever"), L.err("anchor_bias"), L.n_err
    (slice(15, 18, None), slice(19, 27, None), 27)
    """

    _BASE_ERR = {"p": EP, "v": EV, "theta": ETH, "b_a": EBA, "b_g": EBG, "lever": EPIU,
                 "t_d": slice(ETD, ETD + 1)}
    _BASE_NOM = {"p": P, "v": V, "q": Q, "b_a": BA, "b_g": BG, "lever": PIU, "t_d": slice(TD, TD + 1)}

    def __init__(self, n_anchor_bias: int = 0, n_height_bias: int = 0, n_tags: int = 1, n_pair_bias: int = 0):
        if n_anchor_bias < 0 or n_height_bias not in (0, 1) or n_tags < 1 or n_pair_bias < 0:
            raise ValueError("StateLayout: n_anchor_bias >= 0, n_height_bias in (0, 1), n_tags >= 1, "
                             "n_pair_bias >= 0")
        self.n_anchor_bias = int(n_anchor_bias)
        self.n_height_bias = int(n_height_bias)
        self.n_tags = int(n_tags)
        self.n_pair_bias = int(n_pair_bias)
        self._err = dict(self._BASE_ERR)
        self._nom = dict(self._BASE_NOM)
        e, n = ERROR_DIM, NOMINAL_DIM
        # order of the extras: anchor biases, TDoA pair biases, the lever arms of tags 2.., the altimeter bias
        for name, size in (("anchor_bias", self.n_anchor_bias), ("pair_bias", self.n_pair_bias),
                           ("extra_levers", 3 * (self.n_tags - 1)), ("height_bias", self.n_height_bias)):
            self._err[name] = slice(e, e + size)
            self._nom[name] = slice(n, n + size)
            e += size
            n += size
        self.n_err = e
        self.n_nom = n

    def lever_err(self, tag: int) -> slice:
        """Error-state slice of the lever arm of tag number ``tag`` (0: the first, block ``lever``)."""
        if tag == 0:
            return self._err["lever"]
        s0 = self._err["extra_levers"].start + 3 * (tag - 1)
        return slice(s0, s0 + 3)

    def lever_nom(self, tag: int) -> slice:
        """Nominal-state slice of the lever arm of tag number ``tag``."""
        if tag == 0:
            return self._nom["lever"]
        s0 = self._nom["extra_levers"].start + 3 * (tag - 1)
        return slice(s0, s0 + 3)

    @classmethod
    def for_dims(cls, n_err: int, n_anchor_bias: Optional[int] = None) -> "StateLayout":
        """The layout of a one-tag error state of size ``n_err`` (extras are anchor biases unless told)."""
        nb = n_err - ERROR_DIM if n_anchor_bias is None else n_anchor_bias
        return cls(nb, n_err - ERROR_DIM - nb)

    def err(self, name: str) -> slice:
        """Slice of block ``name`` in the error state (and covariance)."""
        return self._err[name]

    def nom(self, name: str) -> slice:
        """Slice of block ``name`` in the nominal state."""
        return self._nom[name]

    def index(self, name: str, i: int = 0) -> int:
        """Error-state index of component ``i`` of block ``name`` (or -1 when the block is empty)."""
        sl = self._err[name]
        return sl.start + i if sl.start + i < sl.stop else -1

    def cov(self, P: np.ndarray, a: str, b: Optional[str] = None) -> np.ndarray:
        """Covariance block ``P[a, b]`` (``b`` defaults to ``a``)."""
        return P[self._err[a], self._err[a if b is None else b]]

    def sd(self, P: np.ndarray, name: str) -> np.ndarray:
        """Standard deviations of block ``name``."""
        return np.sqrt(np.clip(np.diag(P)[self._err[name]], 0.0, None))

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._err)
