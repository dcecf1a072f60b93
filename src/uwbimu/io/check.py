"""Dataset diagnostics: stream statistics, range residuals against ground truth, anchor flags.

Everything here returns data (DataFrames, dataclasses) so that the CLI
(``uwbimu check``), the report and the estimator can reuse it; printing lives
in :mod:`uwbimu.cli.check`.

Range residuals
---------------
``residual = measured range - predicted range`` [m], where the prediction is
``|| p_anchor - (p(t) + R(q(t)) p_IU) ||`` with the ground-truth pose of the
IMU frame interpolated at the range stamp ``t`` (linear in position, slerp in
attitude) and the lever arm ``p_IU`` from ``dataset.yaml``.  Ground truth is on
the UWB clock (dataset format), so the IMU/UWB time offset ``t_d`` does *not*
enter this prediction; :attr:`CheckOptions.gt_time_shift` exists for ground
truth recorded on yet another clock.

Anchor flags
------------
* ``moved``: refitting the anchor position by robust least squares on its
  ranges and the ground-truth antenna positions moves it by more than
  ``move_threshold`` and shrinks the residual score by ``improve_ratio``.
* ``swapped`` / ``wrong_id``: the ranges of anchor A are explained much better
  by the surveyed position of anchor B (both ways: swapped ids).
* ``bias``: a large median residual that neither of the above explains.

The residual *score* of a set of residuals is ``sqrt(median^2 + sigma_r^2)``
with ``sigma_r = 1.4826 MAD``: a robust RMS that counts bias and spread.
"""

from __future__ import annotations

from uwbimu.errors import InputError
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field
from scipy.optimize import least_squares

from uwbimu.io.dataset import Dataset, DatasetMeta
from uwbimu.models.quaternion import quat_normalize, quat_rotate, quat_slerp

__all__ = [
    "CheckOptions",
    "AnchorFlag",
    "CheckResult",
    "stream_summary",
    "anchor_summary",
    "lever_arm_for",
    "interpolate_pose",
    "antenna_track",
    "range_residuals",
    "residual_stats",
    "residual_score",
    "diagnose_anchors",
    "check_dataset",
]

MAD_TO_SIGMA = 1.4826


class CheckOptions(BaseModel):
    """Thresholds of :func:`check_dataset` (SI units)."""

    model_config = ConfigDict(extra="forbid")

    gap_factor: float = Field(default=5.0, gt=1, description="a gap is a time step > gap_factor x median step")
    gt_max_gap: float = Field(default=0.5, gt=0, description="ranges whose ground-truth bracket is longer "
                              "than this [s] are not compared")
    gt_time_shift: float = Field(default=0.0, description="ground truth at UWB time t is read at t + shift [s]")
    move_threshold: float = Field(default=0.3, gt=0, description="flag an anchor whose refit moves it > this [m]")
    improve_ratio: float = Field(default=0.5, gt=0, lt=1, description="... and whose score shrinks below "
                                 "this fraction")
    swap_ratio: float = Field(default=0.5, gt=0, lt=1, description="another anchor's position explains the "
                              "ranges with a score below this fraction of the own score")
    min_bad_score: float = Field(default=0.15, gt=0, description="anchors with a residual score below this [m] "
                                 "are never flagged")
    bias_threshold: float = Field(default=0.3, gt=0, description="flag |median residual| above this [m]")
    min_ranges: int = Field(default=10, ge=4, description="anchors (TDoA pairs) with fewer compared ranges "
                            "(TDoA rows) are not diagnosed")
    tdoa_outlier: float = Field(default=1.0, gt=0, description="a TDoA residual further than this from its "
                                "pair's median is an outlier [m]")
    tdoa_max_outlier_fraction: float = Field(default=0.1, gt=0, lt=1, description="flag a TDoA pair with "
                                             "more outliers than this fraction")


@dataclass
class AnchorFlag:
    """A suspicious anchor found by :func:`diagnose_anchors`."""

    anchor: str
    kind: str  # "moved" | "swapped" | "wrong_id" | "bias"
    message: str
    details: dict = field(default_factory=dict)


@dataclass
class CheckResult:
    """Everything ``uwbimu check`` computes."""

    streams: pd.DataFrame
    anchors: pd.DataFrame
    lever_arm: Optional[np.ndarray] = None
    lever_arm_source: str = ""
    residuals: Optional[pd.DataFrame] = None  # per range
    residual_table: Optional[pd.DataFrame] = None  # per anchor (stats + refit)
    flags: list[AnchorFlag] = field(default_factory=list)
    n_compared: int = 0
    n_outside_truth: int = 0
    notes: list[str] = field(default_factory=list)
    # TDoA (tdoa.csv): per unordered pair, see uwbimu.io.check_tdoa
    tdoa_pairs: Optional[pd.DataFrame] = None  # rows, rate, gaps per pair
    tdoa_residuals: Optional[pd.DataFrame] = None  # per TDoA row
    tdoa_table: Optional[pd.DataFrame] = None  # per pair residual stats
    tdoa_offsets: Optional[pd.Series] = None  # per-anchor offsets fitted to the pair medians [m]
    n_tdoa_compared: int = 0
    n_tdoa_outside_truth: int = 0


# ---------------------------------------------------------------------------
# Stream statistics
# ---------------------------------------------------------------------------
def _time_stats(t: np.ndarray, gap_factor: float) -> dict:
    t = np.asarray(t, float)
    n = len(t)
    out = {"samples": n, "t_start": float(t[0]) if n else np.nan, "t_end": float(t[-1]) if n else np.nan}
    out["duration"] = out["t_end"] - out["t_start"] if n else 0.0
    ut = np.unique(t)
    if len(ut) > 1:
        dt = np.diff(ut)
        med = float(np.median(dt))
        out["rate_hz"] = (n - 1) / out["duration"] if out["duration"] > 0 else np.nan
        out["median_dt"] = med
        out["max_gap"] = float(dt.max())
        out["n_gaps"] = int(np.sum(dt > gap_factor * med))
    else:
        out.update(rate_hz=np.nan, median_dt=np.nan, max_gap=np.nan, n_gaps=0)
    return out


def stream_summary(ds: Dataset, gap_factor: float = 5.0) -> pd.DataFrame:
    """Per stream (imu, uwb, tdoa, groundtruth): samples, start, end, duration [s], rate [Hz], gaps.

    For UWB and TDoA, ``rate_hz`` counts rows (several may share a stamp) while
    ``median_dt``/``max_gap``/``n_gaps`` use the distinct stamps.  A gap is a
    step longer than ``gap_factor`` times the median step.  The ``uwb`` row is
    left out when a TDoA-only dataset has no ranges.
    """
    rows = {"imu": _time_stats(ds.imu["t"].to_numpy(), gap_factor)}
    if len(ds.uwb) or ds.tdoa is None:
        rows["uwb"] = _time_stats(ds.uwb["t"].to_numpy(), gap_factor)
    if ds.tdoa is not None:
        rows["tdoa"] = _time_stats(ds.tdoa["t"].to_numpy(), gap_factor)
    if ds.groundtruth is not None:
        rows["groundtruth"] = _time_stats(ds.groundtruth["t"].to_numpy(), gap_factor)
    return pd.DataFrame.from_dict(rows, orient="index").rename_axis("stream")


def anchor_summary(ds: Dataset, gap_factor: float = 5.0) -> pd.DataFrame:
    """Per anchor: position, number of ranges, rate [Hz], min/median/max range [m], max gap [s]
    and ``tdoa``, the number of TDoA rows it takes part in (0 without ``tdoa.csv``)."""
    from uwbimu.io.check_tdoa import tdoa_participation  # check_tdoa builds on this module

    dur = float(ds.uwb["t"].max() - ds.uwb["t"].min()) if len(ds.uwb) > 1 else np.nan
    rows = []
    for r in ds.anchors.itertuples(index=False):
        sel = ds.uwb[ds.uwb["anchor"] == str(r.anchor)]
        t = sel["t"].to_numpy()
        rng = sel["range"].to_numpy()
        rows.append({
            "anchor": str(r.anchor), "x": r.x, "y": r.y, "z": r.z, "ranges": len(sel),
            "rate_hz": len(sel) / dur if dur and dur > 0 else np.nan,
            "range_min": float(rng.min()) if len(rng) else np.nan,
            "range_median": float(np.median(rng)) if len(rng) else np.nan,
            "range_max": float(rng.max()) if len(rng) else np.nan,
            "max_gap": float(np.diff(t).max()) if len(t) > 1 else np.nan,
        })
    df = pd.DataFrame(rows).set_index("anchor")
    df["tdoa"] = tdoa_participation(ds).reindex(df.index, fill_value=0)
    return df.sort_index(key=_natural_key)


# ---------------------------------------------------------------------------
# Ground truth interpolation and predicted ranges
# ---------------------------------------------------------------------------
def lever_arm_for(meta: DatasetMeta, tag: Optional[str] = None) -> tuple[np.ndarray, str]:
    """Lever arm ``p_IU`` (IMU frame, m) to predict ranges, and where it came from.

    Order: ``truth.tags[tag]``, ``truth.lever_arm``, the tag's (else the first
    tag's) nominal ``lever_arm``, else zero.
    """
    truth = meta.truth
    if tag is not None and truth is not None and truth.tags and tag in truth.tags:
        return np.asarray(truth.tags[tag], float), f"truth.tags.{tag}"
    if truth is not None and truth.lever_arm is not None:
        return np.asarray(truth.lever_arm, float), "truth.lever_arm"
    tags = meta.tags or []
    for tm in tags:
        if tag is not None and tm.name == tag and tm.lever_arm is not None:
            return np.asarray(tm.lever_arm, float), f"tags[{tm.name}].lever_arm"
    if tags and tags[0].lever_arm is not None:
        return np.asarray(tags[0].lever_arm, float), f"tags[0].lever_arm ({tags[0].name})"
    return np.zeros(3), "zero (no lever arm in dataset.yaml)"


def interpolate_pose(gt: pd.DataFrame, t: np.ndarray, max_gap: float = np.inf
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ground-truth pose at times ``t`` (same clock as ``gt['t']``).

    Returns ``(p (N,3), q (N,4), valid (N,))``: linear interpolation of the
    position, slerp of the attitude ``[qw,qx,qy,qz]``; ``valid`` is false
    outside the ground-truth span or where the bracketing samples are more than
    ``max_gap`` seconds apart (those rows hold NaN).
    """
    t = np.asarray(t, float)
    tg = gt["t"].to_numpy(float)
    P = gt[["px", "py", "pz"]].to_numpy(float)
    n = len(t)
    if not all(c in gt.columns for c in ("qw", "qx", "qy", "qz")):
        raise InputError("the ground truth has no attitude (qw, qx, qy, qz): the antenna pose cannot be interpolated")
    Q = gt[["qw", "qx", "qy", "qz"]].to_numpy(float)
    p = np.full((n, 3), np.nan)
    q = np.full((n, 4), np.nan)
    if len(tg) < 2:
        return p, q, np.zeros(n, bool)
    i = np.clip(np.searchsorted(tg, t, side="right") - 1, 0, len(tg) - 2)
    t0, t1 = tg[i], tg[i + 1]
    valid = (t >= tg[0]) & (t <= tg[-1]) & ((t1 - t0) <= max_gap)
    a = np.where(valid, (t - t0) / np.where(t1 > t0, t1 - t0, 1.0), 0.0)
    k = np.flatnonzero(valid)
    if len(k):
        ik, ak = i[k], a[k]
        p[k] = P[ik] + ak[:, None] * (P[ik + 1] - P[ik])
        q[k] = quat_normalize(quat_slerp(Q[ik], Q[ik + 1], ak))
    return p, q, valid


def antenna_track(ds: Dataset, table: pd.DataFrame, lever_arm: Optional[np.ndarray] = None,
                  gt_time_shift: float = 0.0, max_gap: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """World antenna position from the ground truth at the stamps of a measurement table.

    Parameters
    ----------
    ds : dataset with ground truth.
    table : ``ds.uwb`` or ``ds.tdoa`` (column ``t`` [+ ``tag``]).
    lever_arm : (3,) ``p_IU`` [m]; default from ``ds.meta`` per tag (:func:`lever_arm_for`).
    gt_time_shift : the ground truth is read at ``t + gt_time_shift`` [s].
    max_gap : stamps whose ground-truth bracket is longer than this [s] are not covered.

    Returns
    -------
    ``(k, ant)``: the row positions covered by ground truth and the (len(k), 3)
    antenna positions ``p(t) + R(q(t)) p_IU`` there.
    """
    if ds.groundtruth is None:
        raise InputError("residuals against ground truth need ground truth (groundtruth.csv)")
    t = table["t"].to_numpy(float)
    p, q, valid = interpolate_pose(ds.groundtruth, t + gt_time_shift, max_gap)
    if lever_arm is not None:
        lev = np.tile(np.asarray(lever_arm, float), (len(t), 1))
    elif "tag" in table.columns:
        lev = np.zeros((len(t), 3))
        for tag in pd.unique(table["tag"]):
            lev[(table["tag"] == tag).to_numpy()] = lever_arm_for(ds.meta, str(tag))[0]
    else:
        lev = np.tile(lever_arm_for(ds.meta)[0], (len(t), 1))
    k = np.flatnonzero(valid)
    return k, p[k] + quat_rotate(q[k], lev[k])


def range_residuals(ds: Dataset, lever_arm: Optional[np.ndarray] = None, gt_time_shift: float = 0.0,
                    max_gap: float = 0.5) -> pd.DataFrame:
    """Measured minus predicted range for every range covered by ground truth.

    Parameters
    ----------
    ds : dataset with ground truth.
    lever_arm : (3,) ``p_IU`` in the IMU frame [m]; default from ``ds.meta``
        (per tag when ``uwb`` has a ``tag`` column), see :func:`lever_arm_for`.
    gt_time_shift : the ground truth is read at ``t + gt_time_shift`` [s].
    max_gap : ranges whose ground-truth bracket is longer than this are skipped.

    Returns
    -------
    DataFrame with ``t, anchor, range, predicted, residual, ux, uy, uz`` (world
    antenna position) [+ ``tag``], only for compared ranges; ``attrs['n_outside']``
    counts the ranges that could not be compared.
    """
    uwb = ds.uwb
    k, ant = antenna_track(ds, uwb, lever_arm, gt_time_shift, max_gap)
    pos = ds.anchor_positions()
    A = np.array([pos[a] for a in uwb["anchor"].to_numpy()[k]]).reshape(-1, 3)
    pred = np.linalg.norm(A - ant, axis=1)
    out = pd.DataFrame({"t": uwb["t"].to_numpy(float)[k], "anchor": uwb["anchor"].to_numpy()[k],
                        "range": uwb["range"].to_numpy(float)[k], "predicted": pred})
    out["residual"] = out["range"] - out["predicted"]
    out[["ux", "uy", "uz"]] = ant
    if "tag" in uwb.columns:
        out["tag"] = uwb["tag"].to_numpy()[k]
    out.attrs["n_outside"] = int(len(uwb) - len(k))
    return out


def residual_score(res: np.ndarray) -> float:
    """Robust RMS ``sqrt(median^2 + (1.4826 MAD)^2)`` of residuals [m]."""
    res = np.asarray(res, float)
    if len(res) == 0:
        return np.nan
    med = np.median(res)
    mad = np.median(np.abs(res - med))
    return float(np.hypot(med, MAD_TO_SIGMA * mad))


def residual_stats(res: pd.DataFrame) -> pd.DataFrame:
    """Per anchor: n, median, MAD, robust sigma (1.4826 MAD), mean, RMS, p95 |residual| [m]."""
    rows = []
    for a, g in res.groupby("anchor", sort=False):
        r = g["residual"].to_numpy()
        med = float(np.median(r))
        mad = float(np.median(np.abs(r - med)))
        rows.append({"anchor": str(a), "n": len(r), "median": med, "mad": mad,
                     "robust_sigma": MAD_TO_SIGMA * mad, "mean": float(r.mean()),
                     "rms": float(np.sqrt(np.mean(r ** 2))), "p95_abs": float(np.percentile(np.abs(r), 95))})
    df = pd.DataFrame(rows, columns=["anchor", "n", "median", "mad", "robust_sigma", "mean", "rms", "p95_abs"])
    return df.set_index("anchor").sort_index(key=_natural_key)


def _id_key(s) -> tuple:
    """Sort key of one anchor id: "2" before "10", text ids after the numbers."""
    return (0, int(s), "") if str(s).isdigit() else (1, 0, str(s))


def _natural_key(index: pd.Index) -> pd.Index:
    return pd.Index([_id_key(s) for s in index])


# ---------------------------------------------------------------------------
# Anchor diagnosis
# ---------------------------------------------------------------------------
def _fit_anchor(U: np.ndarray, r: np.ndarray, a0: np.ndarray, scale: float) -> np.ndarray:
    """Robust LSQ anchor position from antenna positions ``U`` (N,3) and ranges ``r``."""
    def fun(a):
        return np.linalg.norm(U - a, axis=1) - r

    def jac(a):
        d = a - U
        n = np.linalg.norm(d, axis=1, keepdims=True)
        return d / np.maximum(n, 1e-9)

    sol = least_squares(fun, a0, jac=jac, loss="soft_l1", f_scale=scale, x_scale=1.0, max_nfev=200)
    return sol.x


def diagnose_anchors(res: pd.DataFrame, ds: Dataset, options: Optional[CheckOptions] = None
                     ) -> tuple[pd.DataFrame, list[AnchorFlag]]:
    """Refit each anchor and cross-test anchor ids; return the per-anchor table and flags.

    Returns
    -------
    table : :func:`residual_stats` plus ``score`` (own residual score, m),
        ``fit_x/y/z`` (refitted position, m), ``fit_shift`` (m), ``fit_score`` (m),
        ``best_other`` (the other anchor whose position explains the ranges best)
        and ``other_score`` (m).
    flags : list of :class:`AnchorFlag`.
    """
    options = options or CheckOptions()
    table = residual_stats(res)
    pos = ds.anchor_positions()
    ids = list(table.index)
    all_ids = list(pos)
    cols = {c: [] for c in ("score", "fit_x", "fit_y", "fit_z", "fit_shift", "fit_score",
                            "best_other", "other_score")}
    per_anchor = {}
    for a in ids:
        g = res[res["anchor"] == a]
        U = g[["ux", "uy", "uz"]].to_numpy()
        r = g["range"].to_numpy()
        own = residual_score(g["residual"].to_numpy())
        cols["score"].append(own)
        if len(g) < options.min_ranges:
            for c in ("fit_x", "fit_y", "fit_z", "fit_shift", "fit_score", "other_score"):
                cols[c].append(np.nan)
            cols["best_other"].append("")
            continue
        scale = max(2.0 * MAD_TO_SIGMA * float(table.loc[a, "mad"]), 0.05)
        fit = _fit_anchor(U, r, pos[a], scale)
        fit_score = residual_score(r - np.linalg.norm(U - fit, axis=1))
        best, best_score = "", np.inf
        for b in all_ids:
            if b == a:
                continue
            s = residual_score(r - np.linalg.norm(U - pos[b], axis=1))
            if s < best_score:
                best, best_score = b, s
        for c, v in zip(("fit_x", "fit_y", "fit_z"), fit):
            cols[c].append(float(v))
        cols["fit_shift"].append(float(np.linalg.norm(fit - pos[a])))
        cols["fit_score"].append(fit_score)
        cols["best_other"].append(best)
        cols["other_score"].append(best_score if best else np.nan)
        per_anchor[a] = (own, best, best_score)
    for c, v in cols.items():
        table[c] = v

    flags: list[AnchorFlag] = []
    wrong_id: dict[str, str] = {}
    for a, (own, best, best_score) in per_anchor.items():
        if best and own > options.min_bad_score and best_score < options.swap_ratio * own:
            wrong_id[a] = best
    reported = set()
    for a, b in wrong_id.items():
        if a in reported:
            continue
        if wrong_id.get(b) == a:
            msg = (f"anchors {a} and {b} look swapped: the ranges of {a} fit the position of {b} "
                   f"(score {table.loc[a, 'other_score']:.3f} m vs {table.loc[a, 'score']:.3f} m) and the "
                   f"ranges of {b} fit the position of {a} (score {table.loc[b, 'other_score']:.3f} m vs "
                   f"{table.loc[b, 'score']:.3f} m)")
            for x, y in ((a, b), (b, a)):
                flags.append(AnchorFlag(x, "swapped", msg, {"other": y, "score": float(table.loc[x, "score"]),
                                                            "other_score": float(table.loc[x, "other_score"])}))
            reported |= {a, b}
        else:
            msg = (f"anchor {a}: its ranges fit the position of anchor {b} (score "
                   f"{table.loc[a, 'other_score']:.3f} m vs {table.loc[a, 'score']:.3f} m with its own): "
                   f"wrong id?")
            flags.append(AnchorFlag(a, "wrong_id", msg, {"other": b, "score": float(table.loc[a, "score"]),
                                                         "other_score": float(table.loc[a, "other_score"])}))
            reported.add(a)
    for a in per_anchor:
        if a in reported:
            continue
        row = table.loc[a]
        if (row["score"] > options.min_bad_score and row["fit_shift"] > options.move_threshold
                and row["fit_score"] < options.improve_ratio * row["score"]):
            fit = [round(float(row[c]), 3) for c in ("fit_x", "fit_y", "fit_z")]
            msg = (f"anchor {a} looks misplaced: its ranges fit a position {row['fit_shift']:.2f} m away "
                   f"({fit[0]:.3f}, {fit[1]:.3f}, {fit[2]:.3f}) with score {row['fit_score']:.3f} m "
                   f"instead of {row['score']:.3f} m at the surveyed position")
            # A constant range offset is explained about as well when the ranges
            # come from a narrow cone of directions: say so rather than guess.
            bias_score = MAD_TO_SIGMA * float(row["mad"])
            bias_too = bias_score < 1.5 * float(row["fit_score"])
            if bias_too:
                msg += (f"; a constant range bias of {row['median']:+.3f} m explains the ranges about as well "
                        f"(score {bias_score:.3f} m): check the survey and the antenna delay")
            flags.append(AnchorFlag(a, "moved", msg, {"fitted": fit, "shift": float(row["fit_shift"]),
                                                      "score": float(row["score"]),
                                                      "fit_score": float(row["fit_score"]),
                                                      "bias_explains_too": bool(bias_too)}))
            reported.add(a)
    for a in per_anchor:
        if a in reported:
            continue
        med = float(table.loc[a, "median"])
        if abs(med) > options.bias_threshold:
            flags.append(AnchorFlag(a, "bias", f"anchor {a}: median range residual {med:+.3f} m "
                                    f"(constant range bias or a wrong lever arm?)", {"median": med}))
    return table, flags


def check_dataset(ds: Dataset, options: Optional[CheckOptions] = None,
                  progress: Optional[Callable[[str, float], None]] = None) -> CheckResult:
    """Stream/anchor/TDoA-pair statistics and, with ground truth, range and TDoA residuals and flags.

    ``progress(stage, fraction)``, when given, is called as each stage starts
    (fraction in [0, 1]) and with ``("done", 1.0)`` at the end; the CLI draws
    its progress bar from it.
    """
    from uwbimu.io.check_tdoa import diagnose_tdoa, tdoa_pair_summary, tdoa_residuals  # builds on this module

    options = options or CheckOptions()
    report = progress or (lambda stage, frac: None)
    report("stream statistics", 0.0)
    result = CheckResult(streams=stream_summary(ds, options.gap_factor),
                         anchors=anchor_summary(ds, options.gap_factor))
    has_tdoa = ds.tdoa is not None and len(ds.tdoa) > 0
    if has_tdoa:
        result.tdoa_pairs = tdoa_pair_summary(ds, options.gap_factor)
    unused = [a for a, r in result.anchors.iterrows() if r["ranges"] == 0 and r["tdoa"] == 0]
    if unused:
        result.notes.append(f"anchors without any range{' or TDoA' if ds.tdoa is not None else ''}: "
                            f"{', '.join(unused)}")
    tagged = [t for t in (ds.uwb, ds.tdoa) if t is not None and "tag" in t.columns and len(t)]
    if tagged:
        named = {t.name for t in ds.meta.tags}
        unnamed = sorted(set().union(*(set(t["tag"]) for t in tagged)) - named)
        if unnamed:
            result.notes.append(f"tag(s) {', '.join(unnamed)} in uwb/tdoa have no entry in dataset.yaml tags "
                                f"(no nominal lever arm)")
    if ds.groundtruth is None:
        result.notes.append("no ground truth: range and TDoA residuals not computed")
        report("done", 1.0)
        return result
    if not all(c in ds.groundtruth.columns for c in ("qw", "qx", "qy", "qz")):
        # position-only ground truth: the antenna (p + R l) cannot be placed; the loader warned already
        result.notes.append("ground truth without attitude (qw, qx, qy, qz): range and TDoA residuals against it "
                            "not computed")
        report("done", 1.0)
        return result
    gt_frame = str((ds.meta.extra or {}).get("groundtruth_align", "none"))
    if gt_frame != "none":
        # Ground truth in another frame (e.g. a Vive tracker): predicting ranges from it would
        # flag every anchor as moved or swapped.  Say so instead of comparing.
        result.notes.append(f"ground truth is in another frame (dataset.yaml extra.groundtruth_align: {gt_frame}): "
                            "range and TDoA residuals against it not computed")
        report("done", 1.0)
        return result
    tags = pd.concat([t["tag"] for t in tagged]).unique() if tagged else []
    if len(tags) > 1:
        result.lever_arm, result.lever_arm_source = None, "per tag (dataset.yaml)"
    else:
        result.lever_arm, result.lever_arm_source = lever_arm_for(ds.meta, str(tags[0]) if len(tags) else None)
    if len(ds.uwb):
        report("range residuals", 0.2)
        res = _compared(range_residuals(ds, result.lever_arm, options.gt_time_shift, options.gt_max_gap),
                        "ranges", options, result.notes)
        result.residuals, result.n_compared, result.n_outside_truth = res, len(res), res.attrs["n_outside"]
        if len(res):
            report("anchor refit and id cross-check", 0.4)
            result.residual_table, result.flags = diagnose_anchors(res, ds, options)
    if has_tdoa:
        report("TDoA residuals", 0.7)
        tres = _compared(tdoa_residuals(ds, result.lever_arm, options.gt_time_shift, options.gt_max_gap),
                         "TDoA rows", options, result.notes)
        result.tdoa_residuals, result.n_tdoa_compared, result.n_tdoa_outside_truth = (
            tres, len(tres), tres.attrs["n_outside"])
        if len(tres):
            result.tdoa_table, result.tdoa_offsets, tflags = diagnose_tdoa(tres, ds, options)
            result.flags.extend(tflags)
    report("done", 1.0)
    return result


def _compared(res: pd.DataFrame, what: str, options: CheckOptions, notes: list[str]) -> pd.DataFrame:
    """``res`` (range or TDoA residuals); a note on ``notes`` counts the rows ground truth did not cover."""
    n = int(res.attrs.get("n_outside", 0))
    res.attrs["n_outside"] = n
    if n:
        notes.append(f"{n} {what} lie outside the ground truth (or in gaps > {options.gt_max_gap} s) and were "
                     "not compared")
    return res
