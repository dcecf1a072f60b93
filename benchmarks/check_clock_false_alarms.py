"""False-alarm rate of the clock-fault check on logs whose errors are not white.

One command::

    PYTHONPATH=src python benchmarks/check_clock_false_alarms.py [--seeds 20] [--alpha 1e-4]
        [--real /tmp/ds/inrol2 /tmp/ds/isas2 /tmp/ds/cf3 /tmp/ds/cf16]

Null cases (no clock fault): the built-in 60 s calibration flight with per-anchor AR(1) range
errors added (correlation times 1, 3 and 5 s; 10-20 cm: multipath and vibration the filter's
white range model does not know) and the built-in ``nlos`` scenario (NLOS background and
bursts), noise seeds 0..N-1.  Each log goes through the whole check
(:func:`~uwbimu.eval.clock_faults.handle_clock_faults`, re-runs included).  Printed per case and
in total: the logs whose window tests fired (``candidates``: the first stage alone, the filter's
sds) and the logs with a fault declared and corrected (``false alarms``: the check's outcome,
after :func:`~uwbimu.eval.clock_faults.confirm_fault`), the latter with its exact
(Clopper-Pearson) 95 % interval next to the nominal level (2 alpha per log: two tests at alpha
each).  The stated alpha (1e-4) cannot be resolved by a few dozen logs; ``--alpha 0.01`` runs the
same check at a level that can.  Real logs given with ``--real`` (imported dataset folders) go
through the whole check and print their events (a log stamped by one clock: ``check_skipped``).
"""

from __future__ import annotations

import argparse
import copy

import numpy as np
from scipy.stats import beta

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.eval.clock_faults import handle_clock_faults
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


def null_log(case: str, seed: int):
    """One fault-free log of ``case`` (a key of :data:`CASES`) with noise seed ``seed``."""
    spec = CASES[case]
    if spec is None:
        return simulate(builtin_scenario("nlos").updated(seeds={"noise": seed}))
    base = simulate(builtin_scenario("calibration-flight").updated(duration=60.0, seeds={"noise": seed}))
    return ar1_ranges(base, spec[0], spec[1], 1000 + seed)


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    a = 1 - level
    lo = 0.0 if k == 0 else float(beta.ppf(a / 2, k, n - k + 1))
    hi = 1.0 if k == n else float(beta.ppf(1 - a / 2, k + 1, n - k))
    return lo, hi


def clock_events(res) -> list[dict]:
    return [e for e in res.events if str(e.get("kind", "")).startswith("clock_")]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--alpha", type=float, default=ALPHA, help="false-alarm probability of each test")
    ap.add_argument("--real", nargs="*", default=[], help="imported dataset folders")
    args = ap.parse_args()
    total_c = total_k = total_n = 0
    print(f"alpha = {args.alpha:g} per test")
    print(f"{'case':16s} {'logs':>5s} {'candidates':>10s} {'false alarms':>12s} {'max z/crit':>10s} "
          f"{'max z_cal/crit':>14s} {'median L':>8s}")
    for name in CASES:
        cand = k = 0
        zr, zc, lrv = [], [], []
        for seed in range(args.seeds):
            ds = null_log(name, seed)
            res = run_eskf(ds, EskfOptions())
            out, _ = handle_clock_faults(res, ds, lambda d: run_eskf(d, EskfOptions()), alpha=args.alpha)
            ev = clock_events(out)
            cand += bool(ev)
            k += any(e.get("corrected") for e in ev)
            for e in ev:
                zr.append(e["z"] / e["crit"])
                zc.append(e["z_calibrated"] / e["crit"])
                lrv.append(e["long_run_variance"])
        total_c, total_k, total_n = total_c + cand, total_k + k, total_n + args.seeds
        print(f"{name:16s} {args.seeds:5d} {cand:10d} {k:12d} {max(zr, default=np.nan):10.2f} "
              f"{max(zc, default=np.nan):14.2f} {np.median(lrv) if lrv else np.nan:8.2f}", flush=True)
    lo, hi = clopper_pearson(total_k, total_n)
    if total_n:
        print(f"candidates {total_c}/{total_n}; false alarms {total_k}/{total_n} = {total_k / total_n:.4f} "
              f"(95 % CI {lo:.4f} .. {hi:.4f}); nominal <= {2 * args.alpha:g} per log")
    from uwbimu.io.loader import load_dataset

    for folder in args.real:
        ds = load_dataset(folder)
        res = run_eskf(ds, EskfOptions())
        out, _ = handle_clock_faults(res, ds, lambda d: run_eskf(d, EskfOptions()), alpha=args.alpha)
        ev = [e for e in out.events if str(e.get("kind", "")).startswith("clock_") or e.get("kind") == "check_skipped"]
        c = consistency_tests(windowed_time_offsets(res), float(res.t[0]), args.alpha)
        print(f"{folder}: single_clock={getattr(ds.meta, 'single_clock', None)} window tests z/crit jump "
              f"{c.get('z_jump', np.nan) / c.get('crit_jump', np.nan):.2f} drift "
              f"{c.get('z_drift', np.nan) / c.get('crit_drift', np.nan):.2f}; events (kind, corrected, z, z_cal, L): "
              f"{[(e['kind'], e.get('corrected', e.get('reason')), round(e.get('z', np.nan), 2), round(e.get('z_calibrated', np.nan), 2), round(e.get('long_run_variance', np.nan), 2)) for e in ev] or 'no clock event'}",
              flush=True)


if __name__ == "__main__":
    main()
