"""Streaming error-state EKF: push IMU samples and UWB measurements as they arrive, read the state.

::

    from uwbimu.estimation import Eskf, EskfOptions

    f = Eskf(EskfOptions(), anchors={"A1": [0, 0, 2], "A2": [5, 0, 2], ...})
    for sample in sensor_stream:
        if sample.kind == "imu":
            f.push_imu(sample.t, sample.acc, sample.gyro)
        else:
            f.push_range(sample.t, sample.anchor, sample.range)
        s = f.state()          # None until initialised
    f.finish()                  # end of the data: process what is still waiting

The filter is the batch filter (:func:`uwbimu.estimation.filterpass.advance`, the same kernels, the
same initialiser), fed piece by piece: a measurement stamped ``t`` (UWB clock) is processed once the
IMU reaches its IMU time ``t + t_d_hat``, and the IMU interval ``[k, k+1]`` once sample ``k + 2`` has
arrived (the cubic mid-interval input needs it).  The initialiser waits until the data cover what it
reads (:func:`uwbimu.estimation.init.data_needed`).  Fed in time order (each measurement before the IMU
samples that pass its IMU time by more than ``max_latency_s``), the sequence of propagations and
updates, hence the trajectory, is the batch one whatever the chunk sizes (``tests/test_streaming.py``).
A measurement that arrives later than that is processed on arrival, at its own time (the state is
integrated back over at most ``max_lookback_s``).

Memory: without ``record`` the buffers keep only what the time offset, the rotation gate and a
re-initialisation need; :func:`uwbimu.estimation.run_eskf` records everything.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any, Mapping, Optional, Sequence

import numpy as np

from uwbimu.estimation import kernels as K
from uwbimu.estimation.filterpass import (
    REC_ACC, REC_STATUS, STATUS_NOT_PROCESSED, PassResult, PassState, Problem, advance,
)
from uwbimu.estimation.init import InitialisationError, InitialState, data_needed, hold_time_offset, initialise
from uwbimu.estimation.options import EskfOptions
from uwbimu.estimation.outputs import block_calibration
from uwbimu.estimation.problem import (NOMINAL_PERIOD_SAMPLES, BlockPriors, make_settings, nominal_period,
                                       set_imu_timing)
from uwbimu.estimation.stream_guards import (
    GEOMETRY_SLACK_M, MAX_ACC, MAX_GYRO, NisMonitor, Rejections, as_floats, check_imu_noise, check_options,
    finite_number, positive, push_sigma, same_length,
)
from uwbimu.errors import StreamInputError, UsageError
from uwbimu.models import state as S
from uwbimu.models.imu import ImuNoise
from uwbimu.models.measurements import HeightModel, MeasurementModel, ZeroVelocityModel
from uwbimu.models.quaternion import quat_multiply

#: rotation of 180 deg about x (its own inverse): anchors' z-down frame <-> the filter's z-up world
_FLIP = np.array([1.0, -1.0, -1.0])

#: :meth:`Eskf.push_imu` keeps up to this many accepted samples and processes them as one chunk: the Python
#: bookkeeping of a call into the filter (buffers, mid-interval inputs, gap and rotation statistics, the
#: compiled loop's arguments) costs tens of microseconds whatever the number of samples, the checks of one
#: sample a few.  Every other push and every accessor (``state``, ``events``, ``initialised``, ...)
#: processes the kept samples first, so what a caller can observe is what one-sample processing gives, bit
#: for bit (``tests/test_streaming_chunks.py``).  64 samples are 64 ms at 1 kHz.
IMU_BATCH = 64
#: :meth:`Eskf.push_range` and :meth:`Eskf.push_tdoa` keep up to this many checked measurements (in
#: arrival order, with the IMU samples kept) and hand them to the filter with the next chunk: one call into
#: the buffers and one filter step per chunk instead of one per measurement.  Every other push, every
#: accessor and every rejection processes what is kept first, so the order of events and the estimates are
#: those of one-at-a-time processing (``tests/test_streaming_chunks.py``).
MEAS_BATCH = 64
_Q_FLIP = np.array([0.0, 1.0, 0.0, 0.0])


class _Buffer:
    """A growable array (amortised appends) with a movable start (trimming)."""

    def __init__(self, width: Optional[int], dtype=float, fill=0.0):
        self.shape_tail = () if width is None else (width,)
        self.a = np.full((256,) + self.shape_tail, fill, dtype=dtype)
        self.n = 0
        self.fill = fill

    def _grow(self, need: int) -> None:
        if need > len(self.a):
            cap = max(2 * len(self.a), need)
            b = np.full((cap,) + self.shape_tail, self.fill, dtype=self.a.dtype)
            b[: self.n] = self.a[: self.n]
            self.a = b

    def extend(self, v: np.ndarray) -> None:
        m = len(v)
        self._grow(self.n + m)
        self.a[self.n:self.n + m] = v
        self.n += m

    def reserve(self, n: int) -> None:
        """Make the length ``n`` (new entries filled), keeping capacity for more."""
        if n > self.n:
            self._grow(n)
            self.a[self.n:n] = self.fill
            self.n = n

    def view(self, n: Optional[int] = None) -> np.ndarray:
        return self.a[: self.n if n is None else n]

    def drop_front(self, m: int) -> None:
        if m <= 0:
            return
        self.a[: self.n - m] = self.a[m:self.n].copy()
        self.n -= m


@dataclass
class EskfState:
    """The filter's current estimate (world frame of the anchors, SI units).

    ``t`` is the UWB-clock time of the estimate (``t_imu - time_offset``); every ``*_sd`` is the square
    root of the covariance diagonal; ``covariance`` is the full error-state covariance (19 + number of
    anchor-bias states), ordered as :data:`uwbimu.models.state.ERROR_STATE_NAMES` then the biases.
    """

    t: float
    t_imu: float
    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    accel_bias: np.ndarray
    gyro_bias: np.ndarray
    lever_arm: np.ndarray
    time_offset: float
    anchor_bias: dict[str, float]
    position_sd: np.ndarray
    velocity_sd: np.ndarray
    attitude_sd: np.ndarray
    accel_bias_sd: np.ndarray
    gyro_bias_sd: np.ndarray
    lever_arm_sd: np.ndarray
    time_offset_sd: float
    covariance: np.ndarray
    layout: S.StateLayout
    tags: dict = None  # several tags: name -> (lever arm (3,), sd (3,)); the first is also lever_arm
    height_bias: Optional[float] = None
    height_bias_sd: Optional[float] = None
    #: False when the estimate must not be used; ``invalid_reason`` says why (see :class:`Eskf`)
    valid: bool = True
    invalid_reason: Optional[str] = None
    #: added to the pushed IMU stamps since an IMU clock restart (``t_imu`` is on the shifted clock) [s]
    imu_clock_shift: float = 0.0
    #: every declared block's output, as the batch run writes it to calibration.yaml
    #: (:func:`uwbimu.estimation.outputs.block_calibration`: ``<key>``, ``<key>_sd``, ``<key>_mode`` ...)
    blocks: dict = None

    def cov(self, a: str, b: Optional[str] = None) -> np.ndarray:
        """Covariance block by name (``"p"``, ``"theta"``, ``"lever"``, ``"t_d"``, ``"anchor_bias"``, ...)."""
        return self.layout.cov(self.covariance, a, b)


class Eskf:
    """Streaming tightly-coupled UWB-IMU error-state EKF with online lever arm and time offset.

    Parameters
    ----------
    options : :class:`EskfOptions` (defaults when None).
    anchors : mapping anchor id -> position (3,) [m] in the anchors' frame.
    tags : optional mapping tag name -> nominal lever arm (3,) [m] or None.  The filter estimates the
        lever arm of one tag (``options.tag``, else the first); ranges of other tags are counted and
        not used.
    imu_noise : IMU densities (None: ``options.imu_noise``, else the BMI088 preset).
    range_sigma, tdoa_sigma : measurement noise sd [m] (None: the options', else 0.1 and
        ``sqrt(2) range_sigma``).
    anchor_frame_up : ``"+z"`` (default) or ``"-z"`` when the anchors' frame has z down.
    known_anchor_bias : documented constant range bias per anchor [m], removed from every range.
    record : keep every output row (``output_rate_hz``) and every measurement record (for
        :meth:`passes`); without it the buffers are trimmed as the filter advances.
    max_latency_s : how long [s of IMU time] the filter waits for measurements before it moves its
        outputs on without them.
    tdoa_pairs : anchor-id pairs ``(a, b)`` that get a constant TDoA bias state when
        ``options.tdoa_pair_bias.mode`` is ``"estimate"``.
    max_gap_s : the longest IMU interval [s] the filter propagates across (longer: re-initialisation),
        and the longest time without a processed UWB measurement before ``state().valid`` turns False.
    clock_restart_s : an IMU stamp more than this [s] behind the newest one is an IMU clock restart.
    max_acc, max_gyro : plausibility bounds of ``|acc|`` [m/s^2] (default 50 g) and ``|gyro|`` [rad/s]
        (default 35).

    Input guards (``docs/estimator.md``, "Streaming input guards")
    ----------------------------------------------------------------
    Raised, :class:`uwbimu.errors.StreamInputError` (an ``InputError``; ``field``, ``reason``): arguments of
    a push that are not numbers, have the wrong shape (``acc`` not 3 values, ...) or different lengths; a
    model whose ``z`` has not ``model.dim`` values; a push ``sigma`` that is not finite and > 0.  Nothing of
    such a push is used.  Bad constructor arguments raise :class:`~uwbimu.errors.UsageError`, bad
    ``options`` :class:`~uwbimu.errors.ConfigError` (both name the field).

    Skipped, with an event ``{"kind": "input_rejected", "stream", "reason", "count", "t", "t_last"}``
    (consecutive rejections of one stream and reason are one event) and counted in ``finish``'s
    ``inputs_not_used``: ``imu_not_finite``; ``imu_implausible`` (beyond ``max_acc`` / ``max_gyro``);
    ``imu_not_increasing`` (a stamp equal to the newest one, or behind it by at most
    ``clock_restart_s``); ``not_finite`` (a measurement's stamp or value); ``unknown_anchor``;
    ``same_anchor`` (a TDoA between one anchor); ``other_tag``; ``range_not_positive``;
    ``range_too_long`` (longer than the diagonal of the supervisor's box, the anchors' bounding box
    grown by ``supervisor.hull_margin``, plus 1 m); ``tdoa_too_large`` (``|tdoa|`` beyond the anchors'
    distance plus 1 m and 5 sd); ``before_imu_discontinuity`` (a measurement whose IMU time lies before
    the end of an IMU gap, when re-initialising after it).  :meth:`feed` (arrays of a validated
    :class:`Problem`) applies the IMU checks and the finite / anchor checks only.

    Recovered, with an event ``{"kind": "imu_discontinuity", "t_imu", "jump_s", "action"}``: an IMU
    interval longer than ``max_gap_s`` (a data gap or a forward clock jump) ends the filter pass
    (``action: "reinitialise"``): the filter re-initialises from the measurements after it, and until
    then :meth:`state` returns the last estimate with ``valid=False``; an IMU stamp more than
    ``clock_restart_s`` behind the newest one (a clock restart) shifts that and every later IMU stamp so
    that the stream continues one nominal period after the newest sample (``action: "rebase"``,
    ``shift_s``; :attr:`EskfState.imu_clock_shift`).  Measurements are never re-stamped: a UWB clock that
    jumps leaves its measurements unused (stale, or waiting for the IMU) and the state flagged below.

    Validity (:attr:`EskfState.valid`, :attr:`EskfState.invalid_reason`): ``"not_finite"``;
    ``"divergence"`` (the supervisor's verdict, event ``divergence``; the last estimate until the
    re-initialisation); ``"imu_gap"`` (re-initialising after an IMU discontinuity); ``"stopped"`` (the
    initialiser failed); ``"inconsistent"`` (more than half of the last 50 processed UWB measurements
    have a NIS above 9, events ``inconsistent`` / ``consistent_again``: :class:`NisMonitor`);
    ``"position_sd"`` (above ``supervisor.max_position_sd``); ``"no_measurements"`` (no UWB measurement
    processed for more than ``max_gap_s`` of IMU time).
    """

    def __init__(
        self,
        options: Optional[EskfOptions] = None,
        anchors: Optional[Mapping[str, Sequence[float]]] = None,
        tags: Optional[Mapping[str, Optional[Sequence[float]]]] = None,
        *,
        imu_noise: Optional[ImuNoise] = None,
        range_sigma: Optional[float] = None,
        tdoa_sigma: Optional[float] = None,
        anchor_frame_up: str = "+z",
        known_anchor_bias: Optional[Mapping[str, float]] = None,
        record: bool = False,
        max_latency_s: float = 0.2,
        tdoa_pairs: Optional[Sequence[tuple[str, str]]] = None,
        max_gap_s: float = 2.0,
        clock_restart_s: float = 0.1,
        max_acc: float = MAX_ACC,
        max_gyro: float = MAX_GYRO,
    ):
        self.options = opts = check_options(options if options is not None else EskfOptions())
        if not anchors:
            raise UsageError("Eskf: anchors must map at least one anchor id to its position [x, y, z]")
        self.anchor_ids = [str(a) for a in anchors]
        try:
            pos = np.array([np.asarray(anchors[a], dtype=float).reshape(3) for a in anchors])
        except (TypeError, ValueError):
            raise UsageError("Eskf: anchors must map each anchor id to three numbers [x, y, z]") from None
        if not np.all(np.isfinite(pos)):
            raise UsageError("Eskf: anchor positions must be finite")
        if anchor_frame_up not in ("+z", "-z"):
            raise UsageError(f"Eskf: anchor_frame_up must be '+z' or '-z', got {anchor_frame_up!r}")
        range_sigma = positive("range_sigma", range_sigma)
        tdoa_sigma = positive("tdoa_sigma", tdoa_sigma)
        self.max_gap_s = positive("max_gap_s", max_gap_s, allow_none=False)
        self.clock_restart_s = positive("clock_restart_s", clock_restart_s, allow_none=False)
        self._acc2 = positive("max_acc", max_acc, allow_none=False) ** 2
        self._gyro2 = positive("max_gyro", max_gyro, allow_none=False) ** 2
        positive("max_latency_s", max_latency_s, allow_none=False, zero=True)
        if imu_noise is not None:
            check_imu_noise(imu_noise)
        for k_, v_ in (known_anchor_bias or {}).items():
            finite_number(f"known_anchor_bias[{k_!r}]", v_)
        unknown = [x for pr in (tdoa_pairs or []) for x in pr if str(x) not in self.anchor_ids]
        if unknown:
            raise UsageError(f"Eskf: tdoa_pairs name anchors that are not in anchors: {sorted(set(map(str, unknown)))}")
        self.anchor_frame_up = anchor_frame_up
        self._flip = anchor_frame_up == "-z"
        if self._flip:
            pos = pos * _FLIP
        self._index = {a: i for i, a in enumerate(self.anchor_ids)}
        tags = dict(tags or {})
        self.tag = opts.tag if opts.tag is not None else (next(iter(tags)) if tags else None)
        # several tags and no options.tag: one filter, one lever arm per tag
        self.tag_names = [str(t_) for t_ in tags] if opts.tag is None and len(tags) > 1 else []
        self._tag_index = {n: i for i, n in enumerate(self.tag_names)}

        def prior(name):
            lv = opts.lever_arm.prior
            if lv is None:
                return [0.0, 0.0, 0.0]
            if lv == "dataset":
                nominal = tags.get(name) if name is not None else None
                return list(nominal) if nominal is not None else [0.0, 0.0, 0.0]
            return list(lv)

        lever = [prior(n) for n in self.tag_names] if self.tag_names else prior(self.tag)
        noise = imu_noise if imu_noise is not None else opts.resolve_imu_noise(None)
        rsig = range_sigma or opts.range_sigma or 0.1
        tsig = tdoa_sigma or opts.tdoa_sigma
        pairs = [(self._index[str(a_)], self._index[str(b_)]) for a_, b_ in (tdoa_pairs or [])]
        self._prob, self.priors = make_settings(opts, self.anchor_ids, pos, noise, rsig, tsig, lever,
                                                self.tag_names or None, pairs)
        self._n_models = 0
        self.imu_noise, self.range_sigma = noise, rsig
        self._known_bias = {str(k): float(v) for k, v in (known_anchor_bias or {}).items()}
        self.record = bool(record)
        self.max_latency_s = float(max_latency_s)
        # IMU buffers (indices are buffer indices; _imu_off counts samples trimmed from the front)
        self._t = _Buffer(None)
        self._u = _Buffer(6)
        self._um = _Buffer(6)  # mid-interval inputs, final for intervals < _um_done
        self._um_done = 0
        self._cs = _Buffer(3)  # cumulative gyro sums for the rotation gate (absolute values)
        self._cs2 = _Buffer(None)
        self._rot_mean = _Buffer(3)
        self._rot_ms = _Buffer(None)
        self._gaps: list[int] = []
        self._gap_arrays = None
        self._gaps_done = 0  # samples (buffer index) whose preceding interval was checked for a gap
        self._gap_sd: list[tuple[float, float]] = []
        self._imu_off = 0
        # measurements, in arrival order
        self._mt = _Buffer(None)
        self._ma = _Buffer(None, dtype=np.int64)
        self._mb = _Buffer(None, dtype=np.int64)
        self._mr = _Buffer(None)
        self._mtag = _Buffer(None, dtype=np.int64)
        self._rec = _Buffer(7, fill=np.nan)
        self._m_off = 0
        self._watermark = -np.inf  # newest measurement stamp seen [UWB clock]
        # filter
        self._mode = "init"  # init | run | stopped
        self._j_init = 0
        self._st: Optional[PassState] = None
        self._passes: list[PassResult] = []
        self._n_reinit = 0
        self._final = False
        self._events: list[dict[str, Any]] = []
        self._warnings: list[str] = []
        self._dropped = {"imu_not_increasing": 0, "imu_not_finite": 0, "unknown_anchor": 0,
                         "other_tag": 0, "not_finite": 0}
        self._rej = Rejections(self._events, self._dropped)
        # IMU samples push_imu accepted and not yet processed: (t, ax, ay, az, wx, wy, wz), see IMU_BATCH
        self._pend: list[tuple[float, ...]] = []
        # ranges / TDoAs push_range and push_tdoa accepted and not yet handed to the filter: (t, a, b, z) with
        # b = -1 for a range (the buffers' coding), see MEAS_BATCH
        self._pend_m: list[tuple[float, int, int, float]] = []
        # geometric bounds of a measurement: the supervisor's box (the anchors' bounding box grown by its
        # margin) holds every position it accepts, so no range is longer than its diagonal
        p_ = self._prob
        self._r_max = float(np.linalg.norm(p_.hull_hi - p_.hull_lo)) + GEOMETRY_SLACK_M
        tsd = math.sqrt(p_.tdoa_var) if np.isfinite(p_.tdoa_var) else 0.0
        self._pair_dist = np.linalg.norm(pos[:, None, :] - pos[None, :, :], axis=2) + GEOMETRY_SLACK_M + 5.0 * tsd
        self._imu_shift = 0.0  # added to IMU stamps since an IMU clock restart
        self._imu_floor = -np.inf  # IMU time of the end of the last IMU gap (re-initialise after it)
        self._last: Optional[tuple[np.ndarray, np.ndarray, float]] = None  # (x, P, t_imu) of the last pass
        self._invalid: Optional[str] = None  # why the estimate is not valid (a pass ended, not restarted)
        self._nis = NisMonitor()
        self._t_last_meas = -np.inf  # UWB stamp of the newest processed measurement
        self.initial: Optional[InitialState] = None
        self._initial_given: Optional[InitialState] = None
        self.td_held = False
        self._progress = None

    @classmethod
    def for_dataset(cls, dataset, options: Optional[EskfOptions] = None, **kwargs) -> "Eskf":
        """A filter set up with a dataset's properties (anchors, tags, IMU and range noise, TDoA noise,
        anchor frame, known anchor biases) as :func:`run_eskf` applies them; feed it the data yourself.
        Keyword arguments override (e.g. ``record=True``)."""
        opts = options or EskfOptions()
        meta = dataset.meta
        anchors = {str(a): row for a, row in zip(dataset.anchors["anchor"],
                                                 dataset.anchors[["x", "y", "z"]].to_numpy(float))}
        tags = {tm.name: tm.lever_arm for tm in meta.tags} if meta.tags else None
        frame = opts.anchor_frame_up or getattr(meta, "anchor_frame_up", None) or \
            (meta.extra or {}).get("anchor_frame_up") or "+z"
        args = dict(imu_noise=opts.resolve_imu_noise(meta.imu_noise), range_sigma=opts.range_sigma or meta.range_sigma,
                    tdoa_sigma=opts.tdoa_sigma or (meta.extra or {}).get("tdoa_sigma"), anchor_frame_up=frame,
                    known_anchor_bias=meta.known_anchor_bias)
        args.update(kwargs)
        return cls(opts, anchors, tags, **args)

    @classmethod
    def from_problem(cls, prob: Problem, priors: BlockPriors, options: EskfOptions, *, record: bool = True,
                     initial: Optional[InitialState] = None) -> "Eskf":
        """A filter with the settings of a batch :class:`Problem` (``eskf.build_problem``: anchors already
        in the filter's z-up frame, known biases already removed) and no data yet; feed it with
        :meth:`feed`.  ``initial`` bypasses the initialiser (consistency tests)."""
        f = cls.__new__(cls)
        cls.__init__(f, options, anchors={a: prob.anchors[i] for i, a in enumerate(prob.anchor_ids)},
                     tags={n: None for n in prob.tag_names} or None, record=record)
        settings = Problem(**{**prob.__dict__})
        settings.dt_nom = settings.dt_max = float("nan")
        settings.rot_mean = settings.rot_ms = settings.gap_idx = settings.gap_sd = None
        settings.lever_win, settings.lever_min_rate = 0, 0.0
        settings.t_limit = np.inf
        settings.models = {}
        f._prob = settings
        f.priors = priors
        f._initial_given = initial
        f._sync()
        return f

    def feed(self, imu_t: np.ndarray, imu_u: np.ndarray, meas_t: np.ndarray, meas_a: np.ndarray,
             meas_b: np.ndarray, meas_z: np.ndarray, meas_tag: Optional[np.ndarray] = None) -> None:
        """Push IMU samples ``(n,)``, ``(n, 6)`` and measurements by anchor index (``meas_b >= 0``: TDoA
        to anchor ``meas_b``, else a range) in one go (arrays as in a :class:`Problem`)."""
        self._flush()
        if len(meas_t):
            self._add(np.asarray(meas_t, float), np.asarray(meas_a, np.int64), np.asarray(meas_b, np.int64),
                      np.asarray(meas_z, float), None,
                      None if meas_tag is None else np.asarray(meas_tag, np.int64))
        if len(imu_t):
            imu_u = np.asarray(imu_u, float)
            self.push_imu_chunk(imu_t, imu_u[:, :3], imu_u[:, 3:])

    # ------------------------------------------------------------------ input
    def push_imu(self, t: float, acc: Sequence[float], gyro: Sequence[float]) -> None:
        """One IMU sample: stamp ``t`` [s, IMU clock], specific force ``acc`` [m/s^2] and body rate
        ``gyro`` [rad/s], both in the IMU frame.  Checked as the class docstring says (plain float
        comparisons: this runs at the IMU rate)."""
        try:
            t = float(t) + self._imu_shift
            ax, ay, az = acc
            wx, wy, wz = gyro
            ax, ay, az, wx, wy, wz = float(ax), float(ay), float(az), float(wx), float(wy), float(wz)
        except (TypeError, ValueError):
            raise StreamInputError("Eskf.push_imu: t must be a number, acc and gyro three numbers each",
                                   field="acc, gyro", reason="bad_shape") from None
        isf = math.isfinite
        if not (isf(t) and isf(ax) and isf(ay) and isf(az) and isf(wx) and isf(wy) and isf(wz)):
            self._flush()
            self._rej.add("imu", "imu_not_finite", t)
            return
        if ax * ax + ay * ay + az * az > self._acc2 or wx * wx + wy * wy + wz * wz > self._gyro2:
            self._flush()
            self._rej.add("imu", "imu_implausible", t)
            return
        pend = self._pend
        if pend or self._t.n:
            last = pend[-1][0] if pend else float(self._t.a[self._t.n - 1])
            if t <= last:
                self._flush()
                if t >= last - self.clock_restart_s:
                    self._rej.add("imu", "imu_not_increasing", t)
                    return
                t = self._imu_clock_restart(t, last)
            elif t - last > self.max_gap_s:
                self._flush()
                self._imu_gap(last, t)
        pend.append((t, ax, ay, az, wx, wy, wz))
        if len(pend) >= IMU_BATCH:
            self._flush()

    def _flush(self) -> None:
        """Process the IMU samples :meth:`push_imu` kept (one chunk: the same kernels on the same numbers in
        the same order as one sample at a time, ``tests/test_streaming_chunks.py``)."""
        pm, pend = self._pend_m, self._pend
        if pm:
            m = np.array(pm, dtype=float)
            pm.clear()
            # measurements first, then the IMU samples, then one filter step: what push_ranges followed
            # by push_imu_chunk does (the filter processes a measurement once the IMU covers it, in index
            # order, so the estimates do not depend on when it was handed over)
            self._add(np.ascontiguousarray(m[:, 0]), m[:, 1].astype(np.int64), m[:, 2].astype(np.int64),
                      np.ascontiguousarray(m[:, 3]), None, step=not pend)
        if pend:
            a = np.array(pend, dtype=float)
            pend.clear()
            self._append_imu(np.ascontiguousarray(a[:, 0]), np.ascontiguousarray(a[:, 1:]))

    def push_imu_chunk(self, t: np.ndarray, acc: np.ndarray, gyro: np.ndarray) -> None:
        """Several IMU samples at once (arrays ``(n,)``, ``(n, 3)``, ``(n, 3)``); faster than a loop.
        The samples are checked as :meth:`push_imu` checks one."""
        self._flush()
        t = as_floats("t", t)
        acc, gyro = as_floats("acc", acc, 3), as_floats("gyro", gyro, 3)
        same_length("push_imu_chunk", t=t, acc=acc, gyro=gyro)
        t = t + self._imu_shift
        u = np.hstack([acc, gyro])
        # the checks of push_imu, vectorised; the whole-chunk tests first (the usual case: all pass)
        if not (np.isfinite(t).all() and np.isfinite(u).all()):
            finite = np.isfinite(t) & np.all(np.isfinite(u), axis=1)
            self._rej.add("imu", "imu_not_finite", t[~finite][0], n=int((~finite).sum()))
            t, u = t[finite], u[finite]
        plausible = (np.einsum("ij,ij->i", u[:, :3], u[:, :3]) <= self._acc2) & \
            (np.einsum("ij,ij->i", u[:, 3:], u[:, 3:]) <= self._gyro2)
        if not plausible.all():
            self._rej.add("imu", "imu_implausible", t[~plausible][0], n=int((~plausible).sum()))
            t, u = t[plausible], u[plausible]
        if len(t) and self._t.n:
            # strictly increasing, no clock restart, no gap: what the loop below keeps whole
            last = float(self._t.a[self._t.n - 1])
            d = t[1:] - t[:-1]
            if t[0] > last and t[0] - last <= self.max_gap_s and (not len(d) or (d.min() > 0 and d.max() <= self.max_gap_s)):
                self._append_imu(t, u)
                return
        while len(t):
            last = float(self._t.a[self._t.n - 1]) if self._t.n else -np.inf
            # strictly increasing stamps (repeated stamps of the batch loader are dropped the same way): a
            # sample is kept when it is later than every stamp before it (the last kept one is their maximum)
            prev = np.maximum.accumulate(np.concatenate(([last], t[:-1]))) if len(t) > 1 else np.array([last])
            jump = ((t < prev - self.clock_restart_s) | (t - prev > self.max_gap_s)) & np.isfinite(prev)
            i = int(np.argmax(jump)) if jump.any() else len(t)
            keep = t[:i] > prev[:i]
            if not keep.all():
                self._rej.add("imu", "imu_not_increasing", t[:i][~keep][0], n=int((~keep).sum()))
            if keep.any():
                self._append_imu(t[:i][keep], u[:i][keep])
            if i == len(t):
                return
            last = float(self._t.a[self._t.n - 1])
            if t[i] < last:
                t = t.copy()
                t[i:] += self._imu_clock_restart(float(t[i]), last) - t[i]
            else:
                self._imu_gap(last, float(t[i]))
            self._append_imu(t[i:i + 1], u[i:i + 1])
            t, u = t[i + 1:], u[i + 1:]

    def _append_imu(self, t: np.ndarray, u: np.ndarray) -> None:
        self._t.extend(t)
        self._u.extend(u)
        self._imu_appended()
        self._step()

    def _td_hat(self) -> float:
        """The current time-offset estimate (the prior before the first initialisation)."""
        x = self._st.x if self._st is not None else (self._last[0] if self._last is not None else None)
        td = float(x[S.TD]) if x is not None else float(self.priors.t_d or 0.0)
        return td if math.isfinite(td) else 0.0

    def _imu_clock_restart(self, t: float, last: float) -> float:
        """An IMU stamp ``t`` far behind the newest ``last``: shift the clock so that the sample follows
        ``last`` after one nominal period; the shifted stamp."""
        dt = self._prob.dt_nom
        if not (math.isfinite(dt) and dt > 0):
            n = self._t.n
            dt = float(self._t.a[n - 1] - self._t.a[n - 2]) if n >= 2 else 0.005
        shift = last + dt - t
        self._imu_shift += shift
        self._event({"t": last - self._td_hat(), "kind": "imu_discontinuity", "t_imu": last, "jump_s": t - last,
                     "action": "rebase", "shift_s": self._imu_shift})
        return t + shift

    def _imu_gap(self, last: float, t: float) -> None:
        """An IMU interval ``[last, t]`` longer than ``max_gap_s``: end the pass, re-initialise after it."""
        if self._mode == "run" and self._st is not None and not self._final:
            self._j_init = max(self._j_init, self._st.j)
            self._close_pass()
            self._st = None
            self._mode = "init"
            self._need = None
        if self.initial is not None:
            self._invalid = "imu_gap"
        self._imu_floor = t
        self._event({"t": last - self._td_hat(), "kind": "imu_discontinuity", "t_imu": last, "jump_s": t - last,
                     "action": "reinitialise"})

    def _event(self, ev: dict[str, Any]) -> None:
        self._events.append(ev)

    def push_range(self, t: float, anchor: str, range: float, tag: Optional[str] = None) -> None:
        """One two-way range [m] to ``anchor``, stamped ``t`` [s, UWB clock]; checked as
        :meth:`push_ranges` checks (plain float comparisons).  A range that passes them is kept and handed
        to the filter with the next chunk (:data:`MEAS_BATCH`); a refused one is counted at once."""
        try:
            t, z = float(t), float(range)
        except (TypeError, ValueError):
            self._flush()
            raise StreamInputError("Eskf.push_range: t and range must be numbers", field="t, range",
                                   reason="not_numeric") from None
        key = anchor if type(anchor) is str else str(anchor)
        a = self._index.get(key, -1)
        if a >= 0 and math.isfinite(z) and not 0.0 < z <= self._r_max:
            self._flush()
            self._rej.add("range", "range_not_positive" if z <= 0 else "range_too_long", t)
            return
        z -= self._known_bias.get(key, 0.0)
        if tag is None and a >= 0 and math.isfinite(t) and math.isfinite(z):
            pm = self._pend_m
            pm.append((t, a, -1, z))
            if len(pm) >= MEAS_BATCH:
                self._flush()
            return
        # another tag, an unknown anchor or a non-finite value: counted (or routed) by _add, in order
        self._flush()
        self._add(np.array([t]), np.array([a], dtype=np.int64), np.full(1, -1, dtype=np.int64), np.array([z]),
                  None if tag is None else (tag,), stream="range")

    def push_ranges(self, t: np.ndarray, anchors: Sequence[str], ranges: np.ndarray,
                    tags: Optional[Sequence[Optional[str]]] = None) -> None:
        """Several ranges at once, in time order."""
        self._flush()
        t = as_floats("t", t)
        z = as_floats("ranges", ranges)
        ids = self._ids("anchors", anchors)
        same_length("push_ranges", t=t, anchors=ids, ranges=z, **({} if tags is None else {"tags": tags}))
        a = np.array([self._index.get(x, -1) for x in ids], dtype=np.int64)
        with np.errstate(invalid="ignore"):
            known = (a >= 0) & np.isfinite(z)  # (the rest is refused by _add, counted there)
            short = known & (z <= 0)
            long = known & (z > self._r_max)
        if short.any() or long.any():
            self._rej.add("range", "range_not_positive", t[short][0] if short.any() else np.nan, n=int(short.sum()))
            self._rej.add("range", "range_too_long", t[long][0] if long.any() else np.nan, n=int(long.sum()))
            keep = ~(short | long)
            t, z, a = t[keep], z[keep], a[keep]
            ids = [x for x, k in zip(ids, keep) if k]
            tags = None if tags is None else [x for x, k in zip(tags, keep) if k]
        z = z - np.array([self._known_bias.get(x, 0.0) for x in ids])
        self._add(t, a, np.full(len(t), -1, dtype=np.int64), z, tags, stream="range")

    def push_tdoa(self, t: float, anchor_a: str, anchor_b: str, tdoa: float, tag: Optional[str] = None) -> None:
        """One TDoA ``|p_U - p_b| - |p_U - p_a|`` [m] stamped ``t`` [s, UWB clock]; checked as
        :meth:`push_tdoas` checks.  Kept and handed over with the next chunk as :meth:`push_range`."""
        if tag is None:
            try:
                tf, z = float(t), float(tdoa)
            except (TypeError, ValueError):
                tf = z = math.nan  # push_tdoas says what is wrong
            ka = anchor_a if type(anchor_a) is str else str(anchor_a)
            kb = anchor_b if type(anchor_b) is str else str(anchor_b)
            a, b = self._index.get(ka, -1), self._index.get(kb, -1)
            if a >= 0 and b >= 0 and a != b and math.isfinite(tf) and math.isfinite(z) \
                    and abs(z) <= self._pair_dist[a, b]:
                kb_ = self._known_bias
                pm = self._pend_m
                pm.append((tf, a, b, z - (kb_.get(kb, 0.0) - kb_.get(ka, 0.0))))
                if len(pm) >= MEAS_BATCH:
                    self._flush()
                return
        self.push_tdoas((t,), (anchor_a,), (anchor_b,), (tdoa,), None if tag is None else (tag,))

    def push_tdoas(self, t: np.ndarray, anchors_a: Sequence[str], anchors_b: Sequence[str], tdoa: np.ndarray,
                   tags: Optional[Sequence[Optional[str]]] = None) -> None:
        """Several TDoA measurements at once, in time order."""
        self._flush()
        t = as_floats("t", t)
        z = as_floats("tdoa", tdoa)
        ia, ib = self._ids("anchors_a", anchors_a), self._ids("anchors_b", anchors_b)
        same_length("push_tdoas", t=t, anchors_a=ia, anchors_b=ib, tdoa=z,
                    **({} if tags is None else {"tags": tags}))
        a = np.array([self._index.get(x, -1) for x in ia], dtype=np.int64)
        b = np.array([self._index.get(x, -1) for x in ib], dtype=np.int64)
        same = (a >= 0) & (a == b)
        known = (a >= 0) & (b >= 0) & ~same & np.isfinite(z)
        large = known & (np.abs(np.where(known, z, 0.0)) > self._pair_dist[np.maximum(a, 0), np.maximum(b, 0)])
        if same.any() or large.any():
            self._rej.add("tdoa", "same_anchor", t[same][0] if same.any() else np.nan, n=int(same.sum()))
            self._rej.add("tdoa", "tdoa_too_large", t[large][0] if large.any() else np.nan, n=int(large.sum()))
            keep = ~(same | large)
            t, z, a, b = t[keep], z[keep], a[keep], b[keep]
            ia = [x for x, k in zip(ia, keep) if k]
            ib = [x for x, k in zip(ib, keep) if k]
            tags = None if tags is None else [x for x, k in zip(tags, keep) if k]
        a[b < 0] = -1
        z = z - np.array([self._known_bias.get(y, 0.0) - self._known_bias.get(x, 0.0) for x, y in zip(ia, ib)])
        self._add(t, a, np.maximum(b, 0), z, tags, stream="tdoa")

    @staticmethod
    def _ids(name: str, ids: Any) -> list[str]:
        if isinstance(ids, (str, bytes)) or not hasattr(ids, "__len__"):
            raise StreamInputError(f"Eskf: {name} must be a sequence of anchor ids, got {type(ids).__name__}",
                                   field=name, reason="bad_shape")
        return [str(x) for x in ids]

    def push_height(self, t: float, height: float, sigma: Optional[float] = None) -> None:
        """One altimeter reading: the IMU origin's z coordinate [m] in the anchors' frame, stamped ``t``
        [s, IMU clock]; ``sigma`` [m] defaults to ``options.height.sigma``.  With
        ``options.height.bias = "estimate"`` an altimeter bias is estimated along."""
        sig = self.options.height.sigma if sigma is None else push_sigma("sigma", sigma)
        z = as_floats("height", (height,)) * (-1.0 if self._flip else 1.0)
        self.push(t, HeightModel(sig, self._prob.state_layout()), z)

    def push_zero_velocity(self, t: float, sigma: float = 0.01) -> None:
        """The platform stands still at ``t`` [s, IMU clock] (e.g. a detected stance phase or a landed
        drone): a zero-velocity pseudo-measurement with sd ``sigma`` [m/s] per axis."""
        self.push(t, ZeroVelocityModel(push_sigma("sigma", sigma)), np.zeros(3))

    def push(self, t: float, model: MeasurementModel, z: Sequence[float]) -> None:
        """Any measurement through the model protocol (:mod:`uwbimu.models.measurements`): ``model``
        predicts ``z`` from the state at ``t`` (its own clock, ``model.clock``); processed in order
        with the ranges, with the same gate (chi-square at the options' probability) and robust loss.
        The model works in the filter's world frame (z up; ``anchor_frame_up: -z`` turns y and z).
        A stamp on the IMU clock gets the clock shift of an IMU clock restart."""
        self._flush()
        z = as_floats("z", z)
        dim = getattr(model, "dim", None)
        if not isinstance(dim, (int, np.integer)) or getattr(model, "clock", None) not in ("imu", "uwb"):
            raise StreamInputError(f"Eskf.push: {type(model).__name__} is not a measurement model (dim, clock)",
                                   field="model", reason="not_a_model")
        if len(z) != dim:
            raise StreamInputError(f"Eskf.push: {model.name} has dim {dim}, got {len(z)} values", field="z",
                                   reason="bad_shape")
        try:
            t = float(t)
        except (TypeError, ValueError):
            raise StreamInputError("Eskf.push: t must be a number", field="t", reason="not_numeric") from None
        if model.clock == "imu":
            t += self._imu_shift
        if not (math.isfinite(t) and np.all(np.isfinite(z))):
            self._rej.add("model", "not_finite", t)
            return
        i = self._n_models
        self._n_models += 1
        self._prob.models[i] = (model, z)
        self._mt.extend(np.array([float(t)]))
        self._ma.extend(np.array([-1], dtype=np.int64))
        self._mb.extend(np.array([-2 - i], dtype=np.int64))
        self._mtag.extend(np.zeros(1, dtype=np.int64))
        self._mr.extend(z[:1])
        rec = np.full((1, 7), np.nan)
        rec[:, REC_STATUS] = STATUS_NOT_PROCESSED
        rec[:, REC_ACC] = 0.0
        self._rec.extend(rec)
        if model.clock == "uwb":
            self._watermark = max(self._watermark, float(t))
        self._step()

    def finish(self, progress=None) -> None:
        """End of the data: process everything still waiting (the last IMU intervals included).

        ``progress``: optional callback receiving the filter's IMU sample index as it goes."""
        self._flush()
        self._final = True
        self._progress = progress
        n = self._t.n
        if n >= 2 and self._um_done < n - 1:
            self._um.reserve(n - 1)
            K.midpoints_into(self._t.view(), self._u.view(), self._um_done, n - 1, self._um.a)
            self._um_done = n - 1
        self._step()
        if self._mode == "run" and self._st is not None:
            self._close_pass()
            self._mode = "stopped"
        elif self._mode == "init" or (self._mode == "stopped" and self.initial is None):
            self._warn(f"not initialised: {self._init_failure or 'not enough data'}", "not_initialised",
                       reason=self._init_failure or "not enough data")
            self._mode = "stopped"
        for k, v in self._dropped.items():
            if v:
                self._warn(f"{v} inputs not used ({k.replace('_', ' ')})", "inputs_not_used", reason=k, count=v)

    # ------------------------------------------------------------------ output
    @property
    def initialised(self) -> bool:
        self._flush()
        return self._st is not None

    def _t_imu(self, k: int) -> float:
        return float(self._prob.imu_t[k]) if k < len(self._prob.imu_t) else float("nan")

    def _invalid_reason(self, x: np.ndarray, P: np.ndarray, sd: np.ndarray, t_imu: float) -> Optional[str]:
        """Why the estimate must not be used (None: valid); the cases are listed in the class docstring."""
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(P))):
            return "not_finite"
        if self._invalid is not None:
            return self._invalid
        if self._st is None:
            return "reinitialising"
        if self._nis.inconsistent:
            return "inconsistent"
        if float(np.linalg.norm(sd[S.EP])) > self.options.supervisor.max_position_sd:
            return "position_sd"
        t_new = float(self._t.a[self._t.n - 1]) if self._t.n else t_imu  # the newest IMU sample
        if max(t_imu, t_new) - (self._t_last_meas + float(x[S.TD])) > self.max_gap_s:
            return "no_measurements"
        return None

    def state(self) -> Optional[EskfState]:
        """The current estimate (``None`` before the first initialisation).  Between a divergence or an
        IMU gap and the re-initialisation it is the last estimate, with ``valid=False``."""
        self._flush()
        if self._st is not None:
            x, P = self._st.x, self._st.P
            t_imu = self._t_imu(self._st.k)
        elif self._last is not None:
            x, P, t_imu = self._last
        else:
            return None
        sd = np.sqrt(np.clip(np.diag(P), 0.0, None))
        reason = self._invalid_reason(x, P, sd, t_imu)
        p, v, q = x[S.P].copy(), x[S.V].copy(), x[S.Q].copy()
        Pc = P.copy()
        if self._flip:
            p, v = p * _FLIP, v * _FLIP
            q = quat_multiply(_Q_FLIP, q)
            d = np.ones(P.shape[0])
            d[S.EP], d[S.EV] = _FLIP, _FLIP
            Pc = P * d[:, None] * d[None, :]
        L = self._prob.state_layout()
        nb = L.n_anchor_bias
        return EskfState(
            t=t_imu - float(x[S.TD]), t_imu=t_imu, position=p, velocity=v, quaternion=q,
            accel_bias=x[S.BA].copy(), gyro_bias=x[S.BG].copy(), lever_arm=x[S.PIU].copy(),
            time_offset=float(x[S.TD]),
            anchor_bias={a: float(v) for a, v in zip(self.anchor_ids, x[L.nom("anchor_bias")])} if nb else {},
            position_sd=sd[S.EP].copy(), velocity_sd=sd[S.EV].copy(), attitude_sd=sd[S.ETH].copy(),
            accel_bias_sd=sd[S.EBA].copy(), gyro_bias_sd=sd[S.EBG].copy(), lever_arm_sd=sd[S.EPIU].copy(),
            time_offset_sd=float(sd[S.ETD]), covariance=Pc, layout=L,
            tags={n: (x[L.lever_nom(i)].copy(), sd[L.lever_err(i)].copy()) for i, n in enumerate(self.tag_names)},
            height_bias=float(x[L.nom("height_bias")][0]) if L.n_height_bias else None,
            height_bias_sd=float(sd[L.err("height_bias")][0]) if L.n_height_bias else None,
            valid=reason is None, invalid_reason=reason, imu_clock_shift=self._imu_shift,
            blocks=block_calibration(L, x, sd, self.options, self.anchor_ids, self._prob.pair_index),
        )

    def events(self) -> list[dict[str, Any]]:
        """Structured events so far (``{"t", "kind", ...}``: initialised, divergence, gate_reopened, ...)."""
        self._flush()
        out = list(self._events)
        if self._st is not None:
            out += self._st.events
        return out

    def warnings(self) -> list[str]:
        self._flush()
        return list(self._warnings)

    def passes(self) -> list[PassResult]:
        """The filter passes (one per (re-)initialisation) with their recorded outputs."""
        self._flush()
        return list(self._passes) + ([self._st.result(self._rec.view(), self._st.P.shape[0])]
                                     if self._st is not None and self._mode == "run" else [])

    def problem(self) -> Problem:
        """The filter's data and settings as a :class:`Problem` (the buffers, as far as kept)."""
        self._flush()
        return self._prob

    def records(self) -> np.ndarray:
        """Per-measurement records ``(m, 7)`` (see ``filterpass.REC_*``), in arrival order."""
        self._flush()
        return self._rec.view()

    # ------------------------------------------------------------------ internals
    _init_failure: Optional[str] = None
    _need: Optional[tuple[float, float, int]] = None  # data the pending initialisation needs (t_uwb, t_imu, j)
    _need_recheck: float = -np.inf

    def _warn(self, text: str, kind: str, **fields) -> None:
        self._warnings.append(text)
        t = float(self._mt.a[self._mt.n - 1]) if self._mt.n else 0.0
        self._events.append({"t": t, "kind": kind, **fields})

    def _add(self, t, a, b, z, tags, tag_idx=None, stream: str = "uwb", step: bool = True) -> None:
        ok = a >= 0
        rej = self._rej

        def drop(reason, bad):
            if bad.any():
                rej.add(stream, reason, t[bad][0], n=int(bad.sum()))

        drop("unknown_anchor", ~ok)
        fin = np.isfinite(t) & np.isfinite(z)
        drop("not_finite", ok & ~fin)
        ok &= fin
        if tag_idx is None:
            tag_idx = np.zeros(len(t), dtype=np.int64)
            if tags is not None and self.tag_names:
                tag_idx = np.array([self._tag_index.get(str(tg), -1) if tg is not None else 0 for tg in tags],
                                   dtype=np.int64)
                drop("other_tag", ok & (tag_idx < 0))
                ok &= tag_idx >= 0
            elif tags is not None and self.tag is not None:
                mine = np.array([tg is None or str(tg) == str(self.tag) for tg in tags], dtype=bool)
                drop("other_tag", ok & ~mine)
                ok &= mine
        if not ok.any():
            return
        t, a, b, z, tag_idx = t[ok], a[ok], b[ok], z[ok], tag_idx[ok]
        self._mtag.extend(tag_idx)
        self._mt.extend(t)
        self._ma.extend(a)
        self._mb.extend(b)
        self._mr.extend(z)
        rec = np.full((len(t), 7), np.nan)
        rec[:, REC_STATUS] = STATUS_NOT_PROCESSED
        rec[:, REC_ACC] = 0.0
        self._rec.extend(rec)
        self._watermark = max(self._watermark, float(t.max()))
        if step:
            self._step()

    def _imu_appended(self) -> None:
        """Mid-interval inputs that became final, gaps and rotation-gate statistics of new samples."""
        n = self._t.n
        t, u = self._t.view(), self._u.view()
        self._um.reserve(n - 1)
        hi = n - 2 if n >= 4 else 0  # intervals < n - 2 have their four centred samples
        if hi > self._um_done:
            K.midpoints_into(t, u, self._um_done, hi, self._um.a)
            self._um_done = hi
        if math.isnan(self._prob.dt_nom):
            if n + self._imu_off > NOMINAL_PERIOD_SAMPLES:
                self._set_timing()
        else:
            self._extend_timing()

    def _set_timing(self) -> None:
        set_imu_timing(self._prob, self.options, nominal_period(self._t.view()))
        self._extend_timing()

    def _extend_timing(self) -> None:
        """Gaps and rotation statistics of the samples not yet seen (as the batch computes them)."""
        n = self._t.n
        t, u = self._t.view(), self._u.view()
        dt_max = self._prob.dt_max
        g0 = max(self._gaps_done - 1, 0)
        self._gaps_done = n
        if n - g0 == 2:  # one new sample (the usual streaming call): a scalar test
            new_gaps = [g0] if t[g0 + 1] - t[g0] > dt_max else []
        else:
            new_gaps = (np.flatnonzero(np.diff(t[g0:]) > dt_max) + g0).tolist()
        for g in new_gaps:
            lo = int(np.searchsorted(t, t[g] - 1.0))
            seg = u[lo:g + 2]
            sd = (float(np.max(np.std(seg[:, 0:3], axis=0))), float(np.max(np.std(seg[:, 3:6], axis=0)))) \
                if len(seg) > 2 else (0.0, 0.0)
            if not self._gaps or g > self._gaps[-1]:
                self._gaps.append(int(g))
                self._gap_sd.append(sd)
                self._gap_arrays = None
        if self._prob.lever_min_rate > 0:
            if self._cs.n == 0:
                self._cs.extend(np.zeros((1, 3)))
                self._cs2.extend(np.zeros(1))
            k0 = self._cs.n - 1  # samples already summed
            if n > k0:
                for b, m in ((self._cs, n + 1), (self._cs2, n + 1), (self._rot_mean, n), (self._rot_ms, n)):
                    b.reserve(m)
                K.rotation_stats_into(u, k0, n, max(int(self._prob.lever_win), 1), self._imu_off, self._cs.a,
                                      self._cs2.a, self._rot_mean.a, self._rot_ms.a)

    def _sync(self) -> None:
        """Point the :class:`Problem` at the buffers."""
        p = self._prob
        n = self._t.n
        p.imu_t = self._t.view()
        p.imu_u = self._u.view()
        p.imu_um = self._um.view(max(n - 1, 0))
        if self._final:
            p.t_limit = np.inf
        else:
            p.t_limit = float(p.imu_t[n - 2]) if n >= 4 else -np.inf
        p.uwb_t = self._mt.view()
        p.uwb_a = self._ma.view()
        p.uwb_b = self._mb.view()
        p.uwb_r = self._mr.view()
        if p.tag_lever_err is not None and len(p.tag_lever_err) > 1:
            p.uwb_tag = self._mtag.view()
        if not math.isnan(p.dt_nom):
            if self._gap_arrays is None:
                self._gap_arrays = (np.array(self._gaps, dtype=np.int64),
                                    np.array(self._gap_sd, dtype=float).reshape(-1, 2))
            p.gap_idx, p.gap_sd = self._gap_arrays
            if p.lever_min_rate > 0:
                p.rot_mean = self._rot_mean.view()
                p.rot_ms = self._rot_ms.view()

    def _step(self) -> None:
        self._sync()  # (callers that changed the buffers rely on this)
        for _ in range(2 * self.options.supervisor.max_reinit + 4):
            if self._mode == "init":
                if not self._try_init():
                    return
            if self._mode != "run":
                return
            self._advance()
            if self._st.diverged is None:
                return
            self._on_divergence()

    #: CPU time [s] spent in the initialiser (``time.process_time``): run_eskf reports the filter passes'
    #: CPU time without it
    init_cpu_seconds: float = 0.0

    def _try_init(self) -> bool:
        c0 = time.process_time()
        try:
            return self._try_init_timed()
        finally:
            self.init_cpu_seconds += time.process_time() - c0

    def _try_init_timed(self) -> bool:
        p = self._prob
        m = self._mt.n
        if math.isnan(p.dt_nom):
            if not (self._final and self._t.n >= 10):
                return False
            self._set_timing()
            self._sync()
        if self._imu_floor > -np.inf:
            self._skip_before_floor()
        if self._j_init >= m or self._t.n < 10:
            return False
        if not self._final:
            # what the initialiser will read is fixed once the start of motion is decided: ask once, then
            # wait for the data; while undecided, ask again every half second of new IMU data
            need = self._need
            if need is None or need[2] != self._j_init:
                if p.t_limit < self._need_recheck:
                    return False
                got = data_needed(p, self.options, self.priors, self._j_init)
                if got is None:
                    self._need_recheck = p.t_limit + 0.5
                    return False
                self._need = need = (got[0], got[1], self._j_init)
            if self._watermark <= need[0] or p.t_limit < need[1]:
                return False
        if self._initial_given is not None:
            st, self._initial_given = self._initial_given, None
            self._start(st)
            return True
        try:
            st = initialise(p, self.options, self.priors, j0=self._j_init)
        except InitialisationError as exc:
            # the data the initialiser reads are all here (data_needed): more data would not help
            self._init_failure = str(exc)
            if self.initial is not None:
                self._warnings.append(f"re-initialisation failed: {exc}")
            self._mode = "stopped"
            if self.initial is not None:
                self._invalid = "stopped"
            return False
        self._start(st)
        return True

    def _skip_before_floor(self) -> None:
        """After an IMU gap: measurements whose IMU time is before its end (plus the initialiser's reach
        back in time offset) cannot start the new pass; they are skipped, counted."""
        lim = self._imu_floor + max(self.options.init.td_max_abs_s, 1.0) - self._td_hat()
        ts, j0, m = self._mt.a, self._j_init, self._mt.n
        j = j0
        while j < m and not ts[j] >= lim:
            j += 1
        if j > j0:
            self._rej.add("uwb", "before_imu_discontinuity", float(ts[j0]), n=j - j0)
            self._j_init = j
            self._need = None

    def _start(self, st: InitialState) -> None:
        first = self.initial is None
        if first:
            self.initial = st
        kind = "initialised" if first else "reinitialised"
        self._events.append({"t": float(self._prob.uwb_t[st.j]), "kind": kind, **_plain(st.info)})
        td_init = st.info.get("time_offset_init") or {}
        if first and td_init.get("status") == "not identified" and self.options.time_offset.mode == "estimate":
            # hold t_d at its prior (consider mode) for the whole run, as the initialiser did
            mask = hold_time_offset(self._prob).gain_mask
            self._prob.gain_mask = mask
            self.td_held = True
            pr = self.priors
            self._warnings.append(
                f"time offset not identified by the initial search ({td_init.get('reason')}): held at its prior "
                f"{pr.t_d:g} s (sd {pr.t_d_sd:g} s, consider mode); set time_offset.prior or record more "
                f"excited motion")
            self._events.append({"t": float(self._prob.uwb_t[st.j]), "kind": "time_offset_held",
                                 "reason": td_init.get("reason"), "prior": float(pr.t_d),
                                 "prior_sd": float(pr.t_d_sd)})
        self._st = PassState.start(self._prob, st.x, st.P, st.k, st.j)
        self._mode = "run"
        self._invalid = None
        self._nis.reset(st.j)
        self._t_last_meas = float(self._prob.uwb_t[st.j])

    def _advance(self) -> None:
        p = self._prob
        st = self._st
        # outputs may move on to the IMU time before which no measurement can still arrive
        t_safe = self._watermark + float(st.x[S.TD])
        if p.imu_t.shape[0] >= 4:
            t_safe = max(t_safe, float(p.imu_t[-1]) - self.max_latency_s)
        advance(p, st, self._rec.view(), final=self._final, record=self.record, t_safe=t_safe,
                progress=self._progress)
        if st.j > self._nis.j:
            self._events += self._nis.update(self._rec.a, self._mb.a, self._mt.a, st.j)
            self._t_last_meas = float(self._mt.a[st.j - 1])
        if not self.record and not self._final:
            self._trim()

    def _close_pass(self) -> None:
        st = self._st
        self._last = (st.x.copy(), st.P.copy(), self._t_imu(st.k))
        res = self._st.result(self._rec.view(), self._st.P.shape[0], copy=False)  # the pass is over
        if not self._prob.store_cov:
            res.covs = None
        self._passes.append(res)
        self._events += self._st.events
        self._st.events = []

    def _on_divergence(self) -> None:
        st = self._st
        p = self._prob
        opts = self.options
        x = st.x
        t_div = float(p.imu_t[st.k] - x[S.TD]) if np.isfinite(x[S.TD]) else float(p.imu_t[st.k])
        self._close_pass()
        self._events.append({"t": t_div, "kind": "divergence", "reason": st.diverged})
        self._invalid = "divergence"
        j = st.j
        if self._final and j >= len(p.uwb_t) - 8:
            self._warnings.append(f"divergence at t={t_div:.2f} s ({st.diverged}) near the end of the log; stopped there")
            self._mode = "stopped"
            return
        if self._n_reinit >= opts.supervisor.max_reinit:
            if not (np.all(np.isfinite(x)) and np.all(np.isfinite(st.P))):
                self._warnings.append(f"divergence at t={t_div:.2f} s ({st.diverged}); re-initialisation limit "
                                      f"({opts.supervisor.max_reinit}) reached and the state is not finite: stopped there")
                self._mode = "stopped"
                return
            self._warnings.append(f"divergence at t={t_div:.2f} s ({st.diverged}); re-initialisation limit "
                                  f"({opts.supervisor.max_reinit}) reached, continuing without supervisor")
            p.supervise = False
            self._st = PassState.start(p, x.copy(), st.P.copy(), st.k, j)
            self._nis.reset(j)
            return
        self._n_reinit += 1
        self._warnings.append(f"divergence at t={t_div:.2f} s ({st.diverged}); re-initialised from the ranges "
                              f"at t={p.uwb_t[min(j, len(p.uwb_t) - 1)]:.2f} s")
        self._st = None
        self._j_init = j
        self._mode = "init"

    def _trim(self) -> None:
        """Drop what no later step can read (streaming without ``record``)."""
        st = self._st
        p = self._prob
        # measurements already processed
        jd = st.j
        # IMU: keep what a late measurement (max_lookback), the rotation window and a re-initialisation
        # (time-offset reach) may read behind the filter's sample
        keep_s = p.max_lookback + max(self.options.init.td_max_abs_s, 1.0) + 2.0
        kd = int(np.searchsorted(p.imu_t, p.imu_t[st.k] - keep_s)) - max(int(p.lever_win), 1) - 4
        if kd < 4096 and jd < 4096:
            return
        kd = max(0, min(kd, st.k - 4, self._um_done - 4))
        if kd >= 4096:
            for b in (self._t, self._u, self._um, self._cs, self._cs2, self._rot_mean, self._rot_ms):
                b.drop_front(min(kd, b.n))
            self._um_done -= kd
            self._gaps_done -= kd
            self._imu_off += kd
            st.k -= kd
            g = np.array(self._gaps, dtype=np.int64) - kd
            keep = g >= 0
            self._gaps = g[keep].tolist()
            self._gap_sd = [s for s, k in zip(self._gap_sd, keep) if k]
            self._gap_arrays = None
        if jd >= 4096:
            for bi in self._mb.a[:jd]:
                if bi <= -2:
                    self._prob.models.pop(int(-bi - 2), None)
            for b in (self._mt, self._ma, self._mb, self._mr, self._mtag, self._rec):
                b.drop_front(jd)
            self._m_off += jd
            self._nis.shift(jd)
            st.j -= jd
            st.j0 = max(st.j0 - jd, 0)
        self._sync()


def _plain(d: dict[str, Any]) -> dict[str, Any]:
    out = {}
    for k, v in d.items():
        if isinstance(v, np.ndarray):
            v = v.tolist()
        elif isinstance(v, (np.floating, np.integer)):
            v = v.item()
        elif isinstance(v, dict):
            v = _plain(v)
        out[k] = v
    return out
