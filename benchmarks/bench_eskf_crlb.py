"""Calibration states against the posterior Cramér-Rao bound (issue 11 item 6).

M noise seeds of the built-in 90 s excited flight; the filter starts from the
truth perturbed by a draw of its own prior (a consistent Bayesian start); the
bound is :func:`uwbimu.estimation.crlb.posterior_crlb` with the same prior and
Jacobians at the true trajectory.  Prints, per lever-arm axis and for t_d:
RMS error, sqrt(mean CRLB), their ratio (target <= 1.15) and RMS(error / sd)
(target 0.8..1.2).  Usage::

    PYTHONPATH=src python benchmarks/bench_eskf_crlb.py --seeds 40 [--data-start] [--noise data|preset]
        [--smoother off|forward_backward]

``--smoother forward_backward`` (what ``uwbimu estimate`` runs): the reported lever arm and t_d are the
mean of the forward pass (from the truth-draw start) and a pass over the reversed log (its own data-driven
start), with half their difference in the sd.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from uwbimu.estimation import EskfOptions, InitialState, run_eskf
from uwbimu.estimation.crlb import posterior_crlb
from uwbimu.estimation.eskf import build_problem
from uwbimu.models.state import boxplus
from uwbimu.sim import builtin_scenario, simulate_full

NAMES = ["lever x", "lever y", "lever z", "t_d"]


def truth_states(sim) -> np.ndarray:
    """(n, 20) truth at every IMU sample (row k of the ground truth is IMU sample k)."""
    ds = sim.dataset
    gt = ds.groundtruth
    X = np.zeros((len(gt), 20))
    X[:, 0:3] = gt[["px", "py", "pz"]].to_numpy()
    X[:, 3:6] = gt[["vx", "vy", "vz"]].to_numpy()
    X[:, 6:10] = gt[["qw", "qx", "qy", "qz"]].to_numpy()
    X[:, 10:13] = sim.accel_bias
    X[:, 13:16] = sim.gyro_bias
    X[:, 16:19] = ds.meta.truth.lever_arm
    X[:, 19] = ds.meta.truth.time_offset
    return X


def one_seed(seed: int, duration: float, opts: EskfOptions, scenario: str = "excited-90s",
             data_start: bool = False):
    """Returns (error (4,), filter sd (4,), CRLB sd (4,)) of lever arm and t_d at the end.

    ``data_start``: the filter initialises itself from the data (default initialiser); the bound then
    uses the options' calibration priors (lever arm ``lever_arm.prior_sd``, t_d the uniform spread of the
    initial grid) with the same motion-state prior as the truth start."""
    sc = builtin_scenario(scenario)
    sc = sc.model_copy(update={"duration": duration, "seeds": sc.seeds.model_copy(update={"noise": seed})})
    sim = simulate_full(sc)
    ds = sim.dataset
    X = truth_states(sim)
    td = ds.meta.truth.time_offset
    k0 = int(np.searchsorted(ds.imu_t, ds.uwb["t"].iloc[0] + td))
    noise = ds.meta.imu_noise
    sd0 = np.r_[np.full(3, 0.1), np.full(3, 0.1), np.radians([2.0, 2.0, 5.0]),
                np.full(3, noise.accel_bias_sigma0), np.full(3, noise.gyro_bias_sigma0), np.full(3, 0.05), 0.01]
    P0 = np.diag(sd0**2)
    rng = np.random.default_rng(1000 + seed)
    dx = rng.normal(size=19) * sd0
    dx[9:15] = 0.0  # the simulator drew the biases from N(0, sigma0^2): zero is the consistent prior mean
    x0 = boxplus(X[k0], dx)
    x0[10:16] = 0.0
    if data_start:
        res = run_eskf(ds, opts)
        g = np.asarray(opts.init.td_grid)
        P0 = P0.copy()
        P0[15:18, 15:18] = np.eye(3) * opts.lever_arm.prior_sd**2
        P0[18, 18] = (g.max() - g.min()) ** 2 / 12.0
    else:
        res = run_eskf(ds, opts, initial=InitialState(x=x0, P=P0, k=k0, j=0))
    cal = res.calibration
    est = np.r_[cal["lever_arm"], cal["time_offset"]]
    sd = np.r_[cal["lever_arm_sd"], cal["time_offset_sd"]]
    err = est - np.r_[ds.meta.truth.lever_arm, td]
    prob, _ = build_problem(ds, opts)
    Pc = posterior_crlb(prob, X, P0, k0)
    return err, sd, np.sqrt(np.diag(Pc)[15:19])


def table(seeds: list[int], duration: float, opts: EskfOptions, data_start: bool = False) -> dict:
    rows = [one_seed(s, duration, opts, data_start=data_start) for s in seeds]
    E = np.array([r[0] for r in rows])
    S = np.array([r[1] for r in rows])
    C = np.array([r[2] for r in rows])
    rms = np.sqrt(np.mean(E**2, axis=0))
    crlb = np.sqrt(np.mean(C**2, axis=0))
    return {"rms": rms, "crlb": crlb, "ratio": rms / crlb, "nerr": np.sqrt(np.mean((E / S) ** 2, axis=0)),
            "sd": np.sqrt(np.mean(S**2, axis=0))}


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=40)
    ap.add_argument("--duration", type=float, default=90.0)
    ap.add_argument("--data-start", action="store_true", help="data-driven initialiser instead of a truth-draw start")
    ap.add_argument("--noise", choices=["data", "preset"], default="data",
                    help="the ESKF's noise mode (default: 'data', the noise from the log, as uwbimu estimate)")
    ap.add_argument("--smoother", choices=["off", "forward_backward"], default="off")
    a = ap.parse_args()
    t0 = time.process_time()
    out = table(list(range(a.seeds)), a.duration, EskfOptions(store_covariance=False, noise=a.noise,
                                                                smoother=a.smoother), a.data_start)
    start = "data-driven start" if a.data_start else "start: truth + prior draw"
    print(f"{a.seeds} seeds x {a.duration:g} s excited flight, {start}, noise: {a.noise}, smoother: {a.smoother} "
          f"({time.process_time() - t0:.0f} CPU s)")
    print(f"{'state':8s} {'RMS err':>10s} {'CRLB':>10s} {'ratio':>6s} {'RMS(e/sd)':>9s} {'mean sd':>10s}")
    for i, n in enumerate(NAMES):
        u, f = ("ms", 1e3) if n == "t_d" else ("mm", 1e3)
        print(f"{n:8s} {f * out['rms'][i]:8.3f}{u} {f * out['crlb'][i]:8.3f}{u} {out['ratio'][i]:6.2f} "
              f"{out['nerr'][i]:9.2f} {f * out['sd'][i]:8.3f}{u}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
