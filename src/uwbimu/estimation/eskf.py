"""Tightly-coupled UWB-IMU error-state EKF with online lever-arm and time-offset calibration.

Public entry point: :func:`run_eskf` (dataset -> :class:`EstimationResult`).

* State and kernels: :mod:`uwbimu.estimation.kernels` (19 + nb error states).
* One filter pass, time-offset handling: :mod:`uwbimu.estimation.filterpass`.
* Initialisation from the data: :mod:`uwbimu.estimation.init`.
* Excitation and outage diagnostics: :mod:`uwbimu.estimation.diagnostics`.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace
from typing import Any, Callable, Optional

import numpy as np
import pandas as pd

from uwbimu.errors import InputError
from uwbimu.estimation import kernels as K
from uwbimu.estimation.diagnostics import excitation_warnings, imu_gap_events, outage_warnings
from uwbimu.estimation.filterpass import (
    REC_ACC, REC_INNOV, REC_NIS, REC_PRED, REC_STATUS, STATUS_IN_GAP, STATUS_NOT_PROCESSED, PassResult, Problem, gap_inputs,
    cubic_midpoints, rotation_window_stats,
)
from uwbimu.estimation.init import InitialisationError, InitialState
from uwbimu.estimation.noise_from_data import imu_noise_from_log
from uwbimu.estimation.noise_passes import (
    apply_variance_factor, match_measurement_noise, noise_events, noise_used, unidentified_blocks)
from uwbimu.estimation.noise_search import kind_loglik, search_level
from uwbimu.estimation.timeoffset import (information_verdict, single_clock_time_offset, time_offset_prior_sd,
                                          time_offset_verdict)
from uwbimu.models import state as S
from uwbimu.estimation.options import EskfOptions
from uwbimu.estimation.outputs import block_calibration, fixed_components
from uwbimu.estimation.problem import imu_timing, make_settings, nominal_period
from uwbimu.estimation.streaming import Eskf
from uwbimu.estimation.result import EstimationResult
from uwbimu.estimation.segments import select_segment
from uwbimu.io.dataset import Dataset
from uwbimu.models.quaternion import quat_multiply




#: rotation of 180 deg about x (diagonal of the matrix; it is its own inverse) and its quaternion [w, x, y, z]
FLIP_X = np.array([1.0, -1.0, -1.0])
Q_FLIP_X = np.array([0.0, 1.0, 0.0, 0.0])


def flip_outputs(states: np.ndarray, covs: Optional[np.ndarray]) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Turn filter-frame outputs into a z-down anchors' frame (``anchor_frame_up: -z``).

    ``states`` (K, 20+): position and velocity are world vectors (rotated), the attitude becomes
    ``q_FLIP ⊗ q`` (body -> anchors' frame); biases, lever arm and t_d live in the body or in time
    and do not change.  ``covs`` (K, N, N): the p and v rows/columns are rotated; the attitude error is a
    body perturbation and does not change.  Returns new arrays.
    """
    X = states.copy()
    X[:, S.P] *= FLIP_X
    X[:, S.V] *= FLIP_X
    X[:, S.Q] = quat_multiply(np.broadcast_to(Q_FLIP_X, X[:, S.Q].shape), X[:, S.Q])
    if covs is None:
        return X, None
    d = np.ones(covs.shape[1])
    d[S.EP] = FLIP_X
    d[S.EV] = FLIP_X
    return X, covs * d[None, :, None] * d[None, None, :]


def resolve_anchor_frame_up(ds: Dataset, opts: EskfOptions, warnings: list[str], events: list[dict]) -> str:
    """The anchors' up direction: the options' when given, else the dataset's (``meta.anchor_frame_up``,
    legacy ``meta.extra["anchor_frame_up"]``), else ``"+z"``.  An option that contradicts the dataset
    is used and reported (warning + ``anchor_frame_override`` event)."""
    from_ds = getattr(ds.meta, "anchor_frame_up", None) or (ds.meta.extra or {}).get("anchor_frame_up")
    if from_ds not in (None, "+z", "-z"):
        raise InputError(f"dataset {ds.meta.name!r}: anchor_frame_up must be '+z' or '-z', got {from_ds!r}")
    if opts.anchor_frame_up is None:
        return from_ds or "+z"
    if from_ds is not None and from_ds != opts.anchor_frame_up:
        warnings.append(f"anchor_frame_up: the options' {opts.anchor_frame_up!r} overrides the dataset's {from_ds!r}")
        t0 = float(ds.uwb["t"].iloc[0]) if len(ds.uwb) else 0.0
        events.append({"t": t0, "kind": "anchor_frame_override", "options": opts.anchor_frame_up,
                       "dataset": from_ds})
    return opts.anchor_frame_up


def build_problem(ds: Dataset, opts: EskfOptions) -> tuple[Problem, dict[str, Any]]:
    """Turn a dataset and options into a :class:`Problem` and the calibration priors.

    Returns the problem and a dict of priors / bookkeeping (``warnings``,
    ``events``, ``imu_noise``, ``range_sigma``, ``tag``, ...).
    """
    warnings: list[str] = []
    events: list[dict[str, Any]] = []
    imu = ds.imu.sort_values("t", kind="stable")
    t = imu["t"].to_numpy(float)
    keep = np.concatenate([[True], np.diff(t) > 0])
    if not keep.all():
        warnings.append(f"IMU: {int((~keep).sum())} samples with repeated stamps ignored")
    imu_t = np.ascontiguousarray(t[keep])
    imu_u = np.ascontiguousarray(imu[["ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)[keep])
    if len(imu_t) < 10:
        raise InputError(f"dataset {ds.meta.name!r}: only {len(imu_t)} IMU samples")
    uwb = ds.uwb
    tag = opts.tag
    tag_names: list[str] = []
    if "tag" in uwb.columns:
        tags = list(pd.unique(uwb["tag"].astype(str)))
        if tag is not None and tag not in tags:
            raise InputError(f"tag {tag!r} not in the UWB log (tags: {', '.join(map(str, tags))})")
        if tag is None and len(tags) > 1:
            # several tags, one filter: one lever arm each (dataset.yaml's order first)
            meta_order = [tm.name for tm in ds.meta.tags if tm.name in tags]
            tag_names = meta_order + [t_ for t_ in tags if t_ not in meta_order]
            tag = tag_names[0]
        else:
            tag = tag or tags[0]
            if len(tags) > 1:
                n_other = int((uwb["tag"].astype(str) != tag).sum())
                warnings.append(f"UWB: {len(tags)} tags in the log; using {tag!r} (options.tag), {n_other} ranges "
                                f"of other tags not used")
            uwb = uwb[uwb["tag"].astype(str) == tag]
    uwb = uwb.sort_values("t", kind="stable")
    tag_of_row = (uwb["tag"].astype(str).map({n: i for i, n in enumerate(tag_names)}).to_numpy(np.int64)
                  if tag_names else None)
    anchor_ids = [str(a) for a in ds.anchors["anchor"]]
    index = {a: i for i, a in enumerate(anchor_ids)}
    aid = uwb["anchor"].astype(str).to_numpy()
    known = np.array([a in index for a in aid], dtype=bool)
    rng = uwb["range"].to_numpy(float)
    finite = np.isfinite(rng) & np.isfinite(uwb["t"].to_numpy(float))
    if (~known).any():
        warnings.append(f"UWB: {int((~known).sum())} ranges to anchors missing from anchors.csv not used "
                        f"({sorted(set(aid[~known]))[:5]})")
    if (known & ~finite).any():
        warnings.append(f"UWB: {int((known & ~finite).sum())} non-finite ranges not used")
    sel = known & finite
    uwb_t = np.ascontiguousarray(uwb["t"].to_numpy(float)[sel])
    uwb_a = np.ascontiguousarray(np.array([index[a] for a in aid[sel]], dtype=np.int64))
    uwb_r = np.ascontiguousarray(rng[sel])
    uwb_anchor_ids = aid[sel]
    uwb_tag = tag_of_row[sel] if tag_of_row is not None else np.zeros(len(uwb_t), dtype=np.int64)
    kb = ds.meta.known_anchor_bias or {}
    for a, b in kb.items():
        if a in index:
            uwb_r[uwb_a == index[a]] -= float(b)
    uwb_b = np.full(len(uwb_t), -1, dtype=np.int64)
    tdoa = getattr(ds, "tdoa", None)
    if tdoa is not None and len(tdoa):
        uwb_t, uwb_a, uwb_b, uwb_r, uwb_anchor_ids, uwb_tag = _merge_tdoa(
            tdoa, tag, index, warnings, uwb_t, uwb_a, uwb_r, uwb_anchor_ids, kb, uwb_tag, tag_names)
    anchors = ds.anchor_array(anchor_ids).astype(float)
    frame_up = resolve_anchor_frame_up(ds, opts, warnings, events)
    if frame_up == "-z":
        # the filter's world must have z up (gravity [0, 0, -g]): run in the anchors' frame turned 180 deg
        # about x (y -> -y, z -> -z, a proper rotation); _assemble turns the outputs back
        anchors = anchors * FLIP_X
    if len(uwb_t) < 8:
        raise InputError(f"dataset {ds.meta.name!r}: only {len(uwb_t)} usable ranges / TDoA")

    noise = opts.resolve_imu_noise(ds.meta.imu_noise)
    rsig = opts.range_sigma or ds.meta.range_sigma or 0.1
    # TDoA noise: options, else the dataset's (extra.tdoa_sigma, written by the simulator), else the
    # difference of two independent ranges
    tsig = opts.tdoa_sigma or (ds.meta.extra or {}).get("tdoa_sigma")
    if tag_names:
        levers = [dataset_lever_prior(ds, opts, n) for n in tag_names]
    else:
        levers = dataset_lever_prior(ds, opts, tag)
    pairs = None
    if opts.tdoa_pair_bias.mode == "estimate" and (uwb_b >= 0).any():
        td_rows = uwb_b >= 0
        pairs = sorted({(int(a_), int(b_)) for a_, b_ in zip(uwb_a[td_rows], uwb_b[td_rows])})
    settings, priors = make_settings(opts, anchor_ids, anchors, noise, rsig, tsig, levers, tag_names or None, pairs)
    # the settings plus the data, in one construction
    timing = imu_timing(opts, nominal_period(imu_t))
    gap_idx, gap_sd = gap_inputs(imu_t, imu_u, timing["dt_max"])
    rot_mean, rot_ms = (rotation_window_stats(imu_u, timing["lever_win"]) if timing["lever_min_rate"] > 0
                        else (None, None))
    prob = replace(settings, imu_t=imu_t, imu_u=imu_u, imu_um=cubic_midpoints(imu_t, imu_u),
                   uwb_t=uwb_t, uwb_a=uwb_a, uwb_r=uwb_r,
                   uwb_b=np.ascontiguousarray(uwb_b) if (uwb_b >= 0).any() else None,
                   uwb_tag=np.ascontiguousarray(uwb_tag) if tag_names else None,
                   gap_idx=gap_idx, gap_sd=gap_sd, rot_mean=rot_mean, rot_ms=rot_ms, **timing)
    info = {"warnings": warnings, "events": events, "imu_noise": noise, "range_sigma": rsig, "tdoa_sigma": tsig,
            "tag": tag,
            "tags": tag_names or [tag],
            "anchor_frame_up": frame_up,
            "priors": priors, "uwb_anchor_ids": uwb_anchor_ids}
    return prob, info


def dataset_lever_prior(ds: Dataset, opts: EskfOptions, tag: Optional[str]) -> list[float]:
    """The prior lever arm of the options (``"dataset"``: the tag's nominal one from dataset.yaml)."""
    lever = opts.lever_arm.prior
    if lever is None:
        return [0.0, 0.0, 0.0]
    if lever == "dataset":
        tagmeta = [tm for tm in ds.meta.tags if tm.name == tag] or list(ds.meta.tags[:1])
        return list(tagmeta[0].lever_arm) if tagmeta and tagmeta[0].lever_arm is not None else [0.0, 0.0, 0.0]
    return list(lever)


def _merge_tdoa(tdoa: pd.DataFrame, tag, index: dict[str, int], warnings: list[str], uwb_t, uwb_a, uwb_r,
                uwb_anchor_ids, known_bias: dict[str, float], uwb_tag=None, tag_names=()):
    """Merge ``ds.tdoa`` (``t, anchor_a, anchor_b, tdoa`` [+ ``tag``]) into the UWB stream in time order.

    Returns ``(t, a, b, z, ids)`` with ``b = -1`` for ranges and ``ids`` the (first) anchor's id; rows
    with an unknown anchor or a non-finite value are not used (and counted in ``warnings``).  Known anchor
    range biases (``dataset.yaml`` ``known_anchor_bias``) are removed as ``b_b - b_a``."""
    td = tdoa
    if "tag" in td.columns and tag_names:
        td = td[td["tag"].astype(str).isin(list(tag_names))]
    elif "tag" in td.columns and tag is not None:
        td = td[td["tag"].astype(str) == str(tag)]
    ida = td["anchor_a"].astype(str).to_numpy()
    idb = td["anchor_b"].astype(str).to_numpy()
    kb = {str(k): float(v) for k, v in known_bias.items()}
    z = td["tdoa"].to_numpy(float) - np.array([kb.get(b, 0.0) - kb.get(a, 0.0) for a, b in zip(ida, idb)])
    tt = td["t"].to_numpy(float)
    known = np.array([a in index and b in index for a, b in zip(ida, idb)], dtype=bool)
    ok = known & np.isfinite(z) & np.isfinite(tt) & (ida != idb)
    if (~ok).any():
        warnings.append(f"TDoA: {int((~ok).sum())} rows with unknown / equal anchors or non-finite values not used")
    ta = np.array([index[a] for a in ida[ok]], dtype=np.int64)
    tb = np.array([index[b] for b in idb[ok]], dtype=np.int64)
    t_all = np.concatenate([uwb_t, tt[ok]])
    order = np.argsort(t_all, kind="stable")
    a_all = np.concatenate([uwb_a, ta])[order]
    b_all = np.concatenate([np.full(len(uwb_t), -1, dtype=np.int64), tb])[order]
    z_all = np.concatenate([uwb_r, z[ok]])[order]
    ids = np.concatenate([np.asarray(uwb_anchor_ids, dtype=object),
                          ida[ok].astype(object)])[order]
    if uwb_tag is None:
        uwb_tag = np.zeros(len(uwb_t), dtype=np.int64)
    if "tag" in td.columns and tag_names:
        ttag = td["tag"].astype(str).map({n: i for i, n in enumerate(tag_names)}).to_numpy(np.int64)[ok]
    else:
        ttag = np.zeros(int(ok.sum()), dtype=np.int64)
    tag_all = np.concatenate([np.asarray(uwb_tag, dtype=np.int64), ttag])[order]
    return (np.ascontiguousarray(t_all[order]), np.ascontiguousarray(a_all), np.ascontiguousarray(b_all),
            np.ascontiguousarray(z_all), ids, np.ascontiguousarray(tag_all))


def run_eskf(
    dataset: Dataset,
    options: Optional[EskfOptions] = None,
    progress: Optional[Callable[[float], None]] = None,
    initial: Optional[InitialState] = None,
) -> EstimationResult:
    """Run the error-state EKF over a dataset.

    Parameters
    ----------
    dataset : the log (IMU on its clock, ranges on the UWB clock, anchors).
    options : :class:`EskfOptions` (defaults when None).
    progress : optional callback receiving the fraction of the IMU log done (0..1).
    initial : optional initial state/covariance (bypasses the data-driven
        initialiser; used by consistency tests, never filled from ground truth
        by the estimator itself).

    Returns
    -------
    EstimationResult with output stamps on the UWB clock (``t_imu - t_d_hat``).
    """
    opts = options or EskfOptions()
    t_wall = time.perf_counter()
    cpu0 = time.process_time()
    cpu_filter = 0.0
    dataset, ev_segment = select_segment(dataset, opts.segment, opts.start, opts.end)
    opts, ev_clock = single_clock_time_offset(dataset, opts)
    prob, info = build_problem(dataset, opts)
    warnings: list[str] = list(info["warnings"])
    for ev in ev_clock:
        ev["t"] = float(prob.uwb_t[0]) if len(prob.uwb_t) else None
    events: list[dict[str, Any]] = [ev_segment] + ev_clock + list(info["events"])
    if ev_segment["cropped"]:
        warnings.append(ev_segment["message"])
    priors = info["priors"]
    n_imu = len(prob.imu_t)
    t_imu0, t_imu1 = prob.imu_t[0], prob.imu_t[-1]
    cb = None
    if progress is not None:
        def cb(k: int) -> None:
            progress(min(1.0, (prob.imu_t[min(k, n_imu - 1)] - t_imu0) / max(t_imu1 - t_imu0, 1e-9)))

    ev_gap, warn_gap = imu_gap_events(prob.imu_t, prob.dt_max)
    events += ev_gap
    warnings += warn_gap

    # noise from the data (rule 1): the IMU densities from the log's spectrum
    eff = opts  # the options in effect: the given ones with what the log decided filled in
    noise_report: dict[str, Any] = {"mode": opts.noise}
    if opts.noise == "data" and opts.imu_noise is None and opts.imu_noise_scale == 1.0:
        imu_noise, noise_report["imu"] = imu_noise_from_log(prob.imu_t, prob.imu_u, info["imu_noise"])
        if imu_noise is not info["imu_noise"]:
            eff = eff.model_copy(update={"imu_noise": imu_noise})
            prob, info = build_problem(dataset, eff)
    else:
        noise_report["imu"] = {"status": "given"}

    f, cpu_filter = _filter_pass(prob, priors, eff, initial, cb)
    if f.initial is None:
        raise InitialisationError(f._init_failure or "not enough data to initialise")
    # rule 2: the range / TDoA noise by covariance matching of the first pass's innovations; one more pass
    # (from the same start) when a level is outside its sampling band
    if opts.noise == "data":
        match = match_measurement_noise(f.problem(), f.passes(), info, opts)
        noise_report["measurements"] = match
        update = {f"{k}_sigma": v["sigma_new"] for k, v in match.items() if v.get("changed")}
        if update:
            # both levels explicit: a TDoA sd left to its default would follow the range sd in the search
            eff = eff.model_copy(update={"imu_noise": info["imu_noise"], "range_sigma": info["range_sigma"],
                                         "tdoa_sigma": info.get("tdoa_sigma"), **update})
            prob, info = build_problem(dataset, eff)
            f, cpu2 = _filter_pass(prob, priors, eff, f.initial, cb)
            cpu_filter += cpu2
            # the matched level fits the core; the level the filter predicts its measurements best with is
            # searched from it (noise_search), each corrected kind in turn, from the same start
            cpu_search = [0.0]
            for kind in [k for k, v in match.items() if v.get("changed") and opts.noise_search]:
                def evaluate(sig: float, kind: str = kind, base: EskfOptions = eff, start=f.initial):
                    e2 = base.model_copy(update={f"{kind}_sigma": sig})
                    p2, i2 = build_problem(dataset, e2)
                    f2, c2 = _filter_pass(p2, priors, e2, start, cb)
                    cpu_search[0] += c2
                    return kind_loglik(f2.problem(), f2.passes(), kind), (f2, p2, i2, e2)

                sig0 = float(getattr(eff, f"{kind}_sigma"))
                sig, best, rep = search_level(sig0, kind_loglik(f.problem(), f.passes(), kind), evaluate,
                                              payload0=(f, prob, info, eff))
                match[kind]["likelihood"] = rep
                match[kind]["sigma_new"] = sig
                f, prob, info, eff = best
            cpu_filter += cpu_search[0]
    result = _finish(dataset, f, info, priors, eff, noise_report)
    # a calibration block the log does not identify is held at its prior (consider mode) and the filter
    # rerun: a parameter the data cannot determine would otherwise absorb unmodelled errors into the
    # trajectory (the Crazyflie's 9 cm lever arm wandered to 40 cm and took the position with it)
    held = unidentified_blocks(result, eff) if opts.hold_unidentified else {}
    if held:
        eff = eff.model_copy(update={"imu_noise": info["imu_noise"], "range_sigma": info["range_sigma"],
                                     "tdoa_sigma": info.get("tdoa_sigma"), **held})
        prob, info = build_problem(dataset, eff)
        first = result.calibration
        # why the lever arm is not identified (excitation, rotation gate) is said by the first pass
        first_lever_warnings = [w for w in result.warnings if w.startswith("lever arm")]
        # ... and so are its divergences / re-initialisations (the held rerun may not repeat them)
        first_lever_events = [e for e in result.events if e["kind"] in ("lever_arm_not_updated", "divergence",
                                                                         "reinitialised")
                              or (e["kind"] == "low_excitation" and e.get("parameter") == "lever arm")]
        # from the initialiser again: the first start carries the estimated blocks' search
        f, cpu2 = _filter_pass(prob, priors, eff, initial, cb)
        cpu_filter += cpu2
        result = _finish(dataset, f, info, priors, eff, noise_report)
        result.events.append({"t": float(prob.uwb_t[0]), "kind": "calibration_held",
                              "blocks": sorted(held), "first_pass": {
                                  "lever_arm": first["lever_arm"], "lever_arm_sd": first["lever_arm_sd"],
                                  "time_offset": first["time_offset"], "time_offset_sd": first["time_offset_sd"],
                                  "lever_arm_verdict": first.get("lever_arm_verdict"),
                                  "time_offset_verdict": first.get("time_offset_verdict")}})
        result.warnings.append("lever arm: no axis identified by this log; held at its prior in consider mode "
                               "(the filter rerun; first pass in the calibration_held event)")
        result.warnings += [w for w in first_lever_warnings if w not in result.warnings]
        result.events += [dict(e, first_pass=True) for e in first_lever_events]
    result.warnings = warnings + result.warnings
    result.events = events + result.events
    result.config["resolved"]["modes"] = {"lever_arm": eff.lever_arm.mode, "time_offset": eff.time_offset.mode}
    if opts.smoother == "forward_backward":
        from uwbimu.estimation.smoother import smooth_result

        result = smooth_result(result, dataset, eff, info, prob.gain_mask, run_eskf)
        cpu_filter += (result.extra.get("forward_backward") or {}).get("backward_filter_cpu_seconds", 0.0)
    result.runtime_s = time.perf_counter() - t_wall
    result.extra["filter_cpu_seconds"] = cpu_filter
    result.extra["init_cpu_seconds"] = f.init_cpu_seconds
    for key, value in noise_used(noise_report, info).items():
        result.calibration[key] = value
    result.extra["total_cpu_seconds"] = time.process_time() - cpu0
    # The library stays silent: warnings travel in result.warnings / result.events and the
    # caller (the CLI, a study) decides what to show.
    return result



def _finish(dataset: Dataset, f: Eskf, info: dict[str, Any], priors: dict[str, Any], eff: EskfOptions,
            noise_report: dict[str, Any]) -> EstimationResult:
    """A finished filter run turned into a result with noise events, variance factor and verdicts."""
    if f.initial is None:
        raise InitialisationError(f._init_failure or "not enough data to initialise")
    prob = f.problem()
    w_noise, e_noise = noise_events(noise_report, float(prob.uwb_t[0]))
    result = _assemble(dataset, prob, info, f.passes(), eff)
    result.extra["noise"] = noise_report
    apply_variance_factor(result, prob, f.passes(), eff, f.initial.P)
    _add_time_offset_verdict(result, prob, priors, eff, f.initial)
    # what the filter itself said comes before the diagnostics in the lists
    result.warnings = f.warnings() + w_noise + result.warnings
    result.events = f.events() + e_noise + result.events
    return result


def _filter_pass(prob: Problem, priors: dict[str, Any], opts: EskfOptions, initial: Optional[InitialState],
                 cb) -> tuple[Eskf, float]:
    """One run of the streaming filter over the whole log; returns it and its filter CPU seconds."""
    f = Eskf.from_problem(prob, priors, opts, record=True, initial=initial)
    # the first numba call of a process starts numba's runtime (about 0.1 s of CPU): process start-up, not
    # filter work (it stays in total_cpu_seconds)
    K.robust_weight(0.0, K.ROBUST_NONE, 1.0)
    c0 = time.process_time()
    f.feed(prob.imu_t, prob.imu_u, prob.uwb_t, prob.uwb_a,
           prob.uwb_b if prob.uwb_b is not None else np.full(len(prob.uwb_t), -1, dtype=np.int64), prob.uwb_r,
           prob.uwb_tag)
    f.finish(progress=cb)
    # the filter passes only: the initialiser's hypothesis bank runs inside feed/finish too
    return f, time.process_time() - c0 - f.init_cpu_seconds


def _add_time_offset_verdict(result: EstimationResult, prob: Problem, priors: dict[str, Any],
                             opts: EskfOptions, initial: InitialState) -> None:
    """Verdicts on the calibration: ``time_offset_verdict`` (+ reason) and ``lever_arm_verdict`` per axis.

    One rule for both estimators (:func:`.timeoffset.information_verdict`: the information gain of the
    data over the prior, with the reported sigma, i.e. after the residual variance factor), plus one
    check of the time offset against the log itself: when the filter's final t_d and the initial grid
    search's (the likelihood profile over the first seconds of motion) differ by more than 3 combined
    sigma, the log does not agree on t_d and the verdict is "not identified".
    """
    cal = result.calibration
    sd_prior = time_offset_prior_sd(priors, opts)
    init_status = (initial.info.get("time_offset_init") or {}).get("status")
    verdict, reason = time_offset_verdict(cal["time_offset_sd"], sd_prior, fixed=opts.time_offset.mode == "fixed",
                                          init_status=init_status)
    grid = initial.info.get("time_offset_grid") or {}
    z_grid = None
    if verdict in ("identified", "weakly identified") and grid.get("status") == "found":
        sd_c = math.hypot(cal["time_offset_sd"], float(grid["time_offset_sd"]))
        z_grid = abs(cal["time_offset"] - float(grid["time_offset"])) / sd_c if sd_c > 0 else float("inf")
        if z_grid > 3.0:
            verdict = "not identified"
            reason = (f"the filter's t_d {cal['time_offset'] * 1e3:.0f} ms contradicts the initial search's "
                      f"{float(grid['time_offset']) * 1e3:.0f} ± {float(grid['time_offset_sd']) * 1e3:.0f} ms ({z_grid:.1f} combined sd): "
                      f"the log does not agree on it")
    cal["time_offset_verdict"] = verdict
    cal["time_offset_verdict_reason"] = reason
    cal["time_offset_prior_sd"] = sd_prior
    result.events.append({"t": float(prob.uwb_t[0]), "kind": "time_offset_verdict", "verdict": verdict,
                          "reason": reason, "initial_search": init_status, "prior_sd": sd_prior,
                          "z_initial_search": z_grid})
    if verdict == "not identified":
        result.warnings.append(f"time offset not identified: {reason}")
    # lever arm, per axis, by the same information rule
    if opts.lever_arm.mode != "fixed":
        prior = np.asarray(priors.lever_sd, dtype=float).reshape(-1)
        lv = {}
        for i, c in enumerate("xyz"):
            v, gain = information_verdict(float(cal["lever_arm_sd"][i]), float(prior[i % prior.size]))
            lv[c] = {"verdict": v, "information_gain": gain, "sd": float(cal["lever_arm_sd"][i]),
                     "prior_sd": float(prior[i % prior.size])}
        cal["lever_arm_verdict"] = {c: e["verdict"] for c, e in lv.items()}
        result.events.append({"t": float(prob.uwb_t[0]), "kind": "lever_arm_verdict", "axes": lv})


def _assemble(ds: Dataset, prob: Problem, info: dict[str, Any], passes: list[PassResult],
              opts: EskfOptions) -> EstimationResult:
    """Concatenate the passes into an :class:`EstimationResult` and add diagnostics."""
    warnings: list[str] = []
    events: list[dict[str, Any]] = []
    t_imu = np.concatenate([p.t_imu for p in passes])
    X = np.concatenate([p.states for p in passes])
    D = np.concatenate([p.cov_diag for p in passes])
    covs = np.concatenate([p.covs for p in passes]) if opts.store_covariance else None
    # keep outputs strictly increasing in time (a re-initialisation restarts a bit later)
    keep = np.concatenate([[True], np.diff(t_imu) > 0]) if len(t_imu) else np.zeros(0, bool)
    t_imu, X, D = t_imu[keep], X[keep], D[keep]
    if covs is not None:
        covs = covs[keep]
    L = prob.state_layout()
    nb = L.n_anchor_bias
    t_out = t_imu - X[:, S.TD]
    fixed_err = fixed_components(L, opts)  # blocks whose declared mode option is "fixed"
    fixed = fixed_err[:S.ERROR_DIM]
    sd = np.sqrt(np.clip(D[:, :S.ERROR_DIM], 0, None))
    sd[:, fixed] = np.nan

    # per-range records
    m = len(prob.uwb_t)
    rec = np.full((m, 7), np.nan)
    rec[:, REC_STATUS] = STATUS_NOT_PROCESSED
    rec[:, REC_ACC] = 0.0
    for p in passes:
        rec[p.j0:p.j_end] = p.rec
    processed = rec[:, REC_STATUS] == K.UPD_OK
    residuals = pd.DataFrame({
        "t": prob.uwb_t,
        "anchor": info["uwb_anchor_ids"],
        "range": prob.uwb_r,
        "predicted": rec[:, REC_PRED],
        "innovation": rec[:, REC_INNOV],
        "nis": rec[:, REC_NIS],
        "accepted": rec[:, REC_ACC] > 0,
    })
    if prob.uwb_b is not None and bool(np.any(prob.uwb_b >= 0)):
        # TDoA rows: "anchor" is anchor_a, "range" the measured TDoA [m]; consumers that need ranges keep
        # the rows whose kind is "range"
        is_td = prob.uwb_b >= 0
        residuals["kind"] = np.where(is_td, "tdoa", "range")
        residuals["anchor_b"] = np.where(is_td, np.array(prob.anchor_ids, dtype=object)[np.maximum(prob.uwb_b, 0)], "")
    if prob.tag_names and prob.uwb_tag is not None:
        residuals["tag"] = np.array(prob.tag_names, dtype=object)[prob.uwb_tag]
    n_gap = int((rec[:, REC_STATUS] == STATUS_IN_GAP).sum())
    n_frozen = sum(p.n_lever_frozen for p in passes)
    n_acc = int((rec[:, REC_ACC] > 0).sum())
    if n_frozen:
        warnings.append(
            f"lever arm: not updated by {n_frozen} of {n_acc} accepted ranges ({100 * n_frozen / max(n_acc, 1):.0f}%) "
            f"because the body hardly rotated (RMS gyro rate below lever_arm.min_rotation_rate = "
            f"{opts.lever_arm.min_rotation_rate:g} rad/s over {opts.excitation.window_s:g} s); its sd keeps the prior there")
        events.append({"t": float(prob.uwb_t[0]), "kind": "lever_arm_not_updated", "ranges": int(n_frozen),
                       "accepted_ranges": n_acc, "min_rotation_rate": float(opts.lever_arm.min_rotation_rate)})
    n_unproc = int((~processed).sum()) - n_gap
    if n_gap:
        warnings.append(f"UWB: {n_gap} ranges fall inside IMU gaps (motion unknown) and were not used; "
                        f"kept in residuals with accepted=false")
    if n_unproc:
        warnings.append(f"UWB: {n_unproc} of {m} ranges not processed (before initialisation, outside the IMU "
                        f"log, or older than max_lookback_s); kept in residuals with accepted=false")
    n_rej = int((processed & (rec[:, REC_ACC] == 0)).sum())
    if processed.any() and n_rej / processed.sum() > 0.1:
        warnings.append(f"UWB: {100 * n_rej / processed.sum():.1f}% of the processed ranges rejected by the gate")

    # final filter state (all data used), not the last output row
    x_end = passes[-1].x
    sd_end = np.sqrt(np.clip(np.diag(passes[-1].P), 0, None))
    noise = info["imu_noise"]
    # one entry per declared block (models/blocks.py), the per-tag lever arms after the base blocks
    fixed_lever = bool(fixed_err[S.EPIU.start])
    names = [str(info["tag"] or "tag0")] + [str(n) for n in prob.tag_names[1:]]
    tags = {name: {"lever_arm": [float(v) for v in x_end[L.lever_nom(i)]],
                   "lever_arm_sd": [float(v) if not fixed_lever else 0.0 for v in sd_end[L.lever_err(i)]]}
            for i, name in enumerate(names)}
    calibration = block_calibration(L, x_end, sd_end, opts, prob.anchor_ids, prob.pair_index, tags)

    # diagnostics: excitation, outages
    w_exc, e_exc = excitation_warnings(prob, t_imu, X, sd, info["priors"], opts)
    warnings += w_exc
    events += e_exc
    w_out, e_out = outage_warnings(prob, rec, opts)
    warnings += w_out
    events += e_out

    if info["anchor_frame_up"] == "-z":
        X, covs = flip_outputs(X, covs)
        events.append({"t": float(prob.uwb_t[0]), "kind": "anchor_frame_flipped",
                       "note": "anchor_frame_up: -z; the filter ran in the anchors' frame turned 180 deg about x "
                       "(positions in the 'initialised' events are in that frame); outputs are in the anchors' frame"})
    cfg = opts.model_dump(mode="json")
    cfg["resolved"] = {"imu_noise": noise.model_dump(), "range_sigma": float(info["range_sigma"]),
                       "tag": info["tag"], "anchor_frame_up": info["anchor_frame_up"], "gate_nis": float(prob.gate), "imu_rate_hz": 1.0 / prob.dt_nom}
    res = EstimationResult(
        t=t_out, states=X[:, :S.NOMINAL_DIM].copy(), sd=sd, residuals=residuals, calibration=calibration,
        covariances=covs[:, :S.ERROR_DIM, :S.ERROR_DIM].copy() if covs is not None else None, warnings=warnings, events=events,
        estimator="eskf", config=cfg, t_imu=t_imu,
    )
    if nb:
        res.extra["anchor_bias_states"] = X[:, L.nom("anchor_bias")].copy()
        res.extra["anchor_ids"] = list(prob.anchor_ids)
    return res
