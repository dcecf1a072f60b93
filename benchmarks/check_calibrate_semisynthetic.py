"""Semi-synthetic checks of the batch calibrator on the shared INRoL sequence (issue 12, item 6).

    python benchmarks/check_calibrate_semisynthetic.py DATASET [--config calibrate.yaml] [--window S]
        [--noise-from-preset] [--shifts 0.05,-0.05,0.1,-0.1] [--offset 0.15,-0.10,0.05] [--json OUT.json]

DATASET: ``uwbimu import inrol ../shared/datasets/inrol_uwb_imu DIR``.  ESKF initialisation with
``examples/estimator_real.yaml``; ``--config``: the calibrator's options (default: defaults).

1. **UWB clock shift**: every UWB stamp moved by ``shift``; the same data then has the time offset
   ``t_d(0) - shift``.  Pass: ``|t_d(shift) - (t_d(0) - shift)| <= 3 sigma`` and ``<= 15 ms``
   (sigma: the shifted run's reported marginal sd).  A run whose t_d verdict is not
   ``identified`` fails (nothing to compare).
2. **Lever-arm offset**: every range replaced by ``range + |p_U + R d - a| - |p_U - a|`` where ``p_U``,
   ``R`` are the ground-truth antenna position (documented lever arm) and attitude at the range's
   stamp and ``d`` the offset (IMU frame): the ranges of a tag displaced by ``d``.  Pass:
   ``|lever(altered) - lever(original) - d| <= 1 cm`` per axis.

Each altered run starts from its own ESKF (nothing of the unaltered run is reused).  Every figure
is measured in this run; state the machine load (``uptime``) next to it.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
REAL = REPO / "examples" / "estimator_real.yaml"

sys.path.insert(0, str(Path(__file__).resolve().parent))
from check_self_survey import window as first_seconds  # noqa: E402


def window(ds, seconds: float | None):
    """The first ``seconds`` of the log (the whole log when None or 0)."""
    return first_seconds(ds, seconds) if seconds else ds


def shifted(ds, shift: float):
    """UWB stamps moved by ``shift`` [s] (the true t_d becomes t_d - shift)."""
    uwb = ds.uwb.copy()
    uwb["t"] = uwb["t"] + shift
    return dataclasses.replace(ds, uwb=uwb)


def lever_offset(ds, d: np.ndarray):
    """Ranges of the tag displaced by ``d`` (IMU frame) from the documented lever arm, via the ground truth."""
    from scipy.spatial.transform import Rotation

    from uwbimu.estimation import truth_at

    uwb = ds.uwb.copy()
    t = uwb["t"].to_numpy(float)
    p, q, _v, ok = truth_at(ds, t)
    lever = np.asarray(ds.meta.truth.lever_arm, float)
    R = Rotation.from_quat(np.asarray(q)[:, [1, 2, 3, 0]])
    pos = ds.anchor_positions()
    a = np.array([pos[str(x)] for x in uwb["anchor"].astype(str)])
    pu = p + R.apply(lever)
    delta = np.linalg.norm(pu + R.apply(d) - a, axis=1) - np.linalg.norm(pu - a, axis=1)
    uwb["range"] = uwb["range"].to_numpy(float) + np.where(ok, delta, 0.0)
    keep = ok  # ranges without ground truth cannot be altered consistently: dropped
    return dataclasses.replace(ds, uwb=uwb[keep].reset_index(drop=True)), int((~ok).sum())


def run(ds, opts, eo):
    from uwbimu.calibration import calibrate

    c0 = time.process_time()
    r = calibrate(ds, opts, eskf_options=eo)
    return r.calibration, time.process_time() - c0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dataset")
    ap.add_argument("--config")
    ap.add_argument("--noise-from-preset", action="store_true", help="as in check_calibrate_real.py")
    ap.add_argument("--window", type=float, default=None, help="first seconds of the log (default: all)")
    ap.add_argument("--shifts", default="0.05,-0.05,0.1,-0.1")
    ap.add_argument("--offset", default="0.15,-0.10,0.05")
    ap.add_argument("--json")
    a = ap.parse_args(argv)

    from uwbimu.calibration import CalibrationOptions
    from uwbimu.estimation import EskfOptions
    from uwbimu.io.loader import load_dataset

    ds = window(load_dataset(a.dataset), a.window)
    opts = CalibrationOptions.from_yaml(a.config) if a.config else CalibrationOptions()
    if a.noise_from_preset:
        import sys

        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from check_calibrate_real import options_from_eskf_preset

        opts = options_from_eskf_preset(REAL, opts.model_dump(exclude_unset=True))
    eo = EskfOptions.from_yaml(REAL)
    rep: dict = {"dataset": a.dataset, "config": a.config, "window": a.window, "load_before": os.getloadavg()}
    base, cpu = run(ds, opts, eo)
    td0 = base["time_offset"]
    rep["base"] = {"time_offset": td0, "lever_arm": base["lever_arm"], "lever_arm_sd": base["lever_arm_sd"],
                   "cpu_s": cpu}
    print(f"unaltered: t_d {1000 * td0['value']:.1f} ms ({td0['verdict']}, sd {td0['sd']}), lever arm "
          f"{np.round(100 * np.array(base['lever_arm']), 2)} cm, {cpu:.0f} s CPU")
    rep["shifts"] = []
    for s in [float(x) for x in a.shifts.split(",") if x]:
        c, cpu = run(shifted(ds, s), opts, eo)
        td = c["time_offset"]
        exp = td0["value"] - s
        err = td["value"] - exp
        ok = td["verdict"] == "identified" and abs(err) <= 3 * td["sd"] and abs(err) <= 0.015
        rep["shifts"].append({"shift": s, "time_offset": td, "expected": exp, "error": err, "pass": bool(ok),
                              "cpu_s": cpu})
        sd = "-" if td["sd"] is None else f"{1000 * td['sd']:.1f}"
        print(f"shift {1000 * s:+.0f} ms: t_d {1000 * td['value']:.1f} +/- {sd} ms ({td['verdict']}), expected "
              f"{1000 * exp:.1f}, error {1000 * err:+.1f} ms -> {'pass' if ok else 'FAIL'} ({cpu:.0f} s CPU)")
    d = np.array([float(x) for x in a.offset.split(",")])
    alt, dropped = lever_offset(ds, d)
    c, cpu = run(alt, opts, eo)
    diff = np.subtract(c["lever_arm"], base["lever_arm"])
    err = diff - d
    ok = bool(np.all(np.abs(err) <= 0.01))
    rep["lever_offset"] = {"offset": d.tolist(), "lever_arm": c["lever_arm"], "lever_arm_sd": c["lever_arm_sd"],
                           "recovered": diff.tolist(), "error": err.tolist(), "pass": ok, "dropped_ranges": dropped,
                           "cpu_s": cpu}
    print(f"lever-arm offset {np.round(100 * d, 1)} cm: recovered {np.round(100 * diff, 2)} cm, error "
          f"{np.round(100 * err, 2)} cm (sd {np.round(100 * np.array(c['lever_arm_sd']), 2)}) -> "
          f"{'pass' if ok else 'FAIL'} ({dropped} ranges without ground truth dropped; {cpu:.0f} s CPU)")
    rep["load_after"] = os.getloadavg()
    if a.json:
        Path(a.json).write_text(json.dumps(rep, indent=1, default=float))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
