"""Seed 002, sections XI-XII: optimal control for good observability.

Problem (as written in the seed)
--------------------------------
Point mass ``X = [p, v]`` (6), ``X' = A X + B u`` with ``u`` the inertial
acceleration (seed eq. 1); three beacons, the rows of
``P = diag(10, 15, 10)`` i.e. at (10,0,0), (0,15,0), (0,0,10); start
``X(0) = (8, 9, 11, 0, 0, 0)``, desired position ``(14, 15, 17)``, fixed final
time ``t_f = 2.32 s`` and free final state (transversality ``lambda(T) = 0``).
The observability matrix is ``O = a / (r1 r2 r3)`` where the rows of ``a``
are ``p - b_i`` (so ``det(O)`` equals the determinant of the matrix of *unit*
line-of-sight vectors) and the cost is::

    J = int_0^tf  1/det(O)^2 + 1/2 (X - X_d)^T (X - X_d) + 1/2 u^T u  dt

The seed's ``H_x`` carries ``[(x - x_d)^T, 0_{1x3}]``, i.e. only the *position*
is tracked; we follow that (``track_velocity=False``; switch it on to also
penalise the velocity against ``v_d = 0``).  All weights are 1 in the seed;
they are kept as options (``w_det``, ``w_track``, ``w_u``).

Discretisation (shared by both methods, so that they solve *one* problem)
-------------------------------------------------------------------------
``N`` steps of ``h = t_f / N`` with piecewise-constant control and the exact
zero-order-hold transition of the double integrator,
``p+ = p + h v + h^2/2 u``, ``v+ = v + h u``.  The running state cost
``l(X)`` is integrated with the trapezoid rule on the nodes and the control
cost exactly (``h/2 |u_k|^2``)::

    J_h = sum_k w_k h l(X_k) + sum_k h/2 |u_k|^2 ,  w_0 = w_N = 1/2, else 1.

Indirect method: the discrete Pontryagin conditions of ``J_h`` (discretise,
then optimise) are the state recursion forward, the costate recursion
``lambda_k = A_h^T lambda_{k+1} + w_k h grad l(X_k)`` backward from
``lambda_{N+1} = 0`` (the discrete ``lambda(T) = 0``), and
``H_u,k = u_k + B_h^T lambda_{k+1} / h`` (-> ``u + B^T lambda`` as ``h -> 0``).
As in the seed, ``u <- u - alpha H_u`` is iterated from the PD control until
``max_k |H_u,k|`` is below a threshold; ``alpha`` is chosen per iteration by
Armijo backtracking (the seed does not give its step).

Direct method: the same ``J_h`` and transition as a multiple-shooting NLP in
CasADi's Opti stack, solved by IPOPT with exact Hessians.  At a solution of
either method the other's optimality conditions hold, so both give the same
optimum up to solver tolerance.

PD baseline: ``u = -Kp (p - p_d) - Kd v`` sampled and held on the same grid.
The seed gives no gains; the default is critically damped with its 2 %
settling time equal to ``t_f`` (``Kp = 6.32 /s^2``, ``Kd = 5.03 /s``): the
seed says the PD ends at rest while the optimal control does not, so its PD
settles within ``t_f``.  The alternative ``Kp = 1, Kd = sqrt(2)`` (LQR gain of
the seed's own quadratic weights) is compared in ``docs/trajectory_design.md``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, field_validator

SEED_BEACONS = ((10.0, 0.0, 0.0), (0.0, 15.0, 0.0), (0.0, 0.0, 10.0))
SEED_X0 = (8.0, 9.0, 11.0, 0.0, 0.0, 0.0)
SEED_GOAL = (14.0, 15.0, 17.0)
SEED_TF = 2.32
#: PD gains (the seed gives none): critically damped, 2 % settling time equal
#: to t_f (``omega_n t_f = 5.834``), because the seed's text implies that its PD
#: arrives at the goal with zero velocity by t_f ("one apparent drawback of the
#: Optimal Control is that the final velocity is not zero").
PD_OMEGA = 5.8339 / SEED_TF
PD_KP = PD_OMEGA**2
PD_KD = 2.0 * PD_OMEGA


class TimeGrid:
    """Uniform time grid of an OCP config with fields ``tf`` [s] and ``n_steps`` (mixin)."""

    @property
    def h(self) -> float:
        """Grid step [s]."""
        return self.tf / self.n_steps

    @property
    def t(self) -> np.ndarray:
        """Grid instants ``0, h, ..., tf`` [s], (n_steps + 1,)."""
        return np.linspace(0.0, self.tf, self.n_steps + 1)


def double_integrator_opti(n: int, h: float, x0):
    """CasADi ``Opti`` with the exact zero-order-hold double integrator on ``n`` steps of ``h`` [s].

    Returns ``(opti, X, U)``: states ``X`` (6, n+1) = position [m], velocity [m/s]; controls ``U``
    (3, n) = acceleration [m/s^2]; ``X[:, 0] = x0`` and ``X[:, k+1] = A X[:, k] + B U[:, k]``.
    """
    import casadi as ca

    opti = ca.Opti()
    X = opti.variable(6, n + 1)
    U = opti.variable(3, n)
    Ah = ca.DM(np.block([[np.eye(3), h * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]]))
    Bh = ca.DM(np.vstack([0.5 * h * h * np.eye(3), h * np.eye(3)]))
    opti.subject_to(X[:, 0] == ca.DM(x0))
    opti.subject_to(X[:, 1:] == ca.mtimes(Ah, X[:, :-1]) + ca.mtimes(Bh, U))
    return opti, X, U


class SeedOcpConfig(TimeGrid, BaseModel):
    """Options of the seed OCP (defaults = seed 002 section XII).

    Units: metres, seconds, m/s^2.  Beacons are world-frame positions.
    """

    model_config = ConfigDict(extra="forbid")

    beacons: list[list[float]] = Field(default_factory=lambda: [list(b) for b in SEED_BEACONS])
    x0: list[float] = Field(default_factory=lambda: list(SEED_X0))
    goal: list[float] = Field(default_factory=lambda: list(SEED_GOAL))
    tf: float = Field(SEED_TF, gt=0)
    n_steps: int = Field(232, ge=4, description="grid intervals (232 -> h = 10 ms)")
    w_det: float = Field(1.0, ge=0, description="weight of 1/det(O)^2 (seed: 1)")
    w_track: float = Field(1.0, ge=0, description="weight of 1/2 |p - p_d|^2 (seed: 1)")
    w_u: float = Field(1.0, gt=0, description="weight of 1/2 |u|^2 (seed: 1)")
    track_velocity: bool = Field(False, description="also track v_d = 0 (seed: no, see H_x)")
    kp: float = Field(PD_KP, gt=0, description="PD position gain [1/s^2] (critically damped, settles in tf)")
    kd: float = Field(PD_KD, gt=0, description="PD velocity gain [1/s]")
    # indirect method
    hu_tol: float = Field(1e-6, gt=0, description="stop when max_k |H_u,k| < hu_tol [m/s^2]")
    max_iter: int = Field(20000, ge=1)
    alpha0: float = Field(1.0, gt=0, description="first trial step of the backtracking")
    # direct method
    ipopt_tol: float = Field(1e-10, gt=0)
    ipopt_max_iter: int = Field(200, ge=1)

    @field_validator("beacons")
    @classmethod
    def _three_beacons(cls, v):
        if len(v) != 3 or any(len(b) != 3 for b in v):
            raise ValueError("the seed OCP needs exactly three beacons given as [x, y, z]")
        return v

    @field_validator("x0")
    @classmethod
    def _x0_len(cls, v):
        if len(v) != 6:
            raise ValueError("x0 must be [px, py, pz, vx, vy, vz]")
        return v

    @field_validator("goal")
    @classmethod
    def _goal_len(cls, v):
        if len(v) != 3:
            raise ValueError("goal must be [x, y, z]")
        return v


# --------------------------------------------------------------------------
# det(O) and its gradient
# --------------------------------------------------------------------------
def det_observability(p: np.ndarray, beacons: np.ndarray) -> np.ndarray:
    """``det(O)`` with ``O`` the matrix of unit line-of-sight vectors.

    Parameters
    ----------
    p : (..., 3) positions [m] (world).
    beacons : (3, 3) beacon positions, one per row [m].

    Returns
    -------
    (...,) ``det(a) / (r1 r2 r3)`` with rows ``a_i = p - b_i``, ``r_i = |a_i|``;
    dimensionless, in [-1, 1]; +-1 for mutually orthogonal lines of sight,
    0 on the plane through the beacons.
    """
    a = np.asarray(p, dtype=float)[..., None, :] - np.asarray(beacons, dtype=float)
    r = np.linalg.norm(a, axis=-1)
    return np.linalg.det(a) / np.prod(r, axis=-1)


def det_observability_grad(p: np.ndarray, beacons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``det(O)`` and its gradient w.r.t. ``p``.

    ``grad det(O) = det(O) (a^{-1} 1 - sum_i a_i / r_i^2)`` because
    ``grad ln det(a) = a^{-1} 1`` (each row of ``a`` moves with ``p``) and
    ``grad ln r_i = a_i / r_i^2``.  This is the seed's expression
    (``grad det(a) = det(P) P^{-T} 1`` for ``a = 1 p^T - P``) for any beacons.

    Returns
    -------
    D : (...,) and dD : (..., 3) [1/m].
    """
    a = np.asarray(p, dtype=float)[..., None, :] - np.asarray(beacons, dtype=float)
    r2 = np.sum(a * a, axis=-1)
    D = np.linalg.det(a) / np.sqrt(np.prod(r2, axis=-1))
    ones = np.ones(a.shape[:-1] + (1,))
    ainv1 = np.linalg.solve(a, ones)[..., 0]
    dD = D[..., None] * (ainv1 - np.sum(a / r2[..., None], axis=-2))
    return D, dD


# --------------------------------------------------------------------------
# Discrete dynamics, cost, adjoint
# --------------------------------------------------------------------------
def rollout(x0: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
    """Exact ZOH rollout of the double integrator.

    Parameters
    ----------
    x0 : (6,) ``[p, v]``; u : (N, 3) accelerations held over each step [m/s^2];
    h : step [s].

    Returns
    -------
    (N+1, 6) states on the nodes.
    """
    x0 = np.asarray(x0, dtype=float)
    u = np.asarray(u, dtype=float)
    n = u.shape[0]
    v = np.empty((n + 1, 3))
    v[0] = x0[3:]
    v[1:] = x0[3:] + h * np.cumsum(u, axis=0)
    p = np.empty((n + 1, 3))
    p[0] = x0[:3]
    p[1:] = x0[:3] + np.cumsum(h * v[:-1] + 0.5 * h * h * u, axis=0)
    return np.hstack([p, v])


def _weights(n: int) -> np.ndarray:
    w = np.ones(n + 1)
    w[0] = w[-1] = 0.5
    return w


def running_terms(x: np.ndarray, cfg: SeedOcpConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per-node ``1/det^2`` and tracking integrands (before the weights)."""
    D = det_observability(x[:, :3], np.asarray(cfg.beacons))
    e = x[:, :3] - np.asarray(cfg.goal)
    track = 0.5 * np.sum(e * e, axis=1)
    if cfg.track_velocity:
        track = track + 0.5 * np.sum(x[:, 3:] ** 2, axis=1)
    return 1.0 / D**2, track


def seed_cost(x: np.ndarray, u: np.ndarray, cfg: SeedOcpConfig) -> dict[str, float]:
    """Discrete cost ``J_h`` split into its three terms.

    Returns a dict with ``det_term``, ``track_term``, ``control_term``, ``total``
    (weights applied), and ``det_min``, ``det_mean`` (time average, trapezoid),
    ``det_max``, ``det_final``.
    """
    h = cfg.h
    w = _weights(len(u))
    inv_d2, track = running_terms(x, cfg)
    D = det_observability(x[:, :3], np.asarray(cfg.beacons))
    out = {
        "det_term": float(cfg.w_det * h * np.sum(w * inv_d2)),
        "track_term": float(cfg.w_track * h * np.sum(w * track)),
        "control_term": float(cfg.w_u * 0.5 * h * np.sum(u * u)),
    }
    out["total"] = out["det_term"] + out["track_term"] + out["control_term"]
    out.update(
        det_min=float(D.min()),
        det_mean=float(np.sum(w * D) / np.sum(w)),
        det_max=float(D.max()),
        det_final=float(D[-1]),
    )
    return out


def _cost_total(x, u, cfg) -> float:
    w = _weights(len(u))
    inv_d2, track = running_terms(x, cfg)
    return float(cfg.h * np.sum(w * (cfg.w_det * inv_d2 + cfg.w_track * track)) + cfg.w_u * 0.5 * cfg.h * np.sum(u * u))


def hamiltonian_gradient(x: np.ndarray, u: np.ndarray, cfg: SeedOcpConfig) -> tuple[np.ndarray, np.ndarray]:
    """Backward costate sweep and ``H_u`` on the grid.

    Returns
    -------
    lam : (N+1, 6) costates ``lambda_1..lambda_{N+1}`` shifted so that
        ``lam[k]`` multiplies the transition into node ``k+1`` (``lam[N] = 0``
        is the discrete transversality condition);
    Hu : (N, 3) ``u_k + B_h^T lambda_{k+1} / h`` [m/s^2]; ``h * Hu`` is the exact
        gradient of ``J_h`` w.r.t. ``u_k``.
    """
    h = cfg.h
    n = len(u)
    w = _weights(n)
    bea = np.asarray(cfg.beacons)
    D, dD = det_observability_grad(x[:, :3], bea)
    # gradient of the running cost l(X) at each node
    gp = cfg.w_det * (-2.0 / D[:, None] ** 3) * dD + cfg.w_track * (x[:, :3] - np.asarray(cfg.goal))
    gv = cfg.w_track * x[:, 3:] if cfg.track_velocity else np.zeros_like(gp)
    gp = (w * h)[:, None] * gp
    gv = (w * h)[:, None] * gv
    # lambda_k = A_h^T lambda_{k+1} + g_k, k = N..1, lambda_{N+1} = 0;
    # A_h^T = [[I, 0], [h I, I]] -> lp_k = sum_{j>=k} gp_j,
    # lv_k = sum_{j>=k} gv_j + h sum_{j>k} lp_j.
    lp = np.cumsum(gp[::-1], axis=0)[::-1]  # lp[k] = lambda_p at node k
    lp_next = np.vstack([lp[1:], np.zeros((1, 3))])
    lv = np.cumsum((gv + h * lp_next)[::-1], axis=0)[::-1]
    lam = np.hstack([lp, lv])  # lam[k] = lambda_k, k = 0..N
    lam_next = lam[1:]  # lambda_{k+1} for k = 0..N-1
    Hu = cfg.w_u * u + (0.5 * h * lam_next[:, :3] + lam_next[:, 3:])
    return lam, Hu


def pd_rollout(cfg: SeedOcpConfig) -> tuple[np.ndarray, np.ndarray]:
    """Sampled PD ``u_k = -Kp (p_k - p_d) - Kd v_k`` held over each step.

    Returns ``(x (N+1, 6), u (N, 3))``.
    """
    h = cfg.h
    n = cfg.n_steps
    goal = np.asarray(cfg.goal)
    x = np.empty((n + 1, 6))
    u = np.empty((n, 3))
    x[0] = cfg.x0
    for k in range(n):
        u[k] = -cfg.kp * (x[k, :3] - goal) - cfg.kd * x[k, 3:]
        x[k + 1, :3] = x[k, :3] + h * x[k, 3:] + 0.5 * h * h * u[k]
        x[k + 1, 3:] = x[k, 3:] + h * u[k]
    return x, u


# --------------------------------------------------------------------------
# Indirect method (PMP, gradient descent on u)
# --------------------------------------------------------------------------
@dataclass
class MethodResult:
    """Solution of one method on the shared grid."""

    name: str
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    cost: dict[str, float]
    solve_time_s: float
    iterations: int
    converged: bool
    hu_max: float
    history: dict[str, list[float]] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)


def solve_indirect(cfg: SeedOcpConfig, u_init: np.ndarray | None = None) -> MethodResult:
    """Seed's indirect method: forward state, backward costate, ``u -= alpha H_u``.

    Starts from the PD control (as in the seed) unless ``u_init`` is given and
    stops when ``max_k |H_u,k| < cfg.hu_tol`` or after ``cfg.max_iter``
    iterations.  ``alpha`` per iteration: Armijo backtracking (halving) from
    ``min(2 alpha_prev, cfg.alpha0 * 4)`` with sufficient-decrease constant 1e-4.
    """
    t0 = time.perf_counter()
    x0 = np.asarray(cfg.x0, dtype=float)
    h = cfg.h
    if u_init is None:
        _, u = pd_rollout(cfg)
    else:
        u = np.array(u_init, dtype=float)
    x = rollout(x0, u, h)
    J = _cost_total(x, u, cfg)
    _, Hu = hamiltonian_gradient(x, u, cfg)
    hist = {"hu_max": [float(np.abs(Hu).max())], "cost": [J], "alpha": []}
    alpha = cfg.alpha0
    it = 0
    converged = False
    while it < cfg.max_iter:
        hu_max = float(np.abs(Hu).max())
        if hu_max < cfg.hu_tol:
            converged = True
            break
        g2 = h * float(np.sum(Hu * Hu))  # directional derivative of J_h along -Hu
        a = min(2.0 * alpha, 4.0 * cfg.alpha0)
        while True:
            u_try = u - a * Hu
            x_try = rollout(x0, u_try, h)
            J_try = _cost_total(x_try, u_try, cfg)
            if np.isfinite(J_try) and J_try <= J - 1e-4 * a * g2:
                break
            a *= 0.5
            if a < 1e-14:
                break
        if a < 1e-14:  # no descent possible at machine precision
            break
        alpha = a
        u, x, J = u_try, x_try, J_try
        _, Hu = hamiltonian_gradient(x, u, cfg)
        it += 1
        hist["hu_max"].append(float(np.abs(Hu).max()))
        hist["cost"].append(J)
        hist["alpha"].append(a)
    elapsed = time.perf_counter() - t0
    return MethodResult(
        name="indirect",
        t=cfg.t,
        x=x,
        u=u,
        cost=seed_cost(x, u, cfg),
        solve_time_s=elapsed,
        iterations=it,
        converged=converged,
        hu_max=float(np.abs(Hu).max()),
        history=hist,
    )


# --------------------------------------------------------------------------
# Indirect method with the continuous costate ODE (the seed's text literally)
# --------------------------------------------------------------------------
def _midpoint_states(x: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
    """Exact ZOH states at the interval midpoints ``t_k + h/2`` (N, 6)."""
    hm = 0.5 * h
    p = x[:-1, :3] + hm * x[:-1, 3:] + 0.5 * hm * hm * u
    v = x[:-1, 3:] + hm * u
    return np.hstack([p, v])


def _ell_grad(x: np.ndarray, cfg: SeedOcpConfig) -> tuple[np.ndarray, np.ndarray]:
    """Running cost ``l(X)`` and its gradient (rows of ``x``)."""
    D, dD = det_observability_grad(x[:, :3], np.asarray(cfg.beacons))
    e = x[:, :3] - np.asarray(cfg.goal)
    ell = cfg.w_det / D**2 + cfg.w_track * 0.5 * np.sum(e * e, axis=1)
    g = np.zeros_like(x)
    g[:, :3] = cfg.w_det * (-2.0 / D[:, None] ** 3) * dD + cfg.w_track * e
    if cfg.track_velocity:
        ell = ell + cfg.w_track * 0.5 * np.sum(x[:, 3:] ** 2, axis=1)
        g[:, 3:] = cfg.w_track * x[:, 3:]
    return ell, g


def continuous_cost(x: np.ndarray, u: np.ndarray, cfg: SeedOcpConfig) -> float:
    """``J`` with the running cost integrated by Simpson's rule on each interval (O(h^4))."""
    ell_n, _ = _ell_grad(x, cfg)
    ell_m, _ = _ell_grad(_midpoint_states(x, u, cfg.h), cfg)
    h = cfg.h
    return float(h / 6.0 * np.sum(ell_n[:-1] + 4.0 * ell_m + ell_n[1:]) + cfg.w_u * 0.5 * h * np.sum(u * u))


def continuous_costate(x: np.ndarray, u: np.ndarray, cfg: SeedOcpConfig) -> tuple[np.ndarray, np.ndarray]:
    """Seed's costate ODE integrated backward by RK4, and ``H_u`` per interval.

    ``lambda_p' = -dl/dp``, ``lambda_v' = -lambda_p - dl/dv``, ``lambda(T) = 0``
    (``lambda' = -H_x^T``).  ``H_u,k`` is the interval average of
    ``u + B^T lambda = u + lambda_v`` (Simpson, with the midpoint costate from
    cubic Hermite interpolation), i.e. ``dJ/du_k / h`` of the continuous cost.

    Returns ``lam`` (N+1, 6) at the nodes and ``Hu`` (N, 3).
    """
    h = cfg.h
    n = len(u)
    _, gn = _ell_grad(x, cfg)
    _, gm = _ell_grad(_midpoint_states(x, u, h), cfg)

    def f(lam, g):  # d lambda / dt
        return np.concatenate([-g[:3], -lam[:3] - g[3:]])

    lam = np.zeros((n + 1, 6))
    for k in range(n - 1, -1, -1):  # backward: step -h from t_{k+1}
        l1 = lam[k + 1]
        k1 = f(l1, gn[k + 1])
        k2 = f(l1 - 0.5 * h * k1, gm[k])
        k3 = f(l1 - 0.5 * h * k2, gm[k])
        k4 = f(l1 - h * k3, gn[k])
        lam[k] = l1 - h / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
    dlv = -lam[:, :3] - gn[:, 3:]
    lv_mid = 0.5 * (lam[:-1, 3:] + lam[1:, 3:]) + h / 8.0 * (dlv[:-1] - dlv[1:])
    Hu = cfg.w_u * u + (lam[:-1, 3:] + 4.0 * lv_mid + lam[1:, 3:]) / 6.0
    return lam, Hu


def solve_indirect_continuous(cfg: SeedOcpConfig, u_init: np.ndarray | None = None) -> MethodResult:
    """The seed's indirect method with the *continuous* costate ODE (RK4 backward).

    Same loop as :func:`solve_indirect` (from the PD control, ``u <- u - alpha H_u``,
    Armijo on :func:`continuous_cost`, stop on ``max |H_u| < hu_tol``), but the costate
    and ``H_u`` come from the continuous Pontryagin equations (optimise, then
    discretise).  Its optimum is that of the continuous problem with piecewise-constant
    ``u``; it differs from the trapezoid grid problem of the direct method by
    O(h^2) (measured in ``benchmarks/bench_plan.py``).
    """
    t0 = time.perf_counter()
    x0 = np.asarray(cfg.x0, dtype=float)
    h = cfg.h
    u = pd_rollout(cfg)[1] if u_init is None else np.array(u_init, dtype=float)
    x = rollout(x0, u, h)
    J = continuous_cost(x, u, cfg)
    _, Hu = continuous_costate(x, u, cfg)
    hist = {"hu_max": [float(np.abs(Hu).max())], "cost": [J], "alpha": []}
    alpha, it, converged = cfg.alpha0, 0, False
    while it < cfg.max_iter:
        if float(np.abs(Hu).max()) < cfg.hu_tol:
            converged = True
            break
        g2 = h * float(np.sum(Hu * Hu))
        a = min(2.0 * alpha, 4.0 * cfg.alpha0)
        while a >= 1e-14:
            u_try = u - a * Hu
            x_try = rollout(x0, u_try, h)
            J_try = continuous_cost(x_try, u_try, cfg)
            if np.isfinite(J_try) and J_try <= J - 1e-4 * a * g2:
                break
            a *= 0.5
        if a < 1e-14:  # H_u and the Simpson cost disagree at this level: stop here
            break
        alpha, u, x, J = a, u_try, x_try, J_try
        _, Hu = continuous_costate(x, u, cfg)
        it += 1
        hist["hu_max"].append(float(np.abs(Hu).max()))
        hist["cost"].append(J)
        hist["alpha"].append(a)
    return MethodResult(
        name="indirect_continuous",
        t=cfg.t,
        x=x,
        u=u,
        cost=seed_cost(x, u, cfg),
        solve_time_s=time.perf_counter() - t0,
        iterations=it,
        converged=converged,
        hu_max=float(np.abs(Hu).max()),
        history=hist,
        info={"continuous_cost": J},
    )


# --------------------------------------------------------------------------
# Direct method (CasADi Opti, multiple shooting, IPOPT)
# --------------------------------------------------------------------------
def det_observability_casadi(p, beacons: np.ndarray):
    """Symbolic ``det(O)`` (CasADi) for a 3-vector ``p``; same formula as NumPy."""
    import casadi as ca

    rows = []
    for b in np.asarray(beacons, dtype=float):
        a = p - ca.DM(b)
        rows.append((a / ca.sqrt(ca.sumsqr(a))).T)
    return ca.det(ca.vertcat(*rows))


def solve_direct(cfg: SeedOcpConfig, u_init: np.ndarray | None = None, verbose: bool = False, fixed_final: bool = False) -> MethodResult:
    """Direct multiple shooting on the shared grid, solved by IPOPT.

    ``fixed_final=True`` solves the seed's suggested variant with the final
    state fixed at the goal, at rest (``X_N = [p_d, 0]``), to quantify the
    trade-off the seed describes (final velocity vs observability).

    Decision variables: nodes ``X_0..X_N`` (6 each) and controls ``u_0..u_{N-1}``;
    shooting constraints are the exact ZOH transition (linear), so the NLP's
    only nonlinearity is ``1/det(O)^2``.  Initial guess: the PD trajectory
    (as the indirect method).  ``solve_time_s`` is the wall time of
    ``opti.solve()`` (IPOPT including CasADi function evaluations); building
    the problem is reported separately in ``info['build_time_s']``.
    """
    import casadi as ca

    tb = time.perf_counter()
    n, h = cfg.n_steps, cfg.h
    bea = np.asarray(cfg.beacons, dtype=float)
    goal = ca.DM(cfg.goal)
    w = _weights(n)
    opti, X, U = double_integrator_opti(n, h, cfg.x0)
    if fixed_final:
        opti.subject_to(X[:, -1] == ca.DM(list(cfg.goal) + [0.0, 0.0, 0.0]))
    # running cost as a CasADi Function mapped over the nodes (keeps the graph small)
    xs = ca.SX.sym("x", 6)
    D = det_observability_casadi(xs[:3], bea)
    ell = cfg.w_det / D**2 + cfg.w_track * 0.5 * ca.sumsqr(xs[:3] - goal)
    if cfg.track_velocity:
        ell = ell + cfg.w_track * 0.5 * ca.sumsqr(xs[3:])
    fl = ca.Function("ell", [xs], [ell]).map(n + 1)
    J = h * ca.mtimes(fl(X), ca.DM(w)) + cfg.w_u * 0.5 * h * ca.sumsqr(U)
    opti.minimize(J)
    xpd, upd = pd_rollout(cfg)
    if u_init is not None:
        upd = np.asarray(u_init, dtype=float)
        xpd = rollout(np.asarray(cfg.x0), upd, h)
    opts = {"expand": False, "print_time": False}
    ipopt = {"tol": cfg.ipopt_tol, "max_iter": cfg.ipopt_max_iter, "print_level": 5 if verbose else 0, "sb": "yes"}
    opti.solver("ipopt", opts, ipopt)
    # to_function builds the NLP solver once (derivatives, sparsity): that is
    # the "build"; calling it is the solve.  (expand=True would turn the MX
    # graph into SX: ~4x slower to build here for no gain in solve time.)
    solver = opti.to_function("seed_ocp", [X, U], [X, U])
    build = time.perf_counter() - tb
    ts = time.perf_counter()
    try:
        Xs, Us = solver(xpd.T, upd.T)
        stats = solver.stats()
        ok = bool(stats.get("success", False))
    except RuntimeError as exc:  # IPOPT failed: flag it, keep the initial guess
        ok = False
        Xs, Us = xpd.T, upd.T
        stats = {"return_status": str(exc)}
    elapsed = time.perf_counter() - ts
    x = np.asarray(Xs).T
    u = np.asarray(Us).T.reshape(n, 3)
    _, Hu = hamiltonian_gradient(x, u, cfg)
    if fixed_final:  # lambda(T) = 0 does not hold with a fixed end: H_u of the free problem is meaningless
        Hu = np.full_like(Hu, np.nan)
    return MethodResult(
        name="direct_fixed_final" if fixed_final else "direct",
        t=cfg.t,
        x=x,
        u=u,
        cost=seed_cost(x, u, cfg),
        solve_time_s=elapsed,
        iterations=int(stats.get("iter_count", -1)),
        converged=ok,
        hu_max=float(np.abs(Hu).max()),
        info={"build_time_s": build, "return_status": stats.get("return_status", ""), "objective_ipopt": float(stats["iterations"]["obj"][-1]) if "iterations" in stats else float("nan")},
    )


# --------------------------------------------------------------------------
# All three together
# --------------------------------------------------------------------------
@dataclass
class SeedOcpResult:
    cfg: SeedOcpConfig
    pd: MethodResult
    indirect: MethodResult
    direct: MethodResult
    fixed_final: Optional[MethodResult] = None
    indirect_continuous: Optional[MethodResult] = None

    def agreement(self) -> dict[str, float]:
        """Differences between the two optimal solutions."""
        a, b = self.indirect, self.direct
        return {
            "cost_rel_diff": abs(a.cost["total"] - b.cost["total"]) / abs(b.cost["total"]),
            "u_max_abs_diff": float(np.abs(a.u - b.u).max()),
            "p_max_abs_diff": float(np.abs(a.x[:, :3] - b.x[:, :3]).max()),
        }

    def summary(self) -> dict[str, Any]:
        """Flat JSON-able summary (the content of ``plan.json``)."""
        c = self.cfg
        out: dict[str, Any] = {
            "cost_pd": self.pd.cost["total"],
            "cost_indirect": self.indirect.cost["total"],
            "cost_direct": self.direct.cost["total"],
            "det_mean_pd": self.pd.cost["det_mean"],
            "det_mean_opt": self.direct.cost["det_mean"],
            "det_mean_indirect": self.indirect.cost["det_mean"],
            "solve_time_direct_s": self.direct.solve_time_s,
            "build_time_direct_s": self.direct.info.get("build_time_s"),
            "solve_time_indirect_s": self.indirect.solve_time_s,
            "iterations_indirect": self.indirect.iterations,
            "iterations_direct": self.direct.iterations,
            "converged_indirect": self.indirect.converged,
            "converged_direct": self.direct.converged,
            "hu_max_indirect": self.indirect.hu_max,
            "hu_max_direct": self.direct.hu_max,
            "agreement": self.agreement(),
            "terms": {m.name: m.cost for m in (self.pd, self.indirect, self.direct)},
            "final_state": {m.name: m.x[-1].tolist() for m in (self.pd, self.indirect, self.direct)},
            "config": c.model_dump(),
        }
        ic = self.indirect_continuous
        if ic is not None:
            out.update(
                cost_indirect_continuous=ic.cost["total"],
                continuous_cost_indirect_continuous=ic.info["continuous_cost"],
                solve_time_indirect_continuous_s=ic.solve_time_s,
                converged_indirect_continuous=ic.converged,
                u_max_abs_diff_continuous_vs_direct=float(np.abs(ic.u - self.direct.u).max()),
            )
            out["terms"][ic.name] = ic.cost
        if self.fixed_final is not None:
            ff = self.fixed_final
            out.update(
                cost_direct_fixed_final=ff.cost["total"],
                det_mean_fixed_final=ff.cost["det_mean"],
                converged_fixed_final=ff.converged,
            )
            out["terms"][ff.name] = ff.cost
            out["final_state"][ff.name] = ff.x[-1].tolist()
        return out


def solve_seed_ocp(cfg: SeedOcpConfig | None = None, fixed_final: bool = True, continuous: bool = True) -> SeedOcpResult:
    """PD baseline, indirect and direct solutions of the seed problem, plus the
    fixed-final-state variant (direct) and the continuous-costate indirect method."""
    cfg = cfg or SeedOcpConfig()
    t0 = time.perf_counter()
    x, u = pd_rollout(cfg)
    pd = MethodResult("pd", cfg.t, x, u, seed_cost(x, u, cfg), time.perf_counter() - t0, 0, True, float(np.abs(hamiltonian_gradient(x, u, cfg)[1]).max()))
    ind = solve_indirect(cfg)
    dire = solve_direct(cfg)
    ff = solve_direct(cfg, fixed_final=True) if fixed_final else None
    ic = solve_indirect_continuous(cfg) if continuous else None
    return SeedOcpResult(cfg, pd, ind, dire, ff, ic)
