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
from typing import Any, Optional, Sequence

import numpy as np
from scipy.stats import chi2

from uwbimu.estimation import kernels as K
from uwbimu.estimation.filterpass import Problem
from uwbimu.estimation.options import EskfOptions
from uwbimu.models.imu import ImuNoise
from uwbimu.models import state as S

#: IMU periods whose median is the nominal period (the first ones: known early by a streaming filter)
NOMINAL_PERIOD_SAMPLES = 1000

_ROBUST = {"none": K.ROBUST_NONE, "huber": K.ROBUST_HUBER, "geman-mcclure": K.ROBUST_GM}


def nominal_period(imu_t: np.ndarray) -> float:
    """Median of the first :data:`NOMINAL_PERIOD_SAMPLES` IMU periods [s]."""
    d = np.diff(np.asarray(imu_t[: NOMINAL_PERIOD_SAMPLES + 1], dtype=float))
    return float(np.median(d))


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
) -> tuple[Problem, dict[str, Any]]:
    """A :class:`Problem` with the resolved settings and no data, and the calibration priors.

    Parameters
    ----------
    anchors : (M, 3) anchor positions in the filter's (z-up) world frame [m].
    noise : IMU noise densities (already scaled by the options).
    range_sigma, tdoa_sigma : measurement noise sd [m] (``tdoa_sigma`` None: ``sqrt(2) range_sigma``).
    lever_prior : (3,) prior lever arm [m], IMU frame, or ``(T, 3)``: one per tag of ``tag_names``.
    tag_names : the tags whose lever arms are estimated (one filter, one lever arm each); None: one tag.
    tdoa_pairs : anchor-index pairs ``(a, b)`` that get a bias state (``tdoa_pair_bias.mode: estimate``).
    """
    anchors = np.ascontiguousarray(np.asarray(anchors, dtype=float).reshape(-1, 3))
    M = len(anchor_ids)
    nb = M if opts.anchor_bias.mode != "fixed" else 0
    levers = np.array(lever_prior, dtype=float).reshape(-1, 3)
    n_tags = max(len(tag_names) if tag_names else 1, 1)
    if len(levers) == 1 and n_tags > 1:
        levers = np.repeat(levers, n_tags, axis=0)
    if len(levers) != n_tags:
        raise ValueError(f"make_settings: {len(levers)} lever-arm priors for {n_tags} tags")
    pairs = [tuple(int(v) for v in pq) for pq in (tdoa_pairs or [])] if opts.tdoa_pair_bias.mode == "estimate" else []
    layout = S.StateLayout(nb, 1 if opts.height.bias == "estimate" else 0, n_tags, len(pairs))
    N = layout.n_err
    mask = np.ones(N)
    if opts.lever_arm.mode != "estimate":
        mask[S.EPIU] = 0.0
        mask[layout.err("extra_levers")] = 0.0
    if opts.time_offset.mode != "estimate":
        mask[S.ETD] = 0.0
    if nb and opts.anchor_bias.mode != "estimate":
        mask[layout.err("anchor_bias")] = 0.0
    bias_idx = np.full(M, -1, dtype=np.int64)
    if nb:
        bias_idx[:] = S.ERROR_DIM + np.arange(M)
    gate = float(chi2.ppf(opts.gating.probability, 1)) if opts.gating.probability < 1 else -1.0
    empty = np.zeros(0)
    prob = Problem(
        imu_t=empty, imu_u=np.zeros((0, 6)), imu_um=np.zeros((0, 6)),
        uwb_t=empty, uwb_a=np.zeros(0, dtype=np.int64), uwb_r=empty, anchor_ids=[str(a) for a in anchor_ids],
        anchors=anchors,
        noise=np.array([noise.accel_noise_density**2, noise.gyro_noise_density**2, noise.accel_bias_rw**2,
                        noise.gyro_bias_rw**2, opts.lever_arm.random_walk**2, opts.time_offset.random_walk**2]
                       + _extra_noise(opts, nb, layout.n_height_bias, n_tags - 1, len(pairs))),
        r_var=float(range_sigma**2), bias_idx=bias_idx, gain_mask=mask, dt_nom=float("nan"),
        dt_max=float("nan"), gate=gate, robust_kind=_ROBUST[opts.gating.robust],
        robust_c=opts.gating.robust_c, reopen_after=opts.gating.reopen_after, cov_every=opts.cov_every,
        max_lookback=opts.max_lookback_s, out_period=1.0 / opts.output_rate_hz, store_cov=opts.store_covariance,
        hull_lo=anchors.min(axis=0) - opts.supervisor.hull_margin,
        hull_hi=anchors.max(axis=0) + opts.supervisor.hull_margin,
        max_pos_var=opts.supervisor.max_position_sd**2,
        all_reject_run=opts.supervisor.all_reject_run, supervise=opts.supervisor.enabled,
    )
    prob.layout = layout
    prob.tag_names = list(tag_names) if tag_names else []
    prob.tag_lever_err = np.array([layout.lever_err(i).start for i in range(n_tags)], dtype=np.int64)
    prob.pair_index = {pq: layout.err("pair_bias").start + i for i, pq in enumerate(pairs)}
    prob.pair_sd0 = opts.tdoa_pair_bias.prior_sd if pairs else 0.0
    prob.height_sd0 = opts.height.bias_prior_sd if layout.n_height_bias else 0.0
    tsig = tdoa_sigma or math.sqrt(2.0) * range_sigma
    prob.tdoa_var = float(tsig) ** 2
    sd_ba = opts.accel_bias_sd or (noise.accel_bias_sigma0 if noise.accel_bias_sigma0 > 0 else 0.1)
    sd_bg = opts.gyro_bias_sd or (noise.gyro_bias_sigma0 if noise.gyro_bias_sigma0 > 0 else math.radians(1.0))
    td_mode = opts.time_offset.mode
    priors = {
        "lever": levers[0].copy(),
        "tag_levers": levers,
        "sd_lever": np.zeros(3) if opts.lever_arm.mode == "fixed" else np.full(3, opts.lever_arm.prior_sd),
        "anchor_bias": np.zeros(nb),
        "sd_bias": opts.anchor_bias.prior_sd if nb else 0.0,
        "ba": np.zeros(3), "bg": np.zeros(3), "sd_ba": sd_ba, "sd_bg": sd_bg,
        "td": float(opts.time_offset.prior or 0.0),
        "td_sd": 0.0 if td_mode == "fixed" else opts.time_offset.prior_sd,
        "search_td": td_mode != "fixed" and opts.time_offset.prior is None and opts.init.search_time_offset,
    }
    return prob, priors


def _extra_noise(opts: EskfOptions, nb: int, nh: int, n_lev: int = 0, n_pair: int = 0) -> list[float]:
    """Noise entries after the six densities (see ``models.kernels.cov_step``)."""
    gm = [opts.anchor_bias.prior_sd**2, 1.0 / opts.anchor_bias.correlation_time] \
        if nb and opts.anchor_bias.correlation_time else [0.0, 0.0]
    if nh or n_lev or n_pair:
        return gm + [float(nb), opts.height.bias_random_walk**2, 3.0 * n_lev, float(n_pair)]
    return gm if nb and opts.anchor_bias.correlation_time else []


def set_imu_timing(prob: Problem, opts: EskfOptions, dt_nom: float) -> None:
    """Fix the nominal IMU period and what depends on it (gap threshold, rotation-gate window)."""
    prob.dt_nom = float(dt_nom)
    prob.dt_max = opts.imu_gap_factor * prob.dt_nom
    if opts.lever_arm.mode == "estimate" and opts.lever_arm.min_rotation_rate > 0:
        prob.lever_win = max(1, int(round(opts.excitation.window_s / prob.dt_nom)))
        prob.lever_min_rate = float(opts.lever_arm.min_rotation_rate)
