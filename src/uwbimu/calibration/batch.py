"""``calibrate(dataset)``: the batch calibrator as stages (:mod:`uwbimu.calibration.stages`): ESKF seed (or, when
that run fails the health check, a robust multilateration: :mod:`uwbimu.calibration.start_check`), factor graph,
free solve (second start, range model chosen on it: :mod:`uwbimu.calibration.range_model_stage`, adaptive Huber,
IMU noise scale), t_d profile and final solve, the blocks the log does
not determine held at their priors (:func:`uwbimu.calibration.identifiability.hold_rule`), marginals and report
(the solves and the profile walk: :mod:`uwbimu.calibration.profile_walk`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable, Optional

from math import erfc

import numpy as np
import pandas as pd

from uwbimu.formatting import finite_or_none
from uwbimu.calibration import (anchor_loo, anchors, graph, held, keys, noise_scale, range_model_stage, robust_loss,
                                start_check)
from uwbimu.calibration.identifiability import hold_rule, identifiability
from uwbimu.calibration.uncertainty import (SparseMarginals, _block_event, _calibration_covariance,  # noqa: F401
                                           _marginals, _profile_chi2_scale)
from uwbimu.calibration.options import CalibrationOptions
from uwbimu.calibration.profile import TdProfile, confidence_interval, motion_advice
from uwbimu.calibration.stages import STAGES, Built, Profiled, Solved, StageProgress, Start
# the solves and the profile walk (re-exported: tests and benchmarks address them here)
from uwbimu.calibration.profile_walk import PROFILE_CHI2_TOL, _solve, profile_rows, run_profile, solve  # noqa: F401


@dataclass
class CalibrationResult:
    """Output of :func:`calibrate`.

    Attributes
    ----------
    calibration : plain dict written to ``calibration.yaml`` (value, sd, correlations, verdicts).
    trajectory : DataFrame ``t`` (UWB clock), ``t_imu``, position, quaternion, velocity and their sd.
    residuals : DataFrame ``t, anchor, range, predicted, residual, z, outlier`` (residual = range − predicted, the
        ESKF's innovation sign; z = residual / sigma).
    anchors : DataFrame in the ``anchors.csv`` format plus ``sd_x, sd_y, sd_z`` [m] (marginal; 0 for
        fixed anchors) and ``estimated`` (bool), every anchor, in the gauge frame.
    profile : the t_d profile, or None when disabled.
    eskf : the initialising ESKF result.
    """

    calibration: dict[str, Any]
    trajectory: pd.DataFrame
    residuals: pd.DataFrame
    profile: Optional[TdProfile]
    eskf: Any
    runtime_s: float = float("nan")
    events: list[dict] = field(default_factory=list)
    anchors: Optional[pd.DataFrame] = None


def calibrate(dataset, options: Optional[CalibrationOptions] = None, eskf=None, eskf_options=None,
              progress: Optional[Callable[[float], None]] = None, workers: int = 1,
              executor: Optional[dict] = None, reference_solver: bool = False,
              on_stage: Optional[Callable[[StageProgress], None]] = None) -> CalibrationResult:
    """Full-batch MAP calibration of lever arm, t_d and per-anchor range bias (see docs/calibrate.md).

    Parameters
    ----------
    dataset : :class:`uwbimu.io.dataset.Dataset` with IMU, ranges and anchors (one tag).  A z-down
        anchors' frame (``anchor_frame_up: -z``) and ``known_anchor_bias`` are handled by
        :mod:`uwbimu.calibration.frames`: the outputs are in the anchors' frame, the ranges in
        ``residuals`` have the documented biases removed.
    options : graph settings; defaults when None.
    eskf : an ESKF result (anchors' frame) to initialise from; ``run_eskf(dataset, eskf_options)`` when None.
        Either way the graph starts from it only when it passes the health check
        (:func:`uwbimu.calibration.start_check.eskf_health`), else from a robust multilateration of the log;
        event ``calibration_start`` (``source``, ``reason``) and calibration.yaml ``start`` say which.
    eskf_options : options of that ESKF; ``options.init_eskf`` when None, else the ESKF defaults.
    progress : called with a fraction in [0, 1].
    workers : processes for the t_d profile's walks (:func:`run_profile`, :func:`uwbimu.parallel.execute`); 1
        (default) solves them here, in order, without pickling.  The result does not depend on it.
    executor : further keyword arguments of :func:`uwbimu.parallel.execute` for the profile
        (``client``, ``scheduler`` or ``dask_local``: run it on Dask); None: a local process pool.
    reference_solver : every solve with GTSAM's own ``LevenbergMarquardtOptimizer`` and the profile points
        solved to its convergence rule (``mode="reference"`` of :func:`run_profile`): the slower reference
        the fast path is measured against (``benchmarks/bench_calibrate.py``, ``tests/test_calibrate_speed.py``).
    on_stage : called with a :class:`uwbimu.calibration.stages.StageProgress` when each stage of
        :data:`uwbimu.calibration.stages.STAGES` starts, ends or is skipped, and after each t_d profile point
        (``uwbimu calibrate`` draws its progress bars from these).  The library prints nothing.
    """
    t_start = time.perf_counter()
    o = options or CalibrationOptions()
    report = _StageReporter(progress, on_stage)
    engine = "gtsam" if reference_solver else "python"
    events: list[dict] = []
    report.started("initialising ESKF", 0.0)
    start = _start(dataset, o, eskf, eskf_options, events)
    report.done("initialising ESKF", 0.1)
    report.started("factor graph")
    built = _build(start, o)
    report.done("factor graph")
    report.started("free solve")
    solved = _free_solve(built, engine)
    report.done("free solve")
    if o.second_start and not start.given_eskf and not start.setup.any_estimated:
        report.started("second start")
        start, built, solved = _second_start(start, o, built, solved, engine, events)
        report.done("second start")
    else:
        report.skipped("second start")
    # the range model and Huber threshold chosen on this log, on the residuals about the batch's own free solve,
    # and the graph solved again under it (uwbimu.calibration.range_model_stage; select: auto / cv)
    mode, why = range_model_stage.selection_mode(o, start.dataset, built.problem)
    if mode == "select":
        report.started("range model")
        o, built, solved, selection = range_model_stage.choose_and_resolve(start, o, built, solved,
                                                                           _warm_solver(engine), events)
        report.done("range model")
    else:
        report.skipped("range model")
        selection = {"select": mode, **({"reason": why} if why else {})}
    huber = {"selection": "fixed", "k": float(built.problem.options.huber_k)}
    if o.huber_k == "adaptive":
        report.started("adaptive Huber")
        built, solved, huber = robust_loss.adapt_huber(built, solved, solve=_warm_solver(engine))
        report.done("adaptive Huber")
    else:
        report.skipped("adaptive Huber")
    imu_scale = None
    if o.imu_noise_scale == "estimate":
        report.started("IMU noise scale")
        built, solved, imu_scale = _imu_noise_scale(built, solved, engine, events)
        report.done("IMU noise scale")
    else:
        report.skipped("IMU noise scale")
    profiled = _profile_and_final_solve(start, o, built, solved, engine, workers, executor, reference_solver,
                                        events, report)
    report.started("marginals and report", 0.9)
    cal, traj, res, anchor_table = _report(built.problem, profiled, start.dataset)
    cal["imu_noise"] = _imu_noise_report(built.problem, imu_scale)
    cal["range_model"]["huber"] = huber
    cal["range_model"]["selection"] = selection
    ev = _block_event(cal["covariance"].get("block_check"), drift_on=o.range_bias_drift is not None)
    if ev is not None:
        events.append(ev)
    cal["identifiability"], id_events = identifiability(cal, o)
    hold = hold_rule(cal, cal["identifiability"], events, o)
    if hold:
        first = held.first_pass(cal, hold)
        built, profiled = held.hold_blocks(built, profiled, hold, engine)
        cal, traj, res, anchor_table = _report(built.problem, profiled, start.dataset)
        cal["imu_noise"] = _imu_noise_report(built.problem, imu_scale)
        cal["range_model"]["huber"] = huber
        cal["range_model"]["selection"] = selection
        held.consider_sd(cal, hold, o)
        cal["held_at_prior"] = {"blocks": sorted(k for k in hold if k != "refuted"), "first_pass": first,
                                "refuted": hold["refuted"]}
        events.append({"kind": "calibration_held", "severity": "warning", "blocks": cal["held_at_prior"]["blocks"],
                       "information_gain": {k: v for k, v in hold.items() if k != "refuted"},
                       "refuted": hold["refuted"], "first_pass": first,
                       "message": "the log does not determine " + " / ".join(cal["held_at_prior"]["blocks"]) + " and "
                                  "the residuals refute the noise model: held at the prior and solved again "
                                  "(docs/calibrate.md 'What to trust'); the first solve's values in first_pass"})
        cal["identifiability"], id_events = identifiability(cal, o)
    events += id_events
    for ev in events:
        if ev["kind"] == "time_offset_not_identified":
            cal["time_offset"]["advice"] = ev["advice"]
    ev_start = next(e for e in events if e["kind"] == "calibration_start")
    cal["start"] = {k: ev_start.get(k) for k in ("source", "reason", "health")}
    agree = _estimator_agreement(start.eskf_run, cal)
    events.append(agree)
    cal["estimators"] = agree
    cal["events"] = [{k: v for k, v in ev.items()} for ev in events]
    out = CalibrationResult(calibration=cal, trajectory=traj, residuals=res, profile=profiled.profile,
                            eskf=start.eskf_run, events=events, anchors=anchor_table)
    from uwbimu.calibration.frames import from_graph_frame

    from_graph_frame(out, start.frame)
    report.done("marginals and report", 1.0)
    out.runtime_s = time.perf_counter() - t_start
    return out


def _plain_number(v):
    """A finite float, or None (inf / NaN are not YAML / JSON safe); other values as they are."""
    if isinstance(v, (bool, str)) or v is None:
        return v
    try:
        float(v)
    except (TypeError, ValueError):
        return v
    return finite_or_none(v)


def _estimator_agreement(eskf, cal: dict) -> dict:
    """The event comparing the batch's calibration ``cal`` with the initialising ESKF's
    (:func:`uwbimu.calibration.agreement.estimator_agreement`): kind ``estimators_agree`` (severity ``info``) or
    ``estimators_disagree`` (severity ``warning``, with the one-line ``message`` of
    :func:`~uwbimu.calibration.agreement.agreement_message`); values in m and s, plain floats (a non-finite ``z``
    is None)."""
    from uwbimu.calibration.agreement import agreement_message, estimator_agreement

    modes = ((getattr(eskf, "config", None) or {}).get("resolved") or {}).get("modes")
    ev = estimator_agreement(getattr(eskf, "calibration", None) or {}, cal, modes)
    msg = agreement_message(ev)
    ev["parameters"] = [{k: _plain_number(v) for k, v in row.items()} for row in ev["parameters"]]
    ev["z_threshold"] = float(ev["z_threshold"])
    ev["severity"] = "warning" if msg is not None else "info"
    if msg is not None:
        ev["message"] = msg
    return ev


class _StageReporter:
    """Turns the stages' start / end / skip and the profile's points into the ``progress`` (fraction) and
    ``on_stage`` (:class:`StageProgress`) callbacks; silent when both are None."""

    def __init__(self, progress: Optional[Callable[[float], None]],
                 on_stage: Optional[Callable[[StageProgress], None]]):
        self.progress, self.on_stage = progress, on_stage
        self.fraction = 0.0

    def _emit(self, stage: str, status: str, fraction: Optional[float], done=None, total=None) -> None:
        if fraction is not None:
            self.fraction = fraction
            if self.progress is not None:
                self.progress(fraction)
        if self.on_stage is not None:
            self.on_stage(StageProgress(stage=stage, index=STAGES.index(stage), status=status,
                                        fraction=self.fraction, done=done, total_points=total))

    def started(self, stage: str, fraction: Optional[float] = None) -> None:
        self._emit(stage, "started", fraction)

    def done(self, stage: str, fraction: Optional[float] = None) -> None:
        self._emit(stage, "done", fraction)

    def skipped(self, stage: str) -> None:
        self._emit(stage, "skipped", None)

    def profile_fraction(self, fraction: float) -> None:
        """The profile's own ``progress`` (0.2 .. 0.8 of the whole)."""
        self.fraction = fraction
        if self.progress is not None:
            self.progress(fraction)

    def point(self, done: int, total: int) -> None:
        if self.on_stage is not None:
            self.on_stage(StageProgress(stage="t_d profile", index=STAGES.index("t_d profile"), status="point",
                                        fraction=self.fraction, done=done, total_points=total))


def _warm_solver(engine: str) -> Callable:
    """``solve(pb, imf, values, td0, assoc) -> Solved``, warm-started, t_d free (the re-solves of a stage)."""
    return lambda pb, imf, values, td0, assoc: solve(pb, imf, values, td0, None, assoc=assoc, engine=engine)


def _start(dataset, o: CalibrationOptions, eskf, eskf_options, events: list) -> Start:
    """Stage 1: the part of the log the ESKF uses, in the graph frame, the anchor plan and the seeding ESKF.

    Appends the flight-segment event and the anchor plan's / bootstrap's events to ``events``.
    """
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.estimation.segments import select_segment

    from uwbimu.calibration.frames import to_graph_frame

    given_eskf = eskf is not None
    # by default the ESKF run uwbimu estimate makes (smoothed forward-backward): the batch starts from it and
    # compares its answer with it (estimators_agree / _disagree), one ESKF answer for the user
    eo0 = eskf_options or o.init_eskf or EskfOptions(smoother="forward_backward")
    # the same part of the log as the ESKF (the flight, where the floor's ranges are shadowed): one answer
    dataset, ev_segment = select_segment(dataset, eo0.segment, eo0.start, eo0.end)
    o.check_log(dataset)  # work bounds that depend on the log (drift knots), before any solve
    dataset, eskf_options, eskf, frame = to_graph_frame(dataset, eo0, eskf)
    setup = anchors.plan_anchors(dataset, o)
    events += [ev_segment] + list(setup.events)
    if not setup.any_estimated:
        eskf = eskf if eskf is not None else run_eskf(dataset, eskf_options)
        seed, ev_start = start_check.choose_start(dataset, o, eskf)
    else:
        # self-survey: the ESKF bootstraps on anchor guesses (its disagreement with a multilateration on those
        # same guesses says nothing), and a multilateration needs the positions being estimated
        eskf = _bootstrap(dataset, o, setup, eskf_options, eskf, events)
        seed, ev_start = eskf, {"kind": "calibration_start", "severity": "info", "source": "eskf",
                                "reason": "self_survey_bootstrap", "health": None}
    events.append(ev_start)
    return Start(dataset=dataset, eskf=seed, eskf_options=eskf_options, setup=setup, frame=frame,
                 given_eskf=given_eskf, eskf_run=eskf, source=ev_start["source"])


def _build(start: Start, o: CalibrationOptions) -> Built:
    """Stage 2: the problem and its IMU factors from the seeding ESKF."""
    pb = graph.build_problem(start.dataset, start.eskf, o, start.setup)
    return Built(problem=pb, imu_factors=graph._imu_factors(pb))


def _free_solve(built: Built, engine: str) -> Solved:
    """Stage 3: the first solve, t_d free, from the ESKF's states."""
    pb = built.problem
    return solve(pb, built.imu_factors, graph.initial_values(pb), pb.td0, None, engine=engine)


def _imu_noise_scale(built: Built, solved: Solved, engine: str, events: list) -> tuple[Built, Solved, dict]:
    """Stage: the IMU noise scale (:mod:`uwbimu.calibration.noise_scale`) and the solve under it."""
    warm = _warm_solver(engine)
    pb, imf, fg, values, assoc, iters, scale = noise_scale.estimate_imu_noise_scale(
        built.problem, built.imu_factors, *solved.astuple(), build_imu=graph._imu_factors,
        solve=lambda p, f, v, td, a: warm(p, f, v, td, a).astuple())
    ev = noise_scale.scale_event(scale)
    if ev is not None:
        events.append(ev)
    return Built(problem=pb, imu_factors=imf), Solved(graph=fg, values=values, assoc=assoc, iterations=iters), scale


#: calibration options whose setting asks for t_d on a single-clock log (the user expects a latency)
_TD_FIELDS = ("time_offset_prior", "time_offset_prior_sd", "td_profile")


def single_clock_hold(dataset, o: CalibrationOptions) -> Optional[dict]:
    """The ``time_offset_single_clock`` event when t_d is held at its prior because every stream shares one
    clock, else None.

    The ESKF's rule (:func:`uwbimu.estimation.timeoffset.single_clock_time_offset`) for the batch, so that
    both estimators give one answer: with ``dataset.yaml`` ``single_clock: true`` and none of
    ``time_offset_prior``, ``time_offset_prior_sd`` or ``td_profile`` configured, there is no second clock
    to be offset from and t_d is held at ``time_offset_prior`` (0) in the final solve (no profile; the other
    sigmas are conditional on it, calibration.yaml ``conditional_on_time_offset``).
    """
    from uwbimu.estimation.timeoffset import is_single_clock

    if not is_single_clock(dataset) or any(f in o.model_fields_set for f in _TD_FIELDS):
        return None
    return {"t": None, "kind": "time_offset_single_clock", "severity": "info", "mode": "fixed",
            "t_d": float(o.time_offset_prior),
            "message": "every stream of this log was stamped by one clock (dataset.yaml single_clock: true): "
                       "t_d held at its prior in the final solve; set time_offset_prior_sd or td_profile to "
                       "estimate a latency"}


def _profile_and_final_solve(start: Start, o: CalibrationOptions, built: Built, solved: Solved, engine: str,
                             workers: int, executor: Optional[dict], reference_solver: bool, events: list,
                             report: _StageReporter) -> Profiled:
    """Stages ``t_d profile`` and ``final solve``: the profile about the free solution, then the solve its
    verdict asks for (refined at the vertex, or t_d held at its prior); the free solve itself when disabled."""
    pb, imf = built.problem, built.imu_factors
    free_td = solved.time_offset()
    single = single_clock_hold(start.dataset, o)
    if single is not None:
        # one clock for every stream: no offset to estimate (the ESKF's rule, timeoffset.single_clock_time_offset)
        report.skipped("t_d profile")
        report.started("final solve")
        events.append(single)
        solved = solve(pb, imf, graph.without_td(solved.values), o.time_offset_prior, o.time_offset_prior,
                       engine=engine)
        report.done("final solve")
        return Profiled(solved=solved, profile=None, td_free=False, chi2_scale=1.0, verdict="fixed")
    if not o.td_profile.enabled:
        report.skipped("t_d profile")
        report.skipped("final solve")
        return Profiled(solved=solved, profile=None, td_free=True, chi2_scale=1.0)
    report.started("t_d profile")
    # honesty correction of the white-noise profile: model / sandwich variance of t_d at the free solve
    chi2_scale = _profile_chi2_scale(pb, solved.graph, solved.values, solved.assoc)
    prof = run_profile(pb, imf, solved.values, free_td, report.profile_fraction, workers=workers, executor=executor,
                       mode="reference" if reference_solver else "fast", chi2_scale=chi2_scale,
                       on_point=report.point)
    report.done("t_d profile")
    report.started("final solve")
    td_free = True
    if prof.identified:
        solved = solve(pb, imf, graph.with_td(solved.values, prof.vertex), prof.vertex, None, engine=engine)
        lo, hi = confidence_interval(prof.grid, prof.chi2, prof.confidence_chi2, chi2_scale=chi2_scale)
        if not lo <= solved.time_offset() <= hi:
            # The free optimum contradicts its own profile: report nothing as found.
            prof.verdict = "refinement_left_confidence_set"
    if not prof.identified:
        td_free = False
        events.append({"kind": "time_offset_not_identified", "verdict": prof.verdict,
                       "advice": motion_advice(start.eskf, prof.verdict, prof.grid)})
        solved = solve(pb, imf, graph.without_td(solved.values), o.time_offset_prior, o.time_offset_prior,
                       engine=engine)
    report.done("final solve")
    return Profiled(solved=solved, profile=prof, td_free=td_free, chi2_scale=chi2_scale)


#: What the second start changes in the initialising ESKF's options: the robust range model of the shipped
#: real-data preset (examples/estimator_real.yaml): a white 5 cm part plus a slowly varying bias per anchor.
_ROBUST_ESKF = "real"


def _second_start(start: Start, o: CalibrationOptions, built: Built, solved: Solved, engine: str,
                  events: list) -> tuple[Start, Built, Solved]:
    """The first free solve again from an ESKF with the robust range model of the real-data preset; the lower
    cost wins.

    A filter with a white range model can wander on a short real window (correlated range errors taken as
    independent) and hand the graph a trajectory and lever arm from which it does not return: ISAS-Walk's last
    15 s window with the default ESKF, filter lever arm (-78, 10, 43) cm, graph (-72, 13, 75) cm at chi2 +38
    above the solve from the robust filter's start, (4, 7, -34) cm.  The robust filter keeps the user's
    options otherwise (tags, frames, IMU noise); skipped when they already match it.  Tried after a multilateration
    start too (:mod:`uwbimu.calibration.start_check`: the first ESKF failed its health check).  Event
    ``second_start_won`` when its start gives the lower cost (costs compared as the graphs'; the range
    factors linearise the IMU deltas about each filter's bias, so near-equal costs may pick either).

    Returns the stages of the winner: ``(start, built, solved)`` as given, or those of the robust start.
    """
    import dataclasses

    from uwbimu.estimation import run_eskf
    from uwbimu.estimation.presets import load_preset

    eo = start.eskf_options
    robust = load_preset(_ROBUST_ESKF)
    upd = {"range_sigma": robust.range_sigma, "anchor_bias": robust.anchor_bias}
    if all(getattr(eo, k) == v for k, v in upd.items()):
        return start, built, solved
    eskf2 = run_eskf(start.dataset, eo.model_copy(update=upd))
    start2 = dataclasses.replace(start, eskf=eskf2, eskf_run=eskf2, source="eskf")
    built2 = _build(start2, o)
    solved2 = _free_solve(built2, engine)
    cost1, cost2 = solved.cost(), solved2.cost()
    if not cost2 < cost1:
        return start, built, solved
    events.append({"kind": "second_start_won", "severity": "info", "chi2_gain": 2.0 * (cost1 - cost2),
                   "first_lever_arm": [float(x) for x in solved.values.atVector(keys.lever_arm(0))],
                   "lever_arm": [float(x) for x in solved2.values.atVector(keys.lever_arm(0))],
                   "message": "the solve started from an ESKF with the robust real-data range model reached a lower "
                              "cost than the one started from the configured ESKF: its solution is used"})
    return start2, built2, solved2


def _imu_noise_report(pb, scale_info: Optional[dict]) -> dict:
    """calibration.yaml ``imu_noise``: the densities the graph used and, when estimated, how."""
    infl = float(pb.options.imu_noise_inflation)
    out = {"accel_noise_density": pb.imu_noise["accel_noise_density"] * infl,
           "gyro_noise_density": pb.imu_noise["gyro_noise_density"] * infl,
           "accel_bias_rw": pb.imu_noise["accel_bias_rw"] * infl, "gyro_bias_rw": pb.imu_noise["gyro_bias_rw"] * infl,
           "configured": dict(pb.imu_noise), "configured_source": dict(pb.imu_noise_source), "inflation": infl}
    out["scale"] = scale_info if scale_info is not None else {"method": "fixed"}
    return out


def _bootstrap(dataset, o: CalibrationOptions, setup, eo, eskf, events: list):
    """ESKF initialisation with anchors to estimate (gauge frame), then their initial guesses.

    With 4 or more anchors with surveyed coordinates the ESKF runs on those alone.  With fewer
    (its first fix needs 4), it runs on every anchor, the ``surveyed: false`` ones at their rough
    ``anchors.csv`` guesses, with the range sd raised to ``bootstrap_range_sigma``: an ESKF that
    trusts ranges to wrongly placed anchors diverges, one that de-weights them tracks the IMU
    trajectory to a few tens of cm, which the joint batch solve then refines.  The unsurveyed
    anchors start at the multilateration of their ranges from that trajectory, followed by the
    geometry checks (:func:`_initial_anchors`).  A given ``eskf`` (same frame) is used as is.
    Several tags: the ESKF estimates one lever arm per tag (unless its option ``tag`` picks one), and
    each range is placed at its own tag's antenna.
    """
    from uwbimu.estimation import run_eskf

    if eskf is None:
        guesses = int(setup.surveyed.sum()) < 4 and bool((setup.estimated & ~setup.surveyed).any())
        if guesses:
            sigma = max(float(o.range_sigma or dataset.meta.range_sigma or 0.1), o.bootstrap_range_sigma)
            # its residuals refute the guessed anchors, not the lever arm: the lever arm is not held
            eo = eo.model_copy(update={"range_sigma": sigma, "hold_unidentified": False})
            events.append({"kind": "anchor_bootstrap_from_guesses", "range_sigma": sigma,
                           "message": f"fewer than 4 surveyed anchors: the initialising ESKF used the anchors.csv "
                                      f"guesses of the unsurveyed anchors with a range sd of {sigma:g} m"})
        eskf = run_eskf(anchors.eskf_dataset(dataset, setup, with_unsurveyed=guesses), eo)
    events += _initial_anchors(dataset, eskf, o, setup)
    return eskf


def _initial_anchors(dataset, eskf, o: CalibrationOptions, setup) -> list[dict]:
    """Initial guesses of the estimated anchors (multilateration of the ESKF trajectory) and geometry checks.

    An anchor without prior (``surveyed: false``) starts at the multilateration of its ranges from the
    ESKF antenna positions; one with a prior starts at its ``anchors.csv`` position.  Several tags: the
    ranges of the tags the ESKF used (:func:`uwbimu.calibration.graph.tag_names`), each at its own tag's
    antenna (the ESKF's lever arm of that tag), all of them in the multilateration and the checks.  Degenerate
    geometry (:func:`uwbimu.calibration.anchors.geometry_checks`) refuses an anchor without prior unless
    ``degenerate_anchors: warn``; with a prior it is a warning (the prior decides).
    """
    from uwbimu.errors import InputError

    sigma = float(o.range_sigma or dataset.meta.range_sigma or 0.1)
    bias_sd = o.anchor_bias_prior_sd if o.anchor_bias_estimated(True) else None
    uwb = dataset.uwb
    names, tag_column = graph.tag_names(dataset, eskf)
    levers = None  # one tag: the ESKF's lever arm
    if tag_column and "tag" in uwb.columns:
        uwb = uwb[uwb["tag"].astype(str).isin(names).to_numpy()]
        if len(names) > 1:
            ti = uwb["tag"].astype(str).map({n: i for i, n in enumerate(names)}).to_numpy(np.int64)
            levers = anchors.tag_lever_arms(eskf, names, ti)
    aid = uwb["anchor"].astype(str).to_numpy()
    events = []
    for j in np.flatnonzero(setup.estimated):
        a_id = setup.ids[j]
        sel = (aid == a_id) & (uwb["t"].to_numpy(float) <= eskf.t[-1])  # ranges within the ESKF's span
        rho = uwb["range"].to_numpy(float)[sel]
        has_prior = bool(np.isfinite(setup.prior_sd[j]))
        if sel.sum() < 4 and not has_prior:
            raise InputError(f"anchor self-survey: anchor {a_id!r} has {int(sel.sum())} ranges in uwb.csv; at least 4 "
                             "(from different places) are needed to locate it without a prior")
        if not sel.any():
            continue  # a prior and no ranges: the prior alone places it (its sd says so)
        P, P_sd = anchors.antenna_positions(eskf, uwb["t"].to_numpy(float)[sel], with_sd=True,
                                       lever_arm=None if levers is None else levers[sel])
        if has_prior:
            a0 = setup.pos[j]
        else:
            a0, _rms = anchors.multilaterate(P, rho)
            setup.pos[j] = a0
        found = anchors.geometry_checks(a_id, a0, P, rho, sigma, bias_sd, P_sd)
        for ev in found:
            ev["severity"] = "warning" if has_prior or o.degenerate_anchors == "warn" else "refused"
            ev["has_prior"] = has_prior
        if bias_sd is not None:
            # bias and distance confounded (narrow cone of lines of sight): solvable, but say so (never refused)
            conf = anchors.bias_confounding(a_id, a0, P)["event"]
            if conf is not None:
                found.append(conf | {"severity": "warning", "has_prior": has_prior})
        refused = [ev for ev in found if ev["severity"] == "refused"]
        if refused:
            raise InputError("anchor self-survey refused: " + "; ".join(ev["message"] for ev in refused),
                             hint="give a rough position (surveyed: true) for a weak prior, drop the anchor from "
                                  "--estimate-anchors, or set degenerate_anchors: warn in the calibrate config")
        events += found
    return events


def _report(pb, profiled: Profiled, dataset):
    """calibration.yaml's dict, the trajectory, the residuals and the anchor table of the final solve."""
    solved, td_free, prof, chi2_scale = profiled.solved, profiled.td_free, profiled.profile, profiled.chi2_scale
    values, assoc = solved.values, solved.assoc
    marg = _marginals(pb, solved.graph, values)
    est = [j for j in range(len(pb.anchor_ids)) if pb.estimated(j)]
    param_keys = [keys.lever_arm(0)] + ([keys.time_offset()] if td_free else []) + \
        [keys.anchor_bias(j) for j in range(len(pb.anchor_ids))] + [keys.anchor_position(j) for j in est]
    names = ["lever_arm_x", "lever_arm_y", "lever_arm_z"] + (["time_offset"] if td_free else []) + \
        [f"anchor_bias_{a}" for a in pb.anchor_ids] + \
        [f"anchor_{c}_{pb.anchor_ids[j]}" for j in est for c in "xyz"]
    dmod = pb.options.range_model.direction
    n_dir = graph.n_dir_vectors(pb)
    off_dir = len(names)
    if n_dir:  # after the others, so the offsets below stay valid
        param_keys += [keys.direction_bias(i) for i in range(n_dir)]
        names += [f"direction_{_dir_label(pb, i, '_')}{c}" for i in range(n_dir) for c in dmod.names()]
    amod = pb.options.range_model.anchor_direction
    off_adir = len(names)
    adir = graph.adir_anchors(pb)
    param_keys += [keys.anchor_direction_bias(j) for j in adir]
    names += [f"anchor_direction_{pb.anchor_ids[j]}_{c}" for j in adir for c in (amod.names() if amod else [])]
    off_tags = len(names)
    for i, tag in enumerate(pb.tag_names[1:], start=1):  # several tags: the first one's lever arm is lever_arm_*
        param_keys.append(keys.lever_arm(i))
        names += [f"lever_arm_{tag}_{c}" for c in "xyz"]
    lever = values.atVector(keys.lever_arm(0))
    td = float(values.atVector(keys.time_offset())[0]) if td_free else pb.options.time_offset_prior
    cov, cov_model, cov_sec = _calibration_covariance(pb, solved.graph, values, assoc, param_keys, td, td_free,
                                                      marg=marg)
    if "block_check" in cov_sec:  # per parameter, by name
        bc = cov_sec["block_check"]
        per = {f: bc.pop(f) for f in ("variance_ratio", "dof", "p_value", "significant", "widened")}
        bc["parameters"] = {n: {f: (round(v[i], 6) if isinstance(v[i], float) else v[i]) for f, v in per.items()}
                            for i, n in enumerate(names)}
    systematic = None
    if est:
        # the self-survey's systematic error, measured on the surveyed anchors (anchor_loo.py)
        disp, skipped = anchor_loo.surveyed_anchor_displacements(pb, solved.graph, values, assoc, td)
        s2, raw = anchor_loo.systematic_variance(disp)
        applied = pb.options.anchor_systematic == "surveyed" and s2 is not None
        if applied:
            ia = [names.index(f"anchor_{c}_{pb.anchor_ids[j]}") for j in est for c in "xyz"]
            cov = cov.copy()
            cov[ia, ia] += s2
        systematic = anchor_loo.report(disp, s2, raw, applied, skipped)
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0))
    sd_model = np.sqrt(np.diag(cov_model))
    corr = cov / np.outer(sd, sd)
    # Residuals of the final graph's range factors, in the order of assoc.used.
    e = graph.range_residuals(solved.graph, assoc, values, td)
    used = assoc.used
    res = pd.DataFrame({"t": pb.t_range[used], "anchor": np.array(pb.anchor_ids, dtype=object)[pb.anchor_j[used]],
                        "range": pb.rho[used], "predicted": pb.rho[used] + e, "residual": -e})
    if pb.tag_column:  # the log names its tags: so does residuals.csv
        ti = pb.tag_i[used] if pb.tag_i is not None else np.zeros(len(used), np.int64)
        res.insert(2, "tag", np.array(pb.tag_names, dtype=object)[ti])
    sig = robust_loss.row_sigma(pb, assoc)
    if pb.anchor_b is not None:
        # TDoA rows: "anchor" is anchor_a, "range" the measured TDoA [m]
        b = pb.anchor_b[assoc.used]
        res["kind"] = np.where(b >= 0, "tdoa", "range")
        res["anchor_b"] = np.where(b >= 0, np.array(pb.anchor_ids, dtype=object)[np.maximum(b, 0)], "")
    if pb.drift_knot is not None:
        # the slowly varying bias of each row (already inside "predicted" and "residual")
        res["bias_drift"] = [float(values.atVector(keys.bias_drift(j, n))[0])
                             for j, n in zip(pb.anchor_j[used], pb.drift_knot[used])]
    if n_dir:
        # the direction-dependent bias of each row (already inside "predicted" and "residual")
        res["bias_direction"] = graph.direction_terms(solved.graph, assoc, values, td)
    if amod is not None:
        # the anchor-side direction-dependent bias of each row (already inside "predicted" and "residual")
        res["bias_anchor_direction"] = graph.anchor_direction_terms(solved.graph, assoc, values, td)
    res["z"] = res["residual"] / sig
    res["outlier"] = np.abs(res["z"]) > pb.options.huber_k
    offs = 3 + (1 if td_free else 0)
    bias = {a: float(values.atVector(keys.anchor_bias(j))[0]) for j, a in enumerate(pb.anchor_ids)}
    cal = {
        "method": "batch-map-gtsam",
        "lever_arm": [float(x) for x in lever],
        "lever_arm_sd": [float(x) for x in sd[:3]],
        "lever_arm_sd_model": [float(x) for x in sd_model[:3]],
        "time_offset": {"value": td, "sd": float(sd[3]) if td_free else None,
                        "sd_marginal": float(sd[3]) if td_free else None,
                        "sd_model": float(sd_model[3]) if td_free else None,
                        "profile_chi2_scale": float(chi2_scale),
                        "sd_curvature": (float(prof.sigma_curvature) if prof is not None and prof.identified
                                         else None),
                        "verdict": (prof.verdict if prof is not None else (profiled.verdict or "not_profiled")),
                        "held_at_prior": not td_free,
                        "profile_confidence_interval": (
                            [float(v) for v in confidence_interval(prof.grid, prof.chi2, prof.confidence_chi2,
                                                                   chi2_scale=chi2_scale)]
                            if prof is not None and prof.identified else None),
                        "profile_grid": ([float(prof.grid[0]), float(prof.grid[-1])] if prof is not None else None)},
        "anchor_bias": bias,
        "anchor_bias_sd": {a: float(sd[offs + j]) for j, a in enumerate(pb.anchor_ids)},
        "anchor_bias_sd_model": {a: float(sd_model[offs + j]) for j, a in enumerate(pb.anchor_ids)},
        "covariance": cov_sec,
        "correlations": {"names": names, "matrix": [[round(float(c), 4) for c in row] for row in corr]},
        "ranges": {"used": int(len(assoc.used)), "outside_imu_span": int(len(pb.t_range) - len(assoc.used)),
                   "downweighted": int(res["outlier"].sum()),
                   "expected_downweighted": float(len(res) * erfc(pb.options.huber_k / np.sqrt(2.0))),
                   "outliers_3sigma": int((np.abs(res["z"]) > 3.0).sum()), "huber_k": pb.options.huber_k,
                   "range_sigma": pb.range_sigma},
        "range_model": {"white_sd": pb.range_sigma, "huber_k": pb.options.huber_k,
                        "constant_bias_prior_sd": pb.options.anchor_bias_prior_sd if pb.options.estimate_anchor_bias
                        else None,
                        "drift": (pb.options.range_bias_drift.model_dump() | {"knots_per_anchor": pb.n_knots}
                                  if pb.options.range_bias_drift is not None else None),
                        "direction": _direction_report(pb, values, sd, off_dir)},
        "solver": {"keyframes": int(len(pb.key_idx)), "iterations": int(solved.iterations),
                   "final_cost": solved.cost()},
    }
    if amod is not None:  # only with the option: the layout without it is unchanged
        cal["range_model"]["anchor_direction"] = _anchor_direction_report(pb, values, sd, off_adir)
    if pb.n_tags > 1:
        # several tags: one block each, as the ESKF's calibration.yaml (top-level lever_arm = the first tag's)
        cal = _with_tags(cal, pb, values, sd, off_tags, assoc)
    cal["time_offset_sd"] = cal["time_offset"]["sd"]
    # t_d held at its prior: every other sigma is conditional on that value (its uncertainty is not in them)
    cal["conditional_on_time_offset"] = (None if td_free else td)
    off_p = offs + len(pb.anchor_ids)
    sd_p = {j: sd[off_p + 3 * i: off_p + 3 * i + 3] for i, j in enumerate(est)}
    cal["anchors"], anchor_table = _anchor_report(pb, values, sd_p, dataset)
    if systematic is not None:
        cal["anchors"]["systematic"] = systematic
    traj = _trajectory(pb, values, marg, td)
    return cal, traj, res, anchor_table


def _with_tags(cal: dict, pb, values, sd, off: int, assoc) -> dict:
    """``cal`` with a ``tags`` block after ``lever_arm_sd``: ``{tag: {lever_arm, lever_arm_sd, lever_arm_prior,
    ranges}}`` [m, IMU frame], every tag in order (the first one's values are the top-level ``lever_arm``)."""
    tags = {}
    n_rows = np.bincount(pb.tag_i[assoc.used], minlength=pb.n_tags)
    for i, tag in enumerate(pb.tag_names):
        s = sd[:3] if i == 0 else sd[off + 3 * (i - 1): off + 3 * i]
        tags[tag] = {"lever_arm": [float(x) for x in values.atVector(keys.lever_arm(i))],
                     "lever_arm_sd": [float(x) for x in s],
                     "lever_arm_prior": [float(x) for x in pb.lever_prior[i]],
                     "ranges": int(n_rows[i])}
    out = {}
    for k, v in cal.items():
        out[k] = v
        if k == "lever_arm_sd":
            out["tags"] = tags
    return out


def _dir_label(pb, i: int, sep: str = "/") -> str:
    """Label of direction coefficient vector ``i``: ``[TAG sep][ANCHOR]`` (with ``sep`` appended, ``_`` names) or
    ``all`` (shared, one tag; "" in names)."""
    d = pb.options.range_model.direction
    per = graph.n_dir_per_tag(pb)
    t, a = divmod(i, per)
    parts = ([pb.tag_names[t]] if pb.n_tags > 1 else []) + ([pb.anchor_ids[a]] if d.per_anchor else [])
    if sep == "_":
        return "".join(p + "_" for p in parts)
    return parts[-1] if parts else "all"


def _direction_report(pb, values, sd, off: int):
    """``range_model.direction`` of calibration.yaml: the model, coefficient values and marginal sd [m, m/rad].

    ``coefficients``: ``{ANCHOR or "all": {name: {value, sd}}}`` with one tag; with several, one such
    mapping per tag (``{TAG: {ANCHOR or "all": ...}}``: the body-frame direction belongs to each tag's antenna).
    """
    d = pb.options.range_model.direction
    if d is None:
        return None
    out = d.model_dump() | {"frame": "tag body (IMU) frame, line of sight tag antenna -> anchor",
                            "coefficient_names": d.names(), "coefficients": {}}
    for i in range(graph.n_dir_vectors(pb)):
        c = values.atVector(keys.direction_bias(i))
        s = sd[off + i * d.n_coef: off + (i + 1) * d.n_coef]
        blk = {n: {"value": float(v), "sd": float(e)} for n, v, e in zip(d.names(), c, s)}
        if pb.n_tags > 1:
            out["coefficients"].setdefault(pb.tag_names[i // graph.n_dir_per_tag(pb)], {})[_dir_label(pb, i)] = blk
        else:
            out["coefficients"][_dir_label(pb, i)] = blk
    return out


def _anchor_direction_report(pb, values, sd, off: int):
    """``range_model.anchor_direction`` of calibration.yaml: the model and, per anchor with ranges, its coefficients
    ``{ANCHOR: {name: {value, sd}}}`` [m, m/rad^q]."""
    d = pb.options.range_model.anchor_direction
    if d is None:
        return None
    out = d.model_dump() | {"frame": "anchor antenna frame (anchors.csv qw..qz), line of sight anchor -> tag antenna",
                            "coefficient_names": d.names(), "coefficients": {}}
    for i, j in enumerate(graph.adir_anchors(pb)):
        c = values.atVector(keys.anchor_direction_bias(j))
        s = sd[off + i * d.n_coef: off + (i + 1) * d.n_coef]
        out["coefficients"][pb.anchor_ids[j]] = {n: {"value": float(v), "sd": float(e)}
                                                 for n, v, e in zip(d.names(), c, s)}
    return out


def _anchor_positions(pb, values) -> np.ndarray:
    return np.array([values.atPoint3(keys.anchor_position(j)) if pb.estimated(j) else pb.anchor_pos[j]
                     for j in range(len(pb.anchor_ids))]).reshape(-1, 3)


def _anchor_report(pb, values, sd_p: dict, dataset):
    """``calibration.yaml``'s ``anchors`` section and the ``anchors_estimated.csv`` table.

    Each anchor's entry says whether its constant range bias ``A(j)`` was estimated (``bias_estimated``;
    ``estimate_anchor_bias: false`` holds every bias at 0, ``surveyed_only`` those of the estimated anchors),
    and ``bias_held_at_zero`` lists the anchors whose bias was held at 0.
    """
    s = pb.anchors
    bias_est = [pb.options.anchor_bias_estimated(bool(s.estimated[j])) for j in range(len(pb.anchor_ids))]
    pos = _anchor_positions(pb, values)
    R = s.transform[0]
    file_ids = [str(a) for a in dataset.anchors["anchor"]]
    per = {}
    for j, a in enumerate(pb.anchor_ids):
        e = {"position": [float(v) for v in pos[j]],
             "sd": [float(v) for v in sd_p[j]] if j in sd_p else [0.0, 0.0, 0.0],
             "estimated": bool(s.estimated[j]), "surveyed": bool(s.surveyed[j]),
             "prior_sd": float(s.prior_sd[j]) if np.isfinite(s.prior_sd[j]) else None,
             "bias_estimated": bool(bias_est[j])}
        if s.estimated[j] and s.surveyed[j]:
            e["moved_from_anchors_csv"] = [float(v) for v in pos[j] - s.pos[j]]
        per[a] = e
    out = {"gauge": s.gauge, "estimated": [a for j, a in enumerate(pb.anchor_ids) if s.estimated[j]],
           "positions": per, "bias_held_at_zero": [a for j, a in enumerate(pb.anchor_ids) if not bias_est[j]]}
    if s.pairs is not None:
        out["anchor_ranges"] = [
            {"anchor_a": pb.anchor_ids[int(a)], "anchor_b": pb.anchor_ids[int(b)], "range": float(r), "sd": float(sd),
             "residual": float(r - np.linalg.norm(pos[int(a)] - pos[int(b)])),  # measured - predicted
             "in_graph": bool(s.estimated[int(a)] or s.estimated[int(b)])}
            for a, b, r, sd in s.pairs[["a", "b", "range", "sd"]].itertuples(index=False)]
    j_of = {a: j for j, a in enumerate(pb.anchor_ids)}
    rows = []
    for i, a in enumerate(file_ids):
        j = j_of[a]
        sdj = sd_p.get(j, np.zeros(3))
        rows.append([a, *pos[j], *sdj, bool(s.estimated[j])])
    table = pd.DataFrame(rows, columns=["anchor", "x", "y", "z", "sd_x", "sd_y", "sd_z", "estimated"])
    quat = ["qw", "qx", "qy", "qz"]
    if set(quat) <= set(dataset.anchors.columns):
        from scipy.spatial.transform import Rotation

        q = dataset.anchors[quat].to_numpy(float)
        # Antenna orientations follow the gauge rotation (identity unless the convention applies).
        rq = (Rotation.from_matrix(R) * Rotation.from_quat(q[:, [1, 2, 3, 0]])).as_quat()
        for k, c in enumerate(quat):
            table.insert(4 + k, c, rq[:, [3, 0, 1, 2]][:, k])
    return out, table


def _trajectory(pb, values, marg, td: float) -> pd.DataFrame:
    rows = []
    for k, t in enumerate(pb.t_key):
        pose = values.atPose3(keys.pose(k))
        q = pose.rotation().toQuaternion()
        v = values.atVector(keys.velocity(k))
        cov = marg.marginalCovariance(keys.pose(k))  # tangent [theta, p] in the body frame
        R = pose.rotation().matrix()
        sp = np.concatenate([np.sqrt(np.diag(cov[:3, :3])), np.sqrt(np.diag(R @ cov[3:, 3:] @ R.T))])
        sv = np.sqrt(np.diag(marg.marginalCovariance(keys.velocity(k))))
        rows.append([t - td, t, *pose.translation(), q.w(), q.x(), q.y(), q.z(), *v, *sp[3:], *sp[:3], *sv])
    cols = ["t", "t_imu", "px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz",
            "sd_px", "sd_py", "sd_pz", "sd_rx", "sd_ry", "sd_rz", "sd_vx", "sd_vy", "sd_vz"]
    return pd.DataFrame(rows, columns=cols)
