"""UWB clock jumps and drift relative to the IMU, found in a filter run's innovations.

Why this works: a range stamped ``t`` observes the state at IMU time ``t + t_d``;
the filter predicts it at ``t + t_d_hat``.  To first order the innovation is
``e = r_dot * (t_d - t_d_hat)`` plus noise, with ``r_dot`` the range rate.  Over a
window, the weighted regression of ``e`` on ``r_dot`` gives the correction
``delta``; ``tau = t_d_hat + delta`` then estimates the effective time offset in
that window.  A healthy log has one ``tau`` throughout; a clock jump is a step
in ``tau`` (a change point), a clock drift a trend.

:func:`detect_clock_faults` returns structured events::

    {"kind": "clock_jump", "t": T, "size": s, "sigma": sd, "t_d_before": ..., "t_d_after": ...}
    {"kind": "clock_drift", "rate": r, "sigma": sd, "t0": ..., "t1": ...}

``size`` is the change of the effective offset (s): ranges stamped after ``T``
observe the state ``size`` seconds later than before.  A UWB clock that jumps
forward by J gives ``size = -J``.  :func:`correct_clock_jumps` shifts the UWB
stamps after each jump by ``size`` so the whole log shares one offset, and
:func:`handle_clock_faults` re-runs the estimator on the corrected log.

Significance is judged against the per-window standard deviations (a step or
trend must exceed :data:`SIGNIFICANCE` sigmas) and against the scatter of the
window estimates themselves (so unmodelled effects inflate the threshold).
"""

from __future__ import annotations

from typing import Any, Callable, Optional

import numpy as np
import pandas as pd

from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.models.state import PIU, TD, P, Q, V

#: A step or trend must exceed this many standard deviations to be reported.
SIGNIFICANCE = 6.0
#: Once a jump is significant, its onset is the first window this many sigmas off the earlier ones.
ONSET_SIGNIFICANCE = 3.0
#: Largest clock drift reported [s/s]: quartz clocks drift by tens of ppm; a larger "trend" of
#: the effective offset is model mismatch, not a clock.
MAX_DRIFT = 1e-3
#: A jump is kept when correcting it lowers the clipped NIS sum by more than this (a likelihood
#: ratio for one extra parameter; 30 is about 5.5 sigma).
NIS_DROP_MIN = 30.0
#: Ranges per window of the regression (the window length adapts to the range rate).
RANGES_PER_WINDOW = 120
#: Smallest reported jump [s]: below the resolution the estimator's own t_d tracking absorbs.
MIN_JUMP_S = 0.02


def _antenna_track(result, t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Antenna position, velocity and filter t_d interpolated at UWB times ``t``."""
    X = result.states
    tt = result.t
    p_iu = X[:, PIU]
    R = quat_to_rotmat(X[:, Q])
    p_u = X[:, P] + np.einsum("kij,kj->ki", R, p_iu)
    v = X[:, V]
    td = X[:, TD] if X.shape[1] > TD else np.full(len(tt), result.calibration.get("time_offset", 0.0))
    out_p = np.column_stack([np.interp(t, tt, p_u[:, i]) for i in range(3)])
    out_v = np.column_stack([np.interp(t, tt, v[:, i]) for i in range(3)])
    return out_p, out_v, np.interp(t, tt, td)


def _window_estimates(t, rdot, e, td_hat, n_per):
    """Per-window ``tau`` estimate, its sd and the window's mid time (robust, outliers trimmed)."""
    rows = []
    for s in range(0, len(t) - n_per // 2, n_per):
        sl = slice(s, min(len(t), s + n_per))
        x, y = rdot[sl], e[sl]
        if np.sum(x * x) <= 0:
            continue
        keep = np.ones(len(x), bool)
        for _ in range(3):
            d = np.sum(x[keep] * y[keep]) / np.sum(x[keep] ** 2)
            r = y - x * d
            mad = np.median(np.abs(r[keep] - np.median(r[keep]))) * 1.4826 + 1e-6
            keep = np.abs(r) < 5 * mad
            if keep.sum() < 10:
                break
        if keep.sum() < 10:
            continue
        sxx = float(np.sum(x[keep] ** 2))
        d = float(np.sum(x[keep] * y[keep]) / sxx)
        sigma_r = float(np.std(y[keep] - x[keep] * d, ddof=1))
        rows.append((float(np.median(t[sl])), float(t[sl][0]), float(np.median(td_hat[sl])) + d,
                     sigma_r / np.sqrt(sxx), s, min(len(t), s + n_per)))
    return np.array(rows) if rows else np.zeros((0, 6))


def _weighted_mean(y, w):
    return float(np.sum(w * y) / np.sum(w))


def detect_clock_faults(result, dataset, significance: float = SIGNIFICANCE,
                        ranges_per_window: int = RANGES_PER_WINDOW) -> list[dict[str, Any]]:
    """Clock jumps and drift of the UWB clock relative to the IMU, from a filter run.

    Parameters
    ----------
    result : :class:`uwbimu.estimation.EstimationResult` of an ESKF run (states with t_d).
    dataset : the :class:`~uwbimu.io.dataset.Dataset` it ran on (anchor positions).

    Returns
    -------
    list of event dicts (``kind`` ``clock_jump`` or ``clock_drift``), empty when the
    effective time offset is constant within the noise.
    """
    res = result.residuals
    if res is not None and "kind" in res.columns:
        res = res[res["kind"] == "range"]  # TDoA rows are not ranges (one-line hook, core)
    if res is None or len(res) < 4 * ranges_per_window or "innovation" not in res.columns:
        return []
    res = res[np.isfinite(res["innovation"].to_numpy())]
    res = res.sort_values("t", kind="stable")
    t = res["t"].to_numpy(float)
    inside = (t >= result.t[0]) & (t <= result.t[-1])
    res, t = res[inside], t[inside]
    pos = dataset.anchor_positions()
    pa = np.array([pos[str(a)] for a in res["anchor"]])
    p_u, v_u, td_hat = _antenna_track(result, t)
    d = p_u - pa
    rdot = np.sum(d * v_u, axis=1) / np.maximum(np.linalg.norm(d, axis=1), 1e-6)
    e = res["innovation"].to_numpy(float)
    w = _window_estimates(t, rdot, e, td_hat, ranges_per_window)
    if len(w) < 4:
        return []
    tm, tstart, tau, sd = w[:, 0], w[:, 1], w[:, 2], np.maximum(w[:, 3], 1e-5)
    wt = 1.0 / sd ** 2
    chi_const = float(np.sum(wt * (tau - _weighted_mean(tau, wt)) ** 2))
    # Best single step.
    best = (np.inf, None)
    for k in range(2, len(tau) - 1):
        m1, m2 = _weighted_mean(tau[:k], wt[:k]), _weighted_mean(tau[k:], wt[k:])
        c = float(np.sum(wt[:k] * (tau[:k] - m1) ** 2) + np.sum(wt[k:] * (tau[k:] - m2) ** 2))
        if c < best[0]:
            best = (c, k)
    # Best line.
    A = np.column_stack([np.ones_like(tm), tm - tm.mean()])
    coef, *_ = np.linalg.lstsq(A * np.sqrt(wt)[:, None], tau * np.sqrt(wt), rcond=None)
    chi_line = float(np.sum(wt * (tau - A @ coef) ** 2))
    events: list[dict[str, Any]] = []
    dof = len(tau) - 2
    chi_step, k = best
    # Scale sigmas by the excess scatter of the better model (unmodelled effects).
    inflate = max(1.0, np.sqrt(min(chi_step, chi_line) / max(dof, 1)))
    if k is not None and chi_step <= chi_line:
        m1, m2 = _weighted_mean(tau[:k], wt[:k]), _weighted_mean(tau[k:], wt[k:])
        s_jump = inflate * float(np.sqrt(1 / np.sum(wt[:k]) + 1 / np.sum(wt[k:])))
        size = m2 - m1
        if abs(size) > significance * s_jump and abs(size) >= MIN_JUMP_S:
            k = _onset(tau, sd, wt, ONSET_SIGNIFICANCE, k)
            region = (float(w[k - 1, 1]), float(t[min(int(w[k, 5]), len(t) - 1)]))
            t_jump, gap = _jump_time(t, rdot, e, td_hat, int(w[k - 1, 4]), int(w[k, 5]), m1, m2)
            events.append({"kind": "clock_jump", "t": t_jump, "size": float(size), "sigma": float(s_jump),
                           "stamp_gap": gap,
                           "t_d_before": float(m1), "t_d_after": float(m2), "region": list(region),
                           "size_from": "innovation regression"})
            return events
    if chi_line < chi_const:
        cov = np.linalg.inv((A * wt[:, None]).T @ A)
        s_rate = inflate * float(np.sqrt(cov[1, 1]))
        if (abs(coef[1]) > significance * s_rate and abs(coef[1]) * (tm[-1] - tm[0]) >= MIN_JUMP_S
                and abs(coef[1]) <= MAX_DRIFT):
            events.append({"kind": "clock_drift", "rate": float(coef[1]), "sigma": s_rate,
                           "t0": float(tstart[0]), "t1": float(tm[-1])})
    return events


def _onset(tau, sd, wt, significance: float, k_best: int) -> int:
    """First window that departs from the mean of the windows before it (the jump's onset).

    The best two-mean split can land late when the filter loses track after a large
    jump; the onset scan finds where the departure starts.
    """
    for j in range(2, k_best + 1):
        m = _weighted_mean(tau[:j], wt[:j])
        if abs(tau[j] - m) > significance * np.sqrt(sd[j] ** 2 + 1.0 / np.sum(wt[:j])):
            return j
    return k_best


def _jump_time(t, rdot, e, td_hat, i0, i1, tau_before, tau_after) -> float:
    """Time of the jump in ranges i0..i1: after the largest stamp gap there, else the best two-offset split.

    A forward jump of the UWB clock leaves a gap of its size in the range stamps.
    """
    tt = t[i0:i1]
    gaps = np.diff(tt)
    typical = float(np.median(np.diff(t)[np.diff(t) > 0])) if np.any(np.diff(t) > 0) else 0.0
    if len(gaps) and typical > 0 and gaps.max() > 5 * typical:
        return float(tt[int(np.argmax(gaps)) + 1]), float(gaps.max() - typical)
    return _refine_jump(t, rdot, e, td_hat, i0, i1, tau_before, tau_after), None


def _refine_jump(t, rdot, e, td_hat, i0, i1, tau_before, tau_after) -> float:
    """The split of ranges i0..i1 that fits the two offsets best."""
    x, y, th = rdot[i0:i1], e[i0:i1], td_hat[i0:i1]
    r1 = (y - x * (tau_before - th)) ** 2
    r2 = (y - x * (tau_after - th)) ** 2
    r1 = np.minimum(r1, np.percentile(r1, 95))
    r2 = np.minimum(r2, np.percentile(r2, 95))
    cost = np.concatenate([[0.0], np.cumsum(r1)]) + np.concatenate([np.cumsum(r2[::-1])[::-1], [0.0]])
    s = int(np.argmin(cost))
    return float(t[i0 + min(s, len(x) - 1)])


def correct_clock_jumps(dataset, events: list[dict[str, Any]]):
    """A copy of ``dataset`` whose UWB stamps (ranges, TDoA) after each jump are shifted by its size."""
    import copy

    ds = copy.copy(dataset)
    for name in ("uwb", "tdoa"):
        df = getattr(dataset, name, None)
        if df is None or len(df) == 0:
            continue
        t = df["t"].to_numpy(float).copy()
        for ev in events:
            if ev["kind"] == "clock_jump":
                t[t >= ev["t"]] += ev["size"]
        out = df.copy()
        out["t"] = t
        setattr(ds, name, out.sort_values("t", kind="stable").reset_index(drop=True))
    return ds


def _segment(dataset, a: float, b: float):
    """The part of ``dataset`` with stamps in ``[a, b]`` (all tables)."""
    import copy

    ds = copy.copy(dataset)
    for name in ("imu", "uwb", "tdoa", "groundtruth"):
        df = getattr(dataset, name, None)
        if df is not None:
            t = df["t"].to_numpy(float)
            setattr(ds, name, df[(t >= a) & (t <= b)].reset_index(drop=True))
    return ds


def _fit_cost(result, t_from: float = -np.inf) -> tuple[float, int]:
    """Mean clipped NIS of the processed ranges from ``t_from`` on (rejections cost the clip), and their count."""
    nis = result.residuals["nis"].to_numpy(float)
    nis = nis[np.isfinite(nis) & (result.residuals["t"].to_numpy(float) >= t_from)]
    return (float(np.mean(np.minimum(nis, 25.0))), len(nis)) if len(nis) else (np.inf, 0)


def estimate_jump_size(dataset, event: dict[str, Any], rerun: Callable, half_window: float = 10.0,
                       max_size: float = 1.0) -> dict[str, Any]:
    """Size of a detected jump by re-running the estimator on a segment around it.

    The innovation regression finds *where* the offset changes, but the filter
    partly absorbs a large jump into its position, which biases the regressed size.
    Here the stamps after the jump are shifted by candidate sizes (coarse grid over
    ``±max_size`` s, then a fine grid; only near the stamp gap when the jump left one)
    and the size with the best mean clipped NIS
    of the re-run on ``[t - half_window, t + half_window]`` wins.
    """
    T = event["t"]
    # The filter must have converged before the jump (initialisation takes several seconds):
    # twice as much data before it as after, and only ranges near and after it are scored.
    seg = _segment(dataset, T - 2 * half_window, T + half_window)

    counts: list[int] = []

    def cost(size: float) -> float:
        try:
            c, n = _fit_cost(rerun(correct_clock_jumps(seg, [{"kind": "clock_jump", "t": T, "size": size}])),
                             T - 2.0)
        except Exception:  # noqa: BLE001 - a candidate the estimator cannot run on is simply a bad fit
            return np.inf
        counts.append(n)
        return c

    if event.get("stamp_gap"):
        # A forward jump of J leaves a stamp gap of about J: search near -gap only, and only
        # when shifting by the gap fits better at all (a plain dropout does not).
        step = 0.01
        base = cost(0.0)
        if not cost(-event["stamp_gap"]) < base:
            out = dict(event)
            out.update({"resolution": step, "cost_uncorrected": base, "nis_sum_drop": 0.0})
            return out
        fine = min(((cost(c), c) for c in -event["stamp_gap"] + np.arange(-6, 7) * step), key=lambda x: x[0])
    else:
        coarse = min(((cost(c), c) for c in np.linspace(-max_size, max_size, 11)), key=lambda x: x[0])
        step = 2 * max_size / 10 / 10
        fine = min(((cost(c), c) for c in coarse[1] + np.arange(-5, 6) * step), key=lambda x: x[0])
    edge = (abs(fine[1]) >= max_size - 5 * step if not event.get("stamp_gap")
            else abs(abs(fine[1]) - event["stamp_gap"]) >= 6 * step - 1e-12)
    base = cost(0.0) if not event.get("stamp_gap") else base
    out = dict(event)
    if event.get("size_from") == "innovation regression":
        out["size_regression"] = float(event["size"])
    out.update({"size": float(fine[1]), "resolution": float(step), "size_from": "segment re-run search",
                "at_search_boundary": bool(edge),
                "cost_uncorrected": base, "cost_corrected": fine[0],
                # the clipped-NIS sum is a (robust) log-likelihood: its drop is a likelihood ratio
                "nis_sum_drop": float((base - fine[0]) * (min(counts) if counts else 0))})
    return out


def gap_candidates(dataset, max_candidates: int = 3, min_gap_s: float = MIN_JUMP_S) -> list[dict[str, Any]]:
    """Forward-jump candidates: the largest gaps in the UWB stamps (a forward jump of J leaves a gap of J).

    A gap is also what a dropout looks like; :func:`handle_clock_faults` keeps a candidate
    only when shifting the stamps after it fits the data clearly better.
    """
    u = dataset.uwb if len(dataset.uwb) else getattr(dataset, "tdoa", None)
    if u is None or len(u) < 10:
        return []
    t = np.unique(u["t"].to_numpy(float))
    d = np.diff(t)
    typical = float(np.median(d))
    idx = np.flatnonzero(d > max(5 * typical, min_gap_s + typical))
    idx = idx[np.argsort(d[idx])[::-1][:max_candidates]]
    return [{"kind": "clock_jump", "t": float(t[i + 1]), "size": -float(d[i] - typical), "sigma": float("nan"),
             "stamp_gap": float(d[i] - typical), "size_from": "stamp gap"} for i in sorted(idx)]


def _credible(ev: dict[str, Any]) -> bool:
    """Keep a jump only when the re-run evidence is clear and self-consistent.

    On real logs model mismatch can make an arbitrary shift fit slightly better; such a
    fit has no interior minimum (the best size sits on the search boundary) or contradicts
    the sign of the innovation regression.
    """
    if not (ev.get("nis_sum_drop", 0.0) > NIS_DROP_MIN and abs(ev["size"]) >= MIN_JUMP_S):
        return False
    if ev.get("at_search_boundary"):
        return False
    reg = ev.get("size_regression")
    return reg is None or np.sign(reg) == np.sign(ev["size"])


def handle_clock_faults(result, dataset, rerun: Callable, console=None, max_rounds: int = 2):
    """Detect clock faults in ``result``; on a jump, correct the stamps and re-run (``rerun(dataset)``).

    Returns ``(result, dataset)``: the final run (its ``events`` and ``warnings`` name
    every fault found and how it was handled) and the dataset it ran on.
    """
    found: list[dict[str, Any]] = []
    for _ in range(max_rounds):
        events = detect_clock_faults(result, dataset)
        jumps = [ev for ev in events if ev["kind"] == "clock_jump"]
        if not jumps:
            # Small forward jumps can hide in the innovations; their stamp gap does not.
            jumps = gap_candidates(dataset)
        for ev in events:
            if ev["kind"] == "clock_drift":
                ev["handled"] = "reported only: the filter's t_d tracks slow drift"
                found.append(ev)
        if not jumps:
            break
        jumps = [estimate_jump_size(dataset, ev, rerun) for ev in jumps]
        jumps = [ev for ev in jumps if _credible(ev)]
        if not jumps:
            break
        corrected = correct_clock_jumps(dataset, jumps)
        new = rerun(corrected)
        # The whole log must fit clearly better too (a local improvement on a real log with
        # model mismatch is not enough): same likelihood-ratio test on the full run.
        c0, n0 = _fit_cost(result)
        c1, n1 = _fit_cost(new)
        if not (c0 - c1) * min(n0, n1) > NIS_DROP_MIN:
            break
        for ev in jumps:
            ev["handled"] = "UWB stamps after the jump shifted by its size; estimator re-run"
            ev["full_log_nis_sum_drop"] = float((c0 - c1) * min(n0, n1))
        found.extend(jumps)
        dataset, result = corrected, new
    for ev in found:
        if ev["kind"] == "clock_jump":
            msg = (f"UWB clock jump at t={ev['t']:.3f} s: the time offset changes by {1000 * ev['size']:+.1f} ms "
                   f"(grid resolution {1000 * ev['resolution']:.0f} ms); {ev['handled']}")
        else:
            msg = (f"UWB clock drift of {1e6 * ev['rate']:+.1f} ± {1e6 * ev['sigma']:.1f} ppm between "
                   f"t={ev['t0']:.1f} and {ev['t1']:.1f} s; {ev['handled']}")
        result.warnings.append(msg)
        result.events.append(dict(ev))
        if console is not None:
            console.print(f"[yellow]clock fault:[/yellow] {msg}", soft_wrap=True)
    return result, dataset
