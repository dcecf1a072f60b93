"""TDoA diagnostics of ``uwbimu check``: per-pair rates, residuals against ground truth, pair flags.

A TDoA row ``t, anchor_a, anchor_b, tdoa`` measures ``|p_U - p_b| - |p_U - p_a|`` [m]
(:func:`uwbimu.models.reference.tdoa_measurement`).  Its residual is the measured value minus
that difference predicted from the ground-truth antenna position at ``t``
(:func:`uwbimu.io.check.antenna_track`: ground-truth pose + nominal lever arm, same clock
rules as the range residuals).

Pairs are reported unordered: the rows of ``(b, a)`` are folded into the pair ``(a, b)``
(ids in natural order) with the sign of their value and residual flipped, so that a pair
is one row however the log orders it.

Flags (``AnchorFlag`` records, like the anchors'):

* ``tdoa_bias`` on a pair ``"a-b"``: ``|median residual|`` above ``bias_threshold``;
* ``tdoa_outliers`` on a pair: more than ``tdoa_max_outlier_fraction`` of its residuals lie
  further than ``tdoa_outlier`` from the pair's median (NLOS, wrong packets);
* ``tdoa_anchor_offset`` on an anchor: a range offset ``beta`` of anchor ``x`` (antenna delay,
  misplaced antenna) adds ``beta_b - beta_a`` to every pair; the per-anchor offsets fitted by
  least squares to the pair medians (mean zero: TDoA cannot see a common offset) point at
  the anchor behind several biased pairs.
"""

from __future__ import annotations

from typing import Optional

import numpy as np
import pandas as pd

from uwbimu.io.check import (AnchorFlag, CheckOptions, _id_key, _time_stats,
                             antenna_track, residual_stats)
from uwbimu.io.dataset import Dataset

__all__ = ["tdoa_pairs", "tdoa_participation", "tdoa_pair_summary", "tdoa_residuals",
           "tdoa_pair_stats", "tdoa_anchor_offsets", "diagnose_tdoa"]


def tdoa_pairs(tdoa: pd.DataFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unordered pair of every row: ``(first, second, sign)``.

    ``first``/``second`` are the pair's ids in natural order; ``sign`` is ``+1`` where the row
    is ``(first, second)`` and ``-1`` where the log gave ``(second, first)`` (multiply the value
    or residual by it to read it as ``|p_U - p_second| - |p_U - p_first|``).
    """
    a = tdoa["anchor_a"].astype(str).to_numpy()
    b = tdoa["anchor_b"].astype(str).to_numpy()
    ids = sorted(set(a) | set(b), key=_id_key)
    rank = {x: i for i, x in enumerate(ids)}
    ra = np.array([rank[x] for x in a], int)
    rb = np.array([rank[x] for x in b], int)
    keep = ra < rb
    first = np.where(keep, a, b)
    second = np.where(keep, b, a)
    return first, second, np.where(keep, 1.0, -1.0)


def _labels(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    return np.char.add(np.char.add(first.astype(str), "-"), second.astype(str))


def tdoa_participation(ds: Dataset) -> pd.Series:
    """Number of TDoA rows each anchor of ``anchors.csv`` takes part in (0 without ``tdoa``)."""
    ids = [str(a) for a in ds.anchors["anchor"]]
    if ds.tdoa is None or not len(ds.tdoa):
        return pd.Series(0, index=ids, dtype=int)
    counts = pd.concat([ds.tdoa["anchor_a"].astype(str), ds.tdoa["anchor_b"].astype(str)]).value_counts()
    return counts.reindex(ids, fill_value=0).astype(int)


def tdoa_pair_summary(ds: Dataset, gap_factor: float = 5.0) -> pd.DataFrame:
    """Per unordered pair: rows, rate [Hz] (rows over the TDoA stream's span), gaps (as streams),
    median and extreme values [m] (read as ``second - first``).  Empty without TDoA."""
    cols = ["pair", "anchor_a", "anchor_b", "samples", "rate_hz", "median_dt", "max_gap", "n_gaps",
            "tdoa_min", "tdoa_median", "tdoa_max"]
    td = ds.tdoa
    if td is None or not len(td):
        return pd.DataFrame(columns=cols).set_index("pair")
    first, second, sign = tdoa_pairs(td)
    t = td["t"].to_numpy(float)
    span = float(t.max() - t.min())
    val = sign * td["tdoa"].to_numpy(float)
    label = _labels(first, second)
    rows = []
    for lab in pd.unique(label):
        m = label == lab
        st = _time_stats(t[m], gap_factor)
        v = val[m]
        rows.append({"pair": lab, "anchor_a": first[m][0], "anchor_b": second[m][0], "samples": int(m.sum()),
                     "rate_hz": m.sum() / span if span > 0 else np.nan, "median_dt": st["median_dt"],
                     "max_gap": st["max_gap"], "n_gaps": st["n_gaps"], "tdoa_min": float(v.min()),
                     "tdoa_median": float(np.median(v)), "tdoa_max": float(v.max())})
    return _sorted(pd.DataFrame(rows, columns=cols))


def _sorted(df: pd.DataFrame) -> pd.DataFrame:
    order = sorted(range(len(df)), key=lambda i: (_id_key(df["anchor_a"].iloc[i]),
                                                  _id_key(df["anchor_b"].iloc[i])))
    return df.iloc[order].set_index("pair")


def tdoa_residuals(ds: Dataset, lever_arm: Optional[np.ndarray] = None, gt_time_shift: float = 0.0,
                   max_gap: float = 0.5) -> pd.DataFrame:
    """Measured minus predicted TDoA for every row covered by ground truth.

    Parameters
    ----------
    ds : dataset with ground truth and ``tdoa``.
    lever_arm, gt_time_shift, max_gap : as :func:`uwbimu.io.check.range_residuals`.

    Returns
    -------
    DataFrame ``t, anchor_a, anchor_b, tdoa, predicted, residual, pair, sign`` [m] (as in the
    log; ``pair`` is the unordered label ``"first-second"``, ``sign`` as :func:`tdoa_pairs`)
    [+ ``tag``], only for compared rows; ``attrs['n_outside']`` counts the rows not compared.
    """
    td = ds.tdoa
    k, ant = antenna_track(ds, td, lever_arm, gt_time_shift, max_gap)
    pos = ds.anchor_positions()
    a = td["anchor_a"].astype(str).to_numpy()[k]
    b = td["anchor_b"].astype(str).to_numpy()[k]
    A = np.array([pos[x] for x in a]).reshape(-1, 3)
    B = np.array([pos[x] for x in b]).reshape(-1, 3)
    pred = np.linalg.norm(B - ant, axis=1) - np.linalg.norm(A - ant, axis=1)
    out = pd.DataFrame({"t": td["t"].to_numpy(float)[k], "anchor_a": a, "anchor_b": b,
                        "tdoa": td["tdoa"].to_numpy(float)[k], "predicted": pred})
    out["residual"] = out["tdoa"] - out["predicted"]
    first, second, sign = tdoa_pairs(out)
    out["pair"] = _labels(first, second)
    out["sign"] = sign
    if "tag" in td.columns:
        out["tag"] = td["tag"].to_numpy()[k]
    out.attrs["n_outside"] = int(len(td) - len(k))
    return out


def tdoa_pair_stats(res: pd.DataFrame, outlier: float = 1.0) -> pd.DataFrame:
    """Per unordered pair: :func:`uwbimu.io.check.residual_stats` of the residuals (read as
    ``second - first``) plus ``anchor_a``, ``anchor_b`` and ``outlier_frac``, the fraction further
    than ``outlier`` [m] from the pair's median."""
    signed = pd.DataFrame({"anchor": res["pair"].to_numpy(), "residual": res["sign"] * res["residual"]})
    table = residual_stats(signed).rename_axis("pair")
    ends = res.drop_duplicates("pair").set_index("pair")
    first, second, _ = tdoa_pairs(ends.reset_index())
    firsts = dict(zip(ends.index, first))
    seconds = dict(zip(ends.index, second))
    table.insert(0, "anchor_a", [firsts[p] for p in table.index])
    table.insert(1, "anchor_b", [seconds[p] for p in table.index])
    frac = {p: float(np.mean(np.abs(g.to_numpy() - np.median(g.to_numpy())) > outlier))
            for p, g in signed.groupby("anchor")["residual"]}
    table["outlier_frac"] = [frac[p] for p in table.index]
    return _sorted(table.reset_index())


def tdoa_anchor_offsets(table: pd.DataFrame, anchors: list[str]) -> pd.Series:
    """Per-anchor range offsets [m] that explain the pair medians (weighted by rows), mean zero.

    ``median(a-b) ~ beta_b - beta_a``; anchors in no pair get NaN.  A common offset of all
    anchors cancels in every TDoA and is fixed by the zero-mean gauge.
    """
    used = sorted(set(table["anchor_a"]) | set(table["anchor_b"]), key=_id_key)
    out = pd.Series(np.nan, index=[str(a) for a in anchors], dtype=float)
    if len(table) == 0:
        return out
    col = {a: i for i, a in enumerate(used)}
    M = np.zeros((len(table) + 1, len(used)))
    y = np.zeros(len(table) + 1)
    w = np.sqrt(table["n"].to_numpy(float))
    for r, (a, b, med) in enumerate(zip(table["anchor_a"], table["anchor_b"], table["median"])):
        M[r, col[b]], M[r, col[a]], y[r] = w[r], -w[r], w[r] * med
    M[-1, :] = w.sum()  # gauge: sum of offsets = 0, weighted like a pair
    beta = np.linalg.lstsq(M, y, rcond=None)[0]
    for a, v in zip(used, beta):
        out[a] = float(v)
    return out


def diagnose_tdoa(res: pd.DataFrame, ds: Dataset, options: CheckOptions
                  ) -> tuple[pd.DataFrame, pd.Series, list[AnchorFlag]]:
    """Pair statistics, per-anchor offsets and flags (``tdoa_bias``, ``tdoa_outliers``,
    ``tdoa_anchor_offset``; see the module docstring).  Pairs with fewer than ``min_ranges``
    compared rows are listed but not flagged."""
    table = tdoa_pair_stats(res, options.tdoa_outlier)
    diag = table[table["n"] >= options.min_ranges]
    offsets = tdoa_anchor_offsets(diag, [str(a) for a in ds.anchors["anchor"]])
    flags: list[AnchorFlag] = []
    for pair, r in diag.iterrows():
        ends = {"anchor_a": r["anchor_a"], "anchor_b": r["anchor_b"]}
        if abs(r["median"]) > options.bias_threshold:
            flags.append(AnchorFlag(pair, "tdoa_bias", (
                f"TDoA pair {pair}: median residual {r['median']:+.3f} m (measured - predicted from ground "
                f"truth, read as |p - {r['anchor_b']}| - |p - {r['anchor_a']}|): an antenna delay, a surveyed "
                f"position or a wrong id of {r['anchor_a']} or {r['anchor_b']}?"),
                {**ends, "median": float(r["median"]), "n": int(r["n"])}))
        if r["outlier_frac"] > options.tdoa_max_outlier_fraction:
            flags.append(AnchorFlag(pair, "tdoa_outliers", (
                f"TDoA pair {pair}: {100 * r['outlier_frac']:.1f} % of {int(r['n'])} residuals lie more than "
                f"{options.tdoa_outlier:g} m from the median (robust sd {r['robust_sigma']:.3f} m): "
                f"non-line-of-sight or mixed-up packets?"),
                {**ends, "outlier_frac": float(r["outlier_frac"]), "robust_sigma": float(r["robust_sigma"])}))
    for a, beta in offsets.items():
        if np.isfinite(beta) and abs(beta) > options.bias_threshold:
            pairs = [p for p, r in diag.iterrows() if a in (r["anchor_a"], r["anchor_b"])]
            flags.append(AnchorFlag(a, "tdoa_anchor_offset", (
                f"anchor {a}: the TDoA pair medians point at a range offset of {beta:+.3f} m on this anchor "
                f"(relative to the others; pairs {', '.join(pairs)}): check its antenna delay and survey"),
                {"offset": float(beta), "pairs": pairs}))
    return table, offsets, flags

