"""The batch calibrator's stages and what each hands to the next (typed records instead of tuples).

:func:`uwbimu.calibration.calibrate` runs, in order::

    Start      the part of the log calibrated, in the graph frame, and the ESKF that seeds the graph (or, when
               that run fails the health check, a robust multilateration: calibration/start_check.py)
    Built      the problem (everything that does not depend on t_d) and its IMU factors
    Solved     a solve: factor graph, solution, range association, iterations (free solve, second start,
               range model chosen on that solve, adaptive Huber, IMU noise scale: each stage returns a new Solved)
    Profiled   the t_d profile and the solve that follows its verdict (free, refined, or held at the prior)

and reports from the last :class:`Profiled` (:func:`uwbimu.calibration.batch._report`).  Each record is frozen:
a stage returns a new one and never changes the one it was given.  Progress is reported per stage through
:class:`StageProgress` (the library prints nothing; ``uwbimu calibrate`` renders it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional

from uwbimu.calibration import keys

__all__ = ["Start", "Built", "Solved", "Profiled", "StageProgress", "STAGES"]

#: The stages reported to the ``on_stage`` callback, in order (those that do not apply are reported skipped).
STAGES = ("initialising ESKF", "factor graph", "free solve", "second start", "range model", "adaptive Huber",
          "IMU noise scale", "t_d profile", "final solve", "marginals and report")


@dataclass(frozen=True)
class StageProgress:
    """One progress report of :func:`uwbimu.calibration.calibrate` (the ``on_stage`` callback's argument).

    Attributes
    ----------
    stage : a name of :data:`STAGES`.
    index : its position in :data:`STAGES` (0-based); ``total`` = ``len(STAGES)``.
    status : ``started``, ``done``, ``skipped`` or ``point`` (one t_d profile point solved).
    done, total_points : profile points solved so far and planned so far (``point`` reports; the zoom may add
        points, so ``total_points`` can grow).
    fraction : overall completed fraction in [0, 1] (what the plain ``progress`` callback receives).
    """

    stage: str
    index: int
    status: str
    fraction: float
    done: Optional[int] = None
    total_points: Optional[int] = None

    @property
    def total(self) -> int:
        return len(STAGES)


@dataclass(frozen=True)
class Start:
    """Stage 1: the log to calibrate and the ESKF that seeds the graph.

    Attributes
    ----------
    dataset : the calibrated part of the log (flight segment, start/end), in the graph frame.
    eskf : the initialising ESKF result (graph frame).
    eskf_options : the options it ran with.
    setup : :class:`uwbimu.calibration.anchors.AnchorSetup` (which anchors are estimated, gauge).
    frame : what :func:`uwbimu.calibration.frames.from_graph_frame` undoes on the result.
    given_eskf : the caller passed ``eskf`` (the second start is then not tried).
    eskf_run : the ESKF result that was run (or given); ``eskf`` is it when healthy, else the multilateration
        seed (:mod:`uwbimu.calibration.start_check`).  None: the same as ``eskf``.
    source : what ``eskf`` is: ``eskf`` or ``multilateration`` (the ``calibration_start`` event).
    """

    dataset: Any
    eskf: Any
    eskf_options: Any
    setup: Any
    frame: Any
    given_eskf: bool
    eskf_run: Any = None
    source: str = "eskf"


@dataclass(frozen=True)
class Built:
    """Stage 2: the problem and its IMU factors.

    Attributes
    ----------
    problem : :class:`uwbimu.calibration.graph.Problem`.
    imu_factors : its ``CombinedImuFactor`` list (:func:`uwbimu.calibration.graph._imu_factors`).
    """

    problem: Any
    imu_factors: list


@dataclass(frozen=True)
class Solved:
    """A solve of the factor graph (:func:`uwbimu.calibration.profile_walk.solve`).

    Attributes
    ----------
    graph : the ``gtsam.NonlinearFactorGraph`` solved.
    values : its solution (``gtsam.Values``, variables named by :mod:`uwbimu.calibration.keys`).
    assoc : the range association the graph was built with (:class:`uwbimu.calibration.graph.Association`).
    iterations : Levenberg-Marquardt iterations of the last solve.
    """

    graph: Any
    values: Any
    assoc: Any
    iterations: int

    def time_offset(self) -> float:
        """t_d [s] of the solution (the free solve's variable ``t(0)``); raises when t_d was held fixed."""
        return float(self.values.atVector(keys.time_offset())[0])

    def cost(self) -> float:
        """The graph's cost at the solution (chi-square / 2)."""
        return float(self.graph.error(self.values))

    def astuple(self) -> tuple:
        """``(graph, values, assoc, iterations)``: the shape of the older private API."""
        return self.graph, self.values, self.assoc, self.iterations


@dataclass(frozen=True)
class Profiled:
    """The t_d profile stage and the solve its verdict leads to.

    Attributes
    ----------
    solved : the final solve (refined at the profile's vertex, held at the prior when not identified, or the
        free solve when the profile is disabled).
    profile : the :class:`uwbimu.calibration.profile.TdProfile`, or None when disabled.
    td_free : t_d is a variable of the final solve (False: held at ``time_offset_prior``).
    chi2_scale : the profile's honesty correction (model / sandwich variance of t_d; 1 when not profiled).
    verdict : the t_d verdict when no profile gave one (``fixed``: held at its prior because every
        stream shares one clock); None otherwise.
    """

    solved: Solved
    profile: Any
    td_free: bool
    chi2_scale: float
    verdict: Optional[str] = None
