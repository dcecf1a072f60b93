"""Posterior Cramer-Rao bounds of a simulated flight, for TWR and Loco TDoA (Monte Carlo reference).

For a scenario, the bound is the covariance of the linear-Gaussian problem
obtained by linearising the 19-dim error state (:mod:`uwbimu.models.state`)
at the *truth*: the ESKF's own error-state transition and process noise
(:func:`uwbimu.estimation.kernels.cov_step`, with the simulated IMU's noise
densities), its range Jacobian (:func:`~uwbimu.estimation.kernels.range_jacobian`,
lever arm and time offset included) and the simulated measurement schedule
(Tichavsky et al.'s posterior CRLB; for additive Gaussian noise it is this
Riccati recursion evaluated along the true trajectory).

Measurement noise is modelled exactly as the simulator draws it:

* TWR: independent ``N(0, sigma^2)`` per range;
* TDoA: every *packet* has its own arrival error (variance ``sigma^2 +
  clock_sigma^2``) and a difference is ``h_B - h_A + e_B - e_A``.  The latest
  packet error of each anchor is kept as an extra state (19 + M dims), so
  differences that share a packet (consecutive TDoA2 slots; TDoA3 pairs that
  reuse an anchor's last packet) are handled with their true correlation --
  treating them as independent with variance ``2 sigma^2`` would not give a
  lower bound.

Optionally (TWR, ``anchor_bias_sd``) one unknown constant range bias per
anchor is added as an extra state: the bound of the parameterisation the batch
calibrator estimates by default, against which its efficiency is fairly
measured (the bias-free bound is the other, lower, baseline).

Prior at the first IMU sample (stated; the bound depends on it): the ESKF's
initialisation sds (:class:`uwbimu.estimation.EskfOptions` defaults) --
position 0.3 m, velocity 0.5 m/s, roll/pitch 5 deg, yaw 15 deg, biases from
the IMU model's ``*_bias_sigma0``, lever arm ``lever_arm.prior_sd`` (0.3 m),
time offset ``init.td_sd_after_grid`` (0.03 s).

Not modelled (the bound is for the model without them): NLOS excess,
dropouts beyond the schedule actually simulated (the bound uses the rows
that were emitted in the seeded run) and the anchor-clock random walk.  Each
distance of a difference is linearised at its own packet's arrival, as the
simulator draws it (A's Jacobian mapped to B's instant to first order,
``range_jacobian``'s ``delta``): taking both at B's instant would credit the
model with noise-free velocity information from the telescoping chain of
differences and give a bound that is too low.  Measurements are
applied at the end of the IMU interval that contains them, with every Jacobian
mapped from its own instant to that one.
"""

from __future__ import annotations

from uwbimu.errors import UsageError
import math
from typing import Any

import numpy as np
from numba import njit

from uwbimu.models import state as ST
from uwbimu.models import kernels as _physics
from uwbimu.models.kernels import cov_step, range_jacobian, refresh_stale_cache
from uwbimu.models.reference import G_WORLD


@njit(cache=True)
def _recursion(P, X, U, dt, noise, meas_step, H, r_var, refresh, refresh_var, pos_var):
    """Run the covariance recursion; ``pos_var[k]`` = diag of the position block after step k."""
    D = P.shape[0]
    m = 0
    n_meas = H.shape[0]
    for i in range(3):
        pos_var[0, i] = P[i, i]
    for k in range(dt.shape[0]):
        cov_step(P, X[k], U[k], dt[k], noise)
        while m < n_meas and meas_step[m] <= k:
            for s in range(2):
                r = refresh[m, s]
                if r >= 0:  # a new packet from that anchor: its error is fresh and independent
                    for c in range(D):
                        P[r, c] = 0.0
                        P[c, r] = 0.0
                    P[r, r] = refresh_var
            if r_var[m] >= 0.0:
                h = H[m]
                Ph = P @ h
                S = h @ Ph + r_var[m]
                if S > 1e-300:
                    # Joseph form (stays symmetric positive semi-definite over 10^5 updates)
                    K = Ph / S
                    IKH = -np.outer(K, h)
                    for a in range(D):
                        IKH[a, a] += 1.0
                    P[:, :] = IKH @ P @ IKH.T + np.outer(K, K) * r_var[m]
            m += 1
        for i in range(3):
            pos_var[k + 1, i] = P[i, i]
    return P


def _prior(noise, M: int, extra_var: float) -> np.ndarray:
    """Prior at the first IMU sample; ``M`` extra states (TDoA packet errors or TWR anchor biases) of
    variance ``extra_var``."""
    sd = np.concatenate([
        np.full(3, 0.3), np.full(3, 0.5), np.radians([5.0, 5.0, 15.0]),
        np.full(3, noise.accel_bias_sigma0), np.full(3, noise.gyro_bias_sigma0), np.full(3, 0.3), [0.03],
    ])
    P = np.diag(sd**2)
    if M:
        P = np.pad(P, ((0, M), (0, M)))
        P[ST.ERROR_DIM:, ST.ERROR_DIM:] = np.eye(M) * extra_var
    return np.maximum(P, 0.0)


def posterior_bound(sim_result, scenario, anchor_bias_sd: float | None = None) -> dict[str, Any]:
    """Posterior CRLB along a simulated flight.

    Parameters
    ----------
    sim_result : :class:`uwbimu.sim.SimResult` of ``scenario`` (its schedule is used).
    scenario : the :class:`uwbimu.sim.Scenario`.
    anchor_bias_sd : TWR only.  None: the ranges' model is the simulator's (no bias), the bound of an
        estimator that knows there is none.  A number [m]: every anchor also has an unknown constant range
        bias with prior ``N(0, anchor_bias_sd^2)`` (true value 0 in the simulation), the bound of an estimator
        that estimates them, as the batch calibrator does by default (``anchor_bias_prior_sd``).  It is the
        larger of the two; both are Cramer-Rao bounds, of two parameterisations of the same data.

    Returns
    -------
    dict with ``t`` (IMU instants, UWB clock) and ``pos_sd`` (N, 3) [m]; final
    ``lever_arm_sd`` (3,) [m] and ``time_offset_sd`` [s]; ``P_final`` (19, 19); with ``anchor_bias_sd``
    also ``anchor_bias_sd_final`` (M,) [m], in ``scenario.anchor_ids()`` order.
    """
    ds = sim_result.dataset
    mo = sim_result.motion
    noise = scenario.imu.noise_model()
    u = scenario.uwb
    ids = scenario.anchor_ids()
    A = scenario.anchor_positions()
    lever = np.asarray(scenario.tag_list()[0].lever_arm, float)
    t_d = float(scenario.time_offset)
    N = len(mo.t)
    from uwbimu.models.quaternion import quat_to_rotmat

    R = quat_to_rotmat(mo.q)
    f = np.einsum("nji,nj->ni", R, mo.a + G_WORLD)
    X = np.zeros((N, 20))
    X[:, ST.P], X[:, ST.V], X[:, ST.Q], X[:, ST.PIU], X[:, ST.TD] = mo.p, mo.v, mo.q, lever, t_d
    U = np.ascontiguousarray(np.column_stack([f, mo.w]))
    dt = np.diff(mo.t)
    q = np.array([noise.accel_noise_density**2, noise.gyro_noise_density**2, noise.accel_bias_rw**2,
                  noise.gyro_bias_rw**2, 0.0, 0.0])
    tdoa_mode = u.mode != "twr"
    if tdoa_mode and anchor_bias_sd is not None:
        raise UsageError("posterior_bound: anchor_bias_sd is for TWR scenarios (TDoA has its packet states there)")
    with_bias = anchor_bias_sd is not None
    M = len(ids) if (tdoa_mode or with_bias) else 0
    D = 19 + M
    packet_var = float(u.sigma**2 + u.clock_sigma**2)

    if tdoa_mode:
        tab = ds.tdoa
        t_meas = tab["t"].to_numpy(float)
        ia = np.array([ids.index(a) for a in tab["anchor_a"]], dtype=int)
        ib = np.array([ids.index(b) for b in tab["anchor_b"]], dtype=int)
        packets = sim_result.tdoa_packets
        t_geo = sim_result.tdoa_t_nominal  # true instants (the table's stamps may carry jitter)
    else:
        tab = ds.uwb
        t_meas = tab["t"].to_numpy(float)
        ib = np.array([ids.index(a) for a in tab["anchor"]], dtype=int)
        ia = ib
        t_geo = sim_result.range_t_nominal
    n = len(t_meas)
    # truth at each measurement instant, as a nominal state (biases 0: the input U is bias-free)
    p, qq = sim_result.trajectory.pose(t_geo)
    s = sim_result.trajectory.sample(t_geo)
    xt = np.zeros((n, 20))
    xt[:, ST.P], xt[:, ST.V], xt[:, ST.Q], xt[:, ST.PIU], xt[:, ST.TD] = p, s.v, qq, lever, t_d
    ut = np.column_stack([np.zeros((n, 3)), s.w])
    if tdoa_mode:  # anchor A's distance is taken at its own packet's arrival (as simulated)
        t_a = sim_result.tdoa_t_a
        pa_, qa_ = sim_result.trajectory.pose(t_a)
        sa_ = sim_result.trajectory.sample(t_a)
        xa = np.zeros((n, 20))
        xa[:, ST.P], xa[:, ST.V], xa[:, ST.Q], xa[:, ST.PIU], xa[:, ST.TD] = pa_, sa_.v, qa_, lever, t_d
        ua = np.column_stack([np.zeros((n, 3)), sa_.w])
    # measurement m is applied after the IMU interval that contains its UWB time; every Jacobian is
    # mapped from its own instant to that application instant (first order, range_jacobian's delta),
    # so that no distance is taken at the wrong time
    meas_step = np.clip(np.searchsorted(mo.t, t_meas, side="left") - 1, 0, N - 2)
    t_apply = mo.t[meas_step + 1]
    H = np.zeros((n, D))
    hb, ha = np.zeros(19), np.zeros(19)
    refresh = np.full((n, 2), -1, dtype=np.int64)
    held = np.full(max(M, 1), -1, dtype=np.int64)  # packet index whose error each anchor's state holds
    for m in range(n):
        range_jacobian(xt[m], ut[m], A[ib[m]], -1, float(t_apply[m] - t_geo[m]), hb)
        if tdoa_mode:
            range_jacobian(xa[m], ua[m], A[ia[m]], -1, float(t_apply[m] - t_a[m]), ha)
            H[m, :19] = hb - ha
            H[m, 19 + ib[m]] += 1.0
            H[m, 19 + ia[m]] -= 1.0
            for s_i, (anc, pk) in enumerate(((ia[m], packets[m, 0]), (ib[m], packets[m, 1]))):
                if held[anc] != pk:
                    refresh[m, s_i] = 19 + anc
                    held[anc] = pk
        else:
            H[m, :19] = hb
            if with_bias:
                H[m, 19 + ib[m]] = 1.0  # the anchor's constant bias adds to its range
    r_var = np.zeros(n) if tdoa_mode else np.full(n, float(u.sigma**2))
    order = np.argsort(meas_step, kind="stable")
    P = _prior(noise, M, float(anchor_bias_sd) ** 2 if with_bias else packet_var)
    pos_var = np.zeros((N, 3))
    P = _recursion(P, X, U, dt, q, meas_step[order].astype(np.int64), np.ascontiguousarray(H[order]),
                   r_var[order], refresh[order], packet_var, pos_var)
    out = {} if not with_bias else {"anchor_bias_sd_final": np.sqrt(np.maximum(np.diag(P)[19:], 0.0))}
    return out | {
        "t": mo.t,
        "pos_sd": np.sqrt(np.maximum(pos_var, 0.0)),
        "lever_arm_sd": np.sqrt(np.maximum(np.diag(P)[ST.EPIU], 0.0)),
        "time_offset_sd": float(math.sqrt(max(P[ST.ETD, ST.ETD], 0.0))),
        "P_final": P[:ST.ERROR_DIM, :ST.ERROR_DIM].copy(),
    }


def inside_hull_fraction(points: np.ndarray, anchors: np.ndarray) -> float:
    """Fraction of ``points`` (N, 3) inside the convex hull of ``anchors`` (M, 3) [0..1]."""
    from scipy.spatial import Delaunay

    return float(np.mean(Delaunay(np.asarray(anchors, float)).find_simplex(np.asarray(points, float)) >= 0))


def scenario_bound(scenario_dict: dict, seeds: tuple[int, int, int], skip_initial_s: float = 0.0) -> dict:
    """Bound summary of one study cell: simulate with ``seeds`` and reduce :func:`posterior_bound`.

    Returns JSON-able ``rmse_x/y/z/3d`` (RMS over ``t >= t0 + skip_initial_s`` of the
    position sd: what an efficient estimator's RMSE would be), ``lever_arm_sd_x/y/z``,
    ``time_offset_sd`` (final), and ``inside_hull_fraction`` of the flight.
    """
    from uwbimu.sim import Scenario, simulate_full

    sc = Scenario.model_validate(scenario_dict).updated(seeds={"truth": seeds[0], "noise": seeds[1], "init": seeds[2]})
    res = simulate_full(sc)
    b = posterior_bound(res, sc)
    keep = b["t"] >= b["t"][0] + skip_initial_s
    rms = np.sqrt(np.mean(b["pos_sd"][keep] ** 2, axis=0))
    return {
        "rmse_x": float(rms[0]), "rmse_y": float(rms[1]), "rmse_z": float(rms[2]),
        "rmse_3d": float(np.sqrt(np.sum(rms**2))),
        "lever_arm_sd_x": float(b["lever_arm_sd"][0]), "lever_arm_sd_y": float(b["lever_arm_sd"][1]),
        "lever_arm_sd_z": float(b["lever_arm_sd"][2]), "time_offset_sd": b["time_offset_sd"],
        "inside_hull_fraction": inside_hull_fraction(res.motion.p, sc.anchor_positions()),
        "seeds": list(seeds),
        "prior": "ESKF init defaults: p 0.3 m, v 0.5 m/s, roll/pitch 5 deg, yaw 15 deg, biases sigma0, "
                 "lever 0.3 m, t_d 0.03 s",
    }


# _recursion calls the shared physics kernels: flush its disk cache when they change
refresh_stale_cache(globals(), [_physics])
