"""Repeatability windows with 2 workers against 1, wall time in one process (issue 31 item 5).

    python benchmarks/bench_repeatability_workers.py DATASET [--windows 4] [--estimator eskf] [--repeat 3]

Runs :func:`uwbimu.eval.repeatability.repeatability` on DATASET (a folder, e.g. INRoL imported with
``uwbimu import inrol``) with ``workers=1`` and ``workers=2`` alternately, ``--repeat`` times each, after
one warm-up run (numba's machine code loaded in this process), and prints the best wall time of each,
their ratio, and whether the windows' values are identical (they must be: the same tasks, pickled).
With 2 workers the caller times its first window and starts a pool only when the rest outlasts the
pool's start (``parallel.pool_pays``); where the platform forks, the pool is forked from this warm
process (``parallel.POOL_FORK_S``).
"""

from __future__ import annotations

import argparse
import time


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset")
    ap.add_argument("--windows", type=int, default=4)
    ap.add_argument("--estimator", default="eskf")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    from uwbimu.eval.repeatability import repeatability
    from uwbimu.io.loader import load_dataset

    ds = load_dataset(a.dataset)
    repeatability(ds, a.windows, a.estimator)  # warm-up
    best = {1: float("inf"), 2: float("inf")}
    vals = {}
    for _ in range(a.repeat):
        for w in (1, 2):
            w0 = time.perf_counter()
            r = repeatability(ds, a.windows, a.estimator, workers=w)
            best[w] = min(best[w], time.perf_counter() - w0)
            vals[w] = [win.get("values") for win in r["windows"]]
    print(f"{a.windows} windows of {a.dataset} ({a.estimator}): 1 worker {best[1]:.2f} s, 2 workers {best[2]:.2f} s "
          f"wall (best of {a.repeat}): speed-up {best[1] / best[2]:.2f}x; identical values: {vals[1] == vals[2]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
