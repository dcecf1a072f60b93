"""Files written by ``uwbimu calibrate``: calibration.yaml, trajectory.csv, residuals.csv, anchors_estimated.csv,
td_profile.csv/png."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml

#: Every file the verb may write (the output rule refuses others without --force).
OUTPUT_FILES = ("calibration.yaml", "trajectory.csv", "residuals.csv", "anchors_estimated.csv", "td_profile.csv",
                "td_profile.png")


#: residuals.csv columns that hold a part of the range model already inside ``predicted`` (and ``residual``)
RANGE_MODEL_COLUMNS = ("bias_drift", "bias_direction", "bias_anchor_direction")


def measured_minus_predicted(res) -> np.ndarray:
    """Residual [m] of each row of a batch ``residuals.csv`` as measured − predicted (the ESKF's innovation sign).

    From the ``range`` and ``predicted`` columns when the table has both (whatever the sign of its ``residual``
    column); else ``residual`` (the batch writes ``residual = measured − predicted``; files written before the
    sign was unified had ``predicted − measured`` but always carry ``range`` and ``predicted``). Non-numeric cells
    become NaN.
    """
    import pandas as pd

    if "range" in res.columns and "predicted" in res.columns:
        return (pd.to_numeric(res["range"], errors="coerce").to_numpy(float)
                - pd.to_numeric(res["predicted"], errors="coerce").to_numpy(float))
    return pd.to_numeric(res["residual"], errors="coerce").to_numpy(float)


def residual_without(res, anchor_bias: dict, columns=RANGE_MODEL_COLUMNS) -> np.ndarray:
    """Residual [m], measured − predicted, of each row of a batch ``residuals.csv`` without the estimated range
    model: :func:`measured_minus_predicted` plus the anchor's constant bias (``anchor_bias``: calibration.yaml's,
    by anchor id; NaN for an anchor not in it) plus the per-row terms of ``columns`` that the table has (the model
    terms are inside ``predicted``; non-numeric cells become NaN)."""
    import pandas as pd

    e = measured_minus_predicted(res)
    b = np.array([float(anchor_bias.get(a, np.nan)) for a in res["anchor"].astype(str)])
    out = e + b
    for c in columns:
        if c in res.columns:
            out = out + pd.to_numeric(res[c], errors="coerce").to_numpy(float)
    return out


def calibration_document(result) -> dict:
    """``result.calibration`` in the one schema of calibration.yaml (:mod:`uwbimu.io.calibration_file`): the
    time offset a mapping ``value, sd, unit, mode, verdict, ...`` (``mode: fixed`` when held at its prior, the
    other values conditional on it), NaN sigmas null, ``estimator: batch``."""
    from uwbimu.io import calibration_file as CF
    from uwbimu.io.atomic import to_plain

    cal = CF.migrate(to_plain(result.calibration))
    cal.pop("time_offset_sd", None)
    return {"schema_version": cal.pop("schema_version"), "estimator": "batch", **cal}


def write_calibration(result, out_dir, plots: bool = True) -> list[Path]:
    """Write the result's files into ``out_dir`` (an existing folder); returns the paths."""
    out = Path(out_dir)
    paths = [out / "calibration.yaml", out / "trajectory.csv", out / "residuals.csv"]
    paths[0].write_text(yaml.safe_dump(calibration_document(result), sort_keys=False, allow_unicode=True))
    result.trajectory.to_csv(paths[1], index=False, float_format="%.9g")
    result.residuals.to_csv(paths[2], index=False, float_format="%.9g")
    if getattr(result, "anchors", None) is not None:
        paths.append(out / "anchors_estimated.csv")
        result.anchors.to_csv(paths[-1], index=False, float_format="%.9g")
    prof = result.profile
    if prof is not None:
        paths.append(out / "td_profile.csv")
        prof.frame().to_csv(paths[-1], index=False, float_format="%.9g")
        if plots:
            paths.append(out / "td_profile.png")
            _plot_profile(prof, result.calibration, paths[-1])
    return paths


def _plot_profile(prof, cal, path: Path) -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(6, 3.5))
    ax = fig.add_subplot(1, 1, 1)
    d = prof.chi2 - np.nanmin(prof.chi2)
    ax.plot(1000 * prof.grid, d, "o-", ms=3)
    ax.axhline(prof.confidence_chi2, color="gray", ls="--", lw=0.8, label=f"confidence set (Δχ² < {prof.confidence_chi2:g})")
    from uwbimu.formatting import format_value_sigma

    td = cal["time_offset"]
    if prof.identified and td.get("value") is not None:
        sd = td.get("sd")
        ax.axvline(1000 * td["value"], color="C3", lw=1,
                   label="t_d = " + format_value_sigma(1000 * td["value"], None if sd is None else 1000 * sd, "ms"))
    ax.set_xlabel("time offset t_d [ms]")
    ax.set_ylabel("Δχ² (profile)")
    ax.set_title(f"t_d profile: {prof.verdict}")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=100)
