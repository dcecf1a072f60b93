"""TWR vs TDoA anchor layouts for the same room (issue 13 item 5; docs/placement.md, "TDoA layouts").

1. Runs ``uwbimu place`` on ``examples/placement/room.yaml`` (two-way ranges) and on
   ``examples/placement/room_tdoa.yaml`` (the same room, anchors, objective and optimiser
   with ``measurement: tdoa``): the layout optimised for TWR and the one optimised for TDoA.
2. Evaluates four layouts over the same tag samples with both objectives: the two optimised
   layouts and the two reference layouts of the configs' ``compare`` section
   (all anchors on the ceiling; Bitcraze-style 3 high / 3 low).
3. Prints a markdown table per layout: TWR and TDoA PDOP p95, N-1 worst PDOP p95 (TWR,
   TDoA), the objective of ``room.yaml`` (TWR) and of ``room_tdoa.yaml`` (TDoA), coverage
   (k = 3 links for TWR, 4 for TDoA) and the fraction of the flight volume outside the
   anchors' hull.  ``--json PATH`` also writes the numbers.

Usage::

    PYTHONPATH=src python benchmarks/compare_place_twr_tdoa.py [--seed 0] [--maxiter 20] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))

from uwbimu.design.config import load_config  # noqa: E402
from uwbimu.design.run import _toward, room_evaluator, room_setup, run_placement  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twr", default=str(ROOT / "examples/placement/room.yaml"), help="TWR room config")
    ap.add_argument("--tdoa", default=str(ROOT / "examples/placement/room_tdoa.yaml"), help="TDoA room config")
    ap.add_argument("--seed", type=int, default=None, help="override both configs' seed")
    ap.add_argument("--maxiter", type=int, default=None, help="override the DE generations (optimizer.maxiter)")
    ap.add_argument("--json", default=None, help="also write the results to this JSON file")
    args = ap.parse_args(argv)

    cfgs = {}
    for m, path in (("twr", args.twr), ("tdoa", args.tdoa)):
        cfg = load_config(path)
        if cfg.measurement != m:
            raise SystemExit(f"{path}: expected measurement {m!r}, the config says {cfg.measurement!r}")
        if args.seed is not None:
            cfg.seed = args.seed
        if args.maxiter is not None:
            cfg.optimizer.maxiter = args.maxiter
        cfgs[m] = cfg
    # Same room and tag samples for both (the configs must describe the same room).
    _, pts_t, link, _ = room_setup(cfgs["twr"])
    _, pts_d, _, _ = room_setup(cfgs["tdoa"])
    if pts_t.shape != pts_d.shape or not np.allclose(pts_t, pts_d):
        raise SystemExit("the TWR and TDoA configs describe different flight volumes")
    evs = {"twr": room_evaluator(cfgs["twr"], pts_t, link, "twr"),
           "tdoa": room_evaluator(cfgs["tdoa"], pts_t, link, "tdoa")}

    layouts, runs = {}, {}
    for m in ("twr", "tdoa"):
        t0 = time.perf_counter()
        res = run_placement(cfgs[m])
        runs[m] = {"seconds": time.perf_counter() - t0, "objective": res["objective"], "pdop_p95": res["pdop_p95"]}
        layouts[f"optimised for {m.upper()}"] = (np.asarray(res["anchors"]), np.asarray(res["boresights"]))
    for name, lay in cfgs["twr"].compare.items():
        a = np.asarray(lay, float)
        layouts[name] = (a, _toward(pts_t, a))

    rows = []
    for name, (a, b) in layouts.items():
        row = {"layout": name, "anchors": np.round(a, 4).tolist()}
        for m, ev in evs.items():
            c = ev.evaluate(a, b)
            row.update({f"{m}_pdop_p95": c["pdop_p95"], f"{m}_n1_pdop_p95": c.get("n1_pdop_q"),
                        f"{m}_objective": c["objective"], f"{m}_coverage": c["coverage"]})
            row["hull_outside"] = c["hull_outside"]
        rows.append(row)
    # The optimised layouts' objectives must match what the runs reported (same evaluator).
    for m in ("twr", "tdoa"):
        got = rows[list(layouts).index(f"optimised for {m.upper()}")][f"{m}_objective"]
        if abs(got - runs[m]["objective"]) > 1e-9 * max(1.0, abs(got)):
            raise SystemExit(f"re-evaluated {m} objective {got} differs from the run's {runs[m]['objective']}")

    c0 = cfgs["twr"]
    print(f"room {c0.room.box}, {c0.n_anchors} anchors, seed {c0.seed}, DE generations {c0.optimizer.maxiter} "
          f"(popsize {c0.optimizer.popsize}), {len(pts_t)} tag samples; range sd {c0.radio.range_sigma:g} m, "
          f"TDoA sd {cfgs['tdoa'].radio.tdoa_sigma_m:g} m; run time TWR {runs['twr']['seconds']:.1f} s, "
          f"TDoA {runs['tdoa']['seconds']:.1f} s")
    print()
    print("| layout | TWR PDOP p95 | TDoA PDOP p95 | N-1 p95 TWR | N-1 p95 TDoA | objective TWR | objective TDoA "
          "| coverage TWR (k=3) / TDoA (k=4) | outside hull |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['layout']} | {r['twr_pdop_p95']:.3f} | {r['tdoa_pdop_p95']:.3f} | {r['twr_n1_pdop_p95']:.3f} "
              f"| {r['tdoa_n1_pdop_p95']:.3f} | {r['twr_objective']:.3f} | {r['tdoa_objective']:.3f} "
              f"| {100 * r['twr_coverage']:.1f} % / {100 * r['tdoa_coverage']:.1f} % "
              f"| {100 * r['hull_outside']:.1f} % |")
    if args.json:
        out = {"seed": c0.seed, "maxiter": c0.optimizer.maxiter, "runs": runs, "rows": rows}
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
