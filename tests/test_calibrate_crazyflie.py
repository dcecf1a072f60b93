"""Acceptance of the batch on the two real Crazyflie TDoA logs (issue 27 item 6 / issue 28 item 6), defaults only.

``uwbimu calibrate`` with the default options must give a position RMSE against the logged Vicon pose of at most
0.30 m (TDoA-only multilateration in 0.5 s windows: 0.253 m on traj3, 0.327 m on traj16), a lever arm within 3 sigma
of the UTIL antenna offset on every axis or called not identified, no t_d called identified beyond 0.2 s (IMU and
TDoA share the Crazyflie's clock), no clock event, and a start from the (healthy) ESKF.

Reads ``../shared/datasets/util_0425`` (no licence: never copied into the repository) and skips when it is absent;
about 2 minutes per log (slow).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("gtsam")

UTIL_0425 = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "util_0425"
#: UTIL vehicle-centre-to-tag translation [m] (benchmarks/acceptance_real.py UTIL_TAG_OFFSET)
UTIL_TAG_OFFSET = np.array([-0.01245, 0.00127, 0.0908])


@pytest.mark.slow
@pytest.mark.skipif(not (UTIL_0425 / "raw" / "TDOA2" / "0425-traj3").exists(),
                    reason="UTIL 2021 logs not present (shared data, not in the repo)")
@pytest.mark.parametrize("log", ["TDOA2/0425-traj3", "TDOA3/0425-traj16"])
def test_crazyflie_batch_acceptance(log):
    from uwbimu.calibration import calibrate
    from uwbimu.io.importers.cf_usdlog import convert
    from uwbimu.metrics.filter import truth_at

    ds = convert(UTIL_0425 / "raw" / log, UTIL_0425 / "survey" / "anchors_0425.csv").dataset
    r = calibrate(ds)
    c = r.calibration
    tr = r.trajectory
    ref, _, _, m = truth_at(ds, tr["t"].to_numpy())
    rmse = float(np.sqrt(np.mean(np.sum((tr[["px", "py", "pz"]].to_numpy()[m] - ref[m]) ** 2, axis=1))))
    assert rmse <= 0.30
    verdicts = c["identifiability"]["lever_arm"]
    for i, axis in enumerate("xyz"):
        off = abs(c["lever_arm"][i] - UTIL_TAG_OFFSET[i])
        assert off <= 3.0 * c["lever_arm_sd"][i] or verdicts[axis]["verdict"] == "not identified"
    td = c["time_offset"]
    assert not (td["verdict"] == "identified" and abs(td["value"]) > 0.2)
    assert not [e for e in r.events if str(e.get("kind", "")).startswith("clock")]
    assert c["start"]["source"] == "eskf"
