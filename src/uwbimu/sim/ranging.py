"""UWB two-way ranging on the UWB clock: schedule, noise, NLOS, biases, losses.

A range scheduled at nominal UWB time ``t`` between tag ``k`` and anchor
``a`` is::

    r = || a - (p(t) + R(t) p_IU,k) || + bias_a + n + [NLOS] e,
    n ~ N(0, sigma^2),  e ~ Exponential(mean nlos_scale) > 0

and is logged with stamp ``t + jitter``.  Ranges are lost (and counted) by,
in this order of attribution: an outage window, the maximum range (on the
true distance), a random dropout, a non-positive measured value.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.sim.scenario import Scenario
from uwbimu.sim.trajectory import Trajectory


def nlos_probability(u, t: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Per-event NLOS probability: ``nlos_prob``, raised to ``prob`` inside each burst window."""
    p_nlos = np.full(len(t), u.nlos_prob)
    for b in u.nlos_bursts:
        inside = (t >= b.t0) & (t < b.t1)
        if b.anchor is not None:
            inside &= anchor == b.anchor
        p_nlos = np.where(inside, np.maximum(p_nlos, b.prob), p_nlos)
    return p_nlos


def in_outage(u, t: np.ndarray, anchor: np.ndarray) -> np.ndarray:
    """Per-event flag: inside an outage window of its anchor (or of all anchors)."""
    outage = np.zeros(len(t), bool)
    for t0, t1, a in u.outages:
        hit = (t >= t0) & (t < t1)
        if a is not None:
            hit &= anchor == a
        outage |= hit
    return outage


def schedule(scenario: Scenario, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nominal ranging events in the UWB window ``[lo, hi]``.

    Returns ``(t, anchor_index, tag_index)``.  ``round_robin`` gives one
    (tag, anchor) pair per slot, cycling anchors-major (for one tag: A0, A1,
    ...); ``all`` gives every pair at each slot.
    """
    rate = scenario.uwb.rate_hz
    M, T = len(scenario.anchor_ids()), len(scenario.tag_list())
    j = np.arange(int(np.ceil(lo * rate - 1e-9)), int(np.floor(hi * rate + 1e-9)) + 1)
    t_slot = j / rate
    pair_anchor = np.repeat(np.arange(M), T)
    pair_tag = np.tile(np.arange(T), M)
    P = M * T
    if scenario.uwb.schedule == "round_robin":
        k = j % P
        return t_slot, pair_anchor[k], pair_tag[k]
    return np.repeat(t_slot, P), np.tile(pair_anchor, len(j)), np.tile(pair_tag, len(j))


def simulate_ranges(scenario: Scenario, traj: Trajectory, lo: float, hi: float, rng: np.random.Generator):
    """Simulate the ``uwb`` table; returns ``(DataFrame, info)``.

    ``info`` holds ``counts`` (scheduled, emitted, nlos and each loss cause)
    and, per emitted row, ``t_nominal``, ``true`` range and ``nlos`` flag.
    """
    u = scenario.uwb
    ids = np.array(scenario.anchor_ids(), dtype=object)
    A = scenario.anchor_positions()
    tags = scenario.tag_list()
    levers = np.array([t.lever_arm for t in tags], dtype=float)

    t, ai, ti = schedule(scenario, lo, hi)
    n = len(t)
    p, q = traj.pose(t) if n else (np.zeros((0, 3)), np.zeros((0, 4)))
    # Same relation as reference.range_measurement, batched (pinned by test_sim_sensors).
    antenna = p + np.einsum("nij,nj->ni", quat_to_rotmat(q), levers[ti])
    true = np.linalg.norm(A[ai] - antenna, axis=1)

    # Fixed draw order, every event draws, so one setting never shifts another's randomness.
    white = rng.standard_normal(n) * u.sigma
    nlos_u = rng.random(n)
    excess = rng.exponential(u.nlos_scale, n)
    drop_u = rng.random(n)
    jitter = rng.standard_normal(n) * u.jitter_sd

    nlos = nlos_u < nlos_probability(u, t, ids[ai])
    bias = np.array([u.anchor_bias.get(a, 0.0) for a in ids], dtype=float)[ai] if n else np.zeros(0)
    meas = true + white + bias + np.where(nlos, excess, 0.0)

    outage = in_outage(u, t, ids[ai])
    too_far = (true > u.max_range) if u.max_range is not None else np.zeros(n, bool)
    dropped = drop_u < u.dropout_prob
    nonpos = meas <= 0
    lost_outage = outage
    lost_range = too_far & ~lost_outage
    lost_drop = dropped & ~lost_outage & ~lost_range
    lost_nonpos = nonpos & ~(lost_outage | lost_range | lost_drop)
    keep = ~(lost_outage | lost_range | lost_drop | lost_nonpos)

    stamp = (t + jitter)[keep]
    order = np.argsort(stamp, kind="stable")  # the receiver logs in stamp order
    cols = {"t": stamp[order], "anchor": ids[ai][keep][order].astype(str), "range": meas[keep][order]}
    if len(tags) > 1:
        cols["tag"] = np.array([tg.name for tg in tags], dtype=object)[ti][keep][order].astype(str)
    df = pd.DataFrame(cols)
    counts = {
        "scheduled": int(n),
        "emitted": int(keep.sum()),
        "nlos": int((nlos & keep).sum()),
        "dropped_outage": int(lost_outage.sum()),
        "dropped_max_range": int(lost_range.sum()),
        "dropped_dropout": int(lost_drop.sum()),
        "dropped_nonpositive": int(lost_nonpos.sum()),
    }
    info = {
        "counts": counts,
        "t_nominal": t[keep][order],
        "true": true[keep][order],
        "nlos": nlos[keep][order],
    }
    return df, info
