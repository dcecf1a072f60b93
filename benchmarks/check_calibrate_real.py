"""Batch calibration on a shared real sequence: accuracy, t_d verdict, repeatability, CPU time.

    python benchmarks/check_calibrate_real.py DATASET --kind inrol|isas [--config calibrate.yaml]
        [--noise-from-preset] [--windows 4] [--no-full] [--no-repeatability] [--json OUT.json]

DATASET: an imported folder (``uwbimu import inrol ../shared/datasets/inrol_uwb_imu DIR`` or
``uwbimu import isas-walk ../shared/datasets/isas_walk DIR``).  The ESKF that initialises the graph
runs with the shipped real-data preset (``examples/estimator_real.yaml`` for INRoL,
``examples/estimator_isas.yaml`` for ISAS-Walk); ``--config`` is the calibrator's options (default:
the defaults, i.e. white range noise); ``--noise-from-preset`` adds the preset's noise model (its
white ``range_sigma``, its Gauss-Markov anchor bias as ``range_bias_drift``, its IMU densities).  Printed, all measured in this run:

* full log: CPU seconds of ``calibrate`` (``time.process_time``, this process, one core; the
  initialising ESKF included) and wall seconds; lever arm ± sigma vs the documented value; t_d
  with its verdict and both sigmas; ATE (RMS position error; INRoL ``align none``, ISAS-Walk ``se3``
  as its ground truth is the Vive tracker in the Vive frame) of the batch-smoothed trajectory, of
  the ESKF and of epoch-wise multilateration (``uwbimu.eval.baseline.multilaterate``); per-anchor
  residual median and MAD;
* repeatability: the log cut into ``--windows`` windows, each calibrated with the same options, the
  spread of lever arm and t_d tested against the reported sigmas (``uwbimu.eval.repeatability``,
  chi-square at the 1 % level).  A window whose t_d is held at its prior has no t_d sigma and is
  left out of the t_d test (counted).

Nothing is hard-coded; state the machine load (``uptime``) next to the figures.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
PRESET = {"inrol": REPO / "examples" / "estimator_real.yaml", "isas": REPO / "examples" / "estimator_isas.yaml"}
ALIGN = {"inrol": "none", "isas": "se3"}
EPOCH = {"inrol": 0.1, "isas": 0.0}  # as benchmarks/real_data.py


def options_from_eskf_preset(path: Path, base: dict | None = None):
    """CalibrationOptions with the noise model of a shipped ESKF preset: its white ``range_sigma``, its
    Gauss-Markov anchor bias (``anchor_bias.prior_sd``, ``correlation_time``) as ``range_bias_drift`` and its
    IMU densities when it sets them.  Nothing is fitted here; the preset documents where its values come from."""
    import yaml

    from uwbimu.calibration import CalibrationOptions

    pre = yaml.safe_load(Path(path).read_text()) or {}
    d = dict(base or {})
    if "range_sigma" in pre:
        d["range_sigma"] = float(pre["range_sigma"])
    ab = pre.get("anchor_bias") or {}
    if ab.get("mode") == "estimate" and ab.get("correlation_time"):
        d["range_bias_drift"] = {"sd": float(ab["prior_sd"]), "correlation_time": float(ab["correlation_time"])}
    for k in ("accel_noise_density", "gyro_noise_density", "accel_bias_rw", "gyro_bias_rw"):
        if k in (pre.get("imu_noise") or {}):
            d[k] = float(pre["imu_noise"][k])
    return CalibrationOptions.model_validate(d)


def flat_calibration(res) -> dict:
    """The batch result's calibration in the flat form :mod:`uwbimu.eval.repeatability` reads."""
    c = res.calibration
    td = c["time_offset"]
    return {"lever_arm": c["lever_arm"], "lever_arm_sd": c["lever_arm_sd"], "time_offset": td["value"],
            "time_offset_sd": td["sd"], "verdict": td["verdict"]}


def _ate(traj, ds, align: str) -> float:
    from uwbimu.metrics.trajectory import evaluate_trajectory

    ev = evaluate_trajectory(traj, ds.groundtruth, align=align, compare_attitude=(align == "none"))
    return float(ev.summary["ate_position"]["rmse"])


def full_log(ds, kind: str, opts, eo, save_dir=None) -> dict:
    import pandas as pd

    from uwbimu.calibration import calibrate
    from uwbimu.eval.baseline import multilaterate

    c0, w0 = time.process_time(), time.perf_counter()
    res = calibrate(ds, opts, eskf_options=eo)
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    c = res.calibration
    td = c["time_offset"]
    e = res.eskf
    eskf_traj = pd.DataFrame({"t": e.t, "px": e.states[:, 0], "py": e.states[:, 1], "pz": e.states[:, 2]})
    ml = multilaterate(ds, epoch_s=EPOCH[kind])
    r = res.residuals
    if save_dir is not None:
        Path(save_dir).mkdir(parents=True, exist_ok=True)
        r.to_csv(Path(save_dir) / "residuals.csv", index=False)
        res.trajectory.to_csv(Path(save_dir) / "trajectory.csv", index=False)
    # "before" the range model: the residual without the estimated constant bias, slowly varying bias and
    # direction terms (each already inside "predicted")
    from uwbimu.calibration.outputs import residual_without

    r = r.assign(residual_before=residual_without(r, {str(k): v for k, v in c["anchor_bias"].items()}))

    def _mad(x):
        return 100 * float(np.median(np.abs(x - np.median(x))))

    per_anchor = {str(a): {"median_cm": 100 * float(np.median(g.residual)), "mad_cm": _mad(g.residual),
                           "median_before_cm": 100 * float(np.median(g.residual_before)),
                           "mad_before_cm": _mad(g.residual_before), "n": int(len(g))}
                  for a, g in r.groupby("anchor")}
    out = {"cpu_s": cpu, "wall_s": wall, "n_ranges": int(c["ranges"]["used"]), "keyframes": c["solver"]["keyframes"],
           "lever_arm": c["lever_arm"], "lever_arm_sd": c["lever_arm_sd"],
           "documented_lever_arm": list(ds.meta.truth.lever_arm) if ds.meta.truth and ds.meta.truth.lever_arm else None,
           "td": td, "anchor_bias": c["anchor_bias"], "anchor_bias_sd": c["anchor_bias_sd"],
           "ate_batch": _ate(res.trajectory, ds, ALIGN[kind]), "ate_eskf": _ate(eskf_traj, ds, ALIGN[kind]),
           "ate_multilateration": _ate(ml, ds, ALIGN[kind]), "eskf_lever_arm": e.calibration["lever_arm"],
           "eskf_lever_arm_sd": e.calibration["lever_arm_sd"], "eskf_td": e.calibration["time_offset"],
           "eskf_td_sd": e.calibration["time_offset_sd"], "residuals_per_anchor": per_anchor,
           "downweighted": c["ranges"]["downweighted"], "expected_downweighted": c["ranges"]["expected_downweighted"]}
    out["imu_noise_scale"] = c["imu_noise"]["scale"]
    out["huber"] = {k: v for k, v in c["range_model"]["huber"].items() if k not in ("grid", "variance_factor")}
    out["direction"] = direction_table(res, ds)
    out["range_model_direction"] = c["range_model"].get("direction")
    if save_dir is not None:
        import yaml

        (Path(save_dir) / "calibration.yaml").write_text(yaml.safe_dump(c, sort_keys=False))
    if res.profile is not None:
        out["profile"] = {"grid": [float(x) for x in res.profile.grid],
                          "delta_chi2": [float(x) for x in res.profile.chi2 - np.nanmin(res.profile.chi2)]}
    return out


def direction_table(res, ds, bins: int = 8) -> dict:
    """Residual against the line of sight, per anchor: what a constant bias (+ drift) leaves.

    For every range the unit line of sight anchor -> tag from the batch-smoothed trajectory (no ground
    truth): its azimuth in the world frame (seen from the anchor) and its azimuth in the IMU body frame
    (seen from the tag antenna).  Per anchor and per ``bins`` azimuth sectors: the median residual
    [cm] (sectors with >= 30 ranges; with ``range_bias_drift`` the residual plus the row's slowly
    varying bias, i.e. what the constant bias leaves); ``spread`` = max - min of those medians; ``r2`` = share of the
    residual variance explained by the sector medians.  Also the residuals' autocorrelation at 1 s lag.
    """
    from scipy.spatial.transform import Rotation, Slerp

    r = res.residuals
    tr = res.trajectory
    t = r["t"].to_numpy(float)
    P = np.column_stack([np.interp(t, tr.t, tr[c]) for c in ("px", "py", "pz")])
    q = tr[["qx", "qy", "qz", "qw"]].to_numpy(float)
    rot = Slerp(tr.t.to_numpy(float), Rotation.from_quat(q))(np.clip(t, tr.t.iloc[0], tr.t.iloc[-1]))
    pos = res.anchors.set_index("anchor")[["x", "y", "z"]]
    A = pos.loc[r["anchor"].astype(str)].to_numpy(float)
    los = P + rot.apply(np.asarray(res.calibration["lever_arm"])) - A
    los /= np.linalg.norm(los, axis=1, keepdims=True)
    body = rot.inv().apply(-los)  # tag -> anchor, IMU frame
    az_w = np.degrees(np.arctan2(los[:, 1], los[:, 0]))
    az_b = np.degrees(np.arctan2(body[:, 1], body[:, 0]))
    e = r["residual"].to_numpy(float)
    if "bias_drift" in r.columns:
        e = e + r["bias_drift"].to_numpy(float)  # the correlated part is what this table is about
    out = {}
    edges = np.linspace(-180, 180, bins + 1)
    for a in sorted(r["anchor"].astype(str).unique(), key=str):
        m = (r["anchor"].astype(str) == a).to_numpy()
        row = {}
        for name, az in (("world_azimuth", az_w), ("body_azimuth", az_b)):
            sec = np.clip(np.digitize(az[m], edges) - 1, 0, bins - 1)
            med = np.full(bins, np.nan)
            for b in range(bins):
                if np.sum(sec == b) >= 30:
                    med[b] = np.median(e[m][sec == b])
            fit = np.where(np.isfinite(med[sec]), med[sec], np.median(e[m]))
            r2 = 1.0 - np.var(e[m] - fit) / np.var(e[m])
            row[name] = {"median_cm": [None if not np.isfinite(x) else round(100 * float(x), 1) for x in med],
                         "spread_cm": (100 * float(np.nanmax(med) - np.nanmin(med)) if np.isfinite(med).sum() >= 2
                                       else float("nan")), "r2": float(r2)}
        ta, ea = t[m], e[m]
        j = np.searchsorted(ta, ta + 1.0)
        ok = j < len(ta)
        row["autocorr_1s"] = float(np.corrcoef(ea[ok], ea[j[ok]])[0, 1]) if ok.sum() > 10 else float("nan")
        out[a] = row
    return out


def windows(ds, opts, eo, k: int) -> dict:
    from uwbimu.calibration import calibrate
    from uwbimu.eval.repeatability import repeatability

    c0 = time.process_time()
    scales = []

    def one(w):
        res = calibrate(w, opts, eskf_options=eo)
        scales.append(res.calibration["imu_noise"]["scale"])
        return flat_calibration(res)

    rep = repeatability(ds, k, one, level=0.01)
    rep["cpu_s"] = time.process_time() - c0
    rep["imu_noise_scale"] = scales
    return rep


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("--kind", choices=sorted(PRESET), required=True)
    ap.add_argument("--config", help="calibrate.yaml (CalibrationOptions)")
    ap.add_argument("--noise-from-preset", action="store_true",
                    help="range/IMU noise model of the ESKF preset (white part + Gauss-Markov drift), on top of --config")
    ap.add_argument("--windows", type=int, default=4)
    ap.add_argument("--no-full", action="store_true")
    ap.add_argument("--no-repeatability", action="store_true")
    ap.add_argument("--json", help="write every figure to this JSON file")
    ap.add_argument("--save-dir", help="also write the full-log residuals.csv and trajectory.csv here")
    a = ap.parse_args(argv)

    from uwbimu.calibration import CalibrationOptions
    from uwbimu.estimation import EskfOptions
    from uwbimu.io.loader import load_dataset

    ds = load_dataset(a.dataset)
    opts = CalibrationOptions.from_yaml(a.config) if a.config else CalibrationOptions()
    if a.noise_from_preset:
        opts = options_from_eskf_preset(PRESET[a.kind], opts.model_dump(exclude_unset=True))
    eo = EskfOptions.from_yaml(PRESET[a.kind])
    report = {"dataset": a.dataset, "kind": a.kind, "config": a.config, "options": opts.model_dump(exclude_unset=True),
              "load_before": os.getloadavg()}
    print(f"options: {report['options']}")
    if not a.no_full:
        f = full_log(ds, a.kind, opts, eo, a.save_dir)
        report["full"] = f
        td = f["td"]
        sdc = "-" if td["sd_curvature"] is None else f"{1000 * td['sd_curvature']:.1f}"
        sdm = "-" if td["sd_marginal"] is None else f"{1000 * td['sd_marginal']:.1f}"
        print(f"full log: {f['n_ranges']} ranges, {f['keyframes']} keyframes, calibrate {f['cpu_s']:.0f} s CPU, "
              f"{f['wall_s']:.0f} s wall")
        print(f"  lever arm [cm] {np.round(100 * np.array(f['lever_arm']), 1)} +/- "
              f"{np.round(100 * np.array(f['lever_arm_sd']), 1)} (documented {f['documented_lever_arm']})")
        print(f"  t_d {1000 * td['value']:.1f} ms, verdict {td['verdict']}, sd marginal {sdm} ms, curvature {sdc} ms")
        print(f"  ATE batch {f['ate_batch']:.3f} m, ESKF {f['ate_eskf']:.3f} m, multilateration "
              f"{f['ate_multilateration']:.3f} m ({ALIGN[a.kind]})")
        sc_ = f["imu_noise_scale"]
        print(f"  IMU noise scale {sc_.get('scale', 1.0):.2f}" + (f" +/- {sc_['scale_sd']:.2f} (chi2 {sc_['chi2']:.0f}, "
              f"redundancy {sc_['redundancy']:.0f}, {sc_['steps']} steps)" if sc_.get("scale_sd") else
              f" ({sc_['method']})"))
        h = f["huber"]
        print(f"  Huber threshold {h['k']:.2f} sigma ({h['selection']}"
              + (f"; minimiser {h['k_min']:.2f}, robust scale {h['robust_scale']:.2f}, variance x "
                 f"{h['variance_vs_start']:.2f} of 1.345's, x {h['variance_vs_least_squares']:.2f} of least squares"
                 if h["selection"] == "adaptive" else "")
              + f"), {f['downweighted']} rows down-weighted ({f['expected_downweighted']:.0f} if Gaussian)")
        print("  residual median / MAD per anchor [cm], before -> after the range model: " + ", ".join(
            f"{k}: {v['median_before_cm']:+.1f}/{v['mad_before_cm']:.1f} -> {v['median_cm']:+.1f}/{v['mad_cm']:.1f}"
            for k, v in f["residuals_per_anchor"].items()))
        print("  residual vs line of sight per anchor (spread of 45-deg sector medians [cm], share of variance; "
              "autocorrelation at 1 s):")
        dm = f.get("range_model_direction")
        if dm:
            print("  direction model coefficients [cm or cm/rad] +/- sd: " + "; ".join(
                f"{lab}: " + ", ".join(f"{n} {100 * x['value']:+.1f}+/-{100 * x['sd']:.1f}" for n, x in cs.items())
                for lab, cs in dm["coefficients"].items()))
        for k, v in f["direction"].items():
            print(f"    {k}: world azimuth {v['world_azimuth']['spread_cm']:.1f} cm ({v['world_azimuth']['r2']:.2f}), "
                  f"body azimuth {v['body_azimuth']['spread_cm']:.1f} cm ({v['body_azimuth']['r2']:.2f}), "
                  f"autocorr {v['autocorr_1s']:.2f}")
    if not a.no_repeatability:
        rep = windows(ds, opts, eo, a.windows)
        report["repeatability"] = rep
        print(f"repeatability over {a.windows} windows of {rep['window_s']:.0f} s ({rep['cpu_s']:.0f} s CPU, "
              f"{rep['n_failed']} failed):")
        print("  IMU noise scale per window: " + ", ".join(f"{x.get('scale', 1.0):.1f}" for x in rep["imu_noise_scale"]))
        for w in rep["windows"]:
            if "error" in w:
                print(f"  window {w['i'] + 1}: {w['error']}")
        for name, p in rep["parameters"].items():
            sc = 1000.0 if name in ("time_offset", "td") else 100.0
            print(f"  {name}: mean {sc * p['mean']:.1f}, spread sd {sc * p['std']:.1f}, rms sigma "
                  f"{sc * p['rms_sd']:.1f}, ratio {p['ratio']:.2f}, p {p['p_value']:.3g}, n {p['n']}: {p['verdict']}")
    report["load_after"] = os.getloadavg()
    if a.json:
        Path(a.json).write_text(json.dumps(report, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
