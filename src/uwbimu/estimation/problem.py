"""The filter's numeric settings and IMU bookkeeping, shared by the batch and the streaming paths.

:func:`make_settings` turns :class:`EskfOptions` plus the anchors and the sensor noise into a
:class:`~uwbimu.estimation.filterpass.Problem` without data (gate, noise array, masks, hull, ...) and
the calibration priors; :func:`set_imu_timing` fixes the nominal IMU period and what depends on it;
the streaming filter computes the cubic mid-interval inputs piece by piece
(``kernels.midpoints_into``, pinned to :func:`uwbimu.models.reference.midpoint_inputs`).

Everything here is causal: the nominal IMU period is the median of the first
:data:`NOMINAL_PERIOD_SAMPLES` periods, so the streaming filter and the batch agree on it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Optional, Sequence

import numpy as np
from scipy.special import gammaincinv

from uwbimu.estimation import kernels as K
from uwbimu.estimation.filterpass import Problem
from uwbimu.estimation.options import EskfOptions
from uwbimu.models.imu import ImuNoise
from uwbimu.models import state as S
from uwbimu.models.blocks import BLOCK, BLOCKS, BlockSpec

#: IMU periods whose median is the nominal period (the first ones: known early by a streaming filter)
NOMINAL_PERIOD_SAMPLES = 1000

_ROBUST = {"none": K.ROBUST_NONE, "huber": K.ROBUST_HUBER, "geman-mcclure": K.ROBUST_GM}


def nominal_period(imu_t: np.ndarray) -> float:
    """Median of the first :data:`NOMINAL_PERIOD_SAMPLES` IMU periods [s]."""
    d = np.diff(np.asarray(imu_t[: NOMINAL_PERIOD_SAMPLES + 1], dtype=float))
    return float(np.median(d))


@dataclass
class BlockPriors:
    """The prior of every declared block that is not fixed by the initialiser's fix (typed record).

    Fields are named after the blocks of :mod:`uwbimu.models.blocks` (``<block>`` the prior mean,
    ``<block>_sd`` its sd) in SI units; ``search_t_d`` says whether the initialiser searches the time
    offset over ``init.td_grid`` (no configured prior value).
    """

    lever: np.ndarray  # (3,) first tag's lever arm [m], IMU frame
    tag_levers: np.ndarray  # (T, 3) every tag's lever arm [m]
    lever_sd: np.ndarray  # (3,) [m]; zero when fixed
    anchor_bias: np.ndarray  # (nb,) [m]
    anchor_bias_sd: float  # [m]; zero without anchor-bias states
    b_a: np.ndarray  # (3,) [m/s^2]
    b_g: np.ndarray  # (3,) [rad/s]
    b_a_sd: float
    b_g_sd: float
    t_d: float  # [s]
    t_d_sd: float  # [s]; zero when fixed
    search_t_d: bool
    #: prior sd of every additive extra block with a declared ``prior_sd_option`` [block unit]; 0 when the
    #: run has no instance of it (prior mean zero)
    block_sd: dict[str, float] = field(default_factory=dict)


def _option(opts: EskfOptions, path: str):
    """The option at dotted ``path`` (``"lever_arm.random_walk"``)."""
    v: Any = opts
    for part in path.split("."):
        v = getattr(v, part)
    return v


def block_counts(opts: EskfOptions, n_anchors: int, n_pairs: int, n_tags: int,
                 blocks: tuple[BlockSpec, ...] = BLOCKS) -> dict[str, int]:
    """Instances of every declared block that is not ``"one"``: the multiplicity's number (anchors, pairs,
    extra tags, 1 for ``"optional"``) when the block's ``enabled_by`` option has an enabling value, else 0."""
    per = {"optional": 1, "per_anchor": n_anchors, "per_pair": n_pairs, "per_extra_tag": n_tags - 1}
    out = {}
    for b in blocks:
        if b.multiplicity == "one":
            continue
        on = b.enabled_by is None or _option(opts, b.enabled_by[0]) in b.enabled_by[1]
        out[b.name] = per[b.multiplicity] if on else 0
    return out


def block_process_noise(opts: EskfOptions, layout: S.StateLayout) -> dict[str, tuple[float, float]]:
    """``(q, 1/tau)`` of every present block not driven by the IMU, from its declared ``noise_option``.

    Random walk: ``q`` = the option squared (density^2); Gauss-Markov: ``q`` = the first option squared
    (stationary variance), ``1/tau`` = 1 / the second (0 when unset: a constant); constant: none.
    """
    out: dict[str, tuple[float, float]] = {}
    for b in layout.blocks:
        if b.process_noise == "random_walk":
            out[b.name] = (float(_option(opts, b.noise_option[0])) ** 2, 0.0)
        elif b.process_noise == "gauss_markov":
            tau = _option(opts, b.noise_option[1])
            out[b.name] = (float(_option(opts, b.noise_option[0])) ** 2, 1.0 / tau if tau else 0.0)
    return out


def gain_mask(opts: EskfOptions, layout: S.StateLayout) -> np.ndarray:
    """1 for estimated error components, 0 for consider / fixed ones: each block's declared
    ``mode_option`` section (``mode`` other than ``estimate``)."""
    mask = np.ones(layout.n_err)
    for b in layout.blocks:
        if b.mode_option is not None and _option(opts, b.mode_option).mode != "estimate":
            mask[layout.err(b.name)] = 0.0
    return mask


def block_mode(opts: EskfOptions, b: BlockSpec) -> str:
    """``estimate`` / ``consider`` / ``fixed``: the ``mode`` of the block's declared ``mode_option`` section
    (``estimate`` for a block without one)."""
    return "estimate" if b.mode_option is None else str(_option(opts, b.mode_option).mode)


def block_prior_sd(priors: BlockPriors, opts: EskfOptions, name: str) -> np.ndarray:
    """Prior sd of base block ``name`` per component [block unit]: what is known of it before the data.

    ``priors.<name>_sd``; for a block the initialiser searches (declared ``search_option``, ``priors.search_<name>``)
    at least the sd of a uniform over the searched grid's span (the prior is then the grid, not the configured sd);
    0 where the block is fixed.  The time offset's is :func:`uwbimu.estimation.timeoffset.time_offset_prior_sd`.
    """
    b = BLOCK[name]
    sd = np.broadcast_to(np.asarray(getattr(priors, f"{name}_sd"), dtype=float), (b.size,)).copy()
    if b.search_option is not None and getattr(priors, f"search_{name}", False):
        grid = np.asarray(_option(opts, b.search_option), dtype=float)
        if len(grid) > 1:
            sd = np.where(sd > 0, np.maximum(sd, float(grid.max() - grid.min()) / math.sqrt(12.0)), sd)
    return np.where(sd > 0, sd, 0.0)


def block_prior_covariance(P: np.ndarray, layout: S.StateLayout, priors: BlockPriors) -> None:
    """Set the initial covariance of every extra block with a declared prior sd (in place):
    ``P[b, b] = sd^2 I`` from ``priors.block_sd`` (blocks absent from it are left alone)."""
    for b in layout.blocks:
        if b.multiplicity != "one" and b.name in priors.block_sd:
            sl = layout.err(b.name)
            P[sl, sl] = np.eye(sl.stop - sl.start) * priors.block_sd[b.name] ** 2


def make_settings(
    opts: EskfOptions,
    anchor_ids: Sequence[str],
    anchors: np.ndarray,
    noise: ImuNoise,
    range_sigma: float,
    tdoa_sigma: Optional[float],
    lever_prior: Sequence,
    tag_names: Optional[Sequence[str]] = None,
    tdoa_pairs: Optional[Sequence[tuple[int, int]]] = None,
) -> tuple[Problem, BlockPriors]:
    """A :class:`Problem` with the resolved settings and no data, and the blocks' priors.

    Parameters
    ----------
    anchors : (M, 3) anchor positions in the filter's (z-up) world frame [m].
    noise : IMU noise densities (already scaled by the options).
    range_sigma, tdoa_sigma : measurement noise sd [m] (``tdoa_sigma`` None: ``sqrt(2) range_sigma``).
    lever_prior : (3,) prior lever arm [m], IMU frame, or ``(T, 3)``: one per tag of ``tag_names``.
    tag_names : the tags whose lever arms are estimated (one filter, one lever arm each); None: one tag.
    tdoa_pairs : anchor-index pairs ``(a, b)`` that get a bias state (``tdoa_pair_bias.mode: estimate``).

    The state layout, its process-noise tables and gain mask are compiled from the block declarations
    (:mod:`uwbimu.models.blocks`): multiplicities from the anchors, tags and pairs, process noise and
    modes from each block's declared options.
    """
    anchors = np.ascontiguousarray(np.asarray(anchors, dtype=float).reshape(-1, 3))
    M = len(anchor_ids)
    levers = np.array(lever_prior, dtype=float).reshape(-1, 3)
    n_tags = max(len(tag_names) if tag_names else 1, 1)
    if len(levers) == 1 and n_tags > 1:
        levers = np.repeat(levers, n_tags, axis=0)
    if len(levers) != n_tags:
        raise ValueError(f"make_settings: {len(levers)} lever-arm priors for {n_tags} tags")
    layout = S.StateLayout(counts=block_counts(opts, M, len(tdoa_pairs or []), n_tags))
    pairs = [tuple(int(v) for v in pq) for pq in (tdoa_pairs or [])] if layout.count["pair_bias"] else []
    nb = layout.count["anchor_bias"]
    bias_idx = np.full(M, -1, dtype=np.int64)
    if nb:
        bias_idx[:] = layout.err("anchor_bias").start + np.arange(M)
    sd_ba = opts.accel_bias_sd or (noise.accel_bias_sigma0 if noise.accel_bias_sigma0 > 0 else 0.1)
    sd_bg = opts.gyro_bias_sd or (noise.gyro_bias_sigma0 if noise.gyro_bias_sigma0 > 0 else math.radians(1.0))
    t_d_mode = opts.time_offset.mode
    priors = BlockPriors(
        lever=levers[0].copy(), tag_levers=levers,
        lever_sd=np.zeros(3) if opts.lever_arm.mode == "fixed" else np.full(3, opts.lever_arm.prior_sd),
        anchor_bias=np.zeros(nb), anchor_bias_sd=opts.anchor_bias.prior_sd if nb else 0.0,
        b_a=np.zeros(3), b_g=np.zeros(3), b_a_sd=sd_ba, b_g_sd=sd_bg,
        t_d=float(opts.time_offset.prior or 0.0),
        t_d_sd=0.0 if t_d_mode == "fixed" else opts.time_offset.prior_sd,
        search_t_d=t_d_mode != "fixed" and opts.time_offset.prior is None and opts.init.search_time_offset,
        block_sd={b.name: float(_option(opts, b.prior_sd_option)) if layout.count[b.name] else 0.0
                  for b in layout.declarations if b.prior_sd_option is not None},
    )
    gate = float(2 * gammaincinv(1 / 2, opts.gating.probability)) if opts.gating.probability < 1 else -1.0
    imu = np.array([noise.accel_noise_density**2, noise.gyro_noise_density**2, noise.accel_bias_rw**2,
                    noise.gyro_bias_rw**2])
    pn_values = block_process_noise(opts, layout)
    empty = np.zeros(0)
    prob = Problem(
        imu_t=empty, imu_u=np.zeros((0, 6)), imu_um=np.zeros((0, 6)),
        uwb_t=empty, uwb_a=np.zeros(0, dtype=np.int64), uwb_r=empty, anchor_ids=[str(a) for a in anchor_ids],
        anchors=anchors,
        noise=np.r_[imu, pn_values["lever"][0], pn_values["t_d"][0]],
        process_noise=layout.process_noise(imu, pn_values),
        r_var=float(range_sigma**2), bias_idx=bias_idx, gain_mask=gain_mask(opts, layout), dt_nom=float("nan"),
        dt_max=float("nan"), gate=gate, robust_kind=_ROBUST[opts.gating.robust],
        robust_c=opts.gating.robust_c, reopen_after=opts.gating.reopen_after, cov_every=opts.cov_every,
        max_lookback=opts.max_lookback_s, out_period=1.0 / opts.output_rate_hz, store_cov=opts.store_covariance,
        hull_lo=anchors.min(axis=0) - opts.supervisor.hull_margin,
        hull_hi=anchors.max(axis=0) + opts.supervisor.hull_margin,
        max_pos_var=opts.supervisor.max_position_sd**2,
        all_reject_run=opts.supervisor.all_reject_run, supervise=opts.supervisor.enabled,
        layout=layout, tag_names=list(tag_names) if tag_names else [],
        tag_lever_err=np.array([layout.lever_err(i).start for i in range(n_tags)], dtype=np.int64),
        pair_index={pq: layout.err("pair_bias").start + i for i, pq in enumerate(pairs)},
        tdoa_var=float(tdoa_sigma or math.sqrt(2.0) * range_sigma) ** 2,
        priors=priors,
    )
    return prob, priors


def imu_timing(opts: EskfOptions, dt_nom: float) -> dict[str, Any]:
    """The :class:`Problem` fields fixed by the nominal IMU period ``dt_nom`` [s]: ``dt_nom``, the gap
    threshold ``dt_max`` [s], the lever-arm rotation gate's window ``lever_win`` [samples] and threshold
    ``lever_min_rate`` [rad/s] (0: no gate)."""
    out: dict[str, Any] = {"dt_nom": float(dt_nom), "dt_max": opts.imu_gap_factor * float(dt_nom),
                           "lever_win": 0, "lever_min_rate": 0.0}
    if opts.lever_arm.mode == "estimate" and opts.lever_arm.min_rotation_rate > 0:
        out["lever_win"] = max(1, int(round(opts.excitation.window_s / out["dt_nom"])))
        out["lever_min_rate"] = float(opts.lever_arm.min_rotation_rate)
    return out


def set_imu_timing(prob: Problem, opts: EskfOptions, dt_nom: float) -> None:
    """Fix the nominal IMU period and what depends on it on ``prob`` (:func:`imu_timing`; the streaming
    filter learns the period from its first samples, after construction)."""
    t = imu_timing(opts, dt_nom)
    prob.dt_nom, prob.dt_max = t["dt_nom"], t["dt_max"]
    if t["lever_min_rate"] > 0:
        prob.lever_win, prob.lever_min_rate = t["lever_win"], t["lever_min_rate"]
