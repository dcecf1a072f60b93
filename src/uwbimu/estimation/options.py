"""Options of the error-state EKF, in one typed place (pydantic, loadable from YAML).

Every number the estimator uses is here; ``examples/estimator.yaml`` lists
them all with their defaults.  Calibration parameters have a *mode*:

* ``estimate``: in the state and corrected by the updates;
* ``consider``: kept in the covariance with its prior but never corrected
  (Schmidt / consider update: the uncertainty of a frozen value is accounted
  for in every other state's covariance);
* ``fixed``: taken as exactly known (zero covariance).

Every number must be finite (``allow_inf_nan=False``: a NaN prior or an infinite sigma is refused
when the options are read, naming the field, not after minutes of filtering), and the counts and
rates that size the work have upper bounds.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, field_validator

from uwbimu.models.imu import IMU_PRESETS, ImuNoise, imu_preset

Mode = Literal["estimate", "consider", "fixed"]


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class LeverArmOptions(_Strict):
    mode: Mode = "estimate"

    @field_validator("prior")
    @classmethod
    def _three(cls, v):
        if isinstance(v, list) and len(v) != 3:
            raise ValueError("lever_arm.prior must have 3 components [x, y, z] in metres")
        return v

    prior: Optional[Union[list[float], Literal["dataset"]]] = Field(
        default="dataset",
        description="prior lever arm [m] (IMU frame) as [x, y, z]; 'dataset' (default): the tag's nominal lever "
        "arm from dataset.yaml (an importer's documented mounting, e.g. the UTIL Crazyflie's 9 cm antenna mast; "
        "zero when absent); None: zero. A log that does not identify the lever arm keeps this value (held in "
        "consider mode), so a documented offset is better than zero there",
    )
    prior_sd: float = Field(default=0.3, gt=0, description="prior sd per axis [m]")
    random_walk: float = Field(default=0.0, ge=0, description="process noise density [m/sqrt(s)]")
    min_rotation_rate: float = Field(
        default=0.02, ge=0,
        description="[rad/s] when the RMS bias-corrected gyro rate over the last excitation.window_s is below "
        "this, a range does not update the lever arm (Schmidt/consider for that range): rotation-free motion "
        "carries no lever-arm information, and an EKF linearised at a wandering attitude estimate would "
        "otherwise invent some (false confidence); 0 disables",
    )


class TimeOffsetOptions(_Strict):
    mode: Mode = "estimate"
    prior: Optional[float] = Field(default=None, description="prior t_d [s]; None: from the initialiser's grid search (or 0)")
    prior_sd: float = Field(default=0.1, gt=0, description="prior sd [s] when no grid search is made")
    random_walk: float = Field(default=0.0, ge=0, description="process noise density [s/sqrt(s)]")


class AnchorBiasOptions(_Strict):
    mode: Mode = "fixed"
    prior_sd: float = Field(
        default=0.1, gt=0,
        description="prior sd of each anchor's range bias [m] (the stationary sd when correlation_time is set)",
    )
    correlation_time: Optional[float] = Field(
        default=None, gt=0,
        description="[s] None: constant biases; else each bias is a first-order Gauss-Markov process with this "
        "correlation time and stationary sd prior_sd (slowly varying, direction-dependent range errors)",
    )


class TdoaPairBiasOptions(_Strict):
    """A constant bias per anchor pair of the TDoA (e.g. a clock-correction or antenna-delay error that
    does not split into per-anchor terms); one state per pair seen in the log (``Eskf``: the pairs given
    to the constructor)."""

    mode: Literal["fixed", "estimate"] = Field(default="fixed", description="'estimate': one bias state per pair")
    prior_sd: float = Field(default=0.1, gt=0, description="prior sd of each pair's bias [m]")


class GatingOptions(_Strict):
    probability: float = Field(default=0.999, gt=0, le=1, description="chi2(1) gate level; 1 disables the gate")
    robust: Literal["none", "huber", "geman-mcclure"] = "huber"
    robust_c: float = Field(default=2.5, gt=0, description="robust-loss threshold in innovation sigmas")
    reopen_after: int = Field(default=20, ge=1, description="accept an anchor's range after this many consecutive rejections")


class InitOptions(_Strict):
    window_s: float = Field(default=1.0, gt=0, description="ranges / accelerometer window for the first fix [s]")
    position_sd: float = Field(default=0.3, gt=0, description="[m]")
    velocity_sd: float = Field(default=0.5, gt=0, description="[m/s]")
    roll_pitch_sd_deg: float = Field(default=5.0, gt=0)
    yaw: Optional[float] = Field(default=None, description="known initial yaw [rad]; None: search a bank of hypotheses")
    yaw_sd_deg: float = Field(default=15.0, gt=0, description="yaw sd after the bank search (or around `yaw`)")
    yaw_hypotheses: int = Field(default=12, ge=1, le=360)
    bank_window_s: float = Field(default=8.0, gt=0, description="length of data each hypothesis is scored on [s]")
    max_wait_s: float = Field(default=30.0, gt=0, description="how long to look for the start of motion [s]")
    refine_s: float = Field(
        default=10.0, ge=0,
        description="bootstrap: a first pass over this many seconds after the bank window sets the prior means "
        "(not the covariances) of the final run; 0 disables",
    )
    search_time_offset: bool = True
    td_grid: list[float] = Field(
        default_factory=lambda: [round(-0.25 + 0.05 * i, 3) for i in range(11)], max_length=201,
        description="time-offset hypotheses [s] of the coarse grid search",
    )
    td_sd_after_grid: float = Field(default=0.03, gt=0,
                                    description="lower bound of the t_d prior sd after the grid search [s]")
    td_max_abs_s: float = Field(default=1.0, gt=0,
                                description="a best grid point on an edge widens the grid up to |t_d| = this [s]")


class HeightOptions(_Strict):
    """Altimeter measurements (``Eskf.push_height``): height of the IMU origin on the IMU clock."""

    sigma: float = Field(default=0.1, gt=0, description="altimeter noise sd [m]")
    bias: Literal["fixed", "estimate"] = Field(
        default="fixed", description="'estimate': one altimeter-bias state (random walk); 'fixed': no bias")
    bias_prior_sd: float = Field(default=1.0, gt=0, description="initial sd of the altimeter bias [m]")
    bias_random_walk: float = Field(default=0.01, ge=0, description="altimeter-bias random walk [m/sqrt(s)]")


class SupervisorOptions(_Strict):
    enabled: bool = True
    max_position_sd: float = Field(default=20.0, gt=0, description="[m]; above: divergence")
    hull_margin: float = Field(default=10.0, gt=0, description="[m] beyond the anchors' bounding box: divergence")
    all_reject_run: int = Field(default=100, ge=1, description="consecutive rejections (all anchors): divergence")
    max_reinit: int = Field(default=5, ge=0, le=100)


class ExcitationOptions(_Strict):
    window_s: float = Field(default=5.0, gt=0, description="sliding window [s]")
    min_rotation_rate: float = Field(default=0.3, gt=0, description="RMS body rate below which the lever arm is not excited [rad/s]")
    min_acceleration: float = Field(default=0.3, gt=0, description="RMS world acceleration below which t_d is not excited [m/s^2]")
    sd_ratio_warn: float = Field(default=0.5, gt=0, le=1, description="warn when a final sd exceeds this fraction of its prior")


class EskfOptions(_Strict):
    """All settings of :func:`uwbimu.estimation.run_eskf`."""

    imu_noise: Optional[Union[str, ImuNoise]] = Field(
        default=None, description="preset name or densities; None: the dataset's imu_noise, else 'bmi088'"
    )
    imu_noise_scale: float = Field(default=1.0, gt=0, description="multiplies every IMU density (tuning)")
    noise: Literal["data", "preset"] = Field(
        default="data",
        description="'data': the IMU densities from the log's spectrum (never below the preset) and the "
        "range/TDoA sd by covariance matching of a first pass's innovations (uwbimu.estimation.noise_from_data); "
        "a noise option given explicitly (imu_noise, imu_noise_scale, range_sigma, tdoa_sigma) is used as given. "
        "'preset': the preset/dataset values only")
    noise_search: bool = Field(
        default=True,
        description="with noise 'data': where covariance matching corrected a range/TDoA sd, choose it by the "
        "filter's own one-step predictive likelihood (outlier mixture), searched from the matched level "
        "(uwbimu.estimation.noise_search; two to four more filter passes)")
    smoother: Literal["off", "forward_backward"] = Field(
        default="off",
        description="'forward_backward': after the filter, a second pass over the time-reversed log fused with "
        "it (two-filter smoother, uwbimu.estimation.smoother): the trajectory at each stamp from the data before "
        "and after it, the lever arm and t_d the mean of both passes with half their difference in the sd; "
        "twice the filter time. 'off': the causal filter (what a robot gets online). uwbimu estimate smooths "
        "unless --no-smooth")
    hold_unidentified: bool = Field(
        default=True,
        description="rerun the filter with the lever arm held at its prior in consider mode when the log "
        "identifies none of its axes and the residuals refute the noise model (sigma_scale > 1), so that it "
        "cannot absorb the unmodelled errors into the trajectory")
    sigma_from_residuals: bool = Field(
        default=True,
        description="multiply the calibration sds by the square root of the residuals' long-run variance "
        "factor when it is significantly above 1 (the model is refuted by its own innovations)")
    range_sigma: Optional[float] = Field(default=None, gt=0, description="[m]; None: the dataset's, else 0.1")
    tdoa_sigma: Optional[float] = Field(
        default=None, gt=0, description="TDoA noise sd [m]; None: the dataset's extra.tdoa_sigma, else sqrt(2) range_sigma")
    accel_bias_sd: Optional[float] = Field(default=None, gt=0, description="initial sd [m/s^2]; None: from the IMU noise")
    gyro_bias_sd: Optional[float] = Field(default=None, gt=0, description="initial sd [rad/s]; None: from the IMU noise")
    lever_arm: LeverArmOptions = Field(default_factory=LeverArmOptions)
    time_offset: TimeOffsetOptions = Field(default_factory=TimeOffsetOptions)
    anchor_bias: AnchorBiasOptions = Field(default_factory=AnchorBiasOptions)
    gating: GatingOptions = Field(default_factory=GatingOptions)
    height: HeightOptions = Field(default_factory=HeightOptions)
    tdoa_pair_bias: TdoaPairBiasOptions = Field(default_factory=TdoaPairBiasOptions)
    init: InitOptions = Field(default_factory=InitOptions)
    supervisor: SupervisorOptions = Field(default_factory=SupervisorOptions)
    excitation: ExcitationOptions = Field(default_factory=ExcitationOptions)
    anchor_frame_up: Optional[Literal["+z", "-z"]] = Field(
        default=None,
        description="None: the dataset's (dataset.yaml anchor_frame_up, else '+z'); given: overrides the dataset. "
        "Direction of gravity-up in the anchors' coordinates: '+z' (the usual z-up frame) or '-z' (a "
        "z-down frame, e.g. an RTLS frame defined upside down; the filter then runs in the anchors' frame turned "
        "180 deg about x, and every output is turned back into the anchors' frame)",
    )
    tag: Optional[str] = Field(default=None, description="tag to use when the log has several; None: the first")
    segment: Literal["auto", "whole"] = Field(
        default="auto",
        description="'auto': detect take-off and landing from the IMU and leave out the time on the floor where "
        "the floor ranges contradict the airborne ones (a shadowed radio; uwbimu.estimation.segments); 'whole': "
        "the whole log")
    start: Optional[float] = Field(default=None, allow_inf_nan=False,
                                   description="use the log from this stamp [s] (overrides segment)")
    end: Optional[float] = Field(default=None, allow_inf_nan=False,
                                 description="use the log up to this stamp [s] (overrides segment)")
    cov_every: int = Field(default=1, ge=1, description="IMU samples per covariance step (preintegrated block)")
    output_rate_hz: float = Field(default=20.0, gt=0, le=1000, description="[Hz] rate of the output trajectory")
    store_covariance: bool = True
    max_lookback_s: float = Field(default=0.6, gt=0, description="how far back a range may be predicted [s]")
    imu_gap_factor: float = Field(default=3.0, gt=1, description="an IMU interval longer than this many nominal periods is a gap")
    uwb_outage_s: float = Field(default=1.0, gt=0, description="no accepted range for this long: outage warning [s]")

    @field_validator("imu_noise")
    @classmethod
    def _known_preset(cls, v):
        if isinstance(v, str):
            try:
                imu_preset(v)
            except KeyError:
                raise ValueError(f"unknown IMU preset {v!r}; known presets: {', '.join(sorted(IMU_PRESETS))}, "
                                 f"or give the densities as a mapping") from None
        return v

    @classmethod
    def from_yaml(cls, path: str | Path) -> "EskfOptions":
        """Load options from a YAML file (unknown keys are an error naming the key)."""
        from uwbimu.io.yamlconfig import load_yaml_model

        def unwrap(data: dict) -> dict:
            # a file holding ``estimator: {...}`` (the Monte Carlo / repeatability layout) is accepted too
            if "estimator" in data and isinstance(data["estimator"], dict) and len(data) == 1:
                return data["estimator"]
            return data

        return load_yaml_model(path, cls, what="estimator options", prepare=unwrap)

    def resolve_imu_noise(self, dataset_noise: Optional[ImuNoise]) -> ImuNoise:
        """IMU noise densities to use (option > dataset.yaml > BMI088 preset), scaled."""
        if isinstance(self.imu_noise, str):
            n = imu_preset(self.imu_noise)
        elif isinstance(self.imu_noise, ImuNoise):
            n = self.imu_noise
        elif dataset_noise is not None:
            n = dataset_noise
        else:
            n = imu_preset("bmi088")
        return n.scaled(self.imu_noise_scale) if self.imu_noise_scale != 1.0 else n
