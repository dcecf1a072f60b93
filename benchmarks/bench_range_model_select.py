"""The range model chosen by blocked cross-validation: simulated logs of known model, and real logs.

One command::

    PYTHONPATH=src python benchmarks/bench_range_model_select.py [--seeds 3] [--real /tmp/ds/inrol2 /tmp/ds/isas2]
        [--basis eskf|solve]

Simulated: the built-in 60 s calibration flight (noise seeds 1..N) as it is (white range noise), with a
direction-dependent bias in the body frame (order-2 terms 8 and 5 cm) and with per-anchor AR(1) errors
(10 cm, 3 s).  Prints, per log, the family chosen, the Huber threshold, the mean held-out score of every
family (nats per range, at its best threshold) and the selection's run time; then how often the true
family was chosen.  Real logs (imported dataset folders, ESKF defaults as the trajectory) print the same.
``--basis solve``: the residuals about the batch's first free solve instead (what ``uwbimu calibrate`` selects
on; the select time excludes the solve).
"""

from __future__ import annotations

import argparse
import copy
import sys
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from uwbimu.calibration.range_factor import direction_features
from uwbimu.calibration.range_model_select import select_range_model
from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.sim import builtin_scenario, simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from check_clock_false_alarms import ar1_ranges  # noqa: E402

#: true direction coefficients (cos1, sin1, cos2, sin2) [m]: order 2 only (order 1 is the lever arm's)
COEF = np.array([0.0, 0.0, 0.08, 0.05])


def with_direction_bias(ds, coef=COEF):
    """``ds`` with ``F(w_b) . coef`` added to every range, ``w_b`` the true body-frame line of sight."""
    g, u = ds.groundtruth, ds.uwb.copy()
    t = u["t"].to_numpy(float)
    p = np.column_stack([np.interp(t, g["t"], g[c]) for c in ("px", "py", "pz")])
    q = np.column_stack([np.interp(t, g["t"], g[c]) for c in ("qx", "qy", "qz", "qw")])
    R = Rotation.from_quat(q / np.linalg.norm(q, axis=1)[:, None])
    a = ds.anchors.set_index("anchor").loc[u["anchor"].astype(str), ["x", "y", "z"]].to_numpy(float)
    wb = R.inv().apply(a - (p + R.apply(np.asarray(ds.meta.truth.lever_arm))))
    F, _ = direction_features(wb, (1, 2), False)
    u["range"] = u["range"].to_numpy(float) + F @ coef
    out = copy.copy(ds)
    out.uwb = u
    return out


def free_solve_selection(ds):
    """The selection as ``uwbimu calibrate`` makes it: on the residuals about the batch's first free solve (white
    model, started from the ESKF defaults; no second start), :mod:`uwbimu.calibration.range_model_stage`."""
    from uwbimu.calibration import graph
    from uwbimu.calibration.options import CalibrationOptions
    from uwbimu.calibration.profile_walk import solve
    from uwbimu.calibration.range_model_select import select_on_residuals
    from uwbimu.calibration.range_model_stage import solve_residuals

    pb = graph.build_problem(ds, run_eskf(ds, EskfOptions()), CalibrationOptions())
    sv = solve(pb, graph._imu_factors(pb), graph.initial_values(pb), pb.td0, None)
    t0 = time.perf_counter()
    return select_on_residuals(solve_residuals(pb, sv), CalibrationOptions(), basis="free_solve"), t0


def row(name: str, ds, basis: str = "eskf") -> str:
    if basis == "solve":
        sel, t0 = free_solve_selection(ds)
    else:
        res = run_eskf(ds, EskfOptions())
        t0 = time.perf_counter()
        sel = select_range_model(ds, res)
    dt = time.perf_counter() - t0
    fam = " ".join(f"{f}={np.mean(v):.4f}" for f, v in sel.family_scores.items())
    print(f"| {name} | {sel.chosen} | {sel.huber_k:g} | {fam} | {sel.n_ranges} | {dt:.1f} |", flush=True)
    return sel.chosen


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--real", nargs="*", default=[])
    ap.add_argument("--basis", choices=("eskf", "solve"), default="eskf",
                    help="residuals about the ESKF run (eskf) or the batch's first free solve (solve, as calibrate)")
    a = ap.parse_args()
    print("| log | chosen | Huber k | mean held-out score per family | ranges | select [s] |")
    print("| --- | --- | --- | --- | --- | --- |")
    right = {"white": 0, "direction": 0, "drift": 0}
    for seed in range(1, a.seeds + 1):
        base = simulate(builtin_scenario("calibration-flight").updated(duration=60.0, seeds={"noise": seed}))
        right["white"] += row(f"sim white, seed {seed}", base, a.basis) == "white"
        right["direction"] += row(f"sim direction bias, seed {seed}", with_direction_bias(base), a.basis) == "direction"
        ar1 = ar1_ranges(base, 0.10, 3.0, 1000 + seed)
        right["drift"] += row(f"sim AR(1) 3 s, seed {seed}", ar1, a.basis) == "drift"
    print(f"\ntrue family chosen: {', '.join(f'{k} {v}/{a.seeds}' for k, v in right.items())}")
    from uwbimu.io.loader import load_dataset

    for folder in a.real:
        row(folder, load_dataset(folder), a.basis)


if __name__ == "__main__":
    main()
