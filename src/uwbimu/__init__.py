"""uwbimu: UWB-aided inertial localization with online lever-arm and time-offset calibration.

The public Python API, one obvious entry point per job::

    import uwbimu

    ds = uwbimu.simulate(uwbimu.builtin_scenario("calibration-flight"))   # or uwbimu.load_dataset(path)
    res = uwbimu.run_eskf(ds, uwbimu.EskfOptions())                       # online lever arm / t_d
    verdict = uwbimu.structural_verdict(uwbimu.ObservabilityConfig())     # Lie-derivative rank test

Names are resolved lazily (PEP 562), so ``import uwbimu`` does not pay for numba,
CasADi or matplotlib until a function that needs them is used.  Every error the
toolkit raises on purpose derives from :class:`uwbimu.UwbimuError`.
"""

from __future__ import annotations

from importlib import import_module

__version__ = "0.1.0"

#: public name -> "module:attribute"
_EXPORTS = {
    # data
    "Dataset": "uwbimu.io.dataset:Dataset",
    "load_dataset": "uwbimu.io.loader:load_dataset",
    "write_dataset": "uwbimu.io.dataset:write_dataset",
    "check_dataset": "uwbimu.io.check:check_dataset",
    # simulation
    "Scenario": "uwbimu.sim.scenario:Scenario",
    "builtin_scenario": "uwbimu.sim.builtin:builtin_scenario",
    "simulate": "uwbimu.sim.simulate:simulate",
    # estimation
    "EskfOptions": "uwbimu.estimation.options:EskfOptions",
    "run_eskf": "uwbimu.estimation.eskf:run_eskf",
    "Eskf": "uwbimu.estimation.streaming:Eskf",
    "write_estimate": "uwbimu.estimation.outputs:write_outputs",
    "EstimationResult": "uwbimu.estimation.result:EstimationResult",
    "CalibrationEstimate": "uwbimu.estimation.result:CalibrationEstimate",
    "Event": "uwbimu.estimation.result:Event",
    "CalibrationOptions": "uwbimu.calibration:CalibrationOptions",
    "calibrate": "uwbimu.calibration:calibrate",
    # analysis
    "ObservabilityConfig": "uwbimu.observability.config:ObservabilityConfig",
    "structural_verdict": "uwbimu.observability.structural:structural_verdict",
    "delay_verdict": "uwbimu.observability.delay:delay_verdict",
    "window_observability": "uwbimu.observability.window:window_observability",
    "StructuralVerdict": "uwbimu.observability.verdicts:StructuralVerdict",
    "DelayVerdict": "uwbimu.observability.verdicts:DelayVerdict",
    # design
    "placement_example": "uwbimu.design.run:builtin_example",
    "place": "uwbimu.design.run:run_placement",
    "design_calibration": "uwbimu.design.trajectory.calibration:design_calibration",
    "plan_point_mass": "uwbimu.design.trajectory.pointmass:plan_point_mass",
    "solve_seed_ocp": "uwbimu.design.trajectory.seed_ocp:solve_seed_ocp",
    # studies and evaluation
    "run_study": "uwbimu.studies.runner:run_study",
    "evaluate": "uwbimu.eval.evaluate:evaluate_output",
    "repeatability": "uwbimu.eval.repeatability:repeatability",
    "report": "uwbimu.eval.report:write_report",
    # errors
    "UwbimuError": "uwbimu.errors:UwbimuError",
}

__all__ = sorted([*_EXPORTS, "__version__"])


def __getattr__(name: str):
    target = _EXPORTS.get(name)
    if target is None:
        raise AttributeError(f"module 'uwbimu' has no attribute {name!r}")
    module, attr = target.split(":")
    value = getattr(import_module(module), attr)
    globals()[name] = value  # cache: later look-ups skip __getattr__
    return value


def __dir__() -> list[str]:
    return __all__
