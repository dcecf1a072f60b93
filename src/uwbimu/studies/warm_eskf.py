"""Imported by a process pool's forkserver only (:func:`uwbimu.parallel._new_executor`, when the preload names
:mod:`uwbimu.estimation`): runs the ESKF once on a 3-second built-in flight so that numba's machine code of the
filter kernels is in the server's memory before it forks the workers.

Why: numba loads a kernel's machine code from its disk cache on the kernel's first call *in each process*
(about 1 s of CPU for the filter loop and the kernels it calls, more on a busy machine); a worker forked from
a server that has it loaded starts warm.  The run is the warm-up of ``uwbimu.cli.compile_notice.warm_up``
(same flight, same argument types, so the workers' calls find the loaded code).  A failure here only means
cold workers: it is swallowed.
"""

from __future__ import annotations


def _warm() -> None:
    try:
        from uwbimu.estimation import EskfOptions, run_eskf
        from uwbimu.sim import builtin_scenario, simulate

        run_eskf(simulate(builtin_scenario("calibration-flight").updated(duration=3.0)), EskfOptions())
    except Exception:  # noqa: BLE001 - an optimisation only: the workers then load the code themselves
        pass


_warm()
