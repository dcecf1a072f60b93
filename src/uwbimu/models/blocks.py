"""The filter state's blocks, declared once.

Every block of the ESKF state (nominal ``x`` and error ``dx``) is one :class:`BlockSpec` in
:data:`BLOCKS`, in state order.  :class:`uwbimu.models.state.StateLayout` compiles the declarations
with the run's multiplicities (how many anchors, pairs, tags) into slices for Python and into the
integer / float tables of :class:`ProcessNoise` for the numba kernels, so no code infers a block's
presence, size or offset from an array length or a literal (OpenVINS' ``Type``/``id`` idea in a form
numba reads).

What a declaration says
-----------------------
``name``           the block's one name: ``StateLayout.err(name)`` / ``nom(name)``, covariance blocks
                   (``EskfState.cov(name)``), the keys of the calibration outputs' ``*_sd`` fields.
``size``           error-state components per instance; ``nominal_size`` nominal components per
                   instance (4 for the attitude quaternion, whose error is a 3-vector).
``multiplicity``   ``"one"`` (always present), ``"optional"`` (0 or 1 instance), ``"per_anchor"``,
                   ``"per_pair"`` (TDoA anchor pairs), ``"per_extra_tag"`` (tags 2..T): the count is
                   given to :class:`~uwbimu.models.state.StateLayout` (``counts={name: n}``).
``process_noise``  ``"imu"`` (driven by the IMU densities through the transition: p, v, theta, b_a,
                   b_g), ``"constant"``, ``"random_walk"`` (density^2 ``q`` [unit^2/s] added per second)
                   or ``"gauss_markov"`` (first order: stationary variance ``q`` [unit^2], ``1/tau``
                   [1/s]; ``1/tau = 0`` falls back to constant).
``noise_option``   the :class:`~uwbimu.estimation.options.EskfOptions` path(s) that give ``q``
                   (and ``1/tau``): resolved by ``estimation.problem.block_process_noise``.
``mode_option``    the options section whose ``mode`` (``estimate`` / ``consider`` / ``fixed``) sets
                   the block's gain mask (None: always estimated).
``enabled_by``     for a block that is not ``"one"``: the option and the values that create it (the count
                   is then the number of anchors / pairs / extra tags, or 1); None: always (by count).
``prior_sd_option`` the option of an extra block's prior sd (prior mean zero unless said otherwise).
``prior``          where the initial value and sd come from, and whether the initialiser searches it.
``output_names``   the error-state component names (CSV ``sd_*`` columns, reports) of one instance;
                   ``nominal_names`` the nominal ones.
``unit``           SI unit of the block's components.
``output_key``     the key of the block's final estimate in the calibration outputs (``result.calibration``,
                   calibration.yaml; ``<key>_sd`` its sd, ``<key>_mode`` its mode when it can be other than
                   ``estimate``): the options section's name where the block has one.  Per-anchor blocks are
                   keyed by anchor id, per-pair blocks by ``"<a>-<b>"``; None: not a calibration output.
``label``, ``frame`` the quantity in words ("lever arm") and the frame of its components: warnings, event
                   payloads (``parameter``), the observability directions' names.
``calibration``    the calibration proper (lever arm, time offset; :data:`CALIBRATION_BLOCKS`): the excitation
                   monitor, the observability windows' ``<output_key>_excited`` flags, the reports'
                   calibration / convergence / repeatability tables loop over these blocks.
``table_unit``, ``plot_unit`` ``(scale, unit)`` of tables / warnings and of plots (None: SI).
``excitation``     the motion measure that excites the block (``"rotation"``: RMS body rate,
                   ``"acceleration"``: RMS world acceleration) and ``excitation_advice`` the motion to add.
``search_option``  the option of the grid the initialiser searches the block on (its prior sd is then at
                   least the grid's uniform sd: ``estimation.problem.block_prior_sd``).
``verdict``        the batch calibration's identifiability verdict: ``"information_gain"`` per component,
                   ``"profile"`` (the time offset's profile verdict).
``obs_scale``, ``obs_prior_sd`` typical magnitude and window-start prior sd of the observability analysis.
``legacy_names``   former output names of the components (one per component): readers of the CSV / JSON
                   outputs accept them (:func:`legacy_name_map`); writers use ``output_names``.  The time
                   offset's columns were ``td`` / ``sd_td`` before they took its one output name
                   ``time_offset`` (the options' and calibration.yaml's).

Adding a block
--------------
One more :class:`BlockSpec` in :data:`BLOCKS` (after the blocks it must follow: additive blocks go
after the base 19), and the
Jacobian columns of the measurements that see it (a :class:`~uwbimu.models.measurements.MeasurementModel`
``jacobian`` or a numba update), pinned by the finite-difference harness
(``uwbimu.models.measurements.fd_jacobian``); see CONTRIBUTING.md, "Adding a state block".
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple, Optional

import numpy as np

#: process-noise kind codes of the numba tables (:class:`ProcessNoise` ``kind``)
PN_IMU = 0
PN_CONSTANT = 1
PN_RANDOM_WALK = 2
PN_GAUSS_MARKOV = 3
PN_CODES = {"imu": PN_IMU, "constant": PN_CONSTANT, "random_walk": PN_RANDOM_WALK,
            "gauss_markov": PN_GAUSS_MARKOV}

#: the multiplicities; a block that is not ``"one"`` has a count per run (``StateLayout(counts=...)``)
MULTIPLICITIES = ("one", "optional", "per_anchor", "per_pair", "per_extra_tag")


@dataclass(frozen=True)
class BlockSpec:
    """One block of the filter state (see the module docstring for the fields)."""

    name: str
    size: int
    multiplicity: str
    process_noise: str
    output_names: tuple[str, ...]
    unit: str
    nominal_size: Optional[int] = None  # None: equal to size
    nominal_names: Optional[tuple[str, ...]] = None  # None: equal to output_names
    noise_option: tuple[str, ...] = ()
    mode_option: Optional[str] = None
    output_key: Optional[str] = None  # key of the block's estimate in the calibration outputs (None: not there)
    enabled_by: Optional[tuple[str, tuple[str, ...]]] = None  # (option path, values that create the block)
    prior_sd_option: Optional[str] = None  # option path of the prior sd of an additive extra block
    prior: str = ""
    doc: str = ""
    label: str = ""  # the quantity in words ("lever arm"): warnings, event payloads, direction names
    frame: str = ""  # frame of a vector block's components ("world", "body"; "" for a scalar)
    calibration: bool = False  # the calibration proper (see CALIBRATION_BLOCKS)
    table_unit: Optional[tuple[float, str]] = None  # (scale from SI, unit) of tables and warnings; None: SI
    plot_unit: Optional[tuple[float, str]] = None  # (scale from SI, unit) of the reports' plots; None: SI
    excitation: Optional[str] = None  # the motion measure that excites it: "rotation" or "acceleration"
    excitation_advice: str = ""  # what motion would determine it (the not-determined warning's advice)
    search_option: Optional[str] = None  # option path of the grid the initialiser searches it on
    verdict: str = ""  # identifiability verdict of the batch calibration: "information_gain" or "profile"
    obs_scale: float = 1.0  # typical magnitude [unit] making the observability information dimensionless
    obs_prior_sd: float = 0.0  # prior sd [unit] at an observability window's start (the ESKF's default)
    legacy_names: tuple[str, ...] = ()  # former output names of the components, still accepted by readers

    def __post_init__(self):
        if self.multiplicity not in MULTIPLICITIES or self.process_noise not in PN_CODES:
            raise ValueError(f"BlockSpec {self.name!r}: multiplicity in {MULTIPLICITIES}, process_noise in "
                             f"{tuple(PN_CODES)}")
        if len(self.output_names) != self.size or len(self.nom_names) != self.n_nom:
            raise ValueError(f"BlockSpec {self.name!r}: one output name per component")
        if self.legacy_names and len(self.legacy_names) != self.size:
            raise ValueError(f"BlockSpec {self.name!r}: one legacy name per component")
        if any(not n.startswith(self.symbol) for n in self.output_names) or len(set(self.axes)) != self.size:
            raise ValueError(f"BlockSpec {self.name!r}: output names are one prefix and one suffix per component")

    @property
    def n_nom(self) -> int:
        """Nominal components per instance."""
        return self.size if self.nominal_size is None else self.nominal_size

    @property
    def nom_names(self) -> tuple[str, ...]:
        return self.output_names if self.nominal_names is None else self.nominal_names

    @property
    def kind(self) -> int:
        """Process-noise kind code (``PN_*``)."""
        return PN_CODES[self.process_noise]

    @property
    def symbol(self) -> str:
        """The components' common name prefix (``"l"`` of ``lx, ly, lz``; a scalar's own name): the key of
        the per-block observability scales and the direction names."""
        if self.size == 1:
            return self.output_names[0]
        return self.output_names[0][:-1]

    @property
    def axes(self) -> tuple[str, ...]:
        """The components' suffixes after :attr:`symbol` (``("x", "y", "z")``; ``("",)`` for a scalar)."""
        return tuple(n[len(self.symbol):] for n in self.output_names)

    @property
    def table(self) -> tuple[float, str]:
        """``(scale, unit)`` of the block in tables and warnings (``value * scale`` in ``unit``)."""
        return self.table_unit or (1.0, self.unit)

    @property
    def plot(self) -> tuple[float, str]:
        """``(scale, unit)`` of the block in the reports' plots."""
        return self.plot_unit or (1.0, self.unit)


def _xyz(prefix: str) -> tuple[str, str, str]:
    return (prefix + "x", prefix + "y", prefix + "z")


#: The state's blocks in state order.  The first seven (19 error / 20 nominal components) are always
#: present; the rest are additive extras whose counts come from the run (``StateLayout`` arguments).
BLOCKS: tuple[BlockSpec, ...] = (
    BlockSpec("p", 3, "one", "imu", _xyz("p"), "m", prior="initialiser (multilateration)",
              doc="IMU position, world frame", label="position", frame="world", obs_scale=1.0, obs_prior_sd=0.3),
    BlockSpec("v", 3, "one", "imu", _xyz("v"), "m/s", prior="initialiser", doc="IMU velocity, world frame",
              label="velocity", frame="world", obs_scale=1.0, obs_prior_sd=0.5),
    BlockSpec("theta", 3, "one", "imu", _xyz("th"), "rad", nominal_size=4, nominal_names=("qw", "qx", "qy", "qz"),
              prior="initialiser (gravity, yaw search)",
              doc="attitude: nominal Hamilton q [qw, qx, qy, qz] body->world, error q = q_hat ⊗ Exp(theta)",
              label="attitude", frame="body", obs_scale=1.0, obs_prior_sd=0.1),
    BlockSpec("b_a", 3, "one", "imu", _xyz("ba"), "m/s^2", output_key="accel_bias", prior="zero, sd accel_bias_sd (or the IMU's)",
              doc="accelerometer bias, IMU frame", label="accelerometer bias", frame="body", obs_scale=0.1,
              obs_prior_sd=0.1),
    BlockSpec("b_g", 3, "one", "imu", _xyz("bg"), "rad/s", output_key="gyro_bias", prior="still-phase mean, sd gyro_bias_sd",
              doc="gyroscope bias, IMU frame", label="gyro bias", frame="body", obs_scale=0.01, obs_prior_sd=0.01),
    BlockSpec("lever", 3, "one", "random_walk", _xyz("l"), "m", noise_option=("lever_arm.random_walk",),
              output_key="lever_arm",
              mode_option="lever_arm", prior="lever_arm.prior (dataset), sd lever_arm.prior_sd",
              doc="lever arm p_IU of the first tag: UWB antenna in the IMU frame",
              label="lever arm", frame="body", calibration=True, table_unit=(100.0, "cm"), excitation="rotation",
              excitation_advice="excite rotations about all axes", verdict="information_gain",
              obs_scale=0.1, obs_prior_sd=0.3),
    BlockSpec("t_d", 1, "one", "random_walk", ("time_offset",), "s", noise_option=("time_offset.random_walk",),
              legacy_names=("td",),
              output_key="time_offset",
              mode_option="time_offset",
              prior="time_offset.prior, sd time_offset.prior_sd; searched on init.td_grid when no prior",
              doc="time offset: an IMU sample stamped s describes the motion at UWB time s - t_d",
              label="time offset", calibration=True, table_unit=(1000.0, "ms"), plot_unit=(1000.0, "ms"),
              excitation="acceleration", excitation_advice="move with changing velocity", search_option="init.td_grid",
              verdict="profile", obs_scale=0.01, obs_prior_sd=0.1),
    BlockSpec("anchor_bias", 1, "per_anchor", "gauss_markov", ("b",), "m",
              noise_option=("anchor_bias.prior_sd", "anchor_bias.correlation_time"), mode_option="anchor_bias",
              output_key="anchor_bias",
              enabled_by=("anchor_bias.mode", ("estimate", "consider")), prior_sd_option="anchor_bias.prior_sd",
              prior="zero, sd anchor_bias.prior_sd",
              doc="per-anchor range bias (Gauss-Markov when anchor_bias.correlation_time is set, else constant)",
              label="anchor bias", verdict="information_gain"),
    BlockSpec("pair_bias", 1, "per_pair", "constant", ("b",), "m", mode_option="tdoa_pair_bias",
              output_key="tdoa_pair_bias",
              enabled_by=("tdoa_pair_bias.mode", ("estimate",)), prior_sd_option="tdoa_pair_bias.prior_sd",
              prior="zero, sd tdoa_pair_bias.prior_sd", doc="TDoA bias of one anchor pair", label="TDoA pair bias"),
    BlockSpec("extra_levers", 3, "per_extra_tag", "random_walk", _xyz("l"), "m",
              noise_option=("lever_arm.random_walk",), mode_option="lever_arm",
              prior="the tag's lever arm, sd lever_arm.prior_sd", doc="lever arms of tags 2..T, IMU frame",
              label="lever arm", frame="body"),
    BlockSpec("height_bias", 1, "optional", "random_walk", ("hb",), "m", noise_option=("height.bias_random_walk",),
              enabled_by=("height.bias", ("estimate",)), prior_sd_option="height.bias_prior_sd",
              output_key="height_bias",
              prior="zero, sd height.bias_prior_sd", doc="altimeter (barometer) bias, added to the measured height",
              label="altimeter bias"),
)

BLOCK = {b.name: b for b in BLOCKS}

#: the order of the blocks' estimates in the calibration outputs (calibration.yaml reads top-down: the
#: calibration first, the IMU biases, then the per-anchor / per-pair extras)
OUTPUT_ORDER = ("lever", "t_d", "b_a", "b_g", "anchor_bias", "pair_bias", "height_bias")

#: The calibration proper (``calibration=True``: the lever arm and the time offset), in output order: the
#: excitation monitor, the observability windows' flags and the reports' calibration tables loop over these
CALIBRATION_BLOCKS: tuple[BlockSpec, ...] = tuple(BLOCK[n] for n in OUTPUT_ORDER if BLOCK[n].calibration)


def calibration_components() -> dict[str, tuple[BlockSpec, int]]:
    """Output name of every component of the calibration blocks (``lx, ly, lz, time_offset``) -> (block,
    component)."""
    return {n: (b, i) for b in CALIBRATION_BLOCKS for i, n in enumerate(b.output_names)}


def legacy_name_map() -> dict[str, str]:
    """Former output name -> output name of every declared component, with their ``sd_`` columns
    (``td -> time_offset``, ``sd_td -> sd_time_offset``): what readers of older files rename."""
    out = {}
    for b in BLOCKS:
        for old, new in zip(b.legacy_names, b.output_names):
            out[old], out[f"sd_{old}"] = new, f"sd_{new}"
    return out


class ProcessNoise(NamedTuple):
    """The process-noise tables the numba kernels take (built by ``StateLayout.process_noise``).

    ``imu`` (4,): squared continuous densities ``[s_a^2, s_g^2, s_ba^2, s_bg^2]`` (accel, gyro white
    noise [m^2/s^3, rad^2/s]; accel, gyro bias random walks [m^2/s^5, rad^2/s^3]).  Then one row per
    present block that is not driven by the IMU: ``kind`` (``PN_*``), ``err0`` / ``nom0`` the first
    error / nominal index, ``size`` the number of components (all instances), ``q`` the random-walk
    density^2 or the Gauss-Markov stationary variance, ``inv_tau`` the Gauss-Markov ``1/tau`` [1/s].
    """

    imu: np.ndarray
    kind: np.ndarray
    err0: np.ndarray
    nom0: np.ndarray
    size: np.ndarray
    q: np.ndarray
    inv_tau: np.ndarray
