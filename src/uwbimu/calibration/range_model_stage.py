"""Stage ``range model``: the range model chosen on the batch's own free solve, then the graph solved with it.

By default (``range_model.select: auto``) the batch chooses the range model of each log (white, direction-dependent,
drifting bias, both; and the Huber threshold) by the blocked cross-validation of
:mod:`uwbimu.calibration.range_model_select`, on the range residuals about its **own first free solve** (after the
second start): the trajectory, lever arm and t_d of that solve are held, the candidates are fitted and scored on the
residuals.  The graph is then rebuilt with the chosen model and solved again, warm-started from that solve; the t_d
profile and the final solve use it.

Why the free solve and not the initialising ESKF: a filter can wander on a short real window, and the residuals
about it then carry the wander (ISAS-Walk's last 15 s with a filter estimating its unidentified lever arm:
the model chosen about that filter left the lever arm 3.8 sigma off, ``tests/test_calibrate_noise_scale.py``).  The
batch's free solve is the smoothed, second-started fit whose residuals are those the final model will face.

Which logs (:func:`selection_mode`): with ``auto``, only when the user configured no range model (none of
``range_bias_drift``, ``range_model.direction``, ``range_model.anchor_direction`` set: a configured model is kept as
is, recorded ``select: configured``), and only on logs the candidates describe: two-way ranges to fixed anchors,
one tag, grouped range factors (no TDoA candidates exist: TDoA logs stay as they are, ``select:
not_applicable``).  ``cv`` selects whenever the log allows (replacing a configured model) and refuses a log it
cannot serve; ``given`` never selects.  The stage chooses the family only: the graph's Huber threshold stays
``huber_k``'s rule (``adaptive``, the default: chosen on the re-solve's residuals by
:mod:`uwbimu.calibration.robust_loss`; a number: kept, and the only threshold the families are compared at).  The
selection's own best threshold is recorded (``huber_k`` of the record) but is in units of its fitted innovation sd,
not of the graph's ``range_sigma``, which the stage leaves as configured.
"""

from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from uwbimu.calibration import graph
from uwbimu.calibration.range_model_select import HUBER_GRID, RangeModelSelection, apply_selection, select_on_residuals
from uwbimu.errors import InputError, UsageError

#: Options that configure a range model: with any of them set, ``select: auto`` keeps the model as configured.
MODEL_FIELDS = ("range_bias_drift",)
RANGE_MODEL_FIELDS = ("direction", "anchor_direction")


def configured_model(o) -> list[str]:
    """The range-model options the user set (explicitly, even to none), as dotted names; [] when none."""
    out = [f for f in MODEL_FIELDS if f in o.model_fields_set]
    if "range_model" in o.model_fields_set:
        out += [f"range_model.{f}" for f in RANGE_MODEL_FIELDS if f in o.range_model.model_fields_set]
    return out


def _not_applicable(dataset, pb) -> Optional[str]:
    """Why the candidates do not describe this log (None: they do)."""
    tdoa = getattr(dataset, "tdoa", None)
    if pb.anchor_b is not None or (tdoa is not None and len(tdoa)):
        return "the log has TDoA rows: the selection has no TDoA candidate models"
    if pb.n_tags > 1:
        return "several tags: the candidates' direction term is one tag's"
    if any(pb.estimated(j) for j in range(len(pb.anchor_ids))):
        return ("anchor self-survey: a per-anchor bias and drift are confounded with the estimated anchor's distance "
                "along its mean line of sight")
    if not pb.options.group_range_factors:
        return "group_range_factors: false (the direction and drift terms need grouped range factors)"
    if len(pb.rho) == 0:
        return "the log has no two-way ranges"
    return None


def selection_mode(o, dataset, pb) -> tuple[str, Optional[str]]:
    """``(mode, reason)``: ``select`` (run the selection), ``given``, ``configured`` or ``not_applicable``.

    Raises
    ------
    UsageError : ``select: cv`` on a log the candidates cannot serve (TDoA, several tags, self-survey).
    """
    sel = o.range_model.select
    if sel == "given":
        return "given", None
    why = _not_applicable(dataset, pb)
    if sel == "cv" and why is not None:
        raise UsageError(f"calibrate: range_model.select: cv cannot serve this log ({why})",
                         hint="set range_model.select: given (or auto) and configure the range model")
    if why is not None:
        return "not_applicable", why
    conf = configured_model(o)
    if sel == "auto" and conf:
        return "configured", "configured by the user: " + ", ".join(conf)
    return "select", None


def solve_residuals(pb, solved) -> dict:
    """Range residuals about a solve's trajectory (:func:`select_on_residuals`' input).

    Each used row's residual is ``range - |p_U - a_j|`` with ``p_U`` the tag antenna at the range instant as the
    graph's range factor places it (keyframe state carried by the IMU deltas, the solve's lever arm and t_d): the
    range-model terms of the solve (constant bias, drift, direction) are not subtracted, the selection fits its own.

    Returns
    -------
    dict: ``t`` [s, UWB clock], ``anchor`` (index into ``anchors``, the anchor ids with ranges), ``r`` [m], ``wb``
    (n, 3) line of sight antenna -> anchor in the body frame [m], ``u`` (n, 3) unit line of sight antenna -> anchor,
    world frame; rows in time order.
    """
    fg, assoc, values = solved.graph, solved.assoc, solved.values
    td = solved.time_offset()
    n = len(assoc.used)
    u = np.full((n, 3), np.nan)
    wb = np.full((n, 3), np.nan)
    for fi, grp in assoc.groups.items():
        ks = fg.at(int(fi)).keys()
        geo = grp._geometry(*graph._group_states(grp, ks, values), graph._group_lever(grp, ks, values), td,
                            graph._group_apos(grp, ks, values))
        rows = np.flatnonzero(assoc.slots[:, 0] == fi)
        u[rows] = geo["u"][assoc.slots[rows, 1]]  # p_U - anchor, world
        wb[rows] = geo["wb"][assoc.slots[rows, 1]]
    ok = np.all(np.isfinite(u), axis=1)
    if not ok.any():
        raise InputError("range model selection: the solve has no grouped range rows")
    used = assoc.used[ok]
    dist = np.linalg.norm(u[ok], axis=1)
    order = np.argsort(pb.t_range[used], kind="stable")
    used, dist, los_u, los_b = used[order], dist[order], -u[ok][order], wb[ok][order]
    aj = pb.anchor_j[used]
    present = np.unique(aj)
    return {"t": pb.t_range[used].astype(float), "anchor": np.searchsorted(present, aj).astype(np.int64),
            "anchors": np.array([pb.anchor_ids[j] for j in present]), "r": pb.rho[used] - dist, "wb": los_b,
            "u": los_u / np.maximum(dist, 1e-9)[:, None]}


def warm_values(pb, values):
    """The start of ``pb``'s solve: ``values`` (a solve of the same keyframes) where it has the variable, the
    problem's initial values (zero range-model coefficients) for the variables it adds; variables ``pb`` does not
    have are dropped."""
    import gtsam

    init = graph.initial_values(pb)
    out = gtsam.Values(values)
    for k in list(out.keys()):
        if not init.exists(k):
            out.erase(k)
    extra = gtsam.Values(init)
    for k in list(extra.keys()):
        if out.exists(k):
            extra.erase(k)
    out.insert(extra)
    return out


def choose_and_resolve(start, o, built, solved, solve, events: list):
    """The stage: select on ``solved``'s residuals and solve with the chosen model (or record why not).

    Parameters
    ----------
    start : :class:`uwbimu.calibration.stages.Start` (its dataset and seeding ESKF build the new problem).
    o : the calibration options.
    built, solved : the problem and its free solve (after the second start).
    solve : ``solve(pb, imf, values, td0, assoc) -> Solved``, warm-started, t_d free.
    events : the event ``range_model_selected`` is appended when a model is chosen.

    Returns
    -------
    ``(o, built, solved, record)``: the options with the chosen model (as given when none was chosen), the
    problem and solve under them, and calibration.yaml's ``range_model.selection`` (the selection's record with
    ``select: cv``, else ``{select: given | configured | not_applicable, reason}``; ``not_applicable`` also when
    the log is too short for the time blocks, which with ``select: cv`` raises).

    Raises
    ------
    InputError : ``select: cv`` on a log too short for its time blocks.
    """
    mode, why = selection_mode(o, start.dataset, built.problem)
    if mode != "select":
        return o, built, solved, {"select": mode, **({"reason": why} if why else {})}
    # the graph's threshold stays huber_k's rule (adaptive: chosen on the re-solve's residuals in the graph's own
    # sigma units, robust_loss; a number: kept): the selection's k is in units of its fitted innovation sd, not of
    # range_sigma.  A numeric huber_k is also the only threshold the families are compared at.
    grid = HUBER_GRID if o.huber_k == "adaptive" else (float(o.huber_k),)
    try:
        sel: RangeModelSelection = select_on_residuals(solve_residuals(built.problem, solved), o, huber_grid=grid,
                                                       basis="free_solve")
    except InputError as exc:
        if o.range_model.select == "cv":
            raise
        # too short for the cross-validation (a time block with fewer than MIN_BLOCK_ROWS ranges): the log cannot
        # choose, the configured model is kept
        return o, built, solved, {"select": "not_applicable", "reason": str(exc)}
    o2 = apply_selection(o, sel, huber=False)
    o2.check_log(start.dataset)
    record = {"select": "cv", **sel.as_dict()}
    events.append({"kind": "range_model_selected", "severity": "info", **sel.as_dict(),
                   "message": f"range model chosen on the log (held-out likelihood over {sel.folds} time blocks, "
                              f"residuals about the batch's free solve): {sel.chosen}"})
    pb2 = graph.build_problem(start.dataset, start.eskf, o2, start.setup)
    # the IMU factors depend on the keyframes, the seeding ESKF's biases and the IMU noise only: kept
    built2 = dataclasses.replace(built, problem=pb2)
    solved2 = solve(pb2, built2.imu_factors, warm_values(pb2, solved.values), solved.time_offset(), None)
    return o2, built2, solved2, record
