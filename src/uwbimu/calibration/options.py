"""Options of the batch calibrator (``uwbimu calibrate --config calibrate.yaml``).

Every number must be finite (``allow_inf_nan=False``), and the settings that size the work have
bounds checked when the options are read: the t_d profile grid (:data:`MAX_PROFILE_POINTS` solves),
the iteration counts, and, once the log is known, the drift knots
(:meth:`RangeBiasDrift.knot_count`, at most :data:`MAX_DRIFT_KNOTS`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, field_validator, model_validator

# Validators raise ConfigError (a ValueError, so pydantic wraps it in its ValidationError); load_yaml_model and
# validate_model turn that into one ConfigError naming the file, line and field (exit code 2).
from uwbimu.errors import ConfigError
from uwbimu.estimation.options import EskfOptions

#: Most t_d profile points (each one a graph solve) one profile may ask for.
MAX_PROFILE_POINTS = 401
#: Smallest t_d profile step [s] (0.1 ms; an IMU sample is 1-10 ms).
MIN_PROFILE_STEP = 1e-4
#: Most knots of the slowly varying range bias per anchor (log span / knot_spacing).
MAX_DRIFT_KNOTS = 5000

_FINITE = ConfigDict(extra="forbid", allow_inf_nan=False)


class TdProfileOptions(BaseModel):
    """Time-offset profile likelihood (see docs/calibrate.md)."""

    model_config = _FINITE
    enabled: bool = True
    half_width: float = Field(0.5, gt=0, le=2.0, description="grid spans t_d prior mean +/- this [s]")
    # coarse_step is declared before step so that step's validator sees it (the grid size needs both)
    coarse_step: Optional[float] = Field(
        0.1, ge=MIN_PROFILE_STEP, description="[s] first pass over the whole grid at this step, then `step` within "
                                              "one coarse step of the coarse minimum; null: the whole grid at `step`")
    step: float = Field(0.02, ge=MIN_PROFILE_STEP, description="grid step [s] (near the minimum when coarse_step is "
                                                                "set)")
    confidence_chi2: float = Field(
        9.0, gt=0, description="points whose profile chi2 is within this of the minimum form the confidence set "
                               "(9 = 3 sigma for one parameter)")

    def n_points(self) -> int:
        """Grid points (solves) the profile asks for before any zoom, as ``profile_walk.run_profile`` builds them."""
        return _grid_points(self.half_width, self.coarse_step, self.step)

    @field_validator("coarse_step")
    @classmethod
    def _coarse_work(cls, v, info):
        hw = info.data.get("half_width")
        if v is not None and hw is not None and int(2 * hw / v) + 1 > MAX_PROFILE_POINTS // 2:
            raise ConfigError(f"the coarse grid would have {int(2 * hw / v) + 1} points (one solve each), more than "
                             f"{MAX_PROFILE_POINTS // 2}; make coarse_step coarser (or half_width smaller)")
        return v

    @field_validator("step")
    @classmethod
    def _step_work(cls, v, info):
        hw = info.data.get("half_width")
        if hw is not None and "coarse_step" in info.data:
            n = _grid_points(hw, info.data["coarse_step"], v)
            if n > MAX_PROFILE_POINTS:
                raise ConfigError(f"the grid would have {n} points (one solve each), more than {MAX_PROFILE_POINTS}; "
                                 f"make step coarser (or half_width smaller)")
        return v


def _grid_points(half_width: float, coarse_step: Optional[float], step: float) -> int:
    if coarse_step is not None and coarse_step > step:
        return int(2 * half_width / coarse_step) + 1 + 2 * int(round(coarse_step / step))
    return int(2 * half_width / step) + 1


class BlockCheckOptions(BaseModel):
    """Check of the sandwich sigma against the spread between parts of the log (see docs/calibrate.md
    "Honest sigma: the block check")."""

    model_config = _FINITE
    blocks: int = Field(6, ge=0, le=50, description="contiguous time blocks of the log (0: no check); the range "
                                                    "scores summed per block give a cluster-robust covariance")
    level: float = Field(0.01, gt=0, lt=0.5, description="family-wise level of the test of the HAC sandwich against "
                                                         "the blocks (Bonferroni over the parameters; event "
                                                         "range_errors_correlated_over_blocks); the sigma takes the "
                                                         "blocks' variance wherever it is the larger")

    @model_validator(mode="after")
    def _at_least_two(self):
        if self.blocks == 1:
            raise ConfigError("block_check.blocks: 0 (off) or at least 2")
        return self


class RangeBiasDrift(BaseModel):
    """Slowly varying part of each anchor's range bias: a first-order Gauss-Markov process per anchor.

    Real two-way ranges carry errors that stay correlated for seconds (antenna pattern and multipath
    change slowly with the line of sight); a white model then averages them as independent and is
    over-confident.  Each anchor's bias is ``c_j + d_j(t)``: ``c_j`` the constant bias (prior
    ``anchor_bias_prior_sd``), ``d_j`` piecewise constant on knots ``knot_spacing`` apart with
    ``d_0 ~ N(0, sd^2)`` and ``d_{n+1} = phi d_n + w``, ``phi = exp(-knot_spacing / correlation_time)``,
    ``w ~ N(0, sd^2 (1 - phi^2))`` (stationary sd ``sd``).  ``range_sigma`` is then the white part only.
    """

    model_config = _FINITE
    sd: float = Field(..., gt=0, description="stationary sd of the slowly varying bias [m]")
    correlation_time: float = Field(2.0, gt=0, description="[s]")
    knot_spacing: float = Field(0.5, ge=0.01, description="[s] (UWB clock); at most correlation_time / 2 is sensible")

    def knot_count(self, span: float) -> int:
        """Knots per anchor over ``span`` seconds of ranges; :class:`ConfigError` naming the field above
        :data:`MAX_DRIFT_KNOTS` (checked before the graph is built)."""
        n = int(round(span / self.knot_spacing)) + 1
        if n > MAX_DRIFT_KNOTS:
            raise ConfigError(f"range_bias_drift.knot_spacing: {self.knot_spacing:g} s over the {span:.1f} s of ranges "
                              f"gives {n} knots per anchor, more than {MAX_DRIFT_KNOTS}",
                              hint=f"set range_bias_drift.knot_spacing to at least {span / (MAX_DRIFT_KNOTS - 1):.3g} s")
        return n


class DirectionBias(BaseModel):
    """Direction-dependent range bias: a low-order function of the line of sight in the TAG's body frame.

    Each predicted range gains ``f(az, el) . c``: ``az = atan2(u_y, u_x)`` and ``el = asin(u_z)`` [rad] of
    the unit vector ``u`` from the tag antenna to the anchor in the IMU (body) frame, ``f`` the Fourier
    terms ``cos(n az), sin(n az)`` for ``n = lowest_order .. harmonics`` and, with ``elevation``, ``el``.
    ``c`` [m, m/rad] is one vector shared by all anchors or one per anchor, with a zero-mean prior of sd
    ``prior_sd`` per coefficient.  The order-1 terms shared by all anchors are, to first order, a shift
    of the antenna phase centre, i.e. the lever arm (``-u . dp_IU = -cos(el)(dx cos az + dy sin az) -
    dz sin el``): only the prior and the spread of elevations separate them (docs/calibrate.md).
    """

    model_config = _FINITE
    harmonics: int = Field(2, ge=1, le=6, description="highest Fourier order in body azimuth")
    lowest_order: int = Field(1, ge=1, le=6, description="lowest Fourier order (2 leaves order 1 to the lever arm)")
    elevation: bool = Field(False, description="add a term linear in body elevation [m/rad]")
    per_anchor: bool = Field(False, description="one coefficient vector per anchor (else shared by all anchors)")
    prior_sd: float = Field(0.05, gt=0, description="zero-mean prior sd of every coefficient [m or m/rad]")

    @model_validator(mode="after")
    def _orders(self) -> "DirectionBias":
        if self.lowest_order > self.harmonics:
            raise ConfigError(f"lowest_order ({self.lowest_order}) must not exceed harmonics ({self.harmonics})")
        return self

    @property
    def n_coef(self) -> int:
        """Number of coefficients per vector."""
        return 2 * (self.harmonics - self.lowest_order + 1) + (1 if self.elevation else 0)

    def names(self) -> list[str]:
        """Coefficient names, in vector order."""
        out = [f"{f}{n}" for n in range(self.lowest_order, self.harmonics + 1) for f in ("cos", "sin")]
        return out + (["elevation"] if self.elevation else [])


class AnchorDirectionBias(BaseModel):
    """Direction-dependent range bias at the ANCHOR antenna: a low-order function of the line of sight's angles
    in each anchor's antenna frame (``anchors.csv`` qw..qz, antenna frame -> world).

    Each predicted range to anchor ``j`` gains ``g(az_a, el_a) . c_j``: ``w_a = R_j^T (p_U - p_j)`` is the
    line of sight from the anchor to the tag antenna in the antenna frame, ``az_a = atan2(w_y, w_x)``,
    ``el_a = atan2(w_z, hypot(w_x, w_y))`` [rad]; ``g`` holds ``cos(n az_a), sin(n az_a)`` for ``n =
    lowest_order .. harmonics`` (none with ``harmonics: 0``) and ``el_a^q`` for ``q = elevation_lowest_order ..
    elevation_order``.  The order-1 azimuth terms and the linear elevation term are, to first order, the
    components of the unit line of sight in the antenna frame: common to the anchors in the way a shift of
    the whole trajectory is, they are separated from it only by the prior and the anchors' different
    orientations (docs/calibrate.md); ``lowest_order: 2`` and ``elevation_lowest_order: 2`` leave them out.
    ``c_j`` [m, m/rad^q] is one vector per anchor (shared by every tag: it belongs to the anchor's
    antenna) with a zero-mean prior of sd ``prior_sd`` per coefficient.  An anchor with ranges and no
    orientation in ``anchors.csv`` is refused.
    """

    model_config = _FINITE
    harmonics: int = Field(1, ge=0, le=4, description="highest Fourier order in antenna azimuth (0: none)")
    lowest_order: int = Field(1, ge=1, le=4, description="lowest Fourier order in antenna azimuth")
    elevation_order: int = Field(1, ge=0, le=3, description="highest power q of the antenna elevation [rad] (0: none)")
    elevation_lowest_order: int = Field(
        1, ge=1, le=3, description="lowest power of the antenna elevation (2 leaves the linear term out: with the "
                                   "order-1 azimuth terms it mimics a translation of the trajectory, see docs)")
    prior_sd: float = Field(0.05, gt=0, description="zero-mean prior sd of every coefficient [m, m/rad^q]")

    @model_validator(mode="after")
    def _orders(self) -> "AnchorDirectionBias":
        if self.harmonics and self.lowest_order > self.harmonics:
            raise ConfigError(f"lowest_order ({self.lowest_order}) must not exceed harmonics ({self.harmonics})")
        if self.elevation_order and self.elevation_lowest_order > self.elevation_order:
            raise ConfigError(f"elevation_lowest_order ({self.elevation_lowest_order}) must not exceed elevation_order "
                             f"({self.elevation_order})")
        if self.n_coef == 0:
            raise ConfigError("harmonics: 0 and elevation_order: 0 leave no term")
        return self

    @property
    def orders(self) -> tuple:
        """Fourier orders in antenna azimuth."""
        return tuple(range(self.lowest_order, self.harmonics + 1)) if self.harmonics else ()

    @property
    def powers(self) -> tuple:
        """Powers of the antenna elevation."""
        return tuple(range(self.elevation_lowest_order, self.elevation_order + 1)) if self.elevation_order else ()

    @property
    def n_coef(self) -> int:
        """Number of coefficients per anchor."""
        return 2 * len(self.orders) + len(self.powers)

    def names(self) -> list[str]:
        """Coefficient names, in vector order."""
        out = [f"{f}{n}" for n in self.orders for f in ("cos", "sin")]
        return out + [("elevation" if q == 1 else f"elevation{q}") for q in self.powers]


class RangeModelOptions(BaseModel):
    """Extra terms of the range model (beyond the constant bias and ``range_bias_drift``)."""

    model_config = _FINITE
    direction: Optional[DirectionBias] = Field(
        None, description="direction-dependent bias in the tag's body frame; none: no direction term")
    anchor_direction: Optional[AnchorDirectionBias] = Field(
        None, description="direction-dependent bias in each anchor's antenna frame (anchors.csv qw..qz); none: "
                          "no anchor-side term")
    select: Literal["auto", "cv", "given"] = Field(
        "auto", description="'auto' (default): the range model (white, direction, drift, direction+drift) and the "
                            "Huber threshold are chosen on the log by held-out likelihood over time blocks of the "
                            "residuals about the batch's free solve (uwbimu.calibration.range_model_stage), unless "
                            "range_bias_drift, range_model.direction or range_model.anchor_direction is set (the "
                            "configured model is kept) or the log is TDoA, several tags or a self-survey (kept as "
                            "configured); 'cv': chosen whenever the log allows, replacing a configured model "
                            "(`direction` gives the direction candidate's form); 'given': the model as configured. "
                            "The graph's Huber threshold stays huber_k's (adaptive, or a number: the families are "
                            "then compared at it)")
    select_folds: int = Field(5, ge=3, le=20, description="time blocks of the cross-validation (select: auto or cv)")


#: Huber threshold of the first solves when ``huber_k: adaptive`` (Huber's 95 %-efficiency value, robust enough that
#: gross outliers do not shape the residuals that then choose the final threshold: uwbimu.calibration.robust_loss)
HUBER_START = 1.345


class CalibrationOptions(BaseModel):
    """Factor-graph settings; noise defaults come from ``dataset.yaml`` when it documents them."""

    model_config = _FINITE
    keyframe_hz: float = Field(10.0, gt=0, le=200, description="keyframe rate of the graph [Hz]")
    range_sigma: Optional[float] = Field(None, gt=0, description="range noise sd [m]; default dataset's or 0.1")
    tdoa_sigma: Optional[float] = Field(
        None, gt=0, description="TDoA noise sd [m]; default the dataset's extra.tdoa_sigma, else sqrt(2) range_sigma")
    huber_k: Union[Literal["adaptive"], PositiveFloat] = Field(
        "adaptive", description="Huber threshold in sigmas (down-weighted: |e| > k sigma): a number, or 'adaptive': "
                                "the threshold that minimises the M-estimator's asymptotic variance on the residuals "
                                "of a first solve at 1.345 (uwbimu.calibration.robust_loss; near least squares on "
                                "Gaussian errors, smaller on heavy-tailed ones; calibration.yaml range_model.huber)")
    accel_noise_density: Optional[float] = Field(None, gt=0, description="m/s^2/sqrt(Hz); default dataset's")
    gyro_noise_density: Optional[float] = Field(None, gt=0, description="rad/s/sqrt(Hz); default dataset's")
    accel_bias_rw: Optional[float] = Field(None, gt=0, description="m/s^3/sqrt(Hz); default dataset's")
    gyro_bias_rw: Optional[float] = Field(None, gt=0, description="rad/s^2/sqrt(Hz); default dataset's")
    imu_noise_inflation: float = Field(1.0, gt=0, description="multiplies the IMU noise densities and bias random "
                                                                "walks (the starting point when imu_noise_scale is "
                                                                "'estimate')")
    imu_noise_scale: Literal["estimate", "fixed"] = Field(
        "estimate", description="'estimate': the factor on the IMU noise model (densities and bias random walks) "
                                "is estimated from the log "
                                "(variance component estimation at the free solve: the IMU factors' chi2 equals "
                                "their redundancy; in flight vibration and IMU errors exceed at-rest densities, see "
                                "docs/calibrate.md 'IMU noise scale'); 'fixed': imu_noise_inflation as given")
    imu_noise_prior_dof: float = Field(
        10.0, ge=0, description="weight of the configured IMU densities in the estimated scale, in degrees of freedom "
                                "of a scaled inverse chi-square prior (0: none); the IMU factors' redundancy is the "
                                "data's weight (a few on a 20 s flight, ~350 on INRoL's 190 s)")
    lever_arm_prior: list[float] = Field(default_factory=lambda: [0.0, 0.0, 0.0], min_length=3, max_length=3)
    lever_arm_prior_sd: float = Field(0.5, gt=0, description="[m] per axis")
    time_offset_prior: float = Field(0.0, description="t_d prior mean [s]")
    time_offset_prior_sd: float = Field(0.5, gt=0, description="[s]")
    anchor_bias_prior_sd: float = Field(0.3, gt=0, description="per-anchor constant range bias prior sd [m]")
    estimate_anchor_bias: bool | Literal["surveyed_only"] = Field(
        True, description="estimate each anchor's constant range bias (prior sd anchor_bias_prior_sd): true every "
                          "anchor's, false none (held at 0), surveyed_only those of the fixed anchors only (an "
                          "estimated anchor's bias held at 0: it is confounded with its distance along the mean "
                          "line of sight, see docs/calibrate.md 'Anchor self-survey')")
    range_bias_drift: Optional[RangeBiasDrift] = Field(
        None, description="slowly varying per-anchor bias (correlated range errors of real data); none: white "
                          "range noise plus a constant bias per anchor")
    range_model: RangeModelOptions = Field(default_factory=RangeModelOptions)
    estimate_anchors: list[str] = Field(
        default_factory=list, description="anchor ids whose positions are estimated (self-survey; anchors marked "
                                          "surveyed: false in anchors.csv are always estimated)")
    anchor_systematic: Literal["surveyed", "none"] = Field(
        "surveyed", description="sigma of the estimated anchors: 'surveyed' adds the range model's systematic error "
                                "measured on the surveyed anchors (linearised leave-one-out: where the log would put "
                                "each surveyed anchor had it been estimated, beyond the white model; "
                                "calibration.yaml anchors.systematic); 'none': the white model's (and sandwich's) only")
    anchor_prior_sd: float = Field(0.5, gt=0, description="[m] per axis: weak prior of an estimated anchor around "
                                                          "its anchors.csv position (none when surveyed: false)")
    anchor_range_sigma: float = Field(0.05, gt=0, description="[m] sd of an anchor_ranges.csv range without sd")
    degenerate_anchors: Literal["refuse", "warn"] = Field(
        "refuse", description="an estimated anchor without prior seen from too few directions or mirror-ambiguous "
                              "(coplanar motion): refuse (InputError) or warn (event) and solve")
    bootstrap_range_sigma: float = Field(
        0.5, gt=0, description="[m] range sd of the initialising ESKF when it must use rough anchors.csv guesses "
                               "(fewer than 4 surveyed anchors); about the guesses' error")
    group_range_factors: bool = Field(
        True, description="one vectorised factor per keyframe for the ranges to fixed anchors and the TDoA rows "
                          "between fixed anchors (same model, ~10x faster); false: one GTSAM CustomFactor per row "
                          "(the reference implementation)")
    range_group_keyframes: int = Field(
        5, ge=1, le=50, description="consecutive keyframes whose ranges share one vectorised factor (fewer, larger "
                                    "Python callbacks; same model)")
    covariance: Literal["sandwich", "model"] = Field(
        "sandwich", description="sigma of the calibration parameters: 'sandwich' (HAC / Newey-West over the range "
                                "factors' scores, bandwidth chosen from the data: honest when range errors are "
                                "correlated in time or the range model is misspecified; never below the model's "
                                "sigma, which a short log's noisy sandwich can undercut; the t_d profile's chi2 is "
                                "scaled by model / sandwich variance, at most 1) or 'model' (GTSAM marginals of the "
                                "white range-noise model); calibration.yaml keeps both (sd, sd_model)")
    block_check: BlockCheckOptions = Field(
        default_factory=BlockCheckOptions,
        description="with covariance 'sandwich': test each parameter's HAC sigma against the spread of the range "
                    "scores between contiguous time blocks of the log; each sigma is the larger of the two (a "
                    "range-model error that follows the motion for tens of seconds; event "
                    "range_errors_correlated_over_blocks where the blocks reject the HAC)")
    init_eskf: Optional[EskfOptions] = Field(
        None, description="options of the initialising ESKF (as examples/estimator*.yaml; none: its defaults with "
                          "smoother forward_backward, i.e. the run uwbimu estimate makes, so that the batch starts "
                          "from and compares itself with the same ESKF answer); "
                          "calibrate(eskf_options=...) and `uwbimu calibrate --eskf-config` take precedence. A "
                          "filter that diverges on a short window leaves the graph in a wrong minimum (ISAS-Walk's "
                          "last 15 s window: lever arm 72 cm off with the defaults, within 1 sigma with the "
                          "isas-walk preset)")
    second_start: bool = Field(
        True, description="also initialise from an ESKF with the real-data preset's robust range model (white 5 cm "
                          "+ slowly varying anchor bias) and keep the lower-cost first solve (not with a given ESKF "
                          "result or anchor self-survey); event second_start_won")
    max_iterations: int = Field(50, ge=1, le=1000)
    reassociate_max: int = Field(3, ge=0, le=20, description="re-attach ranges when t_d moved > half a keyframe step")
    td_profile: TdProfileOptions = Field(default_factory=TdProfileOptions)

    def check_log(self, dataset) -> None:
        """Refuse settings whose work grows with the log beyond the bounds (:class:`ConfigError` naming the
        field), before anything is solved: the drift knots per anchor (:meth:`RangeBiasDrift.knot_count`)."""
        if self.range_bias_drift is not None and len(dataset.uwb):
            t = dataset.uwb["t"].to_numpy(float)
            self.range_bias_drift.knot_count(float(t.max() - t.min()))

    def anchor_bias_estimated(self, anchor_estimated: bool) -> bool:
        """Whether the constant range bias of an anchor is estimated (``estimate_anchor_bias``), its position
        estimated (self-survey) or fixed."""
        if self.estimate_anchor_bias == "surveyed_only":
            return not anchor_estimated
        return bool(self.estimate_anchor_bias)

    @classmethod
    def from_yaml(cls, path: str | Path) -> "CalibrationOptions":
        """Load options from a YAML file; errors (:class:`uwbimu.errors.ConfigError`) name file, line and field."""
        from uwbimu.io.yamlconfig import load_yaml_model

        return load_yaml_model(path, cls, what="calibration options")
