"""Simulator of UWB-IMU flights with exact truth.

Public API::

    from uwbimu.sim import Scenario, simulate, builtin_scenario, list_scenarios, load_scenario

    sc = builtin_scenario("calibration-flight")      # a pydantic Scenario
    sc = sc.model_copy(update={"time_offset": 0.05})  # or Scenario.model_validate(dict)
    ds = simulate(sc)                                 # uwbimu.io.dataset.Dataset with truth

See ``docs/simulator.md`` for the scenario YAML reference and the trajectory
file format.
"""

from uwbimu.sim.builtin import builtin_scenario, list_scenarios
from uwbimu.sim.scenario import (
    ANCHOR_PRESETS,
    AnchorSpec,
    ImuSpec,
    NlosBurst,
    Scenario,
    ScenarioError,
    Seeds,
    TagSpec,
    UwbSpec,
    load_scenario,
    validate_scenario,
)
from uwbimu.sim.simulate import SimResult, simulate, simulate_full
from uwbimu.sim.trajfile import TrajectoryFileError, read_trajectory_file, write_trajectory_file

__all__ = [
    "ANCHOR_PRESETS",
    "AnchorSpec",
    "ImuSpec",
    "NlosBurst",
    "Scenario",
    "ScenarioError",
    "Seeds",
    "SimResult",
    "TagSpec",
    "TrajectoryFileError",
    "UwbSpec",
    "builtin_scenario",
    "list_scenarios",
    "load_scenario",
    "read_trajectory_file",
    "simulate",
    "simulate_full",
    "validate_scenario",
    "write_trajectory_file",
]
