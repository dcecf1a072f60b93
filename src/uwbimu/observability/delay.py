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

import os
import time
from typing import Union

import numpy as np

from uwbimu.models import state as ST
from uwbimu.models import reference as ref
from uwbimu.observability.config import ObservabilityConfig, load_config
from uwbimu.observability.verdicts import DelayVerdict
from uwbimu.observability.structural import evaluation_points

#: Legacy absolute cut-off [m per unit input] (no longer used for the verdict;
#: kept for callers that imported it).
SENSITIVITY_TOL = 1e-9
_STEP = 1e-3

#: Time offsets [s] at which the delayed-input sensitivity is probed.  The
#: sensitivity is an analytic function of t_d, so it is non-zero for generic
#: t_d as soon as it is non-zero at one of them: the verdict does not depend
#: on the configured ``time_offset`` (which only sets the reported magnitude).
PROBE_TIME_OFFSETS = (1e-3, 1e-2, 1e-1)

#: A sensitivity counts as non-zero when it exceeds this multiple of the
#: rounding noise of the central difference, ``eps * r / step`` with ``r``
#: the output's own scale (the largest range at the point).
NOISE_MULTIPLE = 1e3
_AXES = ("x", "y", "z")


def _sight_rows(x20: np.ndarray, anchors: np.ndarray, measurement: str = "range") -> np.ndarray:
    """Rows ``c`` with ``d h / d p_U = -c``: unit lines of sight ``e_i`` (ranges) or
    their differences ``e_i - e_0`` (TDoA ``r_i - r_0``)."""
    tag = ref.antenna_position(x20)
    E = np.asarray(anchors, float) - tag
    E = E / np.maximum(np.linalg.norm(E, axis=1, keepdims=True), 1e-300)
    return E[1:] - E[0] if measurement == "tdoa" else E


def measurements(x20: np.ndarray, anchors: np.ndarray, measurement: str = "range") -> np.ndarray:
    """Ranges to every anchor, or the TDoA ``r_i - r_0`` (i = 1..N-1) [m]."""
    r = np.array([ref.range_measurement(x20, a) for a in np.asarray(anchors, float)])
    return r[1:] - r[0] if measurement == "tdoa" else r


def theorem1_conditions(x20: np.ndarray, anchors: np.ndarray, accel_axes, gyro_axes, tol: float = 1e-9,
                        measurement: str = "range") -> dict[str, bool]:
    """Evaluate T1-T3 at a 20-number state for a set of anchors.

    T1 for ranges: the antenna is not at an anchor.  Its TDoA analogue (T1'):
    some pair's difference has a non-zero gradient, ``e_b != e_a`` — the antenna
    is not on the axis of every pair's hyperboloids (the line through the two
    anchors, outside the segment between them).  T2, T3 are unchanged.
    """
    tag = ref.antenna_position(x20)
    if measurement == "tdoa":
        A = np.asarray(anchors, float)
        E = (A - tag) / np.maximum(np.linalg.norm(A - tag, axis=1, keepdims=True), 1e-300)
        t1 = bool(any(np.linalg.norm(E[j] - E[i]) > tol for i in range(len(A)) for j in range(i + 1, len(A))))
    else:
        d = np.linalg.norm(np.asarray(anchors, float) - tag, axis=1)
        t1 = bool(np.any(d > tol))
    t2 = len(accel_axes) > 0
    t3 = bool(np.linalg.norm(x20[ST.PIU]) > tol) and len(gyro_axes) == 3
    return {"T1": t1, "T2": t2, "T3": t3}


def delayed_input_sensitivity(x20: np.ndarray, u: np.ndarray, anchors: np.ndarray, t_d: float,
                              measurement: str = "range") -> np.ndarray:
    """``d range_i / d u_j`` of the input applied at ``t_r - t_d`` (reference model).

    Parameters
    ----------
    x20 : (20,) state at the IMU stamp ``t_I = t_r - t_d``.
    u : (6,) IMU reading ``[a_m, w_m]`` held over ``[t_I, t_r]``.
    anchors : (N, 3) anchor positions [m].
    t_d : time offset [s].

    measurement : ``range`` or ``tdoa`` (rows ``r_i - r_0``).

    Returns
    -------
    (N, 6) (ranges) or (N-1, 6) (TDoA) sensitivities [m per unit input].
    """
    A = np.asarray(anchors, float)

    def ranges(uu):
        return measurements(ref.propagate(x20, uu, uu, t_d), A, measurement)

    out = np.empty((len(A) - 1 if measurement == "tdoa" else len(A), 6))
    for j in range(6):
        du = np.zeros(6)
        du[j] = _STEP
        out[:, j] = (ranges(u + du) - ranges(u - du)) / (2 * _STEP)
    return out


def _noise(x20: np.ndarray, anchors: np.ndarray) -> float:
    """Rounding noise [m per unit input] of the central difference at this point
    (the ranges' own scale; a TDoA is a difference of two of them)."""
    r = max(1.0, max(ref.range_measurement(x20, a) for a in anchors))
    return NOISE_MULTIPLE * np.finfo(float).eps * r / _STEP


def first_order_criterion(x20: np.ndarray, anchors: np.ndarray, accel_axes, gyro_axes,
                          measurement: str = "range") -> dict[str, float]:
    """The seed's first-order terms of eq. (13)-(16) at a point (dimensionless).

    ``accel``: ``max |e_i^T R e_j|`` over anchors ``i`` and excited accelerometer
    axes ``j`` (the range changes by ``e^T R da t_d^2 / 2``); ``gyro``:
    ``max |e_i^T R [e_j]x p_IU| / |p_IU|`` over excited gyro axes.  ``e_i`` is
    the unit line of sight from the antenna to anchor ``i``.  Either can vanish
    *pointwise* although T2 / T3 hold: an excited accelerometer axis
    perpendicular to every line of sight, or every anchor on the IMU-antenna
    line (``e_i`` parallel to ``R p_IU``).  The delayed input then still enters
    at higher order in ``t_d`` and as soon as the line of sight turns along the
    trajectory: Theorem 1's argument, evaluated at one point, does not see it.
    For TDoA ``e_i`` is replaced by ``e_i - e_0`` (see :func:`_sight_rows`).
    """
    R = ref.rotation_matrix(x20[ST.Q])
    E = _sight_rows(x20, anchors, measurement)
    lever = x20[ST.PIU]
    out = {"accel": 0.0, "gyro": 0.0}
    for a in accel_axes:
        out["accel"] = max(out["accel"], float(np.abs(E @ R[:, _AXES.index(a)]).max()))
    nl = np.linalg.norm(lever)
    for g in gyro_axes:
        if nl > 0:
            c = R @ np.cross(np.eye(3)[_AXES.index(g)], lever) / nl
            out["gyro"] = max(out["gyro"], float(np.abs(E @ c).max()))
    return out


def delay_verdict(config: Union[str, dict, ObservabilityConfig]) -> DelayVerdict:
    """Time-offset identifiability of a configuration (the ``delay`` verb).

    The numeric criterion (seed eq. 12: the delayed input appears in the range)
    is evaluated at the probe offsets :data:`PROBE_TIME_OFFSETS` and judged
    against the rounding noise of the output's own scale, so the verdict does
    not change with the configured ``time_offset``; the sensitivity at that
    offset and its leading power in ``t_d`` are reported as the magnitude.

    Returns
    -------
    dict with ``identifiable`` (Theorem 1 holds at every point, or the numeric
    input-output sensitivity is non-zero for an excited channel at every point),
    ``conditions`` ``{T1, T2, T3}`` (at the weakest point), ``theorem1``
    (T1 and (T2 or T3)), ``numeric`` (``sensitivity``: max |dh/du| per excited
    channel at ``time_offset``; ``probe``: the largest over the probe offsets
    relative to the noise; ``tolerance``: the noise level [m per unit input];
    ``nonzero``; ``td_power``: leading power of ``t_d`` in the sensitivity),
    ``first_order`` (the seed's pointwise criterion, see
    :func:`first_order_criterion`), ``explanation`` (why the theorem and the
    numeric check differ, or ``""``), ``basis``, ``agree`` and ``points``.
    """
    t0 = time.perf_counter()
    cfg = load_config(config)
    if cfg.model != "uwb_imu":
        from uwbimu.errors import ConfigError

        where = str(config) if isinstance(config, (str, os.PathLike)) else cfg.name
        raise ConfigError(f"{where}: field 'model': the delay analysis needs model: uwb_imu "
                          "(the point mass has no time offset)")
    A = np.asarray(cfg.anchors, float)
    acc, gyr = cfg.accel_axes(), cfg.gyro_axes()
    excited = [_AXES.index(a) for a in acc] + [3 + _AXES.index(g) for g in gyr]
    chan = [f"a{a}" for a in _AXES] + [f"w{a}" for a in _AXES]
    points = []
    for x19, p in evaluation_points(cfg):
        x20 = np.r_[x19, cfg.time_offset]
        u = p[3 * len(A) :]
        conds = theorem1_conditions(x20, A, acc, gyr, measurement=cfg.measurement)
        thm = conds["T1"] and (conds["T2"] or conds["T3"])
        sens = delayed_input_sensitivity(x20, u, A, cfg.time_offset, cfg.measurement)
        per_chan = {chan[j]: float(np.abs(sens[:, j]).max()) for j in excited}
        noise = _noise(x20, A)
        probe = []
        for td in PROBE_TIME_OFFSETS:
            s_td = delayed_input_sensitivity(np.r_[x19, td], u, A, td, cfg.measurement)
            probe.append(max((float(np.abs(s_td[:, j]).max()) for j in excited), default=0.0))
        nonzero = max(probe, default=0.0) > noise
        power = None  # slope of log |dh/du| vs log t_d over the smallest pair of probes above the noise
        for i in range(len(probe) - 1):
            if probe[i] > noise and probe[i + 1] > noise:
                T = PROBE_TIME_OFFSETS
                power = round(float(np.log10(probe[i + 1] / probe[i]) / np.log10(T[i + 1] / T[i])), 1)
                break
        first = first_order_criterion(x20, A, acc, gyr, cfg.measurement)
        points.append({"conditions": conds, "theorem1": thm, "sensitivity": per_chan, "numeric_nonzero": bool(nonzero),
                       "probe_over_noise": max(probe, default=0.0) / noise, "noise": noise, "td_power": power,
                       "first_order": first})  # fmt: skip
    # weakest point: theorem fails first, then smallest sensitivity
    iw = min(
        range(len(points)),
        key=lambda i: (points[i]["theorem1"], points[i]["numeric_nonzero"], points[i]["probe_over_noise"]),
    )
    w = points[iw]
    thm_all = all(pt["theorem1"] for pt in points)
    num_all = all(pt["numeric_nonzero"] for pt in points)
    identifiable = all(pt["theorem1"] or pt["numeric_nonzero"] for pt in points)
    basis = "Theorem 1" if thm_all else ("input-output sensitivity (eq. 12, k=0)" if num_all else "none")
    return DelayVerdict.from_dict({
        "name": cfg.name,
        "measurement": cfg.measurement,
        "identifiable": bool(identifiable),
        "conditions": w["conditions"],
        "theorem1": bool(thm_all),
        "numeric": {
            "sensitivity": w["sensitivity"],
            "tolerance": w["noise"],
            "probe_over_noise": w["probe_over_noise"],
            "probe_time_offsets": list(PROBE_TIME_OFFSETS),
            "td_power": w["td_power"],
            "nonzero": bool(num_all),
            "time_offset": cfg.time_offset,
        },
        "first_order": w["first_order"],
        "explanation": _explain(w, acc, gyr),
        "basis": basis,
        "agree": bool(thm_all == num_all),
        "n_points": len(points),
        "weakest_point": iw,
        "points": points,
        "elapsed_s": time.perf_counter() - t0,
    })


def _explain(pt: dict, acc, gyr) -> str:
    """Why Theorem 1 and the numeric check (or the seed's pointwise criterion) differ."""
    c, f = pt["conditions"], pt["first_order"]
    notes = []
    if not c["T1"]:
        notes.append("the antenna is at an anchor (ranges) / on the axis of every anchor pair's hyperboloids (TDoA: "
                     "the difference is constant there, its gradient zero) at this point")  # fmt: skip
    elif c["T2"] and f["accel"] < 1e-6:
        notes.append("the excited accelerometer axes are perpendicular to every line of sight (TDoA: every difference "
                     "of lines of sight) at this point, so the seed's first-order criterion (eq. 13) vanishes here")  # fmt: skip
    if c["T1"] and c["T3"] and f["gyro"] < 1e-6 and not (c["T2"] and f["accel"] >= 1e-6):
        notes.append("every line of sight (TDoA: every difference of lines of sight) is parallel to the IMU-antenna "
                     "line at this point, so the gyro term of eq. (13) vanishes here")  # fmt: skip
    if not pt["theorem1"] and pt["numeric_nonzero"]:
        p = pt["td_power"]
        notes.append("Theorem 1's sufficient conditions fail, but the delayed input still enters the range"
                     + (f" (sensitivity ~ t_d^{p:g})" if p is not None else ""))  # fmt: skip
    if notes and pt["numeric_nonzero"]:
        notes.append("t_d is identifiable: the exact input-output sensitivity is non-zero (higher order in t_d, and "
                     "the line of sight turns along any trajectory)")  # fmt: skip
    return "; ".join(notes)
