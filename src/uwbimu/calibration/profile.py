"""Time-offset profile likelihood and its verdict (identified / not identified).

Each grid point ``t_d = g`` is a warm-started solve of the graph with t_d
fixed; its profile value is ``chi2(g) = 2 E(g) + ((g - mu) / sd)^2`` (``E``:
the robust graph cost, the second term the t_d prior, so the profile is the
negative log-posterior in chi-square units).  The verdict is read in those
units, independent of the grid and of the log's length:

* the *confidence set* is the grid points with ``chi2 - min < c``
  (``c = 9``: 3 sigma for one parameter);
* ``at_grid_edge``: the minimum is the first or last grid point;
* ``flat``: the confidence set reaches a grid edge;
* ``multi_modal``: the confidence set is not one run of consecutive points;
* ``not_curved``: the local parabola about the minimum does not open upwards;
* otherwise ``identified``, with ``sigma_curvature = 1 / sqrt(a)`` from
  ``chi2 ~ a (t - t*)^2 + b``, fitted on the minimum and its neighbours.

After an ``identified`` profile the free solve starts at the parabola vertex; a
free optimum outside the profile's confidence interval (:func:`confidence_interval`)
turns the verdict into ``refinement_left_confidence_set``.

A grid-edge value is never reported as found: every verdict but
``identified`` holds t_d at its prior, and :func:`motion_advice` tells the user
what would help (a wider grid for ``at_grid_edge``, other motion otherwise).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class TdProfile:
    grid: np.ndarray  # t_d values [s]
    chi2: np.ndarray  # profile values (chi-square units)
    iterations: np.ndarray
    verdict: str
    best: float  # grid point of the minimum [s]
    vertex: float  # parabola vertex about the minimum [s] (nan unless identified)
    sigma_curvature: float  # [s] (nan unless identified)
    confidence_chi2: float

    @property
    def identified(self) -> bool:
        return self.verdict == "identified"

    def frame(self):
        import pandas as pd

        return pd.DataFrame({"time_offset": self.grid, "chi2": self.chi2, "delta_chi2": self.chi2 - self.chi2.min(),
                             "iterations": self.iterations})


def profile_verdict(grid: np.ndarray, chi2: np.ndarray, confidence_chi2: float = 9.0, chi2_scale: float = 1.0):
    """Verdict, best grid point, parabola vertex and curvature sigma of a profile (see module doc).

    ``chi2_scale`` multiplies the profile first (honesty correction: model / sandwich variance of t_d,
    docs/calibrate.md "Honest sigma"); 1 reads the white-noise likelihood as is.
    """
    grid = np.asarray(grid, float)
    chi2 = chi2_scale * np.asarray(chi2, float)
    nan = float("nan")
    if not np.all(np.isfinite(chi2)):
        return "failed_points", float(grid[int(np.nanargmin(chi2))]) if np.isfinite(chi2).any() else nan, nan, nan
    i = int(np.argmin(chi2))
    if i in (0, len(grid) - 1):
        return "at_grid_edge", float(grid[i]), nan, nan
    inside = np.flatnonzero(chi2 - chi2[i] < confidence_chi2)
    if inside[0] == 0 or inside[-1] == len(grid) - 1:
        return "flat", float(grid[i]), nan, nan
    if np.any(np.diff(inside) != 1):
        return "multi_modal", float(grid[i]), nan, nan
    lo, hi = max(0, i - 2), min(len(grid), i + 3)
    lo, hi = min(lo, inside[0]), max(hi, inside[-1] + 1)
    a, b, _c = np.polyfit(grid[lo:hi] - grid[i], chi2[lo:hi], 2)
    if not a > 0:
        return "not_curved", float(grid[i]), nan, nan
    vertex = float(grid[i] - b / (2 * a))
    return "identified", float(grid[i]), vertex, float(1.0 / np.sqrt(a))


def confidence_interval(grid: np.ndarray, chi2: np.ndarray, confidence_chi2: float,
                        chi2_scale: float = 1.0) -> tuple[float, float]:
    """Ends [s] of the profile's confidence set (grid points with ``chi2_scale * (chi2 - min) <
    confidence_chi2``), widened to the linear-interpolation crossings of the threshold with the
    neighbouring points."""
    grid = np.asarray(grid, float)
    d = chi2_scale * (np.asarray(chi2, float) - np.nanmin(chi2))
    inside = np.flatnonzero(d < confidence_chi2)
    lo_i, hi_i = int(inside[0]), int(inside[-1])

    def cross(i_in: int, i_out: int) -> float:
        if i_out < 0 or i_out >= len(grid) or not np.isfinite(d[i_out]):
            return float(grid[i_in])
        f = (confidence_chi2 - d[i_in]) / (d[i_out] - d[i_in])
        return float(grid[i_in] + f * (grid[i_out] - grid[i_in]))

    return cross(lo_i, lo_i - 1), cross(hi_i, hi_i + 1)


def motion_advice(eskf, verdict: str = "flat", grid: np.ndarray | None = None) -> str:
    """What would make t_d identifiable, by verdict, with the ESKF trajectory's excitation.

    A range's sensitivity to t_d is ``n . (v + R (w x p_IU))``: the antenna's
    radial velocity; t_d is seen when that velocity *changes* (a constant
    velocity shift is indistinguishable from a position shift).  ``at_grid_edge``
    is a grid problem first (the minimum may lie outside it); ``multi_modal``
    is typical of periodic motion (a t_d shifted by a period fits as well).
    """
    st = eskf.states
    t = eskf.t
    acc = np.gradient(st[:, 3:6], t, axis=0)
    rms_speed = float(np.sqrt(np.mean(np.sum(st[:, 3:6] ** 2, axis=1))))
    rms_acc = float(np.sqrt(np.mean(np.sum(acc**2, axis=1))))
    motion = (f"the log's antenna motion (RMS speed {rms_speed:.2f} m/s, RMS acceleration {rms_acc:.2f} m/s^2) "
              "does not pin t_d: fly back-and-forth or circles of ~1 m at 0.5-1 Hz (accelerations of a few "
              "m/s^2 towards and away from the anchors) and rotate about all axes; hovering or constant velocity "
              "leaves t_d unobservable")
    if verdict == "at_grid_edge":
        span = "" if grid is None else f" [{1000 * grid[0]:.0f}, {1000 * grid[-1]:.0f}] ms"
        return (f"the profile's minimum is at an end of the grid{span}: the offset may lie outside it; widen "
                "td_profile.half_width or move time_offset_prior towards that end and rerun (if the minimum "
                "stays at the edge, " + motion + ")")
    if verdict == "multi_modal":
        return ("the profile has several separated minima within the confidence set (typical of periodic "
                "motion: t_d shifted by about a period fits as well); add non-periodic motion with varied "
                "speeds, or narrow time_offset_prior_sd with independent knowledge; " + motion)
    if verdict == "refinement_left_confidence_set":
        return ("the free solve started at the profile's minimum moved outside the profile's confidence set "
                "(the likelihood is not locally quadratic); " + motion)
    return motion
