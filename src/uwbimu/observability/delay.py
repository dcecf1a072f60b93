"""Local identifiability of the time offset ``t_d`` (seed 001, Theorem 1).

Theorem 1: ``t_d`` is locally identifiable from a range if

* (T1) the mobile radio is not co-located with the anchor, and either
* (T2) at least one of ``a_x, a_y, a_z`` is excited, or
* (T3) the radio is not co-located with the IMU (``p_IU != 0``) and all three
  of ``w_x, w_y, w_z`` are excited.

These are *sufficient* conditions.  The criterion they derive from (eq. 12) is
that the delayed input appears in the output: ``d h(x(t_r)) / d u(t_r - t_d)
!= 0``.  :func:`delay_verdict` checks it numerically with the reference model:
the state at the IMU stamp ``t_I = t_r - t_d`` is propagated for ``t_d`` with
:func:`uwbimu.models.reference.propagate` under the IMU reading ``u`` and the
range :func:`uwbimu.models.reference.range_measurement` is differentiated with
respect to each *excited* input channel by central differences.
"""

from __future__ import annotations

import time
from typing import Any, Union

import numpy as np

from uwbimu.models import reference as ref
from uwbimu.observability.config import ObservabilityConfig, load_config
from uwbimu.observability.structural import evaluation_points

#: |dh/du| below this [m per (m/s^2) or m per (rad/s)] counts as zero; central
#: differences with step ``_STEP`` leave ~1e-12 of rounding noise for ranges of
#: ~10 m, while the smallest genuine sensitivities of interest (t_d = 1 ms,
#: lever arm 1 cm: t_d |p_IU| = 1e-5) are far above.
SENSITIVITY_TOL = 1e-9
_STEP = 1e-3
_AXES = ("x", "y", "z")


def theorem1_conditions(x20: np.ndarray, anchors: np.ndarray, accel_axes, gyro_axes, tol: float = 1e-9) -> dict[str, bool]:
    """Evaluate T1-T3 at a 20-number state for a set of anchors."""
    tag = ref.antenna_position(x20)
    d = np.linalg.norm(np.asarray(anchors, float) - tag, axis=1)
    t1 = bool(np.any(d > tol))
    t2 = len(accel_axes) > 0
    t3 = bool(np.linalg.norm(x20[16:19]) > tol) and len(gyro_axes) == 3
    return {"T1": t1, "T2": t2, "T3": t3}


def delayed_input_sensitivity(x20: np.ndarray, u: np.ndarray, anchors: np.ndarray, t_d: float) -> np.ndarray:
    """``d range_i / d u_j`` of the input applied at ``t_r - t_d`` (reference model).

    Parameters
    ----------
    x20 : (20,) state at the IMU stamp ``t_I = t_r - t_d``.
    u : (6,) IMU reading ``[a_m, w_m]`` held over ``[t_I, t_r]``.
    anchors : (N, 3) anchor positions [m].
    t_d : time offset [s].

    Returns
    -------
    (N, 6) sensitivities [m per unit input].
    """
    A = np.asarray(anchors, float)

    def ranges(uu):
        xr = ref.propagate(x20, uu, uu, t_d)
        return np.array([ref.range_measurement(xr, a) for a in A])

    out = np.empty((len(A), 6))
    for j in range(6):
        du = np.zeros(6)
        du[j] = _STEP
        out[:, j] = (ranges(u + du) - ranges(u - du)) / (2 * _STEP)
    return out


def delay_verdict(config: Union[str, dict, ObservabilityConfig]) -> dict[str, Any]:
    """Time-offset identifiability of a configuration (the ``delay`` verb).

    Returns
    -------
    dict with ``identifiable`` (Theorem 1 holds at every point, or the numeric
    input-output sensitivity of eq. 12 is non-zero for an excited channel),
    ``conditions`` ``{T1, T2, T3}`` (at the weakest point), ``theorem1``
    (T1 and (T2 or T3)), ``numeric`` (max |dh/du| per excited channel, the
    tolerance and whether it is non-zero), ``basis`` (which argument decided),
    ``agree`` (theorem and numeric check agree) and ``points``.
    """
    t0 = time.perf_counter()
    cfg = load_config(config)
    if cfg.model != "uwb_imu":
        raise ValueError("the delay analysis needs model: uwb_imu (the point mass has no time offset)")
    A = np.asarray(cfg.anchors, float)
    acc, gyr = cfg.accel_axes(), cfg.gyro_axes()
    excited = [_AXES.index(a) for a in acc] + [3 + _AXES.index(g) for g in gyr]
    chan = [f"a{a}" for a in _AXES] + [f"w{a}" for a in _AXES]
    points = []
    for x19, p in evaluation_points(cfg):
        x20 = np.r_[x19, cfg.time_offset]
        u = p[3 * len(A) :]
        conds = theorem1_conditions(x20, A, acc, gyr)
        thm = conds["T1"] and (conds["T2"] or conds["T3"])
        sens = delayed_input_sensitivity(x20, u, A, cfg.time_offset)
        per_chan = {chan[j]: float(np.abs(sens[:, j]).max()) for j in excited}
        nonzero = any(v > SENSITIVITY_TOL for v in per_chan.values())
        points.append({"conditions": conds, "theorem1": thm, "sensitivity": per_chan, "numeric_nonzero": nonzero})
    # weakest point: theorem fails first, then smallest sensitivity
    iw = min(
        range(len(points)),
        key=lambda i: (points[i]["theorem1"], points[i]["numeric_nonzero"], max(points[i]["sensitivity"].values(), default=0.0)),
    )
    w = points[iw]
    thm_all = all(pt["theorem1"] for pt in points)
    num_all = all(pt["numeric_nonzero"] for pt in points)
    identifiable = all(pt["theorem1"] or pt["numeric_nonzero"] for pt in points)
    basis = "Theorem 1" if thm_all else ("input-output sensitivity (eq. 12, k=0)" if num_all else "none")
    return {
        "name": cfg.name,
        "identifiable": bool(identifiable),
        "conditions": w["conditions"],
        "theorem1": bool(thm_all),
        "numeric": {
            "sensitivity": w["sensitivity"],
            "tolerance": SENSITIVITY_TOL,
            "nonzero": bool(num_all),
            "time_offset": cfg.time_offset,
        },
        "basis": basis,
        "agree": bool(thm_all == num_all),
        "n_points": len(points),
        "weakest_point": iw,
        "points": points,
        "elapsed_s": time.perf_counter() - t0,
    }
