"""Repeatability of the calibration: split a log into K windows and calibrate each.

If the filter's uncertainty is honest, the K window estimates of the lever
arm and the time offset scatter about as much as the sigma the filter
reports for each window.  For each parameter we compute

* the spread (sample sd) of the K estimates and the RMS of their reported
  sigmas, and their ratio (≈ 1 when consistent);
* ``chi2 = Σ_k (x_k − x̄)² / σ_k²`` with ``x̄`` the inverse-variance weighted
  mean; for independent windows and honest sigmas it follows χ²(K − 1).
  A tiny p-value (spread ≫ sigma) means over-confidence — or a parameter
  that really changes between windows; a chi2 in the lower 1 % tail means
  the sigmas are conservative.

The estimator is a name of the estimator registry or any callable ``dataset -> result`` where ``result`` has a
``calibration`` dict (an :class:`~uwbimu.estimation.result.EstimationResult`)
or is that dict, with keys ``lever_arm``, ``lever_arm_sd``, ``time_offset``,
``time_offset_sd``; the CLI uses :func:`uwbimu.estimation.run_eskf`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Callable, Optional, Union

import numpy as np
from scipy.stats import chi2 as _chi2

from uwbimu.io.dataset import Dataset
from uwbimu.models.blocks import BLOCK, calibration_components

#: the calibration blocks' components (``lx, ly, lz, time_offset``: models.blocks output names)
PARAMS = tuple(calibration_components())


def split_windows(ds: Dataset, k: int, t_range: Optional[tuple[float, float]] = None) -> list[Dataset]:
    """Cut a dataset into ``k`` consecutive, non-overlapping, equal-length windows.

    Windows are cut on the IMU time span (IMU clock ≈ UWB clock up to the
    small time offset; a range near a window edge may fall just outside).

    Parameters
    ----------
    ds : the dataset.
    k : number of windows (>= 2).
    t_range : optional ``(t0, t1)`` [s] to split instead of the whole IMU span.

    Returns
    -------
    list of datasets sharing ``anchors`` and ``meta``.
    """
    if k < 2:
        raise ValueError(f"need at least 2 windows, got {k}")
    t_imu = ds.imu_t
    t0, t1 = t_range if t_range is not None else (float(t_imu[0]), float(t_imu[-1]))
    if not t1 > t0:
        raise ValueError(f"empty time range {t0}..{t1}")
    edges = np.linspace(t0, t1, k + 1)
    out = []
    for i in range(k):
        a, b = edges[i], edges[i + 1]
        last = i == k - 1

        def sel(df):
            t = df["t"].to_numpy(float)
            m = (t >= a) & ((t <= b) if last else (t < b))
            return df[m].reset_index(drop=True)

        gt = sel(ds.groundtruth) if ds.groundtruth is not None else None
        meta = ds.meta.model_copy(update={"name": f"{ds.meta.name}[window {i + 1}/{k}]"})
        out.append(Dataset(imu=sel(ds.imu), uwb=sel(ds.uwb), anchors=ds.anchors, groundtruth=gt, meta=meta))
    return out


def _calibration_of(result: Any) -> dict:
    cal = getattr(result, "calibration", result)
    if not isinstance(cal, Mapping):  # a dict or a typed result that reads as one (CalibrationEstimate)
        raise TypeError(f"estimator returned {type(result).__name__} without a calibration dict")
    return cal


def _values(cal: dict) -> tuple[dict, dict]:
    la = cal.get("lever_arm")
    las = cal.get("lever_arm_sd")
    vals, sds = {}, {}
    if la is not None:
        for i, n in enumerate(BLOCK["lever"].output_names):
            vals[n] = float(la[i])
            sds[n] = float(las[i]) if las is not None and las[i] is not None else float("nan")
    if cal.get("time_offset") is not None:
        from uwbimu.io.calibration_file import time_offset_sd, time_offset_value

        # a number (the ESKF in memory) or the mapping of calibration.yaml's schema / the batch calibrator
        (n,) = BLOCK["t_d"].output_names
        vals[n] = time_offset_value(cal)
        s = time_offset_sd(cal)
        sds[n] = float(s) if s is not None else float("nan")
    return vals, sds


def consistency(values: np.ndarray, sds: np.ndarray, level: float = 0.01) -> dict:
    """Spread of repeated estimates against their predicted sigmas.

    Parameters
    ----------
    values : (K,) estimates of one parameter.
    sds : (K,) their reported 1-sigma.
    level : two-sided significance level of the χ²(K−1) test.

    Returns
    -------
    dict: n, mean (weighted), mean_sd (σ of the weighted mean, ``1/sqrt(Σ 1/σ_k²)``), std (sample), rms_sd,
    ratio, chi2, dof, p_value, verdict
    (``consistent``, ``over-confident`` (spread ≫ σ), ``under-confident`` (σ ≫ spread),
    or ``not estimated`` when σ is zero/NaN).
    """
    x = np.asarray(values, float)
    s = np.asarray(sds, float)
    ok = np.isfinite(x) & np.isfinite(s) & (s > 0)
    n = int(ok.sum())
    out = {"n": n, "mean": float(np.nanmean(x)) if len(x) else float("nan"), "mean_sd": float("nan"),
           "std": float(np.std(x[np.isfinite(x)], ddof=1)) if np.isfinite(x).sum() > 1 else float("nan"),
           "rms_sd": float("nan"), "ratio": float("nan"), "chi2": float("nan"), "dof": max(n - 1, 0),
           "p_value": float("nan"), "verdict": "not estimated"}
    if n < 2:
        if n < 2 and np.isfinite(x).sum() >= 2:
            out["verdict"] = "not estimated (sigma zero or missing)"
        return out
    x, s = x[ok], s[ok]
    w = 1.0 / s**2
    xbar = float(np.sum(w * x) / np.sum(w))
    c2 = float(np.sum((x - xbar) ** 2 * w))
    dof = n - 1
    p_hi = float(_chi2.sf(c2, dof))  # probability of a spread at least this large
    p_lo = float(_chi2.cdf(c2, dof))
    verdict = "consistent"
    if p_hi < level / 2:
        verdict = "over-confident"
    elif p_lo < level / 2:
        verdict = "under-confident"
    rms = float(np.sqrt(np.mean(s**2)))
    std = float(np.std(x, ddof=1))
    out.update(mean=xbar, mean_sd=float(1.0 / np.sqrt(np.sum(w))), std=std, rms_sd=rms, ratio=std / rms, chi2=c2, dof=dof, p_value=p_hi, verdict=verdict)
    return out


def _held(res: Any, cal: Mapping) -> list[str]:
    """Parameters a window's estimator held at its prior instead of estimating them: the ESKF's resolved mode
    ``consider`` or ``fixed`` (a lever arm the log does not determine, t_d on a single-clock log), the batch's
    ``held_at_prior`` blocks.  Their window values are the prior, their spread zero by construction: no test
    of the sigma."""
    modes = (((getattr(res, "config", None) or {}).get("resolved") or {}).get("modes") or {})
    blocks = set(((cal.get("held_at_prior") or {}).get("blocks") or []))
    out: list[str] = []
    if modes.get("lever_arm") in ("consider", "fixed") or "lever_arm" in blocks:
        out += list(BLOCK["lever"].output_names)
    if modes.get("time_offset") in ("consider", "fixed") or "time_offset" in blocks:
        out += list(BLOCK["t_d"].output_names)
    return out


def _window_frame(i: int, w: Dataset) -> dict:
    t0, t1 = float(w.imu_t[0]) if len(w.imu) else float("nan"), float(w.imu_t[-1]) if len(w.imu) else float("nan")
    return {"i": i, "t0": t0, "t1": t1, "t_mid": 0.5 * (t0 + t1), "n_imu": len(w.imu), "n_uwb": len(w.uwb)}


def _run_window(i: int, w: Dataset, estimator: Callable[[Dataset], Any]) -> dict:
    rec = _window_frame(i, w)
    try:
        res = estimator(w)
        cal = _calibration_of(res)
        vals, sds = _values(cal)
        rec["values"], rec["sd"] = vals, sds
        rec["held"] = _held(res, cal)
        scale = (cal.get("imu_noise") or {}).get("scale") or {}
        if scale.get("method") == "variance_component":  # the batch's IMU noise scale of this window
            rec["imu_noise_scale"] = float(scale["scale"])
        blocks = ((cal.get("covariance") or {}).get("block_check") or {}).get("parameters") or {}
        if blocks:  # the batch's block check of this window: which sigma it widened (calibration/covariance.py)
            rec["sigma_widened_by_blocks"] = sorted(n for n, b in blocks.items() if b.get("widened"))
        rec["warnings"] = list(getattr(res, "warnings", []) or [])
    except Exception as exc:  # a window that fails is reported, not fatal
        rec["error"] = f"{type(exc).__name__}: {exc}"
    return rec


def _window_task(task) -> dict:
    """One window on an executor's worker: ``(i, window, registry name, options)`` -> record."""
    from uwbimu.estimators import get_estimator

    i, w, name, opts = task
    entry = get_estimator(name)
    return _run_window(i, w, lambda d: entry.run(d, opts, None))


def repeatability(
    ds: Dataset,
    k: int,
    estimator: Union[str, Callable[[Dataset], Any]] = "eskf",
    level: float = 0.01,
    progress: Optional[Callable[[int, int], None]] = None,
    t_range: Optional[tuple[float, float]] = None,
    options: Any = None,
    workers: int = 1,
) -> dict:
    """Calibrate each of ``k`` windows with ``estimator`` and test the spread.

    Parameters
    ----------
    ds : the log.
    k : number of windows.
    estimator : a name of the estimator registry (:mod:`uwbimu.estimators`: ``eskf``,
        ``pointmass``, ``batch``), run with ``options``; or any callable
        ``Dataset -> EstimationResult`` (or calibration dict).
    level : significance level of the consistency test.
    progress : optional callback ``(done, total)``.
    workers : windows calibrated in parallel on the Monte Carlo executors
        (:func:`uwbimu.parallel.execute`, a process pool); 1 (default) runs them here, in
        order.  Only for a registry name (a callable may not be picklable).

    Returns
    -------
    dict (JSON-serialisable): ``k``, ``window_s``, ``windows`` (per window:
    ``t0, t1, t_mid, values, sd, warnings`` or ``error``), ``parameters``
    (per parameter: :func:`consistency` over the windows that estimated it + ``held_windows`` (those that held
    it at its prior: verdict ``held at its prior`` when all did), ``truth``, ``mean_error`` = mean − truth and ``mean_error_z`` =
    mean_error / mean_sd when the dataset's truth is known), ``truth_source`` (``dataset.yaml truth`` or
    None), ``n_failed``.
    """
    name = estimator if isinstance(estimator, str) else None
    if name is not None:
        from uwbimu.estimators import get_estimator

        entry = get_estimator(name)
        opts = entry.options(options)
        estimator = lambda w: entry.run(w, opts, None)  # noqa: E731
    elif options is not None:
        raise ValueError("options apply to a registry name, not to an estimator callable")
    if workers != 1 and name is None:
        raise ValueError("workers > 1 needs an estimator name of the registry (a callable may not be picklable)")
    wins = split_windows(ds, k, t_range=t_range)
    if workers != 1:
        from uwbimu.parallel import execute

        got: dict[int, dict] = {}

        def keep(rec: dict) -> None:
            got[rec["i"]] = rec
            if progress is not None:
                progress(len(got), len(wins))

        # the caller times the first window and starts a pool only when the rest outlasts its start
        # (parallel.pool_pays): a short window is cheaper here than a process start
        failed = execute(_window_task, [(i, w, name, opts) for i, w in enumerate(wins)], keep, workers=workers,
                         caller=True, measure_first=True, describe=lambda t: f"window {t[0]}",
                         preload=("uwbimu.sim", "uwbimu.estimation", "uwbimu.estimators"))
        for line in failed:  # a worker that died: the window is reported as failed, not lost
            i = int(line.split(":")[0].split()[-1])
            got[i] = {**_window_frame(i, wins[i]), "error": line}
        records = [got[i] for i in range(len(wins))]
    else:
        records = []
        for i, w in enumerate(wins):
            records.append(_run_window(i, w, estimator))
            if progress is not None:
                progress(i + 1, len(wins))
    truth = {}
    if ds.meta.truth is not None:
        if ds.meta.truth.lever_arm is not None:
            truth.update(dict(zip(BLOCK["lever"].output_names, map(float, ds.meta.truth.lever_arm))))
        if ds.meta.truth.time_offset is not None:
            truth[BLOCK["t_d"].output_names[0]] = float(ds.meta.truth.time_offset)
    params = {}
    for p in PARAMS:
        have = [r for r in records if p in r.get("values", {})]
        if not have:
            continue
        # a window that held the parameter at its prior tells nothing of its sigma: left out of the test
        ok = [r for r in have if p not in r.get("held", [])]
        st = consistency(np.array([r["values"][p] for r in ok]), np.array([r["sd"][p] for r in ok]), level=level)
        st["held_windows"] = len(have) - len(ok)
        if not ok:
            st["verdict"] = "held at its prior"
            st["mean"] = float(np.mean([r["values"][p] for r in have]))
        if p in truth:
            st["truth"] = truth[p]
            st["mean_error"] = st["mean"] - truth[p]
            ms = st.get("mean_sd")
            st["mean_error_z"] = (st["mean_error"] / ms) if (ms is not None and np.isfinite(ms) and ms > 0) \
                else float("nan")
        params[p] = st
    return {
        "k": k,
        "window_s": float(np.mean([r["t1"] - r["t0"] for r in records])),
        "level": level,
        "windows": records,
        "parameters": params,
        "truth_source": "dataset.yaml truth" if truth else None,
        "n_failed": int(sum("error" in r for r in records)),
    }
