"""Several tags in one filter: one lever arm each (issue 11 item 4)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from uwbimu.estimation import Eskf, EskfOptions, run_eskf, write_outputs
from uwbimu.estimation import kernels as K
from uwbimu.models import reference as ref
from uwbimu.models import state as S
from uwbimu.models.measurements import MeasurementModel, fd_jacobian
from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.models.state import StateLayout
from uwbimu.sim import builtin_scenario, simulate


@pytest.fixture(scope="module")
def two_tag_flight():
    """The excited 90 s flight carrying the two tags of the ``two-tags`` scenario (front, back)."""
    ex = builtin_scenario("excited-90s")
    return simulate(ex.model_copy(update={"tags": builtin_scenario("two-tags").tags}))


@pytest.fixture(scope="module")
def runs(two_tag_flight):
    return run_eskf(two_tag_flight, EskfOptions()), run_eskf(two_tag_flight, EskfOptions(tag="front"))


def test_both_lever_arms_within_1cm_and_3sd(two_tag_flight, runs):
    both, _ = runs
    truth = two_tag_flight.meta.truth.tags
    cal = both.calibration
    assert set(cal["tags"]) == {"front", "back"}
    for name, block in cal["tags"].items():
        err = np.array(block["lever_arm"]) - np.array(truth[name])
        sd = np.array(block["lever_arm_sd"])
        assert np.all(np.abs(err) < 0.01), (name, err)
        assert np.all(np.abs(err) < 3 * sd), (name, err, sd)
    # the top-level keys stay those of the first tag
    assert cal["lever_arm"] == cal["tags"]["front"]["lever_arm"]
    assert set(both.residuals["tag"]) == {"front", "back"}


def _yaw_sd(res) -> np.ndarray:
    """World-yaw sd [rad] over time (the attitude error is a body perturbation: rotate it)."""
    out = np.empty(len(res.t))
    for i, (x, C) in enumerate(zip(res.states, res.covariances)):
        R = quat_to_rotmat(x[S.Q])
        out[i] = np.sqrt((R @ C[S.ETH, S.ETH] @ R.T)[2, 2])
    return out


def test_two_tags_converge_in_yaw_faster_than_one(runs):
    both, one = runs
    y2, y1 = _yaw_sd(both), _yaw_sd(one)
    thr = np.radians(1.0)
    t2 = both.t[np.argmax(y2 < thr)]
    t1 = one.t[np.argmax(y1 < thr)]
    assert np.any(y2 < thr) and np.any(y1 < thr)
    assert t2 < t1
    # and the second tag's ranges are what makes the difference: the final yaw sd is smaller too
    assert y2[-1] < y1[-1]


def test_calibration_yaml_has_a_tags_block(two_tag_flight, runs, tmp_path):
    write_outputs(runs[0], two_tag_flight, tmp_path / "out")
    cal = yaml.safe_load((tmp_path / "out" / "calibration.yaml").read_text())
    text = yaml.safe_dump(cal)
    assert "front" in text and "back" in text


def test_streaming_pushes_with_tag_names_equal_run_eskf(two_tag_flight, runs):
    ds = two_tag_flight
    # one pass on the given noise, as the streaming filter runs
    opts = EskfOptions(noise="preset", hold_unidentified=False)
    batch = run_eskf(ds, opts)
    f = Eskf.for_dataset(ds, opts, record=True)
    imu = ds.imu
    f.push_ranges(ds.uwb["t"].to_numpy(float), ds.uwb["anchor"].astype(str), ds.uwb["range"].to_numpy(float),
                  ds.uwb["tag"].astype(str).tolist())
    f.push_imu_chunk(imu["t"].to_numpy(float), imu[["ax", "ay", "az"]].to_numpy(float),
                     imu[["wx", "wy", "wz"]].to_numpy(float))
    f.finish()
    s = f.state()
    assert s.tags["back"][0].tolist() == batch.calibration["tags"]["back"]["lever_arm"]


class _SecondTagRange(MeasurementModel):
    """Range from the second tag's antenna (lever arm in the extra block) by the reference model."""

    def __init__(self, anchor, layout):
        self.anchor, self.layout = anchor, layout

    def evaluate(self, x, u):
        x2 = x[: S.NOMINAL_DIM].copy()
        x2[S.PIU] = x[self.layout.lever_nom(1)]
        return np.array([ref.range_measurement(x2, self.anchor)])


def test_second_tag_jacobian_matches_finite_differences():
    L = StateLayout(n_anchor_bias=2, n_tags=2)
    rng = np.random.default_rng(8)
    x = np.zeros(L.n_nom)
    x[S.P] = rng.normal(0, 2, 3)
    x[S.V] = rng.normal(0, 1, 3)
    q = rng.normal(size=4)
    x[S.Q] = q / np.linalg.norm(q)
    x[S.BG] = rng.normal(0, 0.02, 3)
    x[S.PIU] = [0.1, -0.05, 0.2]
    x[L.lever_nom(1)] = [-0.2, 0.1, 0.05]
    u = np.concatenate([[0.3, -0.2, 9.9], rng.normal(0, 1, 3)])
    anchor = np.array([4.0, -3.0, 2.0])
    h = np.zeros(L.n_err)
    K.range_jacobian(K._other_tag(x, L.lever_err(1).start), u, anchor, -1, 0.0, h)
    K._move_lever_rows(h, L.lever_err(1).start)
    H_fd = fd_jacobian(_SecondTagRange(anchor, L), x, u, L)
    np.testing.assert_allclose(h, H_fd[0], atol=1e-6)
    assert np.all(h[L.err("lever")] == 0.0)
