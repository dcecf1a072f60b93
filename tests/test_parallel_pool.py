"""uwbimu.parallel.ProcessPool: one local pool over several execute() calls (its workers and their caches
outlive each call), with the results of a pool per call."""

from __future__ import annotations

import os

import pytest

from uwbimu.parallel import ProcessPool, execute

_CACHE: dict = {}


def _task(x):
    """Square ``x``; report this worker's pid and how many tasks its module-level cache has seen."""
    _CACHE["n"] = _CACHE.get("n", 0) + 1
    return x, x * x, os.getpid(), _CACHE["n"]


def test_pool_outlives_each_call():
    got = []
    with ProcessPool(2, preload=()) as pool:
        assert execute(_task, [1, 2, 3], got.append, workers=2, pool=pool, preload=()) == []
        first = {pid for *_, pid, _n in got}
        got2 = []
        assert execute(_task, [4, 5], got2.append, workers=2, pool=pool, preload=()) == []
    assert {pid for *_, pid, _n in got2} <= first  # the same processes
    assert sum(n for *_, n in got2) > 2  # their cache kept what the first call's tasks put in it
    assert sorted((x, y) for x, y, *_ in got + got2) == [(x, x * x) for x in (1, 2, 3, 4, 5)]
    assert os.getpid() not in first
    assert pool.executor is None  # closed with the block


def test_without_a_pool_the_results_are_the_same():
    got = []
    assert execute(_task, [1, 2, 3], got.append, workers=2, preload=()) == []
    assert sorted((x, y) for x, y, *_ in got) == [(1, 1), (2, 4), (3, 9)]


_LAZY_SCRIPT = """
import os
from uwbimu import parallel
import uwbimu._worker_env as cache_home   # any importable module: the cache lives on it

def peek(_):
    import time
    time.sleep(0.2)  # long enough for the pool to take tasks
    return getattr(cache_home, "CACHE", None), os.getpid()

cache_home.CACHE = "filled by the caller"
with parallel.ProcessPool(2, preload=(), caller=True, lazy=True) as pool:
    assert pool.executor is None            # nothing started on entering the block
    pool.start()
    got = []
    assert parallel.execute(peek, list(range(6)), got.append, workers=2, pool=pool, preload=(), caller=True) == []
seen = {v for v, pid in got if pid != os.getpid()}
print("ok" if seen == {"filled by the caller"} else f"bad {got}")
"""


def test_a_lazy_pool_forks_after_the_caller_filled_its_cache():
    """``ProcessPool(lazy=True)`` starts at ``start()``; where the platform forks and one thread runs, its workers
    are forked then and see what the caller put in a module-level cache before (the t_d profile's problem)."""
    import multiprocessing as mp
    import subprocess
    import sys

    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    out = subprocess.run([sys.executable, "-c", _LAZY_SCRIPT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", (out.stdout[-500:], out.stderr[-2000:])
