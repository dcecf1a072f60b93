"""One self-contained HTML calibration report for an estimator output folder.

:func:`write_report` reads what ``uwbimu estimate`` (and optionally
``uwbimu evaluate``, ``uwbimu repeatability`` and the observability analysis)
wrote into ``OUT`` and renders ``OUT/report.html``: every plot is an embedded
base64 PNG, there is no script and no external URL, so the file opens offline
and can be mailed as is.

Sections (``<section id=...>``; a section whose input is missing says so):

``calibration``    lever arm and time offset ± 1 sigma (and the documented/true
                   value with its z-score when known), IMU biases
``batch``          only for a ``uwbimu calibrate`` folder (:func:`is_batch_output`): t_d
                   profile, residual vs body-frame line-of-sight azimuth per anchor, anchor
                   2-sigma error ellipses, residuals without / with the range bias
``convergence``    lever arm and time offset over time with ±3 sigma bands
                   (``states.csv`` columns ``lx, ly, lz, td`` + ``sd_*``, as ``uwbimu estimate`` writes them)
``residuals``      per-anchor innovation table: median, MAD, rejected %, flags
``nis``            histogram of the range NIS against the chi-square(1) density
``trajectory``     top view (and errors with ±3 sigma when ground truth exists)
``repeatability``  spread over windows vs predicted sigma (``repeatability.json``)
``observability``  excitation / observability timeline (``observability.csv``)
``warnings``       estimator warnings
"""

from __future__ import annotations

import base64
import datetime as _dt
import functools
import io
import json
import os
from pathlib import Path
from typing import Any, Optional, Sequence, Union

import numpy as np
import pandas as pd

from markupsafe import Markup

from uwbimu.eval.files import EvalInputError, load_yaml
from uwbimu.io.atomic import write_text
from uwbimu.models.state import NOMINAL_STATE_NAMES

#: Columns of the calibration history: the lever-arm and time-offset states as ``uwbimu estimate``
#: writes them into ``states.csv`` (with ``sd_<name>``), named once in :mod:`uwbimu.models.state`.
CAL_COLUMNS = NOMINAL_STATE_NAMES[16:20]  # lx, ly, lz, td
SECTION_TITLES = {
    "calibration": "Calibration",
    "batch": "Batch calibration",
    "convergence": "Convergence",
    "residuals": "Per-anchor residuals",
    "nis": "NIS",
    "trajectory": "Trajectory and errors",
    "repeatability": "Repeatability",
    "observability": "Observability / excitation",
    "warnings": "Warnings",
}


# --------------------------------------------------------------------------- helpers
def figure_data_uri(fig, dpi: int = 90) -> str:
    """PNG of a matplotlib ``Figure`` as a ``data:`` URI (figure is not kept)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


# HTML is rendered by jinja2 with autoescape from templates shipped as package data
# (uwbimu/eval/templates): a value is escaped unless the code marks it as markup.  Sentences
# with inline markup are built with ``Markup("...{}...").format(value)``, which escapes the
# values (markupsafe, the same escaping jinja2 applies).
@functools.lru_cache(maxsize=1)
def _templates():
    import jinja2

    return jinja2.Environment(loader=jinja2.PackageLoader("uwbimu.eval", "templates"),
                              autoescape=True, trim_blocks=False, undefined=jinja2.StrictUndefined)


def _block(name: str, *args) -> Markup:
    """Call the macro ``name`` of ``templates/blocks.html.j2`` (returns markup)."""
    return Markup(getattr(_templates().get_template("blocks.html.j2").module, name)(*args))


def _join(parts) -> Markup:
    return Markup("").join(parts)


def _fig(name: str, fig, caption: str) -> Markup:
    return _block("figure", name, figure_data_uri(fig), caption)


def _span(cls: str, text: Any) -> Markup:
    return _block("span", cls, text)


def _fmt(x: Any, nd: int = 4) -> str:
    try:
        v = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not np.isfinite(v):
        return "–"
    return f"{v:.{nd}f}"


def _table(header: Sequence[str], rows: Sequence[Sequence[Any]], row_classes: Optional[Sequence[str]] = None,
           left: int = 1) -> Markup:
    """An HTML table; cells are escaped unless they are markup (e.g. :func:`_span`)."""
    return _block("table", list(header), [list(r) for r in rows], list(row_classes or []), left)


def _missing(text: Any) -> Markup:
    return _block("missing", text)


def _sd_col(df: pd.DataFrame, col: str) -> Optional[str]:
    return f"sd_{col}" if f"sd_{col}" in df.columns else None


def _read_csv(path: Path) -> Optional[pd.DataFrame]:
    if not path.is_file():
        return None
    try:
        return pd.read_csv(path)
    except Exception as exc:  # malformed file: report, do not crash the report
        raise EvalInputError(f"cannot read {path}: {exc}") from exc


def _as_bool(s: pd.Series) -> np.ndarray:
    if s.dtype == bool:
        return s.to_numpy()
    return s.astype(str).str.strip().str.lower().isin(["true", "1", "yes", "1.0"]).to_numpy()


# --------------------------------------------------------------------------- inputs
class ReportInputs:
    """Everything the report reads from an output folder (each item may be missing)."""

    def __init__(self, out_dir: Path, dataset=None):
        self.out = out_dir
        self.dataset = dataset
        self.calibration = load_yaml(out_dir / "calibration.yaml")
        self.metrics = load_yaml(out_dir / "metrics.yaml")
        self.trajectory = _read_csv(out_dir / "trajectory.csv")
        self.residuals = _read_csv(out_dir / "residuals.csv")
        # calibration history: states.csv of `uwbimu estimate` (lx, ly, lz, td + sd_*)
        self.states = _read_csv(out_dir / "states.csv")
        self.observability = _read_csv(out_dir / "observability.csv")
        # outputs of `uwbimu calibrate` (batch calibration section)
        self.td_profile = _read_csv(out_dir / "td_profile.csv")
        self.anchors_estimated = _read_csv(out_dir / "anchors_estimated.csv")
        self.eval_errors = _read_csv(out_dir / "evaluation_errors.csv")
        self.evaluation = None
        if (out_dir / "evaluation.json").is_file():
            self.evaluation = json.loads((out_dir / "evaluation.json").read_text())
        self.repeatability = None
        if (out_dir / "repeatability.json").is_file():
            self.repeatability = json.loads((out_dir / "repeatability.json").read_text())
        self.warnings: list[str] = []
        for src in (self.calibration or {}, self.metrics or {}):
            w = src.get("warnings")
            if isinstance(w, list):
                self.warnings += [str(x) for x in w]
        if (out_dir / "warnings.txt").is_file():
            self.warnings += [ln for ln in (out_dir / "warnings.txt").read_text().splitlines() if ln.strip()]
        # ground truth from a dataset given in memory, if no evaluation was written
        if self.evaluation is None and dataset is not None and dataset.groundtruth is not None and self.trajectory is not None:
            self._evaluate_in_memory()

    def _evaluate_in_memory(self) -> None:
        from uwbimu.eval.evaluate import evaluation_table
        from uwbimu.metrics.trajectory import evaluate_trajectory

        extra = self.dataset.meta.extra or {}
        align = str(extra.get("groundtruth_align", "none"))
        try:
            ev = evaluate_trajectory(self.trajectory, self.dataset.groundtruth, align=align,
                                     compare_attitude=bool(extra.get("groundtruth_attitude_comparable", True)))
        except (ValueError, KeyError) as exc:
            self.warnings.append(f"report: could not evaluate against the dataset's ground truth: {exc}")
            return
        self.evaluation = ev.summary
        self.eval_errors = evaluation_table(ev)

    def reference_lever_arm(self) -> tuple[Optional[list], str]:
        """Documented or true lever arm, with a label saying which."""
        ds = self.dataset
        if ds is not None:
            if ds.meta.truth is not None and ds.meta.truth.lever_arm is not None:
                return list(ds.meta.truth.lever_arm), "reference"
            if ds.meta.tags and ds.meta.tags[0].lever_arm is not None:
                return list(ds.meta.tags[0].lever_arm), "nominal"
        return None, ""

    def reference_time_offset(self) -> Optional[float]:
        ds = self.dataset
        if ds is not None and ds.meta.truth is not None:
            return ds.meta.truth.time_offset
        return None


# --------------------------------------------------------------------------- sections
def _calibration_section(inp: ReportInputs) -> Markup:
    c = inp.calibration
    if c is None:
        return _missing(Markup("<code>calibration.yaml</code> not found in the output folder."))
    ref_l, ref_label = inp.reference_lever_arm()
    ref_td = inp.reference_time_offset()
    rows, classes = [], []
    la = c.get("lever_arm")
    las = c.get("lever_arm_sd") or [float("nan")] * 3
    header = ["parameter", "estimate", "± 1σ", f"{ref_label or 'reference'}", "error", "z = error/σ"]

    def add(name, v, s, ref, unit, scale=1.0, nd=4):
        err = (v - ref) if (ref is not None and v is not None) else None
        z = err / s if (err is not None and s and np.isfinite(s) and s > 0) else None
        flag = z is not None and abs(z) > 3
        rows.append([
            f"{name} [{unit}]", _fmt(None if v is None else v * scale, nd), _fmt(None if s is None else s * scale, nd),
            "–" if ref is None else _fmt(ref * scale, nd), "–" if err is None else _fmt(err * scale, nd),
            "–" if z is None else _span("bad" if flag else "ok", f"{z:+.2f}"),
        ])
        classes.append("flag" if flag else "")

    if la is not None:
        for i, ax in enumerate("xyz"):
            add(f"lever arm {ax}", float(la[i]), float(las[i]) if las[i] is not None else None,
                None if ref_l is None else float(ref_l[i]), "m")
    td = c.get("time_offset")
    if isinstance(td, dict):  # uwbimu calibrate: {value, sd, verdict, ...}
        td = td.get("value")
    if td is not None:
        add("time offset", float(td), c.get("time_offset_sd"), ref_td, "ms", scale=1000.0, nd=2)
    parts = [_table(header, rows, classes)]
    mode_bits = [Markup("{}: <code>{}</code>").format(k, c[k])
                 for k in ("lever_arm_mode", "time_offset_mode", "anchor_bias_mode") if k in c]
    if mode_bits:
        parts.append(Markup('<p class="note">Modes — {}.</p>').format(Markup(", ").join(mode_bits)))
    if ref_label:
        note = (inp.dataset.meta.extra or {}).get("lever_arm_note", "")
        parts.append(Markup('<p class="note">Reference lever arm: <code>{}</code> of dataset.yaml (simulation truth, or '
                            'the value documented by the source for real data). {}</p>').format(
            "truth.lever_arm" if ref_label == "reference" else "tags[0].lever_arm", note))
    brows = []
    for key, unit in (("accel_bias", "m/s²"), ("gyro_bias", "rad/s")):
        if c.get(key) is not None:
            sd = c.get(f"{key}_sd") or [float("nan")] * 3
            brows.append([f"{key.replace('_', ' ')} [{unit}]"] + [f"{_fmt(v, 4)} ± {_fmt(s, 4)}" for v, s in zip(c[key], sd)])
    if brows:
        parts.append(_table(["IMU bias", "x", "y", "z"], brows))
    if isinstance(c.get("anchor_bias"), dict):
        sd = c.get("anchor_bias_sd") or {}
        kb = (inp.dataset.meta.known_anchor_bias or {}) if inp.dataset is not None else {}
        arows = [[a, _fmt(v, 3), _fmt(sd.get(a), 3), _fmt(kb.get(a), 3) if a in kb else "–"] for a, v in c["anchor_bias"].items()]
        parts.append(_table(["anchor", "estimated bias [m]", "± 1σ", "known bias [m]"], arows))
    if inp.metrics:
        def mval(v):
            if isinstance(v, list):
                return "[" + ", ".join(_fmt(x, 4) for x in v) + "]"
            if isinstance(v, (bool, str)) or v is None:
                return str(v)
            return _fmt(v, 4)

        extra = (inp.dataset.meta.extra or {}) if inp.dataset is not None else {}
        other_frame = str(extra.get("groundtruth_align", "none")) != "none"
        na = "n/a (ground truth in another frame)"

        def vs_truth(k: str) -> bool:  # the estimator's unaligned comparisons with ground truth
            return k.startswith(("position_rmse", "orientation_rmse", "velocity_rmse", "nees")) and k not in ("position_rmse_after_skip_s", "nees_dof")

        mrows = [[k, na if (other_frame and vs_truth(k)) else mval(v)] for k, v in inp.metrics.items()
                 if not isinstance(v, dict) and k != "warnings"]
        if mrows:
            note = Markup("<p>The dataset's ground truth is in another frame (<code>extra.groundtruth_align: "
                          "{}</code>): the estimator's unaligned comparisons with it are "
                          "not meaningful and shown as n/a; see <a href=\"#trajectory\">Trajectory and errors</a> for "
                          "the aligned errors.</p>").format(extra.get("groundtruth_align")) if other_frame else ""
            parts.append(Markup("<h3>metrics.yaml</h3>") + note + _table(["metric", "value"], mrows))
    return _join(parts)


def _calibration_history(inp: ReportInputs) -> tuple[Optional[pd.DataFrame], dict]:
    for df in (inp.states, inp.trajectory):
        if df is None or "t" not in df.columns:
            continue
        cols = {k: k for k in CAL_COLUMNS if k in df.columns}
        if cols:
            return df, cols
    return None, {}


def _convergence_section(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure

    df, cols = _calibration_history(inp)
    if df is None:
        return _missing(Markup("no calibration history: neither <code>states.csv</code> nor <code>trajectory.csv</code> "
                               "has lever-arm / time-offset columns (<code>lx, ly, lz, td</code> with <code>sd_lx</code>, "
                               "...)."))
    t = df["t"].to_numpy(float)
    ref_l, ref_label = inp.reference_lever_arm()
    ref_td = inp.reference_time_offset()
    fig = Figure(figsize=(9.0, 7.0))
    keys = [k for k in ("lx", "ly", "lz", "td") if cols.get(k)]
    for n, k in enumerate(keys):
        ax = fig.add_subplot(len(keys), 1, n + 1)
        scale, unit = (1000.0, "ms") if k == "td" else (1.0, "m")
        v = df[cols[k]].to_numpy(float) * scale
        ax.plot(t, v, "C0-", lw=1.0, label="estimate")
        sdc = _sd_col(df, cols[k])
        if sdc is not None:
            s = df[sdc].to_numpy(float) * scale
            ax.fill_between(t, v - 3 * s, v + 3 * s, color="C0", alpha=0.2, lw=0, label="±3σ")
        ref = (ref_td if k == "td" else (None if ref_l is None else ref_l["xyz".index(k[1])]))
        if ref is not None:
            ax.axhline(ref * scale, color="k", ls="--", lw=0.9, label=ref_label or "reference")
        # zoom on the converged part: the prior's wide band would flatten everything else
        late = t >= t[0] + 0.1 * (t[-1] - t[0])
        if sdc is not None and late.any():
            lo = np.nanmin((v - 3 * s)[late])
            hi = np.nanmax((v + 3 * s)[late])
            if ref is not None:
                lo, hi = min(lo, ref * scale), max(hi, ref * scale)
            if np.isfinite(lo) and np.isfinite(hi) and hi > lo:
                pad = 0.15 * (hi - lo)
                ax.set_ylim(lo - pad, hi + pad)
        ax.set_ylabel(f"{k} [{unit}]")
        ax.grid(True, alpha=0.3)
        if n == 0:
            ax.legend(loc="upper right", fontsize=8, ncol=3)
    fig.axes[-1].set_xlabel("t [s] (UWB clock)")
    return _fig("convergence", fig, "Lever arm (IMU frame) and time offset over time with ±3σ bands of the filter.")


def anchor_residual_table(res: pd.DataFrame) -> pd.DataFrame:
    """Per-anchor innovation statistics with suspicion flags.

    Columns: ``anchor, n, processed, median, mad, robust_sd, rejected_pct, flags``.
    ``median``/``mad`` use accepted innovations [m]; ``rejected_pct`` is over
    processed ranges (finite NIS).  Flags: ``biased`` when |median| exceeds half
    the overall robust sd and 5 cm, ``noisy`` when the anchor's robust sd is
    twice the overall one, ``rejections`` when its rejection rate is twice the
    overall rate and above 10 %.
    """
    acc = _as_bool(res["accepted"]) if "accepted" in res.columns else np.ones(len(res), bool)
    innov = pd.to_numeric(res["innovation"], errors="coerce").to_numpy(float)
    nis = pd.to_numeric(res["nis"], errors="coerce").to_numpy(float) if "nis" in res.columns else np.full(len(res), np.nan)
    processed = np.isfinite(nis) | acc
    anchors = res["anchor"].astype(str).to_numpy()
    ok_all = acc & np.isfinite(innov)
    med_all = np.median(innov[ok_all]) if ok_all.any() else np.nan
    rsd_all = 1.4826 * np.median(np.abs(innov[ok_all] - med_all)) if ok_all.any() else np.nan
    rej_all = 100.0 * np.sum(processed & ~acc) / max(processed.sum(), 1)
    rows = []
    for a in sorted(set(anchors), key=lambda s: (len(s), s)):
        m = anchors == a
        ok = m & ok_all
        x = innov[ok]
        med = float(np.median(x)) if len(x) else np.nan
        mad = float(np.median(np.abs(x - med))) if len(x) else np.nan
        rsd = 1.4826 * mad
        nproc = int((m & processed).sum())
        rej = 100.0 * int((m & processed & ~acc).sum()) / max(nproc, 1)
        flags = []
        if np.isfinite(med) and np.isfinite(rsd_all) and abs(med) > max(0.5 * rsd_all, 0.05):
            flags.append(f"biased ({med:+.3f} m)")
        if np.isfinite(rsd) and np.isfinite(rsd_all) and rsd > 2.0 * rsd_all and rsd > 0.02:
            flags.append("noisy")
        if rej > max(2.0 * rej_all, 10.0):
            flags.append("rejections")
        if nproc == 0:
            flags.append("never used")
        rows.append({"anchor": a, "n": int(m.sum()), "processed": nproc, "median": med, "mad": mad,
                     "robust_sd": rsd, "rejected_pct": rej, "flags": ", ".join(flags)})
    return pd.DataFrame(rows)


def _residuals_section(inp: ReportInputs) -> Markup:
    res = inp.residuals
    if res is None:
        return _missing(Markup("<code>residuals.csv</code> not found."))
    need = [c for c in ("anchor", "innovation") if c not in res.columns]
    if need:
        return _missing(Markup("<code>residuals.csv</code> lacks column(s) {}.").format(need))
    tab = anchor_residual_table(res)
    rows = [[r.anchor, str(r.n), str(r.processed), _fmt(r.median, 3), _fmt(r.mad, 3), _fmt(r.robust_sd, 3),
             _fmt(r.rejected_pct, 1), r.flags or _span("ok", "ok")] for r in tab.itertuples()]
    classes = ["flag" if r.flags else "" for r in tab.itertuples()]
    n_flag = int((tab["flags"] != "").sum())
    head = Markup('<p class="{}">{} of {} anchors flagged as suspicious.</p>').format(
        "warn" if n_flag else "note", n_flag, len(tab))
    return head + _table(["anchor", "ranges", "processed", "median innov. [m]", "MAD [m]", "robust σ [m]",
                          "rejected %", "flags"], rows, classes) + Markup(
        '<p class="note">Innovation = measured − predicted range over accepted updates. Flags: <i>biased</i> '
        "|median| &gt; max(0.5·overall robust σ, 5 cm); <i>noisy</i> robust σ &gt; 2× overall; <i>rejections</i> "
        "rejection rate &gt; max(2× overall, 10 %).</p>")


def _nis_section(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure
    from scipy.stats import chi2

    res = inp.residuals
    if res is None or "nis" not in res.columns:
        return _missing(Markup("<code>residuals.csv</code> with a <code>nis</code> column not found."))
    nis = pd.to_numeric(res["nis"], errors="coerce").to_numpy(float)
    acc = _as_bool(res["accepted"]) if "accepted" in res.columns else np.ones(len(res), bool)
    nis_f = nis[np.isfinite(nis)]
    if len(nis_f) == 0:
        return _missing("no finite NIS values.")
    bound = chi2.ppf(0.95, 1)
    frac = float(np.mean(nis_f > bound))
    fig = Figure(figsize=(7.5, 4.0))
    ax = fig.add_subplot(111)
    # x-range up to the 99th percentile, at most 50: larger values pile into the last bin
    hi = min(max(10.0, float(np.percentile(nis_f, 99))), 50.0)
    bins = np.linspace(0, hi, 60)
    dens, _, _ = ax.hist(np.clip(nis_f, 0, hi), bins=bins, density=True, color="C0", alpha=0.6,
                         label=f"all processed ({100 * np.mean(nis_f > hi):.1f} % > {hi:.0f} in last bin)")
    acc_nis = nis[np.isfinite(nis) & acc]
    if len(acc_nis):
        ax.hist(np.clip(acc_nis, 0, hi), bins=bins, density=True, histtype="step", color="C1", label="accepted")
    x = np.linspace(bins[1] / 2, hi, 300)
    ax.plot(x, chi2.pdf(x, 1), "k-", lw=1.2, label="χ²(1) density")
    ax.axvline(bound, color="r", ls="--", lw=0.9, label="95 % bound")
    ax.set_yscale("log")
    pos = dens[dens > 0]
    if len(pos):
        ax.set_ylim(0.3 * pos.min(), 2.0 * max(pos.max(), chi2.pdf(bins[1] / 2, 1)))
    ax.set_xlabel("NIS (range innovation² / S)")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    stats = Markup(f"<p>{len(nis_f)} processed ranges: mean NIS {np.mean(nis_f):.2f} (χ²(1): 1.00), median "
             f"{np.median(nis_f):.2f} (χ²(1): 0.45), {100 * frac:.1f} % above the 95 % bound {bound:.2f} (expected 5 %).</p>")
    return stats + _fig("nis", fig, "Normalised innovation squared of the range updates against the χ²(1) density.")


def _trajectory_section(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure

    parts = []
    traj = inp.trajectory
    ev = inp.evaluation
    ee = inp.eval_errors
    if ev is not None and ee is not None and len(ee):
        a = ev["ate_position"]
        ar = ev.get("ate_rotation_deg")
        asc = ev["association"]
        parts.append(Markup(
            "<p>Against ground truth after <b>{}</b> alignment: position ATE RMSE <b>{:.3f} m</b> (mean {:.3f}, "
            "median {:.3f}, max {:.3f} m, n={}){}{}. Ground-truth glitches excluded: {} (position), {} (attitude).</p>"
        ).format(ev["align"]["mode"], a["rmse"], a["mean"], a["median"], a["max"], a["n"],
                 f"; attitude RMSE {ar['rmse']:.2f}°" if ar else "",
                 f"; attitude {ev['ate_rotation']}" if ev.get("ate_rotation") else "",
                 asc["n_groundtruth_glitches_excluded"], asc.get("n_groundtruth_attitude_glitches_excluded", 0)))
        rrows = [[d, str(v["n_pairs"]), _fmt(v["translation"]["rmse"], 3), _fmt(v.get("translation_percent"), 1),
                  _fmt(v["rotation_deg"]["rmse"], 2)] for d, v in ev.get("rpe", {}).items()]
        if rrows:
            parts.append(_table(["RPE distance [m]", "pairs", "trans. RMSE [m]", "drift %", "rot. RMSE [deg]"], rrows))
        fig = Figure(figsize=(6.0, 5.0))
        ax = fig.add_subplot(111)
        ax.plot(ee["px_gt"], ee["py_gt"], "k-", lw=1.2, label="ground truth")
        ax.plot(ee["px_est"], ee["py_est"], "C0-", lw=0.9, label="estimate (aligned)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.legend(fontsize=8)
        ax.grid(True, alpha=0.3)
        parts.append(_fig("trajectory", fig, "Top view, ground-truth frame."))
        fig2 = Figure(figsize=(9.0, 4.0))
        ax2 = fig2.add_subplot(111)
        t = ee["t"].to_numpy(float)
        e = ee[["ex", "ey", "ez"]].to_numpy(float)
        sd = None
        if traj is not None and all(c in traj.columns for c in ("sd_px", "sd_py", "sd_pz")):
            sd = np.column_stack([np.interp(t, traj["t"].to_numpy(float), traj[c].to_numpy(float))
                                  for c in ("sd_px", "sd_py", "sd_pz")])
        if ev["align"]["mode"] in ("none", "position"):
            for i, c in enumerate("xyz"):
                ax2.plot(t, e[:, i], f"C{i}-", lw=0.8, label=f"e{c}")
                if sd is not None:
                    ax2.fill_between(t, -3 * sd[:, i], 3 * sd[:, i], color=f"C{i}", alpha=0.12, lw=0)
            cap = "Position error per axis with the filter's ±3σ bands."
        else:
            ax2.plot(t, np.linalg.norm(e, axis=1), "k-", lw=0.8, label="|e|")
            if sd is not None:
                ax2.plot(t, 3 * np.linalg.norm(sd, axis=1), "C3--", lw=0.8, label="3σ (norm)")
            cap = ("Position error norm (rotation-invariant after SE(3) alignment) against 3× the norm of the "
                   "filter's position σ.")
        ax2.set_xlabel("t [s]")
        ax2.set_ylabel("error [m]")
        ax2.legend(fontsize=8, ncol=4)
        ax2.grid(True, alpha=0.3)
        parts.append(_fig("errors", fig2, cap))
        return _join(parts)
    if traj is None or not all(c in traj.columns for c in ("px", "py")):
        return _missing(Markup("<code>trajectory.csv</code> not found."))
    fig = Figure(figsize=(6.0, 5.0))
    ax = fig.add_subplot(111)
    ax.plot(traj["px"], traj["py"], "C0-", lw=0.9, label="estimate")
    if inp.dataset is not None:
        an = inp.dataset.anchors
        ax.plot(an["x"], an["y"], "k^", ms=7, label="anchors")
        for r in an.itertuples(index=False):
            ax.annotate(str(r.anchor), (r.x, r.y), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m] (anchor frame)")
    ax.set_ylabel("y [m]")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    parts.append(Markup('<p class="note">No ground truth evaluation (run <code>uwbimu evaluate OUT --groundtruth FILE'
                        '</code>).</p>'))
    parts.append(_fig("trajectory", fig, "Estimated trajectory, top view."))
    return _join(parts)


_REP_INDEX = {"lx": 15, "ly": 16, "lz": 17, "td": 18}


def _repeatability_bounds(inp: ReportInputs, wins: list) -> dict:
    """RMS over the repeatability windows of the posterior Cramer-Rao bound of each
    window on its own (default start prior, the dataset's ground truth), or {}."""
    ds = inp.dataset
    if ds is None or getattr(ds, "groundtruth", None) is None or not wins:
        return {}
    try:
        from uwbimu.observability.window import posterior_crb

        sds = []
        for w in wins:
            P, _ = posterior_crb(ds, t_start=float(w["t0"]), t_end=float(w["t1"]))
            sds.append({k: float(np.sqrt(P[i, i])) for k, i in _REP_INDEX.items()})
        return {k: float(np.sqrt(np.mean([d[k] ** 2 for d in sds]))) for k in _REP_INDEX}
    except Exception as exc:  # the bound is context, never a reason to fail the report
        inp.warnings.append(f"report: no per-window Cramér-Rao bound for the repeatability windows: {exc}")
        return {}


def _repeatability_section(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure

    rep = inp.repeatability
    if rep is None:
        return _missing(Markup("<code>repeatability.json</code> not found (run <code>uwbimu repeatability DATASET --out "
                               "OUT</code>)."))
    params = rep.get("parameters", {})
    bounds = _repeatability_bounds(inp, rep.get("windows", []))
    rows, classes = [], []
    for name, p in params.items():
        scale = 1000.0 if name == "td" else 100.0
        unit = "ms" if name == "td" else "cm"
        verdict = p.get("verdict", "")
        rows.append([f"{name} [{unit}]", str(p.get("n", "")), _fmt(p.get("mean", np.nan) * scale, 2),
                     _fmt(p.get("std", np.nan) * scale, 2), _fmt(p.get("rms_sd", np.nan) * scale, 2),
                     _fmt(bounds[name] * scale, 2) if name in bounds else "–", _fmt(p.get("ratio"), 2), _fmt(p.get("chi2"), 2), str(p.get("dof", "")), _fmt(p.get("p_value"), 3),
                     _span("ok" if verdict == "consistent" else "bad", verdict)])
        classes.append("" if verdict == "consistent" else "flag")
    parts = [Markup("<p>{} windows of {} s ({} calibrated).</p>").format(
                 rep.get("k", "?"), _fmt(rep.get("window_s"), 1), len(rep.get("windows", []))),
             _table(["parameter", "windows", "mean", "spread (sd)", "predicted σ (RMS)", "bound (PCRB, RMS)", "spread/σ",
                     "χ²", "dof", "p", "verdict"], rows, classes),
             Markup('<p class="note">χ² = Σ (x_k − x̄)² / σ_k² over windows, compared with χ²(K−1): a spread much larger '
             "than the filter's σ means over-confidence (or a parameter that changes between windows). "
             "Bound: the posterior Cramér-Rao bound of each window on its own (same start prior as the observability "
             "section, ground-truth trajectory). σ close to the bound with a spread well above both means the filter "
             "reports the information in the data but does not reach it on windows this short (initialisation, "
             "linearisation): over-confident here, while the whole-log σ can still match the bound at the end of the "
             "log (observability section).</p>")]
    wins = rep.get("windows", [])
    if wins:
        fig = Figure(figsize=(9.0, 6.0))
        names = list(params)
        for n, name in enumerate(names):
            ax = fig.add_subplot(len(names), 1, n + 1)
            scale = 1000.0 if name == "td" else 1.0
            xs = [w["t_mid"] for w in wins if name in w.get("values", {})]
            vs = np.array([w["values"][name] for w in wins if name in w.get("values", {})], float) * scale
            ss = np.array([w["sd"][name] for w in wins if name in w.get("values", {})], float) * scale
            ax.errorbar(xs, vs, yerr=3 * ss, fmt="o", ms=4, capsize=3)
            ax.axhline(params[name].get("mean", np.nan) * scale, color="k", lw=0.8)
            ax.set_ylabel(f"{name} [{'ms' if name == 'td' else 'm'}]")
            ax.grid(True, alpha=0.3)
        fig.axes[-1].set_xlabel("window centre [s]")
        parts.append(_fig("repeatability", fig, "Per-window estimates with ±3σ error bars; the line is the mean."))
    return _join(parts)


def _bound_vs_sigma(df: pd.DataFrame, cal: Optional[dict]) -> Markup:
    """The bound at the end of the log (last window of a chained PCRB) next to the filter's sigma."""
    if not cal or len(df) == 0:
        return Markup("")
    pairs = []
    sd_l = cal.get("lever_arm_sd") or [None] * 3
    for n, s_f in zip(("lx", "ly", "lz"), sd_l):
        pairs.append((n, s_f, 100.0, "cm"))
    pairs.append(("td", cal.get("time_offset_sd"), 1000.0, "ms"))
    cells = []
    for n, s_f, k, unit in pairs:
        col = f"sd_{n}"
        if s_f is None or col not in df.columns:
            continue
        b = pd.to_numeric(df[col], errors="coerce").to_numpy(float)[-1]
        if not np.isfinite(b) or b <= 0 or not np.isfinite(float(s_f)):
            continue
        cells.append(f"{n} {k * b:.2f} vs {k * float(s_f):.2f} {unit} (σ / bound {float(s_f) / b:.2f})")
    if not cells:
        return Markup("")
    return Markup('<p class="note">Bound at the end of the log (last window; with the chained posterior Cramér-Rao bound '
            "of <code>uwbimu observability log</code> this is the σ a matched filter should reach) vs the estimator's "
            "σ of the calibration section: {}. σ / bound well below 1 means an over-confident "
            "filter, well above 1 one that does not use all the information.</p>").format("; ".join(cells))  # fmt: skip


def _observability_windows(df: pd.DataFrame, cal: Optional[dict] = None) -> Markup:
    """Timeline of the per-window table of ``uwbimu observability`` (t_start, t_end, sd_*, flags)."""
    from matplotlib.figure import Figure

    t0 = pd.to_numeric(df["t_start"], errors="coerce").to_numpy(float)
    t1 = pd.to_numeric(df["t_end"], errors="coerce").to_numpy(float)
    tc = 0.5 * (t0 + t1)

    def col(c):
        return pd.to_numeric(df[c], errors="coerce").replace([np.inf, -np.inf], np.nan).to_numpy(float)

    panels = []
    if "min_eigenvalue" in df.columns:
        panels.append(("min eigenvalue\n(scaled info)", [("min_eigenvalue", col("min_eigenvalue"))], None))
    lev = [(f"sd {n}", col(f"sd_{n}")) for n in ("lx", "ly", "lz") if f"sd_{n}" in df.columns]
    if lev:
        panels.append(("CRLB lever arm [m]", lev, "lever_arm_excited"))
    if "sd_td" in df.columns:
        panels.append(("CRLB t_d [s]", [("sd td", col("sd_td"))], "time_offset_excited"))
    if "gyro_rms" in df.columns:
        panels.append(("gyro RMS [rad/s]", [("gyro rms", col("gyro_rms"))], None))
    fig = Figure(figsize=(9.0, 1.9 * len(panels) + 1.0))
    for n, (label, series, flag) in enumerate(panels):
        ax = fig.add_subplot(len(panels), 1, n + 1)
        for name, y in series:
            ax.plot(tc, y, "o-", ms=3, lw=0.9, label=name)
        ys = np.concatenate([y[np.isfinite(y)] for _, y in series]) if series else np.array([])
        if len(ys) and np.all(ys > 0):
            ax.set_yscale("log")
        if flag is not None and flag in df.columns:
            bad = ~_as_bool(df[flag])
            for a, b in zip(t0[bad], t1[bad]):
                ax.axvspan(a, b, color="orange", alpha=0.2, lw=0)
        ax.set_ylabel(label, fontsize=8)
        ax.grid(True, alpha=0.3)
        if len(series) > 1:
            ax.legend(fontsize=7, ncol=3)
    fig.axes[-1].set_xlabel("window centre [s]")
    parts = [_fig("observability", fig, "Per-window observability: Cramér-Rao bounds of the lever arm and time offset "
                  "at each window's end (shaded: window flagged as not exciting the parameter: its ranges add less "
                  "than 3x the prior's precision).")]
    parts.append(_bound_vs_sigma(df, cal))
    rows = []
    for k in range(len(df)):
        flags = []
        if "lever_arm_excited" in df.columns and not _as_bool(df["lever_arm_excited"].iloc[[k]])[0]:
            flags.append("lever arm not excited")
        if "time_offset_excited" in df.columns and not _as_bool(df["time_offset_excited"].iloc[[k]])[0]:
            flags.append("time offset not excited")
        if flags:
            wd = str(df["weakest_direction"].iloc[k]) if "weakest_direction" in df.columns else ""
            rows.append([f"{t0[k]:.1f}–{t1[k]:.1f}", ", ".join(flags), wd])
    if rows:
        parts.append(_table(["window [s]", "flag", "weakest direction"], rows[:40], left=3))
    else:
        parts.append(Markup('<p class="note">Every window excites the lever arm and the time offset.</p>'))
    return _join(parts)


def _observability_section(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure

    df = inp.observability
    if df is None:
        return _missing(Markup("<code>observability.csv</code> not found (<code>uwbimu observability ... --out OUT</code>)."))
    if {"t_start", "t_end"} <= set(df.columns):
        return _observability_windows(df, inp.calibration)
    tcol = "t" if "t" in df.columns else df.columns[0]
    num = [c for c in df.columns if c != tcol and pd.api.types.is_numeric_dtype(df[c])][:8]
    if not num:
        return _missing(Markup("<code>observability.csv</code> has no numeric columns."))
    t = pd.to_numeric(df[tcol], errors="coerce").to_numpy(float)
    fig = Figure(figsize=(9.0, 1.6 * len(num) + 1.0))
    for n, c in enumerate(num):
        ax = fig.add_subplot(len(num), 1, n + 1)
        y = pd.to_numeric(df[c], errors="coerce").replace([np.inf, -np.inf], np.nan).to_numpy(float)
        ax.plot(t, y, "C0-", lw=0.9)
        pos = y[np.isfinite(y)]
        if len(pos) and np.all(pos > 0) and pos.max() / max(pos.min(), 1e-300) > 1e3:
            ax.set_yscale("log")
        ax.set_ylabel(c, fontsize=8)
        ax.grid(True, alpha=0.3)
    fig.axes[-1].set_xlabel(f"{tcol} [s]")
    return _fig("observability", fig, f"Observability / excitation indicators over time ({', '.join(num)}).")


def _warnings_section(inp: ReportInputs) -> Markup:
    if not inp.warnings:
        return Markup('<p class="note">No warnings recorded.</p>')
    return _join(_block("warn", w) for w in inp.warnings)



# --------------------------------------------------------------------------- batch calibration (uwbimu calibrate)
#: Files only ``uwbimu calibrate`` writes (``uwbimu.calibration.outputs.OUTPUT_FILES``).
BATCH_FILES = ("td_profile.csv", "anchors_estimated.csv")


def is_batch_output(inp: ReportInputs) -> bool:
    """Whether the folder holds ``uwbimu calibrate`` outputs: ``td_profile.csv`` or
    ``anchors_estimated.csv``, or a ``calibration.yaml`` in its layout (``method: batch-...``,
    ``time_offset`` a mapping with a ``verdict``)."""
    if inp.td_profile is not None or inp.anchors_estimated is not None:
        return True
    c = inp.calibration or {}
    return str(c.get("method", "")).startswith("batch") or (
        isinstance(c.get("time_offset"), dict) and "verdict" in c["time_offset"])


def _not_found_or_lacks(name: str, absent: bool, need: Sequence[str]) -> Markup:
    if absent:
        return Markup("<code>{}</code> not found.").format(name)
    return Markup("<code>{}</code> lacks the column(s) {}.").format(name, ", ".join(need))


def _part(key: str, title: str, content: Markup, **attrs: Any) -> Markup:
    return _block("part", key, title, content, [(k.replace("_", "-"), str(v)) for k, v in attrs.items()])


def _batch_td(cal: dict) -> dict:
    td = cal.get("time_offset")
    return td if isinstance(td, dict) else {}


def _batch_profile_part(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure

    td = _batch_td(inp.calibration or {})
    verdict = str(td.get("verdict", "unknown"))
    prof = inp.td_profile
    if prof is None:
        return _part("td-profile", "Time-offset profile", _missing(Markup(
            "<code>td_profile.csv</code> not found (profile disabled: <code>td_profile: {{enabled: false}}</code>); "
            "t_d verdict in <code>calibration.yaml</code>: {}.").format(verdict)), verdict=verdict)
    if "time_offset" not in prof.columns or not ({"delta_chi2", "chi2"} & set(prof.columns)):
        return _part("td-profile", "Time-offset profile", _missing(Markup(
            "<code>td_profile.csv</code> lacks <code>time_offset</code> or <code>delta_chi2</code>/<code>chi2</code> "
            "(columns: {}).").format(", ".join(map(str, prof.columns)))), verdict=verdict)
    g = pd.to_numeric(prof["time_offset"], errors="coerce").to_numpy(float)
    if "delta_chi2" in prof.columns:
        d = pd.to_numeric(prof["delta_chi2"], errors="coerce").to_numpy(float)
    else:
        c2 = pd.to_numeric(prof["chi2"], errors="coerce").to_numpy(float)
        d = c2 - np.nanmin(c2)
    order = np.argsort(g)
    g, d = g[order], d[order]
    value, sd = td.get("value"), td.get("sd")
    ci = td.get("profile_confidence_interval")
    held = bool(td.get("held_at_prior", False))
    fig = Figure(figsize=(7.0, 3.6))
    ax = fig.add_subplot(111)
    ax.plot(1000 * g, d, "o-", ms=3, lw=1.0, color="C0", label="profile (Δχ²)")
    if ci is not None and len(ci) == 2:
        ax.axvspan(1000 * float(ci[0]), 1000 * float(ci[1]), color="C2", alpha=0.15, lw=0,
                   label=f"profile interval [{1000 * float(ci[0]):.1f}, {1000 * float(ci[1]):.1f}] ms")
    if value is not None:
        lab = (f"held at prior {1000 * float(value):.1f} ms" if held or sd is None
               else f"t_d = {1000 * float(value):.1f} ± {1000 * float(sd):.1f} ms")
        ax.axvline(1000 * float(value), color="C3", ls="--" if held else "-", lw=1.0, label=lab)
    ax.set_xlabel("time offset t_d [ms]")
    ax.set_ylabel("Δχ² (profile)")
    ax.set_title(f"verdict: {verdict}", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)

    def ms(v):
        return "–" if v is None else _fmt(1000 * float(v), 2)

    rows = [["verdict", _span("ok" if verdict == "identified" else "bad", verdict)],
            ["t_d [ms]", ms(value)], ["σ (marginal) [ms]", ms(td.get("sd_marginal", sd))],
            ["σ (profile curvature) [ms]", ms(td.get("sd_curvature"))],
            ["profile interval [ms]", "–" if ci is None else f"{ms(ci[0])} … {ms(ci[1])}"],
            ["grid [ms]", f"{ms(np.nanmin(g))} … {ms(np.nanmax(g))} ({len(g)} points)"],
            ["held at prior", "yes" if held else "no"]]
    scale = ((inp.calibration or {}).get("imu_noise") or {}).get("scale") or {}
    if scale.get("method") == "variance_component":  # the IMU model the profile was computed under
        sd_s = scale.get("scale_sd")
        rows.append(["IMU noise scale (estimated)", _fmt(float(scale["scale"]), 3)
                     + ("" if sd_s is None else f" ± {_fmt(float(sd_s), 2)}")])
    parts = [_table(["t_d", "value"], rows)]
    if td.get("advice"):
        parts.append(_block("warn", Markup("t_d not identified on this log: {}").format(td["advice"])))
    parts.append(_fig("batch-td-profile", fig, "Profile of the time offset: Δχ² of the solve with t_d held at each grid "
                      "point (td_profile.csv), the reported value (dashed when held at its prior) and the profile's "
                      "confidence interval (calibration.yaml)."))
    extra = {"imu_noise_scale": repr(float(scale["scale"]))} if scale.get("method") == "variance_component" else {}
    return _part("td-profile", "Time-offset profile", _join(parts), verdict=verdict, **extra)


def _range_rows(res: pd.DataFrame) -> tuple[pd.DataFrame, int]:
    """Two-way range rows of a batch ``residuals.csv`` (TDoA rows have ``kind == "tdoa"``) and the count dropped."""
    if "kind" in res.columns:
        keep = res["kind"].astype(str) == "range"
        return res[keep].reset_index(drop=True), int((~keep).sum())
    return res, 0


def _anchor_table(inp: ReportInputs) -> tuple[Optional[pd.DataFrame], str]:
    """Anchor positions in the trajectory's frame: ``anchors_estimated.csv``, else the dataset's."""
    a = inp.anchors_estimated
    if a is not None and {"anchor", "x", "y", "z"} <= set(a.columns):
        return a, "anchors_estimated.csv"
    if inp.dataset is not None and inp.dataset.anchors is not None:
        return inp.dataset.anchors, "dataset anchors.csv"
    return None, ""


def line_of_sight_azimuth(res: pd.DataFrame, traj: pd.DataFrame, anchors: pd.DataFrame,
                          lever_arm: Optional[Sequence[float]] = None) -> np.ndarray:
    """Body-frame azimuth [deg] of the line of sight from the tag antenna to the anchor, per row.

    Parameters
    ----------
    res : rows with ``t`` (UWB clock) [s] and ``anchor``.
    traj : ``t`` (UWB clock) [s], ``px, py, pz`` [m] (world) and ``qw, qx, qy, qz`` (body to world).
    anchors : ``anchor, x, y, z`` [m], same world frame as ``traj``.
    lever_arm : tag antenna in the body frame [m] (zero when None): one (3,) for every row, or a dict
        ``{tag: (3,)}`` used with ``res["tag"]`` (several tags; a tag not in it gets zero).

    Returns
    -------
    (N,) azimuth ``atan2(u_y, u_x)`` of ``u = R^T (a - p - R l)`` in (-180, 180] deg; NaN outside the
    trajectory's time span or for an unknown anchor.
    """
    from scipy.spatial.transform import Rotation, Slerp

    tt = traj["t"].to_numpy(float)
    t = res["t"].to_numpy(float)
    inside = (t >= tt[0]) & (t <= tt[-1])
    tc = np.clip(t, tt[0], tt[-1])
    p = np.column_stack([np.interp(tc, tt, traj[c].to_numpy(float)) for c in ("px", "py", "pz")])
    q = traj[["qx", "qy", "qz", "qw"]].to_numpy(float)
    R = Slerp(tt, Rotation.from_quat(q))(tc)
    if isinstance(lever_arm, dict):
        tags = res["tag"].astype(str) if "tag" in res.columns else pd.Series([""] * len(res))
        lev = np.array([lever_arm.get(k, (0.0, 0.0, 0.0)) for k in tags], float).reshape(-1, 3)
    else:
        lev = np.zeros(3) if lever_arm is None else np.asarray(lever_arm, float)
    pos = {str(r.anchor): (r.x, r.y, r.z) for r in anchors.itertuples(index=False)}
    a = np.array([pos.get(str(k), (np.nan, np.nan, np.nan)) for k in res["anchor"]], float).reshape(-1, 3)
    u = R.inv().apply(a - p) - lev
    az = np.degrees(np.arctan2(u[:, 1], u[:, 0]))
    az[~inside | ~np.all(np.isfinite(a), axis=1)] = np.nan
    return az


def _anchor_order(ids) -> list:
    return sorted(set(map(str, ids)), key=lambda s: (len(s), s))


def _batch_angle_part(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure

    res = inp.residuals
    need = [c for c in ("t", "anchor", "residual") if res is None or c not in res.columns]
    if res is None or need:
        return _part("residual-angle", "Residual vs line-of-sight angle", _missing(
            _not_found_or_lacks("residuals.csv", res is None, need)), x_axis="none")
    rr, n_tdoa = _range_rows(res)
    traj = inp.trajectory
    anchors, src = _anchor_table(inp)
    why = []
    if traj is None or not {"t", "px", "py", "pz", "qw", "qx", "qy", "qz"} <= set(traj.columns):
        why.append(Markup("<code>trajectory.csv</code> has no attitude (<code>qw, qx, qy, qz</code>)"))
    if anchors is None:
        why.append(Markup("no anchor positions (neither <code>anchors_estimated.csv</code> nor <code>--dataset</code>)"))
    if not len(rr):
        why.append("no two-way range rows (TDoA only)")
    cal = inp.calibration or {}
    lever = cal.get("lever_arm")
    if isinstance(cal.get("tags"), dict) and "tag" in rr.columns:
        # several tags: each row's line of sight leaves its own tag's antenna
        lever = {str(k): v.get("lever_arm") or (0.0, 0.0, 0.0) for k, v in cal["tags"].items()}
    angle = not why
    notes = []
    if angle:
        x = line_of_sight_azimuth(rr, traj, anchors, lever)
        data = rr.assign(x=x)[np.isfinite(x)]
        xlabel, mode = "body-frame azimuth of the line of sight [deg]", "azimuth"
        notes.append(Markup("x axis: azimuth of the line of sight from the tag antenna (trajectory + lever arm of "
                            "<code>calibration.yaml</code>{}) to the anchor ({}), in the body frame, 0° = body x, "
                            "90° = body y.").format("" if lever is not None else ", absent: zero used", src))
        if n_tdoa:
            notes.append(Markup("{} TDoA rows left out (no single line of sight).").format(n_tdoa))
    else:
        data = res.assign(x=pd.to_numeric(res["t"], errors="coerce"))
        xlabel, mode = "t [s] (UWB clock)", "time"
        notes.append(Markup("Residual vs <b>time</b>, not angle: {}.").format(Markup("; ").join(why)))
    ids = _anchor_order(data["anchor"])
    if not ids:
        return _part("residual-angle", "Residual vs line-of-sight angle", _missing("no residual rows."), x_axis=mode)
    ncol = min(4, len(ids))
    nrow = int(np.ceil(len(ids) / ncol))
    fig = Figure(figsize=(2.6 * ncol + 0.6, 2.2 * nrow + 0.6))
    e_all = 100 * pd.to_numeric(data["residual"], errors="coerce").to_numpy(float)
    lim = np.nanpercentile(np.abs(e_all), 99) if np.isfinite(e_all).any() else 1.0
    out_col = _as_bool(data["outlier"]) if "outlier" in data.columns else np.zeros(len(data), bool)
    aid = data["anchor"].astype(str).to_numpy()
    xs = data["x"].to_numpy(float)
    rows = []
    edges = np.linspace(-180.0, 180.0, 13)
    for n, a in enumerate(ids):
        ax = fig.add_subplot(nrow, ncol, n + 1)
        m = aid == a
        ax.plot(xs[m & ~out_col], e_all[m & ~out_col], ".", ms=1.5, color="C0", alpha=0.4)
        if (m & out_col).any():
            ax.plot(xs[m & out_col], e_all[m & out_col], "x", ms=2.5, color="C3", alpha=0.6)
        if mode == "azimuth":
            med = [np.median(e_all[m & (xs >= lo) & (xs < hi)]) if np.sum(m & (xs >= lo) & (xs < hi)) >= 5 else np.nan
                   for lo, hi in zip(edges[:-1], edges[1:])]
            med = np.array(med)
            ax.plot(0.5 * (edges[:-1] + edges[1:]), med, "k-o", ms=2.5, lw=1.0)
            ax.set_xlim(-180, 180)
            ax.set_xticks([-180, -90, 0, 90, 180])
            ok = np.isfinite(med)
            rows.append([a, str(int(m.sum())), str(int(30 * ok.sum())),
                         _fmt(np.ptp(med[ok]) if ok.sum() >= 2 else np.nan, 1)])
        ax.set_ylim(-1.1 * lim, 1.1 * lim)
        ax.axhline(0.0, color="gray", lw=0.6)
        ax.set_title(f"anchor {a}", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(True, alpha=0.3)
    fig.supxlabel(xlabel, fontsize=8)
    fig.supylabel("residual [cm]", fontsize=8)
    parts = [Markup('<p class="note">{}</p>').format(Markup(" ").join(notes))]
    if rows:
        parts.append(_table(["anchor", "ranges", "azimuth covered [deg]", "peak-to-peak of 30° medians [cm]"], rows))
    cap = ("Residual (predicted − measured range, with the estimated range bias) per anchor against "
           + ("the body-frame azimuth of the line of sight; black: median per 30° bin (5 ranges or more)"
              if mode == "azimuth" else "time") + "; red ×: down-weighted (|z| > Huber k, residuals.csv outlier).")
    parts.append(_fig("batch-residual-angle", fig, cap))
    return _part("residual-angle", "Residual vs line-of-sight angle" if mode == "azimuth" else "Residual vs time",
                 _join(parts), x_axis=mode, anchors_from=src or "none")


def _xy_correlation(cal: dict, anchor: str) -> Optional[float]:
    """x-y correlation of an estimated anchor from ``calibration.yaml`` ``correlations`` (None when absent)."""
    corr = cal.get("correlations") or {}
    names = list(corr.get("names") or [])
    try:
        i, j = names.index(f"anchor_x_{anchor}"), names.index(f"anchor_y_{anchor}")
        return float(corr["matrix"][i][j])
    except (ValueError, KeyError, IndexError, TypeError):
        return None


def error_ellipse(sd_x: float, sd_y: float, rho: float = 0.0, k: float = 2.0) -> tuple[float, float, float]:
    """Semi-axes [same unit as sd] and orientation [deg, major axis from x] of the k-sigma ellipse of a
    2-D Gaussian with standard deviations ``sd_x, sd_y`` and correlation ``rho``."""
    c = np.array([[sd_x**2, rho * sd_x * sd_y], [rho * sd_x * sd_y, sd_y**2]])
    w, v = np.linalg.eigh(c)
    w = np.clip(w, 0.0, None)
    return k * float(np.sqrt(w[1])), k * float(np.sqrt(w[0])), float(np.degrees(np.arctan2(v[1, 1], v[0, 1])))


def _nice_factor(x: float) -> float:
    """Smallest 1-2-5 number >= x (at least 1)."""
    if not np.isfinite(x) or x <= 1.0:
        return 1.0
    e = 10 ** np.floor(np.log10(x))
    for m in (1, 2, 5, 10):
        if m * e >= x:
            return float(m * e)
    return float(10 * e)


def _batch_ellipse_part(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure
    from matplotlib.patches import Ellipse

    a = inp.anchors_estimated
    need = [c for c in ("anchor", "x", "y", "sd_x", "sd_y", "estimated") if a is None or c not in a.columns]
    if a is None or need:
        return _part("anchor-ellipses", "Anchor error ellipses", _missing(_not_found_or_lacks(
            "anchors_estimated.csv", a is None, need)), estimated="0")
    cal = inp.calibration or {}
    est = _as_bool(a["estimated"])
    xy = a[["x", "y"]].to_numpy(float)
    sd = a[["sd_x", "sd_y"]].to_numpy(float)
    ell, rows = [], []
    for k, r in enumerate(a.itertuples(index=False)):
        aid = str(r.anchor)
        sdz = getattr(r, "sd_z", np.nan)
        if est[k]:
            rho = _xy_correlation(cal, aid)
            major, minor, ang = error_ellipse(sd[k, 0], sd[k, 1], 0.0 if rho is None else rho)
            ell.append((xy[k], major, minor, ang))
            rows.append([aid, "estimated", _fmt(r.x, 3), _fmt(r.y, 3), _fmt(getattr(r, "z", np.nan), 3),
                         _fmt(100 * sd[k, 0], 1), _fmt(100 * sd[k, 1], 1), _fmt(100 * float(sdz), 1),
                         _fmt("–" if rho is None else rho, 2), _fmt(100 * major, 1), _fmt(100 * minor, 1), _fmt(ang, 0)])
        else:
            rows.append([aid, "fixed", _fmt(r.x, 3), _fmt(r.y, 3), _fmt(getattr(r, "z", np.nan), 3)] + ["–"] * 7)
    fig = Figure(figsize=(6.5, 5.5))
    ax = fig.add_subplot(111)
    traj = inp.trajectory
    if traj is not None and {"px", "py"} <= set(traj.columns):
        ax.plot(traj["px"], traj["py"], "-", color="0.7", lw=0.7, label="trajectory")
    if (~est).any():
        ax.plot(xy[~est, 0], xy[~est, 1], "k^", ms=7, label="fixed (surveyed)")
    span = float(np.ptp(xy[np.isfinite(xy).all(axis=1)], axis=0).max()) if len(xy) > 1 else 1.0
    big = max([e[1] for e in ell], default=0.0)
    mag = _nice_factor(0.05 * span / big) if big > 0 else 1.0
    for n, (c, major, minor, ang) in enumerate(ell):
        ax.add_patch(Ellipse(tuple(c), 2 * mag * major, 2 * mag * minor, angle=ang, fill=False, color="C3", lw=1.2,
                             label=f"estimated, 2σ ellipse ×{mag:g}" if n == 0 else None))
    if est.any():
        ax.plot(xy[est, 0], xy[est, 1], "o", color="C3", ms=4)
    for k, r in enumerate(a.itertuples(index=False)):
        ax.annotate(str(r.anchor), tuple(xy[k]), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3)
    parts = [_table(["anchor", "position", "x [m]", "y [m]", "z [m]", "σx [cm]", "σy [cm]", "σz [cm]", "ρxy",
                     "2σ major [cm]", "2σ minor [cm]", "major axis [deg from x]"], rows, left=2)]
    if not est.any():
        parts.insert(0, Markup('<p class="note">No anchor was estimated: every anchor is fixed.</p>'))
    sys_attrs = {}
    sysm = ((cal.get("anchors") or {}).get("systematic") or {}) if isinstance(cal.get("anchors"), dict) else {}
    if sysm:
        disp = sysm.get("displacements") or {}
        big = max(disp.items(), key=lambda kv: np.linalg.norm(kv[1].get("displacement", [0.0])), default=None)
        sd_sys = sysm.get("sd")
        sys_attrs = {"systematic_sd_cm": _fmt(100 * float(sd_sys), 1) if sd_sys is not None else "–",
                     "surveyed_used": int(sysm.get("surveyed_anchors_used", 0))}
        text = Markup('<p class="note">The σ of the estimated anchors {} a systematic part of {} cm per axis, '
                      "measured on {} surveyed anchors: had each been estimated, the log would have moved it{} "
                      '(linearised leave-one-out; docs/calibrate.md "The self-survey\'s systematic sigma").</p>').format(
            "include" if sysm.get("applied") else ("do not include (anchor_systematic: none)" if sd_sys is not None
                                                   else "do not include (no surveyed anchor with ranges to measure)"),
            sys_attrs["systematic_sd_cm"], sys_attrs["surveyed_used"],
            Markup(" by up to {} cm (anchor {})").format(_fmt(100 * float(np.linalg.norm(big[1]["displacement"])), 1),
                                                        big[0]) if big else "")
        parts.insert(0, text)
    parts.append(_fig("batch-anchor-ellipses", fig,
                      f"Top view of the anchors (anchors_estimated.csv, calibration frame): fixed anchors as triangles, "
                      f"estimated ones with their horizontal 2σ marginal ellipse (x-y correlation from calibration.yaml "
                      f"correlations), drawn ×{mag:g}."))
    return _part("anchor-ellipses", "Anchor error ellipses", _join(parts), estimated=str(int(est.sum())),
                 magnification=f"{mag:g}", **sys_attrs)


def _med_mad(x: np.ndarray) -> tuple[float, float]:
    x = x[np.isfinite(x)]
    if not len(x):
        return np.nan, np.nan
    m = float(np.median(x))
    return m, float(np.median(np.abs(x - m)))


def _batch_before_after_part(inp: ReportInputs) -> Markup:
    res = inp.residuals
    need = [c for c in ("anchor", "residual") if res is None or c not in res.columns]
    if res is None or need:
        return _part("before-after", "Residuals without / with the range bias", _missing(
            _not_found_or_lacks("residuals.csv", res is None, need)), before="absent")
    rr, n_tdoa = _range_rows(res)
    cal = inp.calibration or {}
    bias = cal.get("anchor_bias") if isinstance(cal.get("anchor_bias"), dict) else None
    bias_sd = cal.get("anchor_bias_sd") if isinstance(cal.get("anchor_bias_sd"), dict) else {}
    e = pd.to_numeric(rr["residual"], errors="coerce").to_numpy(float)
    aid = rr["anchor"].astype(str).to_numpy()
    drift = pd.to_numeric(rr["bias_drift"], errors="coerce").to_numpy(float) if "bias_drift" in rr.columns else None
    down = _as_bool(rr["outlier"]) if "outlier" in rr.columns else None
    before = None
    if bias is not None:  # the constant and the slowly varying bias (this part's "without")
        from uwbimu.calibration.outputs import residual_without

        before = residual_without(rr, {str(k): v for k, v in bias.items()}, columns=("bias_drift",))
    rows = []
    ids = _anchor_order(aid)
    for a in ids + ["all"]:
        m = np.ones(len(aid), bool) if a == "all" else aid == a
        mb, sb = _med_mad(before[m]) if before is not None else (np.nan, np.nan)
        ma, sa = _med_mad(e[m])
        bv = bias.get(a) if (bias is not None and a != "all") else None
        rows.append([a, str(int(m.sum())), "–" if down is None else str(int(down[m].sum())),
                     "–" if bv is None else f"{100 * float(bv):+.1f} ± {_fmt(100 * float(bias_sd.get(a, np.nan)), 1)}",
                     _fmt(100 * mb, 2), _fmt(100 * sb, 2), _fmt(100 * ma, 2), _fmt(100 * sa, 2)])
    notes = [Markup("Residual = predicted − measured range (<code>residuals.csv</code> <code>residual</code>, with the "
                    "estimated range bias); MAD = median |x − median|, unscaled.")]
    if bias is None:
        notes.append(Markup("<code>calibration.yaml</code> has no <code>anchor_bias</code>: the “without” columns "
                            "cannot be formed."))
    elif drift is not None:
        notes.append(Markup("“Without” removes the constant bias (<code>anchor_bias</code>) and the slowly varying one "
                            "(<code>bias_drift</code> column)."))
    else:
        notes.append(Markup("“Without” removes the constant bias (<code>anchor_bias</code>); <code>residuals.csv</code> "
                            "has no <code>bias_drift</code> column (no slowly varying bias estimated)."))
    if down is None:
        notes.append(Markup("<code>residuals.csv</code> has no <code>outlier</code> column: down-weighted rows not "
                            "counted."))
    rm = cal.get("range_model") if isinstance(cal.get("range_model"), dict) else {}
    hub = rm.get("huber") if isinstance(rm.get("huber"), dict) else {}
    huber_k = hub.get("k", rm.get("huber_k"))
    if isinstance(huber_k, (int, float)):
        how = ("chosen from this log (<code>huber_k: adaptive</code>: the smallest variance of the estimate on a "
               "first solve's residuals, {:.2f} × that of least squares)").format(
                   float(hub["variance_vs_least_squares"])) \
            if hub.get("selection") == "adaptive" and "variance_vs_least_squares" in hub else "as configured"
        notes.append(Markup("Down-weighted: |residual| > {:.2f} σ, the Huber threshold {}.").format(
            float(huber_k), Markup(how)))
    if n_tdoa:
        notes.append(Markup("{} TDoA rows left out (their bias is a difference of two anchors').").format(n_tdoa))
    table = _table(["anchor", "ranges", "down-weighted", "bias ± 1σ [cm]", "median without [cm]", "MAD without [cm]",
                    "median with [cm]", "MAD with [cm]"], rows)
    return _part("before-after", "Residuals without / with the range bias",
                 table + Markup('<p class="note">{}</p>').format(Markup(" ").join(notes)),
                 before="present" if bias is not None else "absent",
                 drift="present" if drift is not None else "absent",
                 huber_k=f"{float(huber_k):.3f}" if isinstance(huber_k, (int, float)) else "unknown",
                 huber_selection=str(hub.get("selection", "unknown")))


def _batch_sigma_part(inp: ReportInputs) -> Markup:
    """How each calibration sigma was formed: white model, HAC sandwich, block check (calibration.yaml)."""
    cal = inp.calibration or {}
    cov = cal.get("covariance") or {}
    method = str(cov.get("method", "unknown"))
    bc = cov.get("block_check") or {}
    per = bc.get("parameters") or {}
    names = (cal.get("correlations") or {}).get("names") or []
    sd_lever, sd_lever_m = cal.get("lever_arm_sd") or [], cal.get("lever_arm_sd_model") or []
    td = _batch_td(cal)
    sd, sd_m = {}, {}
    for i, c in enumerate("xyz"):
        if i < len(sd_lever):
            sd[f"lever_arm_{c}"] = (sd_lever[i], 100.0, "cm")
        if i < len(sd_lever_m):
            sd_m[f"lever_arm_{c}"] = sd_lever_m[i]
    if td.get("sd") is not None:
        sd["time_offset"] = (td["sd"], 1000.0, "ms")
        sd_m["time_offset"] = td.get("sd_model")
    idf = cal.get("identifiability") or {}
    lever_v = idf.get("lever_arm") or {}
    lever_v = lever_v if set(lever_v) <= {"x", "y", "z"} else next(iter(lever_v.values()), {})  # several tags: the first's
    verdict = {f"lever_arm_{c}": (lever_v.get(c) or {}).get("verdict", "–") for c in "xyz"}
    verdict["time_offset"] = str(td.get("verdict", "–"))
    rows = []
    for n in [n for n in names if n in sd]:
        v, k, unit = sd[n]
        b = per.get(n) or {}
        rows.append([n, unit, _fmt(k * float(sd_m[n]), 3) if sd_m.get(n) is not None else "–", _fmt(k * float(v), 3),
                     verdict.get(n, "–"),
                     _fmt(b["variance_ratio"], 3) if b else "–", _fmt(b["dof"], 3) if b else "–",
                     _fmt(b["p_value"], 3) if b else "–",
                     (_span("bad", "yes") if b.get("widened") else "no") if b else "–"])
    if not rows:
        return _part("sigma", "How the σ were formed", _missing("calibration.yaml has no lever-arm σ."), method=method)
    if bc:
        note = Markup('<p class="note">σ of the white range-noise model (GTSAM marginals), and the reported σ ({}). '
                      "The block check sums the range scores over {} contiguous parts of the log ({} s each): "
                      "where their variance exceeds the HAC sandwich's (ratio &gt; 1) the reported σ is the blocks'; "
                      "p is the test of the sandwich against them (see docs/calibrate.md, \"The block check\").</p>"
                      ).format(method, bc.get("blocks"), _fmt(bc.get("block_s"), 3))
    else:
        note = Markup('<p class="note">σ of the white range-noise model (GTSAM marginals), and the reported σ ({}); '
                      "no block check in this calibration.yaml (<code>block_check: {{blocks: 0}}</code>, "
                      "<code>covariance: model</code>, or written before it existed).</p>").format(method)
    tab = _table(["parameter", "unit", "σ model", "σ reported", "verdict", "block / HAC variance", "dof", "p",
                  "widened"], rows)
    widened = sum(1 for b in per.values() if b.get("widened"))
    return _part("sigma", "How the σ were formed", note + tab, method=method, blocks=bc.get("blocks", 0),
                 widened=widened)


def _batch_section(inp: ReportInputs) -> Optional[Markup]:
    """The ``uwbimu calibrate`` section, or None when the folder holds no batch-calibration output."""
    if not is_batch_output(inp):
        return None
    parts = []
    for key, title, fn in (("td-profile", "Time-offset profile", _batch_profile_part),
                           ("residual-angle", "Residual vs line-of-sight angle", _batch_angle_part),
                           ("anchor-ellipses", "Anchor error ellipses", _batch_ellipse_part),
                           ("before-after", "Residuals without / with the range bias", _batch_before_after_part),
                           ("sigma", "How the σ were formed", _batch_sigma_part)):
        try:
            parts.append(fn(inp))
        except EvalInputError:
            raise
        except Exception as exc:  # one broken part must not lose the others; say what failed
            parts.append(_part(key, title, _block("warn", f"This part failed: {type(exc).__name__}: {exc}"),
                               failed="yes"))
    return Markup('<p class="note">Outputs of <code>uwbimu calibrate</code> (batch MAP, see docs/calibrate.md).</p>') + \
        _join(parts)


SECTIONS = {
    "calibration": _calibration_section,
    "batch": _batch_section,
    "convergence": _convergence_section,
    "residuals": _residuals_section,
    "nis": _nis_section,
    "trajectory": _trajectory_section,
    "repeatability": _repeatability_section,
    "observability": _observability_section,
    "warnings": _warnings_section,
}


def render_report(out_dir: Union[str, os.PathLike], dataset=None, title: Optional[str] = None) -> str:
    """Render the report of ``out_dir`` as an HTML string (nothing written)."""
    out = Path(out_dir)
    if not out.is_dir():
        raise EvalInputError(f"{out}: output folder not found")
    if isinstance(dataset, (str, os.PathLike)):
        from uwbimu.io.loader import load_dataset

        dataset = load_dataset(dataset)
    inp = ReportInputs(out, dataset)
    if inp.calibration is None and inp.trajectory is None and inp.residuals is None:
        raise EvalInputError(f"{out}: no estimator output (calibration.yaml, trajectory.csv, residuals.csv) found")
    body = []
    for key, fn in SECTIONS.items():
        try:
            content = fn(inp)
        except EvalInputError:
            raise
        except Exception as exc:  # one broken input must not lose the whole report; say what failed
            content = _block("warn", f"This section failed: {type(exc).__name__}: {exc}")
        if content is None:  # a section that does not apply to this folder (batch)
            continue
        # a section returns markup; a plain string would be escaped by the template (shown, never run)
        body.append({"key": key, "title": SECTION_TITLES[key], "content": content})
    try:
        from importlib.metadata import version

        ver = version("uwbimu")
    except Exception:  # not installed (source checkout)
        ver = "unknown"
    if title is None:
        name = dataset.meta.name if dataset is not None else out.name
        title = f"uwbimu calibration report — {name}"
    return _templates().get_template("report.html.j2").render(
        title=title, version=ver, out_dir=str(out),
        generated=_dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), sections=body,
    )


def write_report(out_dir: Union[str, os.PathLike], dataset=None, path: Optional[Union[str, os.PathLike]] = None,
                 title: Optional[str] = None) -> Path:
    """Write ``OUT/report.html`` (or ``path``) atomically and return its path.

    Parameters
    ----------
    out_dir : estimator output folder (``uwbimu estimate ... --out OUT``).
    dataset : optional :class:`~uwbimu.io.dataset.Dataset` or dataset folder: adds
        anchors, the documented/true calibration and, when ``OUT/evaluation.json``
        is absent, an evaluation against the dataset's ground truth (alignment
        from ``meta.extra.groundtruth_align``, default ``none``).
    """
    html_text = render_report(out_dir, dataset=dataset, title=title)
    target = Path(path) if path is not None else Path(out_dir) / "report.html"
    return write_text(target, html_text)
