"""The Huber threshold of the range and TDoA factors, chosen from the log (``huber_k: adaptive``).

A fixed threshold is a statement about the error distribution: Huber's 1.345 sigma costs 5 % of the
variance on Gaussian errors and is far from the best threshold on real UWB errors, whose scale and tails
differ from the configured ``range_sigma``.  For a regression M-estimator with symmetric errors the
parameters' asymptotic covariance is ``V(k) (J^T J)^-1`` with

    V(k) = E[psi_k(z)^2] / E[psi_k'(z)]^2,   psi_k(z) = clip(z, -k, k),

``z`` the whitened residual (Huber 1964; the adaptive M-estimator of Hogg 1974 picks ``k`` by minimising
its estimate).  :func:`select_huber_k` evaluates ``V`` on the whitened residuals of a first solve (made
with :data:`HUBER_START`) over a grid of thresholds scaled by their robust scale, and returns the largest
threshold within one standard error of the minimum: on Gaussian residuals ``V`` falls towards 1 as ``k``
grows and the choice is (near) least squares, on heavy-tailed ones it is finite.  :func:`adapt_huber`
re-solves with it, warm-started.

Assumed (stated in docs/calibrate.md): the rows' errors are independent for the purpose of the choice
(their correlation in time scales the covariance of every threshold alike only approximately) and the first
solve's residuals stand for the errors (one adaptive step, not iterated).
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from uwbimu.calibration import keys
from uwbimu.calibration.graph import range_residuals
from uwbimu.calibration.options import HUBER_START  # noqa: F401  (the first solve's threshold; re-exported)

#: candidate thresholds in units of the residuals' robust scale (1.4826 MAD), 5 % apart: from half of it to
#: effectively least squares (at 10 robust sigma no Gaussian row is down-weighted).  Below half, V rests on the
#: residuals' density at zero, which the fit itself inflates: on a simulated 15 s flight 20.5 % of the fitted
#: residuals lie within 0.2 sigma against 16.6 % of the noise draws, and thresholds there won on white noise.
GRID_FACTORS = np.geomspace(0.5, 10.0, 62)


def row_sigma(pb, assoc) -> np.ndarray:
    """Noise sd [m] of every row in ``assoc.used``: ``range_sigma``, ``tdoa_sigma`` for TDoA rows."""
    sig = np.full(len(assoc.used), pb.range_sigma)
    if pb.anchor_b is not None:
        sig[pb.anchor_b[assoc.used] >= 0] = pb.tdoa_sigma
    return sig


def whitened_residuals(pb, graph, assoc, values, td: float | None = None) -> np.ndarray:
    """``z = residual / sigma`` of the range and TDoA rows of ``graph`` at ``values`` (assoc.used order);
    ``td`` [s] the time offset when ``values`` has none (a t_d-fixed graph), else read from ``values``."""
    if td is None:
        td = float(values.atVector(keys.time_offset())[0])
    return range_residuals(graph, assoc, values, td) / row_sigma(pb, assoc)


def variance_factor(z: np.ndarray, k: float) -> float:
    """``V(k) = mean(psi_k(z)^2) / mean(|z| <= k)^2``: the Huber M-estimator's asymptotic variance factor
    estimated on ``z`` (1 for least squares on unit-variance Gaussian rows); inf when no row is inside."""
    return _variance_and_influence(np.asarray(z, float), float(k))[0]


def _variance_and_influence(z: np.ndarray, k: float) -> tuple[float, np.ndarray]:
    """``V(k)`` and each row's influence on it (delta method: the estimate's sampling error is the mean of
    the influences), a float and an (n,) array (zeros when no row is inside)."""
    psi2 = np.minimum(z**2, k * k)
    inside = (np.abs(z) <= k).astype(float)
    a, b = float(psi2.mean()), float(inside.mean())
    if b <= 0.0:
        return float("inf"), np.zeros_like(z)
    return a / b**2, (psi2 - a) / b**2 - 2.0 * a * (inside - b) / b**3


def select_huber_k(z: np.ndarray) -> dict:
    """The threshold chosen on the whitened residuals ``z``: the largest of those whose estimated ``V`` is
    within one standard error of the smallest.

    The minimiser of the estimated ``V`` alone is noisy on a short log (the curve is flat near its minimum,
    750 Gaussian rows put it below 1.345 one time in 15), so the choice leans towards least squares, the
    efficient loss when the errors are as modelled, by no more than the estimate's own sampling error (the
    "one standard error rule"; the error of ``V(k) - V(k_min)`` from the rows' influences).  Memory O(n).

    Returns
    -------
    dict ``k`` (chosen, in sigmas of the configured noise), ``k_min`` (minimiser of the estimate),
    ``robust_scale`` (1.4826 MAD of ``z``), ``grid`` and ``variance_factor`` (V on the grid),
    ``variance_vs_start`` and ``variance_vs_least_squares`` (V at ``k`` over V at :data:`HUBER_START` and over
    ``mean(z^2)``: the variance the choice saves), ``rows``.
    """
    z = np.asarray(z, float)
    z = z[np.isfinite(z)]
    if len(z) == 0:
        from uwbimu.errors import EstimationError

        raise EstimationError("adaptive Huber threshold: the solve left no finite range residual")
    s = 1.4826 * float(np.median(np.abs(z)))
    if not s > 0.0:  # more than half the rows fitted exactly: scale from the mean square instead
        s = float(np.sqrt(np.mean(z**2))) or 1.0
    grid = s * GRID_FACTORS
    v = np.array([variance_factor(z, k) for k in grid])
    i_min = int(np.argmin(v))
    infl_min = _variance_and_influence(z, float(grid[i_min]))[1]
    se = np.array([(_variance_and_influence(z, float(k))[1] - infl_min).std() for k in grid]) / np.sqrt(len(z))
    i = int(np.flatnonzero(v <= v[i_min] + se).max())
    v_ls = float(np.mean(z**2))
    return {"k": float(grid[i]), "k_min": float(grid[i_min]), "start_k": HUBER_START, "robust_scale": s,
            "rows": int(len(z)), "grid": [float(x) for x in grid], "variance_factor": [float(x) for x in v],
            "variance_vs_start": float(v[i] / variance_factor(z, HUBER_START)),
            "variance_vs_least_squares": float(v[i] / v_ls) if v_ls > 0 else 1.0}


def adapt_huber(built, solved, solve: Callable):
    """Choose ``huber_k`` on the residuals of a solution and re-solve with it (stage ``adaptive Huber``).

    Parameters
    ----------
    built : :class:`uwbimu.calibration.stages.Built`, its problem's ``options.huber_k`` a number (the first
        solve's).
    solved : :class:`uwbimu.calibration.stages.Solved`, that solve (t_d free).
    solve : ``solve(pb, imf, values, td0, assoc) -> Solved``, warm-started.

    Returns
    -------
    (built, solved, info): the problem with the chosen threshold in its options, the solution under it, and
    :func:`select_huber_k`'s dict (calibration.yaml ``range_model.huber``) with ``selection: adaptive``.
    """
    pb = built.problem
    info = select_huber_k(whitened_residuals(pb, solved.graph, solved.assoc, solved.values)) | {"selection": "adaptive"}
    pb = dataclasses.replace(pb, options=pb.options.model_copy(update={"huber_k": info["k"]}))
    built = dataclasses.replace(built, problem=pb)
    return built, solve(pb, built.imu_factors, solved.values, solved.time_offset(), solved.assoc), info
