"""Files written for an estimation run (``uwbimu estimate DATASET --out OUT``).

* ``trajectory.csv``: ``t, px, py, pz, qw, qx, qy, qz, vx, vy, vz`` and the
  standard deviations ``sd_px .. sd_vz, sd_thx .. sd_thz`` (UWB clock, pose of
  the IMU frame; attitude sd of the body-frame error, rad);
* ``states.csv``: every output with the full state and the 19 sd (biases,
  lever arm, time offset over time);
* ``run.json``: ``imu_samples``, ``ranges``, ``filter_cpu_seconds``, ``total_cpu_seconds``.
* ``calibration.yaml``: calibration values and sd in the one schema of
  :mod:`uwbimu.io.calibration_file` (``time_offset`` a mapping ``value, sd, unit, mode,
  verdict``), the configuration, the uwbimu version, the warnings;
* ``residuals.csv``: ``t, anchor, range, predicted, innovation, nis, accepted`` (+ ``kind, anchor_b`` with TDoA);
  innovation = measured − predicted;
* ``residual_table.csv``: per anchor (ranges) and per anchor pair (TDoA, column ``pair``), natural anchor order;
* ``events.yaml``: the machine-readable event log;
* with ground truth: ``metrics.yaml`` and PNG plots (trajectory, position
  errors with +/-3 sigma, lever arm and time offset with +/-3 sigma bands,
  NIS histogram against chi-square(1)).

Everything is written atomically; works for any :class:`EstimationResult`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Optional

import numpy as np
import pandas as pd

import uwbimu
from uwbimu.io import atomic
from uwbimu.formatting import natural_key
from uwbimu.io import calibration_file as CF
from uwbimu.io.dataset import Dataset
from uwbimu.models.state import ERROR_STATE_NAMES, NOMINAL_STATE_NAMES
from uwbimu.models import state as S
from uwbimu.models.blocks import CALIBRATION_BLOCKS, OUTPUT_ORDER

def fixed_components(layout: S.StateLayout, opts) -> np.ndarray:
    """(N,) True for the error components of blocks whose declared ``mode_option`` is ``fixed``."""
    fixed = np.zeros(layout.n_err, dtype=bool)
    for b in layout.blocks:
        if b.mode_option is not None and _option(opts, b.mode_option).mode == "fixed":
            fixed[layout.err(b.name)] = True
    return fixed


def _option(opts, path: str):
    v = opts
    for part in path.split("."):
        v = getattr(v, part)
    return v


def block_calibration(layout: S.StateLayout, x: np.ndarray, sd: np.ndarray, opts, anchor_ids,
                      pair_index: Optional[dict] = None, tags: Optional[dict] = None) -> dict[str, Any]:
    """The calibration outputs of a final filter state, one entry per declared block with an ``output_key``.

    Parameters
    ----------
    layout : the run's :class:`~uwbimu.models.state.StateLayout`.
    x, sd : the final extended nominal state and the error-state standard deviations (N,).
    opts : the run's :class:`~uwbimu.estimation.options.EskfOptions` (modes, correlation times).
    anchor_ids : labels of the per-anchor instances; ``pair_index`` ``(a, b) -> error index`` of the
        per-pair instances (labels ``"<id_a>-<id_b>"``).
    tags : written after the blocks that are ``"one"`` (the per-tag lever arms), when given.

    Returns
    -------
    dict with ``<key>`` (float, list, or a dict per anchor / pair) and ``<key>_sd`` (0 for a fixed block),
    ``<key>_mode`` when the block's mode may be other than ``estimate``, ``<key>_correlation_time`` for a
    Gauss-Markov block that has one; in :data:`uwbimu.models.blocks.OUTPUT_ORDER` (other declared blocks
    after those).
    """
    fixed = fixed_components(layout, opts)
    out: dict[str, Any] = {}
    decl = [b for b in layout.blocks if b.output_key]
    rank = {n: i for i, n in enumerate(OUTPUT_ORDER)}  # blocks not listed there come last, in state order
    order = sorted(decl, key=lambda b: rank.get(b.name, len(rank)))
    for i, b in enumerate(order):
        if tags is not None and b.multiplicity != "one" and (i == 0 or order[i - 1].multiplicity == "one"):
            out["tags"] = tags
        key, en, nm = b.output_key, layout.err(b.name), layout.nom(b.name)
        sd_b = np.where(fixed[en], 0.0, sd[en])
        if b.multiplicity == "per_anchor":
            out[key] = {a: float(x[nm][i]) for i, a in enumerate(anchor_ids)}
            out[key + "_sd"] = {a: float(sd[en][i]) for i, a in enumerate(anchor_ids)}
        elif b.multiplicity == "per_pair":
            labels = {i_: f"{anchor_ids[a_]}-{anchor_ids[b_]}" for (a_, b_), i_ in (pair_index or {}).items()}
            out[key] = {lab: float(x[i_ + S.NOM_SHIFT]) for i_, lab in labels.items()}
            out[key + "_sd"] = {lab: float(sd[i_]) for i_, lab in labels.items()}
        elif b.size == 1:
            out[key], out[key + "_sd"] = float(x[nm][0]), float(sd_b[0])
        else:
            out[key], out[key + "_sd"] = [float(v) for v in x[nm]], [float(v) for v in sd_b]
        modes = b.enabled_by[1] if b.enabled_by is not None else ("estimate", "consider", "fixed")
        if b.mode_option is not None and set(modes) != {"estimate"}:
            out[key + "_mode"] = _option(opts, b.mode_option).mode
        if b.process_noise == "gauss_markov" and _option(opts, b.noise_option[1]):
            # Gauss-Markov states vary in time: the values above are the last ones
            out[key + "_correlation_time"] = float(_option(opts, b.noise_option[1]))
    if tags is not None and "tags" not in out:
        out["tags"] = tags
    return out


TRAJ_COLUMNS = ["t", "px", "py", "pz", "qw", "qx", "qy", "qz", "vx", "vy", "vz"]
TRAJ_SD = ["sd_px", "sd_py", "sd_pz", "sd_vx", "sd_vy", "sd_vz", "sd_thx", "sd_thy", "sd_thz"]
RESIDUAL_COLUMNS = ["t", "anchor", "range", "predicted", "innovation", "nis", "accepted"]


def trajectory_frame(result) -> pd.DataFrame:
    """``trajectory.csv`` as a DataFrame."""
    X = result.states
    # one construction from a dict of columns (not a frame grown a column at a time)
    cols = {"t": result.t}
    cols.update({c: X[:, i] for i, c in enumerate(["px", "py", "pz"])})
    cols.update({c: X[:, 6 + i] for i, c in enumerate(["qw", "qx", "qy", "qz"])})
    cols.update({c: X[:, 3 + i] for i, c in enumerate(["vx", "vy", "vz"])})
    cols.update({c: result.sd[:, i] for i, c in enumerate(TRAJ_SD)})
    return pd.DataFrame(cols)


def states_frame(result) -> pd.DataFrame:
    """Full state and error-state sd at every output (``states.csv``)."""
    cols = {"t": result.t}
    if result.t_imu is not None:
        cols["t_imu"] = result.t_imu
    cols.update({c: result.states[:, i] for i, c in enumerate(NOMINAL_STATE_NAMES)})
    cols.update({f"sd_{c}": result.sd[:, i] for i, c in enumerate(ERROR_STATE_NAMES)})
    return pd.DataFrame(cols)


def residual_table(result) -> pd.DataFrame:
    """Per-anchor residual statistics: count, accepted, rejected %, median, MAD of innovations [m].

    Innovation = measured − predicted. Range rows are grouped by ``anchor``; TDoA rows (``kind == "tdoa"``) by
    their ``pair`` ``"a-b"`` (column ``pair``; ``anchor`` is empty for them), ranges first, each in natural order
    (1, 2, ..., 10).
    """
    r = result.residuals
    kind = r["kind"].astype(str).to_numpy() if "kind" in r.columns else np.full(len(r), "range")
    is_td = kind == "tdoa"
    key = r["anchor"].astype(str).to_numpy().astype(object)
    if is_td.any():
        b = r["anchor_b"].astype(str).to_numpy() if "anchor_b" in r.columns else np.full(len(r), "?")
        key[is_td] = [f"{a}-{bb}" for a, bb in zip(key[is_td], b[is_td])]
    rows = []
    for tdoa in (False, True):
        sel = is_td == tdoa
        if not sel.any():
            continue
        g_all = r[sel]
        keys = key[sel]
        for k in sorted(set(keys), key=natural_key):
            g = g_all[keys == k]
            inn = g["innovation"].to_numpy(float)
            proc = np.isfinite(inn)
            acc = g["accepted"].to_numpy(bool)
            med = float(np.median(inn[proc])) if proc.any() else math.nan
            mad = float(np.median(np.abs(inn[proc] - med))) if proc.any() else math.nan
            rows.append({
                "kind": "tdoa" if tdoa else "range", "anchor": "" if tdoa else str(k), "pair": str(k) if tdoa else "",
                "ranges": int(len(g)), "processed": int(proc.sum()), "accepted": int(acc.sum()),
                "rejected_pct": float(100.0 * (proc & ~acc).sum() / max(proc.sum(), 1)),
                "median": med, "mad": mad,
            })
    cols = ["anchor", "ranges", "processed", "accepted", "rejected_pct", "median", "mad"]
    if is_td.any():
        cols = ["kind", "anchor", "pair"] + cols[1:]
    return pd.DataFrame(rows, columns=cols)


def effective_time_offset_mode(result) -> tuple[str, str]:
    """``(mode, configured_mode)`` of the time offset: the run's events decide
    (:func:`uwbimu.io.calibration_file.effective_time_offset_mode`: a ``time_offset_held`` event means consider mode
    whatever the options asked)."""
    return CF.effective_time_offset_mode(result.calibration.get("time_offset_mode", "estimate"), result.events)


def calibration_document(result) -> dict[str, Any]:
    """``result.calibration`` in the one schema of calibration.yaml (:mod:`uwbimu.io.calibration_file`).

    The numbers are the estimator's; the time offset becomes the mapping ``value, sd, unit, mode, verdict``
    (``mode`` from :func:`effective_time_offset_mode`), a NaN sigma becomes null.
    """
    cal = dict(_plain(result.calibration))
    if isinstance(cal.get("time_offset"), dict):
        return CF.migrate(cal)
    mode, configured = effective_time_offset_mode(result)
    cal["time_offset_mode"], cal["configured"] = mode, configured
    out = {"schema_version": CF.SCHEMA_VERSION, **CF.migrate({k: v for k, v in cal.items() if k != "configured"})}
    if configured != mode:
        out["time_offset"]["configured_mode"] = configured
    return out


def _plain(obj: Any) -> Any:
    return atomic.to_plain(obj)  # NaN / inf -> None (YAML null)


def run_summary(result, dataset: Dataset) -> dict[str, Any]:
    """Contents of ``run.json``: data sizes and CPU time of the run.

    ``filter_cpu_seconds``: CPU time of the filter passes (initialisation excluded); ``total_cpu_seconds``:
    CPU time of the whole estimator call (problem set-up, initialisation, passes, assembly); both
    ``time.process_time`` of the estimating process [s], None when the estimator did not record them.
    """
    n_rng = len(dataset.uwb) + (len(dataset.tdoa) if getattr(dataset, "tdoa", None) is not None else 0)
    x = result.extra
    return {"estimator": result.estimator, "imu_samples": int(len(dataset.imu)), "ranges": int(n_rng),
            "filter_cpu_seconds": _plain(x.get("filter_cpu_seconds")),
            "total_cpu_seconds": _plain(x.get("total_cpu_seconds")),
            "wall_seconds": _plain(result.runtime_s),
            "imu_samples_per_filter_cpu_second": (float(len(dataset.imu) / x["filter_cpu_seconds"])
                                                  if x.get("filter_cpu_seconds") else None)}


def write_outputs(result, dataset: Dataset, out_dir: str | Path, plots: bool = True,
                  metrics: Optional[dict[str, Any]] = None) -> dict[str, Any]:
    """Write the files of an estimation run into ``out_dir`` (created if needed).

    Returns ``{"files": [paths], "residual_table": DataFrame, "metrics": dict or None}``.
    """
    from uwbimu.estimation.metrics import compute_metrics

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files: list[Path] = []
    fmt = "%.9g"
    files.append(atomic.write_csv(out / "trajectory.csv", trajectory_frame(result), float_format=fmt))
    files.append(atomic.write_csv(out / "states.csv", states_frame(result), float_format=fmt))
    # TDoA runs add ``kind`` (range | tdoa) and ``anchor_b``; range-only outputs keep the historical columns
    extra_cols = [c for c in ("kind", "anchor_b") if c in result.residuals.columns]
    res = result.residuals.reindex(columns=list(RESIDUAL_COLUMNS) + extra_cols)
    files.append(atomic.write_csv(out / "residuals.csv", res, float_format=fmt))
    calib = {
        **calibration_document(result),
        "estimator": result.estimator,
        "dataset": dataset.meta.name,
        "uwbimu_version": uwbimu.__version__,
        "runtime_s": _plain(result.runtime_s),
        "warnings": list(result.warnings),
        "config": _plain(result.config),
    }
    files.append(atomic.write_yaml(out / "calibration.yaml", calib))
    files.append(atomic.write_yaml(out / "events.yaml", _plain(result.events)))
    files.append(atomic.write_json(out / "run.json", run_summary(result, dataset)))
    table = residual_table(result)
    files.append(atomic.write_csv(out / "residual_table.csv", table, float_format="%.6g"))
    m = metrics
    if dataset.groundtruth is not None and len(dataset.groundtruth) > 1:
        if m is None:
            m = compute_metrics(result, dataset)
        files.append(atomic.write_yaml(out / "metrics.yaml", _plain(m)))
        if plots:
            files += _plots(result, dataset, out)
    return {"files": files, "residual_table": table, "metrics": m}


def _plots(result, dataset: Dataset, out: Path) -> list[Path]:
    """PNG plots against ground truth (object API: no global pyplot state)."""
    from matplotlib.figure import Figure
    from scipy.stats import chi2  # here, not at the top: scipy.stats costs ~0.7 s of every `uwbimu estimate`

    from uwbimu.estimation.metrics import truth_at

    files = []
    truth = dataset.meta.truth
    t_d_true = truth.time_offset if truth is not None else None
    tt = result.t_imu - t_d_true if (result.t_imu is not None and t_d_true is not None) else result.t
    p, q, v, valid = truth_at(dataset, tt)
    X, sd, t = result.states, result.sd, result.t
    anchors = dataset.anchors[["x", "y", "z"]].to_numpy(float)

    fig = Figure(figsize=(11, 5))
    ax = fig.add_subplot(1, 2, 1)
    ax.plot(p[valid, 0], p[valid, 1], "k-", lw=1, label="truth")
    ax.plot(X[:, 0], X[:, 1], "C0-", lw=0.8, label="ESKF")
    ax.plot(anchors[:, 0], anchors[:, 1], "r^", label="anchors")
    ax.set_xlabel("x [m]"); ax.set_ylabel("y [m]"); ax.set_aspect("equal", adjustable="datalim"); ax.legend()
    ax.set_title("trajectory (top view)")
    ax = fig.add_subplot(1, 2, 2)
    ax.plot(t[valid], p[valid, 2], "k-", lw=1, label="truth z")
    ax.plot(t, X[:, 2], "C0-", lw=0.8, label="ESKF z")
    ax.set_xlabel("t [s]"); ax.set_ylabel("z [m]"); ax.legend()
    files.append(atomic.save_figure(out / "trajectory.png", fig))

    fig = Figure(figsize=(10, 7))
    for i, c in enumerate("xyz"):
        ax = fig.add_subplot(3, 1, i + 1)
        e = X[:, i] - p[:, i]
        ax.plot(t[valid], e[valid], "C0-", lw=0.8, label=f"error {c}")
        ax.fill_between(t, -3 * sd[:, i], 3 * sd[:, i], color="C1", alpha=0.3, label="±3σ")
        ax.set_ylabel(f"{c} [m]")
        lim = np.nanpercentile(np.abs(e[valid]), 99) * 2 if valid.any() else 1.0
        ax.set_ylim(-max(lim, 1e-3), max(lim, 1e-3))
        if i == 0:
            ax.legend(loc="upper right")
            ax.set_title("position error with ±3σ")
    ax.set_xlabel("t [s]")
    files.append(atomic.save_figure(out / "position_error.png", fig))

    # one panel per component of each calibration block (lever arm x, y, z; time offset), truth dashed
    panels = [(b, i) for b in CALIBRATION_BLOCKS for i in range(b.size)]
    fig = Figure(figsize=(10, 2 * len(panels)))
    L = S.StateLayout()
    for n, (b, i) in enumerate(panels):
        ax = fig.add_subplot(len(panels), 1, n + 1)
        scale, unit = b.plot
        xi, si = X[:, L.nom(b.name).start + i] * scale, sd[:, L.err(b.name).start + i] * scale
        ax.plot(t, xi, "C0-", lw=0.8, label="estimate")
        ax.fill_between(t, xi - 3 * si, xi + 3 * si, color="C0", alpha=0.2, label="±3σ")
        true = getattr(truth, b.output_key, None) if truth is not None else None
        if true is not None:
            ax.axhline(scale * float(np.atleast_1d(true)[i]), color="k", ls="--", lw=1, label="truth")
        ax.set_ylabel(f"{b.output_names[i]} [{unit}]")
        if n == 0:
            ax.legend(loc="upper right")
            ax.set_title(" and ".join(b.label for b in CALIBRATION_BLOCKS))
    ax.set_xlabel("t [s]")
    files.append(atomic.save_figure(out / "calibration.png", fig))

    fig = Figure(figsize=(6, 4))
    ax = fig.add_subplot(1, 1, 1)
    nis = result.residuals["nis"].to_numpy(float)
    nis = nis[np.isfinite(nis)]
    if len(nis):
        hi = max(float(np.percentile(nis, 99)), 8.0)
        bins = np.linspace(0, hi, 60)
        ax.hist(np.clip(nis, 0, hi), bins=bins, density=True, alpha=0.6, label="NIS")
        xs = np.linspace(bins[1] / 2, hi, 300)
        ax.plot(xs, chi2.pdf(xs, 1), "k-", label="χ²(1)")
        ax.set_yscale("log")
        ax.set_title(f"NIS (mean {np.mean(nis):.2f}, expected 1)")
        ax.legend()
    else:
        ax.set_title("NIS: no processed range")
    ax.set_xlabel("NIS")
    files.append(atomic.save_figure(out / "nis.png", fig))
    return files
