"""Clock-fault check without false alarms (issue 27, item 5).

Single-clock logs are never corrected; coloured (AR(1)) range noise gives no clock event; a
correction that does not raise the innovation likelihood by the chi-square margin is reverted;
no event carries a NaN sigma.  Assertions on structured events.
"""

from __future__ import annotations

import copy
import sys
from pathlib import Path

import numpy as np
import pytest

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.eval.clock_faults import confirm_fault, handle_clock_faults, likelihood_gain
from uwbimu.eval.clock_windows import ALPHA, consistency_tests, windowed_time_offsets
from uwbimu.sim import builtin_scenario, simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from check_clock_false_alarms import ar1_ranges, null_log  # noqa: E402  (the benchmark's coloured-noise model, one copy)


def _flight(seed: int):
    return simulate(builtin_scenario("calibration-flight").updated(duration=60.0, seeds={"noise": seed}))


def _rerun(d):
    return run_eskf(d, EskfOptions())


def _clock_events(res):
    return [e for e in res.events if str(e.get("kind", "")).startswith("clock_")]


def test_single_clock_log_is_never_corrected():
    ds = copy.copy(_flight(1))
    u = ds.uwb.copy()
    u.loc[u["t"] >= 30.0, "t"] += 0.3  # a jump the check would otherwise find
    ds.uwb = u
    ds.meta = ds.meta.model_copy(update={"single_clock": True})
    res = run_eskf(ds, EskfOptions())
    calls = []
    out, same = handle_clock_faults(res, ds, lambda d: calls.append(d) or _rerun(d))
    assert same is ds and out is res and calls == []
    assert _clock_events(out) == []
    skipped = [e for e in out.events if e.get("kind") == "check_skipped"]
    assert len(skipped) == 1 and skipped[0]["check"] == "clock_faults" and skipped[0]["reason"] == "single_clock"


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_coloured_range_noise_gives_no_clock_event(seed):
    ds = ar1_ranges(_flight(seed), sigma=0.10, tau=3.0, seed=100 + seed)
    res = run_eskf(ds, EskfOptions())
    c = consistency_tests(windowed_time_offsets(res), float(res.t[0]))
    assert c["verdict"] is None
    assert np.isfinite(c["step_sd"]) and np.isfinite(c["slope_sd"]) and 0 <= c["phi"] < 1
    out, same = handle_clock_faults(copy.deepcopy(res), ds, _rerun)
    assert _clock_events(out) == [] and same is ds


def test_correction_reverted_when_likelihood_does_not_improve(monkeypatch):
    """A candidate forced on a clean log: its 'correction' does not make the ranges more likely,
    so the input run is kept and the event says not corrected."""
    import uwbimu.eval.clock_faults as cf

    ds = _flight(2)
    res = run_eskf(ds, EskfOptions())
    ev = {"kind": "clock_jump", "t": 30.0, "size": -0.05, "sigma": 0.01, "z": 9.0, "crit": 6.0, "region": [25, 35],
          "stamp_gap": None, "alpha": ALPHA, "dispersion": 1.0, "windows": 20, "window_s": 2.5}
    monkeypatch.setattr(cf, "_candidates", lambda *a, **k: [dict(ev)])
    out, used = cf.handle_clock_faults(res, ds, _rerun, max_rounds=1)
    assert out is res and used is ds
    (clock,) = _clock_events(out)
    assert clock["corrected"] is False and clock["handled"].startswith("not corrected")
    assert clock["confirmed"] is False
    assert (clock["likelihood_gain_calibrated"] <= clock["likelihood_threshold"]
            or clock["z_calibrated"] <= clock["crit"])
    assert np.isfinite(clock["sigma"])


def test_likelihood_gain_is_zero_for_the_same_run():
    res = run_eskf(_flight(3), EskfOptions())
    assert likelihood_gain(res, res) == pytest.approx(0.0)


def test_no_nan_sigma_when_the_corrected_run_cannot_be_measured(monkeypatch):
    import uwbimu.eval.clock_faults as cf

    ds = _flight(0)
    u = ds.uwb.copy()
    u = u[~((u["t"] >= 30.0) & (u["t"] < 30.2))].copy()  # a backward jump of 0.2 s, stamps monotonic
    u.loc[u["t"] >= 30.0, "t"] -= 0.2
    ds = copy.copy(ds)
    ds.uwb = u
    res = run_eskf(ds, EskfOptions())
    monkeypatch.setattr(cf, "_residual_step", lambda *a, **k: None)
    monkeypatch.setattr(cf, "_residual_slope", lambda *a, **k: None)
    out, _ = cf.handle_clock_faults(res, ds, _rerun)
    assert _clock_events(out)  # the fault is found (and reported even when not corrected)
    for e in _clock_events(out):
        assert np.isfinite(e["sigma"]) and e["sigma"] > 0


class _Run:
    """Stand-in for a corrected run: only the long-run variance record the confirmation reads."""

    def __init__(self, lrv: float):
        self.extra = {"residual_variance_factor": {"long_run_variance": lrv}}


@pytest.mark.parametrize("kind", ["clock_jump", "clock_drift"])
def test_confirmation_counts_the_long_run_variance(kind):
    """The same window statistic and likelihood gain: confirmed with white residuals (L = 1, and L
    below 1 is not credited), rejected when the residuals' long-run variance is 9."""
    from scipy.stats import chi2

    thr = chi2.isf(ALPHA, 2 if kind == "clock_jump" else 1)
    ev = {"kind": kind, "z": 1.5 * 5.0, "crit": 5.0, "dispersion": 1.2}
    white = confirm_fault(ev, _Run(1.0), 2.0 * thr)
    assert white["confirmed"] and white["z_calibrated"] == pytest.approx(ev["z"])
    assert confirm_fault(ev, _Run(0.5), 2.0 * thr)["long_run_variance"] == 1.0
    col = confirm_fault(ev, _Run(9.0), 2.0 * thr)
    assert not col["confirmed"]
    assert col["z_calibrated"] == pytest.approx(ev["z"] * 1.2 / 3.0)
    assert col["likelihood_gain_calibrated"] == pytest.approx(2.0 * thr / 9.0)
    # a dispersion already above sqrt(L) is not scaled twice
    assert confirm_fault(dict(ev, dispersion=4.0), _Run(9.0), 20 * thr)["z_calibrated"] == pytest.approx(ev["z"])


def test_forced_candidate_on_coloured_noise_is_not_confirmed(monkeypatch):
    """A jump candidate (the window tests' best split) on a clock-fault-free log with AR(1) range
    errors: the 'corrected' run keeps coloured residuals, so the fault is not confirmed and the
    input run is returned."""
    import uwbimu.eval.clock_faults as cf

    ds = null_log("ar1 3 s 10 cm", 8)
    res = run_eskf(ds, EskfOptions())
    win = windowed_time_offsets(res)
    c = consistency_tests(win, float(res.t[0]))
    ev = {"kind": "clock_jump", "t": c["t_split"], "size": c["m2"] - c["m1"], "sigma": c["step_sd"],
          "z": 1.2 * c["crit_jump"], "crit": c["crit_jump"], "region": [float(win["t0"][0]), float(win["t1"][-1])],
          "stamp_gap": None, "alpha": ALPHA, "dispersion": c["scale"], "windows": c["n"], "window_s": 1.5}
    monkeypatch.setattr(cf, "_candidates", lambda *a, **k: [dict(ev)])
    out, used = cf.handle_clock_faults(res, ds, _rerun, max_rounds=2)
    assert out is res and used is ds
    (clock,) = _clock_events(out)
    assert clock["corrected"] is False and clock["long_run_variance"] > 2.0
