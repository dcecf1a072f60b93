"""Full-batch MAP calibration with GTSAM: the factor graph, its solve and its marginals.

Variables, named by :mod:`uwbimu.calibration.keys` (GTSAM ``Symbol`` keys): ``x(k)`` pose, ``v(k)``
velocity, ``b(k)`` IMU bias of keyframe ``k`` (IMU clock); ``l(i)`` lever arm p_IU of tag ``i`` (IMU frame,
m; ``l(0)`` with one tag); ``t(0)`` time offset t_d (s); ``a(j)`` constant range bias of anchor ``j`` (m).  Factors:
``CombinedImuFactor`` between consecutive keyframes (preintegration with bias
random walk), one robust (Huber) :mod:`uwbimu.calibration.range_factor` per
range, priors on the first keyframe, the lever arm, t_d and the anchor biases.
With ``range_model.direction``, ``h(i)`` holds a coefficient vector of the direction-dependent
range bias (one shared, or one per anchor, for every tag) with a zero-mean prior; with
``range_model.anchor_direction``, ``g(j)`` the anchor-side coefficients of anchor ``j``.
The fixed anchors define the world frame (the gauge).  Self-survey
(:mod:`uwbimu.calibration.anchors`): an estimated anchor's position is a
``Point3`` ``P(j)`` with an optional weak prior, the range factors of its ranges
depend on it, ``anchor_ranges.csv`` adds a factor ``|p_a - p_b| - r`` per measured
pair, and the gauge convention (fewer than two fixed anchors) holds one anchor's y.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from uwbimu.calibration import keys
from uwbimu.calibration.anchors import GAUGE_SIGMA, AnchorSetup
from uwbimu.calibration.options import HUBER_START, CalibrationOptions
from uwbimu.calibration.range_factor import (RangeGroup, direction_features, imu_cumulative, imu_deltas,
                                              make_gtsam_factor, make_gtsam_group_factor, so3_exp)
from uwbimu.calibration.tdoa_factor import TdoaGroup, make_gtsam_tdoa_factor
from uwbimu.models.reference import GRAVITY

#: IMU noise used when neither the options nor dataset.yaml document it (consumer MEMS).
INTEGRATION_COV = 1e-8
DEFAULT_IMU_NOISE = {"accel_noise_density": 2e-3, "gyro_noise_density": 2e-4,
                     "accel_bias_rw": 3e-4, "gyro_bias_rw": 2e-5}


def _keys():
    """Deprecated: the six key functions ``(X, V, B, L, T, A)``; name variables with :mod:`uwbimu.calibration.keys`."""
    return keys.pose, keys.velocity, keys.imu_bias, keys.lever_arm, lambda i=0: keys.symbol(keys.TIME_OFFSET, i), \
        keys.anchor_bias


#: Aliases of :mod:`uwbimu.calibration.keys` (the scheme lives there).
drift_key = keys.bias_drift
dir_key = keys.direction_bias
adir_key = keys.anchor_direction_bias
lever_key = keys.lever_arm


def drift_factors(pb) -> list:
    """Gauss-Markov chain of every anchor's slowly varying bias (linear, C++ ``JacobianFactor``s; cached)."""
    import gtsam

    if pb._drift_factors is not None:
        return pb._drift_factors
    dr = pb.options.range_bias_drift
    phi = float(np.exp(-dr.knot_spacing / dr.correlation_time))
    q = dr.sd * np.sqrt(1.0 - phi**2)
    zero = gtsam.Values()
    for j in range(len(pb.anchor_ids)):
        for n in range(pb.n_knots):
            zero.insert(keys.bias_drift(j, n), np.zeros(1))
    out = []
    one = np.ones((1, 1))
    for j in range(len(pb.anchor_ids)):
        jf = gtsam.JacobianFactor(keys.bias_drift(j, 0), one, np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, dr.sd))
        out.append(gtsam.LinearContainerFactor(jf, zero))
        for n in range(pb.n_knots - 1):
            jf = gtsam.JacobianFactor(keys.bias_drift(j, n), -phi * one, keys.bias_drift(j, n + 1), one, np.zeros(1),
                                      gtsam.noiseModel.Isotropic.Sigma(1, q))
            out.append(gtsam.LinearContainerFactor(jf, zero))
    pb._drift_factors = out
    return out


def n_dir_per_tag(pb) -> int:
    """Direction-bias coefficient vectors per tag (0 without the model)."""
    d = pb.options.range_model.direction
    if d is None:
        return 0
    return len(pb.anchor_ids) if d.per_anchor else 1


def n_dir_vectors(pb) -> int:
    """Number of direction-bias coefficient vectors of the problem (0 without the model)."""
    return n_dir_per_tag(pb) * pb.n_tags


def _P():
    """Deprecated: the key function of an estimated anchor position (:func:`uwbimu.calibration.keys.anchor_position`)."""
    return keys.anchor_position


@dataclass
class Problem:
    """Everything the graph needs that does not depend on t_d."""

    t_imu: np.ndarray
    u_imu: np.ndarray
    key_idx: np.ndarray  # IMU sample index of every keyframe
    t_range: np.ndarray  # UWB clock
    rho: np.ndarray
    anchor_j: np.ndarray  # anchor index of every range
    anchor_ids: list[str]
    anchor_pos: np.ndarray  # (J, 3)
    init_states: np.ndarray  # (K, 16) p, v, q, b_a, b_g at keyframes (ESKF)
    lever0: np.ndarray
    td0: float
    options: CalibrationOptions
    range_sigma: float
    imu_noise: dict = field(default_factory=dict)
    imu_noise_source: dict = field(default_factory=dict)  # per value: options / eskf / dataset / default
    anchors: Optional[AnchorSetup] = None
    # TDoA rows (``tdoa.csv``) merged with the ranges in time order: anchor_b[m] >= 0 makes row m the TDoA
    # rho[m] = |p_U - p_b| - |p_U - p_a| with a = anchor_j[m], b = anchor_b[m]; None: ranges only
    anchor_b: Optional[np.ndarray] = None
    tdoa_sigma: float = 0.0
    # slowly varying bias (options.range_bias_drift): knot index of every row, number of knots per anchor
    drift_knot: Optional[np.ndarray] = None
    n_knots: int = 0
    _drift_factors: Optional[list] = None
    _imu_cum: Optional[dict] = None  # imu_cumulative at the first keyframe's ESKF bias (cached)
    # several tags: tag index of every row, tag names (dataset.yaml order first), ESKF lever arms and priors
    # (n_tags, 3); one tag: tag_i None, levers0 = [lever0], lever_prior = [options.lever_arm_prior]
    tag_i: Optional[np.ndarray] = None
    tag_names: list = field(default_factory=lambda: ["tag0"])
    levers0: Optional[np.ndarray] = None
    lever_prior: Optional[np.ndarray] = None
    tag_column: bool = False  # uwb.csv has a tag column (residuals.csv gets one)
    anchor_rot: Optional[np.ndarray] = None  # (J, 3, 3) antenna frame -> world (anchor_direction)

    @property
    def n_tags(self) -> int:
        return len(self.tag_names)

    def tag_of(self, m: int) -> int:
        return 0 if self.tag_i is None else int(self.tag_i[m])

    def is_tdoa(self, m: int) -> bool:
        return self.anchor_b is not None and int(self.anchor_b[m]) >= 0

    def estimated(self, j: int) -> bool:
        return self.anchors is not None and bool(self.anchors.estimated[j])

    @property
    def t_key(self) -> np.ndarray:
        return self.t_imu[self.key_idx]


def tag_names(dataset, eskf=None) -> tuple[list[str], bool]:
    """The tags a calibration uses and whether the log names them (a ``tag`` column in uwb.csv or tdoa.csv).

    The tags the initialising ESKF used (its ``calibration["tags"]``: every tag of the log in dataset.yaml's
    order, or the one its ``tag`` option picked), else every tag of the log in dataset.yaml's order
    first; ``["tag0"]`` (or the ESKF's single name) when the log has no tag column.
    """
    import pandas as pd

    etags = list(((getattr(eskf, "calibration", None) or {}).get("tags") or {}))
    present: list[str] = []
    for tab in (dataset.uwb, getattr(dataset, "tdoa", None)):
        if tab is not None and len(tab) and "tag" in tab.columns:
            present += [t for t in pd.unique(tab["tag"].astype(str)) if t not in present]
    if not present:
        return (etags[:1] or ["tag0"]), False
    used = [t for t in etags if t in present]
    if not used:
        order = [tm.name for tm in dataset.meta.tags if tm.name in present]
        used = order + [t for t in present if t not in order]
    return used, True


def _tag_levers(dataset, eskf, options: CalibrationOptions, names: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """Initial lever arms (the ESKF's, per tag) and prior means (n_tags, 3) [m, IMU frame].

    One tag: the ESKF's lever arm and, as prior mean, ``options.lever_arm_prior`` when configured, else the
    tag's nominal lever arm in dataset.yaml when documented (the ESKF's default ``lever_arm.prior:
    dataset``), else zero.  Several: each tag's ESKF lever arm (``calibration["tags"]``) and, as prior mean,
    its nominal lever arm in dataset.yaml when documented, else ``options.lever_arm_prior``.
    """
    cal = eskf.calibration
    prior = np.asarray(options.lever_arm_prior, float)
    meta = {tm.name: tm.lever_arm for tm in dataset.meta.tags}
    if len(names) == 1:
        nominal = meta.get(names[0]) if names[0] in meta else next(iter(meta.values()), None)
        if nominal is not None and "lever_arm_prior" not in options.model_fields_set:
            prior = np.asarray(nominal, float)
        return np.asarray(cal["lever_arm"], float)[None], prior[None]
    etag = cal.get("tags") or {}
    pri = np.array([meta[n] if meta.get(n) is not None else prior for n in names], float)
    init = np.array([etag[n]["lever_arm"] if n in etag else pri[i] for i, n in enumerate(names)], float)
    return init, pri


def _anchor_rotations(dataset, ids: list[str], needed, anchors: Optional[AnchorSetup]) -> np.ndarray:
    """(J, 3, 3) antenna orientations (antenna frame -> graph world) from anchors.csv qw..qz; refuses an anchor in
    ``needed`` (ids with ranges) without one (InputError naming ``range_model.anchor_direction``)."""
    from uwbimu.errors import InputError
    from uwbimu.models.quaternion import quat_to_rotmat

    quat = ["qw", "qx", "qy", "qz"]
    tab = dataset.anchors
    if not set(quat) <= set(tab.columns):
        raise InputError("calibrate: range_model.anchor_direction needs the anchor antenna orientations "
                         "(anchors.csv columns qw, qx, qy, qz); this anchors.csv has none",
                         hint="add qw..qz (antenna frame -> world, docs/dataset_format.md) or drop "
                              "range_model.anchor_direction")
    q = {str(a): row for a, row in zip(tab["anchor"].astype(str), tab[quat].to_numpy(float))}
    missing = sorted(a for a in needed if not np.all(np.isfinite(q.get(a, np.full(4, np.nan)))))
    if missing:
        raise InputError(f"calibrate: range_model.anchor_direction needs an antenna orientation (anchors.csv qw..qz) "
                         f"for every anchor with ranges; missing for anchor(s) {missing}",
                         hint="give qw..qz for those anchors or drop range_model.anchor_direction")
    G = anchors.transform[0] if anchors is not None else np.eye(3)
    out = np.empty((len(ids), 3, 3))
    for j, a in enumerate(ids):
        qa = q.get(a)
        if qa is None or not np.all(np.isfinite(qa)):
            out[j] = np.eye(3)  # no ranges: never used
        else:
            out[j] = G @ quat_to_rotmat(qa / np.linalg.norm(qa))
    return out


def imu_noise_sources(dataset, eskf, options: CalibrationOptions) -> tuple[dict, dict]:
    """The IMU noise model of the graph's preintegration factors and where each value came from.

    Per value (densities [m/s^2/sqrt(Hz)], [rad/s/sqrt(Hz)] and bias random walks): the option when given
    (``source`` ``options``), else the initialising ESKF's when it measured them on this log
    (``calibration["imu_noise"]["source"] == "log"``, :mod:`uwbimu.estimation.noise_from_data`: the larger of
    the preset and the in-flight spectrum; ``eskf``), else dataset.yaml's (``dataset``), else
    :data:`DEFAULT_IMU_NOISE` (``default``).  Why the ESKF's: a multirotor's vibration is about 100 times the
    datasheet density (the Crazyflie logs: accel 107x / 61x); preintegration factors that trust the IMU that much
    leave the near-null direction "every position + c, lever arm - c" (little rotation) to absorb the
    disagreement (the Crazyflie lever arm went to metres and the trajectory with it), which the IMU noise scale
    (:mod:`uwbimu.calibration.noise_scale`), estimated only after that solve, cannot undo.

    Returns
    -------
    (noise, source): ``{name: value}`` for the four names of :data:`DEFAULT_IMU_NOISE` and ``{name: source}``.
    """
    meta_noise = dataset.meta.imu_noise
    cal = (getattr(eskf, "calibration", None) or {}).get("imu_noise") or {}
    measured = cal.get("source") == "log"
    noise, source = {}, {}
    for name, default in DEFAULT_IMU_NOISE.items():
        v, src = getattr(options, name), "options"
        if v is None and measured and cal.get(name) is not None:
            v, src = cal[name], "eskf"
        if v is None and meta_noise is not None:
            v, src = getattr(meta_noise, name, None), "dataset"
        if v is None:
            v, src = default, "default"
        noise[name], source[name] = float(v), src
    return noise, source


def _eskf_measured_sigma(eskf, kind: str) -> Optional[float]:
    """The initialising ESKF's ``kind`` (``range`` / ``tdoa``) noise sd [m] when it measured it on this log
    (covariance matching, ``calibration["measurement_noise"][kind]["source"] == "log"``), else None."""
    m = ((getattr(eskf, "calibration", None) or {}).get("measurement_noise") or {}).get(kind) or {}
    return float(m["sigma"]) if m.get("source") == "log" and m.get("sigma") else None


def build_problem(dataset, eskf, options: CalibrationOptions, anchors: Optional[AnchorSetup] = None) -> Problem:
    """Keyframes, ranges, noise and the ESKF initial guess of a log with one tag or several.

    ``anchors`` (self-survey): anchor ids, fixed positions and initial guesses in the
    gauge frame; default: every anchor fixed at its ``anchors.csv`` position.  Several tags
    (:func:`tag_names`): every row keeps its tag, each tag has its own lever arm; the estimated anchors
    (self-survey) are shared by the tags.
    """
    from uwbimu.errors import InputError, UsageError

    if options.huber_k == "adaptive":  # the first solves' threshold; calibrate() then chooses the final one
        options = options.model_copy(update={"huber_k": HUBER_START})
    imu = dataset.imu
    t_imu = imu["t"].to_numpy(float)
    u_imu = imu[["ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    rate = (len(t_imu) - 1) / (t_imu[-1] - t_imu[0])
    step = max(1, int(round(rate / options.keyframe_hz)))
    key_idx = np.arange(0, len(t_imu), step)
    if key_idx[-1] != len(t_imu) - 1:
        key_idx = np.append(key_idx, len(t_imu) - 1)
    if anchors is None:
        pos = dataset.anchor_positions()
        ids = sorted(pos)
    else:
        ids = list(anchors.ids)
        pos = {a: anchors.pos[j] for j, a in enumerate(ids)}
    uwb = dataset.uwb
    known = uwb["anchor"].astype(str).isin(ids).to_numpy()
    uwb = uwb[known]
    names, tag_column = tag_names(dataset, eskf)
    tmap = {n: i for i, n in enumerate(names)}
    if tag_column and "tag" in uwb.columns:
        uwb = uwb[uwb["tag"].astype(str).isin(names).to_numpy()]
        ti = uwb["tag"].astype(str).map(tmap).to_numpy(np.int64)
    else:
        ti = np.zeros(len(uwb), np.int64)
    jmap = {a: j for j, a in enumerate(ids)}
    t_e = eskf.t_imu if eskf.t_imu is not None else eskf.t + eskf.calibration["time_offset"]
    tk = t_imu[key_idx]
    st = eskf.states
    init = np.empty((len(key_idx), 16))
    for c in range(6):
        init[:, c] = np.interp(tk, t_e, st[:, c])
    near = np.clip(np.searchsorted(t_e, tk), 0, len(t_e) - 1)
    init[:, 6:10] = st[near, 6:10]
    init[:, 10:16] = st[near, 10:16]
    noise, noise_src = imu_noise_sources(dataset, eskf, options)
    sigma = options.range_sigma or dataset.meta.range_sigma or 0.1
    t_r = uwb["t"].to_numpy(float)
    rho = uwb["range"].to_numpy(float)
    aj = np.array([jmap[a] for a in uwb["anchor"].astype(str)], dtype=np.int64)
    bj = None
    tdoa = getattr(dataset, "tdoa", None)
    tsig = 0.0
    if tdoa is not None and len(tdoa):
        if anchors is not None and any(anchors.estimated):
            raise UsageError("calibrate: anchor self-survey with TDoA is not supported yet",
                             hint="survey the anchors with ranges, or fix them (no --estimate-anchors)")
        ok = tdoa["anchor_a"].astype(str).isin(ids).to_numpy() & tdoa["anchor_b"].astype(str).isin(ids).to_numpy()
        if len(names) > 1 and "tag" not in tdoa.columns:
            raise InputError(f"calibrate: the log has several tags ({names}) but tdoa.csv has no tag column",
                             hint="add the tag column to tdoa.csv (docs/dataset_format.md)")
        if tag_column and "tag" in tdoa.columns:
            ok &= tdoa["tag"].astype(str).isin(names).to_numpy()
        td = tdoa[ok]
        tti = (td["tag"].astype(str).map(tmap).to_numpy(np.int64) if tag_column and "tag" in td.columns
               else np.zeros(len(td), np.int64))
        ti = np.concatenate([ti, tti])
        t_r = np.concatenate([t_r, td["t"].to_numpy(float)])
        rho = np.concatenate([rho, td["tdoa"].to_numpy(float)])
        aj = np.concatenate([aj, np.array([jmap[a] for a in td["anchor_a"].astype(str)], dtype=np.int64)])
        bj = np.concatenate([np.full(len(uwb), -1, dtype=np.int64),
                             np.array([jmap[b] for b in td["anchor_b"].astype(str)], dtype=np.int64)])
        order = np.argsort(t_r, kind="stable")
        t_r, rho, aj, bj, ti = t_r[order], rho[order], aj[order], bj[order], ti[order]
        base = options.range_sigma or dataset.meta.range_sigma or 0.1
        tsig = float(options.tdoa_sigma or _eskf_measured_sigma(eskf, "tdoa")
                     or (dataset.meta.extra or {}).get("tdoa_sigma") or np.sqrt(2.0) * base)
    knot, n_knots = None, 0
    dr = options.range_bias_drift
    if dr is not None:
        if bj is not None or not options.group_range_factors:
            raise UsageError("calibrate: range_bias_drift works with ranges and grouped range factors only "
                             "(not with TDoA or group_range_factors: false)")
        knot = np.rint((t_r - t_r.min()) / dr.knot_spacing).astype(np.int64)
        n_knots = int(knot.max()) + 1
    for fld in ("direction", "anchor_direction"):
        if getattr(options.range_model, fld) is None:
            continue
        if bj is not None or not options.group_range_factors:
            raise UsageError(f"calibrate: range_model.{fld} works with ranges and grouped range factors only "
                             "(not with TDoA or group_range_factors: false)")
        if fld == "anchor_direction" and anchors is not None and any(anchors.estimated):
            # its first azimuth harmonic and elevation at the anchor are, to first order, a shift of the anchor
            # along its lines of sight: with the position estimated only the priors would separate them
            raise UsageError("calibrate: range_model.anchor_direction is not supported with --estimate-anchors "
                             "(an anchor-side direction bias and the anchor's position are confounded)",
                             hint="survey with range_model.direction (tag side) or fix the anchors")
    rot = None
    if options.range_model.anchor_direction is not None:
        rot = _anchor_rotations(dataset, ids, sorted({ids[j] for j in np.unique(aj)}), anchors)
    levers0, lprior = _tag_levers(dataset, eskf, options, names)
    return Problem(t_imu=t_imu, u_imu=u_imu, key_idx=key_idx, t_range=t_r, drift_knot=knot, n_knots=n_knots,
                   rho=rho, anchor_j=aj, anchor_b=bj, tdoa_sigma=tsig,
                   anchor_ids=ids, anchor_pos=np.array([pos[a] for a in ids]), init_states=init,
                   lever0=levers0[0].copy(),
                   td0=float(eskf.calibration["time_offset"]), options=options, range_sigma=float(sigma),
                   imu_noise=noise, imu_noise_source=noise_src, anchors=anchors, tag_i=ti if len(names) > 1 else None, tag_names=list(names),
                   levers0=levers0, lever_prior=lprior, tag_column=bool(tag_column), anchor_rot=rot)


def _pose(s):
    import gtsam

    q = s[6:10] / np.linalg.norm(s[6:10])
    return gtsam.Pose3(gtsam.Rot3.Quaternion(q[0], q[1], q[2], q[3]), s[0:3])


def _imu_factors(pb: Problem):
    """One CombinedImuFactor per keyframe interval (independent of t_d); noise densities and bias random walks
    times ``imu_noise_inflation``."""
    import gtsam

    n = pb.imu_noise
    infl = pb.options.imu_noise_inflation
    rate = (len(pb.t_imu) - 1) / (pb.t_imu[-1] - pb.t_imu[0])
    params = gtsam.PreintegrationCombinedParams.MakeSharedU(GRAVITY)
    params.setAccelerometerCovariance(np.eye(3) * (infl * n["accel_noise_density"]) ** 2)
    params.setGyroscopeCovariance(np.eye(3) * (infl * n["gyro_noise_density"]) ** 2)
    params.setIntegrationCovariance(np.eye(3) * INTEGRATION_COV)
    # the inflation scales the whole IMU noise model (readings and bias walk), so that the factor's covariance is
    # exactly infl^2 times the configured one: what the noise-scale estimate assumes (calibration/noise_scale.py)
    params.setBiasAccCovariance(np.eye(3) * (infl * n["accel_bias_rw"]) ** 2)
    params.setBiasOmegaCovariance(np.eye(3) * (infl * n["gyro_bias_rw"]) ** 2)
    del rate
    factors = []
    u = pb.u_imu
    for k in range(len(pb.key_idx) - 1):
        i0, i1 = pb.key_idx[k], pb.key_idx[k + 1]
        b = pb.init_states[k, 10:16]
        pim = gtsam.PreintegratedCombinedMeasurements(params, gtsam.imuBias.ConstantBias(b[:3], b[3:]))
        for i in range(i0, i1):
            mid = 0.5 * (u[i] + u[i + 1])
            h = pb.t_imu[i + 1] - pb.t_imu[i]
            # GTSAM rotates the step's acceleration with the attitude at the START of the step; the range
            # factors' IMU deltas (imu_cumulative) use the midpoint attitude.  Hand GTSAM the acceleration
            # already turned by half the step's rotation, so both integrate the same motion (otherwise the
            # trajectory lags half an IMU period against the ranges: t_d biased by about -T/2).
            acc = so3_exp(0.5 * h * (mid[3:] - b[3:])) @ (mid[:3] - b[:3]) + b[:3]
            pim.integrateMeasurement(acc, mid[3:], h)
        factors.append(gtsam.CombinedImuFactor(keys.pose(k), keys.velocity(k), keys.pose(k + 1), keys.velocity(k + 1),
                                               keys.imu_bias(k), keys.imu_bias(k + 1), pim))
    return factors


@dataclass
class Association:
    """Ranges attached to keyframes about ``td0`` (IMU clock ``s0 = t + td0``)."""

    td0: float
    used: np.ndarray  # indices into the problem's ranges
    key: np.ndarray
    deltas: list
    # filled by build_graph: per used row, (graph factor index, row within that factor's residual);
    # groups: graph factor index -> RangeGroup of the grouped (per-keyframe) range factors
    slots: Optional[np.ndarray] = None
    groups: dict = field(default_factory=dict)


def associate(pb: Problem, td0: float, imu_bias=None, rows: Optional[np.ndarray] = None) -> Association:
    """Attach the ranges to keyframes about ``td0`` (IMU clock ``s0 = t + td0``).

    Every range with ``s0`` inside the IMU span is used, or, with ``rows`` (indices into the problem's
    ranges), those of ``rows`` inside it: the t_d profile passes the rows inside the span at every grid
    point, so that all its points see the same data.
    """
    s0 = pb.t_range + td0
    inside = (s0 >= pb.t_key[0]) & (s0 < pb.t_imu[-1])
    if rows is not None:
        keep = np.zeros(len(s0), bool)
        keep[np.asarray(rows, np.int64)] = True
        inside &= keep
    used = np.flatnonzero(inside)
    # Short deltas use the ESKF bias of the earliest keyframe (a fixed linearisation point).
    b = pb.init_states[0, 10:16] if imu_bias is None else imu_bias
    cum = None
    if imu_bias is None:
        if pb._imu_cum is None:
            pb._imu_cum = imu_cumulative(pb.t_imu, pb.u_imu, b[:3], b[3:], pb.t_key)
        cum = pb._imu_cum
    k, deltas = imu_deltas(pb.t_imu, pb.u_imu, b[:3], b[3:], pb.t_key, s0[used], cum=cum)
    return Association(td0=td0, used=used, key=k, deltas=deltas)


def build_graph(pb: Problem, assoc: Association, td_fixed: Optional[float] = None, imu_factors=None):
    """The nonlinear factor graph; ``td_fixed`` removes ``T(0)`` (profile points)."""
    import gtsam

    o = pb.options
    g = gtsam.NonlinearFactorGraph()
    for f in imu_factors if imu_factors is not None else _imu_factors(pb):
        g.add(f)
    s = pb.init_states[0]
    g.add(gtsam.PriorFactorPose3(keys.pose(0), _pose(s), gtsam.noiseModel.Diagonal.Sigmas(
        np.array([0.3, 0.3, 0.3, 1.0, 1.0, 1.0]))))
    g.add(gtsam.PriorFactorVector(keys.velocity(0), s[3:6], gtsam.noiseModel.Isotropic.Sigma(3, 1.0)))
    g.add(gtsam.PriorFactorConstantBias(keys.imu_bias(0), gtsam.imuBias.ConstantBias(np.zeros(3), np.zeros(3)),
                                        gtsam.noiseModel.Diagonal.Sigmas(np.array([0.2] * 3 + [0.05] * 3))))
    for i in range(pb.n_tags):
        prior = pb.lever_prior[i] if pb.lever_prior is not None else np.asarray(o.lever_arm_prior, float)
        g.add(gtsam.PriorFactorVector(keys.lever_arm(i), np.asarray(prior, float),
                                      gtsam.noiseModel.Isotropic.Sigma(3, o.lever_arm_prior_sd)))
    if td_fixed is None:
        g.add(gtsam.PriorFactorVector(keys.time_offset(), np.array([o.time_offset_prior]),
                                      gtsam.noiseModel.Isotropic.Sigma(1, o.time_offset_prior_sd)))
    for j in range(len(pb.anchor_ids)):
        bias_sd = o.anchor_bias_prior_sd if o.anchor_bias_estimated(pb.estimated(j)) else 1e-6
        g.add(gtsam.PriorFactorVector(keys.anchor_bias(j), np.zeros(1), gtsam.noiseModel.Isotropic.Sigma(1, bias_sd)))
    if pb.anchors is not None:
        for f in anchor_factors(pb):
            g.add(f)
    if pb.drift_knot is not None:
        for f in drift_factors(pb):
            g.add(f)
    dmod = o.range_model.direction
    for i in range(n_dir_vectors(pb)):
        g.add(gtsam.PriorFactorVector(keys.direction_bias(i), np.zeros(dmod.n_coef),
                                      gtsam.noiseModel.Isotropic.Sigma(dmod.n_coef, dmod.prior_sd)))
    amod = o.range_model.anchor_direction
    for j in adir_anchors(pb):
        g.add(gtsam.PriorFactorVector(keys.anchor_direction_bias(j), np.zeros(amod.n_coef),
                                      gtsam.noiseModel.Isotropic.Sigma(amod.n_coef, amod.prior_sd)))
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(o.huber_k),
                                           gtsam.noiseModel.Isotropic.Sigma(1, pb.range_sigma))
    tnoise = None
    if pb.anchor_b is not None:
        tnoise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(o.huber_k),
                                                gtsam.noiseModel.Isotropic.Sigma(1, pb.tdoa_sigma))
    # assoc.slots records where each used row's residual lives (_report reads it back).
    slots = np.zeros((len(assoc.used), 2), np.int64)
    assoc.groups = {}
    grouped = np.zeros(len(assoc.used), bool)
    if o.group_range_factors:
        plain = np.array([not pb.is_tdoa(m) for m in assoc.used], bool)
        rows = np.flatnonzero(plain)
        if len(rows):
            for chunk in _group_chunks(pb, assoc, rows):
                kfs, kf = np.unique(np.asarray(assoc.key)[chunk], return_inverse=True)
                ms = assoc.used[chunk]
                tag = pb.tag_of(int(ms[0]))
                js = pb.anchor_j[ms].astype(np.int64)
                ujs, col = np.unique(js, return_inverse=True)
                bkeys = [keys.anchor_bias(int(j)) for j in ujs]
                bmat = None
                if pb.drift_knot is not None:
                    dk = np.array([keys.bias_drift(j, n) for j, n in zip(js, pb.drift_knot[ms])], dtype=np.uint64)
                    udk, dcol = np.unique(dk, return_inverse=True)
                    bmat = np.zeros((len(ms), len(ujs) + len(udk)))
                    bmat[np.arange(len(ms)), col] = 1.0
                    bmat[np.arange(len(ms)), len(ujs) + dcol] = 1.0
                    bkeys += [int(x) for x in udk]
                dkw = {}
                if dmod is not None:
                    dj = (js if dmod.per_anchor else np.zeros(len(js), np.int64)) + tag * n_dir_per_tag(pb)
                    udj, dcol = np.unique(dj, return_inverse=True)
                    orders = tuple(range(dmod.lowest_order, dmod.harmonics + 1))
                    dkw = {"direction": (orders, dmod.elevation), "dir_col": dcol}
                    bkeys += [keys.direction_bias(int(x)) for x in udj]
                if amod is not None:
                    dkw |= {"anchor_direction": (amod.orders, amod.powers), "anchor_rot": pb.anchor_rot[js],
                            "adir_col": col}
                    bkeys += [keys.anchor_direction_bias(int(j)) for j in ujs]
                uest = np.array([pb.estimated(int(j)) for j in ujs], bool)
                if uest.any():  # self-survey: the estimated anchors' positions are variables of the group
                    avar = np.where(uest, np.cumsum(uest) - 1, -1)[col]
                    dkw["anchor_var"] = avar
                    bkeys += [keys.anchor_position(int(j)) for j in ujs[uest]]
                grp = RangeGroup([assoc.deltas[i] for i in chunk], pb.anchor_pos[js], pb.rho[ms], col, assoc.td0,
                                 bias_matrix=bmat, kf=kf, **dkw)
                _add_group(g, assoc, slots, chunk, grp, kfs, tag, bkeys, pb.range_sigma, o.huber_k, td_fixed)
            grouped[rows] = True
        _group_tdoa(pb, assoc, g, slots, grouped, td_fixed)
    for i, (m, k, d) in enumerate(zip(assoc.used, assoc.key, assoc.deltas)):
        if grouped[i]:
            continue
        slots[i] = (g.size(), 0)
        j = int(pb.anchor_j[m])
        if pb.is_tdoa(m):
            jb = int(pb.anchor_b[m])
            factor_keys = [keys.pose(k), keys.velocity(k), keys.lever_arm(pb.tag_of(m))] + \
                ([keys.time_offset()] if td_fixed is None else []) + [keys.anchor_bias(j), keys.anchor_bias(jb)]
            g.add(make_gtsam_tdoa_factor(factor_keys, pb.anchor_pos[j], pb.anchor_pos[jb], pb.rho[m], d, assoc.td0,
                                         tnoise, td_fixed=td_fixed))
            continue
        est = pb.estimated(j)
        factor_keys = [keys.pose(k), keys.velocity(k), keys.lever_arm(pb.tag_of(m))] + \
            ([keys.time_offset()] if td_fixed is None else []) + [keys.anchor_bias(j)] + \
            ([keys.anchor_position(j)] if est else [])
        g.add(make_gtsam_factor(factor_keys, pb.anchor_pos[j], pb.rho[m], d, assoc.td0, noise, td_fixed=td_fixed,
                                anchor_variable=est))
    assoc.slots = slots
    return g


def _group_tdoa(pb: Problem, assoc: Association, g, slots: np.ndarray, grouped: np.ndarray, td_fixed) -> None:
    """One :class:`~uwbimu.calibration.tdoa_factor.TdoaGroup` factor per block of ``range_group_keyframes``
    keyframes and tag for the TDoA rows between fixed anchors with constant biases (the same model as one
    :func:`make_gtsam_tdoa_factor` per row, pinned by ``tests/test_calibrate_factor.py``; ~10x fewer Python
    callbacks).  Fills ``slots`` and ``grouped`` for them; the others keep one factor per row."""
    if pb.anchor_b is None or pb.drift_knot is not None:
        return
    o = pb.options
    used = assoc.used
    ok = np.array([pb.is_tdoa(m) and not pb.estimated(int(pb.anchor_j[m])) and not pb.estimated(int(pb.anchor_b[m]))
                   for m in used], bool) & ~grouped
    rows = np.flatnonzero(ok)
    if not len(rows):
        return
    for chunk in _group_chunks(pb, assoc, rows):
        kfs, kf = np.unique(np.asarray(assoc.key)[chunk], return_inverse=True)
        ms = used[chunk]
        ja, jb = pb.anchor_j[ms].astype(np.int64), pb.anchor_b[ms].astype(np.int64)
        uj, inv = np.unique(np.concatenate([ja, jb]), return_inverse=True)
        bmat = np.zeros((len(ms), len(uj)))
        bmat[np.arange(len(ms)), inv[len(ms):]] += 1.0
        bmat[np.arange(len(ms)), inv[:len(ms)]] -= 1.0
        grp = TdoaGroup([assoc.deltas[i] for i in chunk], pb.anchor_pos[ja], pb.anchor_pos[jb], pb.rho[ms], bmat,
                        assoc.td0, kf=kf)
        _add_group(g, assoc, slots, chunk, grp, kfs, pb.tag_of(int(ms[0])), [keys.anchor_bias(int(j)) for j in uj],
                   pb.tdoa_sigma, o.huber_k, td_fixed)
        grouped[chunk] = True


def _group_chunks(pb: Problem, assoc: Association, rows: np.ndarray) -> list[np.ndarray]:
    """The rows (indices into ``assoc.used``) of one grouped factor each: one group per block of
    ``range_group_keyframes`` keyframes and tag (each tag's rows depend on its own lever arm), rows in keyframe
    order within a group."""
    n = pb.options.range_group_keyframes
    keys_of = np.asarray(assoc.key)[rows]
    tg = pb.tag_i[assoc.used[rows]] if pb.tag_i is not None else np.zeros(len(rows), np.int64)
    order = rows[np.lexsort((keys_of, tg, keys_of // n))]
    gk = np.asarray(assoc.key)[order] // n
    if pb.tag_i is not None:
        gk = gk * pb.n_tags + pb.tag_i[assoc.used[order]]
    return np.split(order, np.flatnonzero(np.diff(gk)) + 1)


def _add_group(g, assoc: Association, slots: np.ndarray, chunk: np.ndarray, grp, kfs, tag: int, extra_keys: list,
               sigma: float, huber_k: float, td_fixed) -> None:
    """Add one grouped factor (keys: its keyframes' pose and velocity, the tag's lever arm, t_d when free, then
    ``extra_keys``) and record where its rows' residuals live (``assoc.groups``, ``slots``)."""
    factor_keys = [key for k in kfs for key in (keys.pose(int(k)), keys.velocity(int(k)))] + [keys.lever_arm(tag)] + \
        ([keys.time_offset()] if td_fixed is None else []) + list(extra_keys)
    fi = g.size()
    g.add(make_gtsam_group_factor(factor_keys, grp, sigma, huber_k, td_fixed=td_fixed))
    assoc.groups[fi] = grp
    slots[chunk, 0] = fi
    slots[chunk, 1] = np.arange(len(chunk))


def _group_states(grp: RangeGroup, ks, values):
    """Attitudes (K, 3, 3), positions (K, 3), velocities (K, 3) of a grouped range factor's keyframes."""
    poses = [values.atPose3(ks[2 * i]) for i in range(grp.n_kf)]
    return (np.array([q.rotation().matrix() for q in poses]), np.array([q.translation() for q in poses]),
            np.array([values.atVector(ks[2 * i + 1]) for i in range(grp.n_kf)]))


def _group_coefs(grp: RangeGroup, ks, values):
    """(n_dir, P) direction-bias coefficients of a grouped range factor (its last keys but the anchor-side
    ones), or None."""
    if not grp.n_dir:
        return None
    off = len(ks) - grp.n_apos - grp.n_adir - grp.n_dir
    return np.array([values.atVector(ks[off + i]) for i in range(grp.n_dir)])


def _group_acoefs(grp: RangeGroup, ks, values):
    """(n_adir, P_a) anchor-side direction-bias coefficients of a grouped range factor (its last keys), or None."""
    if not grp.n_adir:
        return None
    off = len(ks) - grp.n_apos - grp.n_adir
    return np.array([values.atVector(ks[off + i]) for i in range(grp.n_adir)])


def _group_apos(grp: RangeGroup, ks, values):
    """(n_apos, 3) positions [m] of a grouped range factor's estimated anchors (its last keys), or None."""
    if not grp.n_apos:
        return None
    return np.array([values.atPoint3(ks[len(ks) - grp.n_apos + i]) for i in range(grp.n_apos)])


def _group_lever(grp: RangeGroup, ks, values) -> np.ndarray:
    """Lever arm of a grouped range factor's tag (the key after its keyframes)."""
    return values.atVector(ks[2 * grp.n_kf])


def adir_anchors(pb) -> list[int]:
    """Indices of the anchors with anchor-side direction coefficients (those with ranges; none without the model)."""
    if pb.options.range_model.anchor_direction is None:
        return []
    return [int(j) for j in np.unique(pb.anchor_j)]


def range_residuals(graph, assoc: Association, values, td: float) -> np.ndarray:
    """Unwhitened residual [m] of every used row (``assoc.used`` order) of a graph built by :func:`build_graph`."""
    out = np.empty(len(assoc.used))
    for fi, grp in assoc.groups.items():
        ks = graph.at(int(fi)).keys()
        nb_off = len(ks) - grp.n_bias - grp.n_dir - grp.n_adir - grp.n_apos
        biases = np.array([values.atVector(ks[nb_off + i])[0] for i in range(grp.n_bias)])
        e = grp.evaluate(*_group_states(grp, ks, values), _group_lever(grp, ks, values), td, biases,
                         dir_coefs=_group_coefs(grp, ks, values), adir_coefs=_group_acoefs(grp, ks, values),
                         anchor_pos=_group_apos(grp, ks, values))
        rows = np.flatnonzero(assoc.slots[:, 0] == fi)
        out[rows] = e[assoc.slots[rows, 1]]
    single = np.flatnonzero(~np.isin(assoc.slots[:, 0], list(assoc.groups)))
    for i in single:
        out[i] = float(graph.at(int(assoc.slots[i, 0])).unwhitenedError(values)[0])
    return out


def _row_terms(graph, assoc: Association, term_of) -> np.ndarray:
    """Per used row (``assoc.used`` order) the value ``term_of(group, keys)`` gives for the rows of every grouped
    range factor (None: the group has no such term; 0 for those rows and the single factors)."""
    out = np.zeros(len(assoc.used))
    for fi, grp in assoc.groups.items():
        term = term_of(grp, graph.at(int(fi)).keys())
        if term is None:
            continue
        rows = np.flatnonzero(assoc.slots[:, 0] == fi)
        out[rows] = term[assoc.slots[rows, 1]]
    return out


def anchor_direction_terms(graph, assoc: Association, values, td: float) -> np.ndarray:
    """Anchor-side direction-dependent bias [m] of every used row (``assoc.used`` order; 0 for rows without it)."""
    def term(grp, ks):
        if grp.anchor_direction is None:
            return None
        u = grp._geometry(*_group_states(grp, ks, values), _group_lever(grp, ks, values), td,
                          _group_apos(grp, ks, values))["u"]
        return grp.anchor_term(u, _group_acoefs(grp, ks, values))

    return _row_terms(graph, assoc, term)


def direction_terms(graph, assoc: Association, values, td: float) -> np.ndarray:
    """Direction-dependent bias [m] of every used row (``assoc.used`` order; 0 for rows without it)."""
    def term(grp, ks):
        if grp.direction is None:
            return None
        wb = grp.line_of_sight_body(*_group_states(grp, ks, values), _group_lever(grp, ks, values), td,
                                    _group_apos(grp, ks, values))
        F, _ = direction_features(wb, *grp.direction)
        return np.einsum("np,np->n", F, _group_coefs(grp, ks, values)[grp.dir_col])

    return _row_terms(graph, assoc, term)


def pair_error(pa: np.ndarray, pb_: np.ndarray, r: float, jacobians: bool = False):
    """Inter-anchor range residual ``|p_a - p_b| - r`` [m] and, on request, its Jacobians (world frame)."""
    u = np.asarray(pa, float) - np.asarray(pb_, float)
    d = float(np.linalg.norm(u))
    if not jacobians:
        return d - r
    n = u / d
    return d - r, n, -n


def _pair_factor(key_a, key_b, fixed_a, fixed_b, r: float, sd: float):
    """CustomFactor of one anchor_ranges.csv row; a ``None`` key means that anchor is fixed."""
    import gtsam

    factor_keys = [k for k in (key_a, key_b) if k is not None]

    def error(this, values, H):
        pa = values.atPoint3(key_a) if key_a is not None else fixed_a
        pb_ = values.atPoint3(key_b) if key_b is not None else fixed_b
        e, Ja, Jb = pair_error(pa, pb_, r, jacobians=True)
        if H is not None:
            i = 0
            if key_a is not None:
                H[i] = Ja.reshape(1, 3)
                i += 1
            if key_b is not None:
                H[i] = Jb.reshape(1, 3)
        return np.array([e])

    return gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, sd), gtsam.KeyVector(factor_keys), error)


def anchor_factors(pb: Problem) -> list:
    """Priors of the estimated anchors, the gauge constraint and the inter-anchor range factors."""
    import gtsam

    s = pb.anchors
    out = []
    for j in np.flatnonzero(s.estimated):
        if np.isfinite(s.prior_sd[j]):
            out.append(gtsam.PriorFactorPoint3(keys.anchor_position(int(j)), s.pos[j].copy(),
                                               gtsam.noiseModel.Isotropic.Sigma(3, float(s.prior_sd[j]))))
    if s.yaw_fix is not None:
        j, y = s.yaw_fix

        def gauge(this, values, H):
            if H is not None:
                H[0] = np.array([[0.0, 1.0, 0.0]])
            return np.array([values.atPoint3(this.keys()[0])[1] - y])

        out.append(gtsam.CustomFactor(gtsam.noiseModel.Isotropic.Sigma(1, GAUGE_SIGMA),
                                      gtsam.KeyVector([keys.anchor_position(int(j))]), gauge))
    if s.pairs is not None:
        for a, b, r, sd in s.pairs[["a", "b", "range", "sd"]].itertuples(index=False):
            a, b = int(a), int(b)
            if not (s.estimated[a] or s.estimated[b]):
                continue  # both fixed: a check only (reported), no variable to constrain
            out.append(_pair_factor(keys.anchor_position(a) if s.estimated[a] else None,
                                    keys.anchor_position(b) if s.estimated[b] else None,
                                    s.pos[a], s.pos[b], float(r), float(sd)))
    return out


def initial_values(pb: Problem, with_td: bool = True):
    import gtsam

    vals = gtsam.Values()
    for k, s in enumerate(pb.init_states):
        vals.insert(keys.pose(k), _pose(s))
        vals.insert(keys.velocity(k), s[3:6].copy())
        vals.insert(keys.imu_bias(k), gtsam.imuBias.ConstantBias(s[10:13].copy(), s[13:16].copy()))
    levers = pb.levers0 if pb.levers0 is not None else pb.lever0[None]
    for i in range(pb.n_tags):
        vals.insert(keys.lever_arm(i), np.asarray(levers[i], float).copy())
    if with_td:
        vals.insert(keys.time_offset(), np.array([pb.td0]))
    for i in range(n_dir_vectors(pb)):
        vals.insert(keys.direction_bias(i), np.zeros(pb.options.range_model.direction.n_coef))
    for j in adir_anchors(pb):
        vals.insert(keys.anchor_direction_bias(j), np.zeros(pb.options.range_model.anchor_direction.n_coef))
    for j in range(len(pb.anchor_ids)):
        vals.insert(keys.anchor_bias(j), np.zeros(1))
        for n in range(pb.n_knots if pb.drift_knot is not None else 0):
            vals.insert(keys.bias_drift(j, n), np.zeros(1))
        if pb.estimated(j):
            vals.insert(keys.anchor_position(j), np.asarray(pb.anchor_pos[j], float).copy())
    return vals


#: GTSAM's ``LevenbergMarquardtParams`` defaults that :func:`optimize` reproduces (lambda schedule, model
#: fidelity threshold of a successful step).
LM_LAMBDA_INITIAL, LM_LAMBDA_FACTOR, LM_LAMBDA_UPPER, LM_MIN_FIDELITY = 1e-5, 10.0, 1e5, 1e-3


def _damping(values, lam: float):
    """GTSAM's LM damping: one prior ``I dx = 0`` with sd ``1/sqrt(lam)`` per variable of ``values``."""
    import gtsam

    g = gtsam.GaussianFactorGraph()
    models = {}
    for key, dim in values.dims().items():
        if dim not in models:
            models[dim] = (np.eye(dim), np.zeros(dim), gtsam.noiseModel.Isotropic.Sigma(dim, 1.0 / np.sqrt(lam)))
        A, b, m = models[dim]
        g.add(gtsam.JacobianFactor(key, A, b, m))
    return g


def optimize(graph, values, max_iterations: int, relative_tol: float = 1e-6, absolute_tol: float = 1e-9,
             predicted_tol: float | None = None, history: list | None = None, engine: str = "python"):
    """Levenberg-Marquardt on ``graph`` from ``values``: GTSAM's algorithm, driven from Python.

    Same steps as ``gtsam.LevenbergMarquardtOptimizer`` with its default parameters (multifrontal
    Cholesky on the COLAMD ordering of the graph, identity damping, lambda from 1e-5, x10 / /10,
    model-fidelity threshold 1e-3) and the stop rule ``relative decrease <= relative_tol`` or
    ``absolute decrease <= absolute_tol`` (GTSAM's ``checkConvergence``).  Why not GTSAM's optimizer:
    it hands the values it owns to every Python ``CustomFactor`` callback, and pybind11 copies a
    C++-owned ``Values`` on each call (one copy of the ~6000 variables per range group and
    evaluation: 75 % of the solve time on a 3-minute log); here every linearisation and error
    evaluation is called on a Python-owned ``Values``, which pybind11 passes by reference.

    ``predicted_tol`` (cost units, i.e. half chi-square): also stop once the decrease still expected is
    below it.  After two accepted steps with cost decreases ``d1``, ``d2`` (``r = d2 / d1 < 1``) the
    remaining decrease of a linearly converging sequence is ``d2 r / (1 - r)``; after the first step,
    the decrease the linearised system predicted for it (the Gauss-Newton model's own estimate) must be
    below it too.  This saves the last, confirming linearisation of GTSAM's rule (which needs the
    decrease itself to be small).  None: GTSAM's rule only.

    ``history``: a list that receives the cost after every accepted step (the first entry: the start).

    Returns
    -------
    (values, iterations): the estimate and the number of successful (accepted) steps.
    """
    import gtsam

    if engine == "gtsam":  # the reference: GTSAM's own optimizer (same steps, slower; see above)
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_tol)
        params.setAbsoluteErrorTol(absolute_tol)
        opt = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
        result = opt.optimize()
        return result, int(opt.iterations())
    err = graph.error(values)
    if history is not None:
        history.append(err)
    if not np.isfinite(err) or err <= 0.0:
        return values, 0
    ordering = graph.orderingCOLAMD()
    damping: dict = {}
    zero = None
    lam = LM_LAMBDA_INITIAL
    it = 0
    last_d = None
    while it < max_iterations:
        lin = graph.linearize(values)
        if zero is None:
            zero = values.zeroVectors()
        old_lin = lin.error(zero)
        moved = done = False
        while True:
            if lam not in damping:
                damping[lam] = _damping(values, lam)
            damped = lin.clone()
            damped.push_back(damping[lam])
            success = stop = False
            try:
                delta = damped.optimize(ordering)
            except RuntimeError:  # IndeterminateSystemException: more damping
                delta = None
            if delta is not None:
                lin_change = old_lin - lin.error(delta)
                if lin_change >= 0.0:
                    new_values = values.retract(delta)
                    new_err = graph.error(new_values)
                    change = err - new_err
                    if lin_change > np.finfo(float).eps * old_lin:
                        success = change / lin_change > LM_MIN_FIDELITY
                    stop = abs(change) < relative_tol * err
            if success:
                values, prev, err = new_values, err, new_err
                if history is not None:
                    history.append(err)
                lam = max(0.0, lam / LM_LAMBDA_FACTOR)
                it += 1
                moved = True
                if predicted_tol is not None:
                    d = prev - err
                    r = d / last_d if last_d else np.inf
                    remaining = d * r / (1.0 - r) if r < 1.0 else np.inf
                    done = (lin_change < predicted_tol and it == 1) or remaining < predicted_tol
                    last_d = d
                break
            if stop:
                break
            lam *= LM_LAMBDA_FACTOR
            if lam >= LM_LAMBDA_UPPER:
                break
        if not moved or done:
            break
        if err <= 0.0 or (prev - err) / prev <= relative_tol or prev - err <= absolute_tol or not np.isfinite(err):
            break
    return values, it


def with_td(values, td: float):
    """Copy of ``values`` with ``T(0) = td`` inserted or replaced."""
    import gtsam

    out = gtsam.Values(values)
    if out.exists(keys.time_offset()):
        out.update(keys.time_offset(), np.array([td]))
    else:
        out.insert(keys.time_offset(), np.array([td]))
    return out


def without_td(values):
    import gtsam

    out = gtsam.Values(values)
    if out.exists(keys.time_offset()):
        out.erase(keys.time_offset())
    return out
