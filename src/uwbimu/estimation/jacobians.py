"""Dense NumPy error-state Jacobians (reference for the numba kernels and for tests).

Candidates to move into :mod:`uwbimu.models` once another estimator needs them.
The error state is ``dp dv dtheta db_a db_g dp_IU dt_d`` (+ range biases) with a
right attitude perturbation; the noise vector is ``n = [n_a, n_g, n_ba, n_bg]``
(12) with the IMU model ``a_m = a + b_a + n_a``, ``w_m = w + b_g + n_g``.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import expm

from uwbimu.models import state as S
from uwbimu.models.quaternion import quat_to_rotmat, skew


def error_F(x: np.ndarray, u: np.ndarray, n_err: int = S.ERROR_DIM) -> np.ndarray:
    """Continuous-time error-state Jacobian ``F`` (n_err x n_err) at state ``x`` and input ``u``."""
    R = quat_to_rotmat(x[S.Q])
    a = u[0:3] - x[S.BA]
    w = u[3:6] - x[S.BG]
    F = np.zeros((n_err, n_err))
    F[S.EP, S.EV] = np.eye(3)
    F[S.EV, S.ETH] = -R @ skew(a)
    F[S.EV, S.EBA] = -R
    F[S.ETH, S.ETH] = -skew(w)
    F[S.ETH, S.EBG] = -np.eye(3)
    return F


def error_G(x: np.ndarray, n_err: int = S.ERROR_DIM) -> np.ndarray:
    """Continuous-time noise Jacobian ``G`` (n_err x 12) for ``[n_a, n_g, n_ba, n_bg]``."""
    R = quat_to_rotmat(x[S.Q])
    G = np.zeros((n_err, 12))  # noise columns: n_a, n_g, n_ba, n_bg
    G[S.EV, 0:3] = -R
    G[S.ETH, 3:6] = -np.eye(3)
    G[S.EBA, 6:9] = np.eye(3)
    G[S.EBG, 9:12] = np.eye(3)
    return G


def van_loan(F: np.ndarray, G: np.ndarray, Qc: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact discretisation ``(Phi, Qd)`` of ``dx' = F dx + G n``, ``E[n n^T] = Qc delta(t)``."""
    n = F.shape[0]
    A = np.zeros((2 * n, 2 * n))
    A[:n, :n] = -F
    A[:n, n:] = G @ Qc @ G.T
    A[n:, n:] = F.T
    B = expm(A * dt)
    Phi = B[n:, n:].T
    Qd = Phi @ B[:n, n:]
    return Phi, 0.5 * (Qd + Qd.T)
