"""The streaming filter (:class:`uwbimu.estimation.Eskf`) against the batch :func:`run_eskf`.

Tolerance: none.  The streaming filter runs the same kernels in the same order on the same numbers
(a measurement is processed once the IMU reaches it, the mid-interval inputs and the nominal IMU
period are computed causally by the batch too), so sample-by-sample, chunked and one-batch runs give
bit-identical trajectories; any difference is a bug in the bookkeeping, which a tolerance would hide.
"""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.estimation import Eskf, EskfOptions, run_eskf
from uwbimu.estimation.eskf import build_problem
from uwbimu.estimation.presets import load_preset
from uwbimu.io.loader import load_dataset
from uwbimu.sim import builtin_scenario, simulate

from pathlib import Path

EXCERPT = Path(__file__).parent / "data" / "inrol_excerpt"


def _sim(name: str, duration: float, **update):
    return simulate(builtin_scenario(name).model_copy(update={"duration": duration, **update}))


@pytest.fixture(scope="module")
def flight():
    return _sim("calibration-flight", 40.0)


@pytest.fixture(scope="module")
def inrol(tmp_path_factory):
    dst = tmp_path_factory.mktemp("inrol") / "ds"
    res = CliRunner().invoke(app, ["import", "inrol", str(EXCERPT), str(dst)])
    assert res.exit_code == 0, res.output
    return load_dataset(dst)


def _arrival_order(prob, td: float, latency: float = 0.01):
    """Items ``(kind, index)`` in the order a robot would receive them: IMU sample at its stamp, a
    measurement stamped ``t`` (UWB clock) at IMU time ``t + td + latency``."""
    t = np.concatenate([prob.imu_t, prob.uwb_t + td + latency])
    kind = np.concatenate([np.zeros(len(prob.imu_t), int), np.ones(len(prob.uwb_t), int)])
    idx = np.concatenate([np.arange(len(prob.imu_t)), np.arange(len(prob.uwb_t))])
    order = np.lexsort((idx, kind, t))
    return kind[order], idx[order]


def _feed(f: Eskf, prob, kinds, idx, chunk_sizes):
    ub = prob.uwb_b if prob.uwb_b is not None else np.full(len(prob.uwb_t), -1)
    i = 0
    it = iter(chunk_sizes)
    while i < len(kinds):
        n = next(it)
        k = kinds[i]
        j = i
        while j < len(kinds) and j - i < n and kinds[j] == k:
            j += 1
        sel = idx[i:j]
        if k == 0:
            f.feed(prob.imu_t[sel], prob.imu_u[sel], np.zeros(0), np.zeros(0, int), np.zeros(0, int), np.zeros(0))
        else:
            f.feed(np.zeros(0), np.zeros((0, 6)), prob.uwb_t[sel], prob.uwb_a[sel], ub[sel], prob.uwb_r[sel])
        i = j
    f.finish()


def _trajectory(f: Eskf):
    ps = f.passes()
    return np.concatenate([p.t_imu for p in ps]), np.concatenate([p.states for p in ps])[:, :20]


def _same_as_batch(ds, opts, td, chunks):
    # the streaming filter runs on the given noise; the batch's noise-from-data passes are not streamed
    opts = opts.model_copy(update={"noise": "preset", "hold_unidentified": False})
    batch = run_eskf(ds, opts)
    prob, info = build_problem(ds, opts)
    kinds, idx = _arrival_order(prob, td)
    f = Eskf.from_problem(prob, info["priors"], opts, record=True)
    _feed(f, prob, kinds, idx, chunks)
    t, X = _trajectory(f)
    assert X.shape == batch.states.shape
    np.testing.assert_array_equal(t, batch.t_imu)
    np.testing.assert_array_equal(X, batch.states)
    assert f.state().lever_arm.tolist() == batch.calibration["lever_arm"]
    assert f.state().time_offset == batch.calibration["time_offset"]
    return f


def test_sample_by_sample_equals_batch_on_simulated_flight(flight):
    f = _same_as_batch(flight, EskfOptions(), flight.meta.truth.time_offset or 0.0, iter(lambda: 1, None))
    assert [e["kind"] for e in f.events()].count("initialised") == 1


def test_random_chunks_equal_batch_on_simulated_flight(flight):
    rng = np.random.default_rng(7)
    _same_as_batch(flight, EskfOptions(), flight.meta.truth.time_offset or 0.0,
                   iter(lambda: int(rng.integers(1, 400)), None))


def test_sample_by_sample_and_chunks_equal_batch_on_inrol_excerpt(inrol):
    opts = load_preset("real")
    _same_as_batch(inrol, opts, 0.0, iter(lambda: 1, None))
    rng = np.random.default_rng(3)
    _same_as_batch(inrol, opts, 0.0, iter(lambda: int(rng.integers(1, 300)), None))


def test_public_pushes_match_run_eskf_and_trimmed_buffers_stay_bounded():
    ds = _sim("calibration-flight", 90.0)
    opts = EskfOptions(noise="preset", hold_unidentified=False)  # the streaming filter: one pass
    batch = run_eskf(ds, opts)
    f = Eskf.for_dataset(ds)  # record=False: buffers trimmed
    assert f.state() is None
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    uwb = ds.uwb
    ti = 0
    biggest = 0
    td = ds.meta.truth.time_offset or 0.0
    for t, a, r in zip(uwb["t"].to_numpy(float), uwb["anchor"].astype(str), uwb["range"].to_numpy(float)):
        # IMU up to the range's arrival (IMU clock), one sample at a time
        while ti < len(imu) and imu[ti, 0] <= t + td + 0.01:
            f.push_imu(imu[ti, 0], imu[ti, 1:4], imu[ti, 4:7])
            ti += 1
        f.push_range(t, a, r)
        biggest = max(biggest, f.problem().imu_t.shape[0])
    for row in imu[ti:]:
        f.push_imu(row[0], row[1:4], row[4:7])
    f.finish()
    s = f.state()
    assert s.lever_arm.tolist() == batch.calibration["lever_arm"]
    assert s.time_offset == batch.calibration["time_offset"]
    np.testing.assert_array_equal(s.position, batch.states[-1, 0:3]) if batch.t_imu[-1] == s.t_imu else None
    # the IMU buffer holds far less than the log (90 s at the simulator's rate)
    assert biggest < 0.5 * len(imu)
    assert s.time_offset_sd > 0 and np.all(s.lever_arm_sd > 0)
    assert s.covariance.shape == (19, 19)


def test_tdoa_pushes_match_run_eskf():
    ds = _sim("crazyflie-tdoa2", 30.0)
    opts = EskfOptions(noise="preset", hold_unidentified=False)  # the streaming filter: one pass
    batch = run_eskf(ds, opts)
    f = Eskf.for_dataset(ds, opts, record=True)
    imu = ds.imu
    f.push_imu_chunk(imu["t"].to_numpy(float), imu[["ax", "ay", "az"]].to_numpy(float),
                     imu[["wx", "wy", "wz"]].to_numpy(float))
    td = ds.tdoa
    f.push_tdoas(td["t"].to_numpy(float), td["anchor_a"].astype(str), td["anchor_b"].astype(str),
                 td["tdoa"].to_numpy(float))
    f.finish()
    t, X = _trajectory(f)
    np.testing.assert_array_equal(X, batch.states)


def test_late_measurement_is_processed_not_dropped(flight):
    """A range arriving after the IMU has moved on by more than max_latency_s is processed on arrival
    (state integrated back), not lost."""
    opts = EskfOptions()
    prob, info = build_problem(flight, opts)
    f = Eskf.from_problem(prob, info["priors"], opts, record=False)
    n = len(prob.imu_t)
    half = n // 2
    t_half = prob.imu_t[half]
    m_half = int(np.searchsorted(prob.uwb_t, t_half - 0.3))
    ub = np.full(len(prob.uwb_t), -1)
    f.feed(prob.imu_t[:half], prob.imu_u[:half], prob.uwb_t[:m_half], prob.uwb_a[:m_half], ub[:m_half],
           prob.uwb_r[:m_half])
    assert f.initialised
    # one range 0.25 s behind the IMU (beyond the 0.2 s latency, within max_lookback_s = 0.6 s)
    f.feed(np.zeros(0), np.zeros((0, 6)), prob.uwb_t[m_half:m_half + 1], prob.uwb_a[m_half:m_half + 1],
           ub[m_half:m_half + 1], prob.uwb_r[m_half:m_half + 1])
    rec = f.records()
    assert rec[-1, 5] == 0 and rec[-1, 3] == 1.0  # processed (status ok) and accepted


def test_before_initialisation_state_is_none_and_bad_inputs_are_counted(flight):
    f = Eskf.for_dataset(flight)
    f.push_imu(0.0, [0, 0, 9.81], [0, 0, 0])
    f.push_imu(0.0, [0, 0, 9.81], [0, 0, 0])  # repeated stamp
    f.push_range(0.0, "no-such-anchor", 3.0)
    assert f.state() is None
    f.finish()
    ev = {e["reason"]: e for e in f.events() if e["kind"] == "inputs_not_used"}
    assert ev["imu_not_increasing"]["count"] == 1 and ev["unknown_anchor"]["count"] == 1
    assert any(e["kind"] == "not_initialised" for e in f.events())
