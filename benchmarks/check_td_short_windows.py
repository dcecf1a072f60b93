"""The ESKF's time offset in short windows of the demo flight: error, scatter against the reported sd, and the
start-up transient.

    python benchmarks/check_td_short_windows.py [--windows 4] [--seeds 1 11 12 13 14] [--start default|truth]
        [--tight] [--td 0.03] [--hold S] [--batch] [--smoother off|forward_backward] [--reversed]

The demo's repeatability table runs ``run_eskf(window, EskfOptions())`` on 4 windows of 15 s of the
``calibration-flight`` simulation.  Here the same windows of several noise seeds (the trajectory is the
same; ``--td`` sets the simulated t_d) give, over all windows: the mean t_d error and its standard error,
the RMS error against the RMS reported sd (``z_rms``: 1 when the sd is honest), and the mean t_d error at
0.5, 1, 2, 5, 10 and 14.5 s after each window's start (the transient).

``--start truth`` is a controlled experiment, never an estimator: the initialiser runs as usual (grid
search and bootstrap off), then its state is replaced by the truth (position, velocity, attitude, IMU
biases, lever arm and t_d) while its covariance is kept; ``--tight`` also shrinks the initial sds of
everything but t_d (position and velocity 0.05, roll/pitch 1 deg, yaw 2 deg, lever arm 0.02 m, IMU biases
0.0005 rad/s and 0.005 m/s^2).  An exact start with the default covariance still drifts t_d (the
start-up transient of the joint estimate); with the tight covariance it does not.

``--hold S`` is a controlled experiment too: every filter pass holds t_d in consider mode (Schmidt: its
prior covariance and cross-covariances kept, never corrected) for its first S seconds of ranges, then
releases it.  It tests whether the final error comes from t_d absorbing the start-up errors of the other
states while their covariances are large.  ``--batch`` also runs the batch estimator (registry ``batch``,
its default options; about 10 s a window) on the same windows and prints its error and z_rms, and the
mean ESKF - batch difference: the part of the error that is the filter's, not the data's.

Measured (2026-11, seeds 1 11 12 13 14, 4 windows of 15 s): default start -13.4 ms mean error (standard
error 5.3), z_rms 2.75; ``--hold 2`` / ``--hold 4`` leave it (-13.6 / -12.9 ms, z_rms 2.45 / 2.37), and so
does ``--start truth --hold 8`` (-9.6 +- 16 ms at the end); the batch estimator on the same windows: -4.2 ms
(standard error 4.3), RMS 19.0 ms, z_rms 1.33; ESKF - batch -9.2 ms (sd 14.5), correlation 0.79.  The
posterior CRLB of t_d per window (default initial covariance, uninformative t_d prior) is 9-14 ms, about
the filter's reported sd: the filter reports the information of the data but, linearised at its own
estimates on a start from large covariances, does not reach it on windows this short (2 windows of 30 s:
z_rms 1.50; 8 of 7.5 s: 3.25).

With the forward-backward smoothing (2026-11-29, same seeds and windows): ``--reversed`` (the filter over each
window reversed in time) +4.1 ms (s.e. 5.0), z_rms 1.90; ``--smoother forward_backward`` -4.2 ms (s.e. 4.7), RMS
21.0 ms, z_rms 1.62, and with ``--batch`` the batch (now started from the smoothed run) -4.0 ms (s.e. 4.3), z_rms
1.34.  With the smoother the transient trace is the causal filter's track (``smoother.causal_view``).

``--start truth --tight-only BLOCKS`` tightens the initial sd of some blocks only (measured 2026-11-29, same
seeds and windows; exact start, default sds: -12.0 ms, s.e. 3.6, z_rms 1.90): position -10.7, velocity
-11.7, attitude -7.3, lever arm -8.2, gyro bias -8.5, accelerometer bias -6.7, attitude + lever arm -4.7,
attitude + velocity + position -6.0, all six -0.7 ms (s.e. 1.8, z_rms 0.91).  No one block makes the bias:
each loose block the filter linearises about after its first updates adds to it, as expected of an EKF
started from large covariances on a window whose t_d information is weak.
"""

from __future__ import annotations

import argparse

import numpy as np

MARKS_S = (0.5, 1.0, 2.0, 5.0, 10.0, 14.5)


def _truth_start(state: dict):
    """Wrap ``streaming.initialise`` so that its state is replaced by the truth of ``state['window']``."""
    import uwbimu.estimation.streaming as st_mod
    from uwbimu.metrics.filter import truth_at
    from uwbimu.models import state as S

    orig = st_mod.initialise

    def patched(prob, opts, pr, j0=0, td_known=None):
        st = orig(prob, opts, pr, j0=j0, td_known=td_known)
        w = state["window"]
        td = float(w.meta.truth.time_offset)
        p, q, v, _ = truth_at(w, np.array([prob.imu_t[st.k] - td]))
        bias = w.meta.extra["imu_bias"]
        st.x[S.P], st.x[S.V], st.x[S.Q] = p[0], v[0], q[0]
        st.x[S.BA], st.x[S.BG] = bias["accel_initial"], bias["gyro_initial"]
        st.x[S.PIU], st.x[S.TD] = w.meta.truth.lever_arm, td
        return st

    st_mod.initialise = patched


def _hold_time_offset(seconds: float) -> None:
    """Patch the streaming filter so that each pass holds t_d in consider mode for its first ``seconds``
    of ranges (UWB clock), then releases it with its covariance as the consider updates left it."""
    import uwbimu.estimation.streaming as st_mod
    from uwbimu.models import state as S

    start0, advance0 = st_mod.Eskf._start, st_mod.advance

    def start(self, init):
        start0(self, init)
        p, s = self._prob, self._st
        if p.gain_mask[S.ETD] > 0:  # estimated (not already held by the initialiser's verdict)
            s.td_full_mask = p.gain_mask
            held = p.gain_mask.copy()
            held[S.ETD] = 0.0
            p.gain_mask = held
            s.td_release = float(p.uwb_t[s.j]) + seconds

    def advance(p, s, rec, final, t_uwb_end=np.inf, record=True, to_end=True, t_safe=-np.inf, **kw):
        rel = getattr(s, "td_release", None)
        if rel is not None:
            # up to the release stamp only (outputs too: they must not run ahead of the held part)
            advance0(p, s, rec, final, t_uwb_end=min(t_uwb_end, rel), record=record, to_end=False,
                     t_safe=min(t_safe, rel + float(s.x[S.TD])), **kw)
            m = p.uwb_t.shape[0]
            reached = (s.j < m and p.uwb_t[s.j] > rel) or (s.j >= m and final)
            if s.diverged is not None or not reached:
                return
            p.gain_mask, s.td_release = s.td_full_mask, None
        advance0(p, s, rec, final, t_uwb_end=t_uwb_end, record=record, to_end=to_end, t_safe=t_safe, **kw)

    st_mod.Eskf._start = start
    st_mod.advance = advance


def _batch_error(w, td_true: float) -> tuple[float, float]:
    """t_d error and sd [ms] of the batch estimator (registry ``batch``, default options) on window ``w``."""
    import uwbimu.estimators  # noqa: F401  (registers the batch estimator)
    from uwbimu.estimation.registry import get_estimator

    e = get_estimator("batch")
    td = e.run(w, e.options(None), None).calibration["time_offset"]
    return 1e3 * (float(td["value"]) - td_true), 1e3 * float(td["sd"])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--windows", type=int, default=4)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 11, 12, 13, 14], help="noise seeds (1: the demo's)")
    ap.add_argument("--start", choices=("default", "truth"), default="default")
    ap.add_argument("--tight", action="store_true", help="with --start truth: tight initial sds but t_d's")
    ap.add_argument("--tight-only", type=str, default=None, metavar="BLOCKS",
                    help="with --start truth: tight initial sds of these blocks only (comma list of position, "
                         "velocity, attitude, lever, gyro_bias, accel_bias): which loose start makes the bias")
    ap.add_argument("--td", type=float, default=None, help="simulated t_d [s] (default: the scenario's, 0.03)")
    ap.add_argument("--hold", type=float, default=0.0, metavar="S",
                    help="experiment: hold t_d in consider mode for the first S seconds of each pass")
    ap.add_argument("--batch", action="store_true", help="also run the batch estimator on the same windows")
    ap.add_argument("--smoother", choices=("off", "forward_backward"), default="off",
                    help="EskfOptions.smoother (forward_backward: what uwbimu estimate and the demo run)")
    ap.add_argument("--reversed", action="store_true",
                    help="experiment: the filter on each window reversed in time (uwbimu.estimation.smoother."
                         "reverse_dataset), its t_d mapped back (negated); no transient trace")
    a = ap.parse_args()

    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.eval.repeatability import split_windows
    from uwbimu.models import state as S
    from uwbimu.sim import builtin_scenario, simulate

    over: dict = {}
    state: dict = {}
    if a.start == "truth":
        _truth_start(state)
        over["init"] = {"search_time_offset": False, "refine_s": 0.0}
        blocks = ({"position", "velocity", "attitude", "lever", "gyro_bias", "accel_bias"} if a.tight else
                  set(filter(None, (a.tight_only or "").split(","))))
        tight = {"position": lambda: over["init"].update(position_sd=0.05),
                 "velocity": lambda: over["init"].update(velocity_sd=0.05),
                 "attitude": lambda: over["init"].update(roll_pitch_sd_deg=1.0, yaw_sd_deg=2.0),
                 "lever": lambda: over.update(lever_arm={"prior_sd": 0.02}),
                 "gyro_bias": lambda: over.update(gyro_bias_sd=0.0005),
                 "accel_bias": lambda: over.update(accel_bias_sd=0.005)}
        unknown = blocks - set(tight)
        if unknown:
            ap.error(f"--tight-only: unknown block(s) {sorted(unknown)}; choose from {sorted(tight)}")
        for b in blocks:
            tight[b]()
    if a.hold > 0:
        _hold_time_offset(a.hold)
    opts = EskfOptions(**over, smoother=a.smoother)
    errs, sds, trace, b_errs, b_sds = [], [], [], [], []
    for seed in a.seeds:
        sc = builtin_scenario("calibration-flight")
        if seed != 1:
            sc = sc.updated(seeds={"truth": 0, "noise": seed, "init": seed + 1})
        if a.td is not None:
            sc = sc.updated(time_offset=a.td)
        ds = simulate(sc)
        for w in split_windows(ds, a.windows):
            state["window"] = w
            td_true = float(w.meta.truth.time_offset)
            if a.reversed:
                from uwbimu.estimation.smoother import reverse_dataset

                r = run_eskf(reverse_dataset(w), opts)
                errs.append(1e3 * (-float(r.calibration["time_offset"]) - td_true))
                trace.append(np.full(len(MARKS_S), np.nan))
            else:
                from uwbimu.estimation.smoother import causal_view

                r = run_eskf(w, opts)
                errs.append(1e3 * (float(r.calibration["time_offset"]) - td_true))
                c = causal_view(r)  # the transient is the filter's track (a smoothed one is one constant)
                t = np.asarray(c.t, float) - float(w.imu_t[0])
                trace.append(np.interp(MARKS_S, t, 1e3 * (np.asarray(c.states)[:, S.TD] - td_true), right=np.nan))
            sds.append(1e3 * float(r.calibration["time_offset_sd"]))
            line = (f"seed {seed:3d} window {w.imu_t[0]:5.1f}-{w.imu_t[-1]:5.1f} s: t_d error {errs[-1]:+7.1f} ms, "
                    f"reported sd {sds[-1]:5.1f} ms")
            if a.batch:
                be, bs = _batch_error(w, td_true)
                b_errs.append(be)
                b_sds.append(bs)
                line += f"; batch {be:+7.1f} ms (sd {bs:5.1f})"
            print(line, flush=True)
    e, s = np.array(errs), np.array(sds)
    print(f"{len(e)} windows, start {a.start}{' (tight)' if a.tight else ''}: mean error {e.mean():+.1f} ms "
          f"(standard error {e.std(ddof=1) / np.sqrt(len(e)):.1f}), RMS error {np.sqrt(np.mean(e**2)):.1f} ms, "
          f"RMS reported sd {np.sqrt(np.mean(s**2)):.1f} ms, z_rms {np.sqrt(np.mean((e / s) ** 2)):.2f}")
    if a.batch:
        be, bs = np.array(b_errs), np.array(b_sds)
        print(f"batch: mean error {be.mean():+.1f} ms (standard error {be.std(ddof=1) / np.sqrt(len(be)):.1f}), RMS error "
              f"{np.sqrt(np.mean(be**2)):.1f} ms, RMS reported sd {np.sqrt(np.mean(bs**2)):.1f} ms, z_rms "
              f"{np.sqrt(np.mean((be / bs) ** 2)):.2f}; ESKF - batch {np.mean(e - be):+.1f} ms (sd {np.std(e - be, ddof=1):.1f}), "
              f"correlation {np.corrcoef(e, be)[0, 1]:.2f}")
    tr = np.array(trace)
    for m, mean, sd in ([] if a.reversed else zip(MARKS_S, np.nanmean(tr, axis=0), np.nanstd(tr, axis=0))):
        print(f"  {m:5.1f} s after the window start: mean t_d error {mean:+7.1f} ms (sd {sd:5.1f})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
