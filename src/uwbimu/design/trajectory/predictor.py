"""Predicted calibration accuracy of a trajectory: the linearised ESKF covariance.

For a candidate motion (truth) we run the covariance recursion of the
19-state error-state filter along it -- no data, only Jacobians -- with the
IMU noise as process noise and every scheduled range as a scalar update::

    P <- Phi P Phi^T + Q_d,      P <- P - P h h^T P / (h^T P h + sigma^2)

Error dynamics (right/body attitude perturbation, the ESKF's convention,
``q = q_hat ⊗ Exp(dtheta)``), with ``f`` the specific force and ``w`` the
body rate of the truth::

    dp' = dv
    dv' = -R [f]x dth - R db_a + R n_a
    dth' = -[w]x dth - db_g + n_g
    db_a' = n_ba,  db_g' = n_bg,  dp_IU' = 0,  dt_d' = 0

``Phi`` is the estimator's transition (:func:`uwbimu.models.kernels.phi_left_R`: second-order
series with the exact attitude rotation, the blocks of the ESKF's covariance step);
``Q_d = G Q_c G^T dt`` (diagonal: the accelerometer noise is isotropic, so ``R`` drops out).
Range Jacobian of ``h = |a - p - R Exp(dth) p_IU|`` at IMU time ``t + t_d`` (``u`` the unit
vector from the antenna to the anchor)::

    dh/dp = -u^T,  dh/dth = u^T R [p_IU]x,  dh/dp_IU = -u^T R,
    dh/dt_d = -u^T (v + R [w]x p_IU)        (the antenna velocity)

The posterior covariance's calibration block (``dp_IU``, ``dt_d``) gives the
predicted 1-sigma; its inverse is the Fisher information of the calibration
block with the 15 navigation states marginalised (Schur complement), whose
smallest eigenvalue (after scaling by ``scale_lever_arm``,
``scale_time_offset``) is the E-optimality criterion.  The physics is the
estimator's kernels: the range Jacobian is
:func:`uwbimu.models.kernels.range_jacobians` and the transition
:func:`uwbimu.models.kernels.phi_left_R`, both pinned to :mod:`uwbimu.models.reference`
by tests; only the recursion (and its diagonal process noise) is written here.

Why not the observability engine's per-window information
(:mod:`uwbimu.observability.window`)?  It works on a dataset, window by
window, with the IMU noise as an inflation of each range's variance; the
design needs the information accumulated over a whole *candidate* (no
dataset; hundreds of candidates) with the IMU noise correlations through the
shared navigation states, which is exactly the filter's covariance
recursion.  On the built-in calibration flight the prediction matches the
ESKF's reported sd to 1 % on the lever arm and 2 % on t_d (``benchmarks/bench_plan.py``).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from uwbimu.models import kernels as _physics
from uwbimu.models import state as ST
from uwbimu.models.kernels import phi_left_R, range_jacobians, refresh_stale_cache
from uwbimu.models.state import E_BA, E_BG, E_L, E_TH, E_V, ERROR_DIM
from uwbimu.models.quaternion import rotmat_to_quat


def range_jacobian(kin_meas: dict[str, np.ndarray], anchors: np.ndarray, lever_arm: np.ndarray) -> np.ndarray:
    """Range Jacobians w.r.t. the 19-dim error state, one row per range (the estimator's, written once).

    Parameters
    ----------
    kin_meas : truth at the range instants (``p, v, w`` and ``q`` or ``R``: (M, ...)).
    anchors : (M, 3) anchor of each range [m]; lever_arm : (3,) [m] (IMU frame).
    """
    q = kin_meas.get("q")
    if q is None:
        q = np.array([rotmat_to_quat(R) for R in kin_meas["R"]])
    return range_jacobians(kin_meas["p"], kin_meas["v"], q, kin_meas["w"], lever_arm, anchors)[1]


@njit(cache=True)
def _cov_run(P0, R, f, w, dt, qa, qg, qba, qbg, meas_step, H, sigma2):
    """Covariance recursion; updates for measurements assigned to each step after its prediction.

    The prediction ``Phi P Phi^T`` is the estimator's (:func:`uwbimu.models.kernels.phi_left_R`,
    applied to the rows, then to the rows of the transpose); the process noise is the diagonal
    ``Q_d`` of the module docstring.
    """
    n = R.shape[0]
    P = P0.copy()
    PT = np.zeros((ERROR_DIM, ERROR_DIM))
    B = np.zeros((7, 3, 3))
    W = np.zeros((6, 3, 3))
    col = np.zeros(E_L)
    m = 0
    M = meas_step.shape[0]
    for k in range(n):
        # updates assigned to step k (ranges in (t_{k-1}, t_k])
        while m < M and meas_step[m] == k:
            h = H[m]
            Ph = P @ h
            s = h @ Ph + sigma2
            for i in range(ERROR_DIM):
                for j in range(ERROR_DIM):
                    P[i, j] -= Ph[i] * Ph[j] / s
            m += 1
        if k == n - 1:
            break
        phi_left_R(P, R[k], f[k], w[k], dt, B, W, col)  # Phi P
        PT[:, :] = P.T
        phi_left_R(PT, R[k], f[k], w[k], dt, B, W, col)  # Phi (Phi P)^T = (Phi P Phi^T)^T
        P[:, :] = PT
        for i in range(3):
            P[E_V + i, E_V + i] += qa * dt  # R n_a: isotropic, R drops out
            P[E_TH + i, E_TH + i] += qg * dt
            P[E_BA + i, E_BA + i] += qba * dt
            P[E_BG + i, E_BG + i] += qbg * dt
        P = 0.5 * (P + P.T)
    return P


def predict_covariance(
    kin: dict[str, np.ndarray],
    kin_meas: dict[str, np.ndarray],
    meas_anchor: np.ndarray,
    lever_arm: np.ndarray,
    P0: np.ndarray,
    noise,
    range_sigma: float,
) -> np.ndarray:
    """Final 19x19 covariance of the linearised ESKF along a trajectory.

    Parameters
    ----------
    kin : truth on a uniform grid (``t, R, f, w``) used for the prediction.
    kin_meas : truth at the range instants (``t, p, v, R, w``).
    meas_anchor : (M, 3) anchor of each range [m].
    lever_arm : (3,) [m]; P0 : (19, 19) prior covariance.
    noise : :class:`uwbimu.models.imu.ImuNoise` (continuous-time densities).
    range_sigma : range noise sd [m].
    """
    t = kin["t"]
    dt = float(t[1] - t[0])
    H = range_jacobian(kin_meas, meas_anchor, lever_arm)
    step = np.searchsorted(t, kin_meas["t"] - 1e-12).astype(np.int64)  # first grid time >= range time
    step = np.clip(step, 0, len(t) - 1)
    order = np.argsort(step, kind="stable")
    return _cov_run(
        np.ascontiguousarray(P0, dtype=float),
        np.ascontiguousarray(kin["R"]),
        np.ascontiguousarray(kin["f"]),
        np.ascontiguousarray(kin["w"]),
        dt,
        noise.accel_noise_density**2,
        noise.gyro_noise_density**2,
        noise.accel_bias_rw**2,
        noise.gyro_bias_rw**2,
        step[order],
        np.ascontiguousarray(H[order]),
        float(range_sigma) ** 2,
    )


def calibration_metrics(P: np.ndarray, scale_lever_arm: float, scale_time_offset: float) -> dict[str, float | list]:
    """Predicted sigmas and the E-optimality criterion of the calibration block.

    ``lambda_min_scaled`` is the smallest eigenvalue of the Fisher information
    of ``(p_IU / scale_lever_arm, t_d / scale_time_offset)`` (navigation states
    marginalised, prior included): 1 means a 1-sigma of one scale unit along
    the worst direction.
    """
    cal = slice(ST.EPIU.start, ST.ETD + 1)  # lever arm and t_d, adjacent in the error state
    C = P[cal, cal]
    S = np.diag([1.0 / scale_lever_arm] * 3 + [1.0 / scale_time_offset])
    ev = np.linalg.eigvalsh(S @ C @ S)
    return {
        "sigma_lever_arm_m": np.sqrt(np.diag(C)[:3]).tolist(),
        "sigma_time_offset_s": float(np.sqrt(C[3, 3])),
        "lambda_min_scaled": float(1.0 / ev[-1]),
        "lambda_max_scaled": float(1.0 / ev[0]),
    }


# _cov_run inlines the state layout's offsets and the estimator's transition kernel: flush its
# disk cache when models/state.py or models/kernels.py changes
refresh_stale_cache(globals(), [_physics])
