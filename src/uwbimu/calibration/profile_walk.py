"""The solves of the batch calibrator: a free or t_d-fixed solve with re-association (:func:`_solve`), and
the time-offset profile walked over its grid (:func:`run_profile`), on the Monte Carlo executors when asked.

Split from :mod:`uwbimu.calibration.batch` (which orchestrates them); the verdict and the profile's own
arithmetic are in :mod:`uwbimu.calibration.profile`.
"""

from __future__ import annotations

from typing import Callable, Optional

import numpy as np

from uwbimu.calibration import keys
from uwbimu.calibration.graph import _imu_factors, associate, build_graph, optimize, without_td
from uwbimu.calibration.profile import TdProfile, profile_verdict
from uwbimu.calibration.stages import Solved


def solve(pb, imf, values, td0: float, td_fixed: Optional[float], assoc=None, predicted_tol: Optional[float] = None,
          engine: str = "python", rows=None) -> Solved:
    """Solve with ranges attached about ``td0``; re-attach while free t_d moves > half a keyframe step.

    ``assoc``: an association to reuse for the first solve (within half a keyframe step of its ``td0``
    the factor's second-order extrapolation in ``t_d - td0`` covers the motion).
    ``predicted_tol``, ``engine``: see :func:`uwbimu.calibration.graph.optimize`; ``rows``: the ranges
    to use (:func:`uwbimu.calibration.graph.associate`).

    Parameters
    ----------
    pb, imf : the problem and its IMU factors (:class:`uwbimu.calibration.stages.Built`).
    values : the start (``gtsam.Values``; without ``t(0)`` when ``td_fixed`` is given).
    td0 : t_d [s] the ranges are first attached about.
    td_fixed : t_d [s] held fixed (profile points, t_d held at its prior), or None (t_d estimated).

    Returns
    -------
    :class:`uwbimu.calibration.stages.Solved`.
    """
    half = 0.5 / pb.options.keyframe_hz
    for _ in range(pb.options.reassociate_max + 1):
        if assoc is None or abs(assoc.td0 - td0) > half:
            assoc = associate(pb, td0, rows=rows)
        graph = build_graph(pb, assoc, td_fixed=td_fixed, imu_factors=imf)
        values, iters = optimize(graph, values, pb.options.max_iterations, predicted_tol=predicted_tol,
                                 engine=engine)
        if td_fixed is not None:
            break
        td = float(values.atVector(keys.time_offset())[0])
        if abs(td - assoc.td0) <= half:
            break
        td0 = td
    return Solved(graph=graph, values=values, assoc=assoc, iterations=int(iters))


def _solve(pb, imf, values, td0: float, td_fixed: Optional[float], assoc=None, predicted_tol: Optional[float] = None,
           engine: str = "python", rows=None) -> tuple:
    """:func:`solve` as the tuple ``(graph, values, assoc, iterations)`` (tests and benchmarks address it)."""
    return solve(pb, imf, values, td0, td_fixed, assoc, predicted_tol, engine, rows).astuple()


def _profile_grid_points(mu: float, half: float, step: float) -> np.ndarray:
    n = int(round(half / step))
    return np.round(mu + step * np.arange(-n, n + 1), 12)


#: Profile-point stop rule of the fast profile [chi-square units]: a point's solve stops once the decrease
#: still expected (see :func:`uwbimu.calibration.graph.optimize`, ``predicted_tol``) is below this.  The
#: verdict's threshold is 9 and the curvature fit reads differences of tens: 0.02 is far below both.
PROFILE_CHI2_TOL = 0.02


def profile_rows(pb, lo: float, hi: float) -> np.ndarray:
    """Indices of the ranges whose IMU instant ``t + t_d`` lies inside the IMU span for every ``t_d`` in
    ``[lo, hi]`` [s]: the data every profile point uses.

    Without this common set a range near either end of the log would count at some grid points and not
    at others: on the 190 s INRoL log the used ranges fall from 32420 at ``t_d = 0`` to 32333 at
    +/-0.5 s, about 0.8 chi-square each: a tent in the profile with a kink at 0, whose slope shifts the
    vertex (estimated ~1.4 ms there; more on short windows, whose curvature is smaller).
    """
    return np.flatnonzero((pb.t_range + lo >= pb.t_key[0]) & (pb.t_range + hi < pb.t_imu[-1]))


#: The fast profile extrapolates a point's start along the last two solutions only when its distance from the
#: last point is at most this multiple of theirs: a walk's first step leaves a free solution a fraction of a
#: millisecond from the first grid point, and a secant scaled by hundreds sent the INRoL solve (IMU noise
#: scale 24) into a wrong minimum (chi2 +98 000, then every later point of the walk warm-started from it).
PROFILE_MAX_EXTRAPOLATION = 2.0

#: Zoom of a profile whose confidence set is one grid point (:func:`run_profile`): step divisor, number of
#: zoom passes at most, smallest step [s].
PROFILE_ZOOM, PROFILE_ZOOM_LEVELS, PROFILE_MIN_STEP = 5, 3, 1e-4


def _walk(pb, imf, points, start, prev, mode: str = "fast", on_point=None, rows=None) -> list:
    """Solve the profile points in the given order, each warm-started from the previous one.

    Every point attaches the ranges ``rows`` at its own t_d (no reuse of a neighbour's association:
    its extrapolation in ``t_d - td0`` changes chi2 by up to ~1 at 0.04 s on INRoL, more than the
    solver tolerance), so a point's value does not depend on the walk that reached it.

    Parameters
    ----------
    points : t_d values [s], in walking order.
    start : ``(t_d, values)`` the walk starts from (values without ``T(0)``).
    prev : ``(t_d, values)`` one step further back, or None.
    mode : ``fast``: the start of each point is extrapolated along the path of the last two solutions
        (secant in the tangent space) and the solve stops on :data:`PROFILE_CHI2_TOL`; ``reference``:
        each point warm-started from the previous solution and solved to GTSAM's convergence rule
        (relative decrease 1e-6) with GTSAM's own optimizer (the full-solve profile).
    on_point : called after each point.
    rows : the ranges used (:func:`profile_rows`); None: all inside the IMU span at each point.

    Returns
    -------
    list of ``(t_d, chi2, iterations, values)`` in walking order.
    """
    o = pb.options
    mu = o.time_offset_prior
    fast = mode == "fast"
    tol = 0.5 * PROFILE_CHI2_TOL if fast else None  # graph cost = chi2 / 2
    engine = "python" if fast else "gtsam"
    out = []
    for g in points:
        g = float(g)
        init = start[1]
        ratio = (g - start[0]) / (start[0] - prev[0]) if prev is not None and start[0] != prev[0] else 0.0
        extrapolated = fast and 0.0 < abs(ratio) <= PROFILE_MAX_EXTRAPOLATION
        if extrapolated:
            step = prev[1].localCoordinates(start[1])  # prev -> start, in start's tangent convention
            step.scaleInPlace(ratio)
            init = start[1].retract(step)
        graph, vals, _assoc, it = _solve(pb, imf, init, g, g, None, predicted_tol=tol, engine=engine, rows=rows)
        if extrapolated and it >= o.max_iterations:
            # the extrapolated start led the solve astray (it ran out of iterations): start again from the
            # previous point's solution and keep the better of the two
            g2, v2, _a2, it2 = _solve(pb, imf, start[1], g, g, None, predicted_tol=tol, engine=engine, rows=rows)
            if g2.error(v2) < graph.error(vals):
                graph, vals = g2, v2
            it += it2
        chi2 = 2.0 * graph.error(vals) + ((g - mu) / o.time_offset_prior_sd) ** 2
        out.append((g, chi2, it, vals))
        prev, start = start, (g, vals)
        if on_point is not None:
            on_point()
    return out


#: Per worker process: the last problem shipped to it (token, problem, IMU factors), so that the walks of
#: one calibration that land on the same worker rebuild the IMU factors once.
_WORKER_PROBLEM: dict = {}


def _light_problem(pb):
    """Copy of the problem without its caches (GTSAM factors, cumulative IMU deltas): what a task ships."""
    import dataclasses

    return dataclasses.replace(pb, _drift_factors=None, _imu_cum=None)


def _walk_task(task):
    """Executor task: one profile walk in a worker process; returns its points, with the values of the best."""
    token, pb, points, start, prev, mode, rows = task
    if _WORKER_PROBLEM.get("token") != token:
        _WORKER_PROBLEM.clear()
        _WORKER_PROBLEM.update(token=token, pb=pb, imf=_imu_factors(pb))
    pb, imf = _WORKER_PROBLEM["pb"], _WORKER_PROBLEM["imf"]
    return _keep_best(_walk(pb, imf, points, start, prev, mode, rows=rows))


def _keep_best(points: list) -> list:
    """The walk's points with the solution values dropped except at its lowest chi2 (what the caller reads)."""
    if not points:
        return points
    i = min(range(len(points)), key=lambda k: points[k][1])
    return [(g, c, it, v if k == i else None) for k, (g, c, it, v) in enumerate(points)]


def _run_walks(pb, imf, walks: list, mode: str, workers: int, executor: Optional[dict], on_point, rows,
               token: Optional[str] = None) -> list:
    """Run independent walks ``(points, start, prev)``: here in order (``workers == 1``, no pickling) or on the
    Monte Carlo executors (:func:`uwbimu.parallel.execute`), one task per walk.  Same points, same
    warm starts either way, so the same values.  Returns the concatenated points.

    ``token`` names the problem in the workers' cache (:data:`_WORKER_PROBLEM`): the passes of one profile
    share it, so a worker of a kept pool builds the IMU factors once; None: a new one."""
    walks = [w for w in walks if len(w[0])]
    if workers == 1 and not executor:
        out = []
        for points, start, prev in walks:
            out += _keep_best(_walk(pb, imf, points, start, prev, mode, on_point, rows))
        return out
    import uuid

    from uwbimu.errors import EstimationError
    from uwbimu.parallel import execute

    token = token or uuid.uuid4().hex
    # this process runs walks too (execute(caller=True)): it has the problem's IMU factors already
    if _WORKER_PROBLEM.get("token") != token:
        _WORKER_PROBLEM.clear()
        _WORKER_PROBLEM.update(token=token, pb=pb, imf=imf)
    pool = (executor or {}).get("pool")
    if pool is not None and pool.executor is None:
        # started now that this process holds the problem: forked workers inherit it (no rebuild there)
        pool.start()
    light = _light_problem(pb)
    got: dict[int, list] = {}
    tasks = [(i, (token, light, [float(g) for g in w[0]], w[1], w[2], mode, rows)) for i, w in enumerate(walks)]

    def keep(res):
        i, pts = res
        got[i] = pts
        for _ in pts:
            if on_point is not None:
                on_point()

    failed = execute(_indexed_walk_task, tasks, keep, workers=workers, describe=lambda t: f"t_d profile walk {t[0]}",
                     preload=("uwbimu.calibration.profile_walk",),
                     **({"caller": True} if _local(executor) else {}), **(executor or {}))
    if failed:
        raise EstimationError("t_d profile: " + "; ".join(failed))
    return [p for i in range(len(walks)) for p in got[i]]


def _local(executor: Optional[dict]) -> bool:
    """The walks run on a local process pool (not Dask): the caller then walks too (``execute(caller=True)``:
    a pool's workers start cold, seconds of imports and IMU factors, while this process is warm)."""
    ex = executor or {}
    return not (ex.get("client") is not None or ex.get("scheduler") or ex.get("dask_local"))


def _indexed_walk_task(task):
    i, t = task
    return i, _walk_task(t)


def run_profile(pb, imf, free_values, centre: float, progress=None, workers: int = 1,
                executor: Optional[dict] = None, mode: str = "fast", chi2_scale: float = 1.0,
                on_point: Optional[Callable[[int, int], None]] = None) -> TdProfile:
    """Profile of t_d on the grid ``prior +/- half_width``, warm-started outward from ``centre``.

    With ``td_profile.coarse_step`` larger than ``step``: first the whole range at ``coarse_step``,
    then ``step`` within one coarse step either side of the coarse minimum (warm-started from it);
    the verdict reads the union of both (a non-uniform grid).  Otherwise the uniform ``step`` grid.

    Zoom: while the verdict is ``identified`` but its confidence set (``chi2 - min < confidence_chi2``) is
    a single grid point, the profile is sharper than the step (long logs: 10 minutes give sigma ~1 ms
    against a 20 ms step); five points at a step :data:`PROFILE_ZOOM` times finer, centred on the
    parabola vertex, are added (up to :data:`PROFILE_ZOOM_LEVELS` times, not below
    :data:`PROFILE_MIN_STEP`).  Without it the interval read off the grid is far too narrow and the
    free refinement lands outside it (``refinement_left_confidence_set``, t_d held at its prior).

    Each pass is two walks, upward and downward from its start (the free solution at ``centre``, then
    the coarse minimum), each point warm-started from its predecessor (:func:`_walk`, ``mode``).  The
    walks are independent: ``workers > 1`` (or ``executor``: keyword arguments of
    :func:`uwbimu.parallel.execute`, e.g. ``{"dask_local": True}``) runs them as tasks on the
    Monte Carlo executors, ``workers == 1`` here; the points and values are the same either way (at
    most two walks run at once, so more than 2 workers gain nothing here).

    ``chi2_scale``: the honesty correction of the white-noise profile (:func:`_profile_chi2_scale`); the zoom
    decision and the verdict both read the scaled profile (:func:`profile_verdict`).

    ``progress``: called with the overall fraction of :func:`uwbimu.calibration.calibrate` (0.2 to 0.8 here);
    ``on_point``: called ``(points solved, points planned)`` after each point (the zoom adds planned points).
    """
    if workers != 1 and not executor:
        # one local pool for every pass (coarse, fine, zooms): its workers keep the problem and IMU factors
        # (_WORKER_PROBLEM) from the first pass instead of rebuilding them in a new pool per pass
        from uwbimu.parallel import ProcessPool

        with ProcessPool(workers, preload=("uwbimu.calibration.profile_walk",), caller=True, lazy=True) as pool:
            try:
                return run_profile(pb, imf, free_values, centre, progress, workers, {"pool": pool}, mode,
                                   chi2_scale, on_point)
            finally:
                _WORKER_PROBLEM.clear()  # this process's copy (the caller walked too)
    import uuid

    token = uuid.uuid4().hex  # one problem for every pass (the workers' cache key)
    po = pb.options.td_profile
    o = pb.options
    mu = o.time_offset_prior
    base = without_td(free_values)
    found: dict = {}  # grid point -> (chi2, iterations, values or None)
    total = [1]

    def point_done():
        total[0] += 1
        if progress is not None:
            progress(0.2 + 0.6 * min(1.0, total[0] / n_total))
        if on_point is not None:
            on_point(total[0] - 1, n_total)

    def walks_from(points, start_t, start_vals):
        points = np.asarray(points, float)
        i0 = int(np.argmin(np.abs(points - start_t)))
        up, down = points[i0:], points[:i0][::-1]
        return [(up, (start_t, start_vals), None), (down, (start_t, start_vals), None)]

    def record(pts):
        for g, c, it, v in pts:
            found[g] = (c, it, v)

    ends = _profile_grid_points(mu, po.half_width, po.coarse_step if po.coarse_step else po.step)[[0, -1]]
    rows = profile_rows(pb, float(min(ends[0], mu - po.half_width)), float(max(ends[-1], mu + po.half_width)))
    if po.coarse_step is not None and po.coarse_step > po.step:
        coarse = _profile_grid_points(mu, po.half_width, po.coarse_step)
        m = int(round(po.coarse_step / po.step))
        n_total = len(coarse) + 2 * m
        record(_run_walks(pb, imf, walks_from(coarse, centre, base), mode, workers, executor, point_done, rows,
                          token))
        best = min(found, key=lambda g: found[g][0])
        fine = np.round(best + po.step * np.arange(-m, m + 1), 12)
        fine = fine[(fine >= coarse[0]) & (fine <= coarse[-1]) & ~np.isin(fine, list(found))]
        n_total = len(coarse) + len(fine)  # the points the fine pass really solves (progress only)
        start = (best, found[best][2])
        fw = [(fine[fine > best], start, None), (fine[fine < best][::-1], start, None)]
        record(_run_walks(pb, imf, fw, mode, workers, executor, point_done, rows, token))
    else:
        grid = _profile_grid_points(mu, po.half_width, po.step)
        n_total = len(grid)
        record(_run_walks(pb, imf, walks_from(grid, centre, base), mode, workers, executor, point_done, rows,
                          token))
    step = po.step
    for _level in range(PROFILE_ZOOM_LEVELS):
        grid = np.array(sorted(found))
        chi2 = np.array([found[g][0] for g in grid])
        verdict, best, vertex, sig = profile_verdict(grid, chi2, po.confidence_chi2, chi2_scale=chi2_scale)
        if verdict != "identified" or np.sum(chi2_scale * (chi2 - chi2.min()) < po.confidence_chi2) > 1:
            break
        # The confidence set is one grid point: the profile is sharper than the step (a long log), its
        # interpolated interval too narrow and the vertex a fit over points tens of sigma out.  Zoom in.
        step /= PROFILE_ZOOM
        if step < PROFILE_MIN_STEP:
            break
        c = np.round(vertex / step) * step
        zoom = np.round(c + step * np.arange(-2, 3), 12)
        zoom = zoom[(zoom > grid[0]) & (zoom < grid[-1]) & ~np.isin(zoom, grid)]
        n_total += len(zoom)
        start = (best, found[best][2])
        zw = [(np.sort(zoom[zoom > best]), start, None), (np.sort(zoom[zoom < best])[::-1], start, None)]
        record(_run_walks(pb, imf, zw, mode, workers, executor, point_done, rows, token))
    grid = np.array(sorted(found))
    chi2 = np.array([found[g][0] for g in grid])
    iters = np.array([found[g][1] for g in grid], int)
    verdict, best, vertex, sig = profile_verdict(grid, chi2, po.confidence_chi2, chi2_scale=chi2_scale)
    return TdProfile(grid=grid, chi2=chi2, iterations=iters, verdict=verdict, best=best, vertex=vertex,
                     sigma_curvature=sig, confidence_chi2=po.confidence_chi2)
