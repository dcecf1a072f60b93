"""Optimisers for anchor placement: a minimal seeded PSO (seed reproduction only),
scipy differential evolution (maintained, seeded, ``workers``), and greedy / local
search helpers for structures.

The PSO exists only to reproduce the seed's set-up (it used particle swarm
optimisation); ``pyswarms`` is unmaintained, so this is a ~40-line global-best PSO
with Clerc–Kennedy constriction coefficients (w = 0.7298, c1 = c2 = 1.49618),
velocity clamped to 20 % of each variable's range, positions clipped to the bounds,
and every random draw from one ``numpy.random.default_rng(seed)``.
"""

from __future__ import annotations

from typing import Callable, Sequence

import numpy as np
from scipy.optimize import differential_evolution

__all__ = ["pso", "differential_evolution_opt", "greedy_structure", "local_search_structure"]


def pso(
    f: Callable[[np.ndarray], float],
    bounds: Sequence[tuple[float, float]],
    n_particles: int = 24,
    iters: int = 40,
    seed: int = 0,
    callback: Callable[[int, float], None] | None = None,
    x0: np.ndarray | None = None,
) -> dict:
    """Minimise ``f`` over a box with a global-best particle swarm.

    Returns a dict with ``x``, ``fun``, ``nfev``, ``history`` (best value per iteration).
    """
    rng = np.random.default_rng(seed)
    lo = np.array([b[0] for b in bounds], dtype=float)
    hi = np.array([b[1] for b in bounds], dtype=float)
    span = hi - lo
    x = lo + rng.random((n_particles, len(lo))) * span
    if x0 is not None:
        x[0] = np.clip(x0, lo, hi)
    vmax = 0.2 * span
    v = (rng.random(x.shape) * 2.0 - 1.0) * vmax
    fx = np.array([f(xi) for xi in x])
    pbest, pval = x.copy(), fx.copy()
    g = int(np.argmin(pval))
    gbest, gval = pbest[g].copy(), float(pval[g])
    w, c1, c2 = 0.7298, 1.49618, 1.49618
    history, nfev = [gval], n_particles
    for it in range(iters):
        r1, r2 = rng.random(x.shape), rng.random(x.shape)
        v = np.clip(w * v + c1 * r1 * (pbest - x) + c2 * r2 * (gbest - x), -vmax, vmax)
        x = np.clip(x + v, lo, hi)
        fx = np.array([f(xi) for xi in x])
        nfev += n_particles
        better = fx < pval
        pbest[better], pval[better] = x[better], fx[better]
        g = int(np.argmin(pval))
        if pval[g] < gval:
            gbest, gval = pbest[g].copy(), float(pval[g])
        history.append(gval)
        if callback is not None:
            callback(it + 1, gval)
    return {"x": gbest, "fun": gval, "nfev": nfev, "history": history}


def differential_evolution_opt(
    f: Callable[[np.ndarray], float],
    bounds: Sequence[tuple[float, float]],
    seed: int = 0,
    maxiter: int = 30,
    popsize: int = 10,
    workers: int = 1,
    x0: np.ndarray | None = None,
    callback: Callable[[int, float], None] | None = None,
    tol: float = 0.0,
    polish: bool = False,
    init_sigma: np.ndarray | float | None = None,
) -> dict:
    """scipy ``differential_evolution`` with reproducible settings.

    ``init_sigma`` (with ``x0``): start from a Gaussian cloud of that standard
    deviation (per variable) around ``x0`` instead of a Latin hypercube over the box —
    a local refinement of a good discrete solution.
    ``workers > 1`` evaluates the population in a process pool (``f`` must be
    picklable, e.g. :class:`uwbimu.design.structures.StructureProblem`); with
    ``updating="deferred"`` the result is identical for any number of workers.
    Returns a dict with ``x``, ``fun``, ``nfev``, ``nit``, ``population``,
    ``population_energies``.
    """
    it = [0]
    if x0 is not None:
        # scipy rescales x0 to [0, 1] and rejects round-off just outside: nudge inside.
        b = np.asarray(bounds, dtype=float)
        pad = 1e-9 * (b[:, 1] - b[:, 0])
        x0 = np.clip(np.asarray(x0, dtype=float), b[:, 0] + pad, b[:, 1] - pad)
    init = "latinhypercube"
    if x0 is not None and init_sigma is not None:
        r = np.random.default_rng(seed + 7919)  # separate stream from DE's own
        n_pop = max(5, popsize * len(x0))
        cloud = x0 + r.normal(size=(n_pop, len(x0))) * np.asarray(init_sigma, dtype=float)
        init = np.clip(cloud, b[:, 0] + pad, b[:, 1] - pad)
        init[0] = x0
        x0 = None

    def cb(intermediate_result):
        it[0] += 1
        if callback is not None:
            callback(it[0], float(intermediate_result.fun))

    res = differential_evolution(
        f,
        bounds,
        maxiter=maxiter,
        popsize=popsize,
        rng=np.random.default_rng(seed),
        tol=tol,
        polish=polish,
        init=init,
        updating="deferred",
        workers=workers,
        x0=x0,
        callback=cb,
    )
    return {
        "x": np.asarray(res.x),
        "fun": float(res.fun),
        "nfev": int(res.nfev),
        "nit": int(res.nit),
        "population": np.asarray(res.population),
        "population_energies": np.asarray(res.population_energies),
    }


def greedy_structure(problem, step: float = 1.0, rotations: Sequence[float] = (0.0,), callback=None) -> dict:
    """Greedy station placement on a :class:`StructureProblem` (its rails and counts).

    Adds one station at a time, choosing among slide positions every ``step`` metres
    (and the given rotations) the one that maximises the submodular surrogate
    ``sum_p min(count_p, k)`` (each added link counts until a point is k-covered),
    respecting the per-rail station counts.  Returns the decision vector ``x`` (in
    the problem's layout; tilts 0), the order in which stations were added and the
    k-coverage after each addition (marginal value curve).
    """
    from uwbimu.design.radio import count_links_grid

    st = problem.structure
    k = problem.k
    counts = np.zeros(problem.n_points, dtype=np.int32)
    remaining = list(problem.spr)
    chosen: list[tuple[int, float, float]] = []
    curve = []
    cand = [(r, s, rot) for r, rail in enumerate(st.rails) for s in np.arange(0.0, rail.length + 1e-9, step) for rot in rotations]
    cache: dict[tuple, np.ndarray] = {}

    def station_counts(c):
        if c not in cache:
            pos, bor = st.rails[c[0]].station(c[1], problem.station_rotation + c[2], 0.0)
            cache[c] = count_links_grid(problem.axes, pos, bor, problem.lut, problem.sphere).astype(np.int8)
        return cache[c]

    for step_i in range(problem.n_stations):
        base = np.minimum(counts, k).sum()
        best, best_gain = None, -1
        for c in cand:
            if remaining[c[0]] == 0:
                continue
            gain = np.minimum(counts + station_counts(c), k).sum() - base
            if gain > best_gain:
                best, best_gain = c, gain
        counts += station_counts(best)
        remaining[best[0]] -= 1
        chosen.append(best)
        curve.append(float(np.count_nonzero(counts >= k)) / counts.shape[0])
        if callback is not None:
            callback(step_i + 1, curve[-1])
    # Lay the chosen stations out in the problem's decision-vector order (rail by rail).
    n = problem.n_stations
    x = np.zeros(len(problem.bounds))
    slots = {r: [i for i, rr in enumerate(problem.station_rails) if rr == r] for r in range(len(st.rails))}
    for r, s, rot in sorted(chosen):
        i = slots[r].pop(0)
        x[i] = s
        if problem.per >= 2:
            x[n + i] = rot
    return {"x": x, "order": chosen, "curve": curve}


def local_search_structure(problem, x, steps=(4.0, 2.0, 1.0), angle_steps=(0.2, 0.1), max_rounds: int = 3, callback=None) -> dict:
    """Coordinate pattern search on the true objective (``1 - coverage``).

    Tries moving each variable by ``+-step`` (slides, m) or ``+-angle_step`` (rad),
    keeps any improvement, shrinking the step when a round finds none.
    """
    x = np.array(x, dtype=float)
    lo = np.array([b[0] for b in problem.bounds])
    hi = np.array([b[1] for b in problem.bounds])
    fx = problem(x)
    n = problem.n_stations
    nfev = 1
    for step_s, step_a in zip(steps, list(angle_steps) + [angle_steps[-1]] * len(steps)):
        for _ in range(max_rounds):
            improved = False
            for i in range(len(x)):
                d = step_s if i < n else step_a
                for sgn in (1.0, -1.0):
                    y = x.copy()
                    y[i] = np.clip(y[i] + sgn * d, lo[i], hi[i])
                    if y[i] == x[i]:
                        continue
                    fy = problem(y)
                    nfev += 1
                    if fy < fx - 1e-12:
                        x, fx, improved = y, fy, True
                        break
            if callback is not None:
                callback(nfev, fx)
            if not improved:
                break
    return {"x": x, "fun": float(fx), "nfev": nfev}
