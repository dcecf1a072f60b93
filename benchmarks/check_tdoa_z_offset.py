"""Where the Crazyflie logs' +0.2 m z offset comes from: the tag's lever arm and the TDoA pair biases.

    python benchmarks/check_tdoa_z_offset.py DATASET [DATASET ...] [--lever X Y Z] [--no-eskf]

Per log (a folder imported with ``uwbimu import cf-usdlog``), over the flight segment of
``compare_crazyflie.flight_segment`` (ground truth more than 0.3 m above the floor):

1. the ESKF with default options (``run_eskf``): position RMSE and per-axis mean error / RMS against the
   logged Vicon pose (the body origin);
2. per anchor pair, the TDoA residual against the truth: measured TDoA minus ``|p - b| - |p - a|`` with
   ``p`` the time-aligned Vicon position plus the rotated lever arm (``--lever``, the UTIL platform's
   documented antenna offset by default); its mean, median and robust sd (1.4826 MAD), and the mean
   z-gradient of the pair's TDoA (how much a z error moves it);
3. TDoA-only multilateration (``compare_crazyflie.multilaterate_tdoa``, the tag position, 0.5 s windows)
   on the log as it is and on a copy whose TDoAs have each pair's in-flight median residual removed (an
   oracle, from the truth: it shows how much of the z offset the pair biases make, never an estimator).

The multilateration's z mean includes the antenna height above the body origin (lever z); the ESKF's
includes it only when its lever-arm prior is zero (an import without the nominal lever arm, or
``lever_arm.prior: null``): the log does not identify the lever arm, so the ESKF holds it at its prior.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from compare_crazyflie import flight_segment, multilaterate_tdoa  # noqa: E402

#: the UTIL platform's documented vehicle-centre -> UWB tag offset [m] (the importer's nominal lever arm)
from uwbimu.io.importers.cf_usdlog import UTIL_T_UV as UTIL_LEVER  # noqa: E402


def _errors(ds, t, p, span):
    from uwbimu.metrics.filter import truth_at

    ref, _, _, m = truth_at(ds, np.asarray(t, float))
    m &= (t >= span[0]) & (t <= span[1])
    return np.asarray(p, float)[m] - ref[m]


def _axis_line(name: str, e: np.ndarray) -> str:
    rmse = float(np.sqrt(np.mean(np.sum(e**2, axis=1))))
    return (f"  {name:34s} RMSE {rmse:.3f} m  mean (x, y, z) {np.array2string(e.mean(0), precision=3)}"
            f"  RMS {np.array2string(np.sqrt((e**2).mean(0)), precision=3)}")


def pair_residuals(ds, lever, span):
    """TDoA minus the truth's TDoA per row, the in-flight mask, the pair label and the z-gradient."""
    from uwbimu.metrics.filter import truth_at
    from uwbimu.models.quaternion import quat_to_rotmat

    pos = ds.anchor_positions()
    td = ds.tdoa
    t = td["t"].to_numpy(float)
    p, q, _, m = truth_at(ds, t)
    if q is None:
        raise SystemExit("the ground truth has no attitude: the lever arm cannot be rotated")
    pa = p + np.array([quat_to_rotmat(qi) @ np.asarray(lever, float) for qi in q])
    A = np.array([pos[str(a)] for a in td["anchor_a"]], float)
    B = np.array([pos[str(b)] for b in td["anchor_b"]], float)
    ub = (pa - B) / np.linalg.norm(pa - B, axis=1)[:, None]
    ua = (pa - A) / np.linalg.norm(pa - A, axis=1)[:, None]
    res = td["tdoa"].to_numpy(float) - (np.linalg.norm(pa - B, axis=1) - np.linalg.norm(pa - A, axis=1))
    flight = m & (t >= span[0]) & (t <= span[1])
    pair = (td["anchor_a"].astype(str) + "-" + td["anchor_b"].astype(str)).to_numpy()
    return res, flight, pair, (ub - ua)[:, 2]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("datasets", nargs="+")
    ap.add_argument("--lever", nargs=3, type=float, default=UTIL_LEVER, metavar=("X", "Y", "Z"),
                    help="tag lever arm in the body frame [m] (default: the UTIL platform's documented one)")
    ap.add_argument("--no-eskf", action="store_true", help="skip the ESKF run")
    a = ap.parse_args()

    from uwbimu.estimation import run_eskf
    from uwbimu.io.loader import load_dataset

    for path in a.datasets:
        ds = load_dataset(path)
        if ds.tdoa is None or len(ds.tdoa) == 0:
            raise SystemExit(f"{path}: no TDoA measurements")
        span = flight_segment(ds.groundtruth)
        print(f"{path}: flight {span[0]:.1f}-{span[1]:.1f} s, lever {list(a.lever)} m")
        if not a.no_eskf:
            r = run_eskf(ds)
            print(_axis_line("ESKF (defaults)", _errors(ds, r.t, np.asarray(r.states)[:, :3], span)))
        res, fl, pair, gz = pair_residuals(ds, a.lever, span)
        corr = np.zeros(len(res))
        print(f"  TDoA residual against the truth, in flight: mean {res[fl].mean():+.3f} m, sd {res[fl].std():.3f} m")
        for k in sorted(set(pair[fl])):
            s = fl & (pair == k)
            med = float(np.median(res[s]))
            mad = 1.4826 * float(np.median(np.abs(res[s] - med)))
            if s.sum() >= 10:
                corr[pair == k] = med
            print(f"    pair {k:6s} n {int(s.sum()):5d}  mean {res[s].mean():+.3f}  median {med:+.3f}  robust sd {mad:.3f}"
                  f"  dTDoA/dz {gz[s].mean():+.2f}")
        t, p, _ = multilaterate_tdoa(ds)
        print(_axis_line("multilateration", _errors(ds, t, p, span)))
        fixed = ds.tdoa.copy()
        fixed["tdoa"] = fixed["tdoa"].to_numpy(float) - corr
        ds.tdoa = fixed
        t, p, _ = multilaterate_tdoa(ds)
        print(_axis_line("multilateration, pair medians out", _errors(ds, t, p, span)))
        print(f"  (the tag is {a.lever[2]:.3f} m above the body origin: a multilateration without pair biases "
              f"has that z mean)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
