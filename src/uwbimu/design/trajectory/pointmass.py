"""Observability-aware planning for the point mass, in general (CasADi + IPOPT).

Model: the double integrator of seed 002 eq. (1), ``X = [p, v]``,
``u`` = inertial acceleration, exact ZOH on a grid of ``N`` steps ``h``.

Information accumulated along the path
--------------------------------------
Ranges ``r_j = |p - b_j| + n``, ``n ~ N(0, sigma^2)``, from every beacon at
``rate_hz``.  With the control known, the whole trajectory is a function of
the initial state, ``X_k = Phi_k X_0 + ...`` with ``Phi_k = [[I, t_k I],
[0, I]]``, so the Fisher information of ``X_0`` from all ranges is::

    I_0 = I_prior + sum_k c_k sum_j Phi_k^T H_jk^T H_jk Phi_k,
    H_jk = [e_jk^T, 0],  e_jk = (p_k - b_j)/|p_k - b_j|,
    c_k  = w_k h rate_hz / sigma^2      (trapezoid weights w_k)

(each grid node stands for ``h * rate_hz`` ranges per beacon).  With
``M_n = sum_k c_k t_k^n sum_j e e^T`` this is ``[[M0, M1], [M1, M2]]``.
``info_at='final'`` maps it to the final state (``Phi_N^-T I_0 Phi_N^-1``;
log-det is the same, E- and A-optimality differ).  ``info_model='position'``
uses the purely geometric ``M0`` (3x3, the sum of the per-epoch position
information, ignoring that the dynamics link the epochs).

Objectives (``objective``), all plus ``w_u * sum h/2 |u|^2`` and optional
tracking ``w_track * sum h/2 |p - goal|^2``:

* ``logdet``: minimise ``-log det I`` (D-optimal), via a symbolic Cholesky;
* ``min_eig``: maximise ``s`` subject to ``I - s Id = L L^T`` (E-optimal as
  an epigraph: the slack ``s`` is a lower bound of the smallest eigenvalue,
  made tight at the optimum; ``L`` lower-triangular, extra variables);
* ``trace_inv``: minimise ``trace Z`` subject to ``I Z = Id`` (A-optimal,
  ``Z = I^-1`` as extra variables, no symbolic inverse);
* ``none``: control effort (and tracking) only -- the baseline.

The information terms are divided by their value at the initial guess so
that ``w_info`` is a dimensionless trade-off against the control effort.

Constraints: flight box, spheres ``|p - c| >= r + margin``, axis-aligned boxes
through the smooth superellipsoid ``sum ((p_i - c_i)/s_i)^8 >= 1`` with
``s_i = 3^(1/8) (half_i + margin)`` (it contains the box: conservative by at
most 15 % across a face), ``|v_k| <= v_max``, ``|u_k| <= a_max``, terminal
position (exact or within ``goal_tolerance``) and velocity.  Constraints hold
on the grid nodes (between nodes a path may cut a corner by at most
``v_max h / 2``; add that to ``margin`` when it matters).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Literal, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from uwbimu.design.trajectory.platform import MultirotorLimits, Platform
from uwbimu.design.trajectory.seed_ocp import TimeGrid, _weights, double_integrator_opti
from uwbimu.models.reference import GRAVITY


class Obstacle(BaseModel):
    """A sphere (``center``, ``radius``) or an axis-aligned box (``center``, ``half_size``) [m]."""

    model_config = ConfigDict(extra="forbid")
    kind: Literal["sphere", "box"]
    center: list[float] = Field(min_length=3, max_length=3)
    radius: Optional[float] = Field(None, gt=0)
    half_size: Optional[list[float]] = Field(None, min_length=3, max_length=3)
    margin: float = Field(0.0, ge=0)

    @model_validator(mode="after")
    def _shape(self):
        if self.kind == "sphere" and self.radius is None:
            raise ValueError("a sphere obstacle needs 'radius'")
        if self.kind == "box" and (self.half_size is None or min(self.half_size) <= 0):
            raise ValueError("a box obstacle needs positive 'half_size' [hx, hy, hz]")
        return self

    def clearance(self, p: np.ndarray) -> np.ndarray:
        """Constraint value (>= 0 feasible) at positions ``(..., 3)``; the same formula as the NLP."""
        d = np.asarray(p, dtype=float) - np.asarray(self.center)
        if self.kind == "sphere":
            return np.sum(d * d, axis=-1) - (self.radius + self.margin) ** 2
        s = 3.0 ** 0.125 * (np.asarray(self.half_size) + self.margin)
        return np.sum((d / s) ** 8, axis=-1) - 1.0


class PointMassPlanConfig(TimeGrid, BaseModel):
    """Options of the general point-mass planner (SI units, world frame)."""

    model_config = ConfigDict(extra="forbid")

    beacons: list[list[float]] = Field(min_length=1)
    platform: Platform = Field("multirotor", description="multirotor: thrust/tilt/rate limits, flat attitude; handheld: none")
    multirotor: MultirotorLimits = Field(default_factory=MultirotorLimits, description="limits of the multirotor platform")
    yaw: float = Field(0.0, description="constant yaw of the flown trajectory [rad] (the point mass has none)")
    limit_margin: float = Field(
        0.9, gt=0, le=1,
        description="multirotor: the grid constraints use this fraction of the thrust-max / tilt / rate limits "
        "(the simulator's spline through the nodes overshoots the piecewise-constant plan by a few %)",
    )
    x0: list[float] = Field(min_length=6, max_length=6, description="[px, py, pz, vx, vy, vz]")
    tf: float = Field(gt=0)
    n_steps: int = Field(100, ge=4)
    goal: Optional[list[float]] = Field(None, min_length=3, max_length=3, description="terminal position")
    goal_tolerance: float = Field(0.0, ge=0, description="0: exact terminal position; else |p_N - goal|_inf <= tol")
    goal_velocity: Optional[list[float]] = Field(None, min_length=3, max_length=3, description="terminal velocity")
    box_min: Optional[list[float]] = Field(None, min_length=3, max_length=3)
    box_max: Optional[list[float]] = Field(None, min_length=3, max_length=3)
    obstacles: list[Obstacle] = Field(default_factory=list)
    v_max: Optional[float] = Field(None, gt=0)
    a_max: Optional[float] = Field(None, gt=0)
    objective: Literal["logdet", "min_eig", "trace_inv", "none"] = "logdet"
    info_model: Literal["state", "position"] = "state"
    info_at: Literal["initial", "final"] = "initial"
    w_info: float = Field(1.0, ge=0)
    w_u: float = Field(1.0, ge=0)
    w_track: float = Field(0.0, ge=0)
    range_sigma: float = Field(0.1, gt=0, description="range noise sd [m]")
    rate_hz: float = Field(10.0, gt=0, description="ranges per second per beacon")
    prior_sigma_p: float = Field(10.0, gt=0, description="prior sd of the initial position [m] (regularises I)")
    prior_sigma_v: float = Field(10.0, gt=0, description="prior sd of the initial velocity [m/s]")
    ipopt_tol: float = Field(1e-8, gt=0)
    ipopt_max_iter: int = Field(3000, ge=1, description="E-optimality with the multirotor limits needs ~1100")

    @model_validator(mode="after")
    def _check(self):
        for b in self.beacons:
            if len(b) != 3:
                raise ValueError("each beacon must be [x, y, z]")
        if (self.box_min is None) != (self.box_max is None):
            raise ValueError("give both box_min and box_max or neither")
        if self.box_min is not None and any(lo >= hi for lo, hi in zip(self.box_min, self.box_max)):
            raise ValueError("box_min must be below box_max on every axis")
        return self


# --------------------------------------------------------------------------
# Information (NumPy and CasADi share the same assembly)
# --------------------------------------------------------------------------
def _info_from_moments(M0, M1, M2, cfg: PointMassPlanConfig, cat):
    """Assemble the information matrix from the moments (``cat`` = block builder)."""
    if cfg.info_model == "position":
        return M0 + np.eye(3) / cfg.prior_sigma_p**2
    prior = np.diag([1 / cfg.prior_sigma_p**2] * 3 + [1 / cfg.prior_sigma_v**2] * 3)
    I0 = cat(M0, M1, M2) + prior
    if cfg.info_at == "final":
        Pinv = np.block([[np.eye(3), -cfg.tf * np.eye(3)], [np.zeros((3, 3)), np.eye(3)]])
        I0 = Pinv.T @ I0 @ Pinv
    return I0


def information_matrix(x: np.ndarray, cfg: PointMassPlanConfig) -> np.ndarray:
    """Fisher information (6x6, or 3x3 for ``info_model='position'``) of a trajectory.

    Parameters
    ----------
    x : (N+1, >=3) states on the planner grid (positions in the first columns) [m].
    """
    p = np.asarray(x, dtype=float)[:, :3]
    e = _unit(p, cfg)
    c = _weights(len(p) - 1) * cfg.h * cfg.rate_hz / cfg.range_sigma**2
    t = cfg.t
    E = np.einsum("kji,kjl->kil", e, e)  # sum over beacons of e e^T, per node
    M = [np.einsum("k,kil->il", c * t**n, E) for n in range(3)]
    return _info_from_moments(*M, cfg, lambda a, b, cc: np.block([[a, b], [b, cc]]))


def _unit(p: np.ndarray, cfg: PointMassPlanConfig) -> np.ndarray:
    d = np.asarray(p, dtype=float)[:, None, :] - np.asarray(cfg.beacons, dtype=float)[None]
    return d / np.linalg.norm(d, axis=2, keepdims=True)


def info_metrics(info: np.ndarray) -> dict[str, float]:
    """log det, smallest eigenvalue and trace of the inverse of an information matrix."""
    ev = np.linalg.eigvalsh(info)
    return {"logdet": float(np.sum(np.log(ev))), "min_eig": float(ev[0]), "trace_inv": float(np.sum(1.0 / ev))}


def _sym_chol(A, n):
    """Cholesky factor of a symbolic SPD matrix by the textbook loops (n small)."""
    import casadi as ca

    L = [[0] * n for _ in range(n)]
    for j in range(n):
        s = A[j, j] - sum(L[j][k] ** 2 for k in range(j))
        L[j][j] = ca.sqrt(s)
        for i in range(j + 1, n):
            L[i][j] = (A[i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    return L


# --------------------------------------------------------------------------
# Planner
# --------------------------------------------------------------------------
@dataclass
class PointMassPlan:
    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    info: np.ndarray
    metrics: dict[str, float]
    success: bool
    status: str
    solve_time_s: float
    build_time_s: float
    constraint_violation: dict[str, float] = field(default_factory=dict)
    extra: dict[str, Any] = field(default_factory=dict)


def initial_guess(cfg: PointMassPlanConfig) -> tuple[np.ndarray, np.ndarray]:
    """Rest-to-rest minimum-jerk line from ``x0`` to ``goal`` (or hover), as ``(x, u)``."""
    p0 = np.asarray(cfg.x0[:3])
    pg = np.asarray(cfg.goal) if cfg.goal is not None else p0
    s = cfg.t / cfg.tf
    shape = 10 * s**3 - 15 * s**4 + 6 * s**5
    x = np.zeros((cfg.n_steps + 1, 6))
    x[:, :3] = p0 + shape[:, None] * (pg - p0)
    x[:, 3:] = (30 * s**2 - 60 * s**3 + 30 * s**4)[:, None] * (pg - p0) / cfg.tf
    u = np.diff(x[:, 3:], axis=0) / cfg.h
    return x, u


def constraint_violations(x: np.ndarray, u: np.ndarray, cfg: PointMassPlanConfig) -> dict[str, float]:
    """Largest violation of every constraint family (0 = satisfied) [SI units]."""
    out: dict[str, float] = {}
    p, v = x[:, :3], x[:, 3:]
    if cfg.box_min is not None:
        out["box"] = float(max(0.0, np.max(np.asarray(cfg.box_min) - p), np.max(p - np.asarray(cfg.box_max))))
    for i, ob in enumerate(cfg.obstacles):
        out[f"obstacle_{i}"] = float(max(0.0, -np.min(ob.clearance(p))))
    if cfg.v_max is not None:
        out["v_max"] = float(max(0.0, np.max(np.linalg.norm(v, axis=1)) - cfg.v_max))
    if cfg.a_max is not None:
        out["a_max"] = float(max(0.0, np.max(np.linalg.norm(u, axis=1)) - cfg.a_max))
    if cfg.goal is not None:
        out["goal"] = float(max(0.0, np.max(np.abs(p[-1] - cfg.goal)) - cfg.goal_tolerance))
    if cfg.goal_velocity is not None:
        out["goal_velocity"] = float(np.max(np.abs(v[-1] - cfg.goal_velocity)))
    if cfg.platform == "multirotor":
        lim = cfg.multirotor
        T, J = _thrust_and_jerk(u, cfg)
        nT = np.linalg.norm(T, axis=1)
        out["thrust_max"] = float(max(0.0, np.max(nT) - lim.thrust_max))
        out["thrust_min"] = float(max(0.0, lim.thrust_min - np.min(nT)))
        out["tilt"] = float(max(0.0, np.max(np.arccos(np.clip(T[:, 2] / nT, -1, 1))) - lim.tilt_max))
        zd = np.sqrt(np.maximum(np.sum(J * J, 1) - np.sum(J * T[:-1], 1) ** 2 / nT[:-1] ** 2, 0.0)) / nT[:-1]
        out["rate"] = float(max(0.0, np.max(zd, initial=0.0) - lim.rate_max))
    return out


def _rest_ends(cfg: PointMassPlanConfig) -> tuple[bool, bool]:
    """Whether the vehicle is at rest (hovering, zero acceleration) before the start / after the end."""
    start = bool(np.allclose(cfg.x0[3:], 0.0))
    end = cfg.goal_velocity is not None and bool(np.allclose(cfg.goal_velocity, 0.0))
    return start, end


def _thrust_and_jerk(u, cfg: PointMassPlanConfig, lib=np):
    """Thrust per unit mass ``T_k = u_k + g e_z`` (rows) and the jerk between consecutive controls,
    with zero acceleration before / after a rest end (hover: the attitude is level there)."""
    start, end = _rest_ends(cfg)
    u = np.asarray(u, dtype=float)
    seq = [np.zeros((1, 3))] * start + [u] + [np.zeros((1, 3))] * end
    a = np.vstack(seq)
    T = a + np.array([0.0, 0.0, GRAVITY])
    return T, np.diff(a, axis=0) / cfg.h


def _multirotor_constraints(opti, U, cfg: PointMassPlanConfig) -> None:
    """Thrust, tilt and body-rate limits of the multirotor on the grid (ZOH controls).

    ``T = u + g e_z``: ``T_min^2 <= |T|^2 <= T_max^2``, tilt ``T_z >= cos(tilt_max) |T|``
    (as ``T_z >= 0``, ``T_z^2 >= cos^2 |T|^2``); body z rate ``|z'| = |(I - z z^T) j| / |T|``
    with the jerk ``j`` of consecutive controls, squared and multiplied out:
    ``|j|^2 |T|^2 - (T.j)^2 <= rate_max^2 |T|^4`` (with a constant yaw this is the body rate
    up to the small ``w_z`` of Z-Y-X Euler angles; the flown trajectory is checked exactly).
    """
    import casadi as ca

    lim, k = cfg.multirotor, cfg.limit_margin
    start, end = _rest_ends(cfg)
    g = ca.DM([0.0, 0.0, GRAVITY])
    n = U.shape[1]
    cols = ([ca.DM.zeros(3, 1)] if start else []) + [U[:, k] for k in range(n)] + ([ca.DM.zeros(3, 1)] if end else [])
    A = ca.horzcat(*cols)
    T = A + ca.repmat(g, 1, A.shape[1])
    T2 = ca.sum1(T**2)
    opti.subject_to(opti.bounded((lim.thrust_min / k) ** 2, T2, (k * lim.thrust_max) ** 2))
    opti.subject_to(T[2, :] >= 0)
    opti.subject_to(T[2, :] ** 2 >= np.cos(k * lim.tilt_max) ** 2 * T2)
    # at a rest end the first / last control is a hover node too: the simulator's spline brings the
    # acceleration to zero within one node interval, and a jump there would be a body-rate spike
    if start:
        opti.subject_to(U[:, 0] == 0)
    if end:
        opti.subject_to(U[:, -1] == 0)
    Jk = (A[:, 1:] - A[:, :-1]) / cfg.h
    Tk, T2k = T[:, :-1], T2[:-1]
    opti.subject_to(ca.sum1(Jk**2) * T2k - ca.sum1(Tk * Jk) ** 2 <= (k * lim.rate_max) ** 2 * T2k**2)


def flight_trajectory(plan: "PointMassPlan", cfg: PointMassPlanConfig):
    """The plan as the simulator flies it: rows ``t, p, yaw`` on the grid and the simulator trajectory
    (multirotor: :class:`uwbimu.sim.flat.FlatSplineTrajectory`, roll/pitch from the thrust;
    handheld: level, constant yaw)."""
    from uwbimu.sim.flat import FlatSplineTrajectory
    from uwbimu.sim.trajectory import SplineTrajectory

    yaw = np.full(len(plan.t), cfg.yaw)
    if cfg.platform == "multirotor":
        return FlatSplineTrajectory(plan.t, plan.x[:, :3], yaw)
    e = np.zeros((len(plan.t), 3))
    e[:, 2] = yaw
    return SplineTrajectory(plan.t, plan.x[:, :3], e)


def plan_point_mass(cfg: PointMassPlanConfig, x_init=None, u_init=None, verbose: bool = False) -> PointMassPlan:
    """Solve the observability-aware point-mass planning problem with IPOPT."""
    import casadi as ca

    tb = time.perf_counter()
    n, h = cfg.n_steps, cfg.h
    if x_init is None or u_init is None:
        x_init, u_init = initial_guess(cfg)
    opti, X, U = double_integrator_opti(n, h, cfg.x0)
    P = X[:3, :]
    if cfg.box_min is not None:
        opti.subject_to(opti.bounded(ca.DM(cfg.box_min), P, ca.DM(cfg.box_max)))
    for ob in cfg.obstacles:
        d = P - ca.DM(ob.center)
        if ob.kind == "sphere":
            opti.subject_to(ca.sum1(d * d) >= (ob.radius + ob.margin) ** 2)
        else:
            s = ca.DM(3.0 ** 0.125 * (np.asarray(ob.half_size) + ob.margin))
            opti.subject_to(ca.sum1((d / ca.repmat(s, 1, n + 1)) ** 8) >= 1.0)
    if cfg.v_max is not None:
        opti.subject_to(ca.sum1(X[3:, :] ** 2) <= cfg.v_max**2)
    if cfg.a_max is not None:
        opti.subject_to(ca.sum1(U**2) <= cfg.a_max**2)
    if cfg.platform == "multirotor":
        _multirotor_constraints(opti, U, cfg)
    if cfg.goal is not None:
        if cfg.goal_tolerance > 0:
            opti.subject_to(opti.bounded(ca.DM(cfg.goal) - cfg.goal_tolerance, X[:3, -1], ca.DM(cfg.goal) + cfg.goal_tolerance))
        else:
            opti.subject_to(X[:3, -1] == ca.DM(cfg.goal))
    if cfg.goal_velocity is not None:
        opti.subject_to(X[3:, -1] == ca.DM(cfg.goal_velocity))

    J = cfg.w_u * 0.5 * h * ca.sumsqr(U)
    if cfg.w_track > 0 and cfg.goal is not None:
        J = J + cfg.w_track * 0.5 * h * ca.sumsqr(P - ca.repmat(ca.DM(cfg.goal), 1, n + 1))
    info0 = information_matrix(x_init, cfg)
    m0 = info_metrics(info0)
    dim = info0.shape[0]
    extra_init: list[tuple[Any, np.ndarray]] = []
    if cfg.objective != "none" and cfg.w_info > 0:
        # moments of the information, symbolic
        ps = ca.SX.sym("p", 3)
        E = ca.SX.zeros(3, 3)
        for b in np.asarray(cfg.beacons, dtype=float):
            dd = ps - ca.DM(b)
            e = dd / ca.sqrt(ca.sumsqr(dd))
            E += ca.mtimes(e, e.T)
        iu = np.triu_indices(3)
        fE = ca.Function("E", [ps], [ca.vertcat(*[E[i, j] for i, j in zip(*iu)])]).map(n + 1)
        Ek = fE(P)  # 6 x (n+1): unique entries of sum_j e e^T per node
        c = _weights(n) * h * cfg.rate_hz / cfg.range_sigma**2
        t = cfg.t
        # Lifting: the moments are extra variables tied to the nodes by linear-in-E
        # equalities, so the Lagrangian Hessian stays block-sparse (per node +
        # a small dense block on the moments) instead of dense over all nodes.
        n_mom = 1 if cfg.info_model == "position" else 3
        W = np.stack([c * t**k for k in range(n_mom)], axis=1)
        Ek0 = np.stack([np.einsum("kji,kjl->kil", *(2 * [_unit(x_init[:, :3], cfg)]))[:, i, j] for i, j in zip(*iu)])
        Mv0 = Ek0 @ W
        # variables scaled to O(1) (the moments reach 1e5): same optimum, better IPOPT steps
        msc = np.maximum(np.abs(Mv0).max(axis=0), 1e-12)
        Mvs = opti.variable(6, n_mom)
        Mv = Mvs * ca.repmat(ca.DM(msc).T, 6, 1)
        opti.subject_to(Mvs == ca.mtimes(Ek, ca.DM(W / msc)))
        extra_init.append((Mvs, Mv0 / msc))

        def _sym(col):
            return ca.vertcat(
                ca.horzcat(Mv[0, col], Mv[1, col], Mv[2, col]),
                ca.horzcat(Mv[1, col], Mv[3, col], Mv[4, col]),
                ca.horzcat(Mv[2, col], Mv[4, col], Mv[5, col]),
            )

        M = [_sym(k) for k in range(n_mom)] + [None] * (3 - n_mom)
        Info = _info_from_moments(*M, cfg, lambda a, b, cc: ca.vertcat(ca.horzcat(a, b), ca.horzcat(b, cc)))
        Info = 0.5 * (Info + Info.T)
        if cfg.objective == "logdet":
            L = _sym_chol(Info, dim)
            # log det ratio to the initial guess: dimensionless like the other two
            J = J - cfg.w_info * (sum(2 * ca.log(L[i][i]) for i in range(dim)) - m0["logdet"])
        elif cfg.objective == "min_eig":
            lam0 = m0["min_eig"]
            sv = opti.variable()
            Lvv = opti.variable(dim * (dim + 1) // 2)
            s, Lv = lam0 * sv, np.sqrt(lam0) * Lvv
            Lm, k = [[0] * dim for _ in range(dim)], 0
            for i in range(dim):
                for j in range(i + 1):
                    Lm[i][j] = Lv[k]
                    k += 1
            Lsym = ca.vertcat(*[ca.horzcat(*row) for row in Lm])
            R = Info - s * ca.DM.eye(dim) - ca.mtimes(Lsym, Lsym.T)
            opti.subject_to(ca.vec(ca.tril(R)) / lam0 == 0)
            opti.subject_to(sv >= 0)
            J = J - cfg.w_info * s / m0["min_eig"]
            s0 = 0.5 * m0["min_eig"]
            L0 = np.linalg.cholesky(info0 - s0 * np.eye(dim))
            extra_init += [(sv, np.array(s0 / lam0)), (Lvv, L0[np.tril_indices(dim)] / np.sqrt(lam0))]
        elif cfg.objective == "trace_inv":
            zsc = np.sqrt(np.outer(np.diag(np.linalg.inv(info0)), np.diag(np.linalg.inv(info0))))
            Zv = opti.variable(dim, dim)
            Z = Zv * ca.DM(zsc)
            opti.subject_to(ca.vec(ca.mtimes(Info, Z) - ca.DM.eye(dim)) == 0)
            J = J + cfg.w_info * ca.trace(Z) / m0["trace_inv"]
            extra_init.append((Zv, np.linalg.inv(info0) / zsc))
    opti.minimize(J)
    opti.set_initial(X, np.asarray(x_init).T)
    opti.set_initial(U, np.asarray(u_init).T)
    for var, val in extra_init:
        opti.set_initial(var, val)
    opti.solver(
        "ipopt",
        {"expand": True, "print_time": False},
        {"tol": cfg.ipopt_tol, "max_iter": cfg.ipopt_max_iter, "print_level": 5 if verbose else 0, "sb": "yes"},
    )
    build = time.perf_counter() - tb
    ts = time.perf_counter()
    try:
        sol = opti.solve()
        xs, us, st = sol.value(X), sol.value(U), sol.stats()
    except RuntimeError:
        xs, us, st = opti.debug.value(X), opti.debug.value(U), opti.stats()
    solve = time.perf_counter() - ts
    x = np.asarray(xs).T
    u = np.asarray(us).T.reshape(n, 3)
    info = information_matrix(x, cfg)
    return PointMassPlan(
        t=cfg.t,
        x=x,
        u=u,
        info=info,
        metrics=info_metrics(info) | {"control_effort": float(0.5 * h * np.sum(u * u))},
        success=bool(st.get("success", False)),
        status=str(st.get("return_status", "")),
        solve_time_s=solve,
        build_time_s=build,
        constraint_violation=constraint_violations(x, u, cfg),
        extra={"iterations": int(st.get("iter_count", -1)), "metrics_initial_guess": m0},
    )
