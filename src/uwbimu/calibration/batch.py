"""``calibrate(dataset)``: ESKF initialisation, t_d profile, final MAP solve, marginals."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

from math import erfc

import numpy as np
import pandas as pd

from uwbimu.calibration import anchors as AN
from uwbimu.calibration import graph as G
from uwbimu.calibration.options import CalibrationOptions
from uwbimu.calibration.profile import TdProfile, confidence_interval, motion_advice, profile_verdict


@dataclass
class CalibrationResult:
    """Output of :func:`calibrate`.

    Attributes
    ----------
    calibration : plain dict written to ``calibration.yaml`` (value, sd, correlations, verdicts).
    trajectory : DataFrame ``t`` (UWB clock), ``t_imu``, position, quaternion, velocity and their sd.
    residuals : DataFrame ``t, anchor, range, predicted, residual, z, outlier`` (z = residual / sigma).
    anchors : DataFrame in the ``anchors.csv`` format plus ``sd_x, sd_y, sd_z`` [m] (marginal; 0 for
        fixed anchors) and ``estimated`` (bool), every anchor, in the gauge frame.
    profile : the t_d profile, or None when disabled.
    eskf : the initialising ESKF result.
    """

    calibration: dict[str, Any]
    trajectory: pd.DataFrame
    residuals: pd.DataFrame
    profile: Optional[TdProfile]
    eskf: Any
    runtime_s: float = float("nan")
    events: list[dict] = field(default_factory=list)
    anchors: Optional[pd.DataFrame] = None


def _solve(pb, imf, values, td0: float, td_fixed: Optional[float], assoc=None):
    """Solve with ranges attached about ``td0``; re-attach while free t_d moves > half a keyframe step.

    ``assoc``: an association to reuse for the first solve (profile points within half a keyframe
    step of its ``td0``: the factor's second-order extrapolation in ``t_d - td0`` covers them).
    """
    X, V, B, L, T, A = G._keys()
    half = 0.5 / pb.options.keyframe_hz
    for _ in range(pb.options.reassociate_max + 1):
        if assoc is None or abs(assoc.td0 - td0) > half:
            assoc = G.associate(pb, td0)
        graph = G.build_graph(pb, assoc, td_fixed=td_fixed, imu_factors=imf)
        values, iters = G.optimize(graph, values, pb.options.max_iterations)
        if td_fixed is not None:
            break
        td = float(values.atVector(T(0))[0])
        if abs(td - assoc.td0) <= half:
            break
        td0 = td
    return graph, values, assoc, iters


def _profile_grid_points(mu: float, half: float, step: float) -> np.ndarray:
    n = int(round(half / step))
    return np.round(mu + step * np.arange(-n, n + 1), 12)


def run_profile(pb, imf, free_values, centre: float, progress=None) -> TdProfile:
    """Profile of t_d on the grid ``prior +/- half_width``, warm-started outward from ``centre``.

    With ``td_profile.coarse_step`` larger than ``step``: first the whole range at ``coarse_step``,
    then ``step`` within one coarse step either side of the coarse minimum (warm-started from it);
    the verdict reads the union of both (a non-uniform grid).  Otherwise the uniform ``step`` grid.
    """
    po = pb.options.td_profile
    o = pb.options
    mu = o.time_offset_prior
    base = G.without_td(free_values)
    found: dict = {}  # grid point -> (chi2, iterations, values)

    def walk(points, start_t, start_vals, total):
        points = np.asarray(points, float)
        if not len(points):
            return
        start = int(np.argmin(np.abs(points - start_t)))
        for direction in (range(start, len(points)), range(start - 1, -1, -1)):
            vals, assoc = start_vals, None
            for i in direction:
                g = float(points[i])
                graph, vals, assoc, it = _solve(pb, imf, vals, g, g, assoc)
                found[g] = (2.0 * graph.error(vals) + ((g - mu) / o.time_offset_prior_sd) ** 2, it, vals)
                if progress is not None:
                    progress(0.2 + 0.6 * min(1.0, len(found) / total))

    if po.coarse_step is not None and po.coarse_step > po.step:
        coarse = _profile_grid_points(mu, po.half_width, po.coarse_step)
        m = int(round(po.coarse_step / po.step))
        total = len(coarse) + 2 * m
        walk(coarse, centre, base, total)
        best = min(found, key=lambda g: found[g][0])
        fine = np.round(best + po.step * np.arange(-m, m + 1), 12)
        fine = fine[(fine >= coarse[0]) & (fine <= coarse[-1]) & ~np.isin(fine, list(found))]
        walk(fine, best, found[best][2], total)
    else:
        grid = _profile_grid_points(mu, po.half_width, po.step)
        walk(grid, centre, base, len(grid))
    grid = np.array(sorted(found))
    chi2 = np.array([found[g][0] for g in grid])
    iters = np.array([found[g][1] for g in grid], int)
    verdict, best, vertex, sig = profile_verdict(grid, chi2, po.confidence_chi2)
    return TdProfile(grid=grid, chi2=chi2, iterations=iters, verdict=verdict, best=best, vertex=vertex,
                     sigma_curvature=sig, confidence_chi2=po.confidence_chi2)


def calibrate(dataset, options: Optional[CalibrationOptions] = None, eskf=None, eskf_options=None,
              progress: Optional[Callable[[float], None]] = None) -> CalibrationResult:
    """Full-batch MAP calibration of lever arm, t_d and per-anchor range bias (see docs/calibrate.md).

    Parameters
    ----------
    dataset : :class:`uwbimu.io.dataset.Dataset` with IMU, ranges and anchors (one tag).  A z-down
        anchors' frame (``anchor_frame_up: -z``) and ``known_anchor_bias`` are handled by
        :mod:`uwbimu.calibration.frames`: the outputs are in the anchors' frame, the ranges in
        ``residuals`` have the documented biases removed.
    options : graph settings; defaults when None.
    eskf : an ESKF result (anchors' frame) to initialise from; ``run_eskf(dataset, eskf_options)`` when None.
    progress : called with a fraction in [0, 1].
    """
    from uwbimu.estimation import EskfOptions, run_eskf

    from uwbimu.calibration.frames import from_graph_frame, to_graph_frame

    t_start = time.perf_counter()
    o = options or CalibrationOptions()
    dataset, eskf_options, eskf, frame = to_graph_frame(dataset, eskf_options or EskfOptions(), eskf)
    setup = AN.plan_anchors(dataset, o)
    events = list(setup.events)
    eo = eskf_options
    if not setup.any_estimated:
        eskf = eskf if eskf is not None else run_eskf(dataset, eo)
    else:
        eskf = _bootstrap(dataset, o, setup, eo, eskf, events)
    if progress is not None:
        progress(0.1)
    pb = G.build_problem(dataset, eskf, o, setup)
    imf = G._imu_factors(pb)
    X, V, B, L, T, A = G._keys()
    graph, values, assoc, iters = _solve(pb, imf, G.initial_values(pb), pb.td0, None)
    free_td = float(values.atVector(T(0))[0])
    prof = None
    td_free = True
    chi2_scale = 1.0
    if o.td_profile.enabled:
        # honesty correction of the white-noise profile: model / sandwich variance of t_d at the free solve
        chi2_scale = _profile_chi2_scale(pb, graph, values, assoc)
        prof = run_profile(pb, imf, values, free_td, progress)
        if chi2_scale != 1.0:
            prof.verdict, prof.best, prof.vertex, prof.sigma_curvature = profile_verdict(
                prof.grid, prof.chi2, prof.confidence_chi2, chi2_scale=chi2_scale)
        if prof.identified:
            graph, values, assoc, iters = _solve(pb, imf, G.with_td(values, prof.vertex), prof.vertex, None)
            lo, hi = confidence_interval(prof.grid, prof.chi2, prof.confidence_chi2, chi2_scale=chi2_scale)
            td_ref = float(values.atVector(T(0))[0])
            if not lo <= td_ref <= hi:
                # The free optimum contradicts its own profile: report nothing as found.
                prof.verdict = "refinement_left_confidence_set"
        if not prof.identified:
            td_free = False
            events.append({"kind": "time_offset_not_identified", "verdict": prof.verdict,
                           "advice": motion_advice(eskf, prof.verdict, prof.grid)})
            graph, values, assoc, iters = _solve(pb, imf, G.without_td(values), o.time_offset_prior,
                                                 o.time_offset_prior)
    if progress is not None:
        progress(0.9)
    cal, traj, res, anchors = _report(pb, graph, values, assoc, td_free, prof, iters, dataset, chi2_scale=chi2_scale)
    for ev in events:
        if ev["kind"] == "time_offset_not_identified":
            cal["time_offset"]["advice"] = ev["advice"]
    cal["events"] = [{k: v for k, v in ev.items()} for ev in events]
    if progress is not None:
        progress(1.0)
    out = CalibrationResult(calibration=cal, trajectory=traj, residuals=res, profile=prof, eskf=eskf,
                            events=events, anchors=anchors)
    from_graph_frame(out, frame)
    out.runtime_s = time.perf_counter() - t_start
    return out


def _bootstrap(dataset, o: CalibrationOptions, setup, eo, eskf, events: list):
    """ESKF initialisation with anchors to estimate (gauge frame), then their initial guesses.

    With 4 or more anchors with surveyed coordinates the ESKF runs on those alone.  With fewer
    (its first fix needs 4), it runs on every anchor, the ``surveyed: false`` ones at their rough
    ``anchors.csv`` guesses, with the range sd raised to ``bootstrap_range_sigma``: an ESKF that
    trusts ranges to wrongly placed anchors diverges, one that de-weights them tracks the IMU
    trajectory to a few tens of cm, which the joint batch solve then refines.  The unsurveyed
    anchors start at the multilateration of their ranges from that trajectory, followed by the
    geometry checks (:func:`_initial_anchors`).  A given ``eskf`` (same frame) is used as is.
    """
    from uwbimu.estimation import run_eskf

    if eskf is None:
        guesses = int(setup.surveyed.sum()) < 4 and bool((setup.estimated & ~setup.surveyed).any())
        if guesses:
            sigma = max(float(o.range_sigma or dataset.meta.range_sigma or 0.1), o.bootstrap_range_sigma)
            eo = eo.model_copy(update={"range_sigma": sigma})
            events.append({"kind": "anchor_bootstrap_from_guesses", "range_sigma": sigma,
                           "message": f"fewer than 4 surveyed anchors: the initialising ESKF used the anchors.csv "
                                      f"guesses of the unsurveyed anchors with a range sd of {sigma:g} m"})
        eskf = run_eskf(AN.eskf_dataset(dataset, setup, with_unsurveyed=guesses), eo)
    events += _initial_anchors(dataset, eskf, o, setup)
    return eskf


def _initial_anchors(dataset, eskf, o: CalibrationOptions, setup) -> list[dict]:
    """Initial guesses of the estimated anchors (multilateration of the ESKF trajectory) and geometry checks.

    An anchor without prior (``surveyed: false``) starts at the multilateration of its ranges from the
    ESKF antenna positions; one with a prior starts at its ``anchors.csv`` position.  Degenerate
    geometry (:func:`uwbimu.calibration.anchors.geometry_checks`) refuses an anchor without prior unless
    ``degenerate_anchors: warn``; with a prior it is a warning (the prior decides).
    """
    from uwbimu.errors import InputError

    sigma = float(o.range_sigma or dataset.meta.range_sigma or 0.1)
    bias_sd = o.anchor_bias_prior_sd if o.estimate_anchor_bias else None
    uwb = dataset.uwb
    aid = uwb["anchor"].astype(str).to_numpy()
    events = []
    for j in np.flatnonzero(setup.estimated):
        a_id = setup.ids[j]
        sel = (aid == a_id) & (uwb["t"].to_numpy(float) <= eskf.t[-1])  # ranges within the ESKF's span
        rho = uwb["range"].to_numpy(float)[sel]
        has_prior = bool(np.isfinite(setup.prior_sd[j]))
        if sel.sum() < 4 and not has_prior:
            raise InputError(f"anchor self-survey: anchor {a_id!r} has {int(sel.sum())} ranges in uwb.csv; at least 4 "
                             "(from different places) are needed to locate it without a prior")
        if not sel.any():
            continue  # a prior and no ranges: the prior alone places it (its sd says so)
        P, P_sd = AN.antenna_positions(eskf, uwb["t"].to_numpy(float)[sel], with_sd=True)
        if has_prior:
            a0 = setup.pos[j]
        else:
            a0, _rms = AN.multilaterate(P, rho)
            setup.pos[j] = a0
        found = AN.geometry_checks(a_id, a0, P, rho, sigma, bias_sd, P_sd)
        for ev in found:
            ev["severity"] = "warning" if has_prior or o.degenerate_anchors == "warn" else "refused"
            ev["has_prior"] = has_prior
        refused = [ev for ev in found if ev["severity"] == "refused"]
        if refused:
            raise InputError("anchor self-survey refused: " + "; ".join(ev["message"] for ev in refused),
                             hint="give a rough position (surveyed: true) for a weak prior, drop the anchor from "
                                  "--estimate-anchors, or set degenerate_anchors: warn in the calibrate config")
        events += found
    return events


def _calibration_covariance(pb, graph, values, assoc, keys, td: float, td_free: bool):
    """Covariance of ``keys`` by ``options.covariance``: (cov, cov_model, yaml section).

    ``sandwich``: :func:`uwbimu.calibration.covariance.sandwich_covariance` over the range/TDoA rows
    (Huber inliers ``|z| <= huber_k`` in the bread; bandwidth from the lever arm's and t_d's score series).
    """
    import gtsam

    from uwbimu.calibration import covariance as CV

    cov_model = _marginals(pb, graph, values).jointMarginalCovariance(gtsam.KeyVector(keys)).fullMatrix()
    if pb.options.covariance == "model":
        return cov_model, cov_model, {"method": "model", "description": "GTSAM marginals of the white range-noise model"}
    e = G.range_residuals(graph, assoc, values, td)
    sig = np.full(len(e), pb.range_sigma)
    if pb.anchor_b is not None:
        sig[pb.anchor_b[assoc.used] >= 0] = pb.tdoa_sigma
    inlier = np.abs(e / sig) <= pb.options.huber_k
    cov, cov_model, info = CV.sandwich_covariance(graph, values, keys, assoc.slots, pb.t_range[assoc.used],
                                                  1.0 / pb.options.keyframe_hz, inlier=inlier,
                                                  interest=np.arange(4 if td_free else 3), cov_model=cov_model)
    sec = {"method": "sandwich", "description": "HAC (Newey-West, Bartlett kernel) sandwich over the range "
                                                "factors' scores; IMU factors and priors keep their model information",
           "bandwidth_rule": info.method, "bandwidth_s": info.bandwidth_s, "bin_s": info.bin_s,
           "n_bins": info.n_bins, "andrews_bandwidth_s": float(info.andrews_bins * info.bin_s),
           "plateau_bandwidth_s": float(info.plateau_bins * info.bin_s),
           "score_ar1": [round(x, 4) for x in info.rho], "mean_leverage": info.mean_leverage}
    return cov, cov_model, sec


def _profile_chi2_scale(pb, graph, values, assoc) -> float:
    """Model / sandwich variance of t_d at a free solve (1 with ``covariance: model``)."""
    if pb.options.covariance == "model":
        return 1.0
    X, V, B, L, T, A = G._keys()
    td = float(values.atVector(T(0))[0])
    cov, cov_model, _ = _calibration_covariance(pb, graph, values, assoc, [L(0), T(0)], td, True)
    return float(cov_model[3, 3] / cov[3, 3]) if cov[3, 3] > 0 else 1.0


def _report(pb, graph, values, assoc, td_free: bool, prof, iters, dataset, chi2_scale: float = 1.0):
    X, V, B, L, T, A = G._keys()
    P = G._P()
    marg = _marginals(pb, graph, values)
    est = [j for j in range(len(pb.anchor_ids)) if pb.estimated(j)]
    keys = [L(0)] + ([T(0)] if td_free else []) + [A(j) for j in range(len(pb.anchor_ids))] + [P(j) for j in est]
    names = ["lever_arm_x", "lever_arm_y", "lever_arm_z"] + (["time_offset"] if td_free else []) + \
        [f"anchor_bias_{a}" for a in pb.anchor_ids] + \
        [f"anchor_{c}_{pb.anchor_ids[j]}" for j in est for c in "xyz"]
    dmod = pb.options.range_model.direction
    n_dir = G.n_dir_vectors(pb)
    if n_dir:  # last, so the offsets below stay valid
        keys += [G.dir_key(i) for i in range(n_dir)]
        names += [f"direction_{'' if not dmod.per_anchor else pb.anchor_ids[i] + '_'}{c}"
                  for i in range(n_dir) for c in dmod.names()]
    lever = values.atVector(L(0))
    td = float(values.atVector(T(0))[0]) if td_free else pb.options.time_offset_prior
    cov, cov_model, cov_sec = _calibration_covariance(pb, graph, values, assoc, keys, td, td_free)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sd_model = np.sqrt(np.diag(cov_model))
    corr = cov / np.outer(sd, sd)
    # Residuals of the final graph's range factors, in the order of assoc.used.
    e = G.range_residuals(graph, assoc, values, td)
    used = assoc.used
    res = pd.DataFrame({"t": pb.t_range[used], "anchor": np.array(pb.anchor_ids, dtype=object)[pb.anchor_j[used]],
                        "range": pb.rho[used], "predicted": pb.rho[used] + e, "residual": e})
    sig = np.full(len(res), pb.range_sigma)
    if pb.anchor_b is not None:
        # TDoA rows: "anchor" is anchor_a, "range" the measured TDoA [m]
        b = pb.anchor_b[assoc.used]
        res["kind"] = np.where(b >= 0, "tdoa", "range")
        res["anchor_b"] = np.where(b >= 0, np.array(pb.anchor_ids, dtype=object)[np.maximum(b, 0)], "")
        sig[b >= 0] = pb.tdoa_sigma
    if pb.drift_knot is not None:
        # the slowly varying bias of each row (already inside "predicted" and "residual")
        res["bias_drift"] = [float(values.atVector(G.drift_key(j, n))[0])
                             for j, n in zip(pb.anchor_j[used], pb.drift_knot[used])]
    if n_dir:
        # the direction-dependent bias of each row (already inside "predicted" and "residual")
        res["bias_direction"] = G.direction_terms(graph, assoc, values, td)
    res["z"] = res["residual"] / sig
    res["outlier"] = np.abs(res["z"]) > pb.options.huber_k
    offs = 3 + (1 if td_free else 0)
    bias = {a: float(values.atVector(A(j))[0]) for j, a in enumerate(pb.anchor_ids)}
    cal = {
        "method": "batch-map-gtsam",
        "lever_arm": [float(x) for x in lever],
        "lever_arm_sd": [float(x) for x in sd[:3]],
        "lever_arm_sd_model": [float(x) for x in sd_model[:3]],
        "time_offset": {"value": td, "sd": float(sd[3]) if td_free else None,
                        "sd_marginal": float(sd[3]) if td_free else None,
                        "sd_model": float(sd_model[3]) if td_free else None,
                        "profile_chi2_scale": float(chi2_scale),
                        "sd_curvature": (float(prof.sigma_curvature) if prof is not None and prof.identified
                                         else None),
                        "verdict": (prof.verdict if prof is not None else "not_profiled"),
                        "held_at_prior": not td_free,
                        "profile_confidence_interval": (
                            [float(v) for v in confidence_interval(prof.grid, prof.chi2, prof.confidence_chi2,
                                                                   chi2_scale=chi2_scale)]
                            if prof is not None and prof.identified else None),
                        "profile_grid": ([float(prof.grid[0]), float(prof.grid[-1])] if prof is not None else None)},
        "anchor_bias": bias,
        "anchor_bias_sd": {a: float(sd[offs + j]) for j, a in enumerate(pb.anchor_ids)},
        "anchor_bias_sd_model": {a: float(sd_model[offs + j]) for j, a in enumerate(pb.anchor_ids)},
        "covariance": cov_sec,
        "correlations": {"names": names, "matrix": [[round(float(c), 4) for c in row] for row in corr]},
        "ranges": {"used": int(len(assoc.used)), "outside_imu_span": int(len(pb.t_range) - len(assoc.used)),
                   "downweighted": int(res["outlier"].sum()),
                   "expected_downweighted": float(len(res) * erfc(pb.options.huber_k / np.sqrt(2.0))),
                   "outliers_3sigma": int((np.abs(res["z"]) > 3.0).sum()), "huber_k": pb.options.huber_k,
                   "range_sigma": pb.range_sigma},
        "range_model": {"white_sd": pb.range_sigma, "huber_k": pb.options.huber_k,
                        "constant_bias_prior_sd": pb.options.anchor_bias_prior_sd if pb.options.estimate_anchor_bias
                        else None,
                        "drift": (pb.options.range_bias_drift.model_dump() | {"knots_per_anchor": pb.n_knots}
                                  if pb.options.range_bias_drift is not None else None),
                        "direction": _direction_report(pb, values, sd, len(names) - n_dir * (dmod.n_coef if dmod
                                                                                             else 0))},
        "solver": {"keyframes": int(len(pb.key_idx)), "iterations": int(iters),
                   "final_cost": float(graph.error(values))},
    }
    cal["time_offset_sd"] = cal["time_offset"]["sd"]
    # t_d held at its prior: every other sigma is conditional on that value (its uncertainty is not in them)
    cal["conditional_on_time_offset"] = (None if td_free else td)
    off_p = offs + len(pb.anchor_ids)
    sd_p = {j: sd[off_p + 3 * i: off_p + 3 * i + 3] for i, j in enumerate(est)}
    cal["anchors"], anchors = _anchor_report(pb, values, sd_p, dataset)
    traj = _trajectory(pb, values, marg, td)
    return cal, traj, res, anchors


def _direction_report(pb, values, sd, off: int):
    """``range_model.direction`` of calibration.yaml: the model, coefficient values and marginal sd [m, m/rad]."""
    d = pb.options.range_model.direction
    if d is None:
        return None
    out = d.model_dump() | {"frame": "tag body (IMU) frame, line of sight tag antenna -> anchor",
                            "coefficient_names": d.names(), "coefficients": {}}
    labels = list(pb.anchor_ids) if d.per_anchor else ["all"]
    for i, lab in enumerate(labels):
        c = values.atVector(G.dir_key(i))
        s = sd[off + i * d.n_coef: off + (i + 1) * d.n_coef]
        out["coefficients"][lab] = {n: {"value": float(v), "sd": float(e)} for n, v, e in zip(d.names(), c, s)}
    return out


def _anchor_positions(pb, values) -> np.ndarray:
    P = G._P()
    return np.array([values.atPoint3(P(j)) if pb.estimated(j) else pb.anchor_pos[j]
                     for j in range(len(pb.anchor_ids))]).reshape(-1, 3)


def _anchor_report(pb, values, sd_p: dict, dataset):
    """``calibration.yaml``'s ``anchors`` section and the ``anchors_estimated.csv`` table."""
    s = pb.anchors
    pos = _anchor_positions(pb, values)
    R = s.transform[0]
    file_ids = [str(a) for a in dataset.anchors["anchor"]]
    per = {}
    for j, a in enumerate(pb.anchor_ids):
        e = {"position": [float(v) for v in pos[j]],
             "sd": [float(v) for v in sd_p[j]] if j in sd_p else [0.0, 0.0, 0.0],
             "estimated": bool(s.estimated[j]), "surveyed": bool(s.surveyed[j]),
             "prior_sd": float(s.prior_sd[j]) if np.isfinite(s.prior_sd[j]) else None}
        if s.estimated[j] and s.surveyed[j]:
            e["moved_from_anchors_csv"] = [float(v) for v in pos[j] - s.pos[j]]
        per[a] = e
    out = {"gauge": s.gauge, "estimated": [a for j, a in enumerate(pb.anchor_ids) if s.estimated[j]],
           "positions": per}
    if s.pairs is not None:
        out["anchor_ranges"] = [
            {"anchor_a": pb.anchor_ids[int(a)], "anchor_b": pb.anchor_ids[int(b)], "range": float(r), "sd": float(sd),
             "residual": float(np.linalg.norm(pos[int(a)] - pos[int(b)]) - r),
             "in_graph": bool(s.estimated[int(a)] or s.estimated[int(b)])}
            for a, b, r, sd in s.pairs[["a", "b", "range", "sd"]].itertuples(index=False)]
    j_of = {a: j for j, a in enumerate(pb.anchor_ids)}
    rows = []
    for i, a in enumerate(file_ids):
        j = j_of[a]
        sdj = sd_p.get(j, np.zeros(3))
        rows.append([a, *pos[j], *sdj, bool(s.estimated[j])])
    table = pd.DataFrame(rows, columns=["anchor", "x", "y", "z", "sd_x", "sd_y", "sd_z", "estimated"])
    quat = ["qw", "qx", "qy", "qz"]
    if set(quat) <= set(dataset.anchors.columns):
        from scipy.spatial.transform import Rotation

        q = dataset.anchors[quat].to_numpy(float)
        # Antenna orientations follow the gauge rotation (identity unless the convention applies).
        rq = (Rotation.from_matrix(R) * Rotation.from_quat(q[:, [1, 2, 3, 0]])).as_quat()
        for k, c in enumerate(quat):
            table.insert(4 + k, c, rq[:, [3, 0, 1, 2]][:, k])
    return out, table


class SparseMarginals:
    """Marginal covariances from the sparse Gauss-Newton Hessian ``J^T J`` (SciPy ``splu``).

    Used when ``gtsam.Marginals`` refuses a system: GTSAM's Cholesky calls IMU-chain graphs
    "indeterminate" whose conditioning spans ~12 decades (bias random walk against the first
    keyframe's prior, e.g. a hover) although the Hessian is positive definite.  Same linearisation
    (robust weights and noise models baked in by ``graph.linearize``), same covariances: pinned to
    ``gtsam.Marginals`` by ``tests/test_calibrate_sim.py``.
    """

    def __init__(self, graph, values):
        from scipy.sparse.linalg import splu

        from uwbimu.calibration.covariance import linear_system

        J, _b, _row0, self._cols = linear_system(graph, values)  # columns ordered by key
        self._lu = splu((J.T @ J).tocsc())
        self._n = J.shape[1]

    def _block(self, keys):
        cols = np.concatenate([self._cols[int(k)] for k in keys])
        E = np.zeros((self._n, len(cols)))
        E[cols, np.arange(len(cols))] = 1.0
        return self._lu.solve(E)[cols]

    def marginalCovariance(self, key):  # noqa: N802 - gtsam.Marginals' name
        return self._block([key])

    def jointMarginalCovariance(self, keys):  # noqa: N802
        cov = self._block(list(keys))
        return type("Joint", (), {"fullMatrix": lambda _self: cov})()


class _Marginals:
    """``gtsam.Marginals`` that falls back to :class:`SparseMarginals` when GTSAM's Cholesky refuses the
    system, at construction or at any later query (GTSAM eliminates lazily per query)."""

    def __init__(self, graph, values):
        import gtsam

        self._graph, self._values = graph, values
        try:
            self._m = gtsam.Marginals(graph, values)
        except RuntimeError:
            self._m = SparseMarginals(graph, values)

    def _call(self, name, arg):
        try:
            return getattr(self._m, name)(arg)
        except RuntimeError:
            if isinstance(self._m, SparseMarginals):
                raise
            self._m = SparseMarginals(self._graph, self._values)
            return getattr(self._m, name)(arg)

    def marginalCovariance(self, key):  # noqa: N802 - gtsam.Marginals' name
        return self._call("marginalCovariance", key)

    def jointMarginalCovariance(self, keys):  # noqa: N802
        return self._call("jointMarginalCovariance", keys)


def _marginals(pb, graph, values):
    """``gtsam.Marginals``, or :class:`SparseMarginals` when GTSAM's Cholesky refuses the system."""
    return _Marginals(graph, values)


def _trajectory(pb, values, marg, td: float) -> pd.DataFrame:
    X, V, B, *_ = G._keys()
    rows = []
    for k, t in enumerate(pb.t_key):
        pose = values.atPose3(X(k))
        q = pose.rotation().toQuaternion()
        v = values.atVector(V(k))
        cov = marg.marginalCovariance(X(k))  # tangent [theta, p] in the body frame
        R = pose.rotation().matrix()
        sp = np.concatenate([np.sqrt(np.diag(cov[:3, :3])), np.sqrt(np.diag(R @ cov[3:, 3:] @ R.T))])
        sv = np.sqrt(np.diag(marg.marginalCovariance(V(k))))
        rows.append([t - td, t, *pose.translation(), q.w(), q.x(), q.y(), q.z(), *v, *sp[3:], *sp[:3], *sv])
    cols = ["t", "t_imu", "px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz",
            "sd_px", "sd_py", "sd_pz", "sd_rx", "sd_ry", "sd_rz", "sd_vx", "sd_vy", "sd_vz"]
    return pd.DataFrame(rows, columns=cols)
