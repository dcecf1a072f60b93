"""UWB time differences of arrival (Loco Positioning TDoA2 / TDoA3) on the UWB clock.

The tag only listens.  Anchors transmit packets; the tag time-stamps every
packet it receives, and a measurement is the difference of two arrivals
converted to metres.  For a packet ``k`` from anchor ``a_k`` that reaches
the tag at UWB time ``t_k`` the arrival error (metres) is::

    e_k = n_k + c_a(t_k) + [NLOS] x_k,
    n_k ~ N(0, sigma^2)                    (tag receive timestamp noise, per packet)
    c_a(t) = clock_sigma_a * N(0, 1) + w_a(t)  (anchor clock: white per packet + random walk)
    x_k ~ Exponential(mean nlos_scale) > 0   (late first path)

and the difference of packet ``j`` (anchor A, earlier) and packet ``k``
(anchor B) is logged at stamp ``t_k + jitter`` as::

    tdoa = |p_U(t_k) - B| - |p_U(t_j) - A| + e_k - e_j

i.e. ``tdoa = |p_U - p_b| - |p_U - p_a|`` (the dataset convention) with
each distance taken at its own packet's arrival (the tag moves by
``v (t_k - t_j)`` in between, a few millimetres at Loco rates).  Two
differences that share a packet share its error, so consecutive TDoA2
measurements are correlated (coefficient -1/2 for equal noises), as on the
real system.

* **TDoA2** (``mode: tdoa2``): anchors transmit in a fixed slot order
  ``A0, A1, ..., A(M-1), A0, ...`` at ``rate_hz`` slots per second; each
  received packet is differenced with the packet of the *previous slot*
  (anchor ``a-1``) if that one was received (the Loco TDoA2 tag does the same).
* **TDoA3** (``mode: tdoa3``): anchors are free running; anchor ``a``
  transmits at intervals ``M / rate_hz * U(1 - tdoa3_interval_jitter, 1 +
  tdoa3_interval_jitter)`` from a random phase; each received packet is
  differenced with the latest received packet of one *randomly chosen other
  anchor*, among those heard within ``tdoa3_max_age`` seconds.

Packets are lost (and counted) by an outage window of their anchor, the
maximum range (true distance), a random dropout; a difference is emitted
only when both of its packets were received.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.sim.ranging import in_outage, nlos_probability
from uwbimu.sim.scenario import Scenario
from uwbimu.sim.trajectory import Trajectory


def packet_schedule(scenario: Scenario, lo: float, hi: float, rng: np.random.Generator):
    """Transmission instants and anchors of every packet in ``[lo, hi]`` (sorted by time).

    Returns ``(t, anchor_index)``.  TDoA2: slot ``j`` at ``j / rate_hz`` carries
    anchor ``j mod M``.  TDoA3: independent free-running anchors (random phase
    and jittered intervals drawn from ``rng``).
    """
    u = scenario.uwb
    M = len(scenario.anchor_ids())
    if u.mode == "tdoa2":
        j = np.arange(int(np.ceil(lo * u.rate_hz - 1e-9)), int(np.floor(hi * u.rate_hz + 1e-9)) + 1)
        return j / u.rate_hz, j % M
    period = M / u.rate_hz
    n_max = int(np.ceil((hi - lo) / (period * (1 - u.tdoa3_interval_jitter)))) + 2
    phase = rng.random(M) * period
    steps = period * rng.uniform(1 - u.tdoa3_interval_jitter, 1 + u.tdoa3_interval_jitter, (M, n_max))
    times = lo + phase[:, None] + np.concatenate([np.zeros((M, 1)), np.cumsum(steps, axis=1)[:, :-1]], axis=1)
    anchor = np.broadcast_to(np.arange(M)[:, None], times.shape)
    keep = times <= hi
    t, a = times[keep], anchor[keep]
    order = np.argsort(t, kind="stable")
    return t[order], a[order]


def _pairs_tdoa2(anchor: np.ndarray, received: np.ndarray, M: int) -> tuple[np.ndarray, np.ndarray]:
    """Packet index pairs ``(j, k)``: slot k and the slot before it, both received."""
    k = np.arange(1, len(anchor))
    ok = received[k] & received[k - 1] & (anchor[k - 1] == (anchor[k] - 1) % M)
    return k[ok] - 1, k[ok]


def _pairs_tdoa3(t: np.ndarray, anchor: np.ndarray, received: np.ndarray, M: int, max_age: float,
                 rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """For each received packet k, the latest packet of one random other anchor (age <= max_age)."""
    last = np.full(M, -1)
    choice_u = rng.random(len(t))  # one draw per packet, used or not (fixed draw order)
    js, ks = [], []
    for k in range(len(t)):
        if not received[k]:
            continue
        cand = np.flatnonzero((last >= 0) & (np.arange(M) != anchor[k]))
        if len(cand):
            cand = cand[t[k] - t[last[cand]] <= max_age]
        if len(cand):
            js.append(last[cand[int(choice_u[k] * len(cand))]])
            ks.append(k)
        last[anchor[k]] = k
    return np.asarray(js, dtype=int), np.asarray(ks, dtype=int)


def simulate_tdoa(scenario: Scenario, traj: Trajectory, lo: float, hi: float, rng: np.random.Generator):
    """Simulate the ``tdoa`` table; returns ``(DataFrame, info)``.

    ``info`` holds ``counts`` (packets scheduled / received / NLOS and each
    loss cause, differences emitted) and, per emitted row, ``t_nominal`` (B's
    arrival), ``t_a_nominal`` (A's arrival),
    ``true`` (noise-free difference with each distance at its packet's
    arrival), ``nlos`` (either packet NLOS) and ``packets`` (indices j, k).
    """
    u = scenario.uwb
    ids = np.array(scenario.anchor_ids(), dtype=object)
    A = scenario.anchor_positions()
    M = len(ids)
    tag = scenario.tag_list()[0]  # TDoA is simulated for the first tag (the Loco deck has one)
    lever = np.asarray(tag.lever_arm, dtype=float)

    # Fixed draw order: schedule, then per-packet draws, then the TDoA3 partner choice.
    t, ai = packet_schedule(scenario, lo, hi, rng)
    n = len(t)
    white = rng.standard_normal(n) * u.sigma
    clock_white = rng.standard_normal(n)
    nlos_u = rng.random(n)
    excess = rng.exponential(u.nlos_scale, n)
    drop_u = rng.random(n)
    jitter = rng.standard_normal(n) * u.jitter_sd
    clock_rw_steps = rng.standard_normal(n)

    p, q = traj.pose(t) if n else (np.zeros((0, 3)), np.zeros((0, 4)))
    antenna = p + np.einsum("nij,j->ni", quat_to_rotmat(q), lever) if n else np.zeros((0, 3))
    dist = np.linalg.norm(A[ai] - antenna, axis=1)

    # Anchor clock error: white per packet plus a per-anchor random walk in that anchor's packet times.
    clock_sd = np.array([u.anchor_clock_sigma.get(a, u.clock_sigma) for a in ids], dtype=float)
    clock = clock_white * clock_sd[ai]
    if u.clock_rw > 0:
        for m in range(M):
            idx = np.flatnonzero(ai == m)
            if len(idx) > 1:
                dt = np.diff(t[idx], prepend=t[idx[0]])
                clock[idx] += np.cumsum(clock_rw_steps[idx] * u.clock_rw * np.sqrt(dt))

    nlos = nlos_u < nlos_probability(u, t, ids[ai])
    bias = np.array([u.anchor_bias.get(a, 0.0) for a in ids], dtype=float)[ai] if n else np.zeros(0)
    arrival_err = white + clock + bias + np.where(nlos, excess, 0.0)

    outage = in_outage(u, t, ids[ai])
    too_far = (dist > u.max_range) if u.max_range is not None else np.zeros(n, bool)
    dropped = drop_u < u.dropout_prob
    lost_outage = outage
    lost_range = too_far & ~lost_outage
    lost_drop = dropped & ~lost_outage & ~lost_range
    received = ~(lost_outage | lost_range | lost_drop)

    if u.mode == "tdoa2":
        j, k = _pairs_tdoa2(ai, received, M)
    else:
        j, k = _pairs_tdoa3(t, ai, received, M, u.tdoa3_max_age, rng)
    true = dist[k] - dist[j]
    meas = true + arrival_err[k] - arrival_err[j]
    stamp = t[k] + jitter[k]
    order = np.argsort(stamp, kind="stable")
    df = pd.DataFrame({
        "t": stamp[order],
        "anchor_a": ids[ai[j]][order].astype(str),
        "anchor_b": ids[ai[k]][order].astype(str),
        "tdoa": meas[order],
    })
    counts = {
        "packets_scheduled": int(n),
        "packets_received": int(received.sum()),
        "packets_nlos": int((nlos & received).sum()),
        "dropped_outage": int(lost_outage.sum()),
        "dropped_max_range": int(lost_range.sum()),
        "dropped_dropout": int(lost_drop.sum()),
        "emitted": int(len(k)),
    }
    info = {
        "counts": counts,
        "t_nominal": t[k][order],
        "t_a_nominal": t[j][order],
        "true": true[order],
        "nlos": (nlos[j] | nlos[k])[order],
        "packets": np.column_stack([j, k])[order] if len(k) else np.zeros((0, 2), int),
    }
    return df, info


def tdoa_sigma(scenario: Scenario) -> float:
    """Marginal sd of one simulated difference without NLOS [m]: ``sqrt(2 (sigma^2 + clock^2))``.

    (Uses the default ``clock_sigma``; per-anchor overrides and the clock random
    walk make the true sd pair- and time-dependent.)
    """
    u = scenario.uwb
    return float(np.sqrt(2.0 * (u.sigma**2 + u.clock_sigma**2)))
