"""Posterior Cramér-Rao bound of the ESKF's error state (independent of the filter's linearisation).

For additive Gaussian noise the posterior CRLB (Tichavsky et al., 1998) of a
state-space model with linearisable dynamics is the covariance of the
information recursion with every Jacobian evaluated at the TRUE trajectory:
an EKF covariance linearised about truth, with no gating and every
measurement used.  :func:`posterior_crlb` runs that recursion on the same
discretisation as the filter (the shared primitives of
:mod:`uwbimu.models.kernels`) but at the true states; the filter's own
estimates never enter it.  Comparing the filter's Monte Carlo RMS error to
the square root of its diagonal shows the price of linearising at the
estimate (``benchmarks/bench_eskf_crlb.py``).
"""

from __future__ import annotations

import numpy as np

from uwbimu.estimation import kernels as K
from uwbimu.estimation.filterpass import Problem
from uwbimu.models import state as S


def posterior_crlb(prob: Problem, x_true: np.ndarray, P0: np.ndarray, k0: int, j0: int = 0,
                   t_end: float | None = None) -> np.ndarray:
    """Posterior CRLB of the error state at the end of the log (or at IMU time ``t_end``).

    Parameters
    ----------
    prob : :class:`Problem` from :func:`uwbimu.estimation.eskf.build_problem` (IMU on its clock,
        ranges on the UWB clock, noise densities, range variance).
    x_true : (n, 20 + nb) true extended nominal state at every IMU sample (biases, lever arm, t_d
        included).
    P0 : (N, N) prior covariance at IMU sample ``k0`` (the filter's prior, for a like-for-like bound).
    k0, j0 : first IMU sample and first range used.
    t_end : stop at this IMU time [s] (None: end of the log).

    Returns
    -------
    (N, N) bound on the error covariance at the last IMU sample reached [SI units of the error state].
    """
    if prob.uwb_b is not None and np.any(prob.uwb_b >= 0):
        raise NotImplementedError("posterior_crlb: TDoA rows are not supported yet (ranges only)")
    n = len(prob.imu_t)
    P = np.array(P0, dtype=float, copy=True)
    N = P.shape[0]
    h = np.empty(N)
    xt = np.empty(x_true.shape[1])
    ut = np.empty(6)
    pn = prob.process_noise_tables()  # every declared block's process noise (not only the base 19)
    k = k0
    k_last = n - 1 if t_end is None else min(n - 1, int(np.searchsorted(prob.imu_t, t_end)))
    for j in range(j0, len(prob.uwb_t)):
        tau = prob.uwb_t[j] + x_true[min(k, n - 1), S.TD]  # IMU time of the range (true offset)
        if tau < prob.imu_t[k0]:
            continue
        k_tau = int(np.searchsorted(prob.imu_t, tau))  # first IMU sample at or after tau
        if k_tau > k_last:
            break
        while k < k_tau:
            K.cov_step_blocks(P, x_true[k], prob.imu_u[k], prob.imu_t[k + 1] - prob.imu_t[k], pn)
            k += 1
        if K.state_at(x_true[k], prob.imu_t, prob.imu_u, prob.imu_um, k, tau, prob.dt_max, xt, ut) != K.UPD_OK:
            continue
        a = int(prob.uwb_a[j])
        K.range_jacobian(xt, ut, prob.anchors[a], int(prob.bias_idx[a]), prob.imu_t[k] - tau, h)
        Ph = P @ h
        s = float(h @ Ph) + prob.r_var
        P -= np.outer(Ph, Ph) / s
    while k < k_last:
        K.cov_step_blocks(P, x_true[k], prob.imu_u[k], prob.imu_t[k + 1] - prob.imu_t[k], pn)
        k += 1
    return 0.5 * (P + P.T)
