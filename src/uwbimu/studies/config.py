"""Monte Carlo study configuration: the YAML model, scenario resolution, per-run seeds.

A study is described by a :class:`MonteCarloConfig` (YAML, see ``docs/montecarlo.md``).
For each scenario and each run index ``i`` the scenario is simulated with seeds derived from
``(seed_base, i)`` (:func:`run_seeds`) -- the same seeds for every scenario, so that
scenarios are compared on the same noise draws (paired design).
"""

from __future__ import annotations

import copy
import json
import os
from pathlib import Path
from typing import Any, Literal, Optional

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from uwbimu.errors import ConfigError, InputError
from uwbimu.io.yamlconfig import load_yaml_model, validate_model

CONFIG_FILE = "montecarlo_config.json"
CHUNK_DIR = "chunks"
FORMAT_VERSION = 1

#: Columns of ``montecarlo.csv`` (one row per scenario x run x estimator).
ROW_COLUMNS = [
    "scenario", "run", "estimator", "seed_truth", "seed_noise", "seed_init", "status", "error",
    "n_samples", "rmse_x", "rmse_y", "rmse_z", "rmse_3d", "final_err_x", "final_err_y", "final_err_z",
    "max_err_3d", "nees_pos_mean", "nees_kind", "lever_arm_err", "lever_arm_err_x", "lever_arm_err_y",
    "lever_arm_err_z", "time_offset_err", "ranges_accepted", "n_warnings", "coverage", "divergences", "sim_s",
    "est_s", "sim_cpu_s", "est_cpu_s",
]  # fmt: skip

#: Columns that depend on the machine (excluded from reproducibility checks).
TIMING_COLUMNS = ("sim_s", "est_s", "sim_cpu_s", "est_cpu_s")


class MonteCarloError(InputError):
    """A study that cannot run: OUT started with another config, OUT not a study folder... (exit code 1)."""


class StudyConfigError(MonteCarloError, ConfigError):
    """A study configuration that cannot be used; names file, line and field (exit code 2)."""

    exit_code = ConfigError.exit_code


# --------------------------------------------------------------------------
# Configuration
# --------------------------------------------------------------------------
class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ScenarioEntry(_Strict):
    """One scenario of the study: a built-in name, a YAML file or an inline scenario."""

    name: str = Field(description="label used in the outputs")
    builtin: Optional[str] = Field(default=None, description="name of a built-in scenario")
    file: Optional[str] = Field(default=None, description="scenario YAML (relative to the config file)")
    scenario: Optional[dict[str, Any]] = Field(default=None, description="inline scenario fields")
    overrides: dict[str, Any] = Field(default_factory=dict, description="fields merged (deeply) on top")

    @model_validator(mode="after")
    def _one_source(self):
        n = sum(x is not None for x in (self.builtin, self.file, self.scenario))
        if n != 1:
            raise ValueError(f"scenario {self.name!r}: give exactly one of builtin, file, scenario")
        return self


class EstimatorEntry(_Strict):
    """One estimator of the study with its options."""

    name: str = Field(description="label used in the outputs")
    kind: Literal["eskf", "pointmass"] = "eskf"
    options: dict[str, Any] = Field(default_factory=dict, description="EskfOptions / PointMassOptions fields")
    initial_position_sd: Optional[float] = Field(
        default=None, gt=0,
        description="start from a surveyed take-off point: the true initial position plus N(0, sd^2) per axis "
        "(seeds.init), instead of the estimator's multilateration (needed by the ESKF with 3 anchors; see "
        "uwbimu.studies.eskf_fix)",
    )


class MonteCarloConfig(_Strict):
    """A Monte Carlo study (YAML-loadable)."""

    name: str = "montecarlo"
    description: str = ""
    runs: int = Field(default=100, ge=1, description="seeds per scenario (CLI --runs overrides)")
    seed_base: int = Field(default=0, ge=0, description="run i uses seeds derived from (seed_base, i)")
    chunk_size: Optional[int] = Field(default=None, ge=1, description="runs per task; None: automatic")
    skip_initial_s: float = Field(default=0.0, ge=0, description="exclude the first seconds from RMSE and NEES [s]")
    trace_rate_hz: float = Field(default=5.0, gt=0, description="rate of the stored error traces (for plots) [Hz]")
    crlb: bool = Field(
        default=False,
        description="compute each scenario's posterior Cramer-Rao bound (uwbimu.studies.crlb) once, on the "
        "seeds of run 0, and report RMSE / calibration errors against it (does not change any run)",
    )
    scenarios: list[ScenarioEntry] = Field(min_length=1)
    estimators: list[EstimatorEntry] = Field(min_length=1)

    @model_validator(mode="after")
    def _unique(self):
        for what, items in (("scenario", self.scenarios), ("estimator", self.estimators)):
            names = [x.name for x in items]
            dup = sorted({n for n in names if names.count(n) > 1})
            if dup:
                raise ValueError(f"duplicate {what} names: {dup}")
            bad = [n for n in names if not n or any(c in n for c in "/\\ ,") or n.startswith(".")]
            if bad:
                raise ValueError(f"{what} names must be non-empty without '/', '\\\\', ',' or spaces: {bad}")
        return self


def load_config(path: str | os.PathLike) -> MonteCarloConfig:
    """Read a study YAML; errors name the file and the field."""
    path = Path(path)

    def prepare(data: dict) -> dict:
        for sc in data.get("scenarios") or []:
            if isinstance(sc, dict) and isinstance(sc.get("file"), str) and not Path(sc["file"]).is_absolute():
                sc["file"] = str((path.parent / sc["file"]).resolve())
        return data

    return load_yaml_model(path, MonteCarloConfig, what="Monte Carlo config", error=StudyConfigError, prepare=prepare)


def config_from_dict(data: dict, source: str = "<config>") -> MonteCarloConfig:
    """Validate a study given as a mapping; errors name ``source`` and the field."""
    return validate_model(data, MonteCarloConfig, source=source, what="Monte Carlo config", error=StudyConfigError)


def _deep_merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def resolve_scenario(entry: ScenarioEntry) -> dict:
    """The full scenario of an entry as a plain (JSON-able) dict, validated."""
    from uwbimu.sim import Scenario, builtin_scenario, load_scenario

    try:
        if entry.builtin is not None:
            base = builtin_scenario(entry.builtin).model_dump(mode="json", exclude_none=True)
        elif entry.file is not None:
            base = load_scenario(entry.file).model_dump(mode="json", exclude_none=True)
        else:
            base = dict(entry.scenario or {})
        sc = Scenario.model_validate(_deep_merge(base, entry.overrides))
    except (ValidationError, KeyError, InputError) as exc:  # a scenario that cannot be used (a plain ValueError is a bug)
        raise StudyConfigError(f"scenario '{entry.name}': {exc}") from None
    return sc.model_dump(mode="json", exclude_none=True)


def resolved_study(cfg: MonteCarloConfig) -> dict:
    """Everything that determines the results except the number of runs.

    Stored in ``OUT/montecarlo_config.json``; a rerun into the same ``OUT`` must
    resolve to the same dict (scenarios are stored fully resolved, so a changed
    built-in is caught too).
    """
    d = cfg.model_dump(mode="json")
    d.pop("runs")
    d.pop("chunk_size")  # how work is cut does not change any result
    d.pop("description")
    d.pop("crlb")  # computed at the end from the scenarios; no run depends on it
    d["scenarios"] = [{"name": e.name, "scenario": resolve_scenario(e)} for e in cfg.scenarios]
    d["format_version"] = FORMAT_VERSION
    return json.loads(json.dumps(d, sort_keys=True))


def run_seeds(seed_base: int, run: int) -> tuple[int, int, int]:
    """Seeds ``(truth, noise, init)`` of run ``run`` (independent streams)."""
    s = np.random.SeedSequence([int(seed_base), int(run)]).generate_state(3, dtype=np.uint32)
    return int(s[0] >> 1), int(s[1] >> 1), int(s[2] >> 1)
