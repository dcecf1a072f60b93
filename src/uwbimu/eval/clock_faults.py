"""UWB clock jumps and drift relative to the IMU: detected, timed, corrected, reported.

Detection (no re-run): :func:`uwbimu.eval.clock_windows.windowed_time_offsets` turns the
filter's own (lever arm, t_d) information track into per-window estimates of the effective time
offset ``tau`` (a range stamped ``t`` observes the IMU at ``t + tau``), and
:func:`~uwbimu.eval.clock_windows.consistency_tests` tests them for a step (jump) and a trend
(drift) at false-alarm probability :data:`~uwbimu.eval.clock_windows.ALPHA` each, with the
window sds scaled by their measured scatter.  A clean log therefore costs nothing beyond the
run that produced it.

Handling (re-runs, only when a fault was found): the UWB stamps are corrected, the estimator
re-runs, and the residual step / trend measured on the corrected run is added (secant on the
filter's absorption gain: it partly absorbs a jump into position and attitude, so one round
under-estimates it) until it is below half its sd.  When both tests pass, both corrections are
made and the one whose corrected log is more likely is kept.

Confirmation (:func:`confirm_fault`, the stated rule that holds the false-alarm probability
when the range errors are not white): the window tests credit the filter's information, which
holds for white range errors.  Coloured (vibration, multipath) and heavy-tailed (NLOS) errors
carry less information about a slow parameter, by the long-run variance ``L`` of the normalised
innovations (batch means, :func:`uwbimu.estimation.noise_from_data.residual_variance_factor`),
measured on the corrected run (the residuals under the alternative: a real fault leaves white
residuals once corrected).  A fault is declared and corrected only when the window statistic
with its sds scaled by ``max(c, sqrt(L))`` still exceeds its critical value and the innovation
log-likelihood gain divided by ``L`` exceeds the chi-square(k) threshold at ``alpha``;
otherwise the input run is kept and the event says ``corrected: False``.
Corrections act on the input stamps ``t``:

* drift: ``t' = t + s (t - t0)`` (``s`` the slope of tau, ``t0`` the first UWB stamp), i.e. the
  time offset modelled as ``t_d(t) = t_d0 + s (t - t0)``; the reported clock rate is
  ``rate = -s / (1 + s)`` (UWB clock rate relative to the IMU's, s/s; ppm = 1e6 rate);
* jump: ``t' = t + size`` for ``t >= T`` (``size`` = change of tau at ``T``; a UWB clock that
  jumps forward by J gives ``size = -J``).

Events (``result.events``)::

    {"kind": "clock_jump", "t": T, "size": s, "sigma": sd, "z": z, "crit": zc, "alpha": a,
     "t_d": ..., "t_d_sd": ..., ...}
    {"kind": "clock_drift", "t": t0, "t0": t0, "t1": t1, "rate": r, "sigma": sd, "rate_ppm": ...,
     "sigma_ppm": ..., "t_d_slope": s, "t_d0": td0, "t_d0_sd": ..., ...}

``sigma`` is the scaled sd of the last residual estimate over the absorption gain; ``t_d_sd``
(also written into the run's ``calibration["time_offset_sd"]``) includes the correction's
uncertainty.  The jump time ``T`` is the first stamp after a stamp gap when the jump left one
(forward jumps; the size is then the gap unless the corrected run contradicts it), else the
onset of the NIS excess when it stands out against the log before it, else where finer windows
of tau reach the later level.

Shown by tests (``tests/test_clock_faults.py``, ``tests/test_clock_drift.py``,
``tests/test_clock_faults_round27.py``, seeded simulations): jumps of +0.3, -0.3, -0.2 (stamps
monotonic) and +0.12 s found within 0.5 s with the size within 3 sd, drifts of 3000 and 300 ppm
found with the rate within 3 sd, no event on clean logs or a dropout, calibration after handling
within 3 sd of the truth, a candidate on AR(1) range noise not confirmed, single-clock logs
never tested.  Measured (``benchmarks/check_clock_false_alarms.py``): no fault declared on 80
fault-free logs with AR(1) or NLOS range errors (95 % upper bound 4.5 %), 1/80 at alpha = 0.01
(nominal 2 %).  Not shown: the stated alpha (1e-4) itself, which a few dozen logs cannot
resolve; one fault per log is corrected (a second one still significant afterwards is a
warning); a fault the filter cannot follow ends in divergence and re-initialisations, across
which no window is formed (then only a warning); on coloured logs a fault must be larger to be
confirmed (the data say less).
"""

from __future__ import annotations

import copy
from typing import Any, Callable, Optional

import numpy as np

from uwbimu.estimation.noise_from_data import residual_variance_factor
from uwbimu.eval.clock_windows import ALPHA, consistency_tests, fit_step, windowed_time_offsets

#: Most correction rounds (each one estimator re-run).
MAX_ROUNDS = 6
#: A residual correction is applied while it exceeds this many of its sds (the residual step is
#: itself partly absorbed, so the rounds stop a little below one sd rather than at it).
REFINE_SD = 0.5
#: Regions are measured in windows: the filter's t_d answers a jump this many windows late at most.
LAG_WINDOWS = 6


def _range_rows(result):
    """Residual rows with an NIS (ranges and TDoA alike: the NIS is normalised)."""
    res = result.residuals
    if res is None or len(res) == 0 or "nis" not in res.columns:
        return res.iloc[0:0] if res is not None else None
    return res


def _max_excess(x: np.ndarray) -> tuple[float, int]:
    """Largest sum of a contiguous stretch of ``x`` and the stretch's first index (Kadane)."""
    best, start, run_sum, run_start = -np.inf, 0, 0.0, 0
    for i, v in enumerate(x):
        if run_sum <= 0:
            run_sum, run_start = 0.0, i
        run_sum += v
        if run_sum > best:
            best, start = run_sum, run_start
    return float(best), start


def _nis_onset(result, t_lo: float, t_hi: float) -> Optional[float]:
    """Start of the stretch of excess NIS in ``[t_lo, t_hi]`` (the filter's surprise after a jump),
    or None when that excess is not larger than in every same-length stretch before it (an
    empirical null from the log itself: on real logs model mismatch can hide the jump's NIS)."""
    r = _range_rows(result)
    if r is None or len(r) == 0:
        return None
    rt = r["t"].to_numpy(float)
    nis = r["nis"].to_numpy(float)
    ok = np.isfinite(nis)
    rt = rt[ok]
    gate = float((result.config.get("resolved") or {}).get("gate_nis") or 10.8)
    x = np.minimum(nis[ok], gate)
    inside = (rt >= t_lo) & (rt <= t_hi)
    before = rt < t_lo  # the log before the jump: after it the filter may still be recovering
    if inside.sum() < 8 or before.sum() < 8:
        return None
    base = float(np.mean(x[before]))
    s_in, i0 = _max_excess(x[inside] - base)
    span = t_hi - t_lo
    null = []
    for a in np.arange(rt[0], t_lo - span + 1e-9, span / 4):  # same-length stretches before the region
        m = (rt >= a) & (rt < a + span)
        if m.sum() >= 8:
            null.append(_max_excess(x[m] - base)[0])
    if not null or not s_in > max(null):
        return None
    # CUSUM reference halfway between the levels: small fluctuations before the jump reset the sum
    xi = x[inside]
    end = i0 + int(np.argmax(np.cumsum(xi[i0:] - base))) + 1
    level = float(np.mean(xi[i0:end]))
    return float(rt[inside][_max_excess(xi - 0.5 * (base + level))[1]])


def _window_onset(result, t_lo: float, t_hi: float, m1: float, m2: float, W: float) -> Optional[float]:
    """First of finer windows (W/4) in ``[t_lo, t_hi]`` from which tau sits at the later level ``m2``."""
    fine = windowed_time_offsets(result, window_s=W / 4)
    m = (fine["t"] >= t_lo) & (fine["t"] <= t_hi)
    y, w, t0 = fine["tau"][m], 1.0 / fine["sd"][m] ** 2, fine["t0"][m]
    if len(y) < 2:
        return None
    cost = [np.sum(w[:k] * (y[:k] - m1) ** 2) + np.sum(w[k:] * (y[k:] - m2) ** 2) for k in range(1, len(y))]
    return float(t0[1 + int(np.argmin(cost))])


def _jump_time(result, dataset, t_lo: float, t_hi: float, m1: float, m2: float,
               W: float) -> tuple[float, Optional[float]]:
    """Time of a jump in ``[t_lo, t_hi]`` and the stamp gap it left (or None).

    In order: after the largest stamp gap there if it is far beyond the spacing's jitter (a
    forward jump of J leaves a gap of J); else where the NIS excess starts, when that excess stands
    out against the rest of the log; else where finer windows of tau reach the later level.
    """
    u = dataset.uwb if len(dataset.uwb) else getattr(dataset, "tdoa", None)
    t_all = np.unique(u["t"].to_numpy(float)) if u is not None else np.zeros(0)
    d_all = np.diff(t_all)
    typical = float(np.median(d_all[d_all > 0])) if np.any(d_all > 0) else 0.0
    tt = t_all[(t_all >= t_lo) & (t_all <= t_hi)]
    if len(tt) > 2 and typical > 0:
        gaps = np.diff(tt)
        i = int(np.argmax(gaps))
        # a gap far beyond the spread of the spacing (robust z above 10) is no jitter
        spread = 1.4826 * float(np.median(np.abs(d_all - typical))) + 1e-9
        if gaps[i] - typical > max(10 * spread, 4 * typical):
            return float(tt[i + 1]), float(gaps[i] - typical)
    T = _nis_onset(result, t_lo, t_hi)
    if T is None:
        T = _window_onset(result, t_lo, t_hi, m1, m2, W)
    return (T if T is not None else 0.5 * (t_lo + t_hi)), None


def apply_clock_corrections(dataset, jumps: list[dict[str, Any]], slope: float = 0.0, t0: float = 0.0):
    """A copy of ``dataset`` with UWB stamps (ranges, TDoA) corrected.

    ``t' = t + slope (t - t0)``, then ``t' += size`` for each jump with ``t >= jump["t"]``
    (``t`` the input stamps throughout).
    """
    ds = copy.copy(dataset)
    for name in ("uwb", "tdoa"):
        df = getattr(dataset, name, None)
        if df is None or len(df) == 0:
            continue
        t = df["t"].to_numpy(float)
        tn = t + slope * (t - t0)
        for ev in jumps:
            tn = tn + np.where(t >= ev["t"], ev["size"], 0.0)
        out = df.copy()
        out["t"] = tn
        setattr(ds, name, out.sort_values("t", kind="stable").reset_index(drop=True))
    return ds


def correct_clock_jumps(dataset, events: list[dict[str, Any]]):
    """A copy of ``dataset`` whose UWB stamps after each ``clock_jump`` event are shifted by its size."""
    return apply_clock_corrections(dataset, [e for e in events if e.get("kind") == "clock_jump"])


def range_long_run_variance(result) -> dict[str, Any]:
    """Long-run variance of the run's normalised UWB innovations (rule 3 of
    :mod:`uwbimu.estimation.noise_from_data`: batch means per channel, pooled).

    Taken from ``result.extra["residual_variance_factor"]`` when the estimator computed it (on its
    accepted records), else computed by
    :func:`~uwbimu.estimation.noise_from_data.residual_variance_factor` on the residual table's
    accepted rows (channel: the ``anchor`` column).  Returns that function's record.
    """
    vf = (getattr(result, "extra", None) or {}).get("residual_variance_factor")
    if isinstance(vf, dict) and np.isfinite(vf.get("long_run_variance", np.nan)):
        return vf
    r = _range_rows(result)
    if r is None or len(r) == 0 or "innovation" not in r.columns:
        return {"long_run_variance": float("nan"), "n": 0}
    if "accepted" in r.columns:
        r = r[r["accepted"].to_numpy(bool)]
    nis, inn = r["nis"].to_numpy(float), r["innovation"].to_numpy(float)
    with np.errstate(divide="ignore", invalid="ignore"):
        S = inn ** 2 / nis
    ch = (r["anchor"].astype("category").cat.codes.to_numpy() if "anchor" in r.columns
          else np.zeros(len(r), int))
    return residual_variance_factor(inn, S, ch)


def _candidates(result, dataset, alpha: float) -> list[dict[str, Any]]:
    """Every significant hypothesis (jump, drift), the verdict's first."""
    win = windowed_time_offsets(result)
    t_ref = float(result.t[0])
    c = consistency_tests(win, t_ref, alpha)
    if "scale" not in c:
        return []
    W = float(np.median(win["t1"] - win["t0"]))
    common = {"alpha": alpha, "dispersion": c["scale"], "windows": c["n"], "window_s": W}
    out = []
    if c["z_jump"] > c["crit_jump"]:
        lo = float(win["t0"][max(0, c["k"] - LAG_WINDOWS)])
        hi = float(win["t1"][c["k"]])
        T, gap = (_jump_time(result, dataset, lo, hi, c["m1"], c["m2"], W) if dataset is not None
                  else (c["t_split"], None))
        out.append({"kind": "clock_jump", "t": T, "size": float(c["m2"] - c["m1"]), "sigma": c["step_sd"],
                    "z": c["z_jump"], "crit": c["crit_jump"], "region": [lo, hi], "stamp_gap": gap, **common})
    if c["z_drift"] > c["crit_drift"]:
        s = c["slope"]
        out.append({"kind": "clock_drift", "t": t_ref, "t0": t_ref, "t1": float(result.t[-1]), "t_d_slope": s,
                    "rate": -s / (1 + s), "sigma": c["slope_sd"], "z": c["z_drift"], "crit": c["crit_drift"],
                    **common})
    out.sort(key=lambda e: e["kind"] != {"jump": "clock_jump", "drift": "clock_drift"}.get(c["verdict"]))
    return out


def detect_clock_faults(result, dataset=None, alpha: float = ALPHA) -> list[dict[str, Any]]:
    """Clock jumps and drift of the UWB clock relative to the IMU, from one filter run (no re-run).

    Parameters
    ----------
    result : ESKF :class:`~uwbimu.estimation.EstimationResult` (t_d estimated, covariances kept).
    dataset : the dataset it ran on (for the jump time: stamp gaps); optional.
    alpha : false-alarm probability of each test.

    Returns
    -------
    list with at most one event, the tests' verdict (``clock_jump`` with ``t``, ``size`` as first
    measured, or ``clock_drift`` with ``rate``), with its test statistic ``z``, critical value
    ``crit``, ``alpha`` and the scale ``dispersion`` applied to the window sds; empty when the
    effective time offset is constant within the noise (or cannot be tested: t_d held or fixed).
    """
    return _candidates(result, dataset, alpha)[:1]


def _residual_step(result, T: float, alpha: float) -> Optional[tuple[float, float]]:
    """Step of tau at ``T`` (split fixed) on a run: ``(size, scaled sd)``, None when not measurable."""
    win = windowed_time_offsets(result)
    c = consistency_tests(win, float(result.t[0]), alpha)
    if "scale" not in c:
        return None
    # the jump's own window and the next carry the filter's transient: leave them out
    k = int(np.searchsorted(win["t0"], T))
    keep = np.ones(len(win["t"]), bool)
    keep[max(0, k - 1):k + 1] = False
    y, w = win["tau"][keep], 1.0 / win["sd"][keep] ** 2
    kk = int(np.sum(win["t"][keep] < T))
    if kk < 2 or kk > len(y) - 2:
        return None
    m1, m2, sd, _ = fit_step(y, w, kk)
    return m2 - m1, sd * c["scale"]


def _residual_slope(result, alpha: float) -> Optional[tuple[float, float]]:
    """Trend of tau on a run: ``(slope, scaled sd)``."""
    c = consistency_tests(windowed_time_offsets(result), float(result.t[0]), alpha)
    return (c["slope"], c["slope_sd"]) if "slope" in c else None


def _nis_cost(result) -> float:
    """Mean NIS of the ranges, each clipped at the gate (a robust fit measure across re-runs)."""
    r = _range_rows(result)
    if r is None or len(r) == 0:
        return np.inf
    nis = r["nis"].to_numpy(float)
    nis = nis[np.isfinite(nis)]
    gate = float((result.config.get("resolved") or {}).get("gate_nis") or 10.8)
    return float(np.mean(np.minimum(nis, gate))) if len(nis) else np.inf


def log_likelihood(result) -> tuple[float, int]:
    """Gaussian innovation log-likelihood of a run's UWB rows and their number.

    Per row ``-0.5 (min(NIS, gate) + ln(2 pi S))`` with ``S = innovation^2 / NIS`` (the residual
    table's own variance); the NIS is clipped at the gate so that a few outliers (NLOS) do not
    decide between two runs.  Rows without a finite positive NIS (not processed) are left out.
    """
    r = _range_rows(result)
    if r is None or len(r) == 0 or "innovation" not in r.columns:
        return -np.inf, 0
    nis = r["nis"].to_numpy(float)
    inn = r["innovation"].to_numpy(float)
    ok = np.isfinite(nis) & np.isfinite(inn) & (nis > 0) & (inn != 0)
    if not ok.any():
        return -np.inf, 0
    gate = float((result.config.get("resolved") or {}).get("gate_nis") or 10.8)
    S = inn[ok] ** 2 / nis[ok]
    return float(-0.5 * np.sum(np.minimum(nis[ok], gate) + np.log(2 * np.pi * S))), int(ok.sum())


def likelihood_gain(before, after) -> float:
    """``2 (l_after - l_before)`` per row times the rows both runs processed (the stamp correction
    can move a few rows in or out of the processed span)."""
    (l0, n0), (l1, n1) = log_likelihood(before), log_likelihood(after)
    if n0 == 0 or n1 == 0:
        return -np.inf
    return float(2 * min(n0, n1) * (l1 / n1 - l0 / n0))


#: Parameters a correction adds: a jump's time and size, a drift's slope.
ADDED_PARAMETERS = {"clock_jump": 2, "clock_drift": 1}


class _Fault:
    """One corrected quantity (a jump's size or the drift's slope) and its correction rounds.

    Each round measures the residual ``r`` (what the corrected run still shows) for the applied
    value ``a``.  The filter absorbs part of a fault, so ``r = g (true - a)`` with a gain
    ``g <= 1``; the secant of the last two rounds estimates ``g`` and the next value is
    ``a + r / g`` (first round: ``g = 1``).  A forward jump's stamp gap measures its size
    directly: that value is kept unless the corrected run still shows a significant step.
    """

    def __init__(self, event: dict[str, Any], first: float, trusted: bool = False):
        self.event = event
        self.applied = [0.0]
        self.residual = [float(event["size"] if event["kind"] == "clock_jump" else event["t_d_slope"])]
        self.sd = [float(event["sigma"])]
        self.next_value = first
        self.trusted = trusted

    def gain(self) -> float:
        if len(self.applied) < 2 or self.applied[-1] == self.applied[-2]:
            return 1.0
        g = (self.residual[-2] - self.residual[-1]) / (self.applied[-1] - self.applied[-2])
        return float(np.clip(g, 0.2, 1.0))

    def update(self, measured: Optional[tuple[float, float]]) -> bool:
        """Record the residual of the run with ``next_value`` applied; True when another round is due."""
        self.applied.append(self.next_value)
        if measured is None or not (np.isfinite(measured[0]) and np.isfinite(measured[1]) and measured[1] > 0):
            # the corrected run could not be measured: the last measured sd stands (never NaN)
            self.residual.append(0.0)
            self.sd.append(self.sd[-1])
            return False
        self.residual.append(float(measured[0]))
        self.sd.append(float(measured[1]))
        if self.trusted and abs(measured[0]) <= self.event["crit"] * measured[1]:
            self.residual[-1] = 0.0  # the gap's value stands: the corrected run shows no step
            return False
        self.trusted = False
        self.next_value = self.value()
        return abs(measured[0]) > REFINE_SD * measured[1]

    def value(self) -> float:
        return self.applied[-1] + self.residual[-1] / self.gain()

    def value_sd(self) -> float:
        return self.sd[-1] / self.gain()


def _correct(result, dataset, ev: dict[str, Any], rerun: Callable, alpha: float, max_rounds: int):
    """Correction rounds for one hypothesis; returns ``(fault, run, dataset, t0, leftover events)``."""
    u = dataset.uwb if len(dataset.uwb) else dataset.tdoa
    t0 = float(u["t"].min())
    if ev["kind"] == "clock_jump":
        gap = ev.get("stamp_gap")
        trusted = bool(gap) and ev["size"] < 0
        fault = _Fault({**ev, "t_detected": ev["t"]}, -gap if trusted else ev["size"], trusted)
    else:
        fault = _Fault(ev, ev["t_d_slope"])
    current, cur_ds = result, dataset
    for _ in range(max_rounds):
        if fault.event["kind"] == "clock_jump":
            cur_ds = apply_clock_corrections(dataset, [{"t": ev["t"], "size": fault.next_value}])
        else:
            cur_ds = apply_clock_corrections(dataset, [], fault.next_value, t0)
        current = rerun(cur_ds)
        if fault.event["kind"] == "clock_jump":
            split = ev["t"] + max(fault.next_value, 0.0)  # first corrected post-jump stamp
            again = fault.update(_residual_step(current, split, alpha))
        else:
            again = fault.update(_residual_slope(current, alpha))
        if not again:
            break
    return fault, current, cur_ds, t0, detect_clock_faults(current, cur_ds, alpha)


def handle_clock_faults(result, dataset, rerun: Callable, console=None, alpha: float = ALPHA,
                        max_rounds: int = MAX_ROUNDS):
    """Detect clock faults in ``result``; correct the stamps and re-run (``rerun(dataset)``) until the
    residual jump / trend is below its sd.

    When both a jump and a drift are significant (a jump the filter absorbs slowly looks like a
    ramp; a drift is also fitted by a step), both corrections are made and the one whose corrected
    log has the higher innovation likelihood is kept; it is applied only when
    :func:`confirm_fault` confirms it (the residuals' long-run variance counted).  One fault per
    log is corrected; one still significant afterwards is reported as a warning.

    Returns ``(result, dataset)``: the final run (its ``events`` and ``warnings`` name the fault
    found, its time, size or rate with sd, and how it was handled; its ``calibration`` t_d sd
    includes the uncertainty of the correction) and the dataset it ran on.  A clean log returns
    ``result`` unchanged without any re-run.
    """
    from uwbimu.estimation.timeoffset import is_single_clock

    if is_single_clock(dataset):
        result.events.append({"kind": "check_skipped", "check": "clock_faults", "reason": "single_clock",
                              "detail": "every stream was stamped by one clock (dataset.yaml single_clock: true): "
                                        "no UWB-IMU clock to jump or drift; nothing tested, nothing corrected"})
        return result, dataset
    found = _candidates(result, dataset, alpha)
    if not found:
        if not len(windowed_time_offsets(result)["t"]):
            result.warnings.append("clock-fault check not made: no window estimates of the time offset (t_d held or fixed, or the log too short)")
        elif any(e.get("kind") == "reinitialised" for e in result.events):
            result.warnings.append("clock-fault check: no clock fault found between the re-initialisations; a UWB "
                                   "clock jump or drift larger than the filter can follow also ends in divergence")
        return result, dataset
    tried = [_correct(result, dataset, ev, rerun, alpha, max_rounds) for ev in found]
    gains = [likelihood_gain(result, t[1]) for t in tried]
    best = int(np.argmax(gains))
    fault, current, cur_ds, t0, leftover = tried[best]
    ev = _final_event(fault, current, t0, alpha)
    ev.update({"nis_cost": _nis_cost(current), "alternatives": [
        {"kind": t[0].event["kind"], "likelihood_gain": g} for i, (t, g) in enumerate(zip(tried, gains)) if i != best]})
    ev.update(confirm_fault(ev, current, gains[best], alpha))
    ev["corrected"] = ev["confirmed"]
    if not ev["corrected"]:
        # not confirmed at the stated level once the residuals' long-run variance is counted: revert
        ev["handled"] = (f"not corrected: with the residuals' long-run variance L = {ev['long_run_variance']:.2f} "
                         f"counted, z/sqrt(L) = {ev['z_calibrated']:.1f} (needs > {ev['crit']:.1f}) and "
                         f"2 dl / L = {ev['likelihood_gain_calibrated']:.1f} (needs > {ev['likelihood_threshold']:.1f})")
        current, cur_ds = result, dataset
    else:
        cal = current.calibration
        cal["time_offset_filter"], cal["time_offset_sd_filter"] = cal.get("time_offset"), cal.get("time_offset_sd")
        cal["time_offset"], cal["time_offset_sd"] = ev["t_d"], ev["t_d_sd"]
    current.events.append(ev)
    if ev["corrected"]:
        current.warnings.append(_message(ev))
    else:
        current.warnings.append(f"clock-fault check: a possible {ev['kind'].replace('_', ' ')} (window test "
                                f"z={ev['z']:.1f} > {ev['crit']:.1f} on the filter's sds) was not confirmed; "
                                f"{ev['handled']}")
    if leftover and ev["corrected"]:
        current.warnings.append(f"clock-fault check: after the correction the log still shows a {leftover[0]['kind']} "
                                f"(z={leftover[0]['z']:.1f}); not corrected")
    if console is not None:
        for w in current.warnings[-2:]:
            if "clock" in w:
                console.print(f"[yellow]clock fault:[/yellow] {w}", soft_wrap=True)
    return current, cur_ds


def confirm_fault(ev: dict[str, Any], corrected_run, gain: float, alpha: float = ALPHA) -> dict[str, Any]:
    """The second stage of the check: is the fault found by the window tests real at level ``alpha``?

    The window tests (:func:`detect_clock_faults`) take the filter's window sds, scaled by their
    robust dispersion ``c``: they hold ``alpha`` when the range errors are white.  Coloured
    (vibration, multipath) and heavy-tailed (NLOS) range errors carry less information about a
    slow parameter than the filter credits, by the long-run variance ``L`` of the normalised
    innovations (batch means over ``sqrt(n)``-sample blocks per channel,
    :func:`range_long_run_variance`, rule 3 of :mod:`uwbimu.estimation.noise_from_data`).  ``L``
    is measured on the *corrected* run, i.e. on the residuals under the alternative: a real
    fault leaves white residuals once corrected (``L`` near 1, no power lost), whereas the
    innovations of an uncorrected fault are themselves coloured by the filter's lag, which would
    hide the fault (measured: ``L`` 5 to 10 after a 0.3 s jump).  The fault is confirmed when

    * ``z c / max(c, sqrt(L)) > crit`` (the window statistic with the sds scaled by the larger of
      the windows' dispersion and ``sqrt(L)``: what ``consistency_tests`` gives on sds times
      ``sqrt(L)``), and
    * ``2 (l_corrected - l_input) / L > chi2_{1 - alpha}(k)`` (``k`` parameters the correction
      adds: 2 for a jump, 1 for a drift; the Gaussian likelihood-ratio statistic of correlated
      residuals is ``L`` times too large),

    with ``L`` floored at 1 (the filter's own sds are never shrunk).

    Returns ``{confirmed, long_run_variance, z_calibrated, likelihood_gain, likelihood_gain_calibrated,
    likelihood_threshold}``.
    """
    lrv = float(range_long_run_variance(corrected_run).get("long_run_variance", np.nan))
    L = max(1.0, lrv) if np.isfinite(lrv) else 1.0
    c = float(ev.get("dispersion", 1.0))
    z = float(ev["z"]) * c / max(c, np.sqrt(L))
    from scipy.special import chdtri

    threshold = float(chdtri(ADDED_PARAMETERS[ev["kind"]], alpha))
    g = float(gain) / L
    return {"confirmed": bool(z > float(ev["crit"]) and g > threshold), "long_run_variance": L,
            "long_run_variance_measured": lrv, "z_calibrated": z, "likelihood_gain": float(gain),
            "likelihood_gain_calibrated": g, "likelihood_threshold": threshold}


def _final_event(f: _Fault, result, t0: float, alpha: float) -> dict[str, Any]:
    """The event of a handled fault: applied correction plus the last residual, with its sd.

    The run's t_d inherits the correction's uncertainty: for a jump, the share of the t_d
    information after it times the size sd; for a drift, the lever from t0 to the information
    centre times the slope sd.
    """
    ev = f.event
    win = windowed_time_offsets(result)
    w = 1.0 / win["sd"] ** 2
    td, td_sd = float(result.calibration.get("time_offset", np.nan)), float(result.calibration.get("time_offset_sd", np.nan))
    common = {"z": ev["z"], "crit": ev["crit"], "alpha": alpha, "dispersion": ev["dispersion"],
              "rounds": len(f.applied) - 1, "absorption_gain": f.gain()}
    if ev["kind"] == "clock_jump":
        size, sd = f.value(), f.value_sd()
        share = float(np.sum(w[win["t"] > ev["t"]]) / np.sum(w)) if len(w) else 0.5
        return {"kind": "clock_jump", "t": float(ev["t"]), "size": size, "sigma": sd,
                "size_first": float(ev["size"]), "stamp_gap": ev.get("stamp_gap"), "region": ev["region"], **common,
                "t_d": td, "t_d_sd": float(np.hypot(td_sd, share * sd)),
                "handled": "UWB stamps after the jump shifted by its size; estimator re-run"}
    s, sd = f.value(), f.value_sd()
    # The run's t_d is the (re-stamped) offset near the information-weighted centre of the log; what is
    # left of the slope moves the offset at t0 by the residual slope times that lever.
    t_c = float(np.sum(w * win["t"]) / np.sum(w)) if len(w) else float(t0)
    td0 = td - (s - f.applied[-1]) * (t_c - t0)
    return {"kind": "clock_drift", "t": float(t0), "t0": float(t0), "t1": ev["t1"], "t_d_slope": s,
            "rate": -s / (1 + s), "sigma": sd / (1 + s) ** 2, "rate_ppm": -1e6 * s / (1 + s),
            "sigma_ppm": 1e6 * sd / (1 + s) ** 2, "t_d0": float(td0), "t_d0_sd": float(np.hypot(td_sd, sd * (t_c - t0))),
            "t_centre": t_c, **common, "t_d": float(td0), "t_d_sd": float(np.hypot(td_sd, sd * (t_c - t0))),
            "handled": "time offset modelled as t_d(t) = t_d0 + t_d_slope (t - t0): UWB stamps re-stamped as "
                       "t + t_d_slope (t - t0); estimator re-run"}


def _message(ev: dict[str, Any]) -> str:
    if ev["kind"] == "clock_jump":
        return (f"UWB clock jump at t={ev['t']:.3f} s: the time offset changes by {1000 * ev['size']:+.1f} "
                f"± {1000 * ev['sigma']:.1f} ms (test z={ev['z']:.1f} > {ev['crit']:.1f}, false-alarm "
                f"probability {ev['alpha']:g}); {ev['handled']}")
    return (f"UWB clock drift of {ev['rate_ppm']:+.0f} ± {ev['sigma_ppm']:.0f} ppm relative to the IMU between "
            f"t={ev['t0']:.1f} and {ev['t1']:.1f} s, t_d(t0) = {1000 * ev['t_d0']:.1f} ± {1000 * ev['t_d0_sd']:.1f} ms (test z={ev['z']:.1f} > {ev['crit']:.1f}, false-alarm "
            f"probability {ev['alpha']:g}); {ev['handled']}")
