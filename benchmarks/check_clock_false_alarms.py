"""False-alarm rate of the clock-fault check on logs whose errors are not white.

One command::

    PYTHONPATH=src python benchmarks/check_clock_false_alarms.py [--seeds 50] [--real /tmp/inrol /tmp/isas]

Null cases (no clock fault): the built-in 60 s calibration flight with per-anchor AR(1) range
errors added (correlation times 1, 3 and 5 s; 10-20 cm: multipath and vibration the filter's
white range model does not know) and the built-in ``nlos`` scenario (NLOS background and
bursts), noise seeds 0..N-1.  Prints, per case and in total, the logs with a clock event
(:func:`~uwbimu.eval.clock_faults.detect_clock_faults`: the tests alone, no re-run) and the
measured rate with its exact (Clopper-Pearson) 95 % interval next to the nominal level
(2 alpha per log: two tests at alpha each).  Real logs given with ``--real`` (imported dataset
folders) go through the whole check (re-runs included) and print their events.
"""

from __future__ import annotations

import argparse
import copy

import numpy as np
from scipy.stats import beta

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.eval.clock_faults import detect_clock_faults, handle_clock_faults
from uwbimu.eval.clock_windows import ALPHA, consistency_tests, windowed_time_offsets
from uwbimu.sim import builtin_scenario, simulate

CASES = {"ar1 1 s 10 cm": (0.10, 1.0), "ar1 3 s 10 cm": (0.10, 3.0), "ar1 5 s 20 cm": (0.20, 5.0), "nlos": None}


def ar1_ranges(ds, sigma: float, tau: float, seed: int):
    """``ds`` with per-anchor AR(1) range errors (sd ``sigma`` [m], correlation time ``tau`` [s])."""
    rng = np.random.default_rng(seed)
    u = ds.uwb.copy()
    r, t, a = u["range"].to_numpy().copy(), u["t"].to_numpy(), u["anchor"].to_numpy()
    for name in np.unique(a):
        idx = np.flatnonzero(a == name)
        rho = np.exp(-np.diff(t[idx], prepend=t[idx[0]]) / tau)
        rho[0] = 0.0
        e = 0.0
        for i, p, wn in zip(idx, rho, rng.standard_normal(len(idx))):
            e = p * e + np.sqrt(1 - p * p) * sigma * wn
            r[i] += e
    u["range"] = r
    out = copy.copy(ds)
    out.uwb = u
    return out


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = 1 - level
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--real", nargs="*", default=[], help="imported dataset folders (INRoL, ISAS-Walk)")
    args = ap.parse_args()
    total_k = total_n = 0
    print(f"{'case':16s} {'logs':>5s} {'events':>6s} {'max z/crit':>10s} {'median phi':>10s}")
    for name, spec in CASES.items():
        k, zmax, phis = 0, 0.0, []
        for seed in range(args.seeds):
            if spec is None:
                ds = simulate(builtin_scenario("nlos").updated(seeds={"noise": seed}))
            else:
                base = simulate(builtin_scenario("calibration-flight").updated(duration=60.0, seeds={"noise": seed}))
                ds = ar1_ranges(base, spec[0], spec[1], 1000 + seed)
            res = run_eskf(ds, EskfOptions())
            k += bool(detect_clock_faults(res, ds))
            c = consistency_tests(windowed_time_offsets(res), float(res.t[0]))
            if "scale" in c:
                zmax = max(zmax, c["z_jump"] / c["crit_jump"], c["z_drift"] / c["crit_drift"])
                phis.append(c["phi"])
        total_k, total_n = total_k + k, total_n + args.seeds
        print(f"{name:16s} {args.seeds:5d} {k:6d} {zmax:10.2f} {np.median(phis) if phis else np.nan:10.2f}")
    lo, hi = clopper_pearson(total_k, total_n)
    print(f"false-alarm rate {total_k}/{total_n} = {total_k / total_n:.4f} (95 % CI {lo:.4f} .. {hi:.4f}); "
          f"nominal <= {2 * ALPHA:g} per log")
    from uwbimu.io.loader import load_dataset

    for folder in args.real:
        ds = load_dataset(folder)
        res = run_eskf(ds, EskfOptions())
        out, _ = handle_clock_faults(res, ds, lambda d: run_eskf(d, EskfOptions()))
        ev = [e for e in out.events if str(e.get("kind", "")).startswith("clock_") or e.get("kind") == "check_skipped"]
        print(f"{folder}: {[(e['kind'], e.get('corrected', e.get('reason'))) for e in ev] or 'no clock event'}")


if __name__ == "__main__":
    main()
