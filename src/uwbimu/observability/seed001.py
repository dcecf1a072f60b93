"""The blocks of seed 001's proof of Theorem 2 (Lemmas 1-4), from the engine's symbols.

The proof eliminates ``O`` blockwise (section 3.2.4); its lemmas are rank
statements about these blocks, built here from the same CasADi model
(:func:`uwbimu.observability.models.uwb_imu_model`) with the seed's output
``h = 0.5 ||p_a - p_U||^2`` (eq. 21):

* Lemma 1: ``delta_p_ijk`` (3x3), rows ``p_a - R p_IU - p``;
* Lemma 2: ``F5 F0 - F6`` (3 rows per excited accelerometer axis x 4),
  ``F5 = d/dp, F6 = d/dq`` of ``L_{f1,j} L_{f0} h``, ``F0 = d(R p_IU)/dq``;
* Lemma 3: ``F13 R - F15`` (3 rows per excited gyro axis x 3),
  ``F13 = d/dp, F15 = d/dp_IU`` of ``L_{f2,j} h``;
* Lemma 4: ``F5 F3 + F18`` (3 rows per excited accelerometer axis x 3),
  ``F3 = 0.5 F0 Xi(q)``, ``F18 = d/db_g`` of ``L_{f0} L_{f1,j} L_{f0} h``.

The drift here is the seed's ``f0`` (no constant input), as in eq. (20).
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from uwbimu.models import state as ST
from uwbimu.models import reference as ref

AXES = ("x", "y", "z")


@lru_cache(maxsize=4)
def _blocks_function(n_anchors: int = 3):
    import casadi as ca

    ops = ref.casadi_ops()
    x = ca.SX.sym("x", 19)
    x20 = ca.vertcat(x, 0)
    A = ca.SX.sym("a", 3 * n_anchors)
    f0, F = ref.control_affine_fields(x20, ops)
    f0, F = f0[:19], F[:19, :]
    p, q, bg, l = x[ST.P], x[ST.Q], x[ST.BG], x[ST.PIU]
    R = ref.rotation_matrix(q, ops)
    pU = ref.antenna_position(x20, ops)
    h = ca.vertcat(*[0.5 * ca.sumsqr(A[3 * i : 3 * i + 3] - pU) for i in range(n_anchors)])
    dp = ca.vertcat(*[(A[3 * i : 3 * i + 3] - pU).T for i in range(n_anchors)])
    F0 = ca.jacobian(ca.mtimes(R, l), q)
    Xi = ref.quaternion_rate_matrix(q, ops)
    F3 = 0.5 * ca.mtimes(F0, Xi)
    Lf0 = ca.jtimes(h, x, f0)
    outs = [dp]
    for j in range(3):
        L = ca.jtimes(Lf0, x, F[:, j])  # L_{f1,j} L_{f0} h
        F5 = ca.jacobian(L, p)
        F6 = ca.jacobian(L, q)
        L3 = ca.jtimes(L, x, f0)  # L_{f0} L_{f1,j} L_{f0} h
        F18 = ca.jacobian(L3, bg)
        outs += [ca.mtimes(F5, F0) - F6, ca.mtimes(F5, F3) + F18]
    for j in range(3):
        L = ca.jtimes(h, x, F[:, 3 + j])  # L_{f2,j} h
        outs.append(ca.mtimes(ca.jacobian(L, p), R) - ca.jacobian(L, l))
    return ca.Function("seed001_blocks", [x, A], outs)


def seed001_blocks(x: np.ndarray, anchors: np.ndarray, accel_axes=AXES, gyro_axes=AXES) -> dict[str, np.ndarray]:
    """Numeric Lemma 1-4 blocks at a 19-number state for 3 anchors.

    Returns a dict ``lemma1`` (3x3), ``lemma2`` (3k x 4), ``lemma3`` (3m x 3),
    ``lemma4`` (3k x 3) with ``k``/``m`` the numbers of excited accelerometer /
    gyro axes (rows of non-excited axes are left out, as their input fields
    do not enter the words).
    """
    A = np.asarray(anchors, float).reshape(-1, 3)
    fn = _blocks_function(len(A))
    out = [np.asarray(o) for o in fn(np.asarray(x, float), A.ravel())]
    acc = [AXES.index(a) for a in accel_axes]
    gyr = [AXES.index(g) for g in gyro_axes]
    empty = lambda c: np.zeros((0, c))  # noqa: E731
    return {
        "lemma1": out[0],
        "lemma2": np.vstack([out[1 + 2 * j] for j in acc]) if acc else empty(4),
        "lemma4": np.vstack([out[2 + 2 * j] for j in acc]) if acc else empty(3),
        "lemma3": np.vstack([out[7 + j] for j in gyr]) if gyr else empty(3),
    }
