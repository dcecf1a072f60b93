"""Benchmark: k-coverage of the jib-crane grid (192,000 points x 40 anchors).

Range + directional antenna gain (cos^n patch), no ray casting, one core.
Compares the numba float32 grid kernel (``count_links_grid``), the numba
point-list kernel (``count_links_fast``) and the naive NumPy float64 reference
(``LinkModel.links``, full (P, N) broadcasting) timed in the same process.

Run: ``python benchmarks/bench_coverage.py`` (target: grid kernel < 25 ms).
``--crane-sweep`` additionally reproduces the R0 calibration table of
docs/placement.md (seed set-up with PSO vs ours, per 0 dBi range; a few minutes).
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import time  # noqa: E402

import numpy as np  # noqa: E402

from uwbimu.design.radio import count_links_fast, count_links_grid, lobe_sphere, to_soa  # noqa: E402
from uwbimu.design.run import CRANE_R0_CALIBRATED  # noqa: E402
from uwbimu.design.structures import StructureProblem, jib_crane  # noqa: E402


def _time(fn, reps):
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        out = fn()
        ts.append(time.perf_counter() - t)
    return np.array(ts) * 1e3, out


def main() -> None:
    st = jib_crane(range_m=CRANE_R0_CALIBRATED)
    pr = StructureProblem(st)
    x = np.r_[np.linspace(3, 57, 5), np.linspace(3, 57, 5)]  # 10 stations, 40 anchors
    anchors, bores = pr.decode(x)
    axes = pr.axes
    pts = st.points()
    lut = st.link.reach_lut()
    sphere = lobe_sphere(lut)
    soa = to_soa(pts)
    print(f"grid {len(pts)} points x {len(anchors)} anchors, k = {st.k}, R0 = {st.link.max_range} m, "
          f"peak reach {st.link.peak_range:.1f} m")
    count_links_grid(axes, anchors, bores, lut, sphere)  # JIT / cache load
    count_links_fast(soa, anchors, bores, lut)
    t_grid, c_grid = _time(lambda: count_links_grid(axes, anchors, bores, lut, sphere), 30)
    t_pts, c_pts = _time(lambda: count_links_fast(soa, anchors, bores, lut), 10)
    t_ref, links = _time(lambda: st.link.links(pts, anchors, bores, ray_cast=False), 2)
    c_ref = links.sum(axis=1)
    cov = [float(np.mean(c >= st.k)) for c in (c_grid, c_pts, c_ref)]
    print(f"numba grid kernel   : median {np.median(t_grid):7.2f} ms  min {t_grid.min():7.2f} ms  coverage {100 * cov[0]:.3f} %")
    print(f"numba point kernel  : median {np.median(t_pts):7.2f} ms  min {t_pts.min():7.2f} ms  coverage {100 * cov[1]:.3f} %")
    print(f"naive NumPy (f64)   : median {np.median(t_ref):7.2f} ms  min {t_ref.min():7.2f} ms  coverage {100 * cov[2]:.3f} %")
    print(f"speed-up grid kernel vs naive NumPy: {np.median(t_ref) / np.median(t_grid):.0f}x (median), "
          f"point kernel: {np.median(t_ref) / np.median(t_pts):.0f}x")
    print(f"link-count mismatches vs reference (LUT interpolation at the reach boundary): grid "
          f"{int(np.sum(c_grid != c_ref))}, points {int(np.sum(c_pts != c_ref))} of {len(pts)}")
    ok = np.median(t_grid) < 25.0
    print(f"target < 25 ms per evaluation: {'MET' if ok else 'NOT MET'} ({np.median(t_grid):.2f} ms median)")


def crane_sweep(ranges=(24.0, 26.0, CRANE_R0_CALIBRATED, 28.0, 30.0)) -> None:
    from uwbimu.design.optimize import greedy_structure, local_search_structure, pso

    print("R0 [m] | seed set-up, PSO 24x40 (seed 0) | greedy+local, seed variables | ours rotate-tilt | seconds")
    for r0 in ranges:
        t = time.perf_counter()
        st = jib_crane(range_m=r0)
        ps = StructureProblem(st)
        r = pso(ps, ps.bounds, 24, 40, seed=0)
        g = greedy_structure(ps)
        ls = local_search_structure(ps, g["x"])
        pf = StructureProblem(st, freedom="rotate-tilt")
        gf = greedy_structure(pf, rotations=(-0.6, -0.3, 0.0, 0.3, 0.6))
        lf = local_search_structure(pf, gf["x"])
        print(f"{r0:6.1f} | {100 * (1 - r['fun']):8.2f} % | {100 * (1 - ls['fun']):8.2f} % | "
              f"{100 * (1 - lf['fun']):8.2f} % | {time.perf_counter() - t:6.1f}", flush=True)


if __name__ == "__main__":
    import sys

    main()
    if "--crane-sweep" in sys.argv[1:]:
        crane_sweep()
