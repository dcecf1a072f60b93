"""uwbimu: UWB-aided inertial localization with online lever-arm and time-offset calibration."""

__version__ = "0.1.0"
