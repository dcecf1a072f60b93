"""Built-in models of the observability engine.

* :func:`uwb_imu_model` — seed 001's model (eq. 20-21): state
  ``x~ = (p, v, q, b_a, b_g, p_IU)`` (19 numbers, 18 tangent dimensions; no
  ``t_d``, which Theorem 1 treats separately), N anchors, IMU inputs. The fields
  come from :func:`uwbimu.models.reference.control_affine_fields` and the
  antenna position from :func:`uwbimu.models.reference.antenna_position`
  evaluated with CasADi symbols: the very lines the simulator and estimator use.
  The output is seed eq. (9)/(21), ``0.5 ||p_anchor - p_U||^2``, which has the
  same observability codistribution as the range wherever the range is non-zero
  (``d(phi(h)) = phi'(h) dh`` with ``phi' != 0``) and much smaller expressions.
* :func:`point_mass_model` — seed 002's 6-state point mass ``p' = v, v' = a``
  (world acceleration input) with N beacons (``0.5 r^2``, as seed 002's ``r^2``)
  and optionally an altimeter measuring the height ``z`` (ground at z = 0).

Parameters (anchor positions, the constant input of non-excited channels) are
CasADi parameters, so a compiled model serves every configuration with the same
number of anchors and the same excited axes.  Specifications are frozen
dataclasses and the compiled engines are cached per (spec, order) with
:func:`functools.lru_cache`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from uwbimu.models import state as ST
from uwbimu.models import reference as ref
from uwbimu.observability.engine import ControlAffineModel, LieObservability

AXES = ("x", "y", "z")

#: Tangent coordinate names of the 19-state model (18 = 3+3+3+3+3+3).
UWB_IMU_TANGENT_NAMES = (
    "px", "py", "pz", "vx", "vy", "vz", "thx", "thy", "thz",
    "bax", "bay", "baz", "bgx", "bgy", "bgz", "lx", "ly", "lz",
)  # fmt: skip
UWB_IMU_STATE_NAMES = (
    "px", "py", "pz", "vx", "vy", "vz", "qw", "qx", "qy", "qz",
    "bax", "bay", "baz", "bgx", "bgy", "bgz", "lx", "ly", "lz",
)  # fmt: skip
POINT_MASS_NAMES = ("px", "py", "pz", "vx", "vy", "vz")


@dataclass(frozen=True)
class UwbImuSpec:
    """Structure of the 19-state model: anchor count and excited input axes."""

    n_anchors: int = 3
    accel_axes: tuple[str, ...] = AXES
    gyro_axes: tuple[str, ...] = AXES
    measurement: str = "range"  # "range" | "tdoa"


@dataclass(frozen=True)
class PointMassSpec:
    """Structure of the 6-state point mass: beacon count, altimeter, excited axes."""

    n_beacons: int = 3
    altimeter: bool = False
    accel_axes: tuple[str, ...] = ()


def _axes_idx(axes) -> list[int]:
    return [AXES.index(a) for a in axes]


def random_quaternion(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    return q / np.linalg.norm(q)


# --------------------------------------------------------------------------
# 19-state UWB-IMU model (seed 001)
# --------------------------------------------------------------------------
def uwb_imu_model(spec: UwbImuSpec) -> ControlAffineModel:
    """Seed 001's model (eq. 20-21) with ``spec.n_anchors`` anchors.

    Parameters of the compiled functions: ``p = [anchors (3N), u0 (6)]`` where
    ``u0 = [a_m, w_m]`` is the constant IMU reading of the non-excited channels
    (it enters the drift ``f0 + F u0``; excited channels also get their own
    input field).
    """
    import casadi as ca

    ops = ref.casadi_ops()
    x = ca.SX.sym("x", 19)
    x20 = ca.vertcat(x, 0)  # t_d is not part of this model (Theorem 1 handles it)
    N = spec.n_anchors
    A = ca.SX.sym("anchors", 3 * N)
    u0 = ca.SX.sym("u0", 6)
    f0, F = ref.control_affine_fields(x20, ops)
    f0, F = f0[:19], F[:19, :]
    drift = f0 + ca.mtimes(F, u0)
    fields, names = [], []
    for j in _axes_idx(spec.accel_axes):
        fields.append(F[:, j])
        names.append(f"a{AXES[j]}")
    for j in _axes_idx(spec.gyro_axes):
        fields.append(F[:, 3 + j])
        names.append(f"w{AXES[j]}")
    pU = ref.antenna_position(x20, ops)
    if spec.measurement == "tdoa":
        # differences to anchor 0 span every pair's difference (r_b - r_a = (r_b - r_0) - (r_a - r_0))
        r = [ca.norm_2(A[3 * i : 3 * i + 3] - pU) for i in range(N)]
        h = ca.vertcat(*[r[i] - r[0] for i in range(1, N)])
    else:
        h = ca.vertcat(*[0.5 * ca.sumsqr(A[3 * i : 3 * i + 3] - pU) for i in range(N)])
    Xi = ref.quaternion_rate_matrix(x[ST.Q], ops)
    T = ca.SX.zeros(19, 18)
    T[0:6, 0:6] = ca.SX.eye(6)
    # right (body) perturbation q (x) Exp(dtheta): dq/ddtheta = 0.5 Xi(q)
    T[6:10, 6:9] = 0.5 * Xi
    T[10:19, 9:18] = ca.SX.eye(9)

    def sampler(rng):
        return sample_uwb_imu_state(rng), np.r_[rng.uniform(-5, 5, 3 * N), rng.normal(0, 2, 6)]

    return ControlAffineModel(
        name=f"uwb_imu[{N} anchors{', tdoa' if spec.measurement == 'tdoa' else ''}]",
        x=x,
        params=ca.vertcat(A, u0),
        drift=drift,
        fields=fields,
        field_names=names,
        outputs=h,
        state_names=UWB_IMU_STATE_NAMES,
        tangent=T,
        tangent_names=UWB_IMU_TANGENT_NAMES,
        sampler=sampler,
    )


def sample_uwb_imu_state(rng: np.random.Generator, lever_arm=None, box: float = 3.0) -> np.ndarray:
    """A random 19-number state ``(p, v, q, b_a, b_g, p_IU)`` (generic values)."""
    x = np.empty(19)
    x[ST.P] = rng.uniform(-box, box, 3)
    x[ST.V] = rng.normal(0, 1.0, 3)
    x[ST.Q] = random_quaternion(rng)
    x[ST.BA] = rng.normal(0, 0.1, 3)
    x[ST.BG] = rng.normal(0, 0.05, 3)
    x[ST.PIU] = rng.normal(0, 0.2, 3) if lever_arm is None else lever_arm
    return x


@lru_cache(maxsize=64)
def compiled_uwb_imu(spec: UwbImuSpec, order: int) -> LieObservability:
    """Compiled engine for a 19-state model structure (cached per process)."""
    return LieObservability(uwb_imu_model(spec), order)


# --------------------------------------------------------------------------
# Point mass (seed 002)
# --------------------------------------------------------------------------
def point_mass_model(spec: PointMassSpec) -> ControlAffineModel:
    """Seed 002's point mass ``p' = v, v' = a0 + sum_j e_j a_j``.

    Outputs ``0.5 ||p - b_i||^2`` per beacon (seed 002 uses ``r^2``) and, with
    ``spec.altimeter``, the height ``z``.  Parameters ``[beacons (3N), a0 (3)]``.
    """
    import casadi as ca

    x = ca.SX.sym("x", 6)
    N = spec.n_beacons
    B = ca.SX.sym("beacons", 3 * N)
    a0 = ca.SX.sym("a0", 3)
    drift = ca.vertcat(x[3:6], a0)
    fields, names = [], []
    for j in _axes_idx(spec.accel_axes):
        e = ca.SX.zeros(6)
        e[3 + j] = 1
        fields.append(e)
        names.append(f"a{AXES[j]}")
    outs = [0.5 * ca.sumsqr(x[0:3] - B[3 * i : 3 * i + 3]) for i in range(N)]
    if spec.altimeter:
        outs.append(x[2])

    def sampler(rng):
        return np.r_[rng.uniform(-3, 3, 3), rng.normal(0, 1, 3)], np.r_[rng.uniform(-5, 5, 3 * N), rng.normal(0, 1, 3)]

    return ControlAffineModel(
        name=f"point_mass[{N} beacons{' + altimeter' if spec.altimeter else ''}]",
        x=x,
        params=ca.vertcat(B, a0),
        drift=drift,
        fields=fields,
        field_names=names,
        outputs=ca.vertcat(*outs),
        state_names=POINT_MASS_NAMES,
        sampler=sampler,
    )


@lru_cache(maxsize=64)
def compiled_point_mass(spec: PointMassSpec, order: int) -> LieObservability:
    """Compiled engine for a point-mass structure (cached per process)."""
    return LieObservability(point_mass_model(spec), order)
