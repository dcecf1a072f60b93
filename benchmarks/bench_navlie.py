"""Per-sample cost against navlie (decargroup/navlie), the best-known Python peer, in the same run.

    python benchmarks/bench_navlie.py [--seconds 20]

Both filters run the same simulated ``calibration-flight`` (200 Hz IMU, 50 Hz ranges to 8 anchors):

* navlie: ``ExtendedKalmanFilter`` with ``IMUKinematics`` (15 states: SE_2(3) + biases; no lever arm,
  no time offset) and a range model from the IMU position (navlie's default finite-difference
  Jacobian), one ``predict`` per IMU sample and one ``correct`` per range, as ``run_filter`` does;
  started from the truth;
* uwbimu: the streaming :class:`uwbimu.estimation.Eskf` (21+ states with lever arm and t_d), one
  ``push_imu`` per sample and one ``push_range`` per range, after initialisation; and ``run_eskf``
  over the whole log.

Prints CPU microseconds per IMU sample (ranges included) and the ratios.  navlie is not a dependency:
without it (``pip install`` it with its ``pymlg``) the script says so and measures uwbimu only.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from uwbimu.estimation import Eskf, EskfOptions, run_eskf
from uwbimu.sim import builtin_scenario, simulate


def navlie_cost(ds, seconds: float):
    """CPU seconds per IMU sample of navlie's EKF over the first ``seconds`` of the log (or None)."""
    try:
        import navlie as nav
        from navlie.lib.imu import IMU, IMUKinematics, IMUState
    except Exception as exc:  # noqa: BLE001 - any import problem means "not available"
        print(f"navlie not available ({type(exc).__name__}: {exc}); uwbimu only")
        return None

    class Range(nav.MeasurementModel):
        def __init__(self, anchor, var):
            self.a = np.asarray(anchor, float)
            self.R = np.array([[var]])

        def evaluate(self, x):
            return np.array([np.linalg.norm(self.a - x.position)])

        def covariance(self, x):
            return self.R

    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    imu = imu[imu[:, 0] <= imu[0, 0] + seconds]
    uwb = ds.uwb[ds.uwb["t"] <= imu[-1, 0]]
    anchors = {str(a): r for a, r in zip(ds.anchors["anchor"], ds.anchors[["x", "y", "z"]].to_numpy(float))}
    gt = ds.groundtruth
    from uwbimu.models.quaternion import quat_to_rotmat

    q0 = gt[["qw", "qx", "qy", "qz"]].to_numpy(float)[0]
    T = np.eye(5)
    T[:3, :3] = quat_to_rotmat(q0)
    T[:3, 3] = gt[["vx", "vy", "vz"]].to_numpy(float)[0] if "vx" in gt else 0.0
    T[:3, 4] = gt[["px", "py", "pz"]].to_numpy(float)[0]
    x = IMUState(T, np.zeros(3), np.zeros(3), stamp=float(imu[0, 0]))
    P = np.eye(15) * 0.01
    Q = np.eye(12) * 1e-4
    ekf = nav.ExtendedKalmanFilter(IMUKinematics(Q, gravity=np.array([0, 0, -9.81])))
    est = nav.StateWithCovariance(x, P)
    tu = uwb["t"].to_numpy(float)
    au = uwb["anchor"].astype(str).to_numpy()
    ru = uwb["range"].to_numpy(float)
    j = 0
    c0 = time.process_time()
    for k in range(len(imu) - 1):
        u = IMU(imu[k, 4:7], imu[k, 1:4], imu[k, 0])
        while j < len(tu) and tu[j] <= imu[k + 1, 0]:
            est = ekf.correct(est, nav.Measurement(ru[j], tu[j], Range(anchors[au[j]], 0.01)), u)
            j += 1
        est = ekf.predict(est, u, dt=imu[k + 1, 0] - imu[k, 0])
    cost = (time.process_time() - c0) / (len(imu) - 1)
    # sanity: navlie's filter did real work (its position ends near the truth)
    td = ds.meta.truth.time_offset or 0.0
    i = int(np.argmin(np.abs(gt["t"].to_numpy(float) - (imu[-1, 0] - td))))
    err = np.linalg.norm(est.state.position - gt[["px", "py", "pz"]].to_numpy(float)[i])
    print(f"navlie: final position error {100 * err:.1f} cm after {imu[-1, 0] - imu[0, 0]:.0f} s")
    return cost


def uwbimu_cost(ds):
    opts = EskfOptions(store_covariance=False)
    run_eskf(ds, opts)  # JIT warm-up
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    tu = ds.uwb["t"].to_numpy(float)
    au = ds.uwb["anchor"].astype(str).to_numpy()
    ru = ds.uwb["range"].to_numpy(float)
    td = ds.meta.truth.time_offset or 0.0
    f = Eskf.for_dataset(ds, opts)
    j = 0
    cpu = 0.0
    n = 0
    for row in imu:
        c0 = time.process_time()
        while j < len(tu) and tu[j] + td <= row[0]:
            f.push_range(tu[j], au[j], ru[j])
            j += 1
        f.push_imu(row[0], row[1:4], row[4:7])
        if f.initialised:
            cpu += time.process_time() - c0
            n += 1
    f.finish()
    c0 = time.process_time()
    run_eskf(ds, opts)
    batch = (time.process_time() - c0) / len(imu)
    return cpu / max(n, 1), batch


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seconds", type=float, default=20.0, help="navlie runs on this much of the log")
    a = ap.parse_args()
    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 60.0}))
    stream, batch = uwbimu_cost(ds)
    nv = navlie_cost(ds, a.seconds)
    print(f"uwbimu Eskf, push_imu/push_range per sample: {1e6 * stream:.1f} us CPU per IMU sample")
    print(f"uwbimu run_eskf (whole log, incl. initialiser): {1e6 * batch:.1f} us CPU per IMU sample")
    if nv is not None:
        print(f"navlie EKF predict/correct per sample (15 states, FD range Jacobian): {1e6 * nv:.1f} us CPU "
              f"per IMU sample")
        print(f"ratios: navlie / uwbimu streaming {nv / stream:.1f}x, navlie / uwbimu run_eskf {nv / batch:.1f}x")


if __name__ == "__main__":
    main()
