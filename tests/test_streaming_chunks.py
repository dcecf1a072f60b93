"""The chunked pushes (``push_imu_chunk``, ``push_ranges``: the fast way to feed the streaming filter from
Python, ``benchmarks/bench_streaming.py``) against one ``push_imu`` / ``push_range`` call per sample.

Tolerance: none.  Both paths run the same kernels on the same numbers in the same order; the input
guards are the same checks, vectorised for a chunk, so the same samples are refused with the same counts.
"""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.estimation import Eskf, EskfOptions
from uwbimu.sim import builtin_scenario, simulate

T_FAULT = 25.0  # [s] faults are injected after the initialisation


@pytest.fixture(scope="module")
def flight_with_faults():
    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 40.0}))
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float, copy=True)
    k = int(np.searchsorted(imu[:, 0], T_FAULT))
    imu[k + 3, 3] = np.nan                 # not finite
    imu[k + 10, 6] = 40.0                  # gyro beyond the plausible rate
    imu[k + 20, 0] = imu[k + 19, 0]        # repeated stamp
    imu[k + 30:k + 33, 1] = np.inf         # a run of three
    t = ds.uwb["t"].to_numpy(float)
    a = ds.uwb["anchor"].astype(str).to_numpy().astype(object)
    r = ds.uwb["range"].to_numpy(float).copy()
    j = int(np.searchsorted(t, T_FAULT))
    r[j + 2] = -1.0                        # not positive
    r[j + 5] = 1e4                         # longer than the room allows
    r[j + 7] = np.nan                      # not finite
    a[j + 9] = "nope"                      # unknown anchor
    td = ds.meta.truth.time_offset or 0.0
    # arrival order: an IMU sample at its stamp, a range 10 ms after its IMU time
    at = np.concatenate([imu[:, 0], t + td + 0.01])
    kind = np.concatenate([np.zeros(len(imu), int), np.ones(len(t), int)])
    idx = np.concatenate([np.arange(len(imu)), np.arange(len(t))])
    order = np.lexsort((idx, kind, at))
    return ds, imu, (t, a, r), kind[order], idx[order]


def _per_sample(ds, imu, rng_, kinds, idx):
    f = Eskf.for_dataset(ds, EskfOptions(), record=True)
    t, a, r = rng_
    for k, i in zip(kinds.tolist(), idx.tolist()):
        if k == 0:
            f.push_imu(imu[i, 0], imu[i, 1:4], imu[i, 4:7])
        else:
            f.push_range(t[i], a[i], r[i])
    f.finish()
    return f


def _chunked(ds, imu, rng_, kinds, idx, sizes):
    f = Eskf.for_dataset(ds, EskfOptions(), record=True)
    t, a, r = rng_
    i = 0
    while i < len(kinds):
        n, k, j = next(sizes), kinds[i], i
        while j < len(kinds) and j - i < n and kinds[j] == k:
            j += 1
        sel = idx[i:j]
        if k == 0:
            f.push_imu_chunk(imu[sel, 0], imu[sel, 1:4], imu[sel, 4:7])
        else:
            f.push_ranges(t[sel], list(a[sel]), r[sel])
        i = j
    f.finish()
    return f


def _rejections(f):
    out = {}
    for e in f.events():
        if e["kind"] == "input_rejected":
            out[e["stream"], e["reason"]] = out.get((e["stream"], e["reason"]), 0) + e["count"]
    return out


@pytest.mark.parametrize("seed,largest", [(1, 8), (2, 400)])
def test_chunks_give_the_per_sample_state_and_the_same_guards(flight_with_faults, seed, largest):
    ds, imu, rng_, kinds, idx = flight_with_faults
    one = _per_sample(ds, imu, rng_, kinds, idx)
    gen = np.random.default_rng(seed)
    many = _chunked(ds, imu, rng_, kinds, idx, iter(lambda: int(gen.integers(1, largest + 1)), None))
    s1, s2 = one.state(), many.state()
    assert s1 is not None and s1.t_imu == s2.t_imu
    for name in ("position", "velocity", "quaternion", "accel_bias", "gyro_bias", "lever_arm"):
        np.testing.assert_array_equal(getattr(s2, name), getattr(s1, name))
    assert s2.time_offset == s1.time_offset
    np.testing.assert_array_equal(s2.covariance, s1.covariance)
    p1, p2 = one.passes(), many.passes()
    assert len(p1) == len(p2) >= 1
    for a, b in zip(p1, p2):
        np.testing.assert_array_equal(b.states, a.states)
    # the same samples refused for the same reasons (the faults above, all of them)
    got = _rejections(one)
    assert got == _rejections(many)
    assert got == {("imu", "imu_not_finite"): 4, ("imu", "imu_implausible"): 1, ("imu", "imu_not_increasing"): 1,
                   ("range", "range_not_positive"): 1, ("range", "range_too_long"): 1,
                   ("range", "not_finite"): 1, ("range", "unknown_anchor"): 1}
    # and the same other events (initialisation, ...) in the same order
    rest = [[{k: v for k, v in e.items()} for e in f.events() if e["kind"] != "input_rejected"] for f in (one, many)]
    assert rest[0] == rest[1]
    assert [e["kind"] for e in rest[0]].count("initialised") == 1


def _replay_one_call_at_a_time(flight_with_faults, look_every: int):
    """Feed the flight one push per sample in arrival order, reading the state every ``look_every`` calls (a
    caller looking now and then); the filter and the states read."""
    ds, imu, (t, a, r), kinds, idx = flight_with_faults
    f = Eskf.for_dataset(ds, EskfOptions(), record=True)
    seen = []
    for n, (k, i) in enumerate(zip(kinds.tolist(), idx.tolist())):
        if k == 0:
            f.push_imu(imu[i, 0], imu[i, 1:4], imu[i, 4:7])
        else:
            f.push_range(t[i], a[i], r[i])
        if n % look_every == 0:
            s = f.state()
            seen.append(None if s is None else (s.t_imu, s.position.tolist(), s.covariance.tobytes()))
    f.finish()
    return f, seen


def test_push_imu_batching_is_invisible(flight_with_faults, monkeypatch):
    """push_imu keeps up to IMU_BATCH samples before processing them; every accessor and every other push
    processes them first: states read along the way and events are those of one-sample processing."""
    from uwbimu.estimation import streaming

    batched, seen_b = _replay_one_call_at_a_time(flight_with_faults, 137)
    assert streaming.IMU_BATCH > 1
    monkeypatch.setattr(streaming, "IMU_BATCH", 1)
    single, seen_1 = _replay_one_call_at_a_time(flight_with_faults, 137)
    assert seen_b == seen_1 and any(x is not None for x in seen_1)
    assert batched.events() == single.events()
    np.testing.assert_array_equal(batched.passes()[-1].states, single.passes()[-1].states)


def test_measurement_batching_is_invisible(flight_with_faults, monkeypatch):
    """push_range keeps up to MEAS_BATCH checked ranges (with the kept IMU samples) before handing them to
    the filter; states read along the way and the event list (rejections included, in order) are those of
    handing each range over at once (MEAS_BATCH = IMU_BATCH = 1), and so are the final states."""
    from uwbimu.estimation import streaming

    assert streaming.MEAS_BATCH > 1
    batched, seen_b = _replay_one_call_at_a_time(flight_with_faults, 211)
    assert len(batched._pend_m) == 0
    monkeypatch.setattr(streaming, "MEAS_BATCH", 1)
    monkeypatch.setattr(streaming, "IMU_BATCH", 1)
    single, seen_1 = _replay_one_call_at_a_time(flight_with_faults, 211)
    assert seen_b == seen_1 and any(x is not None for x in seen_1)
    assert batched.events() == single.events()
    assert any(e["kind"] == "input_rejected" and e["stream"] == "range" for e in single.events())
    np.testing.assert_array_equal(batched.passes()[-1].states, single.passes()[-1].states)


def test_tdoa_batching_is_invisible(monkeypatch):
    """The same for push_tdoa on a TDoA flight with refused rows (same anchor, too large, unknown)."""
    from uwbimu.estimation import streaming

    ds = simulate(builtin_scenario("crazyflie-tdoa3").model_copy(update={"duration": 30.0}))
    assert ds.tdoa is not None and len(ds.tdoa) > 1000
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    td_ = ds.tdoa
    t = td_["t"].to_numpy(float)
    aa = td_["anchor_a"].astype(str).to_numpy().astype(object)
    bb = td_["anchor_b"].astype(str).to_numpy().astype(object)
    z = td_["tdoa"].to_numpy(float).copy()
    j = int(np.searchsorted(t, 20.0))
    bb[j + 1] = aa[j + 1]   # same anchor
    z[j + 4] = 1e3          # longer than the pair's baseline allows
    aa[j + 6] = "nope"      # unknown anchor
    z[j + 8] = np.nan       # not finite
    at = np.concatenate([imu[:, 0], t + 0.01])
    order = np.argsort(at, kind="stable")
    n_imu = len(imu)

    def run():
        f = Eskf.for_dataset(ds, EskfOptions(), record=True)
        for i in order.tolist():
            if i < n_imu:
                f.push_imu(imu[i, 0], imu[i, 1:4], imu[i, 4:7])
            else:
                k = i - n_imu
                f.push_tdoa(t[k], aa[k], bb[k], z[k])
        f.finish()
        return f

    batched = run()
    monkeypatch.setattr(streaming, "MEAS_BATCH", 1)
    monkeypatch.setattr(streaming, "IMU_BATCH", 1)
    single = run()
    reasons = {e["reason"] for e in single.events() if e["kind"] == "input_rejected"}
    assert {"same_anchor", "tdoa_too_large", "unknown_anchor", "not_finite"} <= reasons
    assert batched.events() == single.events()
    assert batched.initialised and single.initialised
    np.testing.assert_array_equal(batched.passes()[-1].states, single.passes()[-1].states)


def test_state_carries_every_declared_block_as_the_batch_writes_it():
    """EskfState.blocks is block_calibration of the current state: the keys a batch run writes."""
    from uwbimu.estimation.eskf import run_eskf
    from uwbimu.estimation.options import AnchorBiasOptions

    ds = simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0}))
    opts = EskfOptions(noise="preset", hold_unidentified=False, sigma_from_residuals=False,
                       anchor_bias=AnchorBiasOptions(mode="estimate"))
    f = Eskf.for_dataset(ds, opts, record=False)
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    f.push_imu_chunk(imu[:, 0], imu[:, 1:4], imu[:, 4:7])
    f.push_ranges(ds.uwb["t"].to_numpy(float), list(ds.uwb["anchor"].astype(str)), ds.uwb["range"].to_numpy(float))
    f.finish()
    st = f.state()
    batch = run_eskf(ds, opts).calibration
    assert {"lever_arm", "lever_arm_sd", "time_offset", "time_offset_sd", "anchor_bias"} <= set(st.blocks)
    assert {k for k in st.blocks if not k.endswith("_mode")} <= set(batch)
    assert st.blocks["anchor_bias"].keys() == st.anchor_bias.keys()
    np.testing.assert_array_equal(np.asarray(st.blocks["lever_arm"], float), st.lever_arm)
    np.testing.assert_array_equal(np.asarray(st.blocks["lever_arm_sd"], float), st.lever_arm_sd)
    assert st.blocks["time_offset"] == st.time_offset
