"""``execute(..., caller=True)``: the caller is one of the workers (it runs tasks while the pool starts);
every task runs once, the results are the serial ones, failures are reported as lines."""

from __future__ import annotations

import os
import time

import pytest

from uwbimu.parallel import ProcessPool, execute


def _task(x):
    if x == "boom":
        raise ValueError("bad task")
    time.sleep(0.02)
    return x, x * x, os.getpid()


def _slow(x):
    time.sleep(0.3)
    return x, os.getpid()


def _die(x):
    if x == 1 and os.environ.get("UWBIMU_TEST_PARENT") != str(os.getpid()):
        os._exit(3)  # a worker dies (never the caller)
    return x, os.getpid()


def test_every_task_once_with_the_serial_results():
    got = []
    assert execute(_task, list(range(30)), got.append, workers=2, preload=(), caller=True) == []
    assert sorted((x, y) for x, y, _ in got) == [(x, x * x) for x in range(30)]
    assert os.getpid() in {pid for *_, pid in got}  # the caller worked


def test_the_pool_takes_tasks_once_it_is_up():
    # tasks long against the pool's start: both processes work
    got = []
    assert execute(_slow, list(range(12)), got.append, workers=2, preload=(), caller=True) == []
    pids = {pid for _, pid in got}
    assert sorted(x for x, _ in got) == list(range(12))
    assert os.getpid() in pids and len(pids) == 2


def test_a_failing_task_is_a_line_in_the_caller_too():
    got = []
    failed = execute(_task, [1, "boom", 2], got.append, workers=2, preload=(), caller=True,
                     describe=lambda t: f"task {t}")
    assert len(failed) == 1 and failed[0].startswith("task boom: ValueError")
    assert sorted(x for x, *_ in got) == [1, 2]


def test_a_dead_worker_is_reported_and_the_caller_finishes_the_rest(monkeypatch):
    monkeypatch.setenv("UWBIMU_TEST_PARENT", str(os.getpid()))
    got = []
    # task 1 kills a pool worker if it lands there; the caller runs it fine: either way nothing is lost
    failed = execute(_die, [1] + [_ for _ in range(2, 8)], got.append, workers=2, preload=(), caller=True,
                     describe=lambda t: f"task {t}")
    done = sorted(x for x, _ in got)
    assert sorted(done + [int(line.split()[1].rstrip(":")) for line in failed]) == list(range(1, 8))


@pytest.mark.parametrize("n", [0, 1])
def test_empty_and_single(n):
    got = []
    assert execute(_task, list(range(n)), got.append, workers=2, preload=(), caller=True) == []
    assert len(got) == n


def test_kept_pool_with_caller():
    got = []
    with ProcessPool(2, preload=(), caller=True) as pool:
        assert pool.executor._max_workers == 1
        for chunk in ([1, 2, 3], [4, 5]):
            assert execute(_slow, chunk, got.append, workers=2, pool=pool, preload=(), caller=True) == []
    assert sorted(x for x, _ in got) == [1, 2, 3, 4, 5]
