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

import math
import os
import time
import uuid
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Optional

from uwbimu.optional import require

# --------------------------------------------------------------------------
# Executors
# --------------------------------------------------------------------------
# one BLAS thread per worker, set in the workers only (a top-level module: importing it loads no NumPy)
_WORKER_ENV = "uwbimu._worker_env"
# imported by the server after the preload when the tasks run the ESKF: loads its machine code once
_WARM_ESKF = "uwbimu.studies.warm_eskf"

#: seconds a fresh local pool takes to be up (the forkserver imports the preload and loads numba's machine
#: code, then forks a worker): 4.7 s wall measured for the ESKF preload on the 2-core development machine
#: (``_new_executor(1, ("uwbimu.sim", "uwbimu.estimation", "uwbimu.estimators"))`` to its first result),
#: 3 s on an idle one; an upper-side figure, so a pool is started only where it clearly pays
POOL_START_S = 4.0
#: the same once this process's forkserver runs (a later pool only forks workers from it)
POOL_RESTART_S = 0.3
#: a pool forked from this (warm) process, :func:`_fork_executor`: the workers inherit its imports and
#: numba's loaded machine code, so they start in a fraction of a second (7 ms wall to the first result for
#: one worker forked from a process with the estimator loaded, 2-core development machine; an upper-side
#: figure, for a loaded machine and a larger process)
POOL_FORK_S = 0.3


def pool_start_estimate() -> float:
    """Seconds [s] until a new local pool would run its first task: :data:`POOL_START_S`, or
    :data:`POOL_RESTART_S` when this process's forkserver already runs (an earlier pool started it)."""
    try:
        from multiprocessing import forkserver

        alive = getattr(forkserver._forkserver, "_forkserver_pid", None) is not None
    except Exception:  # noqa: BLE001 - no forkserver on this platform: every pool starts cold
        alive = False
    return POOL_RESTART_S if alive else POOL_START_S


def pool_pays(remaining_s: float, task_s: float = 0.0, start_s: Optional[float] = None) -> bool:
    """The rule of ``execute(..., caller=True, measure_first=True)``: start a pool only when the serial work
    left, ``remaining_s`` [s], exceeds the pool's start ``start_s`` (default :func:`pool_start_estimate`)
    plus two tasks of ``task_s`` [s].

    Why: while the pool starts, the caller runs tasks alone (no gain) and the start's imports take a core
    from it; once it is up the pool shortens the job by at most half the work left (2 workers), and the last
    task a worker took may end up to a task after the caller's (the caller then waits for it).  Measured with the repeatability
    windows on the 2-core development machine (``workers=2`` on a plain pool against serially): 4 INRoL
    windows of ~1 s, 11.0 s wall against 4.7 s; 6 windows of a 10-minute 1 kHz log, 15.7 s against 11.7 s:
    a start that cannot pay costs more than it saves."""
    start = pool_start_estimate() if start_s is None else start_s
    return remaining_s > start + 2.0 * task_s


def fork_pays(n_left: int, task_s: float, workers: int = 2, start_s: Optional[float] = None) -> bool:
    """The rule for a pool forked from the caller (:func:`_fork_executor`): its start, ``start_s`` [s]
    (default :data:`POOL_FORK_S`), blocks the caller, then ``workers`` processes share the ``n_left`` tasks of
    ``task_s`` [s] each; it pays when that ends before the caller alone would,
    ``start_s + ceil(n_left / workers) * task_s < n_left * task_s``.  Unlike a forkserver's start
    (:func:`pool_pays`) it is short against a task, so two tasks left of a few tenths of a second each
    already pay (the repeatability windows)."""
    start = POOL_FORK_S if start_s is None else start_s
    n = int(n_left)
    return n >= 2 and start + math.ceil(n / max(int(workers), 1)) * task_s < n * task_s


def _can_fork() -> bool:
    """Whether :func:`_fork_executor` may be used now: the platform has ``fork`` and this process runs one
    thread (a fork copies only the calling thread: a lock another thread held would stay locked in the
    child forever)."""
    import multiprocessing as mp
    import threading

    return "fork" in mp.get_all_start_methods() and threading.active_count() == 1


def _fork_executor(workers: int) -> ProcessPoolExecutor:
    """A pool whose workers are forked from this process, now, from this thread (call only when
    :func:`_can_fork`).  Why: the caller of ``execute(..., caller=True, measure_first=True)`` has just run
    a task, so its imports are done and numba's machine code is loaded; forked workers start warm, where a
    forkserver's would import and load it all again (:data:`POOL_START_S`).  A ``fork`` pool starts its
    processes at the first submit, before its manager thread: the probe submitted here forks them while
    this process still runs one thread."""
    import multiprocessing as mp

    ex = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("fork"), initializer=_one_blas_thread)
    ex.submit(os.getpid).result()
    return ex


def _one_blas_thread() -> None:
    """Pool initializer (runs in the worker, not in the caller): one BLAS thread where the variables are unset.

    Where there is no forkserver it is the only place they are set.  A forkserver pool runs it too: a
    server already running when the pool starts (one the user's code or another library started, with
    its own preload) keeps that preload, so :data:`_WORKER_ENV` may never have been imported there."""
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(k, "1")


def _new_executor(workers: int, preload) -> ProcessPoolExecutor:
    import multiprocessing as mp

    ctx = mp.get_context("forkserver") if "forkserver" in mp.get_all_start_methods() else None
    initializer = _one_blas_thread
    if ctx is not None:
        # Workers fork from a server that has already imported the heavy modules; the server
        # imports _worker_env first, so the BLAS thread variables are set before NumPy loads.
        # Tasks that run the ESKF: the server also loads its compiled kernels (_WARM_ESKF), once,
        # instead of every worker loading them on its first task.
        extra = [_WARM_ESKF] if "uwbimu.estimation" in preload else []
        ctx.set_forkserver_preload([_WORKER_ENV, *preload, *extra])
    # spawn (no forkserver): the initializer is what sets them in each worker before it runs a task
    return ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=initializer)


def _take(f, t, on_chunk, describe, failures: list[str]) -> None:
    """Hand a finished future's chunk to ``on_chunk``, or record why task ``t`` failed."""
    try:
        chunk = f.result()
    except Exception as exc:  # e.g. BrokenProcessPool: a worker died
        failures.append(f"{describe(t)}: {type(exc).__name__}: {exc}")
        return
    on_chunk(chunk)


def _run_with_caller(fn, tasks: list, workers: int, on_chunk: Callable[[Any], None], describe, preload,
                     pool: Optional["ProcessPool"] = None, measure_first: bool = False) -> list[str]:
    """:func:`execute` with the caller as one of the ``workers``: ``workers - 1`` pool processes and this one.

    Why: a pool's processes start cold (the forkserver imports the preload, each worker loads numba's
    machine code and rebuilds its caches: seconds of start), while this process is warm.  The caller runs
    tasks from the back of the list at once; feeder threads hand tasks from the front to the pool only
    after a probe task came back (the pool is up), so no task waits for a pool that is still starting, and a
    short job ends as fast as serially.  Each task is pickled and unpickled before the caller runs it (the
    copy a worker gets), so a task's result does not depend on where it ran.  The pool is started in a
    thread too: a forkserver's first process start blocks until the server has imported the preload.

    ``measure_first``: before any pool starts, the caller runs tasks (from the back) and times each; the pool
    starts once the tasks left would take longer serially than its start and two tasks (:func:`pool_pays`
    with the latest task's duration; the first task's only when one task is left, as it carries the
    process's one-time warm-up), else the caller runs them all and no pool starts (a job of short windows
    ends as fast as serially, with no core lost to a start that cannot pay).  An open ``pool`` is used as
    it is.
    """
    import pickle
    import queue as _queue
    import threading
    from collections import deque

    failures: list[str] = []
    own = pool is None or pool.executor is None
    box = [None if own else pool.executor]  # the executor, created by the starter thread when own
    todo = deque(tasks)

    def run_here(t) -> None:
        try:
            chunk = fn(pickle.loads(pickle.dumps(t)))
        except Exception as exc:  # noqa: BLE001 - reported like a worker's failure
            failures.append(f"{describe(t)}: {type(exc).__name__}: {exc}")
        else:
            on_chunk(chunk)

    forked = False
    if measure_first and own:
        n_done = 0
        while todo:
            w0 = time.perf_counter()
            run_here(todo.pop())
            n_done += 1
            # the first task carries this process's one-time warm-up (numba's machine code, caches): its
            # duration decides only when it was the last but one
            d = time.perf_counter() - w0
            if _can_fork():
                # a forked pool costs little: decide on the first task (its warm-up only makes it look longer)
                if fork_pays(len(todo), d, workers):
                    break
            elif (n_done > 1 or len(todo) <= 1) and pool_pays(len(todo) * d, d):
                break
        if not todo:
            return failures
        tasks = list(todo)
        if _can_fork():
            try:
                box[0] = _fork_executor(max(1, workers - 1))
                forked = True
            except Exception:  # noqa: BLE001 - no fork pool: the forkserver's, started below
                box[0] = None
    results: _queue.Queue = _queue.Queue()
    stop, up, dead = threading.Event(), threading.Event(), threading.Event()
    lock = threading.Lock()
    if forked:
        up.set()  # the probe came back in _fork_executor

    def starter() -> None:
        # in a thread: a forkserver's first process start blocks until the server has imported the preload
        try:
            if box[0] is None:
                box[0] = _new_executor(max(1, workers - 1), preload)
            box[0].submit(os.getpid).result()  # the probe: the pool is up
            ok = True
        except Exception:  # noqa: BLE001 - a pool that cannot start: the caller runs everything
            ok = False
        with lock:
            (up if ok else dead).set()
            if stop.is_set() and own and box[0] is not None:  # the caller finished first
                box[0].shutdown(wait=False, cancel_futures=True)

    def feeder() -> None:
        while not (up.is_set() or dead.is_set() or stop.is_set()):
            up.wait(0.05)
        if not up.is_set():
            return
        ex = box[0]
        while not stop.is_set():
            try:
                t = todo.popleft()
            except IndexError:
                return
            try:
                f = ex.submit(fn, t)
            except Exception:  # noqa: BLE001 - shut down or broken: back to the caller
                todo.appendleft(t)
                return
            wait([f])
            results.put((f, t))
            if isinstance(f.exception(), BrokenProcessPool):
                return

    threads = [] if forked else [threading.Thread(target=starter, daemon=True, name="uwbimu-pool-start")]
    threads += [threading.Thread(target=feeder, daemon=True, name=f"uwbimu-feeder-{i}")
                for i in range(max(1, workers - 1))]
    for th in threads:
        th.start()

    def finish(cancel: bool) -> None:
        with lock:
            stop.set()
            started = up.is_set() or dead.is_set()
        if own and started and box[0] is not None:
            # not waited for after an exception; otherwise the pool is idle by now (every task handled)
            box[0].shutdown(wait=not cancel, cancel_futures=True)

    handled = 0
    try:
        while handled < len(tasks):
            while True:  # pool results first (on_chunk runs in this thread only)
                try:
                    f, t = results.get_nowait()
                except _queue.Empty:
                    break
                _take(f, t, on_chunk, describe, failures)
                handled += 1
            try:
                t = todo.pop()
            except IndexError:
                try:  # the rest is in the pool (or handed back by a feeder: look again)
                    f, t = results.get(timeout=0.05)
                except _queue.Empty:
                    continue
                _take(f, t, on_chunk, describe, failures)
                handled += 1
                continue
            run_here(t)
            handled += 1
    except BaseException:
        finish(cancel=True)
        raise
    finish(cancel=False)  # a pool still starting is shut down by its starter, not waited for
    return failures


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

    def __init__(self, workers: int, preload: tuple[str, ...] = ("uwbimu.sim", "uwbimu.estimation"),
                 caller: bool = False, lazy: bool = False):
        self.workers = int(workers)
        self.preload = tuple(preload)
        #: the caller is one of the workers (``execute(..., caller=True)``): the pool has ``workers - 1``
        self.caller = bool(caller)
        #: the processes start at :meth:`start`, not on entering the block: a caller that fills a module-level
        #: cache first (the t_d profile's problem) then starts them, forked from itself where it can
        #: (:func:`_can_fork`), so the workers inherit the cache and the loaded modules
        self.lazy = bool(lazy)
        self.executor: Optional[ProcessPoolExecutor] = None

    def __enter__(self) -> "ProcessPool":
        if not self.lazy:
            self.start()
        return self

    def start(self) -> None:
        """Start the processes (once): forked from this process where the platform forks and one Python
        thread runs (a lazy pool), else from the forkserver with the preload."""
        if self.executor is not None:
            return
        n = max(1, self.workers - 1) if self.caller else self.workers
        self.executor = _fork_executor(n) if self.lazy and _can_fork() else _new_executor(n, self.preload)

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
                _take(f, pending.pop(f), on_chunk, describe, failures)
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
    caller: bool = False,
    measure_first: bool = False,
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
    caller : the calling process is one of the ``workers`` (local pool only): it runs tasks at once while
        ``workers - 1`` pool processes start, and the pool gets tasks once it is up
        (:func:`_run_with_caller`).  Worth it where a worker's start (imports, numba's machine code, a
        per-worker cache) is not small against a task: the t_d profile's two walks, short windows.  A
        task that raises in the caller is reported like a worker's failure; ``on_result`` still runs in
        the caller's thread only.
    measure_first : (with ``caller``) time one task in the caller first and start a pool only when the tasks
        left would take longer serially than the pool's start (:func:`pool_pays`): for jobs whose size is
        not known in advance, such as the repeatability windows (a few tenths of a second each).  Where
        the platform forks and this process runs one thread, the pool's workers are forked from this warm
        process (:func:`_fork_executor`, start :data:`POOL_FORK_S`), else started by the forkserver.

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
    if caller:
        return _run_with_caller(fn, tasks, workers, on_result, describe, preload, pool, measure_first)
    return _run_pool(fn, tasks, workers, on_result, describe, preload, pool)
