"""Honest time-offset decisions: the initialiser's grid search and the final verdict.

Grid search (:func:`search_time_offset`)
    The bank scores are mean robust negative log-likelihoods per innovation;
    multiplied by half the number of innovations they become differences of
    total log-likelihood [nats], which is what the decisions use (a scale-free
    statistic: the likelihood-ratio test, 1.92 nats = the 95 % point of
    chi^2_1 / 2).  A minimum on the edge of the grid is never returned as
    found: the grid is widened on that side (up to ``max_abs_s``); a flat score
    (every point within the likelihood-ratio threshold of the best, or the
    plausible set reaching the widened edge) is reported as "not identified"
    and the time offset is held at its prior.  Otherwise the minimum is refined
    by a parabola through it and its neighbours, whose curvature also gives the
    sd of the refined value.

Verdict (:func:`time_offset_verdict`)
    From the information the data added relative to the prior,
    ``gain = (sd_prior / sd_post)^2 - 1`` (so independent of units and of the
    size of the offset): "identified" when the data carry at least 99 % of the
    final information (gain >= 99, i.e. sd shrank 10x), "weakly identified"
    when they carry at least half of it (gain >= 1), "not identified" below,
    and always "not identified" when the initial search failed (the filter then
    holds t_d at its prior in consider mode: no information is gained).
"""

from __future__ import annotations

import math
from typing import Callable, Optional

import numpy as np

LR_THRESHOLD_NATS = 1.92  # 95 % point of chi^2_1 / 2: likelihood-ratio interval of one parameter


def search_time_offset(score: Callable[[list[float]], tuple[np.ndarray, np.ndarray]], grid: list[float],
                       max_abs_s: float = 1.0, max_widen: int = 4) -> dict:
    """Grid search of the time offset with widening, flatness test and parabolic refinement.

    Parameters
    ----------
    score : callable taking a list of t_d values [s] and returning ``(mean_nll, n)``
        arrays: the mean robust NLL per innovation and the number of innovations.
    grid : initial, evenly spaced hypotheses [s].
    max_abs_s : widening stops at ``|t_d| = max_abs_s`` [s].
    max_widen : at most this many widenings.

    Returns
    -------
    dict with ``status`` ("found" | "not identified"), ``td`` and ``td_sd`` [s]
    (None when not identified), ``reason``, and the evaluated ``grid`` /
    ``scores`` / ``delta_nats`` (sorted by t_d).
    """
    g = sorted(float(v) for v in grid)
    step = float(np.median(np.diff(g))) if len(g) > 1 else 0.05
    s, n = score(g)
    tds, means, counts = list(g), list(s), list(n)
    reason = ""
    for _ in range(max_widen + 1):
        order = np.argsort(tds)
        tds = [tds[i] for i in order]
        means = [means[i] for i in order]
        counts = [counts[i] for i in order]
        m = np.asarray(means)
        if not np.any(np.isfinite(m)):
            return _out("not identified", None, None, "every hypothesis failed to score", tds, m, counts)
        i_best = int(np.nanargmin(np.where(np.isfinite(m), m, np.nan)))
        edge = i_best in (0, len(tds) - 1)
        if not edge:
            break
        lo, hi = tds[0], tds[-1]
        span = hi - lo + step
        if i_best == 0 and lo - step >= -max_abs_s - 1e-9:
            new = [round(lo - step * (i + 1), 6) for i in range(int(round(span / step)))]
            new = [v for v in new if v >= -max_abs_s - 1e-9]
        elif i_best == len(tds) - 1 and hi + step <= max_abs_s + 1e-9:
            new = [round(hi + step * (i + 1), 6) for i in range(int(round(span / step)))]
            new = [v for v in new if v <= max_abs_s + 1e-9]
        else:
            new = []
        if not new:
            reason = f"best score on the edge of the widest grid (|t_d| <= {max_abs_s:g} s)"
            break
        s2, n2 = score(new)
        tds += new
        means += list(s2)
        counts += list(n2)
    m = np.asarray(means, dtype=float)
    cnt = np.asarray(counts, dtype=float)
    i_best = int(np.nanargmin(np.where(np.isfinite(m), m, np.nan)))
    n_eff = float(cnt[i_best])
    delta = 0.5 * n_eff * (m - m[i_best])  # total NLL above the best [nats]
    if reason:
        return _out("not identified", None, None, reason, tds, m, counts, delta)
    plausible = np.isfinite(delta) & (delta < LR_THRESHOLD_NATS)
    if plausible.all():
        return _out("not identified", None, None,
                    f"flat score: every hypothesis within {LR_THRESHOLD_NATS} nats of the best", tds, m, counts, delta)
    if plausible[0] or plausible[-1]:
        return _out("not identified", None, None,
                    "the likelihood interval reaches the edge of the widest grid", tds, m, counts, delta)
    # parabola through the best point and its neighbours (total NLL in nats)
    x = np.asarray(tds[i_best - 1:i_best + 2])
    y = delta[i_best - 1:i_best + 2]
    if not np.all(np.isfinite(y)):
        return _out("found", tds[i_best], step, "neighbours of the best point did not score", tds, m, counts, delta)
    a, b, _ = np.polyfit(x, y, 2)
    if a <= 0:
        return _out("found", tds[i_best], step, "non-convex neighbourhood; kept the grid point", tds, m, counts,
                    delta)
    td = float(np.clip(-b / (2 * a), x[0], x[-1]))
    sd = float(1.0 / math.sqrt(2 * a))  # NLL = (td - td*)^2 / (2 sd^2)
    return _out("found", td, sd, "", tds, m, counts, delta)


def _out(status, td, sd, reason, tds, m, counts, delta=None) -> dict:
    return {"status": status, "time_offset": td, "time_offset_sd": sd, "reason": reason, "grid": [float(v) for v in tds],
            "scores": [float(v) for v in np.asarray(m, dtype=float)], "n": [int(c) for c in counts],
            "delta_nats": None if delta is None else [float(v) for v in delta]}


#: Information gain of the data over the prior, ``(sd_prior / sd_post)^2 - 1``, from which a parameter counts as
#: identified (the data carry >= 99x the prior's information: the prior sets under 1 % of it) and weakly
#: identified (as much as the prior or more).  One convention for every estimator's verdicts.
GAIN_IDENTIFIED, GAIN_WEAK = 99.0, 1.0


def time_offset_prior_sd(priors, opts) -> float:
    """The one definition of the time offset's prior sd [s]: what is known of t_d before the data.

    The configured ``time_offset.prior_sd``; when the initialiser searches the grid ``init.td_grid``
    (no configured prior value), the sd of a uniform over the searched span when that is larger. Used by
    the verdict (:func:`time_offset_verdict`), the excitation diagnostics and the reports; 0 when fixed.
    """
    sd = float(priors.t_d_sd)
    if sd <= 0:
        return 0.0
    if priors.search_t_d and len(opts.init.td_grid) > 1:
        g = np.asarray(opts.init.td_grid, dtype=float)
        sd = max(sd, float(g.max() - g.min()) / math.sqrt(12.0))
    return sd


def information_verdict(sd_post: float, sd_prior: float) -> tuple[str, float]:
    """``(verdict, gain)``: ``identified | weakly identified | not identified`` from the information gain
    ``(sd_prior / sd_post)^2 - 1`` of the data over the prior (scale-free; NaN gain: not identified)."""
    if not (np.isfinite(sd_post) and sd_post > 0 and np.isfinite(sd_prior) and sd_prior > 0):
        return "not identified", float("nan")
    gain = float((sd_prior / sd_post) ** 2 - 1.0)
    if gain >= GAIN_IDENTIFIED:
        return "identified", gain
    if gain >= GAIN_WEAK:
        return "weakly identified", gain
    return "not identified", gain


def time_offset_verdict(sd_post: float, sd_prior: float, fixed: bool = False,
                        init_status: Optional[str] = None) -> tuple[str, str]:
    """Verdict on the time offset from the information gained relative to the prior.

    Returns ``(verdict, reason)`` with verdict ``identified | weakly identified |
    not identified`` (``fixed`` when the time offset was not estimated).
    """
    if fixed:
        return "fixed", "time offset held at its configured value"
    if init_status == "not identified":
        return "not identified", ("the initial grid search could not locate it; held at its prior (consider "
                                  "mode, not updated by the data)")
    verdict, gain = information_verdict(sd_post, sd_prior)
    if not np.isfinite(gain):
        return verdict, "no finite posterior/prior sd"
    return verdict, f"sd {sd_post * 1e3:.3g} ms from prior {sd_prior * 1e3:.3g} ms (information gain {gain:.3g}x the prior)"


def is_single_clock(dataset) -> bool:
    """Whether ``dataset.yaml`` says every stream was stamped by one clock (``single_clock: true``): then
    there is no second clock for t_d to be offset from (the rule of both estimators)."""
    return getattr(getattr(dataset, "meta", None), "single_clock", None) is True


def single_clock_time_offset(dataset, opts):
    """The time-offset options for a log whose streams share one clock.

    With ``dataset.yaml`` ``single_clock: true`` (a Crazyflie uSD log: the IMU, the UWB and the ground
    truth were stamped by one clock) there is no second clock to be offset from: estimating t_d there
    only lets it trade with the other states (on the two shared Crazyflie logs it wandered between
    -0.5 and +0.8 s across settings).  Unless the user configured ``time_offset`` (any field), t_d is
    held fixed at 0 and an event ``time_offset_single_clock`` says so.  Returns ``(options, events)``.
    """
    if not is_single_clock(dataset) or "time_offset" in opts.model_fields_set:
        return opts, []
    t_d = opts.time_offset.model_copy(update={"mode": "fixed", "prior": 0.0})
    event = {"t": None, "kind": "time_offset_single_clock", "mode": "fixed", "t_d": 0.0,
             "message": "every stream of this log was stamped by one clock (dataset.yaml single_clock: true): "
                        "t_d held at 0; set time_offset.mode: estimate to estimate a latency"}
    return opts.model_copy(update={"time_offset": t_d}), [event]
