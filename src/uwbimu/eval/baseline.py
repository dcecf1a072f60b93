"""A model-free reference: epoch-wise multilateration of the UWB tag.

Used to sanity-check an imported real dataset independently of any filter:
if the multilaterated tag track, rigidly aligned to the ground truth, is
close to it, the ranges, anchor positions, anchor ids, known biases and
clocks of the import are consistent.  It ignores the IMU and the lever arm
(it locates the antenna, not the IMU), so it is a sanity bound, not a
competitor of the ESKF.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.optimize import least_squares

from uwbimu.io.dataset import Dataset


def multilaterate(
    ds: Dataset,
    min_anchors: int = 4,
    epoch_s: float = 0.0,
    max_rms: float = 0.3,
    loss_scale: float = 0.1,
) -> pd.DataFrame:
    """Least-squares tag position per ranging epoch.

    Parameters
    ----------
    ds : dataset (ranges minus ``meta.known_anchor_bias``, anchors in the world frame).
    min_anchors : epochs with fewer distinct anchors are skipped.
    epoch_s : ranges within this window [s] form one epoch (0: identical stamps).
    max_rms : epochs whose robust fit leaves an RMS residual above this [m] are dropped.
    loss_scale : soft-L1 scale [m] of the robust fit.

    Returns
    -------
    DataFrame ``t, px, py, pz, rms, n`` (tag position, world frame, UWB clock).
    """
    pos = ds.anchor_positions()
    kb = ds.meta.known_anchor_bias or {}
    u = ds.uwb.sort_values("t", kind="stable")
    t = u["t"].to_numpy(float)
    key = t if epoch_s <= 0 else np.floor((t - t[0]) / epoch_s)
    anchors = u["anchor"].astype(str).to_numpy()
    r = u["range"].to_numpy(float) - np.array([kb.get(a, 0.0) for a in anchors])
    P_all = np.array([pos.get(a, (np.nan,) * 3) for a in anchors], float)
    A = np.array(list(pos.values()))
    x0 = A.mean(axis=0)
    rows = []
    bounds = np.flatnonzero(np.r_[True, key[1:] != key[:-1], True])
    for i0, i1 in zip(bounds[:-1], bounds[1:]):
        sel = slice(i0, i1)
        ok = np.isfinite(P_all[sel]).all(axis=1)
        if len(set(anchors[sel][ok])) < min_anchors:
            continue
        P, rr = P_all[sel][ok], r[sel][ok]
        sol = least_squares(lambda x: np.linalg.norm(P - x, axis=1) - rr, x0, loss="soft_l1", f_scale=loss_scale)
        rms = float(np.sqrt(np.mean(sol.fun**2)))
        if rms <= max_rms:
            rows.append((float(np.mean(t[sel])), *sol.x, rms, int(ok.sum())))
            x0 = sol.x
    return pd.DataFrame(rows, columns=["t", "px", "py", "pz", "rms", "n"])
