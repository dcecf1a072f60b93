"""``execute(..., caller=True, measure_first=True)``: the caller times one task and starts a pool only when the
work left is longer than the pool's start (``parallel.pool_pays``); the results are the serial ones either way."""

from __future__ import annotations

import os
import time

from uwbimu import parallel
from uwbimu.parallel import execute, pool_pays


def _quick(x):
    return x, x * x, os.getpid()


def _slow(x):
    time.sleep(0.25)
    return x, x * x, os.getpid()


def _fails(x):
    if x == 3:
        raise ValueError("bad task")
    return x, x * x, os.getpid()


def test_the_rule_compares_the_work_left_with_the_start_and_two_tasks():
    assert pool_pays(5.0, 0.4, start_s=4.0)
    assert not pool_pays(4.7, 0.4, start_s=4.0)  # longer than the start, not by two tasks
    assert not pool_pays(3.9, 0.0, start_s=4.0)
    assert not pool_pays(0.0, 0.0, start_s=0.0)


def test_short_tasks_run_in_the_caller_and_no_pool_starts(monkeypatch):
    started = []
    monkeypatch.setattr(parallel, "_new_executor", lambda *a, **k: started.append(a) or None)
    got = []
    assert execute(_quick, list(range(20)), got.append, workers=2, preload=(), caller=True,
                   measure_first=True) == []
    assert sorted((x, y) for x, y, _ in got) == [(x, x * x) for x in range(20)]
    assert {pid for *_, pid in got} == {os.getpid()}
    assert started == []


def test_long_tasks_start_the_pool_and_both_processes_work(monkeypatch):
    # a start of 0.1 s against 10 tasks of 0.25 s left (after two measured): the pool pays
    monkeypatch.setattr(parallel, "POOL_START_S", 0.1)
    monkeypatch.setattr(parallel, "POOL_RESTART_S", 0.1)
    got = []
    assert execute(_slow, list(range(12)), got.append, workers=2, preload=(), caller=True,
                   measure_first=True) == []
    assert sorted((x, y) for x, y, _ in got) == [(x, x * x) for x in range(12)]
    pids = {pid for *_, pid in got}
    assert os.getpid() in pids and len(pids) == 2


def test_a_failing_task_is_a_line_when_measured_first_too(monkeypatch):
    monkeypatch.setattr(parallel, "_new_executor", lambda *a, **k: None)
    got = []
    failed = execute(_fails, [1, 2, 3, 4], got.append, workers=2, preload=(), caller=True, measure_first=True,
                     describe=lambda t: f"task {t}")
    assert len(failed) == 1 and failed[0].startswith("task 3: ValueError")
    assert sorted(x for x, *_ in got) == [1, 2, 4]


def test_the_fork_rule_compares_the_shared_work_with_the_caller_alone():
    # two windows of 0.7 s left: forked start 0.3 s + one window each (1.0 s) < 1.4 s alone
    assert parallel.fork_pays(2, 0.7, workers=2, start_s=0.3)
    assert not parallel.fork_pays(2, 0.25, workers=2, start_s=0.3)  # 0.55 s shared, 0.5 s alone
    assert not parallel.fork_pays(1, 10.0, workers=2, start_s=0.0)  # one task: nothing to share
    assert parallel.fork_pays(3, 0.4, workers=2, start_s=0.3)      # 0.3 + 0.8 < 1.2
    assert not parallel.fork_pays(3, 0.3, workers=2, start_s=0.3)  # 0.9, not less than 0.9


_FORK_SCRIPT = """
import os, time
from uwbimu import parallel

def slow(x):
    time.sleep(0.25)
    return x, x * x, os.getpid()

forked = []
real = parallel._fork_executor
parallel._fork_executor = lambda w: forked.append(w) or real(w)
def no_forkserver(*a, **k):
    raise AssertionError("forkserver pool started")
parallel._new_executor = no_forkserver
got = []
assert parallel._can_fork()
assert parallel.execute(slow, list(range(8)), got.append, workers=2, preload=(), caller=True,
                        measure_first=True) == []
assert forked == [1], forked
assert sorted((x, y) for x, y, _ in got) == [(x, x * x) for x in range(8)]
pids = {pid for *_, pid in got}
assert os.getpid() in pids and len(pids) == 2, pids
print("ok")
"""


def test_a_warm_single_threaded_caller_forks_its_pool():
    """Where the platform forks and the caller runs one thread, the pool is forked from it (its workers start
    warm); the results are the serial ones and both processes work.  In a fresh interpreter: a test process
    under pytest-xdist runs other threads, where the forkserver is used instead."""
    import multiprocessing as mp
    import subprocess
    import sys

    import pytest

    if "fork" not in mp.get_all_start_methods():
        pytest.skip("no fork on this platform")
    out = subprocess.run([sys.executable, "-c", _FORK_SCRIPT], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-2000:]
