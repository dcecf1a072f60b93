"""Anchor self-survey on the FULL shared INRoL log: 3 of its 8 anchors unknown, against anchor.txt.

    python benchmarks/check_self_survey_real.py DATASET --full [--profile] [--json OUT.json]
    python benchmarks/check_self_survey_real.py DATASET --sets 2,5,7 --variants bias,nobias [--window 60]
    python benchmarks/check_self_survey_real.py DATASET --floor-only

DATASET: an imported INRoL folder (``uwbimu import inrol ../shared/datasets/inrol_uwb_imu DIR``).

``--full`` runs the whole 190 s log for the four unknown triples fixed (by rule, before any result)
in ``TRIPLES`` and the range-bias variants ``bias`` (every anchor's constant range bias estimated,
the default), ``nobias`` (``estimate_anchor_bias: false``) and ``surveyed_only`` (the fixed anchors' biases
estimated, the unknown anchors' held at 0), t_d profile off unless ``--profile``
(the default profile).  In every run the unknown anchors are marked ``surveyed: false`` and their
coordinates overwritten with 0 (nothing of the documented value reaches the calibrator); the other
5 anchors stay fixed at ``anchor.txt`` and fix the frame.

Per unknown anchor it prints the error against ``anchor.txt`` (vector and norm, cm), the marginal
sd per axis that ``calibration.yaml`` reports (and ``sd_model`` next to it when the calibrator
writes one, e.g. a sandwich/HAC covariance with the white-model sd kept as ``sd_model``), the
normalised error per axis and the Mahalanobis distance ``sqrt(e' C^-1 e)`` with the anchor's 3x3
marginal covariance (rebuilt from ``correlations`` and ``sd``; expected ~ sqrt(3) = 1.7 for an
honest sigma), whether the constant range bias is estimated, and the geometry events.

The **range-only floor** (``--floor-only``, also printed by ``--full``) is a diagnostic that uses
the motion-capture ground truth, which the calibrator never sees: each anchor multilaterated from
its ranges at the TRUE antenna positions (mocap pose + documented lever arm), Huber, with and without
a constant range bias, over the whole log and over 4 quarters of it.  Its error is what the range
errors alone (direction dependent, time correlated) cause, whatever the trajectory estimate.

Every number printed is measured in this run; CPU is ``time.process_time()`` of the calibrate call
(all threads of this process); state the machine load (``uptime``) next to it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd



REPO = Path(__file__).resolve().parents[1]
REAL = REPO / "examples" / "estimator_real.yaml"

#: Unknown triples, fixed by rule before any full-log result (docs/calibrate.md "Measured: self-survey"):
#: the 60-s benchmark's spread triple; the three anchors the dataset README names worst (low anchors);
#: three of the four high anchors (clustered, one layer); one low anchor and two high ones on three
#: different corners (spread, both layers).
TRIPLES = {"spread-2,5,7": ("2", "5", "7"), "readme-worst-2,3,4": ("2", "3", "4"),
           "high-6,7,8": ("6", "7", "8"), "spread-1,3,8": ("1", "3", "8")}
LEVER_ARM_DOC = np.array([0.0, 0.0, 0.01])  # documented IMU -> tag lever arm (dataset.yaml) [m]


def window(ds, seconds: float | None):
    """The first ``seconds`` of the log (None: the whole log)."""
    if seconds is None:
        return ds
    t0 = float(ds.imu["t"].iloc[0])
    imu = ds.imu[ds.imu.t < t0 + seconds].reset_index(drop=True)
    uwb = ds.uwb[ds.uwb.t < t0 + seconds - 0.2].reset_index(drop=True)
    return dataclasses.replace(ds, imu=imu, uwb=uwb)


def documented(ds) -> pd.DataFrame:
    """anchor.txt positions (the imported anchors.csv) [m], indexed by anchor id (str)."""
    return ds.anchors.set_index(ds.anchors["anchor"].astype(str))[["x", "y", "z"]].astype(float)


def anchor_covariance(cal: dict, a: str) -> np.ndarray | None:
    """3x3 marginal covariance [m^2] of estimated anchor ``a`` from calibration.yaml's correlations and sd."""
    names = cal["correlations"]["names"]
    want = [f"anchor_{c}_{a}" for c in "xyz"]
    if not set(want) <= set(names):
        return None
    idx = [names.index(w) for w in want]
    corr = np.asarray(cal["correlations"]["matrix"], float)[np.ix_(idx, idx)]
    sd = np.asarray(cal["anchors"]["positions"][a]["sd"], float)
    return corr * np.outer(sd, sd)


#: --variants: estimate_anchor_bias and a label
VARIANTS = {"bias": (True, "estimated"), "nobias": (False, "off"),
            "surveyed_only": ("surveyed_only", "of the surveyed anchors only (unknown anchors' held at 0)")}


def run_one(ds, unknown, bias, profile: bool):
    """One calibration with ``unknown`` anchors surveyed: false; returns (result, cpu_s, wall_s).

    ``bias``: ``estimate_anchor_bias`` (True, False or "surveyed_only")."""
    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.estimation import EskfOptions

    an = ds.anchors.copy()
    an["surveyed"] = [str(a) not in unknown for a in an["anchor"]]
    an.loc[~an["surveyed"], ["x", "y", "z"]] = 0.0
    cfg = {"estimate_anchor_bias": bias}
    if not profile:
        cfg["td_profile"] = {"enabled": False}
    opts = CalibrationOptions.model_validate(cfg)
    c0, w0 = time.process_time(), time.perf_counter()
    r = calibrate(dataclasses.replace(ds, anchors=an), opts, eskf_options=EskfOptions.from_yaml(REAL))
    return r, time.process_time() - c0, time.perf_counter() - w0


def inflation(r, ds, a: str) -> float:
    """:func:`uwbimu.calibration.anchors.bias_confounding` inflation of estimated anchor ``a``.

    On the calibrated anchor position and the initialising ESKF's antenna positions at its range times
    (what the calibrator's geometry checks see; no ground truth).
    """
    from uwbimu.calibration import anchors as AN

    t = ds.uwb["t"].to_numpy(float)[ds.uwb["anchor"].astype(str).to_numpy() == a]
    t = t[t <= r.eskf.t[-1]]
    P = AN.antenna_positions(r.eskf, t)
    return AN.bias_confounding(a, np.asarray(r.calibration["anchors"]["positions"][a]["position"], float), P)[
        "inflation"]


def table(r, unknown, doc: pd.DataFrame, label: str, ds=None) -> list[dict]:
    """Print the per-anchor table of one run; return its rows (for --json)."""
    cal = r.calibration
    pos = cal["anchors"]["positions"]
    bias_est = cal["range_model"]["constant_bias_prior_sd"] is not None
    print(f"\n#### {label}")
    print("| anchor | error x, y, z (cm) | abs error (cm) | sd x, y, z (cm) | error / sd | Mahalanobis | "
          "range bias (cm) | bias inflation |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for a in unknown:
        est = np.asarray(pos[a]["position"], float)
        sd = np.asarray(pos[a]["sd"], float)
        err = est - doc.loc[a].to_numpy(float)
        C = anchor_covariance(cal, a)
        maha = float(np.sqrt(err @ np.linalg.solve(C, err))) if C is not None else float("nan")
        b, bsd = cal["anchor_bias"][a], cal["anchor_bias_sd"][a]
        btxt = f"{100 * b:+.1f} +/- {100 * bsd:.1f}" if bias_est else "not estimated"
        infl = inflation(r, ds, a) if ds is not None else float("nan")
        print(f"| {a} | {', '.join(f'{100 * e:+.1f}' for e in err)} | {100 * np.linalg.norm(err):.1f} | "
              f"{', '.join(f'{100 * s:.1f}' for s in sd)} | {', '.join(f'{e / s:+.1f}' for e, s in zip(err, sd))} | "
              f"{maha:.1f} | {btxt} | {infl:.0f} |")
        row = {"anchor": a, "error_m": err.tolist(), "abs_error_m": float(np.linalg.norm(err)), "sd_m": sd.tolist(),
               "mahalanobis": maha, "bias_estimated": bias_est, "bias_m": b if bias_est else None,
               "bias_inflation": infl}
        if "sd_model" in pos[a]:
            sm = np.asarray(pos[a]["sd_model"], float)
            row["sd_model_m"] = sm.tolist()
            print(f"|   | sd_model x, y, z (cm): {', '.join(f'{100 * s:.1f}' for s in sm)}; error / sd_model: "
                  f"{', '.join(f'{e / s:+.1f}' for e, s in zip(err, sm))} | | | | | | |")
        rows.append(row)
    la, las = cal["lever_arm"], cal["lever_arm_sd"]
    to = cal["time_offset"]
    tdtxt = f"{1000 * to['value']:.1f} +/- {1000 * to['sd']:.1f} ms" if to["sd"] is not None else \
        f"held at {1000 * to['value']:.1f} ms"
    print(f"lever arm (cm): {', '.join(f'{100 * (v - d):+.1f}' for v, d in zip(la, LEVER_ARM_DOC))} off documented, "
          f"sd {', '.join(f'{100 * v:.1f}' for v in las)}; t_d {tdtxt} ({to['verdict']})")
    for ev in r.events:
        if ev["kind"].startswith("anchor_") and ev["kind"] != "anchor_unsurveyed_estimated":
            print(f"event {ev['kind']}: {ev.get('message', '')}")
    return rows


# ---------------------------------------------------------------- range-only floor (uses ground truth)

def true_antenna(ds):
    """(t, P): UWB rows inside the mocap span and the true antenna positions there [m] (world)."""
    from scipy.spatial.transform import Rotation, Slerp

    gt = ds.groundtruth.drop_duplicates("t").sort_values("t")
    t = ds.uwb["t"].to_numpy(float)
    ok = (t > gt["t"].iloc[0]) & (t < gt["t"].iloc[-1])
    tg = gt["t"].to_numpy(float)
    p = np.column_stack([np.interp(t[ok], tg, gt[c].to_numpy(float)) for c in ("px", "py", "pz")])
    rot = Slerp(tg, Rotation.from_quat(gt[["qx", "qy", "qz", "qw"]].to_numpy(float)))(t[ok])
    return ok, p + rot.apply(LEVER_ARM_DOC), rot


def multilaterate_direction(P, rho, rot, a0, harmonics=2, elevation=False, prior_sd=0.05, sigma=0.1, k=1.345,
                            iters=30):
    """As :func:`multilaterate_huber` without range bias, plus the tag-side direction model of the calibrator.

    Bias ``sum_n c_n cos(n az) + s_n sin(n az) (+ e el)`` of the line of sight tag -> anchor in the TAG
    body frame (``range_model.direction``, ``per_anchor: true``), zero-mean prior ``prior_sd`` per
    coefficient.  Returns the position [m].
    """
    a = np.asarray(a0, float).copy()
    x = np.zeros(2 * harmonics + int(elevation))
    for _ in range(iters):
        u = a - P
        r = np.linalg.norm(u, axis=1)
        n = u / r[:, None]
        ub = rot.inv().apply(n)
        az, el = np.arctan2(ub[:, 1], ub[:, 0]), np.arcsin(np.clip(ub[:, 2], -1.0, 1.0))
        F = np.column_stack([f(h * az) for h in range(1, harmonics + 1) for f in (np.cos, np.sin)]
                            + ([el] if elevation else []))
        e = r + F @ x - rho
        w = np.minimum(1.0, k * sigma / np.maximum(np.abs(e), 1e-12))
        J = np.column_stack([n, F])
        H = (J * w[:, None]).T @ J / sigma**2
        g = (J * w[:, None]).T @ e / sigma**2
        H[3:, 3:] += np.eye(len(x)) / prior_sd**2
        g[3:] += x / prior_sd**2
        step = -np.linalg.solve(H, g)
        a, x = a + step[:3], x + step[3:]
    return a


def multilaterate_huber(P, rho, a0, bias: bool, sigma=0.1, k=1.345, iters=30, t=None, hac_lag_s=5.0):
    """Anchor position (and constant bias) from ranges at known antenna positions, Huber IRLS.

    Returns (position [m], bias [m], white-model sd per axis [m], HAC sd per axis [m] or None).  The HAC
    (sandwich, Newey-West, Bartlett weights over ``hac_lag_s`` seconds of the range times ``t``) sd
    treats the residuals as time-correlated, not white.
    """
    a, b = np.asarray(a0, float).copy(), 0.0
    for _ in range(iters):
        u = a - P
        r = np.linalg.norm(u, axis=1)
        e = r + b - rho
        w = np.minimum(1.0, k * sigma / np.maximum(np.abs(e), 1e-12))
        J = np.column_stack([u / r[:, None]] + ([np.ones(len(r))] if bias else []))
        step = -np.linalg.solve((J * w[:, None]).T @ J, (J * w[:, None]).T @ e)
        a = a + step[:3]
        b = b + (step[3] if bias else 0.0)
    sd = np.sqrt(np.diag(np.linalg.inv(J.T @ J))[:3]) * sigma
    hac = None
    if t is not None:
        g = J * (w * e)[:, None]  # per-range score
        S = g.T @ g
        dt = float(np.median(np.diff(t)))
        for lag in range(1, int(hac_lag_s / dt) + 1):
            wl = 1.0 - lag / (hac_lag_s / dt + 1.0)
            G = g[lag:].T @ g[:-lag]
            S += wl * (G + G.T)
        Ainv = np.linalg.inv((J * w[:, None]).T @ J)
        hac = np.sqrt(np.diag(Ainv @ S @ Ainv)[:3])
    return a, b, sd, hac


def floor(ds, ids) -> list[dict]:
    """Range-only floor per anchor (see module doc); prints a table."""
    from uwbimu.calibration.anchors import bias_confounding

    ok, P, rot = true_antenna(ds)
    uwb = ds.uwb[ok]
    aid = uwb["anchor"].astype(str).to_numpy()
    rho = uwb["range"].to_numpy(float)
    doc = documented(ds)
    tr = uwb["t"].to_numpy(float)
    quarters = np.array_split(np.arange(len(uwb)), 4)
    print("\n#### Range-only floor: multilateration at the TRUE antenna positions (mocap; diagnostic only)")
    print("| anchor | bias | error x, y, z (cm) | abs (cm) | white sd x, y, z (cm) | HAC sd x, y, z (cm) | "
          "quarters: abs error (cm) | quarters: sd of estimate x, y, z (cm) | bias inflation |")
    print("|---|---|---|---|---|---|---|---|---|")
    out = []
    for a in ids:
        a0 = doc.loc[a].to_numpy(float)
        m = aid == a
        infl = bias_confounding(a, a0, P[m])["inflation"]
        for bias in (False, True):
            est, b, sd, hac = multilaterate_huber(P[m], rho[m], a0 + 0.3, bias, t=tr[m])
            err = est - a0
            q = []
            for idx in quarters:
                mq = np.zeros(len(uwb), bool)
                mq[idx] = True
                mq &= m
                q.append(multilaterate_huber(P[mq], rho[mq], a0 + 0.3, bias)[0] - a0)
            q = np.array(q)
            print(f"| {a} | {'est. %+.0f cm' % (100 * b) if bias else 'off'} | "
                  f"{', '.join(f'{100 * e:+.1f}' for e in err)} | {100 * np.linalg.norm(err):.1f} | "
                  f"{', '.join(f'{100 * s:.1f}' for s in sd)} | {', '.join(f'{100 * s:.1f}' for s in hac)} | "
                  f"{', '.join(f'{100 * np.linalg.norm(e):.0f}' for e in q)} | "
                  f"{', '.join(f'{100 * s:.0f}' for s in q.std(axis=0, ddof=1))} | {infl:.0f} |")
            out.append({"anchor": a, "bias": bias, "error_m": err.tolist(), "bias_m": b, "white_sd_m": sd.tolist(),
                        "hac_sd_m": hac.tolist(), "quarter_errors_m": q.tolist(), "bias_inflation": infl})
    print("\nRange-only floor with the tag-side direction model (no constant bias, per anchor, prior sd 5 cm): "
          "abs error (cm)")
    print("| model | " + " | ".join(ids) + " | median |")
    print("|---" * (len(ids) + 2) + "|")
    for lab, kw in (("none", None), ("harmonics 2", {}), ("harmonics 2 + elevation", {"elevation": True})):
        errs = []
        for a in ids:
            a0 = doc.loc[a].to_numpy(float)
            m = aid == a
            est = (multilaterate_huber(P[m], rho[m], a0 + 0.3, False)[0] if kw is None else
                   multilaterate_direction(P[m], rho[m], rot[np.flatnonzero(m)], a0 + 0.3, **kw))
            errs.append(100 * np.linalg.norm(est - a0))
        print(f"| {lab} | " + " | ".join(f"{e:.1f}" for e in errs) + f" | {np.median(errs):.1f} |")
        out.append({"direction_model": lab, "abs_error_cm": dict(zip(ids, errs))})
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--full", action="store_true", help="whole log, the 4 TRIPLES, variants bias and nobias, floor")
    ap.add_argument("--window", type=float, default=None, help="first seconds of the log [s] (default: whole log)")
    ap.add_argument("--sets", default=None, help="unknown triples, e.g. '2,5,7;6,7,8' (default: TRIPLES)")
    ap.add_argument("--variants", default="bias,nobias", help="comma list of bias, nobias, surveyed_only")
    ap.add_argument("--profile", action="store_true", help="default t_d profile on (else off)")
    ap.add_argument("--floor-only", action="store_true", help="only the range-only floor (ground truth), no solve")
    ap.add_argument("--json", type=Path, default=None, help="write every row to this JSON file")
    args = ap.parse_args()

    from uwbimu.io.loader import load_dataset

    ds = window(load_dataset(args.dataset), None if args.full else args.window)
    doc = documented(ds)
    out = {"runs": [], "floor": None}
    if args.full or args.floor_only:
        out["floor"] = floor(ds, sorted(doc.index))
    if args.floor_only:
        return
    sets = ({f"set-{s}": tuple(a.strip() for a in s.split(",")) for s in args.sets.split(";")}
            if args.sets else TRIPLES)
    span = float(ds.imu["t"].iloc[-1] - ds.imu["t"].iloc[0])
    for name, unknown in sets.items():
        for v in [x.strip() for x in args.variants.split(",")]:
            if v not in VARIANTS:
                raise SystemExit(f"--variants: {v!r} is not one of {', '.join(VARIANTS)}")
            r, cpu, wall = run_one(ds, unknown, VARIANTS[v][0], args.profile)
            label = (f"{name}, range bias {VARIANTS[v][1]}, profile "
                     f"{'on (default)' if args.profile else 'off'}; {span:.0f} s, {len(ds.uwb)} ranges; "
                     f"CPU {cpu:.0f} s, wall {wall:.0f} s")
            rows = table(r, unknown, doc, label, ds)
            out["runs"].append({"set": name, "variant": v, "profile": args.profile, "cpu_s": cpu, "wall_s": wall,
                                "rows": rows, "lever_arm_m": r.calibration["lever_arm"],
                                "time_offset": r.calibration["time_offset"],
                                "events": [e["kind"] for e in r.events]})
            if args.json:
                args.json.write_text(json.dumps(out, indent=1, default=float))


if __name__ == "__main__":
    main()
