"""Initialisation of the ESKF from the data alone (never from ground truth).

1. Position and velocity from a multilateration of the first ranges
   (robust Gauss-Newton on ``p0 + v0 (t - t0)``, lever arm neglected).
2. Roll and pitch from the averaged accelerometer (specific force points up).
3. Yaw from a bank of hypotheses: one short filter run per hypothesis over
   ``bank_window_s``; the hypothesis with the lowest robust negative
   log-likelihood of its innovations wins.
4. Time offset from a coarse grid (default -0.25..0.25 s by 0.05 s), scored the
   same way with the chosen yaw, widened when the best point is on an edge and
   refined by a parabola (:mod:`uwbimu.estimation.timeoffset`); a flat score is
   reported as "not identified" and t_d stays at its prior.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Optional

import numpy as np
from scipy.optimize import least_squares

from uwbimu.estimation import kernels as K
from uwbimu.estimation.timeoffset import search_time_offset
from uwbimu.estimation.filterpass import REC_NIS, REC_S, REC_STATUS, Problem, run_pass
from uwbimu.errors import EstimationError
from uwbimu.estimation.options import EskfOptions
from uwbimu.estimation.problem import BlockPriors, block_prior_covariance
from uwbimu.models import state as S
from uwbimu.models.quaternion import quat_from_euler, quat_to_rotmat


@dataclass
class InitialState:
    """Initial extended nominal state ``x`` (20 + nb) and error covariance ``P``
    at IMU sample ``k`` (IMU clock); ranges from index ``j`` on are processed."""

    x: np.ndarray
    P: np.ndarray
    k: int = 0
    j: int = 0
    info: dict[str, Any] = field(default_factory=dict)


class InitialisationError(EstimationError):
    """Not enough data to initialise, e.g. fewer than 4 anchors heard (a RuntimeError; exit code 5)."""


def multilaterate(prob: Problem, j0: int, window: float) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Fit ``p(t) = p0 + v0 (t - t0)`` to the ranges in ``[t0, t0 + window]`` (UWB clock).

    The window is widened (up to 8x) until at least 4 anchors and 8 ranges are
    in it.  Returns ``p0`` (3,), ``v0`` (3,), the RMS residual [m] and the number
    of ranges used.  ``t0 = uwb_t[j0]``.
    """
    t = prob.uwb_t
    t0 = t[j0]
    ub = prob.uwb_b if prob.uwb_b is not None else np.full(len(t), -1, dtype=np.int64)
    for grow in (1, 2, 4, 8):
        sel = (t >= t0) & (t <= t0 + window * grow)
        heard = np.union1d(prob.uwb_a[sel], ub[sel][ub[sel] >= 0])
        if len(heard) >= 4 and sel.sum() >= 8:
            break
    else:
        raise InitialisationError(
            f"cannot initialise at t={t0:.3f} s: fewer than 4 anchors / 8 ranges within {8 * window:.1f} s"
        )
    a = prob.anchors[prob.uwb_a[sel]]
    bsel = ub[sel]
    is_td = bsel >= 0
    # TDoA rows: z = |p - b| - |p - a|; range rows use b = a and a zero-distance first term below
    b = prob.anchors[np.where(is_td, bsel, prob.uwb_a[sel])]
    sign = np.where(is_td, 1.0, 0.0)
    r = prob.uwb_r[sel]
    dt = t[sel] - t0
    centre = prob.anchors.mean(axis=0)
    spread = max(float(np.ptp(prob.anchors, axis=0).max()), 1.0)

    def resid(z):
        p = z[:3][None, :] + z[3:][None, :] * dt[:, None]
        # range: |a - p| - r; TDoA: |p - b| - |p - a| - z  (sign selects the second term)
        ra = np.linalg.norm(a - p, axis=1)
        return sign * np.linalg.norm(b - p, axis=1) + (1.0 - 2.0 * sign) * ra - r

    def fit(z0):
        # absurd ranges (a stream of garbage) can overflow the solver into non-finite values: no fix from there
        try:
            sol = least_squares(resid, z0, loss="soft_l1", f_scale=0.3, max_nfev=200)
        except (ValueError, np.linalg.LinAlgError):
            return None
        return sol if np.all(np.isfinite(sol.x)) and np.isfinite(sol.cost) else None

    best = None
    # two starting points, above and below the anchors' centre: with near-planar
    # anchors the mirror solution is a local minimum too
    for dz in (-0.25 * spread, 0.25 * spread, 0.0):
        z0 = np.concatenate([centre + np.array([0.0, 0.0, dz]), np.zeros(3)])
        sol = fit(z0)
        if sol is not None and (best is None or sol.cost < best.cost - 1e-9):
            best = sol
    if best is None:
        raise InitialisationError(f"cannot initialise at t={t0:.3f} s: the multilateration of the first ranges "
                                  f"diverged (non-finite solution)")
    # gross outliers (e.g. a +100 m range spike) must not set the position prior: residuals beyond 5 sd of
    # the inliers' robust scale (never below the range noise) are dropped and the fit repeated without them
    res = resid(best.x)
    sigma_r = math.sqrt(max(prob.r_var, prob.tdoa_var if is_td.any() else 0.0))
    scale = max(1.4826 * float(np.median(np.abs(res - np.median(res)))), sigma_r)
    inl = np.abs(res) <= 5.0 * scale
    n_out = int((~inl).sum())
    if n_out and inl.sum() >= 8 and len(np.union1d(prob.uwb_a[sel][inl], bsel[inl & is_td])) >= 4:
        a, b, sign, r, dt = a[inl], b[inl], sign[inl], r[inl], dt[inl]
        best = fit(best.x) or best
        res = resid(best.x)
    elif n_out:
        res = res[inl] if inl.any() else res
    rms = float(np.sqrt(np.mean(res**2)))
    return best.x[:3], best.x[3:], rms, int(len(r))


def level_attitude(prob: Problem, k0: int, window: float) -> tuple[float, float]:
    """Roll and pitch [rad] from the mean accelerometer over ``window`` seconds from sample ``k0``."""
    t = prob.imu_t
    k1 = int(np.searchsorted(t, t[k0] + window))
    k1 = max(k1, k0 + 1)
    a = prob.imu_u[k0:k1, :3].mean(axis=0)
    roll = math.atan2(a[1], a[2])
    pitch = math.atan2(-a[0], math.hypot(a[1], a[2]))
    return roll, pitch


def motion_start(prob: Problem, k0: int, max_s: float, smooth_s: float = 0.1,
                 rate_thr: float = 0.15, acc_thr: float = 0.4, undecided_nan: bool = False) -> float:
    """IMU time at which the vehicle starts moving, searching ``max_s`` seconds from sample ``k0``.

    Motion is a (0.1 s moving-average) body rate or specific-force magnitude
    departing from the values of the first 0.3 s by more than ``rate_thr``
    [rad/s] or ``acc_thr`` [m/s^2].  Returns ``imu_t[k0]`` when moving from the
    start and ``inf`` when no motion is found.  Only data up to the first moving sample (plus the
    averaging half-window) decide the answer; with ``undecided_nan`` a search the data do not yet
    cover (no motion so far, window not complete) returns NaN (the streaming filter waits).
    """
    t = prob.imu_t
    k1 = int(np.searchsorted(t, t[k0] + max_s))
    # data that end before the search window does (a stream still arriving, or the end of the log): the
    # moving averages of the last samples are not final, and motion not found yet may still come
    truncated = k1 >= len(t) and t[-1] < t[k0] + max_s
    if k1 - k0 < 10:
        return float("nan") if truncated and undecided_nan else float(t[k0])
    u = prob.imu_u[k0:k1]
    n = max(1, int(round(smooth_s / prob.dt_nom)))
    ker = np.ones(n) / n
    w = np.column_stack([np.convolve(u[:, 3 + i], ker, mode="same") for i in range(3)])
    a = np.linalg.norm(np.column_stack([np.convolve(u[:, i], ker, mode="same") for i in range(3)]), axis=1)
    m = max(n, int(round(0.3 / prob.dt_nom)))
    w0 = w[n:m].mean(axis=0) if m > n else w[0]
    a0 = a[n:m].mean() if m > n else a[0]
    moving = (np.linalg.norm(w - w0, axis=1) > rate_thr) | (np.abs(a - a0) > acc_thr)
    moving[: n] = False  # edge effect of the moving average
    if truncated:
        moving[max(len(moving) - n, 0):] = False
    idx = np.flatnonzero(moving)
    if len(idx) == 0:
        return float("nan") if truncated and undecided_nan else float("inf")
    return float(t[k0 + idx[0]]) if idx[0] > m else float(t[k0])


@dataclass
class Prior:
    """Everything needed to assemble ``x0``/``P0`` besides the hypothesis (yaw, t_d)."""

    p: np.ndarray
    v: np.ndarray
    roll: float
    pitch: float
    lever: np.ndarray
    ba: np.ndarray
    bg: np.ndarray
    anchor_bias: np.ndarray
    sd_p: float
    sd_v: float
    sd_rp: float
    sd_ba: float
    sd_bg: float
    sd_lever: np.ndarray  # (3,) zero when fixed
    sd_bias: float  # zero when fixed
    extra_levers: Optional[np.ndarray] = None  # (T-1, 3) lever arms of tags 2.. (several tags)


def assemble(prob: Problem, pr: Prior, yaw: float, yaw_sd: float, td: float, td_sd: float, k0: int,
             t0_uwb: float, v_t0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Extended nominal state and covariance for one (yaw, t_d) hypothesis at IMU sample ``k0``."""
    L = prob.state_layout()
    x = np.zeros(L.n_nom)
    dt = prob.imu_t[k0] - td - t0_uwb  # UWB-time elapsed since the fix
    x[S.P] = pr.p + v_t0 * dt
    x[S.V] = pr.v
    q = quat_from_euler(pr.roll, pr.pitch, yaw)
    x[S.Q] = q
    x[S.BA] = pr.ba
    x[S.BG] = pr.bg
    x[S.PIU] = pr.lever
    x[S.TD] = td
    x[L.nom("anchor_bias")] = pr.anchor_bias
    P = np.zeros((L.n_err, L.n_err))
    if L.n_tags > 1:
        x[L.nom("extra_levers")] = np.asarray(pr.extra_levers, dtype=float).reshape(-1)
        el = L.err("extra_levers")
        P[el, el] = np.diag(np.tile(pr.sd_lever**2, L.n_tags - 1))
    P[S.EP, S.EP] = np.eye(3) * pr.sd_p**2
    P[S.EV, S.EV] = np.eye(3) * pr.sd_v**2
    # roll/pitch/yaw uncertainty is about world axes; the error state is a body
    # (right) perturbation, dtheta_body = R^T dtheta_world
    R = quat_to_rotmat(q)
    Cw = np.diag([pr.sd_rp**2, pr.sd_rp**2, yaw_sd**2])
    P[S.ETH, S.ETH] = R.T @ Cw @ R
    P[S.EBA, S.EBA] = np.eye(3) * pr.sd_ba**2
    P[S.EBG, S.EBG] = np.eye(3) * pr.sd_bg**2
    P[S.EPIU, S.EPIU] = np.diag(pr.sd_lever**2)
    P[S.ETD, S.ETD] = td_sd**2
    ab = L.err("anchor_bias")
    P[ab, ab] = np.eye(L.n_anchor_bias) * pr.sd_bias**2
    if prob.priors is not None:  # every further declared block from its declared prior sd
        block_prior_covariance(P, L, prob.priors)
    return x, P


def start_index(prob: Problem, t0_uwb: float, td: float) -> int:
    """First IMU sample at or after IMU time ``t0_uwb + td`` (clamped into the log)."""
    k = int(np.searchsorted(prob.imu_t, t0_uwb + td))
    return min(max(k, 0), len(prob.imu_t) - 2)


def score_hypothesis(prob: Problem, x0, P0, k0: int, j0: int, t_from: float, t_to: float,
                     return_count: bool = False):
    """Robust negative log-likelihood of the innovations of a short run (lower is better).

    The lever-arm rotation gate is off here: the hypotheses start before the gyro bias is known (the gate
    would freeze the lever arm for most of the short window and distort the scores of wrong yaws)."""
    if prob.lever_min_rate > 0:
        prob = replace(prob, lever_min_rate=0.0)
    res = run_pass(prob, x0, P0, k0, j0, t_uwb_end=t_to, record=False, to_end=False)
    rec = res.rec
    if rec.shape[0] == 0:
        return (np.inf, 0) if return_count else np.inf
    tt = prob.uwb_t[j0:j0 + rec.shape[0]]
    ok = (rec[:, REC_STATUS] == 0) & (tt >= t_from) & np.isfinite(rec[:, REC_NIS])
    if ok.sum() < 5 or not np.all(np.isfinite(res.x)):
        return (np.inf, 0) if return_count else np.inf
    nis = np.minimum(rec[ok, REC_NIS], 50.0)
    score = float(np.mean(nis + np.log(rec[ok, REC_S])))
    return (score, int(ok.sum())) if return_count else score


def initialise(prob: Problem, opts: EskfOptions, pr_fixed: BlockPriors, j0: int = 0,
               td_known: Optional[float] = None) -> InitialState:
    """Initial state at range index ``j0`` from the data only.

    ``pr_fixed`` carries the calibration priors (:class:`~uwbimu.estimation.problem.BlockPriors`).
    ``td_known`` skips the time-offset grid.
    """
    io = opts.init
    t0 = float(prob.uwb_t[j0])
    p0, v0, rms, nfix = multilaterate(prob, j0, io.window_s)
    td_prior = pr_fixed.t_d if td_known is None else td_known
    k_lvl = start_index(prob, t0, td_prior)
    roll, pitch = level_attitude(prob, k_lvl, io.window_s)
    pr = Prior(
        p=p0, v=v0, roll=roll, pitch=pitch, lever=pr_fixed.lever, ba=pr_fixed.b_a, bg=pr_fixed.b_g,
        anchor_bias=pr_fixed.anchor_bias, sd_p=max(io.position_sd, 2 * rms), sd_v=io.velocity_sd,
        sd_rp=math.radians(io.roll_pitch_sd_deg), sd_ba=pr_fixed.b_a_sd, sd_bg=pr_fixed.b_g_sd,
        sd_lever=pr_fixed.lever_sd, sd_bias=pr_fixed.anchor_bias_sd,
        extra_levers=np.asarray(pr_fixed.tag_levers, dtype=float)[1:],
    )
    info: dict[str, Any] = {"t0": t0, "fix_position": p0.tolist(), "fix_velocity": v0.tolist(),
                            "fix_rms": rms, "fix_ranges": nfix, "roll": roll, "pitch": pitch}
    # yaw and time offset are only observable once the vehicle moves: score the
    # hypotheses on a window that contains bank_window_s of motion
    t_move = motion_start(prob, k_lvl, io.max_wait_s)
    bg, sd_bg = pr_fixed.b_g, pr_fixed.b_g_sd
    if np.isfinite(t_move):
        t_move_uwb = t_move - td_prior
        t_from = max(t0 + 0.25 * io.bank_window_s, t_move_uwb + 0.5)
        t_to = max(t0 + io.bank_window_s, t_move_uwb + 0.75 * io.bank_window_s)
        still = t_move - prob.imu_t[k_lvl]
        info["motion_start"] = float(t_move_uwb)
        if still >= 1.0:
            # a stationary start: the mean gyro reading is the gyro bias (Earth rate neglected)
            k_m = int(np.searchsorted(prob.imu_t, t_move - 0.2))
            wmean = prob.imu_u[k_lvl:k_m, 3:6].mean(axis=0)
            sd_g = max(3.0 * math.sqrt(prob.noise[1] / max(still - 0.2, 0.1)), 1e-3)
            if np.all(np.abs(wmean) < 3 * pr_fixed.b_g_sd + 0.01):
                bg = wmean
                sd_bg = min(sd_g, pr_fixed.b_g_sd)
                info["stationary_gyro_bias"] = wmean.tolist()
    else:
        t_from = t0 + 0.25 * io.bank_window_s
        t_to = t0 + io.bank_window_s
        info["motion_start"] = None
        info["note"] = f"no motion within {io.max_wait_s:g} s: yaw and time offset not observable at start"
    pr.bg = bg
    pr.sd_bg = sd_bg
    info["bank_window"] = [float(t_from), float(t_to)]
    yaw_sd_final = math.radians(io.yaw_sd_deg)

    def run_bank(yaws, tds, yaw_sd, td_sd):
        scores = np.full((len(yaws), len(tds)), np.inf)
        for a, yaw in enumerate(yaws):
            for b, td in enumerate(tds):
                k0 = start_index(prob, t0, td)
                x0, P0 = assemble(prob, pr, yaw, yaw_sd, td, td_sd, k0, t0, v0)
                try:
                    scores[a, b] = score_hypothesis(prob, x0, P0, k0, j0, t_from, t_to)
                except (FloatingPointError, np.linalg.LinAlgError):
                    scores[a, b] = np.inf
        return scores

    search_td = pr_fixed.search_t_d and td_known is None
    if search_td and not np.isfinite(t_move):
        # no motion, no time-offset information: scoring the grid on a standing vehicle would pick noise
        search_td = False
        info["time_offset_init"] = {"status": "not identified",
                           "reason": f"no motion within {io.max_wait_s:g} s of the start (t_d not observable there)"}
    td = td_prior
    td_sd = pr_fixed.t_d_sd
    if io.yaw is not None:
        yaw = float(io.yaw)
    elif io.yaw_hypotheses > 1:
        yaws = np.arange(io.yaw_hypotheses) * 2 * np.pi / io.yaw_hypotheses
        # the time offset is unknown at this stage: let each hypothesis estimate it
        td_sd_bank = max(td_sd, 0.1) if search_td else td_sd
        s = run_bank(yaws, [td], math.pi / io.yaw_hypotheses, td_sd_bank)[:, 0]
        yaw = float(yaws[int(np.argmin(s))]) if np.any(np.isfinite(s)) else 0.0
        info["yaw_bank"] = {"yaws": yaws.tolist(), "scores": s.tolist()}
    else:
        yaw = 0.0
    if search_td and len(io.td_grid) > 1:
        def score_tds(tds):
            out = np.full(len(tds), np.inf)
            cnt = np.zeros(len(tds), dtype=int)
            for b, td_h in enumerate(tds):
                k0 = start_index(prob, t0, td_h)
                x0, P0 = assemble(prob, pr, yaw, yaw_sd_final, td_h, io.td_sd_after_grid, k0, t0, v0)
                try:
                    out[b], cnt[b] = score_hypothesis(prob, x0, P0, k0, j0, t_from, t_to, return_count=True)
                except (FloatingPointError, np.linalg.LinAlgError):
                    pass
            return out, cnt

        found = search_time_offset(score_tds, list(io.td_grid), max_abs_s=io.td_max_abs_s)
        info["time_offset_grid"] = found
        if found["status"] == "found":
            td = float(found["time_offset"])
            # the bank window's data are counted again by the main run: keep the prior loose
            td_sd = max(io.td_sd_after_grid, float(found["time_offset_sd"]))
        else:
            td, td_sd = td_prior, pr_fixed.t_d_sd
        info["time_offset_init"] = {"status": found["status"], "reason": found["reason"]}
        if io.yaw is None and io.yaw_hypotheses > 1 and abs(td - td_prior) > 1e-12:
            # refine the yaw choice with the chosen time offset
            yaws = np.arange(io.yaw_hypotheses) * 2 * np.pi / io.yaw_hypotheses
            s2 = run_bank(yaws, [td], math.pi / io.yaw_hypotheses, td_sd)[:, 0]
            if np.any(np.isfinite(s2)):
                yaw = float(yaws[int(np.argmin(s2))])
            info["yaw_bank_refined"] = {"yaws": yaws.tolist(), "scores": s2.tolist()}
    info.update({"yaw": yaw, "time_offset": td, "time_offset_sd": td_sd})
    yaw_sd0 = yaw_sd_final if io.yaw_hypotheses > 1 or io.yaw is not None else math.pi
    k0 = start_index(prob, t0, td)
    x0, P0 = assemble(prob, pr, yaw, yaw_sd0, td, td_sd, k0, t0, v0)
    if io.refine_s > 0:
        prob_r = hold_time_offset(prob) if info.get("time_offset_init", {}).get("status") == "not identified" else prob
        x0, P0, k0 = _refine(prob_r, pr, x0, P0, k0, j0, t0, v0, yaw_sd0, td_sd, t_to + io.refine_s, info)
    return InitialState(x=x0, P=P0, k=k0, j=j0, info=info)


def data_needed(prob: Problem, opts: EskfOptions, pr_fixed: BlockPriors, j0: int) -> Optional[tuple[float, float]]:
    """How far the data must reach before :func:`initialise` at range ``j0`` gives its final answer.

    Returns ``(t_uwb, t_imu)``: every range stamped up to ``t_uwb`` (UWB clock) and the IMU up to
    ``t_imu`` (IMU clock) must be in ``prob``; ``None`` while the start of motion is still undecided.
    :func:`initialise` reads no data beyond these (the fix window, the level window, the motion
    search, the hypothesis bank and the bootstrap pass, for any time offset the grid may reach), so a
    streaming filter that waits for them initialises exactly as the batch does.
    """
    io = opts.init
    t0 = float(prob.uwb_t[j0])
    td_prior = pr_fixed.t_d
    k_lvl = start_index(prob, t0, td_prior)
    t_move = motion_start(prob, k_lvl, io.max_wait_s, undecided_nan=True)
    if math.isnan(t_move):
        return None
    if np.isfinite(t_move):
        t_to = max(t0 + io.bank_window_s, t_move - td_prior + 0.75 * io.bank_window_s)
    else:
        t_to = t0 + io.bank_window_s
    t_end = t_to + io.refine_s
    t_uwb = max(t_end, t0 + 8.0 * io.window_s)
    td_reach = max(io.td_max_abs_s, abs(td_prior)) if pr_fixed.search_t_d else abs(td_prior)
    t_imu = max(t_uwb + td_reach, float(prob.imu_t[k_lvl]) + io.max_wait_s if not np.isfinite(t_move) else 0.0)
    return t_uwb, t_imu + prob.max_lookback


def hold_time_offset(prob: Problem) -> Problem:
    """The same problem with the time offset in consider mode (its uncertainty kept, never updated).

    Used when the initial search could not identify t_d: the filter then holds it at its prior instead
    of letting a weakly informed, nonlinear update drift it (ISAS-Walk: to 0.35 s)."""
    mask = prob.gain_mask.copy()
    mask[S.ETD] = 0.0
    return replace(prob, gain_mask=mask)


def _refine(prob: Problem, pr: Prior, x0, P0, k0: int, j0: int, t0: float, v0, yaw_sd: float, td_sd: float,
            t_end: float, info: dict[str, Any]):
    """Bootstrap of the linearisation point (the priors' covariances are kept).

    A first pass runs until ``t_end``; its attitude is integrated back with the
    gyro to the start and its calibration (biases, lever arm, time offset) taken
    as the new prior *means*, with the original prior covariances.  This only
    moves the point the EKF linearises about at the start (large initial yaw,
    lever-arm and time-offset errors together bias an EKF); the information of
    the data is counted once by the final run.
    """
    res = run_pass(prob, x0, P0, k0, j0, t_uwb_end=t_end, record=False, to_end=False)
    x = res.x
    if res.diverged or not np.all(np.isfinite(x)) or abs(x[S.TD] - x0[S.TD]) > 3 * max(td_sd, 1e-9) + 1e-9:
        info["refine"] = "skipped (first pass unreliable)"
        return x0, P0, k0
    td = float(x[S.TD])
    k_new = start_index(prob, t0, td)
    xt = np.empty_like(x)
    ut = np.empty(6)
    st = K.state_at(x, prob.imu_t, prob.imu_u, prob.imu_um, res.k, prob.imu_t[k_new], prob.dt_max, xt, ut)
    if st != K.UPD_OK:
        info["refine"] = "skipped (start not reachable)"
        return x0, P0, k0
    q = xt[S.Q] / np.linalg.norm(xt[S.Q])
    yaw = math.atan2(2 * (q[0] * q[3] + q[1] * q[2]), 1 - 2 * (q[2] ** 2 + q[3] ** 2))
    pr2 = Prior(**{**pr.__dict__})
    pr2.ba = x[S.BA].copy()
    pr2.bg = x[S.BG].copy()
    pr2.lever = x[S.PIU].copy()
    L = prob.state_layout()
    pr2.anchor_bias = x[L.nom("anchor_bias")].copy()
    pr2.extra_levers = x[L.nom("extra_levers")].reshape(-1, 3).copy()
    pr2.roll = math.atan2(2 * (q[0] * q[1] + q[2] * q[3]), 1 - 2 * (q[1] ** 2 + q[2] ** 2))
    pr2.pitch = math.asin(max(-1.0, min(1.0, 2 * (q[0] * q[2] - q[3] * q[1]))))
    x1, P1 = assemble(prob, pr2, yaw, yaw_sd, td, td_sd, k_new, t0, v0)
    info["refine"] = {"t_end": float(t_end), "yaw": yaw, "time_offset": td, "lever": x[S.PIU].tolist()}
    return x1, P1, k_new
