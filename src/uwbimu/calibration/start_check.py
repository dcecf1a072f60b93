"""Where the batch starts: the ESKF's trajectory when that run is healthy, else a robust multilateration.

The factor graph is solved by Levenberg-Marquardt from its initial values; from a diverged or wandering filter
it converges to a wrong local minimum (or not at all).  :func:`eskf_health` states the rule on structured data
the ESKF result already has, :func:`multilaterate_track` is the model-free reference it is checked against and
the fallback's positions, and :func:`multilateration_seed` turns that track into a seed the graph can start from
(position and velocity from a smoothing spline through the fixes, attitude from gravity on the quiet start and
the gyro, yaw from the horizontal velocity changes).

The rule (docs/calibrate.md "What to trust"), every check on the graph frame's data:

1. ``diverged``: the ESKF reported a ``divergence`` or ``reinitialised`` event (its supervisor's verdict);
2. ``non_finite``: a position, velocity or attitude state is not finite;
3. ``accepted_fraction``: fewer than :data:`MIN_ACCEPTED` of its range / TDoA updates were accepted by its gate;
4. ``multilateration``: its antenna track (``p + R p_IU`` at the fixes' times) lies farther from the robust
   multilateration than the fixes' own scatter allows: the median over the fixes of ``d_i / s_i`` exceeds
   :data:`AGREEMENT_K` (``d_i`` the distance [m], ``s_i`` the fix's 3-D position sd from its robust residual
   scale and geometry, floored at :data:`MIN_FIX_SD`), or more than :data:`MAX_FAR_FRACTION` of the fixes are
   farther than ``3 AGREEMENT_K s_i`` (a filter that was right for the first half and then lost).  The bound
   scales with the log's own fix quality, not with a fixed distance.  Skipped (not a failure) with fewer than
   :data:`MIN_FIXES` fixes.

The ESKF is healthy when no check fails.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
import pandas as pd

from uwbimu.estimation.segments import measurement_rows

#: smallest fraction of the ESKF's range / TDoA updates that must pass its gate
MIN_ACCEPTED = 0.5
#: median of distance / fix sd above which the ESKF disagrees with the multilateration
AGREEMENT_K = 3.0
#: fraction of fixes farther than 3 AGREEMENT_K sd above which the ESKF is lost over part of the log
MAX_FAR_FRACTION = 0.2
#: floor of a fix's sd [m] (a fix from many rows can state a sd below the ranges' systematic errors)
MIN_FIX_SD = 0.05
#: window of one multilateration fix [s]
WINDOW_S = 0.5
#: fewest fixes for the agreement check (and for the fallback start)
MIN_FIXES = 10
#: per-axis gyro sd [rad/s] below which the first seconds count as quiet (their mean is the gyro bias)
QUIET_GYRO_SD = 0.02
#: the ESKF events that mean its supervisor lost the track
DIVERGENCE_EVENTS = ("divergence", "reinitialised")


def _rows(dataset, tag: Optional[str] = None):
    """Every range / TDoA row (of ``tag`` when given and the table names its tags) in time order as ``(t,
    anchor b position, anchor a position or NaN, measured, anchor pair, every anchor's position)``."""
    rows = measurement_rows(dataset, tag=tag)
    if rows is None:
        return None
    t, B, A, Z, I = rows
    fin = np.isfinite(Z) & np.isfinite(t)
    order = np.argsort(t[fin], kind="stable")
    return t[fin][order], B[fin][order], A[fin][order], Z[fin][order], I[fin][order], \
        np.array(list(dataset.anchor_positions().values()))


def _fit(x0, B, A, Z):
    """Robust fix of one window: soft-L1, then the rows beyond 3 robust sd dropped and a second soft-L1 fit."""
    from scipy.optimize import least_squares

    td = np.isfinite(A[:, 0])
    A0 = np.where(td[:, None], A, 0.0)

    def resid(x, B=B, A0=A0, Z=Z, td=td):
        return np.linalg.norm(x - B, axis=1) - np.where(td, np.linalg.norm(x - A0, axis=1), 0.0) - Z

    r0 = resid(x0)
    sol = least_squares(resid, x0, loss="soft_l1", f_scale=max(float(np.median(np.abs(r0))), 0.1))
    s = max(1.4826 * float(np.median(np.abs(sol.fun))), 0.01)
    keep = np.abs(sol.fun) <= 3.0 * s
    if keep.sum() >= 6:
        B, A0, Z, td = B[keep], A0[keep], Z[keep], td[keep]
        sol = least_squares(lambda x: resid(x, B, A0, Z, td), sol.x, loss="soft_l1", f_scale=s)
    s = max(1.4826 * float(np.median(np.abs(sol.fun))), 0.01)
    try:
        cov = np.linalg.inv(sol.jac.T @ sol.jac) * s * s
        sd = float(np.sqrt(np.trace(cov)))
    except np.linalg.LinAlgError:
        sd = float("inf")
    return sol.x, sd, int(len(Z))


def multilaterate_track(dataset, window_s: float = WINDOW_S, tag: Optional[str] = None) -> pd.DataFrame:
    """Robust, outlier-rejecting multilateration of the tag antenna in consecutive windows.

    Parameters
    ----------
    dataset : ranges (``uwb``) and / or TDoA (``tdoa``) with the anchors (world frame, z up, known biases
        removed: the graph frame of :func:`uwbimu.calibration.frames.to_graph_frame`).
    window_s : window length [s].
    tag : with several tags, the one to locate (the rows of the others are left out); None: every row.

    Returns
    -------
    DataFrame ``t`` (window centre, UWB clock [s]), ``px, py, pz`` (antenna position [m], world frame), ``sd``
    (3-D position sd [m]: robust residual scale times the geometry), ``n`` (rows used).  A window needs 6 rows
    from 4 distinct anchors (pairs); each fit is soft-L1 with the rows beyond 3 robust sd dropped, and a fix more
    than 3 robust sd (and 3 own sd) from the median of its 5 neighbours is dropped afterwards (Hampel filter).
    """
    cols = ["t", "px", "py", "pz", "sd", "n"]
    rows = _rows(dataset, tag)
    if rows is None or len(rows[0]) < 6:
        return pd.DataFrame(columns=cols)
    t, B, A, Z, ids, anchors = rows
    centre = anchors.mean(axis=0)
    x = centre
    out = []
    edges = np.arange(t[0], t[-1] + window_s, window_s)
    lo = np.searchsorted(t, edges[:-1])
    hi = np.searchsorted(t, edges[1:])
    for w0, w1, i0, i1 in zip(edges[:-1], edges[1:], lo, hi):
        if i1 - i0 < 6 or len(set(ids[i0:i1])) < 4:
            continue
        p, sd, n = _fit(x, B[i0:i1], A[i0:i1], Z[i0:i1])
        if not (np.all(np.isfinite(p)) and np.isfinite(sd)):
            continue
        out.append([0.5 * (w0 + w1), *p, sd, n])
        x = p
    df = pd.DataFrame(out, columns=cols)
    if len(df) >= 5:
        P = df[["px", "py", "pz"]].to_numpy()
        med = np.stack([pd.Series(P[:, c]).rolling(5, center=True, min_periods=3).median().to_numpy()
                        for c in range(3)], axis=1)
        dev = np.linalg.norm(P - med, axis=1)
        s = 1.4826 * float(np.median(dev))
        bad = (dev > 3.0 * s) & (dev > 3.0 * df["sd"].to_numpy())
        df = df[~bad].reset_index(drop=True)
    return df


def _antenna_track(eskf, t: np.ndarray) -> np.ndarray:
    """The ESKF's antenna position ``p + R(q) p_IU`` [m] at UWB times ``t`` (linear in position, nearest attitude)."""
    from uwbimu.models.quaternion import quat_to_rotmat

    st = np.asarray(eskf.states, float)
    te = np.asarray(eskf.t, float)
    p = np.stack([np.interp(t, te, st[:, c]) for c in range(3)], axis=1)
    near = np.clip(np.searchsorted(te, t), 0, len(te) - 1)
    lever = np.asarray(eskf.calibration["lever_arm"], float)
    return p + np.array([quat_to_rotmat(q / np.linalg.norm(q)) @ lever for q in st[near, 6:10]])


def eskf_health(eskf, track: Optional[pd.DataFrame]) -> dict[str, Any]:
    """The health rule of the module docstring applied to an ESKF result.

    Parameters
    ----------
    eskf : :class:`uwbimu.estimation.result.EstimationResult` (graph frame): ``events``, ``states``, ``t``,
        ``residuals`` (``accepted``), ``calibration`` (``lever_arm``).
    track : :func:`multilaterate_track` of the same log, or None (the agreement check is skipped).

    Returns
    -------
    ``{healthy: bool, failed: [check names], checks: {name: {...measured values, bound, ok}}}``.
    """
    checks: dict[str, dict] = {}
    kinds = [str(e.get("kind", "")) for e in (getattr(eskf, "events", None) or [])]
    n_div = sum(k in DIVERGENCE_EVENTS for k in kinds)
    checks["diverged"] = {"events": n_div, "ok": n_div == 0}
    st = np.asarray(eskf.states, float)
    finite = bool(len(st)) and bool(np.all(np.isfinite(st[:, :10])))
    checks["non_finite"] = {"ok": finite}
    res = getattr(eskf, "residuals", None)
    if res is not None and len(res) and "accepted" in res.columns:
        frac = float(np.mean(res["accepted"].to_numpy(bool)))
        checks["accepted_fraction"] = {"value": frac, "bound": MIN_ACCEPTED, "ok": frac >= MIN_ACCEPTED}
    else:
        checks["accepted_fraction"] = {"value": None, "bound": MIN_ACCEPTED, "ok": False}
    if track is not None and len(track) >= MIN_FIXES and finite:
        t = track["t"].to_numpy(float)
        inside = (t >= float(eskf.t[0])) & (t <= float(eskf.t[-1]))
        if inside.sum() >= MIN_FIXES:
            P = track[["px", "py", "pz"]].to_numpy(float)[inside]
            s = np.maximum(track["sd"].to_numpy(float)[inside], MIN_FIX_SD)
            d = np.linalg.norm(_antenna_track(eskf, t[inside]) - P, axis=1)
            ratio = d / s
            med = float(np.median(ratio))
            far = float(np.mean(ratio > 3.0 * AGREEMENT_K))
            checks["multilateration"] = {
                "fixes": int(inside.sum()), "median_distance": float(np.median(d)), "median_fix_sd": float(np.median(s)),
                "median_ratio": med, "bound": AGREEMENT_K, "far_fraction": far, "far_bound": MAX_FAR_FRACTION,
                "ok": bool(med <= AGREEMENT_K and far <= MAX_FAR_FRACTION)}
    if "multilateration" not in checks:
        checks["multilateration"] = {"fixes": 0 if track is None else int(len(track)), "ok": True, "skipped": True}
    failed = [k for k, v in checks.items() if not v["ok"]]
    return {"healthy": not failed, "failed": failed, "checks": checks}


@dataclass
class SeedResult:
    """A trajectory the graph can start from, shaped as the part of an ESKF result that
    :func:`uwbimu.calibration.graph.build_problem` reads.

    Attributes
    ----------
    t, t_imu : (K,) stamps on the UWB and IMU clocks [s].
    states : (K, 16) ``p, v, q, b_a, b_g`` (IMU position [m] and velocity [m/s], world frame; Hamilton body->world;
        biases [m/s^2], [rad/s]).
    calibration : ``lever_arm`` (the prior), ``time_offset`` (the prior), and the ESKF's ``imu_noise`` when it
        measured it on the log (the spectrum does not depend on the filter's health).
    extra : how the seed was made (``yaw_from``, ``fixes``).
    """

    t: np.ndarray
    t_imu: np.ndarray
    states: np.ndarray
    calibration: dict
    events: list = field(default_factory=list)
    config: dict = field(default_factory=dict)
    extra: dict = field(default_factory=dict)
    estimator: str = "multilateration"


def _tilt(f: np.ndarray) -> np.ndarray:
    """Rotation body -> world (yaw 0) that turns the specific force ``f`` at rest to +z."""
    from scipy.spatial.transform import Rotation

    z = f / np.linalg.norm(f)
    axis = np.cross(z, [0.0, 0.0, 1.0])
    s = np.linalg.norm(axis)
    if s < 1e-12:
        return np.eye(3) if z[2] > 0 else np.diag([1.0, -1.0, -1.0])
    return Rotation.from_rotvec(axis / s * np.arctan2(s, z[2])).as_matrix()


def multilateration_seed(dataset, track: pd.DataFrame, lever: np.ndarray, td: float, imu_noise: Optional[dict] = None,
                         rest_s: float = 1.0, step_s: float = 0.01) -> SeedResult:
    """The fallback start: the robust multilateration track with attitude from gravity and the gyro.

    Parameters
    ----------
    dataset : the calibrated log (graph frame); its IMU ``t, ax..wz``.
    track : :func:`multilaterate_track` (at least :data:`MIN_FIXES` fixes).
    lever : the lever-arm prior [m, IMU frame] (antenna = IMU position + R lever).
    td : the time-offset prior [s] (IMU stamp = UWB stamp + td).
    imu_noise : the ESKF's measured IMU noise (``calibration["imu_noise"]``), passed on to the graph.
    rest_s : the first ``rest_s`` seconds of IMU give the roll, pitch (mean specific force) and, when quiet
        (gyro sd below :data:`QUIET_GYRO_SD` per axis), the gyro bias (mean rate; else 0).
    step_s : spacing of the seed's states [s].

    Returns
    -------
    :class:`SeedResult`.  Position and velocity: a smoothing spline through the fixes (weights 1 / sd, its
    smoothing by generalised cross-validation), the lever arm's rotation taken off.  Attitude: the tilt from the
    rest's mean specific force, then the gyro (less the rest's mean) integrated; yaw: the rotation about z that
    best turns the IMU's horizontal velocity changes over 1 s (specific force in the yaw-0 frame plus gravity,
    integrated) onto the spline's (``extra["yaw_from"] = "velocity_changes"``), 0 when the horizontal motion is
    too small to tell (``"none"``).
    """
    from scipy.interpolate import make_smoothing_spline
    from scipy.spatial.transform import Rotation

    from uwbimu.errors import InputError
    from uwbimu.models.reference import GRAVITY

    if len(track) < MIN_FIXES:
        raise InputError(f"calibrate: the multilateration fallback start needs {MIN_FIXES} fixes; the log gives "
                         f"{len(track)}", hint="check the anchors and the ranges / TDoA of the log")
    imu = dataset.imu
    ti = imu["t"].to_numpy(float)
    u = imu[["ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    rest = ti <= ti[0] + rest_s
    f0 = u[rest, :3].mean(axis=0)
    # the gyro bias from the first seconds only when they are quiet (a log cropped to its flight starts moving)
    quiet = bool(np.all(u[rest, 3:].std(axis=0) < QUIET_GYRO_SD))
    bg = u[rest, 3:].mean(axis=0) if quiet else np.zeros(3)
    # attitude on a regular grid: the gyro less its rest mean, integrated (midpoint rate over each step)
    tg = np.arange(ti[0], ti[-1], step_s)
    tg = np.append(tg, ti[-1]) if tg[-1] < ti[-1] else tg
    w = np.stack([np.interp(tg, ti, u[:, 3 + c]) for c in range(3)], axis=1) - bg
    f = np.stack([np.interp(tg, ti, u[:, c]) for c in range(3)], axis=1)
    steps = Rotation.from_rotvec(0.5 * (w[1:] + w[:-1]) * np.diff(tg)[:, None])
    R = [Rotation.from_matrix(_tilt(f0))]
    for s in steps:
        R.append(R[-1] * s)
    R = Rotation.concatenate(R)
    # the antenna track (UWB clock) as a smooth curve; the IMU clock is UWB + td
    tt = track["t"].to_numpy(float) + td
    P = track[["px", "py", "pz"]].to_numpy(float)
    wts = 1.0 / np.maximum(track["sd"].to_numpy(float), MIN_FIX_SD) ** 2
    splines = [make_smoothing_spline(tt, P[:, c], w=wts / wts.mean()) for c in range(3)]
    tc = np.clip(tg, tt[0], tt[-1])
    pa = np.stack([s(tc) for s in splines], axis=1)
    va = np.stack([s.derivative()(tc) for s in splines], axis=1)
    va[(tg < tt[0]) | (tg > tt[-1])] = 0.0
    # yaw: IMU velocity changes over 1 s (yaw-0 frame) against the spline's
    a0 = R.apply(f) - GRAVITY
    dv_imu = np.cumsum(np.vstack([np.zeros(3), 0.5 * (a0[1:] + a0[:-1]) * np.diff(tg)[:, None]]), axis=0)
    k = max(1, int(round(1.0 / step_s)))
    inside = np.flatnonzero((tg >= tt[0]) & (tg + 1.0 <= tt[-1]))
    inside = inside[inside + k < len(tg)]
    yaw, yaw_from = 0.0, "none"
    if len(inside) > 2:
        du = (dv_imu[inside + k] - dv_imu[inside])[:, :2]
        dw = (va[inside + k] - va[inside])[:, :2]
        cross = float(np.sum(du[:, 0] * dw[:, 1] - du[:, 1] * dw[:, 0]))
        dot = float(np.sum(np.sum(du * dw, axis=1)))
        # the fit is trusted when the horizontal changes carry more signal than the spline's noise
        if np.hypot(cross, dot) > 0.5 * float(np.sum(du * du)) and np.sqrt(np.mean(np.sum(dw * dw, 1))) > 0.1:
            yaw, yaw_from = float(np.arctan2(cross, dot)), "velocity_changes"
    R = Rotation.from_euler("z", yaw) * R
    Rm = R.as_matrix()
    lever = np.asarray(lever, float)
    p = pa - Rm @ lever
    q = R.as_quat()[:, [3, 0, 1, 2]]
    states = np.hstack([p, va, q, np.zeros((len(tg), 3)), np.tile(bg, (len(tg), 1))])
    cal = {"lever_arm": [float(x) for x in lever], "time_offset": float(td), "tags": {}}
    if imu_noise:
        cal["imu_noise"] = dict(imu_noise)
    return SeedResult(t=tg - td, t_imu=tg, states=states, calibration=cal,
                      extra={"yaw_from": yaw_from, "yaw": yaw, "fixes": int(len(track)), "quiet_start": quiet})


def choose_start(dataset, o, eskf) -> tuple[Any, dict]:
    """The graph's start: the ESKF when healthy (:func:`eskf_health`), else the robust multilateration seed
    (:func:`multilateration_seed`, lever arm and t_d at the priors of the calibration options ``o``); and the
    ``calibration_start`` event (``source`` ``eskf`` | ``multilateration``, ``reason``: ``healthy`` or the failed
    checks joined by ``+``, ``health``: the checks' values)."""
    from uwbimu.calibration.graph import tag_names

    names, tagged = tag_names(dataset, eskf)
    # the ESKF's top-level lever arm is its first tag's: locate that antenna alone
    track = multilaterate_track(dataset, tag=names[0] if tagged else None)
    health = eskf_health(eskf, track)
    ev = {"kind": "calibration_start", "severity": "info", "source": "eskf", "reason": "healthy",
          "health": health}
    if health["healthy"]:
        return eskf, ev
    reason = "+".join(health["failed"])
    if len(track) < MIN_FIXES:
        # nothing better to start from: the ESKF it is, said as a warning
        ev.update(severity="warning", reason=reason + "+too_few_fixes",
                  message=f"the initialising ESKF failed the health check ({reason}) and the log gives only "
                          f"{len(track)} multilateration fixes: the batch starts from the ESKF anyway")
        return eskf, ev
    imu_noise = (getattr(eskf, "calibration", None) or {}).get("imu_noise")
    seed = multilateration_seed(dataset, track, np.asarray(o.lever_arm_prior, float), float(o.time_offset_prior),
                                imu_noise if (imu_noise or {}).get("source") == "log" else None)
    ev.update(source="multilateration", reason=reason, severity="warning", yaw_from=seed.extra["yaw_from"],
              fixes=seed.extra["fixes"],
              message=f"the initialising ESKF failed the health check ({reason}): the batch starts from a robust "
                      "multilateration of the log (attitude from gravity and the gyro); docs/calibrate.md "
                      "'What to trust'")
    return seed, ev
