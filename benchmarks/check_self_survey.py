"""Anchor self-survey on the shared INRoL sequence: 3 of its 8 anchors treated as unknown.

    python benchmarks/check_self_survey.py DATASET [--window 60] [--unknown 2,5,7] [--no-bias]

DATASET: an imported INRoL folder (``uwbimu import inrol ../shared/datasets/inrol_uwb_imu DIR``).
The ``--unknown`` anchors are marked ``surveyed: false`` and their coordinates overwritten with 0
(nothing of the documented value reaches the calibrator); the calibrator estimates them with no
prior, from the first ``--window`` seconds of the log.  The full-log survey (four triples, range
bias estimated and off, the ground-truth range-only floor) is ``benchmarks/check_self_survey_real.py
DATASET --full``.  The
errors are against the documented ``anchor.txt`` values (the imported anchors.csv).  Every number
printed is measured in this run; state the machine load (``uptime``) next to it.
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / "examples" / "estimator_real.yaml"


def window(ds, seconds: float):
    t0 = float(ds.imu["t"].iloc[0])
    imu = ds.imu[ds.imu.t < t0 + seconds].reset_index(drop=True)
    uwb = ds.uwb[ds.uwb.t < t0 + seconds - 0.2].reset_index(drop=True)
    return dataclasses.replace(ds, imu=imu, uwb=uwb)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--window", type=float, default=60.0, help="first seconds of the log [s]")
    ap.add_argument("--unknown", default="2,5,7", help="anchor ids treated as unknown")
    ap.add_argument("--no-bias", action="store_true", help="no per-anchor range bias (estimate_anchor_bias: false)")
    args = ap.parse_args()

    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.estimation import EskfOptions
    from uwbimu.io.loader import load_dataset

    ds = window(load_dataset(args.dataset), args.window)
    unknown = [a.strip() for a in args.unknown.split(",")]
    doc = ds.anchors.set_index(ds.anchors["anchor"].astype(str))[["x", "y", "z"]].astype(float)
    an = ds.anchors.copy()
    an["surveyed"] = [str(a) not in unknown for a in an["anchor"]]
    an.loc[~an["surveyed"], ["x", "y", "z"]] = 0.0
    opts = CalibrationOptions.model_validate({"td_profile": {"enabled": False},
                                              "estimate_anchor_bias": not args.no_bias})
    t = time.perf_counter()
    r = calibrate(dataclasses.replace(ds, anchors=an), opts, eskf_options=EskfOptions.from_yaml(REAL))
    runtime = time.perf_counter() - t
    print(f"INRoL first {args.window:g} s ({len(ds.uwb)} ranges), unknown anchors {', '.join(unknown)}, "
          f"range bias {'off' if args.no_bias else 'estimated'}; runtime {runtime:.0f} s")
    print("| anchor | error x, y, z (cm) | abs error (cm) | sd x, y, z (cm) | error / sd |")
    print("|---|---|---|---|---|")
    tab = r.anchors.set_index(r.anchors["anchor"].astype(str))
    for a in unknown:
        est = tab.loc[a, ["x", "y", "z"]].to_numpy(float)
        sd = tab.loc[a, ["sd_x", "sd_y", "sd_z"]].to_numpy(float)
        err = est - doc.loc[a].to_numpy(float)
        print(f"| {a} | {', '.join(f'{100 * e:+.1f}' for e in err)} | {100 * np.linalg.norm(err):.1f} | "
              f"{', '.join(f'{100 * s:.1f}' for s in sd)} | {', '.join(f'{e / s:+.1f}' for e, s in zip(err, sd))} |")
    cal = r.calibration
    print(f"lever arm (cm): {', '.join(f'{100 * v:+.1f}' for v in cal['lever_arm'])} +/- "
          f"{', '.join(f'{100 * v:.1f}' for v in cal['lever_arm_sd'])}; t_d {1000 * cal['time_offset']['value']:.1f} "
          f"+/- {1000 * cal['time_offset']['sd']:.1f} ms")
    for ev in r.events:
        print(f"event {ev['kind']}: {ev.get('message', '')}")


if __name__ == "__main__":
    main()
