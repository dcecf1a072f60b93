"""A z-down anchors' frame (anchor_frame_up: -z) and documented range biases (known_anchor_bias) in the batch
calibrator: the same log written that way gives the same calibration, and the outputs come back in its frame."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("gtsam")

from uwbimu.calibration import CalibrationOptions, calibrate  # noqa: E402
from uwbimu.calibration.frames import FLIP, flip_quat  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402


def _z_down_with_known_bias(ds, bias: dict):
    """The same log in the anchors' frame turned 180 deg about x, with documented biases added to the ranges."""
    anchors = ds.anchors.copy()
    anchors[["x", "y", "z"]] = anchors[["x", "y", "z"]].to_numpy(float) * FLIP
    uwb = ds.uwb.copy()
    uwb["range"] = uwb["range"].to_numpy(float) + uwb["anchor"].astype(str).map(bias).fillna(0.0).to_numpy(float)
    meta = ds.meta.model_copy(update={"anchor_frame_up": "-z", "known_anchor_bias": bias})
    return dataclasses.replace(ds, anchors=anchors, uwb=uwb, meta=meta)


def test_z_down_frame_and_known_bias_give_the_same_calibration():
    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 8.0}))
    a0, a1 = (str(a) for a in ds.anchors["anchor"].iloc[:2])
    bias = {a0: 0.12, a1: -0.07}
    opts = CalibrationOptions(td_profile={"enabled": False})
    ref = calibrate(ds, opts)
    alt = calibrate(_z_down_with_known_bias(ds, bias), opts)
    c, r = alt.calibration, ref.calibration
    np.testing.assert_allclose(c["lever_arm"], r["lever_arm"], atol=1e-6)
    np.testing.assert_allclose(c["lever_arm_sd"], r["lever_arm_sd"], rtol=1e-4)
    assert c["time_offset"]["value"] == pytest.approx(r["time_offset"]["value"], abs=1e-6)
    for a in (a0, a1):  # the graph's bias is what remains on top of the documented one
        assert c["anchor_bias"][a] == pytest.approx(r["anchor_bias"][a], abs=1e-6)
    assert c["anchor_frame_up"] == "-z" and c["known_anchor_bias_removed"] == bias
    # trajectory, velocity and attitude back in the z-down frame; sds unchanged
    P, Pr = alt.trajectory[["px", "py", "pz"]].to_numpy(), ref.trajectory[["px", "py", "pz"]].to_numpy()
    np.testing.assert_allclose(P, Pr * FLIP, atol=1e-5)
    np.testing.assert_allclose(alt.trajectory[["vx", "vy", "vz"]].to_numpy(),
                               ref.trajectory[["vx", "vy", "vz"]].to_numpy() * FLIP, atol=1e-5)
    q, qr = alt.trajectory[["qw", "qx", "qy", "qz"]].to_numpy(), flip_quat(ref.trajectory[["qw", "qx", "qy", "qz"]].to_numpy())
    assert np.min(np.abs(np.sum(q * qr, axis=1))) > 1 - 1e-9
    np.testing.assert_allclose(alt.trajectory["sd_pz"], ref.trajectory["sd_pz"], rtol=1e-3)
    np.testing.assert_allclose(alt.anchors[["x", "y", "z"]].to_numpy(), ref.anchors[["x", "y", "z"]].to_numpy() * FLIP)
    # the initialising ESKF is returned in the anchors' frame too
    np.testing.assert_allclose(alt.eskf.states[:, 0:3], ref.eskf.states[:, 0:3] * FLIP, atol=1e-6)
    # residuals: ranges with the documented biases removed
    np.testing.assert_allclose(alt.residuals["range"], ref.residuals["range"], atol=1e-12)
