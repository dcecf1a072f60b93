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


_FOREIGN_SERVER = """
import multiprocessing as mp, os
from uwbimu.parallel import execute

def blas(_):
    return tuple(os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"))

if __name__ == "__main__":
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.pop(k, None)
    ctx = mp.get_context("forkserver")
    ctx.set_forkserver_preload(["json"])        # the user's own forkserver, started first
    p = ctx.Process(target=print, args=("",))
    p.start(); p.join()
    seen = []
    assert execute(blas, [0, 1, 2], seen.append, workers=2, preload=()) == []
    print("ok" if set(seen) == {("1", "1", "1")} else f"bad {seen}")
"""


def test_workers_get_one_blas_thread_from_a_forkserver_started_by_someone_else(tmp_path):
    """A forkserver that runs before the first pool keeps its own preload (it never imported
    uwbimu._worker_env): the workers still get one BLAS thread (the pool's initializer).  CI once saw
    ``(None, None, None)`` in the test above after other tests had run in the same process."""
    import multiprocessing as mp
    import subprocess
    import sys

    import pytest

    if "forkserver" not in mp.get_all_start_methods():
        pytest.skip("no forkserver on this platform")
    script = tmp_path / "foreign_server.py"
    script.write_text(_FOREIGN_SERVER)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip().endswith("ok"), (out.stdout[-500:], out.stderr[-2000:])
