"""The studies' generic executor: every task's result reaches on_result once, serial or pooled."""

from __future__ import annotations

from uwbimu.studies import execute


def test_execute_serial_and_pool_give_the_same_results():
    tasks = [-3, -1, 4, -1, -5, 9]
    serial, pooled = [], []
    assert execute(abs, tasks, serial.append, workers=1) == []
    assert execute(abs, tasks, pooled.append, workers=2, preload=()) == []
    assert serial == [3, 1, 4, 1, 5, 9]           # serial keeps the order
    assert sorted(pooled) == sorted(serial)        # a pool hands results over as they finish


def test_execute_reports_failed_tasks_by_description():
    got = []
    failures = execute(abs, [2, "x", -7], got.append, workers=2, preload=(), describe=lambda t: f"task {t!r}")
    assert sorted(got) == [2, 7]
    assert len(failures) == 1 and failures[0].startswith("task 'x': TypeError")
