"""The seed's jib crane under both readings of its stations (docs/placement.md, section 4).

For each reading (``diagonal``: anchors on the corners facing along the diagonals;
``axis-aligned``: on the face centres facing along the face normals) this fits R0 so that
the seed's own set-up (10 variables, PSO 24 x 40, seed 0) reproduces the paper's 91.3 %, then
attributes the gain of our layout (orientation sweep, our optimiser on the same 10
variables, per-station rotation + tilt).  Also prints both readings at the other reading's
R0 so the effect of the reading alone is visible.

    python benchmarks/crane_readings.py            # full grid (192,000 points), ~10-15 min on 2 cores
    python benchmarks/crane_readings.py --quick    # 4 m grid, small PSO: a smoke run (not the docs' numbers)
"""

from __future__ import annotations

import argparse
import time

from uwbimu.design.crane import attribute_gain, fit_seed_range


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="4 m grid and a small PSO (smoke run)")
    ap.add_argument("--readings", default="diagonal,axis-aligned")
    ap.add_argument("--no-fit", action="store_true", help="skip the R0 fit; use --r0 for every reading")
    ap.add_argument("--r0", type=float, default=26.7, help="R0 [m] when --no-fit")
    a = ap.parse_args()
    kw = dict(step=4.0, particles=8, iters=10) if a.quick else {}
    readings = [r.strip() for r in a.readings.split(",") if r.strip()]
    t0 = time.perf_counter()
    fits = {}
    for rd in readings:
        if a.no_fit:
            fits[rd] = a.r0
            continue
        f = fit_seed_range(rd, callback=lambda r0, c, rd=rd: print(f"  fit {rd}: R0 {r0:6.2f} m -> {100 * c:6.2f} %",
                                                                        flush=True), **kw)
        fits[rd] = f.range_m
        print(f"{rd}: R0 fitted = {f.range_m:.2f} m (seed set-up {100 * f.coverage:.2f} %, target 91.3 %)", flush=True)
    print()
    res = {}
    for rd in readings:
        res[rd] = attribute_gain(fits[rd], rd, **kw)
        print(f"[{time.perf_counter() - t0:.0f} s] {rd} done", flush=True)
    print("\n| step | " + " | ".join(f"{rd} (R0 {fits[rd]:.1f} m)" for rd in readings) + " |")
    print("|---|" + "---|" * len(readings))
    names = [n for n, _ in res[readings[0]].rows()]
    for i, name in enumerate(names):
        label = name if "common station rotation" not in name else "+ best common station rotation, 10 variables, PSO"
        cells = []
        for rd in readings:
            n_rd, v = res[rd].rows()[i]
            extra = f" ({res[rd].best_angle_deg:g} deg)" if "common" in n_rd else ""
            cells.append(f"{100 * v:.2f} %{extra}")
        print(f"| {label} | " + " | ".join(cells) + " |")
    print("\norientation sweep (seed set-up, PSO, one common rotation of every station):")
    print("| rotation [deg] | " + " | ".join(readings) + " |")
    print("|---|" + "---|" * len(readings))
    for ang in res[readings[0]].orientation:
        print(f"| {ang:g} | " + " | ".join(f"{100 * res[rd].orientation[ang]:.2f} %" for rd in readings) + " |")
    print(f"\ntotal {time.perf_counter() - t0:.0f} s wall")


if __name__ == "__main__":
    main()
