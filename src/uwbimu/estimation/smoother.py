"""Forward-backward (two-filter) smoothing of an ESKF run over a recorded log.

The ESKF is causal: at time ``t`` it has used the data up to ``t`` only, and it is linearised at its own
running estimates, which on a short or badly excited log are still settling (its start-up transient).
Both leave marks a smoother removes: a position error that follows the filter's recent past, and a
calibration that carries the transient (the time offset of 15 s windows of the demo flight: -13 ms mean
error forward, see docs/estimator.md "Short logs").

A second filter runs on the **time-reversed log** and is fused with the forward one (Fraser and Potter's
two-filter smoother; the combined forward/reverse solution of GNSS/INS post-processing).  Reversing the
log (stamps ``t -> T - t`` on both clocks, ``T`` = first + last IMU stamp, so the span maps onto itself;
rows in reverse order) keeps the equations of motion when

* the gyro reading is negated (``dR/d(-t) = -R [w]x``), so is the gyro bias;
* the accelerometer reading is kept (``d(-v)/d(-t) = dv/dt``): the velocity is negated, the
  accelerometer bias kept;
* positions, attitudes, the lever arm and anchor or pair biases are kept;
* the time offset is negated: an IMU sample stamped ``s`` describes UWB time ``s - t_d``; reversed, the
  sample stamped ``T - s`` describes UWB time ``T - s + t_d``.

Fusion, at every output stamp of the forward run (on the IMU clock: the attitude is the gyro's integral):

* the trajectory (position, velocity, attitude, IMU biases: the first 15 error components): the backward
  estimate is a measurement of them with its covariance, independent of the forward filter's data (it
  used the data after ``t``), folded into the forward state by one Kalman update in error coordinates,
  block by block (Joseph form; blocks the forward run holds in consider mode or fixes get no gain).  Its
  own prior is counted twice there, which matters only within the initialisation window of either end.
  Each block's fused covariance is then scaled by the passes' agreement, ``1 + |1 - r|`` with ``r`` the
  mean normalised squared difference of the two estimates per dof (:func:`fuse_trajectory`): errors the
  passes share (the consider-mode lever arm) are not averaged away, and passes that disagree beyond their
  covariances widen it.
* the calibration (the lever arm, the time offset: constants estimated from the whole log by both
  passes): for a linear-Gaussian model the two final estimates would be the same full-data posterior;
  their difference is what the filters' linearisation and transients made of the data.  The reported
  value is their mean and its sd ``sqrt((sd_f^2 + sd_b^2)/2 + ((f - b)/2)^2)``: the passes' own sd and
  half their disagreement in quadrature.  The verdicts are then re-derived from that sd by the same
  information rule (:func:`uwbimu.estimation.timeoffset.time_offset_verdict`,
  :func:`~uwbimu.estimation.timeoffset.information_verdict`).

The residuals, NIS and noise levels stay the forward filter's (the backward pass runs with the forward
pass's noise levels, not its own estimate, so that both fuse one model).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from uwbimu.errors import EstimationError
from uwbimu.io.dataset import Dataset
from uwbimu.models import state as S
from uwbimu.models.quaternion import (quat_conjugate, quat_exp, quat_log, quat_multiply, quat_normalize,
                                      quat_slerp)

#: error components fused as a trajectory (p, v, theta, b_a, b_g)
CORE = S.N_DYN


def reversal_time(ds: Dataset) -> float:
    """``T`` of the reversal ``t -> T - t``: the first plus the last IMU stamp [s]."""
    t = ds.imu_t
    return float(t[0] + t[-1])


def reverse_dataset(ds: Dataset, T: float | None = None) -> Dataset:
    """The time-reversed log (see the module docstring): stamps ``T - t``, rows reversed, gyro negated,
    ground-truth velocity and the true time offset negated.  Anchors, ranges, TDoA values are kept."""
    T = reversal_time(ds) if T is None else float(T)

    def rev(df, negate=()):
        if df is None or len(df) == 0:
            return df
        out = df.iloc[::-1].reset_index(drop=True).copy()
        out["t"] = T - out["t"].to_numpy(float)
        for c in negate:
            if c in out.columns:
                out[c] = -out[c]
        return out

    meta = ds.meta
    if meta.truth is not None and meta.truth.time_offset is not None:
        meta = meta.model_copy(update={"truth": meta.truth.model_copy(update={"time_offset": -meta.truth.time_offset})})
    return dataclasses.replace(ds, imu=rev(ds.imu, ("wx", "wy", "wz")), uwb=rev(ds.uwb), tdoa=rev(ds.tdoa),
                               groundtruth=rev(ds.groundtruth, ("vx", "vy", "vz")), meta=meta)


def _signs(n_err: int) -> np.ndarray:
    """+1/-1 per error component: the reversal's effect (velocity, gyro bias and time offset negated)."""
    s = np.ones(n_err)
    s[S.EV] = -1.0
    s[S.EBG] = -1.0
    s[S.ETD] = -1.0
    return s


def unreverse(states: np.ndarray, covs: np.ndarray | None, sd: np.ndarray) -> tuple:
    """A reversed run's nominal states, covariances and sds mapped back to forward time's conventions."""
    X = states.copy()
    X[:, S.V] *= -1.0
    X[:, S.BG] *= -1.0
    X[:, S.TD] *= -1.0
    D = sd.copy()  # sds are unsigned: the reversal leaves them
    C = None
    if covs is not None:
        sc = _signs(covs.shape[1])
        C = covs * sc[None, :, None] * sc[None, None, :]
    return X, C, D


def _on_grid(t_src: np.ndarray, X: np.ndarray, C: np.ndarray, t: np.ndarray):
    """States (quaternions by slerp) and covariances linearly interpolated from stamps ``t_src`` (increasing)
    to ``t`` (inside them)."""
    i = np.clip(np.searchsorted(t_src, t) - 1, 0, len(t_src) - 2)
    a = ((t - t_src[i]) / np.maximum(t_src[i + 1] - t_src[i], 1e-12)).clip(0.0, 1.0)
    X0, X1 = X[i], X[i + 1]
    Xi = X0 + a[:, None] * (X1 - X0)
    Xi[:, S.Q] = quat_slerp(X0[:, S.Q], X1[:, S.Q], a)
    Ci = C[i] + a[:, None, None] * (C[i + 1] - C[i])
    return Xi, Ci


#: output stamps fused at a time: bounds the temporaries of the batched Joseph products (a few 10 MB)
CHUNK = 4096

#: the fused blocks (error slices) and their names in the agreement report
BLOCKS = (("position", S.EP), ("velocity", S.EV), ("attitude", S.ETH), ("accel_bias", S.EBA), ("gyro_bias", S.EBG))


def _fuse_chunk(Xf, Cf, Xb, Cb, gain_mask):
    """One chunk of :func:`fuse_trajectory`: the fused states, their covariances before the agreement factor,
    and per block the sum of ``d' (P_f + P_b)^-1 d`` and its count over the chunk's stamps."""
    n = Cf.shape[1]
    c = CORE
    # innovation: backward minus forward in error coordinates (body attitude error, the filter's convention)
    d = np.zeros((len(Xf), c))
    d[:, S.EP] = Xb[:, S.P] - Xf[:, S.P]
    d[:, S.EV] = Xb[:, S.V] - Xf[:, S.V]
    d[:, S.ETH] = quat_log(quat_multiply(quat_conjugate(Xf[:, S.Q]), Xb[:, S.Q]))
    d[:, S.EBA] = Xb[:, S.BA] - Xf[:, S.BA]
    d[:, S.EBG] = Xb[:, S.BG] - Xf[:, S.BG]
    # gain block by block (position, velocity, attitude, each IMU bias: K_i = P_f,ii (P_f,ii + P_b,ii)^-1),
    # not the full-state gain: on real logs the two passes' yaws can differ by tens of degrees with sds that
    # do not say so, and the full gain carries that through the attitude-position correlations into the
    # position (Crazyflie traj16: 0.47 m vs 0.27 m block by block); the Joseph form below gives the
    # covariance of this (suboptimal) gain exactly
    K = np.zeros((len(Xf), n, c))
    q_sum = {}
    for name, sl in BLOCKS:
        Sm = Cf[:, sl, sl] + Cb[:, sl, sl]
        Sm = 0.5 * (Sm + np.swapaxes(Sm, 1, 2))
        K[:, sl, sl] = np.swapaxes(np.linalg.solve(Sm, np.swapaxes(Cf[:, sl, sl], 1, 2)), 1, 2)
        q = np.einsum("ki,ki->k", d[:, sl], np.linalg.solve(Sm, d[:, sl][..., None])[..., 0])
        q = q[np.isfinite(q)]
        q_sum[name] = (float(q.sum()), len(q))
    K *= gain_mask[None, :, None]
    dx = np.einsum("kij,kj->ki", K, d)
    IKH = np.broadcast_to(np.eye(n), Cf.shape).copy()
    IKH[:, :, :c] -= K
    Cs = IKH @ Cf @ np.swapaxes(IKH, 1, 2) + K @ Cb[:, :c, :c] @ np.swapaxes(K, 1, 2)
    Cs = 0.5 * (Cs + np.swapaxes(Cs, 1, 2))
    Xs = Xf.copy()
    Xs[:, S.P] += dx[:, S.EP]
    Xs[:, S.V] += dx[:, S.EV]
    Xs[:, S.Q] = quat_normalize(quat_multiply(Xf[:, S.Q], quat_exp(dx[:, S.ETH])))
    Xs[:, S.BA] += dx[:, S.EBA]
    Xs[:, S.BG] += dx[:, S.EBG]
    Xs[:, S.PIU] += dx[:, S.EPIU]
    Xs[:, S.TD] += dx[:, S.ETD]
    Xs[:, S.NOMINAL_DIM:] += dx[:, S.ERROR_DIM:n]
    return Xs, Cs, q_sum


def fuse_trajectory(t_f, X_f, C_f, t_b, X_b, C_b, gain_mask, chunk: int = CHUNK
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """The forward states updated by the backward estimate of their first ``CORE`` error components.

    ``t_*`` output stamps on the IMU clock (the backward's mapped to forward time and increasing): the
    attitude is the integral of the gyro, an IMU-clock quantity, and the two passes' t_d differ by
    milliseconds (a body turning at 1 rad/s turns 0.06 deg per ms: aligned on the UWB clock the fused
    attitude of the demo flight had NEES 16 for 3 dof),
    ``X_*`` nominal states, ``C_*`` error covariances (the backward's already mapped, see :func:`unreverse`),
    ``gain_mask`` (N,) 1 where the forward run may correct a component; ``chunk`` stamps at a time.  Returns
    the fused states, covariances, a mask of the forward stamps the backward run covers (the others are
    kept) and the passes' agreement per block (``{block: {"r", "factor"}}``, see the comment in the body)."""
    X, C = X_f.copy(), C_f.copy()
    cover = (t_f >= t_b[0]) & (t_f <= t_b[-1])
    if cover.sum() == 0 or len(t_b) < 2:
        return X, C, cover, {}
    idx = np.flatnonzero(cover)
    n = C_f.shape[1]
    q_tot = {name: [0.0, 0] for name, _ in BLOCKS}
    for a in range(0, len(idx), chunk):
        ii = idx[a:a + chunk]
        Xb, Cb = _on_grid(t_b, X_b, C_b, t_f[ii])
        X[ii], C[ii], q_sum = _fuse_chunk(X_f[ii], C_f[ii], Xb, Cb, gain_mask)
        for name, (qs, m) in q_sum.items():
            q_tot[name][0] += qs
            q_tot[name][1] += m
    # the two passes' agreement, block by block: r = mean of d' (P_f + P_b)^-1 d / 3 over the fused stamps is 1
    # when their errors are independent and their covariances right.  r < 1: they agree better than that, so
    # they share an error (the consider-mode lever arm, a common model error) and fusing them gains less:
    # with a shared part c (P_f + P_b) / 2 of their errors, c = 1 - r, the fused covariance is (1 + c) times
    # the independent one (twice it at r = 0: fully correlated estimates, one estimate's covariance).  r > 1:
    # they disagree beyond their covariances, both too small by r (method of moments).  Hence the factor
    # 1 + |1 - r| on each block's rows and columns (D C D: correlations and PSD kept)
    agreement: dict[str, dict[str, float]] = {}
    g = np.ones(n)
    for name, sl in BLOCKS:
        qs, m = q_tot[name]
        if not np.any(gain_mask[sl]) or m == 0:
            continue
        r = qs / m / (sl.stop - sl.start)
        g[sl] = 1.0 + abs(1.0 - r)
        agreement[name] = {"r": r, "factor": float(g[sl.start])}
    sg = np.sqrt(g)
    for a in range(0, len(idx), chunk):
        ii = idx[a:a + chunk]
        C[ii] *= sg[None, :, None] * sg[None, None, :]
    return X, C, cover, agreement


def combine(f: float, sd_f: float, b: float, sd_b: float) -> tuple[float, float]:
    """Mean of two full-data estimates of one constant and its sd: the passes' sd and half their
    disagreement in quadrature (module docstring)."""
    return 0.5 * (f + b), math.sqrt(0.5 * (sd_f ** 2 + sd_b ** 2) + (0.5 * (f - b)) ** 2)


def combine_calibration(cal_f: dict[str, Any], cal_b: dict[str, Any], modes: dict[str, str]) -> dict[str, Any]:
    """The lever arm and time offset of the smoothed result (only the estimated ones change) and a report.

    ``cal_b`` is the backward run's calibration as it reported it (reversed conventions: its t_d is
    negated here).  Returns ``{"calibration": updates, "report": per-parameter forward/backward/combined}``.
    """
    upd: dict[str, Any] = {}
    rep: dict[str, Any] = {}
    if modes.get("time_offset") == "estimate" and cal_b.get("time_offset") is not None:
        f, sf = float(cal_f["time_offset"]), float(cal_f["time_offset_sd"])
        b, sb = -float(cal_b["time_offset"]), float(cal_b["time_offset_sd"])
        v, sd = combine(f, sf, b, sb)
        upd["time_offset"], upd["time_offset_sd"] = v, sd
        rep["time_offset"] = {"forward": f, "forward_sd": sf, "backward": b, "backward_sd": sb,
                              "value": v, "sd": sd}
    if modes.get("lever_arm") == "estimate" and cal_b.get("lever_arm") is not None:
        lv, ls, r = [], [], {}
        for i, c in enumerate("xyz"):
            f, sf = float(cal_f["lever_arm"][i]), float(cal_f["lever_arm_sd"][i])
            b, sb = float(cal_b["lever_arm"][i]), float(cal_b["lever_arm_sd"][i])
            v, sd = combine(f, sf, b, sb)
            lv.append(v)
            ls.append(sd)
            r[c] = {"forward": f, "forward_sd": sf, "backward": b, "backward_sd": sb, "value": v, "sd": sd}
        upd["lever_arm"], upd["lever_arm_sd"] = lv, ls
        rep["lever_arm"] = r
    return {"calibration": upd, "report": rep}


_RANK = {"identified": 2, "weakly identified": 1, "not identified": 0}


def backward_options(eff, info: dict[str, Any]):
    """The options of the reversed pass: the forward pass's model as it ended (noise levels measured or
    searched there, blocks held there), a configured t_d prior negated (the reversal's rule), on the whole
    (already selected) log, without another noise search, hold rerun or smoothing."""
    upd: dict[str, Any] = {"noise": "preset", "imu_noise": info["imu_noise"], "imu_noise_scale": 1.0,
                           "range_sigma": info["range_sigma"], "segment": "whole", "start": None, "end": None,
                           "hold_unidentified": False, "smoother": "off", "store_covariance": True}
    if info.get("tdoa_sigma") is not None:
        upd["tdoa_sigma"] = info["tdoa_sigma"]
    if eff.time_offset.prior is not None:
        upd["time_offset"] = eff.time_offset.model_copy(update={"prior": -float(eff.time_offset.prior)})
    return eff.model_copy(update=upd)


def smooth_result(forward, dataset: Dataset, eff, info: dict[str, Any], gain_mask: np.ndarray, run) -> Any:
    """``forward`` (an :class:`~uwbimu.estimation.result.EstimationResult` of ``dataset``, the segment it
    ran on, with options ``eff`` and problem ``info``) smoothed by a pass of ``run(dataset, options)`` over
    the reversed log; the result is changed in place and returned.

    ``gain_mask`` (N,): the forward problem's.  Adds ``extra["filtered"]`` (the causal track: stamps, states,
    sds, covariances; :func:`causal_view`), ``extra["forward_backward"]``, calibration ``smoothing`` and an
    event ``forward_backward``; re-derives the calibration verdicts.  A reversed pass that fails leaves the
    causal run with a warning event ``forward_backward_skipped``."""
    from uwbimu.estimation.timeoffset import information_verdict, time_offset_verdict

    T = reversal_time(dataset)
    rev = reverse_dataset(dataset, T)
    # the reversed pass starts from its own data (fix, yaw bank, t_d grid): its lever arm and t_d stay an
    # estimate independent of the forward pass's (starting it from the forward's final navigation state
    # instead bought 0.003-0.006 m on the real logs and raised the simulated attitude NEES 4.2 -> 5.0)
    try:
        back = run(rev, backward_options(eff, info))
    except EstimationError as exc:
        # e.g. too few anchors heard at the end of the log to start there: the causal run stands, and says so
        msg = f"smoothing skipped: the pass over the reversed log failed ({exc}); the trajectory is the causal filter's"
        forward.warnings.append(msg)
        forward.events.append({"t": float(forward.t[0]) if len(forward.t) else None, "kind": "forward_backward_skipped",
                               "severity": "warning", "message": msg, "error": type(exc).__name__})
        return forward
    Xb, Cb, _ = unreverse(back.states[::-1], None if back.covariances is None else back.covariances[::-1],
                          back.sd[::-1])
    t_b = T - np.asarray(back.t_imu if back.t_imu is not None else back.t, float)[::-1]
    n = forward.states.shape[0]
    C_f = forward.covariances
    if C_f is None:  # the forward run stored sds only: fuse with diagonal covariances
        d = np.nan_to_num(forward.sd, nan=0.0) ** 2
        C_f = np.einsum("ki,ij->kij", d, np.eye(d.shape[1]))
    if Cb is None:
        d = np.nan_to_num(back.sd[::-1], nan=0.0) ** 2
        Cb = np.einsum("ki,ij->kij", d, np.eye(d.shape[1]))
    mask = np.asarray(gain_mask, float)[:C_f.shape[1]].copy()
    cal = forward.calibration
    modes = dict(forward.config.get("resolved", {}).get("modes", {}))
    if any(e.get("kind") == "time_offset_verdict" and e.get("initial_search") == "not identified"
           for e in forward.events):
        modes["time_offset"] = "consider"  # held at its prior by the initialiser: no gain, no combination
    for key, sl in (("lever_arm", S.EPIU), ("time_offset", slice(S.ETD, S.ETD + 1))):
        if modes.get(key, "estimate") != "estimate":
            mask[sl] = 0.0
    t_imu = np.asarray(forward.t_imu if forward.t_imu is not None else forward.t, float)
    X, C, cover, agreement = fuse_trajectory(t_imu, forward.states, C_f, t_b, Xb, Cb, mask)
    # the causal track, kept whole: what a robot had online, and the information history that the clock-fault
    # check differences window by window (causal_view)
    forward.extra["filtered"] = {"t": np.asarray(forward.t, float).copy(), "t_imu": None if forward.t_imu is None
                                 else np.asarray(forward.t_imu, float).copy(), "states": forward.states,
                                 "sd": forward.sd, "covariances": forward.covariances}
    # new arrays from here on (fuse_trajectory copied them): the causal track above stays as it was
    forward.states = X
    sd = np.sqrt(np.clip(np.diagonal(C, axis1=1, axis2=2), 0.0, None))[:, :forward.sd.shape[1]]
    forward.sd = np.where(np.isnan(forward.sd), np.nan, sd)
    if forward.covariances is not None:
        forward.covariances = C
    comb = combine_calibration(cal, back.calibration, modes)
    verdicts: dict[str, Any] = {}
    if "time_offset" in comb["report"]:
        r = comb["report"]["time_offset"]
        sd_prior = float(cal.get("time_offset_prior_sd", float("nan")))
        v, reason = time_offset_verdict(r["sd"], sd_prior)
        if _RANK.get(v, 0) > _RANK.get(cal.get("time_offset_verdict"), 0):
            v, reason = cal.get("time_offset_verdict"), cal.get("time_offset_verdict_reason")
        if _RANK.get(v, 0) < _RANK.get(cal.get("time_offset_verdict"), 0):
            reason = (f"the forward and backward passes give {r['forward'] * 1e3:.1f} and {r['backward'] * 1e3:.1f} ms; "
                      f"their mean {r['value'] * 1e3:.1f} ± {r['sd'] * 1e3:.1f} ms (half their difference in the sd): {reason}")
        verdicts["time_offset"] = {"forward": cal.get("time_offset_verdict"), "smoothed": v}
        cal["time_offset_verdict"], cal["time_offset_verdict_reason"] = v, reason
    if "lever_arm" in comb["report"]:
        prior = None
        for e in forward.events:
            if e.get("kind") == "lever_arm_verdict":
                prior = {c: a["prior_sd"] for c, a in e["axes"].items()}
        if prior is not None:
            old = dict(cal.get("lever_arm_verdict") or {})
            new = {}
            for c, r in comb["report"]["lever_arm"].items():
                v, _ = information_verdict(r["sd"], float(prior[c]))
                new[c] = v if _RANK.get(v, 0) <= _RANK.get(old.get(c), 2) else old.get(c)
            cal["lever_arm_verdict"] = new
            verdicts["lever_arm"] = {"forward": old, "smoothed": new}
    if "lever_arm" in comb["calibration"] and isinstance(cal.get("tags"), dict):
        for entry in cal["tags"].values():  # the first tag's entry repeats the top-level lever arm
            if isinstance(entry, dict) and entry.get("lever_arm") == cal["lever_arm"]:
                entry["lever_arm"] = list(comb["calibration"]["lever_arm"])
                entry["lever_arm_sd"] = list(comb["calibration"]["lever_arm_sd"])
                break
    for k, v in comb["calibration"].items():
        cal[k] = v
    # a constant's smoothed estimate is the same at every stamp: the combined value over the covered outputs
    # (the states belong to their IMU stamps; their UWB-clock stamps follow the one t_d)
    def set_constant(nom, err, value, sd_new):
        forward.states[cover, nom] = value
        if forward.covariances is not None:
            # rows and columns scaled (D C D, D > 0 diagonal): the new variance, correlations and PSD kept
            ii = np.arange(forward.covariances.shape[1])[err]
            old = np.sqrt(np.clip(forward.covariances[cover][:, ii, ii], 1e-300, None))
            r = np.ones((int(cover.sum()), forward.covariances.shape[1]))
            r[:, err] = np.asarray(sd_new, float) / old
            forward.covariances[cover] *= r[:, :, None] * r[:, None, :]
        forward.sd[cover, err] = sd_new

    if "lever_arm" in comb["calibration"]:
        set_constant(S.PIU, S.EPIU, np.asarray(cal["lever_arm"], float), np.asarray(cal["lever_arm_sd"], float))
    if "time_offset" in comb["calibration"]:
        set_constant(S.TD, S.ETD, float(cal["time_offset"]), float(cal["time_offset_sd"]))
        if forward.t_imu is not None:
            # the UWB-clock stamps of the IMU-clock states, by the one t_d (kept where that would not
            # increase strictly, e.g. next to an uncovered stamp after a large t_d change)
            t_new = forward.t_imu - forward.states[:, S.TD]
            if np.all(np.diff(t_new) > 0):
                forward.t = t_new
    # the backward pass's own warnings repeat the forward's findings on the same data (noise, held blocks):
    # they travel in the event, not in the run's warnings
    rep = {"covered": [float(t_b[0]), float(t_b[-1])], "outputs_fused": int(cover.sum()), "outputs": int(n),
           "backward_runtime_s": float(back.runtime_s),
           "backward_filter_cpu_seconds": float(back.extra.get("filter_cpu_seconds") or 0.0),
           "calibration": comb["report"], "verdicts": verdicts, "agreement": agreement,
           "backward_warnings": list(back.warnings)}
    forward.extra["forward_backward"] = rep
    # calibration.yaml's record of it (the report reads it there)
    cal["smoothing"] = {"method": "forward_backward", "message": message(rep), **comb["report"]}
    t0 = float(forward.t[0]) if n else None
    forward.events.append({"t": t0, "kind": "forward_backward", "severity": "info", "message": message(rep), **rep})
    return forward


def causal_view(result):
    """``result`` with the causal filter's track (stamps, states, sds, covariances) in place of the smoothed one;
    ``result`` itself when it was not smoothed.  For what reads the filter's information history rather than
    the trajectory: the clock-fault check differences the filter's information window by window, which a
    smoothed track (one t_d everywhere) no longer carries (a -0.2 s clock jump went unseen, t_d 126 ms)."""
    f = (getattr(result, "extra", None) or {}).get("filtered")
    if not isinstance(f, dict) or "t" not in f:
        return result
    return dataclasses.replace(result, t=f["t"], t_imu=f["t_imu"], states=f["states"], sd=f["sd"],
                               covariances=f["covariances"])


def message(rep: dict[str, Any]) -> str:
    """The one line the console and the report print for a smoothed run (its ``forward_backward`` event)."""
    from uwbimu.formatting import format_value_sigma

    out = (f"trajectory smoothed forward-backward ({rep['outputs_fused']} of {rep['outputs']} outputs; "
           f"--no-smooth for the causal filter alone)")
    td = (rep.get("calibration") or {}).get("time_offset")
    if td:
        out += (f"; time offset forward {format_value_sigma(1e3 * td['forward'], 1e3 * td['forward_sd'], 'ms')}, "
                f"backward {format_value_sigma(1e3 * td['backward'], 1e3 * td['backward_sd'], 'ms')}, "
                f"reported {format_value_sigma(1e3 * td['value'], 1e3 * td['sd'], 'ms')} (their mean; half "
                f"their difference in the sd)")
    return out
