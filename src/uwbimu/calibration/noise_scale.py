"""Scale of the IMU noise model estimated from the log: variance component estimation (VCE).

Why: the IMU noise densities of ``dataset.yaml`` are measured at rest or read from a datasheet.  In
flight, vibration, scale-factor, misalignment and bias dynamics make the preintegrated IMU deltas
disagree with any smooth trajectory by far more (INRoL: the accelerometer's noise density above 15 Hz
is 6-8x its at-rest value in flight).  A graph that trusts the IMU that much cannot bend the
trajectory where the IMU is wrong; the calibration parameters bend instead (INRoL: the lever arm's
z jumped by +22 and -15 cm between windows of one log, 3 sigma each).

Method (Foerstner 1979; Koch, *Parameter Estimation and Hypothesis Testing in Linear Models*, 1999,
sec. 3.6): for a group ``g`` of whitened rows whose covariance is ``s^2`` times the modelled one, the
least-squares solution has ``E[r_g^T r_g] = s^2 rho_g`` with the group's redundancy
``rho_g = n_g - tr(J_g H^-1 J_g^T)`` (``n_g`` rows minus their leverages).  Here the group is every
row of the IMU preintegration factors (``CombinedImuFactor``: readings and bias walk) and ``s``
multiplies the whole IMU noise model, the accelerometer and gyroscope densities and the bias random
walks (``imu_noise_inflation``), so that the group's covariance is exactly ``s^2`` times the configured
one.  (Scaling the densities alone leaves the bias part of the same whitened rows at its model and the
estimate comes out low: 5.0 for a true 8 in simulation.)  The configured densities
enter as a conjugate (scaled inverse chi-square) prior worth ``nu0 = imu_noise_prior_dof`` degrees of
freedom: the fixed point ``(chi2_g(s) + nu0 / s^2) / (rho_g(s) + nu0) = 1`` (``chi2_g`` whitened at
``s``) is found in ``log s`` (Foerstner's step ``log s += log(chi2 / rho) / 2``
first, then secant steps), each point a warm-started solve, until the step is below a quarter of the
estimate's own statistical sd (``1 / sqrt(2 (rho + nu0))`` in ``log s``): the stopping rule scales with
what the log can tell, not with a fixed tolerance.  The leverages come from random probes (as the
sandwich's, :func:`uwbimu.calibration.covariance.leverages`): their sum over thousands of rows is
exact to well under that sd
(:func:`imu_variance_ratio`).

The IMU redundancy is small: the trajectory's 15 states per keyframe absorb nearly all of the IMU
rows, and only where the ranges pin the position over several keyframes do the IMU residuals show
(INRoL, 190 s: about 100 of 28 710 rows at the at-rest densities, 318 at the estimate; a 30 s
simulated flight: 5).  The prior keeps such short logs near the configured model; long logs decide
by themselves.  ``s`` measures any disagreement between the IMU and the ranges at the keyframe
scale, whatever its source: with a 15-25 cm unmodelled direction-dependent range bias in simulation it
reached 25 (1.07 with the bias modelled; docs/calibrate.md 'IMU noise scale').
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

#: Foerstner/secant steps at most; each is one warm-started solve
MAX_STEPS = 12
#: ``s`` is kept within [1 / LIMIT, LIMIT] x the configured inflation (a log with no IMU redundancy at
#: all would otherwise walk off: it is reported as not converged)
LIMIT = 1e3


def imu_rows(graph, row0: np.ndarray) -> np.ndarray:
    """Indices of the whitened rows of the IMU preintegration factors (``CombinedImuFactor``, or ``ImuFactor``)
    in ``graph``'s linear system (``row0``: first row of every factor,
    :func:`uwbimu.calibration.covariance.linear_system`)."""
    import gtsam

    out = []
    for i in range(graph.size()):
        f = graph.at(i)
        if isinstance(f, (gtsam.CombinedImuFactor, gtsam.ImuFactor)):
            out.append(np.arange(row0[i], row0[i] + f.dim()))
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def imu_variance_ratio(graph, values, n_probes: int = 128, seed: int = 0) -> tuple[float, float, int]:
    """``(chi2, redundancy, rows)`` of the IMU factors of a solved graph.

    ``chi2``: sum of their squared whitened residuals; ``redundancy``: rows minus their leverages (the part
    of the residuals the solution could not absorb).  ``chi2 / redundancy`` estimates the factor by which
    the IMU noise variances are misstated (1 when the model is right).

    The leverages of all rows sum to the number of variables ``p`` (``tr(H^-1 J^T J)``), so the IMU rows'
    sum is ``p`` minus that of the other rows (ranges, priors), estimated from random probes.  Estimated
    directly, the IMU rows' sum (thousands of leverages near 1) has a probe sd of ``sqrt(2 n_rows /
    n_probes)``, larger than the redundancy itself; the other rows' leverages are small and their sum's
    sd is about ``sqrt(2 sum / n_probes)`` (INRoL, a 48 s window: exact 16.87; 64 probes 16.3-17.5, 256 probes
    15.7-16.7 over three seeds).
    """
    from uwbimu.calibration import covariance as CV

    J, b, row0, _cols = CV.linear_system(graph, values)
    rows = imu_rows(graph, row0)
    if len(rows) == 0:
        return 0.0, 0.0, 0
    rest = np.setdiff1d(np.arange(J.shape[0]), rows)
    lu = CV._SymmetricFactor(J.T @ J)
    h_rest = CV.leverages(J, lu, J[rest], n_probes=n_probes, seed=seed)
    red = len(rows) - (J.shape[1] - float(np.sum(h_rest)))
    return float(np.sum(b[rows] ** 2)), float(red), int(len(rows))


def estimate_imu_noise_scale(pb, imf, graph, values, assoc, iters: int, solve: Callable, build_imu: Callable):
    """Solve with the IMU noise model scaled so that the IMU factors' chi2 equals their redundancy (plus prior).

    Parameters
    ----------
    pb, imf, graph, values, assoc, iters : the problem, its IMU factors and a free solution (``_solve``'s output).
    solve : ``solve(pb, imf, values, td0, assoc) -> (graph, values, assoc, iterations)``, warm-started.
    build_imu : ``build_imu(pb) -> imf``: the IMU factors with ``pb.options.imu_noise_inflation``.

    Returns
    -------
    (pb, imf, graph, values, assoc, iterations, info): the problem with the estimated inflation in its
    options and the solution under it; ``info`` (written to calibration.yaml ``imu_noise``): ``scale``
    (relative to the configured densities), ``scale_sd``, ``chi2``, ``redundancy``, ``rows``, ``steps``,
    ``converged``, ``history`` ``[(scale, chi2 / redundancy), ...]``.
    """
    from uwbimu.calibration import keys
    base = float(pb.options.imu_noise_inflation)
    nu0 = float(pb.options.imu_noise_prior_dof)
    log_s = 0.0  # relative to base
    hist = []  # (log_s, log(chi2 / redundancy))
    converged = False
    chi2 = red = 0.0
    rows = 0
    for step in range(MAX_STEPS + 1):
        chi2, red, rows = imu_variance_ratio(graph, values)
        if rows == 0 or red + nu0 <= 0.5:
            # no IMU redundancy left and no prior (without a prior a short log's estimate can walk toward 0,
            # where the IMU absorbs everything): nothing to estimate from; back to the configured model
            if log_s != 0.0:
                log_s = 0.0
                pb = dataclasses.replace(pb, options=pb.options.model_copy(update={"imu_noise_inflation": base}))
                imf = build_imu(pb)
                graph, values, assoc, iters = solve(pb, imf, values, float(values.atVector(keys.time_offset())[0]), assoc)
                chi2, red, rows = imu_variance_ratio(graph, values)
            break
        # the estimating equation with the prior: (chi2 + nu0 / s^2) / (redundancy + nu0) = 1
        f = float(np.log(max(chi2 + nu0 * np.exp(-2.0 * log_s), 1e-300) / (red + nu0)))
        hist.append((log_s, f))
        if abs(0.5 * f) < 0.25 / np.sqrt(2.0 * (red + nu0)):  # a quarter of the estimate's own sd in log s
            converged = True
            break
        if step == MAX_STEPS:
            break
        delta = 0.5 * f
        if len(hist) >= 2:
            (x0, f0), (x1, f1) = hist[-2], hist[-1]
            if x1 != x0 and (f1 - f0) / (x1 - x0) < 0:  # a decreasing ratio, as it must be: secant
                delta = -f1 * (x1 - x0) / (f1 - f0)
        log_s = float(np.clip(log_s + delta, -np.log(LIMIT), np.log(LIMIT)))
        pb = dataclasses.replace(pb, options=pb.options.model_copy(update={"imu_noise_inflation":
                                                                          base * float(np.exp(log_s))}))
        imf = build_imu(pb)
        td = float(values.atVector(keys.time_offset())[0])
        graph, values, assoc, iters = solve(pb, imf, values, td, assoc)
    scale = float(np.exp(log_s))
    info = {"method": "variance_component", "scale": scale,
            "scale_sd": (scale / float(np.sqrt(2.0 * (red + nu0))) if red + nu0 > 0.5 else None),
            "prior_dof": nu0,
            "configured_inflation": base, "chi2": chi2, "redundancy": red, "rows": rows,
            "steps": len(hist), "converged": converged,
            "history": [[round(float(np.exp(x)), 5), round(float(np.exp(v)), 5)] for x, v in hist]}
    return pb, imf, graph, values, assoc, iters, info


def scale_event(info: dict) -> dict | None:
    """Event ``imu_noise_scaled`` (severity ``info``) when the estimated scale differs from the configured
    model by more than 3 of its own sd (in ``log s``): the IMU factors disagree with the ranges at the
    keyframe scale more (or less) than the stated noise allows.  None otherwise."""
    sd = info.get("scale_sd")
    s = info.get("scale", 1.0)
    if not sd or not info.get("converged") or abs(np.log(s)) <= 3.0 * sd / s:
        return None
    return {"kind": "imu_noise_scaled", "severity": "info", "scale": float(s), "scale_sd": float(sd),
            "message": f"the IMU noise model was scaled by {s:.3g} +/- {sd:.2g} (estimated from the IMU factors' "
                       "residuals): in flight, vibration and IMU errors exceed at-rest densities, or the range "
                       "model leaves errors the IMU cannot follow; see docs/calibrate.md 'IMU noise scale'"}
