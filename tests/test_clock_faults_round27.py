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
from uwbimu.eval.clock_faults import handle_clock_faults, likelihood_gain
from uwbimu.eval.clock_windows import ALPHA, consistency_tests, windowed_time_offsets
from uwbimu.sim import builtin_scenario, simulate

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from check_clock_false_alarms import ar1_ranges  # noqa: E402  (the benchmark's coloured-noise model, one copy)


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
    assert clock["likelihood_gain"] <= clock["likelihood_threshold"]
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
