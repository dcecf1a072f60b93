"""Run a placement config (room or structure) and write its outputs.

``run_placement(cfg)`` returns a result dict; ``write_outputs(result, out)`` writes
``placement.json``, ``anchors.csv`` (dataset format), and the plots, all atomically.
Built-in examples: :func:`builtin_example` (``room``, ``crane``, ``bridge``).
"""

from __future__ import annotations

from uwbimu.errors import ConfigError, UsageError
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd

from uwbimu.design.config import PlacementConfig
from uwbimu.design.lint import lint_layout
from uwbimu.design.metrics import pdop as metrics_pdop
from uwbimu.design.metrics import tdoa_pdop
from uwbimu.design.placement import (
    CandidateSet,
    LayoutEvaluator,
    Room,
    RoomObjective,
    lazy_greedy_logdet,
    obstacles_from_config,
    pareto_front,
    refine_de,
    swap_search,
)
from uwbimu.design.radio import CosN, LinkModel, Omni, RANGE_PRESETS, count_links_grid, load_pattern_csv

__all__ = ["builtin_example", "EXAMPLES", "run_placement", "write_outputs", "link_model_from_config",
           "room_evaluator", "room_setup"]

SEED_COVERAGE = 0.913  # the seed's published jib-crane coverage with 40 modules
GEOMETRIC_PDOP_MAX = 5.0  # room "geometric coverage": k-covered AND PDOP <= this
CRANE_R0_CALIBRATED = 26.7  # see docs/placement.md: seed set-up (PSO) reproduces ~91 % at this range
# R0 fitted per reading of the crane's stations (benchmarks/crane_readings.py; docs/placement.md section 4)
CRANE_R0_FITTED = {"diagonal": CRANE_R0_CALIBRATED, "axis-aligned": 22.43}

EXAMPLES: dict[str, dict] = {
    "room": {
        "mode": "room",
        "seed": 0,
        "n_anchors": 6,
        "radio": {"preset": "dw1000-indoor", "antenna": {"type": "omni"}, "range_sigma": 0.1, "k": 3},
        "room": {
            "box": [10.0, 8.0, 3.0],
            "mount": {"surfaces": ["walls", "ceiling", "floor"], "standoff": 0.2, "spacing": 1.0},
            "flight_volume": {"lo": [0.5, 0.5, 0.3], "hi": [9.5, 7.5, 2.5]},
            "grid_step": 0.5,
        },
        # hull: the practitioner rule "tags inside the anchors' hull" as a penalty (see docs/placement.md;
        # examples/placement/room_pdop_only.yaml drops it: better PDOP, 61 % of the volume outside the hull)
        "objective": {"weights": {"coverage": 10.0, "pdop": 1.0, "n1_pdop": 0.25, "hull": 0.05}, "percentile": 95,
                      "pareto": True},
        "optimizer": {"greedy": True, "swaps": True, "swap_rounds": 2, "refine": True, "maxiter": 20, "popsize": 8,
                      "workers": 1},
        "compare": {
            "all-on-ceiling": [[x, y, 2.8] for x in (0.2, 5.0, 9.8) for y in (0.2, 7.8)],
            "bitcraze-3-high-3-low": [[0.2, 0.2, 2.8], [5.0, 0.2, 0.2], [9.8, 0.2, 2.8],
                                      [9.8, 7.8, 0.2], [5.0, 7.8, 2.8], [0.2, 7.8, 0.2]],
        },
    },
    "crane": {
        "mode": "structure",
        "seed": 0,
        "n_anchors": 40,
        "structure": {"name": "jib-crane", "range_m": CRANE_R0_CALIBRATED, "beamwidth_deg": 90.0,
                      "stations_per_rail": [5, 5], "freedom": "rotate-tilt", "reproduce_seed": True,
                      "pso_particles": 24, "pso_iters": 40},
    },
    "bridge": {
        "mode": "structure",
        "seed": 0,
        "n_anchors": 16,
        "structure": {"name": "bridge", "range_m": 30.0, "beamwidth_deg": 90.0, "stations_per_rail": [1, 1, 1, 1],
                      "freedom": "rotate-tilt", "reproduce_seed": True, "pso_particles": 16, "pso_iters": 25},
    },
}


def builtin_example(name: str) -> PlacementConfig:
    if name not in EXAMPLES:
        raise UsageError(f"unknown example {name!r}; choose one of {', '.join(map(str, sorted(EXAMPLES)))}")
    return PlacementConfig.model_validate(EXAMPLES[name])


# --------------------------------------------------------------------------- helpers
class _Progress:
    """Thin wrapper over rich.progress (or silent)."""

    def __init__(self, enabled: bool):
        self.enabled = enabled
        self._p = None

    def __enter__(self):
        if self.enabled:
            from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

            self._p = Progress(TextColumn("{task.description}"), BarColumn(), TextColumn("{task.fields[info]}"),
                               TimeElapsedColumn(), transient=False)
            self._p.__enter__()
        return self

    def __exit__(self, *exc):
        if self._p is not None:
            self._p.__exit__(*exc)

    @contextmanager
    def task(self, description: str, total: int):
        if self._p is None:
            yield lambda i, info="": None
            return
        t = self._p.add_task(description, total=total, info="")

        def update(i, info=""):
            self._p.update(t, completed=min(i, total), info=str(info))

        yield update
        self._p.update(t, completed=total)


def link_model_from_config(radio, obstacles=()) -> LinkModel:
    ant = radio.antenna
    if ant.type == "omni":
        pat = Omni(ant.gain_dbi)
    elif ant.type == "cosn":
        pat = CosN(ant.beamwidth_deg, ant.peak_gain_dbi, ant.front_to_back_db)
    else:
        pat = load_pattern_csv(ant.csv)
    r0 = radio.max_range if radio.max_range is not None else RANGE_PRESETS[radio.preset]
    return LinkModel(max_range=r0, anchor_pattern=pat, tag_gain_dbi=radio.tag_gain_dbi,
                     nlos_loss_db=radio.nlos_loss_db, obstacles=list(obstacles))


def _ids(n: int) -> list[str]:
    return [f"A{i + 1}" for i in range(n)]


def _toward(points, anchors) -> np.ndarray:
    c = np.asarray(points).mean(axis=0)
    d = c - np.asarray(anchors, float)
    n = np.linalg.norm(d, axis=1, keepdims=True)
    return np.where(n > 1e-9, d / np.maximum(n, 1e-9), np.array([0.0, 0.0, -1.0]))


def _single_failures(ev: LayoutEvaluator, anchors, bores, ids) -> tuple[dict, list[dict]]:
    rows = []
    for i in range(len(anchors)):
        keep = [j for j in range(len(anchors)) if j != i]
        c = ev.evaluate(anchors[keep], bores[keep], n1=False)
        rows.append({"anchor": ids[i], "coverage": c["coverage"], "pdop_p95": c["pdop_p95"]})
    worst = max(rows, key=lambda r: (r["pdop_p95"], -r["coverage"])) if rows else {}
    return worst, rows


# --------------------------------------------------------------------------- room mode
def room_evaluator(cfg: PlacementConfig, points, link: LinkModel, measurement: str | None = None) -> LayoutEvaluator:
    """The room objective of ``cfg`` over ``points`` for ``measurement`` (default: the config's).

    ``twr`` uses ``radio.range_sigma``, ``tdoa`` ``radio.tdoa_sigma`` (default sqrt(2) range
    sd); ``k`` is ``radio.k`` (at least 4 for TDoA, where a 3-D fix needs 4 anchors in range).
    """
    m = cfg.measurement if measurement is None else measurement
    oc = cfg.objective
    sigma = cfg.radio.tdoa_sigma_m if m == "tdoa" else cfg.radio.range_sigma
    k = max(cfg.radio.k, 4) if m == "tdoa" else cfg.radio.k
    return LayoutEvaluator(points, link, k, oc.percentile, oc.pdop_cap, dict(oc.weights), sigma, m)


def room_setup(cfg: PlacementConfig) -> tuple[Room, np.ndarray, LinkModel, list]:
    """Room, tag samples (P, 3) [m], link model and obstacles of a room-mode config."""
    rc = cfg.room
    obstacles = obstacles_from_config(rc.obstacles)
    if rc.box is not None:
        room = Room.box(*rc.box, obstacles=obstacles)
    else:
        room = Room(np.asarray(rc.polygon, float), float(rc.height), obstacles)
    link = link_model_from_config(cfg.radio, obstacles)
    fv = rc.flight_volume
    points = room.flight_points(fv.lo if fv else None, fv.hi if fv else None, rc.grid_step)
    if len(points) < 4:
        raise ConfigError(f"flight volume holds only {len(points)} tag samples; enlarge it or lower room.grid_step")
    return room, points, link, obstacles


def _run_room(cfg: PlacementConfig, progress: bool) -> dict:
    rc = cfg.room
    room, points, link, obstacles = room_setup(cfg)
    oc = cfg.objective
    ev = room_evaluator(cfg, points, link)
    timings = {}
    if rc.candidates is not None:
        pos = np.asarray(rc.candidates, float)
        bad = np.flatnonzero(~room.contains(pos))
        if len(bad):
            raise ConfigError(f"room.candidates[{bad[0]}] = {pos[bad[0]].tolist()} lies outside the room "
                             f"({len(bad)} candidate(s) outside)")
        bor = _toward(points, pos)
        sid = np.full(len(pos), -1)
        par, surfs, dropped = None, [], 0
    else:
        m = rc.mount
        pos, bor, sid, par, surfs, dropped = room.candidates(m.surfaces, m.standoff, m.spacing, m.z_min, m.z_max)
    if len(pos) < cfg.n_anchors:
        raise ConfigError(f"only {len(pos)} candidate positions for {cfg.n_anchors} anchors; lower mount.spacing")
    t0 = time.perf_counter()
    cs = CandidateSet(ev, pos, bor)
    oc_ = cfg.optimizer
    result_pareto = []
    with _Progress(progress) as pg:
        if oc_.greedy:
            with pg.task("greedy log-det", cfg.n_anchors) as upd:
                g = lazy_greedy_logdet(cs, cfg.n_anchors, callback=lambda i, v: upd(i, f"gain {v:.1f}"))
            idx = g["idx"]
        else:  # seeded random start (for comparisons of the later stages)
            idx = np.random.default_rng(cfg.seed).choice(len(cs), cfg.n_anchors, replace=False).tolist()
        timings["greedy_s"] = time.perf_counter() - t0
        if oc_.swaps and oc_.swap_rounds > 0:
            t1 = time.perf_counter()
            with pg.task("local swaps", oc_.swap_rounds) as upd:
                s = swap_search(cs, idx, oc_.swap_rounds, callback=lambda r, f: upd(r, f"J {f:.3f}"))
            idx = s["idx"]
            timings["swaps_s"] = time.perf_counter() - t1
        anchors, bores = pos[idx], bor[idx]
        if oc_.refine and par is not None:
            t2 = time.perf_counter()
            obj = RoomObjective(room, surfs, sid[idx], ev, rc.mount.standoff)
            with pg.task("differential evolution", oc_.maxiter) as upd:
                d = refine_de(obj, par[idx].ravel(), cfg.seed, oc_.maxiter, oc_.popsize, oc_.workers,
                              callback=lambda i, f: upd(i, f"J {f:.3f}"))
            cand_anchors, cand_bores = obj.decode(d["x"])
            if obj(d["x"]) <= ev.evaluate(anchors, bores)["objective"] + 1e-12:
                anchors, bores = cand_anchors, cand_bores
            timings["refine_s"] = time.perf_counter() - t2
            if oc.pareto:
                F, layouts = [], []
                for x in d["population"]:
                    a_, b_ = obj.decode(x)
                    if not room.valid_mount(a_, rc.mount.standoff).all():
                        continue
                    c = ev.evaluate(a_, b_)
                    F.append([1 - c["coverage"], c["pdop_q"], c.get("n1_pdop_q", c["pdop_q"])]
                             + ([c["hull_outside"]] if oc.weights.get("hull") else []))
                    layouts.append((a_, c))
                for i in pareto_front(F):
                    a_, c = layouts[i]
                    result_pareto.append({"anchors": a_.round(4).tolist(), "coverage": c["coverage"],
                                          "pdop_q": c["pdop_q"], "n1_pdop_q": c.get("n1_pdop_q"),
                                          "hull_outside": c["hull_outside"]})
    timings["total_s"] = time.perf_counter() - t0
    ids = _ids(len(anchors))
    comp = ev.evaluate(anchors, bores)
    worst, n1_rows = _single_failures(ev, anchors, bores, ids)
    # Marginal value: order the final anchors greedily (log-det) and evaluate each prefix.
    fin = CandidateSet(ev, anchors, bores)
    order = lazy_greedy_logdet(fin, len(anchors))
    marginal = [{"n": i + 1, "anchor": ids[j], "coverage": c["coverage"], "pdop_p95": c["pdop_p95"]}
                for i, (j, c) in enumerate(zip(order["idx"], order["curve"]))]
    table = [{"layout": "optimised", "coverage": comp["coverage"], "pdop_p50": comp["pdop_p50"],
              "pdop_p95": comp["pdop_p95"], "n1_pdop_p95": comp.get("n1_pdop_q"),
              "hull_outside": comp["hull_outside"], "anchors": len(anchors)}]
    for name, lay in cfg.compare.items():
        la = np.asarray(lay, float)
        c = ev.evaluate(la, _toward(points, la))
        table.append({"layout": name, "coverage": c["coverage"], "pdop_p50": c["pdop_p50"],
                      "pdop_p95": c["pdop_p95"], "n1_pdop_p95": c.get("n1_pdop_q"),
                      "hull_outside": c["hull_outside"], "anchors": len(la)})
    links = link.links(points, anchors, bores)
    pd_all = (tdoa_pdop if cfg.measurement == "tdoa" else metrics_pdop)(points, anchors, links)
    geo = float(np.mean((links.sum(axis=1) >= cfg.radio.k) & (pd_all <= GEOMETRIC_PDOP_MAX)))
    lint = lint_layout(anchors, points, room.surface_distance,
                       single_failure={**worst, "coverage_all": comp["coverage"]}, ids=ids,
                       space_extent=[*np.ptp(room.polygon, axis=0), room.height])
    return {
        "mode": "room",
        "measurement": cfg.measurement,
        "noise_sigma_m": ev.sigma,
        "anchors": anchors,
        "boresights": bores,
        "ids": ids,
        "coverage": comp["coverage"],
        "pdop_p50": comp["pdop_p50"],
        "pdop_p95": comp["pdop_p95"],
        "geometric_coverage": geo,
        "hull_outside": comp["hull_outside"],
        "worst_single_failure": worst,
        "single_failures": n1_rows,
        "objective": comp["objective"],
        "objective_name": "weighted: " + ", ".join(f"{k}={v:g}" for k, v in oc.weights.items())
        + f" (PDOP p{oc.percentile:g}, cap {oc.pdop_cap:g})"
        + (f"; TDoA information (>= {ev.min_links} anchors in range, TDoA sd {ev.sigma:g} m)"
           if cfg.measurement == "tdoa" else ""),
        "seed": cfg.seed,
        "table": table,
        "marginal": marginal,
        "pareto": result_pareto,
        "lint": [w.to_dict() for w in lint],
        "timings": timings,
        "candidates": {"count": int(len(pos)), "dropped": int(dropped)},
        "_plot": {"points": points, "counts": links.sum(axis=1), "pdop": pd_all, "k": cfg.radio.k,
                  "polygon": room.polygon, "height": room.height, "bars": [o for o in obstacles if hasattr(o, "p0")],
                  "lo": [*room.polygon.min(axis=0), 0.0], "hi": [*room.polygon.max(axis=0), room.height]},
    }


# --------------------------------------------------------------------------- structure mode
def _run_structure(cfg: PlacementConfig, progress: bool) -> dict:
    from uwbimu.design.optimize import greedy_structure, local_search_structure, pso
    from uwbimu.design.structures import StructureProblem, girder_bridge, jib_crane

    sc = cfg.structure
    if sc.name == "jib-crane":
        st = jib_crane(sc.range_m, sc.beamwidth_deg, sc.reading)
    else:
        st = girder_bridge(sc.range_m, sc.beamwidth_deg)
    spr = sc.stations_per_rail or st.stations_per_rail
    per_station = len(st.rails[0].offsets)
    if sum(spr) * per_station != cfg.n_anchors:
        raise ConfigError(f"n_anchors = {cfg.n_anchors} but stations_per_rail {spr} x {per_station} anchors "
                         f"per station = {sum(spr) * per_station}")
    timings, table = {}, []
    if sc.name == "jib-crane":
        table.append({"layout": "seed paper (MATLAB, PSO)", "coverage": SEED_COVERAGE, "anchors": 40, "variables": 10})
    t0 = time.perf_counter()
    with _Progress(progress) as pg:
        if sc.reproduce_seed:
            ps = StructureProblem(st, spr, "seed", sc.grid_step)
            with pg.task("seed set-up: PSO, 10 variables", sc.pso_iters) as upd:
                r = pso(ps, ps.bounds, sc.pso_particles, sc.pso_iters, cfg.seed,
                        callback=lambda i, f: upd(i, f"coverage {100 * (1 - f):.2f} %"))
            timings["seed_pso_s"] = time.perf_counter() - t0
            table.append({"layout": "seed set-up (same radio model), our PSO", "coverage": 1 - r["fun"],
                          "anchors": cfg.n_anchors, "variables": len(ps.bounds), "seconds": timings["seed_pso_s"]})
        t1 = time.perf_counter()
        pr = StructureProblem(st, spr, sc.freedom, sc.grid_step)
        rots = (0.0,) if sc.freedom == "seed" else (-0.6, -0.3, 0.0, 0.3, 0.6)
        with pg.task(f"greedy stations ({sc.freedom})", pr.n_stations) as upd:
            g = greedy_structure(pr, rotations=rots, callback=lambda i, c: upd(i, f"coverage {100 * c:.2f} %"))
        x = g["x"]
        if sc.local_search:
            with pg.task("local pattern search", 3) as upd:
                ls = local_search_structure(pr, x, callback=lambda n, f: upd(0, f"coverage {100 * (1 - f):.2f} %"))
            x = ls["x"]
        if sc.objective == "geometric":
            pg_ = StructureProblem(st, spr, sc.freedom, sc.grid_step, "geometric", sc.pdop_max)
            with pg.task(f"pattern search, geometric (PDOP <= {sc.pdop_max:g})", 3) as upd:
                ls = local_search_structure(pg_, x, callback=lambda n, f: upd(0, f"geometric {100 * (1 - f):.2f} %"))
            x = ls["x"]
        timings["ours_s"] = time.perf_counter() - t1
    anchors, bores = pr.decode(x)
    counts = pr.counts(x)
    coverage = float(np.mean(counts >= pr.k))
    geo_prob = StructureProblem(st, spr, sc.freedom, sc.grid_step, "geometric", sc.pdop_max)
    table.append({"layout": f"ours: greedy + search ({sc.freedom}, {sc.objective})", "coverage": coverage,
                  "geometric_coverage": geo_prob.geometric_coverage(x),
                  "anchors": len(anchors), "variables": len(pr.bounds), "seconds": timings["ours_s"]})
    seed_setup = {}
    if sc.reproduce_seed:
        table[-2]["geometric_coverage"] = StructureProblem(st, spr, "seed", sc.grid_step, "geometric",
                                                           sc.pdop_max).geometric_coverage(r["x"])
        # The seed set-up's own layout (drawn as the seed's Figs 5-6: anchors with their facing, covered points).
        sa, sb = ps.decode(r["x"])
        seed_setup = {"anchors": sa, "boresights": sb, "counts": ps.counts(r["x"]), "x": np.asarray(r["x"])}
    ids = _ids(len(anchors))
    # N-1 on the full grid (fast kernel), PDOP on a 2 m sub-grid with the reference link model.
    per = [count_links_grid(pr.axes, anchors[i:i + 1], bores[i:i + 1], pr.lut, pr.sphere) for i in range(len(anchors))]
    pts_c = st.points(2.0 * (sc.grid_step or st.step))
    links_c = st.link.links(pts_c, anchors, bores, ray_cast=False)
    pd_c = metrics_pdop(pts_c, anchors, links_c)
    geo = table[-1]["geometric_coverage"]  # full grid, fast kernel
    cap = 20.0

    def p95(pdv):
        v = np.where(np.isfinite(pdv), pdv, cap)
        return float(np.percentile(np.minimum(v, cap), 95, method="higher"))

    n1_rows = []
    for i in range(len(anchors)):
        cov_i = float(np.mean(counts - per[i] >= pr.k))
        n1_rows.append({"anchor": ids[i], "coverage": cov_i, "index": i})
    worst = min(n1_rows, key=lambda r: r["coverage"])
    keep = [j for j in range(len(anchors)) if j != worst["index"]]
    worst = {"anchor": worst["anchor"], "coverage": worst["coverage"],
             "pdop_p95": p95(metrics_pdop(pts_c, anchors[keep], links_c[:, keep]))}
    # Marginal value of each added station (greedy over the final stations).
    m = per_station
    st_counts = [np.sum(per[s * m:(s + 1) * m], axis=0) for s in range(len(anchors) // m)]
    acc = np.zeros_like(counts, dtype=np.int32)
    left = list(range(len(st_counts)))
    marginal = []
    while left:
        best = max(left, key=lambda s: np.count_nonzero(acc + st_counts[s] >= pr.k) * 1e6
                   + np.minimum(acc + st_counts[s], pr.k).sum())
        acc = acc + st_counts[best]
        left.remove(best)
        marginal.append({"n": (len(st_counts) - len(left)) * m, "station": int(best),
                         "coverage": float(np.mean(acc >= pr.k))})
    ray = {}
    if st.link.obstacles:
        pts_f = st.points()
        lk = st.link.links(pts_f, anchors, bores, ray_cast=True)
        ray = {"coverage_with_ray_casting": float(np.mean(lk.sum(axis=1) >= pr.k))}
    timings["total_s"] = time.perf_counter() - t0
    lint = lint_layout(anchors, st.points(4.0), single_failure={**worst, "coverage_all": coverage},
                       single_failure_pdop_limit=10.0, ids=ids,
                       space_extent=np.asarray(st.space_hi, float) - np.asarray(st.space_lo, float))
    return {
        "mode": "structure",
        "structure": st.name,
        "anchors": anchors,
        "boresights": bores,
        "ids": ids,
        "coverage": coverage,
        "pdop_p50": float(np.percentile(np.minimum(np.where(np.isfinite(pd_c), pd_c, cap), cap), 50, method="higher")),
        "pdop_p95": p95(pd_c),
        "geometric_coverage": geo,
        "worst_single_failure": worst,
        "single_failures": [{k: v for k, v in r.items() if k != "index"} for r in n1_rows],
        "objective": 1.0 - (geo if sc.objective == "geometric" else coverage),
        "objective_name": (f"1 - {pr.k}-coverage over {pr.n_points} grid points" if sc.objective == "coverage" else
                           f"1 - fraction of {pr.n_points} grid points with >= {pr.k} links and PDOP <= {sc.pdop_max:g}"),
        "seed": cfg.seed,
        "table": table,
        "marginal": marginal,
        "decision_vector": np.asarray(x).tolist(),
        "seed_setup_decision_vector": seed_setup["x"].tolist() if seed_setup else None,
        "reading": sc.reading if sc.name == "jib-crane" else None,
        "radio": {"range_m_0dBi": sc.range_m, "beamwidth_deg": sc.beamwidth_deg,
                  "peak_range_m": st.link.peak_range, "note": _radio_note(sc)},
        **ray,
        "lint": [w.to_dict() for w in lint],
        "timings": timings,
        "_plot": {"points": st.points(sc.grid_step), "counts": counts, "pdop": pd_c, "pdop_points": pts_c, "k": pr.k,
                  "bars": st.bars, "lo": st.space_lo, "hi": st.space_hi, "seed_setup": seed_setup},
    }


def _radio_note(sc) -> str:
    """Plain statement of where the structure's range came from (printed by the CLI, stored in the JSON)."""
    note = (f"radio model: cos^n anchor antennas ({sc.beamwidth_deg:g} deg half-power beamwidth), omni tag, "
            f"0 dBi LOS range R0 = {sc.range_m:g} m")
    fitted = CRANE_R0_FITTED.get(sc.reading)
    if sc.name == "jib-crane" and abs(sc.range_m - fitted) < 1e-9:
        note += (f" -- R0 is FITTED for the {sc.reading} reading of the stations (one unknown: the seed gives neither "
                 "its measured range model nor which way a station's anchors face) so that the seed's own set-up "
                 "(10 variables, PSO) reproduces the seed's 91.3 %; it is not a measurement")
    elif sc.name == "jib-crane":
        note += (f" -- not the value fitted for the {sc.reading} reading ({fitted:g} m), so the seed's 91.3 % is "
                 "not directly comparable")
    return note + ". Every row of the table uses this same radio model."


def run_placement(cfg: PlacementConfig, progress: bool = False) -> dict:
    """Run the configured placement; returns the result dict (see :func:`write_outputs`)."""
    if cfg.mode == "room":
        return _run_room(cfg, progress)
    return _run_structure(cfg, progress)


def write_outputs(result: dict, out: str | Path, plots: bool = True) -> list[Path]:
    """Write ``placement.json``, ``anchors.csv``, ``anchors_scenario.yaml`` and plots into ``out`` (atomically)."""
    from uwbimu.io.atomic import write_csv, write_json, write_yaml

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    a = np.asarray(result["anchors"], float)
    js = {k: v for k, v in result.items() if not k.startswith("_")}
    js["anchors"] = a.round(4).tolist()
    js["boresights"] = np.asarray(result["boresights"]).round(5).tolist()
    written = [write_json(out / "placement.json", js)]
    df = pd.DataFrame({"anchor": result["ids"], "x": a[:, 0].round(4), "y": a[:, 1].round(4), "z": a[:, 2].round(4)})
    written.append(write_csv(out / "anchors.csv", df))
    # The simulator's scenario format lists anchors inline: a snippet to paste into a scenario.
    snippet = {"anchors": [{"id": i, "position": [float(v) for v in p]} for i, p in zip(result["ids"], a.round(4))]}
    written.append(write_yaml(out / "anchors_scenario.yaml", snippet))
    if plots:
        from uwbimu.design import plots as P

        pl = result["_plot"]
        written.append(P.plot_layout_3d(out / "anchors_3d.png", a, result["boresights"], pl.get("bars", ()),
                                        pl.get("polygon"), pl.get("height"), ids=result["ids"],
                                        title=f"{result['mode']}: {len(a)} anchors", lo=pl.get("lo"), hi=pl.get("hi")))
        written.append(P.plot_coverage_map(out / "coverage_map.png", pl["points"], pl["counts"], pl["k"]))
        written.append(P.plot_pdop_slices(out / "pdop_slices.png", pl.get("pdop_points", pl["points"]), pl["pdop"],
                                          axis=2 if result["mode"] == "room" else 0))
        if pl.get("seed_setup"):
            ss = pl["seed_setup"]
            written.append(P.plot_structure_coverage(
                out / "seed_layout.png", ss["anchors"], ss["boresights"], pl["bars"], pl["points"], ss["counts"],
                pl["k"], pl["lo"], pl["hi"],
                title=f"seed set-up ({result.get('reading') or 'diagonal'} reading): "
                      f"{100 * float(np.mean(ss['counts'] >= pl['k'])):.2f} % {pl['k']}-covered"))
        mg = result["marginal"]
        written.append(P.plot_marginal(out / "marginal_value.png", [r["n"] for r in mg], [r["coverage"] for r in mg],
                                       [r["pdop_p95"] for r in mg] if mg and "pdop_p95" in mg[0] else None))
    return written
