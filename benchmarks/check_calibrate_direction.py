"""Direction-dependent range bias on simulation: a known body-azimuth bias, calibrated with and without the model.

    python benchmarks/check_calibrate_direction.py [--duration 20] [--c1 0.05] [--s2 0.03]

Simulates the built-in calibration flight, adds ``c1 cos(az) + s2 sin(2 az)`` [m] to every range (``az`` the
true body-frame azimuth of the line of sight tag antenna -> anchor, as in tests/test_calibrate_direction.py),
and prints the lever-arm error and the direction coefficients (cm) for: no model, shared K = 2, shared K = 2
with lowest_order 2, per anchor K = 2, per anchor K = 2 with range_bias_drift.  Profile off.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=20.0)
    ap.add_argument("--c1", type=float, default=0.05)
    ap.add_argument("--s2", type=float, default=0.03)
    a = ap.parse_args(argv)
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_calibrate_direction import _with_body_azimuth_bias

    from uwbimu.calibration import CalibrationOptions, calibrate
    from uwbimu.sim import builtin_scenario, simulate

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": a.duration}))
    ds, _inj = _with_body_azimuth_bias(ds, a.c1, a.s2)
    truth = np.asarray(ds.meta.truth.lever_arm, float)
    base = dict(td_profile={"enabled": False})
    runs = [("none", {}), ("shared K=2", {"harmonics": 2}),
            ("shared K=2 lowest_order 2", {"harmonics": 2, "lowest_order": 2}),
            ("per anchor K=2", {"harmonics": 2, "per_anchor": True}),
            ("per anchor K=2 + drift", {"harmonics": 2, "per_anchor": True, "_drift": True})]
    eskf = None
    for name, d in runs:
        kw = dict(base)
        if d.pop("_drift", False):
            kw["range_bias_drift"] = {"sd": 0.05, "correlation_time": 2.0}
        if d:
            kw["range_model"] = {"direction": d}
        c0 = time.process_time()
        r = calibrate(ds, CalibrationOptions(**kw), eskf=eskf)
        eskf = r.eskf
        c = r.calibration
        err = 100 * (np.asarray(c["lever_arm"]) - truth)
        sd = np.round(100 * np.asarray(c["lever_arm_sd"]), 2)
        print(f"{name}: lever arm error [cm] {np.round(err, 2)} +/- {sd}, "
              f"{c['solver']['iterations']} iterations, {time.process_time() - c0:.1f} s CPU")
        dm = c["range_model"]["direction"]
        if dm:
            for lab, cs in dm["coefficients"].items():
                print(f"    {lab}: " + ", ".join(f"{n} {100 * x['value']:+.2f} +/- {100 * x['sd']:.2f}"
                                             for n, x in cs.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
