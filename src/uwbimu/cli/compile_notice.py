"""One-time compilation of the estimator's numba kernels, announced and timed (issue 30 item 1).

The ESKF's compiled loop (:func:`uwbimu.estimation.kernels.filter_loop` and the kernels it
calls) is compiled by numba on its first call and kept in numba's disk cache
(``cache=True``); on a fresh installation, or after a kernel source changed, that first
call takes from ~20 s on an idle machine to minutes on a busy one, and used to pass as
silence followed by a "run time" that was mostly compilation.

:func:`ensure_compiled` is called by every verb that runs the ESKF, before the run: when
the compiled cache is cold it prints one line, compiles the kernels by running the ESKF on
a 3-second built-in simulated flight (the same argument types as a real run, so the real
run finds the compiled code), and prints the measured cost.  The verb's own timings then
hold the filter pass only, and the compile time is reported next to them.

The per-window observability bounds (``observability log``, the demo's timeline) have their own
kernels and the same treatment (group ``"window"``, :data:`GROUPS`).

Cold is read from numba's cache index of the kernels (an index holding no entry for the
current source, see ``numba.core.caching``), never by compiling; kernels already compiled
in this process count as warm.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Optional

#: Entry points of the ESKF's compiled code (module ``uwbimu.estimation.kernels``); the filter
#: loop calls every other kernel of a run, so its cache entry stands for them all.
ESKF_KERNELS = ("filter_loop",)
#: Entry points of the per-window observability bounds (module ``uwbimu.observability.window``):
#: the posterior CRB (``--bound pcrb``) and the Gramian (``--bound gramian``).
WINDOW_KERNELS = ("_window_pcrb", "_window_information")
#: Kernel groups: module, entry points and a one-word description for the notice.
GROUPS = {
    "eskf": ("uwbimu.estimation.kernels", ESKF_KERNELS, "the estimator's kernels"),
    "window": ("uwbimu.observability.window", WINDOW_KERNELS, "the observability kernels"),
}
#: Duration of the warm-up flight [s]: long enough for the initialiser and every update kind
#: the built-in flight has, short enough that the filter pass itself takes milliseconds.
WARMUP_DURATION_S = 3.0


@dataclass
class CompileNotice:
    """What :func:`ensure_compiled` did.

    Attributes
    ----------
    cold : bool
        The compiled cache was cold (so the kernels were compiled now).
    seconds : float
        Wall time of the compilation (warm-up run included) [s]; 0.0 when warm.
    error : str or None
        ``"ExceptionType: message"`` when the warm-up run itself failed (the kernels the
        run reached are compiled; the real run compiles the rest, and reports its own error).
    """

    cold: bool
    seconds: float = 0.0
    error: Optional[str] = None


def _dispatchers(group: str = "eskf"):
    import importlib

    module, names, _ = GROUPS[group]
    mod = importlib.import_module(module)
    return [getattr(mod, name) for name in names]


def kernels_cold(group: str = "eskf") -> bool:
    """True when a group's compiled kernels are neither in this process nor in numba's disk cache.

    Reads the cache index of each entry point (:data:`GROUPS`): numba returns an empty index
    when none was written or when it was written for another version of the source (which
    :func:`uwbimu.models.kernels.refresh_stale_cache` also empties).  An index that cannot be
    read counts as cold.
    """
    for d in _dispatchers(group):
        if not hasattr(d, "signatures"):  # NUMBA_DISABLE_JIT=1: plain Python, nothing to compile
            return False
        if d.signatures:  # compiled (or loaded) in this process already
            continue
        cache = getattr(d, "_cache", None)
        try:
            index = cache._cache_file._load_index()  # numba's own staleness rule (source stamp)
        except Exception:  # noqa: BLE001 - any unreadable cache is a cold cache
            return True
        if not index:
            return True
    return False


def warm_up(group: str = "eskf") -> None:
    """Compile a group's kernels by running its code on a short built-in simulated flight."""
    from uwbimu.sim import builtin_scenario, simulate

    if group == "eskf":
        from uwbimu.estimation import EskfOptions, run_eskf

        run_eskf(simulate(builtin_scenario("calibration-flight").updated(duration=WARMUP_DURATION_S)), EskfOptions())
        return
    from uwbimu.observability.window import WindowOptions, window_observability

    ds = simulate(builtin_scenario("calibration-flight").updated(duration=4 * WARMUP_DURATION_S))
    for bound in ("pcrb", "gramian"):
        window_observability(ds, None, WindowOptions(window=2 * WARMUP_DURATION_S, bound=bound))


def ensure_compiled(console=None, group: str = "eskf") -> CompileNotice:
    """Compile a group of kernels now when the cache is cold, with a notice and its measured cost.

    Parameters
    ----------
    console : rich.console.Console, optional
        Where the two lines go (nothing is printed without one).
    group : str
        ``"eskf"`` (the filter) or ``"window"`` (the per-window observability bounds).

    Returns
    -------
    CompileNotice
        ``cold`` and the compile time [s]; a warm cache returns at once with ``cold=False``.
    """
    if not kernels_cold(group):
        return CompileNotice(cold=False)
    what = GROUPS[group][2]
    if console is not None:
        console.print(f"compiling {what} (once per installation; up to a few minutes) ...")
    t0 = time.perf_counter()
    error = None
    try:
        if console is not None:
            with console.status(f"compiling {what} (numba)"):
                warm_up(group)
        else:
            warm_up(group)
    except Exception as exc:  # noqa: BLE001 - the real run reports its own error
        error = f"{type(exc).__name__}: {' '.join(str(exc).split())}"
    seconds = time.perf_counter() - t0
    if console is not None:
        console.print(f"compiled in {seconds:.0f} s, once" + (" (warm-up run failed; the run compiles the rest)"
                                                            if error else ""))
    return CompileNotice(cold=True, seconds=seconds, error=error)
