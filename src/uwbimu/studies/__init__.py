"""Monte Carlo studies: scenarios x seeds x estimators, on a process pool or Dask.

Public API::

    from uwbimu.studies import load_config, run_study, execute

    summary = run_study(load_config("study.yaml"), "out/", workers=4)

Modules, one concern each (imports go config <- worker, store <- report <- runner):
``config`` (YAML model, seeds), ``worker`` (one task: simulate, estimate, score),
``store`` (output folder, chunks, resume), ``executors`` (:func:`execute`: process pool,
serial or Dask), ``report`` (summary and plots), ``crlb`` (posterior Cramer-Rao bound),
``runner`` (:func:`run_study`), ``examples`` (built-in studies), ``eskf_fix`` (ESKF from
a surveyed take-off point).  See ``docs/montecarlo.md``.
"""

from uwbimu.studies.config import (  # noqa: F401
    CHUNK_DIR, CONFIG_FILE, ROW_COLUMNS, TIMING_COLUMNS, EstimatorEntry, MonteCarloConfig, MonteCarloError, StudyConfigError,
    ScenarioEntry, config_from_dict, load_config, resolve_scenario, resolved_study, run_seeds,
)
from uwbimu.parallel import execute  # noqa: F401
from uwbimu.studies.runner import iter_rows_equal_ignoring_timing, run_study  # noqa: F401
from uwbimu.studies.store import chunk_files, read_done  # noqa: F401
from uwbimu.studies.worker import run_chunk, run_metrics  # noqa: F401

__all__ = [
    "CHUNK_DIR", "CONFIG_FILE", "ROW_COLUMNS", "TIMING_COLUMNS", "EstimatorEntry", "MonteCarloConfig",
    "MonteCarloError", "StudyConfigError", "ScenarioEntry", "config_from_dict", "load_config", "resolve_scenario", "resolved_study",
    "run_seeds", "execute", "iter_rows_equal_ignoring_timing", "run_study", "chunk_files", "read_done",
    "run_chunk", "run_metrics",
]
