"""TDoA2 / TDoA3 simulation: geometry, pairing, shared-packet correlation, losses, NLOS, round trip."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.sim import ScenarioError, builtin_scenario, simulate_full, validate_scenario
from uwbimu.sim.sensors import antenna_positions


def _short(name: str, **uwb) -> object:
    sc = builtin_scenario(name).updated(duration=8.0, imu={"rate_hz": 200.0})
    return sc.updated(uwb=uwb) if uwb else sc


@pytest.fixture(scope="module")
def tdoa2_exact():
    return simulate_full(_short("crazyflie-tdoa2", sigma=0.0, clock_sigma=0.0))


@pytest.fixture(scope="module")
def tdoa3_exact():
    return simulate_full(_short("crazyflie-tdoa3", sigma=0.0, clock_sigma=0.0))


def _geometric(res, sc, t_a, t_b, a_ids, b_ids):
    ids = sc.anchor_ids()
    A = sc.anchor_positions()
    lever = sc.tag_list()[0].lever_arm

    def dist(t, anchors):
        p, q = res.trajectory.pose(t)
        u = antenna_positions(p, q, lever)
        return np.linalg.norm(A[[ids.index(a) for a in anchors]] - u, axis=1)

    return dist(t_b, b_ids) - dist(t_a, a_ids)


@pytest.mark.parametrize("fixture", ["tdoa2_exact", "tdoa3_exact"])
def test_noise_free_tdoa_is_the_distance_difference(fixture, request):
    res = request.getfixturevalue(fixture)
    ds = res.dataset
    sc = builtin_scenario("crazyflie-tdoa3")
    assert ds.tdoa is not None and len(ds.tdoa) > 1000 and len(ds.uwb) == 0
    np.testing.assert_allclose(ds.tdoa["tdoa"].to_numpy(), res.tdoa_true, atol=1e-12)
    # Each distance at its own packet's arrival: B at the stamp, A at the earlier packet.
    a, b = ds.tdoa["anchor_a"].to_numpy(), ds.tdoa["anchor_b"].to_numpy()
    t_b = ds.tdoa["t"].to_numpy()
    # A's arrival instant is not in the table; the difference to same-instant geometry is the
    # tag's motion between the packets (speed < 2 m/s, packets < max_age apart).
    same_instant = _geometric(res, sc, t_b, t_b, a, b)
    max_gap = 0.1 if fixture == "tdoa3_exact" else 1 / sc.uwb.rate_hz
    assert np.max(np.abs(same_instant - res.tdoa_true)) <= 2.0 * max_gap + 1e-9
    assert np.median(np.abs(same_instant - res.tdoa_true)) < 0.01


def test_tdoa2_pairs_are_consecutive_slots(tdoa2_exact):
    df = tdoa2_exact.dataset.tdoa
    a = df["anchor_a"].astype(int).to_numpy()
    b = df["anchor_b"].astype(int).to_numpy()
    assert np.all(b == (a + 1) % 8)
    dt = np.diff(df["t"].to_numpy())
    np.testing.assert_allclose(dt, 1 / 400.0, rtol=1e-9)


def test_tdoa3_pairs_are_random_and_recent(tdoa3_exact):
    df = tdoa3_exact.dataset.tdoa
    pairs = set(zip(df["anchor_a"], df["anchor_b"]))
    assert all(x != y for x, y in pairs)
    assert len(pairs) == 56  # every ordered pair of 8 anchors occurs
    counts = df.groupby(["anchor_a", "anchor_b"]).size().to_numpy()
    # Uniform partner choice: pair counts spread like a multinomial, not concentrated.
    expected = len(df) / 56
    assert np.all(np.abs(counts - expected) < 5 * np.sqrt(expected))


def test_tdoa2_consecutive_errors_share_a_packet():
    res = simulate_full(_short("crazyflie-tdoa2", sigma=0.05, clock_sigma=0.0))
    err = res.dataset.tdoa["tdoa"].to_numpy() - res.tdoa_true
    n = len(err)
    assert abs(np.std(err) / (0.05 * np.sqrt(2)) - 1) < 5 / np.sqrt(2 * n)
    rho = np.corrcoef(err[:-1], err[1:])[0, 1]
    assert abs(rho + 0.5) < 5 / np.sqrt(n)  # shared packet: -1/2 for equal noises


def test_clock_noise_per_anchor():
    res = simulate_full(_short("crazyflie-tdoa3", sigma=0.0, clock_sigma=0.0, anchor_clock_sigma={"3": 0.2}))
    df = res.dataset.tdoa
    err = df["tdoa"].to_numpy() - res.tdoa_true
    with3 = (df["anchor_a"] == "3") | (df["anchor_b"] == "3")
    assert np.all(err[~with3] == 0)
    assert abs(np.std(err[with3]) / 0.2 - 1) < 0.15


def test_losses_nlos_and_outage():
    sc = _short("crazyflie-tdoa2", sigma=0.0, clock_sigma=0.0, dropout_prob=0.2, outages=[[2.0, 4.0, "5"]],
                nlos_bursts=[{"t0": 5.0, "t1": 7.0, "anchor": "2", "prob": 1.0}], nlos_scale=0.5)
    res = simulate_full(sc)
    df = res.dataset.tdoa
    c = res.dataset.meta.extra["uwb_counts"]
    assert c["dropped_outage"] > 0 and c["dropped_dropout"] > 0
    assert c["packets_received"] == c["packets_scheduled"] - c["dropped_outage"] - c["dropped_dropout"]
    t = df["t"].to_numpy()
    involved5 = (df["anchor_a"] == "5") | (df["anchor_b"] == "5")
    assert not np.any(involved5 & (t >= 2.0) & (t < 4.0))
    # TDoA2 needs both packets of a pair: about (1 - p)^2 of the slots outside the outage.
    frac = len(df) / c["packets_scheduled"]
    assert 0.55 < frac < 0.7
    err = df["tdoa"].to_numpy() - res.tdoa_true
    burst = (t >= 5.0) & (t < 7.0)
    assert np.all(err[burst & (df["anchor_b"] == "2")] > 0)  # late arrival of B: difference too long
    assert np.all(err[burst & (df["anchor_a"] == "2")] < 0)
    assert np.all(err[~burst] == 0)
    assert np.all(res.tdoa_nlos[burst & ((df["anchor_a"] == "2") | (df["anchor_b"] == "2"))])


def test_round_trip_and_metadata(tmp_path, tdoa3_exact):
    from uwbimu.io.dataset import write_dataset
    from uwbimu.io.loader import load_dataset

    ds = tdoa3_exact.dataset
    assert ds.meta.extra["uwb_mode"] == "tdoa3" and ds.meta.range_sigma is None
    out = write_dataset(ds, tmp_path / "d")
    back = load_dataset(out)
    assert back.tdoa is not None and len(back.tdoa) == len(ds.tdoa)
    np.testing.assert_allclose(back.tdoa["tdoa"].to_numpy(), ds.tdoa["tdoa"].to_numpy(), rtol=1e-12)
    assert list(back.tdoa["anchor_a"].astype(str)) == list(ds.tdoa["anchor_a"])


def test_deterministic_and_seeded():
    a = simulate_full(_short("crazyflie-tdoa3")).dataset.tdoa
    b = simulate_full(_short("crazyflie-tdoa3")).dataset.tdoa
    c = simulate_full(_short("crazyflie-tdoa3").updated(seeds={"noise": 7})).dataset.tdoa
    assert a.equals(b)
    assert not a["tdoa"].equals(c["tdoa"])


def test_refusals_name_the_field():
    base = builtin_scenario("crazyflie-tdoa3").model_dump(mode="json", exclude_none=True)
    with pytest.raises(ScenarioError, match="anchor_clock_sigma"):
        validate_scenario({**base, "uwb": {**base["uwb"], "anchor_clock_sigma": {"9": 0.1}}})
    two = {**base, "tags": [{"name": "a", "lever_arm": [0, 0, 0]}, {"name": "b", "lever_arm": [0.1, 0, 0]}]}
    two.pop("lever_arm")
    with pytest.raises(ScenarioError, match="one tag"):
        validate_scenario(two)
    with pytest.raises(ScenarioError, match="uwb.mode"):
        validate_scenario({**base, "uwb": {**base["uwb"], "mode": "tdoa4"}})


def test_clock_random_walk_grows_with_time():
    res = simulate_full(_short("crazyflie-tdoa3", sigma=0.0, clock_sigma=0.0, clock_rw=0.05))
    df = res.dataset.tdoa
    err = df["tdoa"].to_numpy() - res.tdoa_true
    t = df["t"].to_numpy()
    early, late = np.var(err[t < 2.0]), np.var(err[t > 6.0])
    # a random walk of density q: each anchor's error variance is q^2 t, the difference's 2 q^2 t
    assert late > 2 * early > 0
    assert 0.3 < np.mean(err[t > 6.0] ** 2) / (2 * 0.05**2 * 7.0) < 3.0
