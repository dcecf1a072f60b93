"""One pass of the ESKF over (part of) a dataset, with the data in plain arrays.

:class:`Problem` holds the dataset as contiguous arrays plus the resolved
numeric settings; :func:`run_pass` runs the filter from a given initial
state, range index and IMU sample until the data (or a window) ends or the
supervisor declares divergence.  The initialiser's hypothesis bank and the
main run both use it.  The per-sample work runs in one compiled loop
(:func:`kernels.filter_loop`, driven by :func:`advance`); :func:`advance_python`
is the same pass as a Python loop over the kernels (bit-identical results).

Time-offset handling
--------------------
A range stamped ``t`` (UWB clock) observes the state at IMU time
``tau = t + t_d_hat``.  The filter is propagated with the IMU samples until
its time ``t_k`` (an IMU stamp) passes ``tau`` — so ranges are processed with
a delay of at most one IMU period when ``t_d > 0`` and as soon as possible when
``t_d < 0`` — then the state at ``tau`` is obtained by integrating the actual
IMU samples *backward* from the current estimate (:func:`kernels.state_at`).
The update itself is applied at ``t_k`` with the measurement Jacobian mapped
through ``dx(tau) = (I - F (t_k - tau)) dx(t_k)`` (first order); since
``t_k - tau`` is below one IMU period except right after a large correction of
``t_d_hat`` (bounded by ``max_lookback_s``), this approximation of the
correlation between the two instants is of order ``dt_imu`` and negligible.
The Jacobian with respect to ``t_d`` is the time derivative of the predicted
antenna position, ``-u^T (v + R [w]x p_IU)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

import numpy as np

from uwbimu.errors import InputError
from uwbimu.estimation import kernels as K
from uwbimu.estimation.kernels import (  # noqa: F401  (re-exported)
    REC_ACC, REC_INNOV, REC_NIS, REC_PRED, REC_S, REC_STATUS, REC_W, STATUS_IN_GAP, STATUS_STALE,
)
from uwbimu.models.measurements import vector_update
from uwbimu.models.blocks import ProcessNoise
from uwbimu.models.state import StateLayout
from uwbimu.models import state as S

# columns of the per-range output record (REC_*) and the statuses beyond the kernels' UPD_* codes
# (STATUS_STALE, STATUS_IN_GAP) are defined in kernels, with the compiled loop that writes them
STATUS_NOT_PROCESSED = -1


@dataclass
class Problem:
    """A dataset as arrays, with the numeric settings resolved from the options."""

    imu_t: np.ndarray  # (n,) IMU clock [s]
    imu_u: np.ndarray  # (n, 6)
    imu_um: np.ndarray  # (n-1, 6) cubic mid-interval inputs (reference.midpoint_inputs)
    uwb_t: np.ndarray  # (m,) UWB clock [s]
    uwb_a: np.ndarray  # (m,) anchor index
    uwb_r: np.ndarray  # (m,) range [m] (documented biases already removed)
    anchor_ids: list[str]
    anchors: np.ndarray  # (M, 3)
    # (6,) the base 19-state's squared densities for the public ``kernels.cov_step`` (IMU accel / gyro white
    # noise, accel / gyro bias random walks, lever-arm and t_d random walks); the filter itself reads
    # process_noise
    noise: np.ndarray
    r_var: float  # range variance [m^2]
    bias_idx: np.ndarray  # (M,) error index of each anchor's bias or -1
    gain_mask: np.ndarray  # (N,)
    dt_nom: float
    dt_max: float
    gate: float  # NIS threshold (<= 0: none)
    robust_kind: int
    robust_c: float
    reopen_after: int
    cov_every: int
    max_lookback: float
    out_period: float
    store_cov: bool
    hull_lo: np.ndarray = field(default_factory=lambda: np.full(3, -np.inf))
    hull_hi: np.ndarray = field(default_factory=lambda: np.full(3, np.inf))
    max_pos_var: float = np.inf
    all_reject_run: int = 10**9
    supervise: bool = False
    # lever-arm rotation gate (lever_arm.min_rotation_rate): per IMU sample k, the mean gyro (n, 3) and the
    # mean squared gyro norm (n,) over the trailing window of lever_win samples ending at k (see
    # rotation_window_stats), and the threshold [rad/s]; 0 disables
    rot_mean: Optional[np.ndarray] = None
    rot_ms: Optional[np.ndarray] = None
    lever_win: int = 0
    lever_min_rate: float = 0.0

    def rotation_rms(self, k: int, b_g: np.ndarray) -> float:
        """RMS bias-corrected body rate [rad/s] over the ``lever_win`` IMU samples up to ``k``."""
        k = min(int(k), self.rot_ms.shape[0] - 1)
        m0, m1, m2 = self.rot_mean[k].tolist()
        b0, b1, b2 = b_g.tolist()
        ms = float(self.rot_ms[k]) - 2.0 * (m0 * b0 + m1 * b1 + m2 * b2) + (b0 * b0 + b1 * b1 + b2 * b2)
        return math.sqrt(ms) if ms > 0.0 else 0.0

    # IMU gaps: first sample index of each gap (imu_t[g + 1] - imu_t[g] > dt_max) and the sd of the
    # unknown input there (accelerometer [m/s^2], gyro [rad/s]); see gap_inflation
    gap_idx: Optional[np.ndarray] = None
    gap_sd: Optional[np.ndarray] = None  # (G, 2)
    # TDoA rows merged into the UWB stream (time order): uwb_b[j] >= 0 makes row j the TDoA
    # uwb_r[j] = |p_U - p_b| - |p_U - p_a| [m] with a = uwb_a[j], b = uwb_b[j], variance tdoa_var [m^2];
    # None (or -1 everywhere): every row is a range
    uwb_b: Optional[np.ndarray] = None
    tdoa_var: float = 0.0
    # the filter does not propagate beyond this IMU time (a streaming filter: the newest samples wait
    # for the next one that the cubic mid-interval input needs)
    t_limit: float = np.inf
    # measurements through the Python model protocol (height, zero velocity, user models): row j with
    # uwb_b[j] <= -2 is models[-uwb_b[j] - 2] = (model, z); uwb_a[j] = -1
    models: dict = field(default_factory=dict)
    layout: Optional[StateLayout] = None
    # several tags: tag number of each row (None: all the first tag), the error index of each tag's
    # lever block and the tags' names
    uwb_tag: Optional[np.ndarray] = None
    tag_lever_err: Optional[np.ndarray] = None
    tag_names: list = field(default_factory=list)
    # TDoA pair biases: (a, b) anchor indices -> error index of the pair's bias state
    pair_index: dict = field(default_factory=dict)
    # the declared blocks' process-noise tables (StateLayout.process_noise; None: the base 19-state's
    # from ``noise``, extras constant) and priors (estimation.problem.BlockPriors)
    process_noise: Optional[ProcessNoise] = None
    priors: Any = None

    @property
    def pair_sd0(self) -> float:
        """Prior sd of the TDoA pair-bias states [m] (``priors.block_sd``; 0 without priors)."""
        return float(self.priors.block_sd.get("pair_bias", 0.0)) if self.priors is not None else 0.0

    @property
    def height_sd0(self) -> float:
        """Prior sd of the altimeter-bias state [m] (``priors.block_sd``; 0 without priors)."""
        return float(self.priors.block_sd.get("height_bias", 0.0)) if self.priors is not None else 0.0

    def process_noise_tables(self) -> ProcessNoise:
        """The process-noise tables the kernels take (:attr:`process_noise`, else the base state's)."""
        if self.process_noise is None:
            self.process_noise = K.base_process_noise(np.ascontiguousarray(self.noise, dtype=float))
        return self.process_noise

    def state_layout(self) -> StateLayout:
        return self.layout  # set by estimation.problem.make_settings (never inferred from an array length)

    @property
    def n_err(self) -> int:
        return self.gain_mask.shape[0]


@dataclass
class PassResult:
    """Outputs of :func:`run_pass`."""

    t_imu: np.ndarray  # (K,) filter times (IMU clock)
    states: np.ndarray  # (K, 20 + nb)
    cov_diag: np.ndarray  # (K, N)
    covs: Optional[np.ndarray]  # (K, N, N) or None
    rec: np.ndarray  # (m, 7) per-range record for ranges [j0, j_end)
    j0: int
    j_end: int
    x: np.ndarray
    P: np.ndarray
    k: int
    diverged: Optional[str] = None
    events: list[dict[str, Any]] = field(default_factory=list)
    n_lever_frozen: int = 0  # accepted ranges that did not update the lever arm (rotation gate)


def cubic_midpoints(imu_t: np.ndarray, imu_u: np.ndarray) -> np.ndarray:
    """The cubic mid-interval IMU inputs ``(n-1, 6)`` of :func:`uwbimu.models.reference.midpoint_inputs`
    (Lagrange cubic through the four samples around each interval) by the compiled
    :func:`kernels.midpoints_into`: the same values (``tests/test_speed_midpoints.py``: bit-identical), a
    tenth of the time (no ``(n, 4, 6)`` temporaries: 0.35 s of a 10-minute 1 kHz log's set-up otherwise).

    ``imu_t`` (n,) IMU clock [s], strictly increasing; ``imu_u`` (n, 6) ``[a (m/s^2), w (rad/s)]``.
    """
    t = np.ascontiguousarray(imu_t, dtype=float)
    u = np.ascontiguousarray(imu_u, dtype=float)
    if t.ndim != 1 or u.ndim != 2 or u.shape != (len(t), 6):
        raise InputError(f"cubic_midpoints needs times (n,) and inputs (n, 6); got {t.shape} and {u.shape}")
    out = np.empty((max(len(t) - 1, 0), 6))
    if len(t) >= 2:
        K.midpoints_into(t, u, 0, len(t) - 1, out)
    return out


def rotation_window_stats(imu_u: np.ndarray, win: int) -> tuple[np.ndarray, np.ndarray]:
    """Trailing-window mean gyro (n, 3) and mean squared gyro norm (n,) over ``win`` samples ending at each
    sample (fewer at the start): ``E|w - b|^2 = ms - 2 b.mean + |b|^2`` for any bias ``b``."""
    w = imu_u[:, 3:6]
    n = w.shape[0]
    cs = np.vstack([np.zeros((1, 3)), np.cumsum(w, axis=0)])
    cs2 = np.concatenate([[0.0], np.cumsum(np.sum(w * w, axis=1))])
    i1 = np.arange(1, n + 1)
    i0 = np.maximum(0, i1 - max(int(win), 1))
    cnt = (i1 - i0).astype(float)
    return (cs[i1] - cs[i0]) / cnt[:, None], (cs2[i1] - cs2[i0]) / cnt


def gap_inputs(imu_t: np.ndarray, imu_u: np.ndarray, dt_max: float, around_s: float = 1.0):
    """IMU gaps and the sd of the unknown input inside each.

    Across a gap the filter integrates a linear interpolation of the IMU; the
    real input differs from it by an unknown amount, which the white-noise
    densities (made for one sample period) do not cover.  Its sd is taken from
    the data: the per-axis standard deviation of the accelerometer and gyro
    readings within ``around_s`` before the gap and the first sample after it
    (largest axis).
    Returns ``(gap_idx (G,), gap_sd (G, 2))``.
    """
    d = np.diff(imu_t)
    idx = np.flatnonzero(d > dt_max)
    sd = np.zeros((len(idx), 2))
    for i, g in enumerate(idx):
        lo = np.searchsorted(imu_t, imu_t[g] - around_s)
        hi = g + 2  # past data only (and the first sample after the gap): a streaming filter knows no more
        u = imu_u[lo:hi]
        if len(u) > 2:
            sd[i, 0] = float(np.max(np.std(u[:, 0:3], axis=0)))
            sd[i, 1] = float(np.max(np.std(u[:, 3:6], axis=0)))
    return idx, sd


def gap_inflation(P: np.ndarray, T: float, sd_a: float, sd_w: float) -> None:
    """Add to ``P`` (in place) the effect of an unknown input error held over a gap of ``T`` seconds.

    An acceleration error ``da`` (sd ``sd_a`` per world axis) gives ``dv = da T`` and
    ``dp = da T^2 / 2``; a body-rate error ``dw`` (sd ``sd_w``) gives ``dtheta = dw T``.
    """
    qa = sd_a * sd_a
    for i in range(3):
        P[i, i] += qa * T**4 / 4.0
        P[i, 3 + i] += qa * T**3 / 2.0
        P[3 + i, i] += qa * T**3 / 2.0
        P[3 + i, 3 + i] += qa * T * T
        P[6 + i, 6 + i] += sd_w * sd_w * T * T


def _propagate(prob: Problem, x: np.ndarray, P: np.ndarray, k: int, t_target: float, ws: np.ndarray) -> int:
    """:func:`kernels.propagate_until` that also inflates ``P`` for the unknown input across IMU gaps."""
    gi = prob.gap_idx
    if gi is not None and len(gi):
        n = prob.imu_t.shape[0]
        while True:
            # next gap not yet crossed, whose start the target reaches
            i = int(np.searchsorted(gi, k))
            if i >= len(gi) or gi[i] + 1 >= n or prob.imu_t[gi[i]] >= t_target:
                break
            g = int(gi[i])
            k = K.propagate_until(x, P, prob.imu_t, prob.imu_u, prob.imu_um, k, prob.imu_t[g + 1],
                                  prob.process_noise_tables(), prob.dt_max, prob.cov_every, ws)
            if k < g + 1:
                return k
            gap_inflation(P, prob.imu_t[g + 1] - prob.imu_t[g], prob.gap_sd[i, 0], prob.gap_sd[i, 1])
    return K.propagate_until(x, P, prob.imu_t, prob.imu_u, prob.imu_um, k, t_target, prob.process_noise_tables(),
                             prob.dt_max, prob.cov_every, ws)


def _diverged(prob: Problem, x: np.ndarray, P: np.ndarray, all_rej: int) -> Optional[str]:
    """The supervisor's verdict (None: healthy); the checks run compiled, the message only on failure."""
    code = K.divergence_code(x, P, prob.max_pos_var, prob.hull_lo, prob.hull_hi, all_rej, prob.all_reject_run)
    if code == 0:
        return None
    if code == 1:
        return "NaN in state or covariance"
    if code == 2:
        return "negative covariance diagonal"
    if code == 3:
        return f"position sd {np.sqrt(P[0, 0] + P[1, 1] + P[2, 2]):.1f} m above limit"
    if code == 4:
        return f"position {np.round(x[:3], 2).tolist()} far outside the anchors' hull"
    return f"{all_rej} consecutive ranges rejected"


@dataclass
class PassState:
    """Where a filter pass stands: state, covariance, IMU sample ``k``, next range ``j`` and the
    bookkeeping of the gate and the supervisor.  :func:`advance` moves it on as far as the data in the
    :class:`Problem` allows, so a pass can be resumed when more data arrive (the streaming filter) or
    run to the end in one call (:func:`run_pass`).

    The recorded outputs are the first ``n_out`` rows of ``out_t`` (IMU time), ``out_x`` (states),
    ``out_d`` (covariance diagonals) and ``out_P`` (covariances; None when not stored), arrays that
    grow as needed (:meth:`reserve_outputs`)."""

    x: np.ndarray
    P: np.ndarray
    k: int
    j: int
    j0: int
    next_out: float
    consec: np.ndarray  # (M,) consecutive rejections per anchor
    all_rej: int = 0
    n_frozen: int = 0
    diverged: Optional[str] = None
    n_out: int = 0
    out_t: Optional[np.ndarray] = None
    out_x: Optional[np.ndarray] = None
    out_d: Optional[np.ndarray] = None
    out_P: Optional[np.ndarray] = None
    events: list = field(default_factory=list)
    loop_args: Any = None  # advance's cached arguments of the compiled loop (_LoopArgs)

    @classmethod
    def start(cls, prob: "Problem", x0: np.ndarray, P0: np.ndarray, k0: int, j0: int) -> "PassState":
        return cls(x=np.array(x0, dtype=float), P=np.array(P0, dtype=float), k=int(k0), j=int(j0), j0=int(j0),
                   next_out=float(prob.imu_t[int(k0)]), consec=np.zeros(len(prob.anchor_ids) + 1, dtype=np.int64))

    def reserve_outputs(self, n_more: int, store_cov: bool) -> None:
        """Room for ``n_more`` further output rows (capacity at least doubled when it grows)."""
        cap = 0 if self.out_t is None else self.out_t.shape[0]
        need = self.n_out + int(n_more)
        if need <= cap:
            return
        cap = max(need, 2 * cap, 16)
        nx, N, n = self.x.shape[0], self.P.shape[0], self.n_out
        out_t, out_x, out_d = np.empty(cap), np.empty((cap, nx)), np.empty((cap, N))
        out_P = np.empty((cap, N, N)) if store_cov else None
        if n:
            out_t[:n], out_x[:n], out_d[:n] = self.out_t[:n], self.out_x[:n], self.out_d[:n]
            if out_P is not None and self.out_P is not None:
                out_P[:n] = self.out_P[:n]
        self.out_t, self.out_x, self.out_d, self.out_P = out_t, out_x, out_d, out_P

    def push_output(self, t: float, store_cov: bool) -> None:
        """Record the current state as an output row at IMU time ``t``."""
        self.reserve_outputs(1, store_cov)
        n = self.n_out
        self.out_t[n] = t
        self.out_x[n] = self.x
        self.out_d[n] = np.diag(self.P)
        if self.out_P is not None:
            self.out_P[n] = self.P
        self.n_out = n + 1

    def result(self, rec: np.ndarray, N: int, copy: bool = True) -> "PassResult":
        """The pass so far as a :class:`PassResult` (``rec`` indexed by absolute range index).

        ``copy=False`` returns views of the output arrays (for a pass that is over: nothing writes them
        any more)."""
        nb = self.x.shape[0]
        n = self.n_out
        if n:
            t_imu, states, cov_diag = self.out_t[:n], self.out_x[:n], self.out_d[:n]
            covs = self.out_P[:n] if self.out_P is not None else None
            if copy:
                t_imu, states, cov_diag = t_imu.copy(), states.copy(), cov_diag.copy()
                covs = covs.copy() if covs is not None else None
        else:
            t_imu, states, cov_diag, covs = np.zeros(0), np.zeros((0, nb)), np.zeros((0, N)), None
        return PassResult(
            t_imu=t_imu,
            states=states,
            cov_diag=cov_diag,
            covs=covs,
            rec=rec[self.j0:self.j],
            j0=self.j0,
            j_end=self.j,
            x=self.x,
            P=self.P,
            k=self.k,
            diverged=self.diverged,
            events=self.events,
            n_lever_frozen=self.n_frozen,
        )


def run_pass(
    prob: Problem,
    x0: np.ndarray,
    P0: np.ndarray,
    k0: int,
    j0: int,
    t_uwb_end: float = np.inf,
    record: bool = True,
    to_end: bool = True,
    progress: Optional[Callable[[int], None]] = None,
    engine: str = "compiled",
) -> PassResult:
    """Run the filter from IMU sample ``k0`` (state ``x0``, ``P0``) and range ``j0`` to the end of the data.

    Ranges with stamps beyond ``t_uwb_end`` are left alone.  ``record``
    stores the state and covariance every ``out_period`` seconds; ``to_end``
    propagates (and records) to the end of the IMU stream after the last range.
    ``engine``: ``"compiled"`` (:func:`advance`) or ``"python"`` (:func:`advance_python`, the pass as a
    Python loop over the kernels; same results bit for bit, kept as the benchmark's baseline).
    """
    st = PassState.start(prob, x0, P0, k0, j0)
    m = prob.uwb_t.shape[0]
    rec = np.full((m, 7), np.nan)
    rec[j0:, REC_STATUS] = STATUS_NOT_PROCESSED
    rec[j0:, REC_ACC] = 0.0
    advance(prob, st, rec, final=True, t_uwb_end=t_uwb_end, record=record, to_end=to_end, progress=progress,
            engine=engine)
    res = st.result(rec, P0.shape[0], copy=False)
    if not prob.store_cov:
        res.covs = None
    return res


def _frozen_mask(prob: Problem) -> np.ndarray:
    """The gain mask of an update whose lever arms are frozen by the rotation gate (consider mode): every
    block declared with the ``lever_arm`` mode option (``lever``, ``extra_levers``)."""
    mask = prob.gain_mask.copy()
    L = prob.state_layout()
    for b in L.blocks:
        if b.mode_option == "lever_arm":
            mask[L.err(b.name)] = 0.0
    return mask


_NO_INT = np.full(1, -1, dtype=np.int64)  # placeholder of an unused integer array argument
_NO_GAPS = np.zeros(0, dtype=np.int64)
_NO_ROT_MEAN = np.zeros((1, 3))
_NO_ROT_MS = np.zeros(1)
_EVENT_SLOTS = 64


class _LoopArgs:
    """The arguments of :func:`kernels.filter_loop` that only depend on the settings of the
    :class:`Problem` (kept on the :class:`PassState` between :func:`advance` calls: the streaming filter
    calls it for every pushed sample), and its state and event arrays."""

    def __init__(self, prob: Problem, key: tuple):
        self.key = key
        self.gain_mask = prob.gain_mask
        self.mask_frozen = _frozen_mask(prob)
        M = max(len(prob.anchor_ids), 1)
        self.pair_mat = np.full((M, M), -1, dtype=np.int64)
        for (a_, b_), i_ in prob.pair_index.items():
            self.pair_mat[a_, b_] = i_
        self.tag_lever_err = prob.tag_lever_err if prob.tag_lever_err is not None else _NO_INT
        self.fpar = np.zeros(K.FP_SIZE)
        self.fpar[[K.FP_DT_MAX, K.FP_GATE, K.FP_ROBUST_C, K.FP_MAX_LOOKBACK, K.FP_OUT_PERIOD, K.FP_R_VAR, K.FP_TDOA_VAR,
                   K.FP_MAX_POS_VAR, K.FP_LEVER_MIN_RATE]] = key[-9:]
        self.ipar = np.zeros(K.IP_SIZE, dtype=np.int64)
        self.ipar[[K.IP_ROBUST, K.IP_REOPEN, K.IP_COV_EVERY, K.IP_ALL_REJECT_RUN, K.IP_SUPERVISE,
                   K.IP_STORE_COV]] = [prob.robust_kind, prob.reopen_after, prob.cov_every,
                                       min(prob.all_reject_run, 2**62), prob.supervise, prob.store_cov]
        self.ist = np.zeros(K.IS_SIZE, dtype=np.int64)
        self.fst = np.zeros(1)
        self.ev = np.empty((_EVENT_SLOTS, 3), dtype=np.int64)
        N = prob.gain_mask.shape[0]
        self.no_cov = np.empty((0, N, N))  # out_P when covariances are not stored


def _loop_args(prob: Problem, st: PassState) -> _LoopArgs:
    """The :class:`_LoopArgs` of ``st`` for the current settings of ``prob`` (rebuilt when any changed)."""
    key = (id(prob.gain_mask), id(prob.layout), id(prob.pair_index), len(prob.pair_index), id(prob.tag_lever_err),
           len(prob.anchor_ids), _EVENT_SLOTS, prob.robust_kind, prob.reopen_after, prob.cov_every,
           prob.all_reject_run, prob.supervise, prob.store_cov,
           prob.dt_max, prob.gate, prob.robust_c, prob.max_lookback, prob.out_period, prob.r_var, prob.tdoa_var,
           prob.max_pos_var, prob.lever_min_rate)
    a = st.loop_args
    if a is None or a.key != key or a.gain_mask is not prob.gain_mask:
        a = st.loop_args = _LoopArgs(prob, key)
    return a


def _nothing_to_do(prob: Problem, st: PassState, x: np.ndarray, t_last: float, t_uwb_end: float) -> bool:
    """No measurement can be processed now (the next one is not reached by the IMU yet, or none is left);
    the caller has checked that no output is due either."""
    j = st.j
    if j >= prob.uwb_t.shape[0]:
        return True
    tj = prob.uwb_t[j]
    if tj > t_uwb_end:
        return True
    if prob.uwb_b is not None and prob.uwb_b[j] <= -2:
        return False  # a Python model (its own clock): let the loop decide
    return tj + x[S.TD] > t_last


def advance(
    prob: Problem,
    st: PassState,
    rec: np.ndarray,
    final: bool,
    t_uwb_end: float = np.inf,
    record: bool = True,
    to_end: bool = True,
    t_safe: float = -np.inf,
    progress: Optional[Callable[[int], None]] = None,
    engine: str = "compiled",
) -> None:
    """Move the pass ``st`` on (in place) through the ranges and IMU samples of ``prob``.

    A range is processed once the IMU stream reaches its IMU time ``tau = t + t_d_hat``; the ranges are
    taken in index order.  With ``final`` the data are complete: the pass stops at the first range the
    IMU does not reach and (``record`` and ``to_end``) records outputs to the end of the IMU stream.
    Without it (streaming) the pass waits there instead, and outputs are recorded only up to ``t_safe``
    (IMU clock), the time before which no further range can arrive; the sequence of propagations and
    updates is the same as in one final call over the same data, so chunked and batch runs agree.
    ``rec`` (m, 7) receives the per-range records at the ranges' absolute indices.

    The per-sample work runs in one compiled loop (:func:`kernels.filter_loop`); it comes back here only
    for what needs Python: a measurement of a Python model (processed by :func:`advance_python`, one
    row), the covariance inflation at the end of an IMU gap, the supervisor's message, progress reports
    (``progress`` is called about once per second of data, and at the end), growing the output arrays.
    ``engine="python"`` runs :func:`advance_python` instead (bit-identical results).
    """
    if engine == "python":
        advance_python(prob, st, rec, final, t_uwb_end, record, to_end, t_safe, progress)
        return
    if engine != "compiled":
        raise ValueError(f"advance: engine must be 'compiled' or 'python', got {engine!r}")
    imu_t = prob.imu_t
    x, P = st.x, st.P
    t_last = min(imu_t[-1], prob.t_limit)
    t_out_end = t_last + 1e-12 if (final and to_end) else min(t_last, t_safe)
    if not (record and st.next_out <= t_out_end) and _nothing_to_do(prob, st, x, t_last, t_uwb_end):
        # (the streaming filter's usual call: a sample arrived and no measurement is due yet)
        if progress is not None:
            progress(st.k)
        return
    gate_lever = prob.lever_min_rate > 0 and prob.rot_ms is not None and prob.gain_mask[S.EPIU.start] > 0
    multi = prob.uwb_tag is not None and prob.tag_lever_err is not None and len(prob.tag_lever_err) > 1
    store_cov = bool(prob.store_cov)
    if record and t_out_end >= st.next_out:
        st.reserve_outputs(int((t_out_end - st.next_out) / prob.out_period) + 2, store_cov)
    elif st.out_t is None:
        st.reserve_outputs(1, store_cov)
    a = _loop_args(prob, st)
    fpar, ipar, ist, fst, ev = a.fpar, a.ipar, a.ist, a.fst, a.ev
    fpar[K.FP_T_LAST], fpar[K.FP_T_UWB_END], fpar[K.FP_T_OUT_END] = t_last, t_uwb_end, t_out_end
    ipar[K.IP_GATE_LEVER], ipar[K.IP_MULTI], ipar[K.IP_RECORD] = gate_lever, multi, record
    ipar[K.IP_PROGRESS_EVERY] = max(1, int(round(1.0 / prob.out_period))) if progress is not None else 0
    ipar[K.IP_HAS_B] = prob.uwb_b is not None
    uwb_b = prob.uwb_b if prob.uwb_b is not None else _NO_INT
    uwb_tag = prob.uwb_tag if multi else _NO_INT
    rot_mean, rot_ms = (prob.rot_mean, prob.rot_ms) if gate_lever else (_NO_ROT_MEAN, _NO_ROT_MS)
    gap_idx = prob.gap_idx if prob.gap_idx is not None and len(prob.gap_idx) else _NO_GAPS
    mask_frozen, pair_mat, tag_lever_err = a.mask_frozen, a.pair_mat, a.tag_lever_err
    phase = K.PHASE_ROWS
    while True:
        ist[:K.IS_GAP] = (st.k, st.j, st.all_rej, st.n_frozen, st.n_out, phase)
        ist[K.IS_N_EV] = 0
        fst[0] = st.next_out
        out_P = st.out_P if st.out_P is not None else a.no_cov
        code = K.filter_loop(x, P, imu_t, prob.imu_u, prob.imu_um, prob.uwb_t, prob.uwb_a, uwb_b, prob.uwb_r,
                             uwb_tag, prob.anchors, prob.bias_idx, a.gain_mask, mask_frozen, tag_lever_err,
                             pair_mat, prob.process_noise_tables(), prob.hull_lo, prob.hull_hi, rot_mean, rot_ms, gap_idx,
                             st.consec, rec, st.out_t, st.out_x, st.out_d, out_P, ev, fpar, ipar, ist, fst)
        st.k, st.j, st.all_rej, st.n_frozen, st.n_out, phase, gap_i, _, n_ev = ist.tolist()
        st.next_out = float(fst[0])
        for jj, aa, cc in (ev[:n_ev].tolist() if n_ev else ()):
            st.events.append({"t": float(prob.uwb_t[jj]), "kind": "gate_reopened", "anchor": prob.anchor_ids[aa],
                              "after_rejections": int(cc)})
        if code == K.LOOP_DONE:
            break
        if code == K.LOOP_OUT_FULL:
            st.reserve_outputs(max(16, st.out_t.shape[0]), store_cov)
        elif code == K.LOOP_GAP:
            g = int(gap_idx[gap_i])
            gap_inflation(P, imu_t[g + 1] - imu_t[g], prob.gap_sd[gap_i, 0], prob.gap_sd[gap_i, 1])
        elif code == K.LOOP_PROGRESS:
            progress(st.k)
        elif code == K.LOOP_DIVERGED:
            st.diverged = _diverged(prob, x, P, st.all_rej)
            break
        elif code == K.LOOP_MODEL:
            j = st.j
            advance_python(prob, st, rec, final, t_uwb_end, record, to_end, t_safe, progress, j_stop=j + 1)
            if st.diverged is not None:
                break
            if st.j == j:  # not reached yet: the measurements end here for now
                phase = K.PHASE_TAIL
        # LOOP_EVENTS_FULL: the events were drained above
    if progress is not None:
        progress(st.k)


def advance_python(
    prob: Problem,
    st: PassState,
    rec: np.ndarray,
    final: bool,
    t_uwb_end: float = np.inf,
    record: bool = True,
    to_end: bool = True,
    t_safe: float = -np.inf,
    progress: Optional[Callable[[int], None]] = None,
    j_stop: Optional[int] = None,
) -> None:
    """:func:`advance` as a Python loop over the kernels (the filter pass before the compiled loop; kept
    as the reference of ``tests/test_filter_loop.py`` and the baseline of ``benchmarks/bench_eskf.py``,
    and used by :func:`advance` for the measurements of Python models).

    ``j_stop``: process the measurements before index ``j_stop`` only, then return (no outputs after the
    last one, no final progress call).
    """
    imu_t = prob.imu_t
    n_imu = imu_t.shape[0]
    x, P = st.x, st.P
    ws = np.zeros(1)
    m = prob.uwb_t.shape[0]
    o = np.empty(7)
    gate_lever = prob.lever_min_rate > 0 and prob.rot_ms is not None and prob.gain_mask[S.EPIU.start] > 0
    mask_frozen = _frozen_mask(prob)
    multi = prob.uwb_tag is not None and prob.tag_lever_err is not None and len(prob.tag_lever_err) > 1
    consec = st.consec
    # locals for the per-range loop (attribute lookups cost as much as the kernels' calls here)
    uwb_t, uwb_a, uwb_b, uwb_r = prob.uwb_t, prob.uwb_a, prob.uwb_b, prob.uwb_r
    imu_u, imu_um, anchors, bias_idx = prob.imu_u, prob.imu_um, prob.anchors, prob.bias_idx
    i_bg = S.EBG.start
    pair_index = prob.pair_index
    store_cov = bool(prob.store_cov)

    def _record():
        st.push_output(imu_t[st.k], store_cov)

    t_last = min(imu_t[-1], prob.t_limit)
    j = st.j
    m_stop = m if j_stop is None else min(m, j_stop)
    while j < m_stop and st.diverged is None:
        tj = uwb_t[j]
        if tj > t_uwb_end:
            break
        b = -1 if uwb_b is None else int(uwb_b[j])
        model = prob.models[-b - 2][0] if b <= -2 else None
        # a UWB-clock stamp sees the IMU-clock state t_d later
        tau = tj + x[S.TD] if model is None or model.clock == "uwb" else tj
        if tau > t_last:
            break
        if record:
            while st.next_out <= tau:
                st.k = _propagate(prob, x, P, st.k, st.next_out, ws)
                _record()
                st.next_out += prob.out_period
                if prob.supervise:
                    st.diverged = _diverged(prob, x, P, st.all_rej)
                    if st.diverged:
                        break
                if progress is not None:
                    progress(st.k)
            if st.diverged:
                break
        st.k = k = _propagate(prob, x, P, st.k, tau, ws)
        if imu_t[k] - tau > prob.max_lookback:
            rec[j, REC_STATUS] = STATUS_STALE
            j += 1
            continue
        if k > 0 and imu_t[k] - imu_t[k - 1] > prob.dt_max and imu_t[k - 1] < tau < imu_t[k]:
            rec[j, REC_STATUS] = STATUS_IN_GAP
            j += 1
            continue
        a = uwb_a[j]
        if a < 0:
            a = consec.shape[0] - 1  # the gate counter of the model measurements
        force = consec[a] >= prob.reopen_after
        # no rotation, no lever-arm information: Schmidt (consider) update for the lever arm only
        # (the rate must stand out from the gyro-bias uncertainty: before the bias has converged an
        # uncorrected bias would otherwise pass for rotation)
        frozen = gate_lever and (prob.rotation_rms(k, x[S.BG])
                                 - math.sqrt(max(P[i_bg, i_bg] + P[i_bg + 1, i_bg + 1] + P[i_bg + 2, i_bg + 2], 0.0))
                                 < prob.lever_min_rate)
        mask = mask_frozen if frozen else prob.gain_mask
        lev = int(prob.tag_lever_err[prob.uwb_tag[j]]) if multi else S.E_L
        if model is not None:
            _model_update(prob, x, P, k, tau, model, prob.models[-b - 2][1], force, mask, o)
        elif b < 0:
            K.range_update(
                x, P, imu_t, imu_u, imu_um, k, tau, anchors[a], bias_idx[a], uwb_r[j],
                prob.r_var, prob.gate, force, prob.robust_kind, prob.robust_c, mask, prob.dt_max, o, lev,
            )
        else:
            # per-anchor bias states (anchor_bias mode estimate): the TDoA sees their difference b_b - b_a
            K.tdoa_update(
                x, P, imu_t, imu_u, imu_um, k, tau, anchors[a], anchors[b], bias_idx[a], bias_idx[b], uwb_r[j],
                prob.tdoa_var, prob.gate, force, prob.robust_kind, prob.robust_c, mask, prob.dt_max, o, lev,
                pair_index.get((int(a), b), -1) if pair_index else -1,
            )
        rec[j] = o
        if o[REC_ACC] > 0:
            st.n_frozen += int(frozen)
            if force:
                # a reopened gate does not prove the filter healthy: keep counting towards divergence
                st.events.append({"t": float(tj), "kind": "gate_reopened",
                                  "anchor": prob.anchor_ids[a] if a < len(prob.anchor_ids) else model.name,
                                  "after_rejections": int(consec[a])})
                st.all_rej += 1
            else:
                st.all_rej = 0
            consec[a] = 0
        elif o[REC_STATUS] == K.UPD_OK:
            consec[a] += 1
            st.all_rej += 1
        j += 1
        if prob.supervise and st.all_rej >= prob.all_reject_run:
            st.diverged = _diverged(prob, x, P, st.all_rej)
    st.j = j
    if j_stop is not None:
        return
    if st.diverged is None and record:
        t_out_end = t_last + 1e-12 if (final and to_end) else min(t_last, t_safe)
        while st.next_out <= t_out_end:
            st.k = _propagate(prob, x, P, st.k, st.next_out, ws)
            _record()
            st.next_out += prob.out_period
            if st.k >= n_imu - 1:
                break
    if progress is not None:
        progress(st.k)


def _model_update(prob: Problem, x: np.ndarray, P: np.ndarray, k: int, tau: float, model, z: np.ndarray,
                  force: bool, mask: np.ndarray, o: np.ndarray) -> None:
    """One measurement through the Python model protocol (:mod:`uwbimu.models.measurements`).

    The model is evaluated at ``tau`` (state integrated back from the filter's sample ``k``, as for a
    range) and its Jacobian applied at the filter time: ``tau`` lies within one IMU period of it, the
    first-order time mapping the range kernel applies is neglected here (an error of order dt_imu)."""
    xt = np.empty_like(x)
    u_tau = np.empty(6)
    st = K.state_at(x, prob.imu_t, prob.imu_u, prob.imu_um, k, tau, prob.dt_max, xt, u_tau)
    o[5] = st
    if st != K.UPD_OK:
        o[0:5] = (np.nan, np.nan, np.nan, 0.0, 0.0)
        o[6] = np.nan
        return
    L = prob.state_layout()
    pred = np.atleast_1d(model.evaluate(xt, u_tau))
    H = np.atleast_2d(model.jacobian(xt, u_tau, L))
    r = np.atleast_1d(z) - pred
    gate_p = 1.0 if prob.gate <= 0 else _gate_probability(prob.gate)
    res = vector_update(x, P, H, r, np.atleast_2d(model.covariance()), gate_p, force,
                        prob.robust_c if prob.robust_kind != K.ROBUST_NONE else 0.0, mask, K.inject)
    o[0], o[1], o[2] = pred[0], r[0], res["nis"]
    o[3] = 1.0 if res["accepted"] else 0.0
    o[4] = res["weight"]
    o[6] = res["S"]


def _gate_probability(gate_nis_1dof: float) -> float:
    """The acceptance probability behind a one-degree-of-freedom NIS threshold (same for any dim)."""
    # scipy.special, not scipy.stats (whose import costs about a second): chi2.cdf(x, k) is chdtr(k, x)
    from scipy.special import chdtr

    return float(chdtr(1, gate_nis_1dof))
