"""What a range-error model could reach on a real log: oracle corrections fitted to the ground truth.

    python benchmarks/check_range_error_oracle.py DATASET [--models none,constant,...] [--epoch-s 0.1] [--json OUT.json]

Why: the batch calibrator estimates a constant range bias per anchor (optionally a slowly varying
one and a low-order direction-dependent term) from the log alone.  When the fused trajectory stays
far from the ground truth (INRoL: ATE 0.16 m against the 0.10 m goal of issue 12), is that the
estimation of the range model, or the model class itself?  This benchmark answers with oracles:
each model is fitted **to the ground-truth range residuals** (``uwbimu.io.check.range_residuals``,
measured minus the range from the ground-truth antenna position), the fitted correction is
subtracted from the ranges, and the batch calibrator (default options, t_d profile off, anchor
biases *not* estimated: the oracle already removed them) smooths the corrected log.  The ATE of
that trajectory is what a perfect estimate of that model class would give; it bounds from below
what estimating the class from the log can reach (up to the batch's own errors).

Models (per anchor, fitted robustly: rows within 5 MAD of the anchor's median):

* ``none``: the raw ranges (anchor biases not estimated either);
* ``constant``: the anchor's median residual;
* ``distance``: constant + slope in the true distance (a received-power-dependent bias);
* ``direction``: constant + the tag-side line of sight in the IMU body frame (azimuth harmonics 1-2,
  elevation and elevation^2) + the anchor-side azimuth harmonic 1 and elevation when ``anchors.csv``
  has orientations;
* ``smooth:T``: a running median of the anchor's residual over ``T`` seconds (a time-varying bias
  with that time scale: what ``range_bias_drift`` models).

Also printed per model: the ATE of epoch-wise multilateration of the corrected ranges
(``uwbimu.eval.baseline.multilaterate``) and the residual MAD left by the oracle.  The ground truth
must be in the anchors' frame (INRoL, simulated logs): the script refuses a log whose ground-truth
residuals have a median absolute value above 0.5 m (a ground truth in another frame, such as
ISAS-Walk's Vive frame).  Nothing here is used by the calibrator; it is a diagnosis.
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import time

import numpy as np


def _features(model: str, res, ds) -> np.ndarray:
    """Design matrix of one oracle model for the rows of ``res`` (``range_residuals`` output); the direction
    terms are the calibrator's own (:func:`uwbimu.calibration.range_factor.direction_features`)."""
    from uwbimu.calibration.range_factor import direction_features
    from uwbimu.io.check import interpolate_pose
    from uwbimu.models.quaternion import quat_conjugate, quat_rotate

    n = len(res)
    cols = [np.ones((n, 1))]
    A = np.array([ds.anchor_positions()[a] for a in res["anchor"]]).reshape(-1, 3)
    ant = res[["ux", "uy", "uz"]].to_numpy(float)
    d = np.linalg.norm(A - ant, axis=1)
    if model == "distance":
        cols.append(d[:, None])
    elif model == "direction":
        _, q, _ = interpolate_pose(ds.groundtruth, res["t"].to_numpy(float))
        los_body = quat_rotate(quat_conjugate(q), A - ant)  # tag -> anchor, IMU body frame
        cols.append(direction_features(los_body, (1, 2), 2)[0])
        anc = ds.anchors.set_index("anchor")
        if {"qw", "qx", "qy", "qz"} <= set(anc.columns) and anc[["qw", "qx", "qy", "qz"]].notna().all().all():
            qa = np.array([anc.loc[a, ["qw", "qx", "qy", "qz"]].to_numpy(float) for a in res["anchor"]])
            los_anchor = quat_rotate(quat_conjugate(qa), ant - A)  # anchor -> tag, anchor antenna frame
            cols.append(direction_features(los_anchor, (1,), 1)[0])
    return np.hstack(cols)


def oracle_correction(model: str, res, ds) -> np.ndarray:
    """Per-row correction (m) of ``res``'s ranges under ``model``, fitted per anchor to the residuals."""
    import pandas as pd

    if model not in ("none", "constant", "distance", "direction") and not (
            model.startswith("smooth:") and model[7:].replace(".", "", 1).isdigit() and float(model[7:]) > 0):
        raise ValueError(f"unknown oracle model {model!r}: none, constant, distance, direction or smooth:T (T > 0 s)")
    r = res["residual"].to_numpy(float)
    corr = np.zeros(len(res))
    if model == "none":
        return corr
    X = None if model == "constant" or model.startswith("smooth:") else _features(model, res, ds)
    for a, idx in res.groupby("anchor").indices.items():
        ra = r[idx]
        med = np.median(ra)
        mad = 1.4826 * np.median(np.abs(ra - med))
        ok = np.abs(ra - med) <= 5.0 * max(mad, 1e-6)
        if model == "constant":
            corr[idx] = np.median(ra[ok])
        elif model.startswith("smooth:"):
            T = float(model.split(":", 1)[1])
            s = pd.Series(np.where(ok, ra, np.nan), index=pd.to_datetime(res["t"].to_numpy(float)[idx], unit="s"))
            corr[idx] = s.rolling(f"{int(round(T * 1000))}ms", center=True, min_periods=1).median().ffill().bfill().to_numpy()
        else:
            c, *_ = np.linalg.lstsq(X[idx][ok], ra[ok], rcond=None)
            corr[idx] = X[idx] @ c
    return corr


def run(ds, models: list[str], progress=print, epoch_s: float = 0.1) -> list[dict]:
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.eval.baseline import multilaterate
    from uwbimu.io.check import range_residuals
    from check_calibrate_real import _ate

    res = range_residuals(ds)
    # each compared range's row in uwb.csv (those outside the ground truth keep a zero correction: counted)
    key = ds.uwb[["t", "anchor"]].reset_index(drop=True).reset_index()
    row_of = res[["t", "anchor"]].merge(key, on=["t", "anchor"], how="left", validate="one_to_one")["index"].to_numpy()
    progress(f"{len(res)} ranges compared with the ground truth, {res.attrs.get('n_outside', 0)} outside it (not corrected)")
    if np.median(np.abs(res["residual"])) > 0.5:
        raise SystemExit("the ground-truth range residuals have a median above 0.5 m: is the ground truth in the "
                         "anchors' frame? (this oracle needs it there)")

    def ate(traj):  # the ground truth is in the anchors' frame (checked above): no alignment
        return _ate(traj, ds, "none")

    rows = []
    for m in models:
        corr = oracle_correction(m, res, ds)
        dsc = copy.deepcopy(ds)
        full = np.zeros(len(ds.uwb))
        full[row_of] = corr
        dsc.uwb["range"] = ds.uwb["range"].to_numpy(float) - full
        left = res["residual"].to_numpy(float) - corr
        t0 = time.process_time()
        out = calibrate(dsc, CalibrationOptions.model_validate({"td_profile": {"enabled": False},
                                                                "estimate_anchor_bias": False}))
        cal = out.calibration
        row = {"model": m, "ate_batch": ate(out.trajectory), "ate_multilateration": ate(multilaterate(dsc, epoch_s=epoch_s)),
               "residual_mad_cm": 100 * float(np.median(np.abs(left - np.median(left)))),
               "lever_arm_cm": [100 * x for x in cal["lever_arm"]], "lever_arm_sd_cm": [100 * x for x in cal["lever_arm_sd"]],
               "td_ms": 1000 * cal["time_offset"]["value"], "cpu_s": time.process_time() - t0}
        rows.append(row)
        progress(f"| {m} | {row['ate_batch']:.3f} | {row['ate_multilateration']:.3f} | {row['residual_mad_cm']:.1f} | "
                 f"({', '.join(f'{x:+.1f}' for x in row['lever_arm_cm'])}) | {row['td_ms']:+.1f} | {row['cpu_s']:.0f} |")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--models", default="none,constant,distance,direction,smooth:20,smooth:5,smooth:1")
    ap.add_argument("--epoch-s", type=float, default=0.1,
                    help="multilateration epoch [s] (0.1 for INRoL's 1-3 ranges per stamp, as benchmarks/real_data.py)")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    from uwbimu.io.loader import load_dataset

    ds = load_dataset(a.dataset)
    print("| oracle range model | ATE batch (m) | ATE multilateration (m) | residual MAD left (cm) | lever arm (cm) | t_d (ms) | CPU (s) |")
    print("|---|---|---|---|---|---|---|")
    sys.stdout.flush()
    rows = run(ds, [m.strip() for m in a.models.split(",")], progress=lambda s: print(s, flush=True), epoch_s=a.epoch_s)
    if a.json:
        with open(a.json, "w") as fh:
            json.dump({"dataset": a.dataset, "rows": rows}, fh, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
