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

Every block is declared once in :mod:`uwbimu.models.blocks`; the slices and index constants here
(``P`` .. ``TD`` nominal, ``EP`` .. ``ETD`` error, ``N_*`` / ``E_*`` their first indices for numba,
``NOM_SHIFT``, ``N_DYN``) are computed from those declarations, and :class:`StateLayout` compiles
them with a run's multiplicities.  The time offset is ``t_d`` everywhere in code (block ``t_d``;
``TD`` / ``ETD`` / ``N_TD`` / ``E_TD`` are its indices), ``time_offset`` in the options and the
calibration outputs and as its state-column name (``time_offset``, ``sd_time_offset``; formerly ``td``).
"""

from __future__ import annotations

from typing import Optional

import numpy as np

from uwbimu.models.quaternion import quat_exp, quat_multiply, quat_normalize, quat_conjugate, quat_log

from uwbimu.models.blocks import BLOCK, BLOCKS, PN_IMU, BlockSpec, ProcessNoise


def _base_offsets() -> tuple[dict[str, slice], dict[str, slice], int, int]:
    """Slices of the always-present blocks (multiplicity ``"one"``), from the declarations."""
    err, nom, e, n = {}, {}, 0, 0
    for b in BLOCKS:
        if b.multiplicity != "one":
            continue
        err[b.name], nom[b.name] = slice(e, e + b.size), slice(n, n + b.n_nom)
        e, n = e + b.size, n + b.n_nom
    return err, nom, e, n


_E, _N, ERROR_DIM, NOMINAL_DIM = _base_offsets()

# nominal-state slices (from the declarations in models/blocks.py)
P, V, Q, BA, BG, PIU = _N["p"], _N["v"], _N["theta"], _N["b_a"], _N["b_g"], _N["lever"]
TD = _N["t_d"].start  # nominal index of the time offset t_d

# error-state slices
EP, EV, ETH, EBA, EBG, EPIU = _E["p"], _E["v"], _E["theta"], _E["b_a"], _E["b_g"], _E["lever"]
ETD = _E["t_d"].start  # error index of the time offset t_d

# First indices of the blocks, for numba kernels (integer globals are compile-time constants there;
# slices are not): nominal ``N_*`` and error-state ``E_*`` offsets of the slices above.
N_P, N_V, N_Q, N_BA, N_BG, N_L, N_TD = P.start, V.start, Q.start, BA.start, BG.start, PIU.start, TD
E_P, E_V, E_TH, E_BA, E_BG, E_L, E_TD = EP.start, EV.start, ETH.start, EBA.start, EBG.start, EPIU.start, ETD

#: nominal index - error index of every block after the attitude (the quaternion has one component more
#: than its error): ``x[i + NOM_SHIFT]`` is the nominal component of error component ``i >= E_BA``
NOM_SHIFT = N_BA - E_BA
if any(_N[b.name].start - _E[b.name].start != NOM_SHIFT for b in BLOCKS[BLOCKS.index(BLOCK["theta"]) + 1:]
       if b.multiplicity == "one"):  # pragma: no cover - a declaration change must keep the shift uniform
    raise ImportError("models.state: every block after the attitude must sit NOM_SHIFT further in the nominal state")

#: error components driven by the IMU through the transition (p, v, theta, b_a, b_g: the first N_DYN): the
#: kernels apply ``Phi`` to these rows only, every later block has identity transition rows
N_DYN = sum(b.size for b in BLOCKS if b.process_noise == "imu")
if any(_E[b.name].stop > N_DYN for b in BLOCKS if b.process_noise == "imu"):  # pragma: no cover
    raise ImportError("models.state: the IMU-driven blocks must come first")

#: Names of the 19 error-state components, in order (used for CSV columns and reports).
ERROR_STATE_NAMES = tuple(n for b in BLOCKS if b.multiplicity == "one" for n in b.output_names)

#: Names of the 20 nominal-state components, in order.
NOMINAL_STATE_NAMES = tuple(n for b in BLOCKS if b.multiplicity == "one" for n in b.nom_names)


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
    """The extended filter state's blocks, compiled from the declarations of :mod:`uwbimu.models.blocks`.

    The extended nominal state is the 20 numbers above followed by ``n_anchor_bias`` per-anchor range
    biases [m], ``n_pair_bias`` TDoA pair biases [m] (``pair_bias``), the lever arms of tags
    2..``n_tags`` [m] (``extra_levers``; the first tag's is ``lever``) and ``n_height_bias`` (0 or 1)
    altimeter biases [m], in the order of :data:`~uwbimu.models.blocks.BLOCKS`; the error state is the 19
    above followed by the same additive components.  ``err(name)`` and ``nom(name)`` give slices,
    ``cov(P, a, b)`` a covariance block (as OpenVINS addresses its covariance by the variable's id),
    :meth:`process_noise` the numba tables, ``lever_err(i)`` / ``lever_nom(i)`` per tag.

    >>> L = StateLayout(n_anchor_bias=8)
    >>> L.err("lever"), L.err("anchor_bias"), L.n_err
    (slice(15, 18, None), slice(19, 27, None), 27)
    """

    def __init__(self, n_anchor_bias: int = 0, n_height_bias: int = 0, n_tags: int = 1, n_pair_bias: int = 0,
                 *, counts: Optional[dict[str, int]] = None, blocks: tuple[BlockSpec, ...] = BLOCKS):
        counts = {"anchor_bias": n_anchor_bias, "height_bias": n_height_bias, "extra_levers": n_tags - 1,
                  "pair_bias": n_pair_bias, **(counts or {})}
        #: the declarations this layout is compiled from (models.blocks.BLOCKS unless given)
        self.declarations = tuple(blocks)
        #: number of instances of each declared block (1 for the base blocks)
        self.count: dict[str, int] = {}
        for b in self.declarations:
            c = 1 if b.multiplicity == "one" else int(counts.get(b.name, 0))
            if c < 0 or (b.multiplicity == "optional" and c > 1):
                raise ValueError(f"StateLayout: {c} instances of block {b.name!r} ({b.multiplicity})")
            self.count[b.name] = c
        self.n_anchor_bias = self.count.get("anchor_bias", 0)
        self.n_height_bias = self.count.get("height_bias", 0)
        self.n_tags = self.count.get("extra_levers", 0) + 1
        self.n_pair_bias = self.count.get("pair_bias", 0)
        self._err: dict[str, slice] = {}
        self._nom: dict[str, slice] = {}
        e = n = 0
        for b in self.declarations:
            c = self.count[b.name]
            self._err[b.name] = slice(e, e + c * b.size)
            self._nom["q" if b.name == "theta" else b.name] = slice(n, n + c * b.n_nom)
            e += c * b.size
            n += c * b.n_nom
        self.n_err = e
        self.n_nom = n

    @property
    def blocks(self) -> tuple[BlockSpec, ...]:
        """The declarations of the blocks present (count > 0), in state order."""
        return tuple(b for b in self.declarations if self.count[b.name] > 0)

    def error_names(self) -> tuple[str, ...]:
        """Error-state component names of the whole layout: a ``"one"`` or ``"optional"`` block's output names,
        ``<block>_<i>_<name>`` for the instances of the other blocks."""
        return tuple(nm if b.multiplicity in ("one", "optional") else f"{b.name}_{i}_{nm}" for b in self.blocks
                     for i in range(self.count[b.name]) for nm in b.output_names)

    def process_noise(self, imu: np.ndarray, values: dict[str, tuple[float, float]]) -> ProcessNoise:
        """The numba tables of the process noise (:class:`~uwbimu.models.blocks.ProcessNoise`).

        Parameters
        ----------
        imu : (4,) squared IMU densities ``[s_a^2, s_g^2, s_ba^2, s_bg^2]``.
        values : block name -> ``(q, inv_tau)`` for every present block not driven by the IMU (random
            walk: ``q`` the density^2 [unit^2/s]; Gauss-Markov: ``q`` the stationary variance [unit^2],
            ``inv_tau`` [1/s], 0: constant; constant: ignored).
        """
        rows = [b for b in self.blocks if b.kind != PN_IMU]
        missing = [b.name for b in rows if b.process_noise != "constant" and b.name not in values]
        if missing:
            raise ValueError(f"StateLayout.process_noise: no process noise for blocks {missing}")
        q = [float(values.get(b.name, (0.0, 0.0))[0]) for b in rows]
        it = [float(values.get(b.name, (0.0, 0.0))[1]) for b in rows]
        return ProcessNoise(
            imu=np.ascontiguousarray(np.asarray(imu, dtype=float).reshape(4)),
            kind=np.array([b.kind for b in rows], dtype=np.int64),
            err0=np.array([self._err[b.name].start for b in rows], dtype=np.int64),
            nom0=np.array([self._nom[b.name].start for b in rows], dtype=np.int64),
            size=np.array([self._err[b.name].stop - self._err[b.name].start for b in rows], dtype=np.int64),
            q=np.array(q, dtype=float), inv_tau=np.array(it, dtype=float))

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
