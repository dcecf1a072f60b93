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


def _thread_vars(_task):
    import os

    return tuple(os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"))


def test_pool_workers_use_one_blas_thread_without_touching_the_callers_environment(monkeypatch):
    """Issue 15 item 6: the library never edits os.environ; the workers get one BLAS thread."""
    import os

    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.delenv(k, raising=False)
    from collections.abc import MutableMapping

    writes = []

    class Recording(MutableMapping):  # os.environ that records every write in this process
        def __init__(self, real):
            self.real = real

        def __getitem__(self, k):
            return self.real[k]

        def __setitem__(self, k, v):
            writes.append(k)
            self.real[k] = v

        def __delitem__(self, k):
            writes.append(k)
            del self.real[k]

        def __iter__(self):
            return iter(self.real)

        def __len__(self):
            return len(self.real)

        def copy(self):
            return dict(self.real)

    # warm-up: modules that the pool imports on first use may set variables of their own at import
    # (that is theirs, not ours, and made this test order-dependent); the check is on our calls
    execute(_thread_vars, [0], lambda _: None, workers=2, preload=())
    before = dict(os.environ)
    monkeypatch.setattr(os, "environ", Recording(os.environ))
    seen = []
    assert execute(_thread_vars, [0, 1, 2], seen.append, workers=2, preload=()) == []
    assert writes == []
    # the variables the library could set (uwbimu._worker_env, parallel._one_blas_thread) are unchanged in
    # the caller; other variables may be written by third-party threads of earlier tests in this process
    blas = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
    changed = {k for k in blas if before.get(k) != os.environ.real.get(k)}
    assert changed == set()
    assert set(seen) == {("1", "1", "1")}
