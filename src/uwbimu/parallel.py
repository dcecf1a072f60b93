"""Executors: run a list of tasks on a local process pool, serially, or on Dask.

A low-level module (next to :mod:`uwbimu.errors`): it imports nothing of ours but
:mod:`uwbimu.optional`, so every layer may use it.  :func:`execute` is the one entry point (the
study runner, the trajectory proof, the t_d profile walks of the batch calibrator and the
repeatability windows use it): it calls ``fn(task)`` for every task, hands each
result to ``on_result`` in the client process as it arrives, and returns the tasks that did
not finish (a dead worker is reported, not fatal).  ``fn`` must be a module-level function
(picklable).
"""

from __future__ import annotations

import os
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from typing import Any, Callable, Optional

from uwbimu.optional import require

# --------------------------------------------------------------------------
# Executors
# --------------------------------------------------------------------------
# one BLAS thread per worker, set in the workers only (a top-level module: importing it loads no NumPy)
_WORKER_ENV = "uwbimu._worker_env"


def _one_blas_thread() -> None:
    """Pool initializer where there is no forkserver (runs in the worker, not in the caller)."""
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(k, "1")


def _new_executor(workers: int, preload) -> ProcessPoolExecutor:
    import multiprocessing as mp

    ctx = mp.get_context("forkserver") if "forkserver" in mp.get_all_start_methods() else None
    initializer = None
    if ctx is not None:
        # Workers fork from a server that has already imported the heavy modules; the server
        # imports _worker_env first, so the BLAS thread variables are set before NumPy loads.
        ctx.set_forkserver_preload([_WORKER_ENV, *preload])
    else:  # spawn (no forkserver): set them in each worker before it runs a task
        initializer = _one_blas_thread
    return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=initializer)


class ProcessPool:
    """A local process pool kept open over several :func:`execute` calls (``execute(..., pool=p)``).

    Its worker processes live until the ``with`` block ends, so a module-level cache a task fills in a
    worker (e.g. the t_d profile's problem and IMU factors, :mod:`uwbimu.calibration.profile_walk`) serves
    the tasks of the later calls too, and the processes start once.  Same workers and preload rules as
    :func:`execute`'s own pool::

        with ProcessPool(2, preload=("uwbimu.calibration.profile_walk",)) as pool:
            execute(fn, tasks_a, keep, workers=2, pool=pool)
            execute(fn, tasks_b, keep, workers=2, pool=pool)
    """

    def __init__(self, workers: int, preload: tuple[str, ...] = ("uwbimu.sim", "uwbimu.estimation")):
        self.workers = int(workers)
        self.preload = tuple(preload)
        self.executor: Optional[ProcessPoolExecutor] = None

    def __enter__(self) -> "ProcessPool":
        self.executor = _new_executor(self.workers, self.preload)
        return self

    def __exit__(self, exc_type, *exc) -> None:
        ex, self.executor = self.executor, None
        if ex is not None:
            # after an exception (Ctrl-C): do not wait for queued tasks
            ex.shutdown(wait=exc_type is None, cancel_futures=exc_type is not None)


def _run_pool(fn, tasks: list, workers: int, on_chunk: Callable[[Any], None], describe, preload,
              pool: Optional[ProcessPool] = None) -> list[str]:
    failures: list[str] = []
    own = pool is None or pool.executor is None
    ex = _new_executor(workers, preload) if own else pool.executor
    try:
        pending = {ex.submit(fn, t): t for t in tasks}  # workers start here
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for f in done:
                t = pending.pop(f)
                try:
                    chunk = f.result()
                except Exception as exc:  # e.g. BrokenProcessPool: a worker died
                    failures.append(f"{describe(t)}: {type(exc).__name__}: {exc}")
                    continue
                on_chunk(chunk)
    except BaseException:
        # Ctrl-C or a failed write: do not wait for the queued tasks (finished ones are on disk).
        if own:
            ex.shutdown(wait=False, cancel_futures=True)
        raise
    if own:
        ex.shutdown(wait=True)
    return failures


def _run_dask(fn, tasks: list, client, on_chunk: Callable[[Any], None], describe) -> list[str]:
    require("distributed", "dask", "a Dask study")
    from distributed import as_completed

    failures: list[str] = []
    token = uuid.uuid4().hex[:8]
    futs = [client.submit(fn, t, pure=False, key=f"{getattr(fn, '__name__', 'task')}-{token}-{i}")
            for i, t in enumerate(tasks)]
    by_key = {f.key: t for f, t in zip(futs, tasks)}
    gather_retries: dict[str, int] = {}
    ac = as_completed(futs)
    for f in ac:
        t = by_key[f.key]
        try:
            chunk = f.result()
        except Exception as exc:
            # A worker that dies while its result is being fetched leaves the key re-queued
            # ("couldn't gather keys ... processing") and the fetch raises on the client although
            # the task did not fail: wait for it again. A task that itself failed on every
            # retry has status "error" and is reported.
            n = gather_retries.get(f.key, 0)
            if f.status != "error" and n < 3:
                gather_retries[f.key] = n + 1
                time.sleep(0.5)
                ac.add(f)
                continue
            failures.append(f"{describe(t)}: {type(exc).__name__}: {exc}")
            continue
        on_chunk(chunk)
        f.release()
    return failures



def _with_dask(fn, tasks, client, scheduler, dask_local, workers, on_chunk, describe) -> list[str]:
    if client is not None:
        return _run_dask(fn, tasks, client, on_chunk, describe)
    require("distributed", "dask", "a Dask study")
    from distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler) as c:
            return _run_dask(fn, tasks, c, on_chunk, describe)
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster, Client(cluster) as c:
        return _run_dask(fn, tasks, c, on_chunk, describe)


def execute(
    fn: Callable[[Any], Any],
    tasks: list,
    on_result: Callable[[Any], None],
    workers: Optional[int] = None,
    client=None,
    scheduler: Optional[str] = None,
    dask_local: bool = False,
    describe: Callable[[Any], str] = repr,
    preload: tuple[str, ...] = ("uwbimu.sim", "uwbimu.estimation"),
    pool: Optional[ProcessPool] = None,
) -> list[str]:
    """Run ``fn(task)`` for every task and pass each result to ``on_result`` as it arrives.

    Parameters
    ----------
    fn : module-level (picklable) function ``task -> result``.
    tasks : the tasks (picklable).
    on_result : called in this process, once per finished task, in completion order.
    workers : local processes (default: all cores); 1 runs serially in this process
        (exceptions then propagate).  With ``dask_local``: the LocalCluster's workers.
    client, scheduler, dask_local : run on Dask instead (an existing ``distributed.Client``,
        a scheduler address, or a loopback LocalCluster).
    describe : ``task -> str`` naming a task in the failure list.
    preload : modules the forkserver imports once before forking the pool's workers.
    pool : an open :class:`ProcessPool` to run on (its workers and preload; ``workers`` > 1 still required):
        the processes and their caches outlive this call.  None: a pool for this call only.

    Returns
    -------
    One line ``"<describe(task)>: <error>"`` per task that did not finish (e.g. a dead
    worker); the others have been handed to ``on_result``.
    """
    if client is not None or scheduler or dask_local:
        return _with_dask(fn, tasks, client, scheduler, dask_local, int(workers or os.cpu_count() or 1),
                          on_result, describe)
    workers = int(workers or os.cpu_count() or 1)
    if workers == 1:
        for t in tasks:
            on_result(fn(t))
        return []
    return _run_pool(fn, tasks, workers, on_result, describe, preload, pool)
