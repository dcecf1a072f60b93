"""Measurement models of the filter: a small protocol and the built-in models.

A model maps the extended nominal state ``x`` (:class:`~uwbimu.models.state.StateLayout`) at the
measurement's time, and the IMU input ``u = [acc, gyro]`` there, to the predicted measurement::

    class MyModel(MeasurementModel):
        dim = 1
        clock = "imu"            # stamped on the IMU clock ("uwb": the UWB clock, shifted by t_d)
        def evaluate(self, x, u):
            return np.array([x[2]])
        def covariance(self):
            return np.array([[0.05 ** 2]])

``jacobian(x, u, layout)`` (rows: measurement, columns: error state) defaults to central finite
differences on the error state (``x ⊞ dx``, :func:`uwbimu.models.state.boxplus`), and for a
UWB-clock model adds the time-offset column from the state's rate (a measurement stamped on the UWB
clock sees the state ``t_d`` later on the IMU clock), so a user-defined model works without
derivatives.  The built-in models give analytic Jacobians; ``tests/test_measurement_models.py``
pins each of them to the finite-difference default and to :mod:`uwbimu.models.reference`.

The streaming filter runs the range and TDoA models through its numba kernels and every other model
(height, zero velocity, user-defined) through :func:`vector_update`.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np

from uwbimu.models import reference as ref
from uwbimu.models import state as S
from uwbimu.models.state import StateLayout

#: finite-difference step per error component (position/velocity/lever [m], attitude [rad], ...)
FD_STEP = 1e-6


class MeasurementModel:
    """Base class of a measurement model (see the module docstring).

    Attributes
    ----------
    dim : number of components.
    clock : ``"uwb"`` (stamp on the UWB clock: the state is taken at IMU time ``t + t_d``) or
        ``"imu"`` (stamp on the IMU clock).
    name : short name used in records and events.
    """

    dim: int = 1
    clock: str = "uwb"
    name: str = "model"

    def evaluate(self, x: np.ndarray, u: np.ndarray) -> np.ndarray:
        """Predicted measurement ``(dim,)`` from the extended nominal state and the IMU input."""
        raise NotImplementedError

    def covariance(self) -> np.ndarray:
        """Measurement noise covariance ``(dim, dim)``."""
        raise NotImplementedError

    def jacobian(self, x: np.ndarray, u: np.ndarray, layout: StateLayout) -> np.ndarray:
        """``d evaluate / d dx`` ``(dim, layout.n_err)``; default: :func:`fd_jacobian`."""
        return fd_jacobian(self, x, u, layout)


def state_rate(x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Time derivative of the extended nominal state under the IMU input ``u`` (extras constant)."""
    xd = np.zeros_like(x)
    xd[: S.NOMINAL_DIM] = ref.continuous_dynamics(x[: S.NOMINAL_DIM], u)
    return xd


def fd_jacobian(model: MeasurementModel, x: np.ndarray, u: np.ndarray, layout: StateLayout,
                step: float = FD_STEP) -> np.ndarray:
    """Central finite-difference Jacobian of ``model.evaluate`` on the error state.

    The time-offset column of a UWB-clock model is the derivative along the state's motion (the
    measurement at UWB time ``t`` sees the state at IMU time ``t + t_d``): ``dh/dx · x_dot``, also
    by central differences, plus any explicit dependence on ``x[t_d]``.
    """
    n = layout.n_err
    H = np.zeros((model.dim, n))
    for i in range(n):
        dx = np.zeros(n)
        dx[i] = step
        H[:, i] = (np.atleast_1d(model.evaluate(S.boxplus(x, dx), u))
                   - np.atleast_1d(model.evaluate(S.boxplus(x, -dx), u))) / (2 * step)
    if model.clock == "uwb":
        xd = state_rate(x, u)
        xp = x + step * xd
        xm = x - step * xd
        xp[S.Q] /= np.linalg.norm(xp[S.Q])
        xm[S.Q] /= np.linalg.norm(xm[S.Q])
        H[:, S.ETD] += (np.atleast_1d(model.evaluate(xp, u)) - np.atleast_1d(model.evaluate(xm, u))) / (2 * step)
    return H


class RangeModel(MeasurementModel):
    """Two-way range [m] from the antenna (lever arm ``p_IU``) to an anchor, plus the anchor's range
    bias when the layout has one (``bias_index``: component of the ``anchor_bias`` block)."""

    dim = 1
    clock = "uwb"
    name = "range"

    def __init__(self, anchor, sigma: float, bias_index: Optional[int] = None):
        self.anchor = np.asarray(anchor, dtype=float).reshape(3)
        self.sigma = float(sigma)
        self.bias_index = bias_index

    def _bias(self, x):
        return x[S.NOMINAL_DIM + self.bias_index] if self.bias_index is not None else 0.0

    def evaluate(self, x, u):
        return np.array([float(ref.range_measurement(x[: S.NOMINAL_DIM], self.anchor)) + self._bias(x)])

    def covariance(self):
        return np.array([[self.sigma**2]])

    def jacobian(self, x, u, layout):
        from uwbimu.models.kernels import range_jacobian

        h = np.zeros(layout.n_err)
        bi = layout.index("anchor_bias", self.bias_index) if self.bias_index is not None else -1
        range_jacobian(np.ascontiguousarray(x, dtype=float), np.asarray(u, dtype=float), self.anchor, bi, 0.0, h)
        return h[None, :]


class TdoaModel(MeasurementModel):
    """TDoA ``|p_U - p_b| - |p_U - p_a|`` [m], plus ``b_b - b_a`` when the layout has anchor biases."""

    dim = 1
    clock = "uwb"
    name = "tdoa"

    def __init__(self, anchor_a, anchor_b, sigma: float, bias_a: Optional[int] = None, bias_b: Optional[int] = None):
        self.a = np.asarray(anchor_a, dtype=float).reshape(3)
        self.b = np.asarray(anchor_b, dtype=float).reshape(3)
        self.sigma = float(sigma)
        self.bias_a, self.bias_b = bias_a, bias_b

    def evaluate(self, x, u):
        z = float(ref.tdoa_measurement(x[: S.NOMINAL_DIM], self.a, self.b))
        if self.bias_b is not None:
            z += x[S.NOMINAL_DIM + self.bias_b]
        if self.bias_a is not None:
            z -= x[S.NOMINAL_DIM + self.bias_a]
        return np.array([z])

    def covariance(self):
        return np.array([[self.sigma**2]])

    def jacobian(self, x, u, layout):
        from uwbimu.models.kernels import tdoa_jacobian

        n = layout.n_err
        h, work = np.zeros(n), np.zeros(n)
        tdoa_jacobian(np.ascontiguousarray(x, dtype=float), np.asarray(u, dtype=float), self.a, self.b, -1, 0.0, h, work)
        if self.bias_b is not None:
            h[layout.index("anchor_bias", self.bias_b)] += 1.0
        if self.bias_a is not None:
            h[layout.index("anchor_bias", self.bias_a)] -= 1.0
        return h[None, :]


class HeightModel(MeasurementModel):
    """Altimeter: height of the IMU origin [m] (world ``p_z``), plus the altimeter bias when the layout
    has one (``height_bias`` block).  Stamped on the IMU clock (an altimeter usually shares the
    flight controller's clock)."""

    dim = 1
    clock = "imu"
    name = "height"

    def __init__(self, sigma: float, layout: Optional[StateLayout] = None):
        self.sigma = float(sigma)
        sl = layout.nom("height_bias") if layout is not None else slice(0, 0)
        self._bias_nom = sl.start if sl.stop > sl.start else None

    def evaluate(self, x, u):
        return np.array([x[2] + (x[self._bias_nom] if self._bias_nom is not None else 0.0)])

    def covariance(self):
        return np.array([[self.sigma**2]])

    def jacobian(self, x, u, layout):
        h = np.zeros((1, layout.n_err))
        h[0, 2] = 1.0
        if self._bias_nom is not None:
            h[0, layout.index("height_bias")] = 1.0
        return h


class ZeroVelocityModel(MeasurementModel):
    """Zero-velocity pseudo-measurement (the platform is known to stand still): ``v = 0`` (world,
    m/s), stamped on the IMU clock."""

    dim = 3
    clock = "imu"
    name = "zero_velocity"

    def __init__(self, sigma: float = 0.01):
        self.sigma = float(sigma)

    def evaluate(self, x, u):
        return np.array(x[S.V], dtype=float)

    def covariance(self):
        return np.eye(3) * self.sigma**2

    def jacobian(self, x, u, layout):
        H = np.zeros((3, layout.n_err))
        H[:, S.EV] = np.eye(3)
        return H


def vector_update(x: np.ndarray, P: np.ndarray, H: np.ndarray, r: np.ndarray, R: np.ndarray, gate_p: float,
                  force: bool, robust_c: float, gain_mask: np.ndarray, inject) -> dict:
    """Gated, robustly weighted Joseph-form update of ``x``, ``P`` (in place) by one vector measurement.

    ``r`` the innovation ``z - h(x)``, ``H`` its Jacobian, ``R`` the noise covariance; ``gate_p`` the
    chi-square acceptance probability (>= 1: no gate); ``robust_c`` > 0 a Huber weight on the
    Mahalanobis distance (in sigmas); ``gain_mask`` zeroes the gain of consider/fixed components
    (the Joseph form keeps ``P`` right for that gain); ``inject(x, dx)`` the error-state injection.
    Returns ``{"nis", "accepted", "weight", "S"}`` (``S``: trace of the innovation covariance).
    """
    from scipy.stats import chi2

    m = len(r)
    PHt = P @ H.T
    S0 = H @ PHt + R
    nis = float(r @ np.linalg.solve(S0, r))
    gate = chi2.ppf(gate_p, m) if gate_p < 1 else np.inf
    out = {"nis": nis, "accepted": False, "weight": 0.0, "S": float(np.trace(S0))}
    if not (force or nis <= gate):
        return out
    d = math.sqrt(max(nis, 0.0))
    w = 1.0 if robust_c <= 0 or d <= robust_c else robust_c / d
    w = max(w, 1e-6)
    Sw = H @ PHt + R / w
    K = np.linalg.solve(Sw, PHt.T).T * gain_mask[:, None]
    IKH = np.eye(P.shape[0]) - K @ H
    P[:] = IKH @ P @ IKH.T + K @ (R / w) @ K.T
    P[:] = 0.5 * (P + P.T)
    inject(x, K @ r)
    out.update(accepted=True, weight=w)
    return out
