"""uwbimu.parallel.ProcessPool: one local pool over several execute() calls (its workers and their caches
outlive each call), with the results of a pool per call."""

from __future__ import annotations

import os

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
