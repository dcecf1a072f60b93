"""The ESKF's passes over the noise: what the log says of its own noise, applied to a finished run.

Helpers of :func:`uwbimu.estimation.eskf.run_eskf` for the rules of :mod:`.noise_from_data`: covariance
matching of a pass's innovations (rule 2), the residual variance factor on the calibration sigmas
(rule 3), the lever arm held when the log does not identify it, and what calibration.yaml reports of
the noise used.
"""

from __future__ import annotations

import math
from typing import Any, Optional

import numpy as np

from uwbimu.estimation import kernels as K
from uwbimu.estimation.filterpass import REC_ACC, REC_INNOV, REC_S, REC_STATUS, PassResult, Problem
from uwbimu.estimation.noise_from_data import measurement_noise_from_innovations, residual_variance_factor
from uwbimu.estimation.options import EskfOptions
from uwbimu.estimation.result import EstimationResult
from uwbimu.models import state as S

#: a noise level this many times the preset's (or below its inverse) is reported as a warning
FAR_FROM_PRESET = 3.0


def accepted_records(prob: Problem, passes: list[PassResult]) -> tuple[np.ndarray, np.ndarray]:
    """Per-measurement records of all passes (NaN rows where not processed) and the accepted mask."""
    rec = np.full((len(prob.uwb_t), 7), np.nan)
    for p in passes:
        rec[p.j0:p.j_end] = p.rec
    acc = (rec[:, REC_ACC] > 0) & (rec[:, REC_STATUS] == K.UPD_OK)
    return rec, acc


def match_measurement_noise(prob: Problem, passes: list[PassResult], info: dict[str, Any],
                             opts: EskfOptions, statistic: str = "robust") -> dict[str, Any]:
    """Rule 2 of :mod:`.noise_from_data` per measurement kind (a kind whose sd the options give is kept).

    ``statistic="robust"`` matches the accepted measurements' core; ``"mean_square"`` every processed
    measurement, accepted by the gate or not (the tails included: a sigma fitted to the accepted ones
    would confirm itself), for a pass whose sigma already came from the robust step."""
    rec, acc = accepted_records(prob, passes)
    processed = np.isfinite(rec[:, REC_INNOV]) & np.isfinite(rec[:, REC_S]) & (rec[:, REC_STATUS] == K.UPD_OK)
    use = acc if statistic == "robust" else processed
    is_td = (prob.uwb_b >= 0) if prob.uwb_b is not None else np.zeros(len(prob.uwb_t), bool)
    rsig = float(info["range_sigma"])
    tsig = float(info.get("tdoa_sigma") or math.sqrt(2.0) * rsig)
    out: dict[str, Any] = {}
    for kind, mask, sig, given in (("range", ~is_td, rsig, opts.range_sigma is not None),
                                   ("tdoa", is_td, tsig, opts.tdoa_sigma is not None)):
        sel = mask & use
        if not mask.any():
            continue
        if given:
            out[kind] = {"n": int(sel.sum()), "sigma": sig, "sigma_new": sig, "changed": False, "given": True}
            continue
        r = measurement_noise_from_innovations(rec[sel, REC_INNOV], rec[sel, REC_S], sig, statistic=statistic)
        r["rejected_fraction"] = float(1.0 - (mask & acc).sum() / max(int((mask & np.isfinite(rec[:, REC_INNOV])).sum()), 1))
        out[kind] = r
    return out


def noise_events(report: dict[str, Any], t0: float) -> tuple[list[str], list[dict[str, Any]]]:
    """One ``noise_from_data`` event with what was used, and a warning when the log is far from the preset."""
    warnings: list[str] = []
    if report.get("mode") != "data":
        return warnings, []
    imu = report.get("imu", {})
    for sensor, unit in (("accel", "m/s^2/sqrt(Hz)"), ("gyro", "rad/s/sqrt(Hz)")):
        e = imu.get(sensor)
        if e and e["ratio"] > FAR_FROM_PRESET:
            warnings.append(f"IMU: the log's {sensor} noise density {e['log']:.3g} {unit} (5-25 Hz spectrum) is "
                            f"{e['ratio']:.0f} x the preset's {e['preset']:.3g}: vibration; the filter uses the log's")
    for kind, e in (report.get("measurements") or {}).items():
        if e.get("changed") and not (1.0 / FAR_FROM_PRESET <= e["sigma_new"] / e["sigma"] <= FAR_FROM_PRESET):
            warnings.append(f"UWB: the {kind} innovations ask for sd {e['sigma_new']:.3g} m against the "
                            f"{e['sigma']:.3g} m configured; the filter was rerun with it")
    return warnings, [{"t": t0, "kind": "noise_from_data", **report}]


def apply_variance_factor(result: EstimationResult, prob: Problem, passes: list[PassResult], opts: EskfOptions,
                           P0: Optional[np.ndarray] = None) -> None:
    """Rule 3 of :mod:`.noise_from_data`: the calibration sds grow with the residuals' long-run variance."""
    rec, acc = accepted_records(prob, passes)
    innov, rec_s = rec[:, REC_INNOV], rec[:, REC_S]
    a = prob.uwb_a
    b = prob.uwb_b if prob.uwb_b is not None else np.full(len(a), -1)
    channel = a * 1000 + (b + 1)
    vf = residual_variance_factor(innov[acc], rec_s[acc], channel[acc])
    vf["enabled"] = bool(opts.sigma_from_residuals)
    cal = result.calibration
    cal["sigma_scale"] = float(vf["factor"]) if opts.sigma_from_residuals else 1.0
    result.extra["residual_variance_factor"] = vf
    fac = cal["sigma_scale"]
    if fac != 1.0:
        # the data's share of the information is divided by fac^2, the prior's kept:
        # 1/sd'^2 = 1/sd0^2 + (1/sd^2 - 1/sd0^2) / fac^2 (sd0 the filter's initial sd of the state);
        # a state held at its prior (no information from the data) keeps its sd
        sd0 = np.sqrt(np.clip(np.diag(P0), 0, None)) if P0 is not None else None

        def grow(sd: float, i: int) -> float:
            if sd <= 0 or sd0 is None or not (0 < sd < sd0[i]):
                return sd if sd0 is not None else sd * fac
            info = 1.0 / sd0[i] ** 2 + (1.0 / sd**2 - 1.0 / sd0[i] ** 2) / fac**2
            return float(1.0 / math.sqrt(info))

        L = prob.state_layout()
        cal["lever_arm_sd_filter"] = list(cal["lever_arm_sd"])
        cal["time_offset_sd_filter"] = cal["time_offset_sd"]
        cal["lever_arm_sd"] = [grow(v, S.EPIU.start + k) for k, v in enumerate(cal["lever_arm_sd"])]
        cal["time_offset_sd"] = grow(cal["time_offset_sd"], S.ETD)
        for t_i, tb in enumerate(cal.get("tags", {}).values()):
            idx = range(L.lever_err(t_i).start, L.lever_err(t_i).stop)
            tb["lever_arm_sd"] = [grow(v, i) for v, i in zip(tb["lever_arm_sd"], idx)]
        if "anchor_bias_sd" in cal:
            i0 = L.err("anchor_bias").start
            cal["anchor_bias_sd"] = {k: grow(v, i0 + i) for i, (k, v) in enumerate(cal["anchor_bias_sd"].items())}
        if "tdoa_pair_bias_sd" in cal and prob.pair_index:
            cal["tdoa_pair_bias_sd"] = {k: grow(v, i) for (k, v), i in
                                        zip(cal["tdoa_pair_bias_sd"].items(), prob.pair_index.values())}
        result.warnings.append(
            f"the residuals' long-run variance is {vf['long_run_variance']:.3g} (1 when they agree with the "
            f"noise model; 99 % bound {vf['threshold']:.3g}): the data's information on the calibration "
            f"divided by {fac**2:.3g} (sds up to {fac:.3g} x)")
    result.events.append({"t": float(prob.uwb_t[0]), "kind": "sigma_from_residuals", **vf})


def unidentified_blocks(result: EstimationResult, eff: EskfOptions) -> dict[str, Any]:
    """Option updates that hold the lever arm in consider mode when the log identifies none of its axes and its
    residuals refute the noise model."""
    cal = result.calibration
    held: dict[str, Any] = {}
    lv = cal.get("lever_arm_verdict")
    # both conditions: none of its axes identified, and residuals that refute the noise model (the variance
    # factor applied), so that unmodelled errors are there to be absorbed; a clean log keeps its estimate
    refuted = cal.get("sigma_scale", 1.0) > 1.0
    if eff.lever_arm.mode == "estimate" and refuted and lv and not any(v == "identified" for v in lv.values()):
        held["lever_arm"] = eff.lever_arm.model_copy(update={"mode": "consider"})
    # the time offset is not held: its value in consider mode would be the initial search's, which is the
    # least reliable of its estimates on the logs where the filter's t_d is not identified (INRoL: -589 ms)
    return held


def noise_used(report: dict[str, Any], info: dict[str, Any]) -> dict[str, Any]:
    """calibration.yaml ``imu_noise`` and ``measurement_noise``: the noise the final pass used, and whence."""
    n = info["imu_noise"]
    imu = report.get("imu", {})
    src = "log" if imu.get("status") == "measured" else ("given" if imu.get("status") == "given" else "preset")
    out_imu = {"accel_noise_density": n.accel_noise_density, "gyro_noise_density": n.gyro_noise_density,
               "accel_bias_rw": n.accel_bias_rw, "gyro_bias_rw": n.gyro_bias_rw, "source": src}
    if src == "log":
        out_imu.update({"ratio_to_preset": {"accel": imu["accel"]["ratio"], "gyro": imu["gyro"]["ratio"]},
                        "preset": {"accel_noise_density": imu["accel"]["preset"],
                                   "gyro_noise_density": imu["gyro"]["preset"]},
                        "band_hz": imu["band_hz"]})
    meas = {}
    for kind, key in (("range", "range_sigma"), ("tdoa", "tdoa_sigma")):
        m = (report.get("measurements") or {}).get(kind)
        if m is None:
            continue
        meas[kind] = {"sigma": float(info[key] if info.get(key) is not None else m["sigma_new"]),
                      "source": "given" if m.get("given") else ("log" if m.get("changed") else "preset"),
                      "robust_variance_ratio": m.get("k"), "rejected_fraction": m.get("rejected_fraction")}
        lk = m.get("likelihood")
        if m.get("changed"):
            # how the log's level was found: matching alone, or then the predictive likelihood (noise_search)
            meas[kind]["method"] = "predictive_likelihood" if lk else "covariance_matching"
        if lk:
            meas[kind]["outlier_fraction"] = lk["outlier_fraction"]
    if not meas:
        meas["range"] = {"sigma": float(info["range_sigma"]), "source": "preset"}
    return {"imu_noise": out_imu, "measurement_noise": meas}
