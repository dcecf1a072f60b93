"""Forward-backward smoothing against the causal filter on every built-in scenario.

    python benchmarks/check_smoother.py [--duration 30] [--scenarios NAME ...] [--seeds N ...] [--blocks]
        [--cost MINUTES]

Per scenario (``builtin_scenario(NAME).updated(duration=...)``, default seeds): ``run_eskf`` with
``smoother="off"`` and ``"forward_backward"`` (what ``uwbimu estimate`` runs), the position RMSE and the position
NEES (3 dof, :func:`uwbimu.metrics.filter.compute_metrics`) of each, and the smoothed run's t_d verdict and the
passes' agreement factors (event ``forward_backward``).  ``--seeds N ...``: each scenario with noise seed N
(truth seed 0, init seed N + 1: the flights of ``tests/test_smoother.py``), and the t_d of both passes.  ``--blocks``: also the mean NEES of position, velocity and
attitude (3 dof each) on the full 60 s demo flight (``calibration-flight``), filter and smoothed, with the truth
taken at each state's IMU stamp (``truth_at(ds, t_imu - t_d)``).  ``--cost MINUTES``: the CPU time of
``run_eskf`` with and without smoothing on a calibration flight that long.
"""

from __future__ import annotations

import argparse

import numpy as np


def block_nees(ds, r) -> dict[str, float]:
    """Mean NEES of the position, velocity and attitude blocks of run ``r`` against the simulated truth."""
    from uwbimu.metrics.filter import attitude_error, truth_at
    from uwbimu.models import state as S

    tt = np.asarray(r.t_imu) - ds.meta.truth.time_offset
    p, q, v, ok = truth_at(ds, tt)
    X, C = r.states, r.covariances
    out = {}
    for name, sl, e in (("position", S.EP, X[:, S.P] - p), ("velocity", S.EV, X[:, S.V] - v),
                        ("attitude", S.ETH, attitude_error(X[:, S.Q], q))):
        n = np.einsum("ki,ki->k", e, np.linalg.solve(C[:, sl, sl], e[..., None])[..., 0])
        out[name] = float(np.nanmean(n[ok]))
    return out


def main() -> int:
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.metrics.filter import compute_metrics
    from uwbimu.sim import builtin_scenario, simulate
    from uwbimu.sim.builtin import list_scenarios

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=30.0)
    ap.add_argument("--scenarios", nargs="+", default=None, help="default: every built-in scenario")
    ap.add_argument("--seeds", type=int, nargs="+", default=None, help="noise seeds (default: the scenario's)")
    ap.add_argument("--blocks", action="store_true", help="per-block NEES on the 60 s demo flight")
    ap.add_argument("--cost", type=float, default=None, metavar="MINUTES", help="CPU time on a flight this long")
    a = ap.parse_args()
    names = a.scenarios or list(list_scenarios())
    print(f"{'scenario':20s} {'RMSE filter':>11s} {'smoothed':>9s} {'NEES_p filter':>13s} {'smoothed':>9s}  "
          f"t_d verdict; agreement factors (position, velocity, attitude)")
    runs = [(name, None) for name in names] if a.seeds is None else [(n, k) for n in names for k in a.seeds]
    for name, seed in runs:
        sc = builtin_scenario(name).updated(duration=a.duration)
        if seed is not None:
            sc = sc.updated(seeds={"truth": 0, "noise": seed, "init": seed + 1})
        ds = simulate(sc)
        f = run_eskf(ds, EskfOptions(smoother="off"))
        s = run_eskf(ds, EskfOptions(smoother="forward_backward"))
        mf, ms = compute_metrics(f, ds), compute_metrics(s, ds)
        ag = (s.extra.get("forward_backward") or {}).get("agreement", {})
        fac = ", ".join(f"{ag[b]['factor']:.2f}" if b in ag else "-" for b in ("position", "velocity", "attitude"))
        td = (s.extra.get("forward_backward") or {}).get("calibration", {}).get("time_offset")
        tds = "" if td is None else (f"; t_d forward {1e3 * td['forward']:.1f}, backward {1e3 * td['backward']:.1f} -> "
                                     f"{1e3 * td['value']:.1f} +- {1e3 * td['sd']:.1f} ms")
        label = name if seed is None else f"{name} s{seed}"
        print(f"{label:20s} {mf['position_rmse']:11.3f} {ms['position_rmse']:9.3f} {mf['nees_position_mean']:13.2f} "
              f"{ms['nees_position_mean']:9.2f}  {s.calibration.get('time_offset_verdict')}; {fac}{tds}", flush=True)
    if a.blocks:
        ds = simulate(builtin_scenario("calibration-flight"))
        for sm in ("off", "forward_backward"):
            nees = block_nees(ds, run_eskf(ds, EskfOptions(smoother=sm)))
            print(f"demo flight 60 s, smoother {sm}: " + ", ".join(f"{k} NEES {v:.2f}" for k, v in nees.items())
                  + " (3 dof each)")
    if a.cost:
        import time

        ds = simulate(builtin_scenario("calibration-flight").updated(duration=60.0 * a.cost))
        for sm in ("off", "forward_backward"):
            c0 = time.process_time()
            r = run_eskf(ds, EskfOptions(smoother=sm))
            print(f"{a.cost:g} min flight ({len(ds.imu)} IMU samples, {len(r.t)} outputs), smoother {sm}: "
                  f"run_eskf {time.process_time() - c0:.2f} CPU s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
