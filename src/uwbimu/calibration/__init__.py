"""Batch (full-log) calibration with a GTSAM factor graph: ``uwbimu calibrate``.

    from uwbimu.calibration import CalibrationOptions, calibrate, write_calibration

    res = calibrate(dataset, CalibrationOptions())
    write_calibration(res, "out/")   # calibration.yaml, trajectory.csv, residuals.csv, td_profile.csv/png

See docs/calibrate.md.
"""

from uwbimu.calibration.options import CalibrationOptions, TdProfileOptions  # noqa: F401
from uwbimu.calibration.batch import CalibrationResult, calibrate  # noqa: F401
from uwbimu.calibration.outputs import write_calibration  # noqa: F401

__all__ = ["CalibrationOptions", "TdProfileOptions", "CalibrationResult", "calibrate", "write_calibration"]
