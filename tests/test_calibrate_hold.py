"""The batch holds a block at its prior by the ESKF's rule (issue 27 item 6): none of its elements is identified
(information gain below ``HOLD_GAIN`` = the verdicts' 99) and the residuals refute the noise model.

Unit tests of :func:`uwbimu.calibration.identifiability.hold_rule` on constructed calibration dicts, and of the
held re-solve on a simulated log with the rule forced (the lever arm then sits at its prior with its prior's sd
and is called not identified).
"""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.calibration import CalibrationOptions
from uwbimu.calibration.identifiability import HOLD_GAIN, REFUTED_RATIO, hold_rule, identifiability


def _cal(lever_sd, bias_sd, model_ratio=1.0):
    return {"lever_arm_sd": list(lever_sd), "lever_arm_sd_model": [s / model_ratio for s in lever_sd],
            "anchor_bias_sd": {str(j): s for j, s in enumerate(bias_sd)}, "anchors": {"bias_held_at_zero": []},
            "time_offset": {"verdict": "flat"}}


def _rule(cal, events=(), o=None):
    o = o or CalibrationOptions()
    section, _ = identifiability(cal, o)
    return hold_rule(cal, section, list(events), o)


SCALED = [{"kind": "imu_noise_scaled", "scale": 2.7, "scale_sd": 0.1}]
#: an sd with information gain g over the 0.5 m lever-arm prior: 0.5 / sqrt(1 + g)
LEVER = lambda g: 0.5 / np.sqrt(1.0 + g)  # noqa: E731
BIAS = lambda g: 0.3 / np.sqrt(1.0 + g)  # noqa: E731


def test_undetermined_blocks_are_held_when_the_residuals_refute_the_model():
    cal = _cal([LEVER(1.1), LEVER(4.1), LEVER(5.7)], [BIAS(2.0), BIAS(4.0)])
    h = _rule(cal, SCALED)
    assert set(h) == {"lever_arm", "anchor_bias", "refuted"}
    assert h["lever_arm"]["x"] == pytest.approx(1.1)
    assert h["refuted"]["imu_noise_scale"] == 2.7


def test_nothing_is_held_when_the_residuals_agree_with_the_model():
    cal = _cal([LEVER(1.1), LEVER(4.1), LEVER(5.7)], [BIAS(2.0), BIAS(4.0)])
    assert _rule(cal, []) == {}
    # an IMU noise scale below 1 does not refute it either
    assert _rule(cal, [{"kind": "imu_noise_scaled", "scale": 0.7, "scale_sd": 0.05}]) == {}


def test_a_sandwich_sigma_above_the_model_refutes_it():
    cal = _cal([LEVER(1.1), LEVER(4.1), LEVER(5.7)], [BIAS(2.0)], model_ratio=REFUTED_RATIO * 1.05)
    assert "lever_arm" in _rule(cal, [])
    cal = _cal([LEVER(1.1), LEVER(4.1), LEVER(5.7)], [BIAS(2.0)], model_ratio=REFUTED_RATIO * 0.95)
    assert _rule(cal, []) == {}


def test_one_identified_element_keeps_the_block():
    # INRoL-like: every element identified (gains 176-383)
    cal = _cal([LEVER(326.0), LEVER(383.0), LEVER(176.0)], [BIAS(782.0), BIAS(176.0)])
    assert _rule(cal, SCALED) == {}
    # one identified lever-arm axis keeps the lever arm; biases all below the threshold are held
    cal = _cal([LEVER(1.0), LEVER(2.0), LEVER(HOLD_GAIN * 1.01)], [BIAS(1.0), BIAS(HOLD_GAIN * 0.99)])
    h = _rule(cal, SCALED)
    assert "lever_arm" not in h and "anchor_bias" in h


def test_weakly_identified_blocks_are_held_like_the_eskfs():
    # ISAS-Walk-like: lever-arm gains 45-74 (weakly identified), biases 8-55: the ESKF's rule holds both
    cal = _cal([LEVER(74.0), LEVER(61.0), LEVER(45.0)], [BIAS(23.0), BIAS(7.9), BIAS(55.0)])
    h = _rule(cal, SCALED)
    assert set(h) == {"lever_arm", "anchor_bias", "refuted"}
    assert HOLD_GAIN == 99.0  # the verdicts' "identified" threshold, not a separate one


def test_biases_not_estimated_are_not_held_again():
    cal = _cal([LEVER(1.0)] * 3, [BIAS(1.0)] * 3)
    h = _rule(cal, SCALED, CalibrationOptions(estimate_anchor_bias=False))
    assert "anchor_bias" not in h and "lever_arm" in h


@pytest.mark.slow
def test_held_resolve_puts_the_lever_arm_at_its_prior(monkeypatch):
    """With the rule forced on a simulated log: the lever arm at the prior, reported with the prior's sd (not
    identified), the first solve's estimate in the event, the anchor biases at 0."""
    from uwbimu.calibration import batch, calibrate
    from uwbimu.sim import builtin_scenario, simulate

    sc = builtin_scenario("calibration-flight")
    ds = simulate(sc.model_copy(update={"duration": 10.0}))
    forced = {"lever_arm": {"x": 0.0, "y": 0.0, "z": 0.0}, "anchor_bias": {}, "refuted": {"imu_noise_scale": 2.0,
                                                                                        "sd_ratio": 1.0}}
    monkeypatch.setattr(batch, "hold_rule", lambda *a, **k: dict(forced))
    o = CalibrationOptions.model_validate({"td_profile": {"enabled": False}})
    r = calibrate(ds, o)
    c = r.calibration
    assert c["lever_arm"] == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)
    assert c["lever_arm_sd"] == [o.lever_arm_prior_sd] * 3 and c["lever_arm_held"] is True
    assert {v["verdict"] for v in c["identifiability"]["lever_arm"].values()} == {"not identified"}
    assert max(abs(v) for v in c["anchor_bias"].values()) < 1e-5  # at 0 under a 1e-6 m prior
    ev = [e for e in r.events if e["kind"] == "calibration_held"]
    assert len(ev) == 1 and ev[0]["blocks"] == ["anchor_bias", "lever_arm"]
    first = np.asarray(ev[0]["first_pass"]["lever_arm"])
    assert np.linalg.norm(first - np.asarray(ds.meta.truth.lever_arm)) < 0.1  # the free solve found the truth
    assert c["held_at_prior"]["blocks"] == ev[0]["blocks"]
