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

A grid-edge value is never reported as found: every verdict but
``identified`` holds t_d at its prior.
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


def profile_verdict(grid: np.ndarray, chi2: np.ndarray, confidence_chi2: float = 9.0):
    """Verdict, best grid point, parabola vertex and curvature sigma of a profile (see module doc)."""
    grid = np.asarray(grid, float)
    chi2 = np.asarray(chi2, float)
    i = int(np.argmin(chi2))
    nan = float("nan")
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


def motion_advice(eskf) -> str:
    """Which motion would make t_d visible, from the ESKF trajectory's excitation.

    A range's sensitivity to t_d is ``n . (v + R (w x p_IU))``: the antenna's
    radial velocity; t_d is seen when that velocity *changes* (a constant
    velocity shift is indistinguishable from a position shift).
    """
    st = eskf.states
    t = eskf.t
    acc = np.gradient(st[:, 3:6], t, axis=0)
    rms_speed = float(np.sqrt(np.mean(np.sum(st[:, 3:6] ** 2, axis=1))))
    rms_acc = float(np.sqrt(np.mean(np.sum(acc**2, axis=1))))
    return (f"the log's antenna motion is weak for t_d (RMS speed {rms_speed:.2f} m/s, RMS acceleration "
            f"{rms_acc:.2f} m/s^2): fly back-and-forth or circles of ~1 m at 0.5-1 Hz (accelerations of a few "
            "m/s^2 towards and away from the anchors) and rotate about all axes; hovering or constant velocity "
            "leaves t_d unobservable")
