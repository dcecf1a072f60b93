"""The report's sections for every estimator output (the batch-only section is in :mod:`.batch`)."""

from __future__ import annotations

from typing import Optional

import numpy as np
import pandas as pd
from markupsafe import Markup

from uwbimu.eval.report.common import (CAL_COLUMNS, _as_bool, _block, _fig, _fmt, _join, _missing, _sd_col, _span,
                                       _table, calibration_estimate)
from uwbimu.eval.report.inputs import CHI2_1_95, CHI2_1_MEDIAN, ReportInputs
from uwbimu.formatting import format_number, format_value_sigma, natural_key
from uwbimu.io.calibration_file import sd_or_none
from uwbimu.models.blocks import CALIBRATION_BLOCKS, calibration_components
from uwbimu.models.state import ERROR_STATE_NAMES


# --------------------------------------------------------------------------- sections
def _tagged(element: str, cls: str, attrs: dict, content) -> Markup:
    return _block("tagged", element, cls, [(k, str(v)) for k, v in attrs.items()], content)


def _calibration_section(inp: ReportInputs):
    c = inp.calibration
    if c is None:
        return _missing(Markup("<code>calibration.yaml</code> not found in the output folder."))
    _, ref_label = inp.reference_lever_arm()
    td = inp.time_offset()
    rows, classes = [], []
    header = ["parameter", "estimate ± 1σ", f"{ref_label or 'reference'}", "error", "z = error/σ"]

    def add(name, v, s, ref, unit, scale=1.0):
        s = sd_or_none(s)
        err = (v - ref) if (ref is not None and v is not None) else None
        z = err / s if (err is not None and s) else None
        flag = z is not None and abs(z) > 3
        rows.append([
            f"{name} [{unit}]", format_value_sigma(None if v is None else v * scale, None if s is None else s * scale),
            "–" if ref is None else _same_place(ref * scale, None if s is None else s * scale),
            "–" if err is None else _same_place(err * scale, None if s is None else s * scale),
            "–" if z is None else _span("bad" if flag else "ok", f"{z:+.2f}"),
        ])
        classes.append("flag" if flag else "")

    for b in CALIBRATION_BLOCKS:  # one row per component of each calibration block
        values, sds = calibration_estimate(c, b)
        ref = inp.reference(b)
        scale, unit = b.table
        for i, ax in enumerate(b.axes if values is not None else ()):
            add(f"{b.label} {ax}".strip(), values[i], sds[i], None if ref is None else ref[i], unit, scale=scale)
    parts = [_table(header, rows, classes)]
    # the modes and the verdict, from the one source (ReportInputs.time_offset: calibration.yaml + the run's events)
    bits = []
    if "lever_arm_mode" in c:
        bits.append(Markup("lever arm <code>{}</code>").format(c["lever_arm_mode"]))
    attrs = {"estimator": inp.estimator()}
    if td:
        attrs.update({"td-mode": td["mode"], "td-verdict": td.get("verdict") or "unknown"})
        extra = (Markup(" (configured <code>{}</code>)").format(td["configured_mode"])
                 if td.get("configured_mode") and td["configured_mode"] != td["mode"] else "")
        bits.append(Markup("time offset <code>{}</code>{}, verdict <b>{}</b>").format(
            td["mode"], extra, td.get("verdict") or "unknown"))
    if "anchor_bias_mode" in c:
        bits.append(Markup("anchor bias <code>{}</code>").format(c["anchor_bias_mode"]))
    if bits:
        parts.append(_tagged("p", "note", {"mode": td.get("mode", "unknown"), "verdict": td.get("verdict") or "unknown"},
                             Markup("Modes — {}.").format(Markup(", ").join(bits))))
    if td.get("mode") == "consider":
        parts.append(Markup('<p class="note">Consider mode: t_d was held at its prior and not updated by the data '
                            "(its uncertainty is kept in the other σ); its σ is the prior's.</p>"))
    elif td.get("mode") == "fixed":
        parts.append(Markup('<p class="note">t_d was held at {} ms; the other values and σ are conditional on it '
                            "(its uncertainty is not in them).</p>").format(format_number(1000 * float(td["value"]))))
    if ref_label:
        note = (inp.dataset.meta.extra or {}).get("lever_arm_note", "")
        parts.append(Markup('<p class="note">Reference lever arm: <code>{}</code> of dataset.yaml (simulation truth, or '
                            'the value documented by the source for real data). {}</p>').format(
            "truth.lever_arm" if ref_label == "reference" else "tags[0].lever_arm", note))
    brows = []
    for key, unit in (("accel_bias", "m/s²"), ("gyro_bias", "rad/s")):
        if c.get(key) is not None:
            sd = c.get(f"{key}_sd") or [None] * 3
            brows.append([f"{key.replace('_', ' ')} [{unit}]"] + [format_value_sigma(v, s) for v, s in zip(c[key], sd)])
    if brows:
        parts.append(_table(["IMU bias", "x", "y", "z"], brows))
    if isinstance(c.get("anchor_bias"), dict):
        sd = c.get("anchor_bias_sd") or {}
        kb = (inp.dataset.meta.known_anchor_bias or {}) if inp.dataset is not None else {}
        arows = [[a, format_value_sigma(100 * float(c["anchor_bias"][a]),
                                        None if sd_or_none(sd.get(a)) is None else 100 * float(sd[a])),
                  format_number(100 * float(kb[a])) if a in kb else "–"]
                 for a in sorted(c["anchor_bias"], key=natural_key)]
        parts.append(_table(["anchor", "estimated bias ± 1σ [cm]", "known bias [cm]"], arows))
    if inp.metrics:
        parts.append(_metrics_table(inp))
        other = str(((inp.dataset.meta.extra or {}) if inp.dataset is not None else {}).get("groundtruth_align",
                                                                                             "none")) != "none"
        attrs["metrics-vs-truth"] = "n/a" if other else "shown"
    return _join(parts), attrs


def _same_place(x: float, sigma) -> str:
    """``x`` to the decimal place of ``sigma`` by the one rounding rule (3 significant digits without a σ)."""
    if sigma is None or not sigma > 0:
        return format_number(x)
    return format_value_sigma(x, sigma).split(" ± ")[0]


def _metric_value(v) -> str:
    if isinstance(v, list):
        return ", ".join(_metric_value(x) for x in v)
    if isinstance(v, bool):
        return "yes" if v else "no"
    if v is None or isinstance(v, str):
        return "n/a" if v is None else v
    return format_number(v)


def _metrics_table(inp: ReportInputs) -> Markup:
    """metrics.yaml, formatted by the one rounding rule; the unaligned comparisons are n/a when the ground truth is in
    another frame; the position RMSE is the one the trajectory section shows (one figure per quantity)."""
    extra = (inp.dataset.meta.extra or {}) if inp.dataset is not None else {}
    other_frame = str(extra.get("groundtruth_align", "none")) != "none"
    na = "n/a (ground truth in another frame)"

    def vs_truth(k: str) -> bool:  # the estimator's unaligned comparisons with ground truth
        return k.startswith(("position_rmse", "orientation_rmse", "velocity_rmse", "nees")) and \
            k not in ("position_rmse_after_skip_s", "nees_dof")

    mrows = [[k, na if (other_frame and vs_truth(k)) else _metric_value(v)] for k, v in inp.metrics.items()
             if not isinstance(v, dict) and k != "warnings"]
    if not mrows:
        return Markup("")
    note = Markup("<p>The dataset's ground truth is in another frame (<code>extra.groundtruth_align: "
                  "{}</code>): the estimator's unaligned comparisons with it are "
                  "not meaningful and shown as n/a; see <a href=\"#trajectory\">Trajectory and errors</a> for "
                  "the aligned errors.</p>").format(extra.get("groundtruth_align")) if other_frame else ""
    return Markup("<h3>metrics.yaml</h3>") + note + _table(["metric", "value"], mrows)


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
                               "has lever-arm / time-offset columns (<code>{}</code> with <code>sd_{}</code>, "
                               "...).").format(", ".join(CAL_COLUMNS), CAL_COLUMNS[0]))
    t = df["t"].to_numpy(float)
    _, ref_label = inp.reference_lever_arm()
    comp = calibration_components()
    refs = {b.name: inp.reference(b) for b in CALIBRATION_BLOCKS}
    fig = Figure(figsize=(9.0, 7.0))
    keys = [k for k in CAL_COLUMNS if cols.get(k)]
    for n, k in enumerate(keys):
        ax = fig.add_subplot(len(keys), 1, n + 1)
        b, i = comp[k]
        scale, unit = b.plot
        v = df[cols[k]].to_numpy(float) * scale
        ax.plot(t, v, "C0-", lw=1.0, label="estimate")
        sdc = _sd_col(df, cols[k])
        if sdc is not None:
            s = df[sdc].to_numpy(float) * scale
            ax.fill_between(t, v - 3 * s, v + 3 * s, color="C0", alpha=0.2, lw=0, label="±3σ")
        ref = None if refs[b.name] is None else refs[b.name][i]
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

    Columns: ``anchor, n, processed, median, mad, robust_sd, rejected_pct, flags``; TDoA rows (``kind == "tdoa"``)
    are grouped by their pair ``"a-b"`` in ``anchor``; rows in natural anchor order.
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
    anchors = res["anchor"].astype(str).to_numpy().astype(object)
    if "kind" in res.columns and "anchor_b" in res.columns:  # TDoA rows under their pair "a-b", not anchor a
        td = (res["kind"].astype(str) == "tdoa").to_numpy()
        anchors[td] = [f"{a}-{b}" for a, b in zip(anchors[td], res["anchor_b"].astype(str).to_numpy()[td])]
    anchors = anchors.astype(str)
    ok_all = acc & np.isfinite(innov)
    med_all = np.median(innov[ok_all]) if ok_all.any() else np.nan
    rsd_all = 1.4826 * np.median(np.abs(innov[ok_all] - med_all)) if ok_all.any() else np.nan
    rej_all = 100.0 * np.sum(processed & ~acc) / max(processed.sum(), 1)
    rows = []
    for a in sorted(set(anchors), key=natural_key):
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
        return _missing(Markup("<code>residuals.csv</code> lacks the column(s) {}.").format(", ".join(need)))
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


def _nis_section(inp: ReportInputs):
    from matplotlib.figure import Figure
    from scipy.stats import chi2

    res = inp.residuals
    summ = inp.nis
    if res is None or "nis" not in res.columns:
        return _missing(Markup("<code>residuals.csv</code> with a <code>nis</code> column not found."))
    if summ is None:
        return _missing("no finite NIS values.")
    nis = pd.to_numeric(res["nis"], errors="coerce").to_numpy(float)
    acc = _as_bool(res["accepted"]) if "accepted" in res.columns else np.ones(len(res), bool)
    nis_f = nis[np.isfinite(nis)]
    bound = CHI2_1_95
    fig = Figure(figsize=(7.5, 4.0))
    ax = fig.add_subplot(111)
    # x-range up to the 99th percentile, at most 50: larger values pile into the last bin
    hi = min(max(10.0, float(np.percentile(nis_f, 99))), 50.0)
    bins = np.linspace(0, hi, 60)
    dens, _, _ = ax.hist(np.clip(nis_f, 0, hi), bins=bins, density=True, color="C0", alpha=0.6,
                         label=f"all processed ({format_number(100 * np.mean(nis_f > hi))} % > {hi:.0f} in last bin)")
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
    ax.set_xlabel("NIS (innovation² / S)")
    ax.set_ylabel("density")
    ax.legend(fontsize=8)
    ax.grid(True, alpha=0.3)
    what = {"consistent": "consistent with χ²(1)",
            "heavy-tailed": "consistent with χ²(1) in the bulk, with a heavy tail: the mean over all processed "
                            "updates is dominated by a few far outliers",
            "over-confident": "larger than χ²(1): the stated noise is too small for these residuals (over-confident)",
            "under-confident": "smaller than χ²(1): the stated noise is larger than these residuals need"}[summ.verdict]
    n_rej = summ.n - summ.n_accepted
    stats = _tagged("p", "nis-summary", summ.attrs(), Markup(
        "{} processed updates ({} accepted, {} rejected by the gate). Accepted: mean NIS <b>{}</b> (χ²(1): 1). "
        "All processed: median {} (χ²(1): {}), {} % above the 95 % bound {} (expected 5 %), mean {}. "
        "Verdict: <b>{}</b> — {}.").format(
        summ.n, summ.n_accepted, n_rej, format_number(summ.mean_accepted), format_number(summ.median),
        format_number(CHI2_1_MEDIAN), format_number(summ.above_95_pct), format_number(bound),
        format_number(summ.mean_all), summ.verdict, what))
    return stats + _fig("nis", fig, "Normalised innovation squared of the updates against the χ²(1) density."), \
        {f"{k}": v for k, v in summ.attrs().items()}


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
        mode = ev["align"]["mode"]
        band = "smoother" if inp.estimator() == "batch" else "filter"
        m = inp.metrics or {}
        attrs = {"align": mode, "band": f"{band} ±3σ"}
        # one figure per quantity: with no alignment, the position RMSE is metrics.yaml's (the figure `uwbimu
        # estimate` prints); after an alignment, the aligned ATE, with the alignment named
        if mode == "none" and isinstance(m.get("position_rmse"), (int, float)):
            rmse, src = float(m["position_rmse"]), Markup("<code>metrics.yaml</code>, as <code>uwbimu estimate</code> "
                                                         "prints it")
        else:
            rmse = float(a["rmse"])
            src = (Markup("ATE, no alignment: ground truth in the estimate's frame") if mode == "none"
                   else Markup("ATE after <b>{}</b> alignment").format(mode))
        attrs["position-rmse"] = repr(rmse)
        parts.append(Markup(
            "<p>Against ground truth: position RMSE <b>{} m</b> ({}); error max {} m over {} samples{}{}. "
            "Ground-truth glitches excluded: {} (position), {} (attitude).</p>"
        ).format(format_number(rmse), src, format_number(a["max"]), a["n"],
                 Markup("; attitude RMSE {}°").format(format_number(ar["rmse"])) if ar else "",
                 Markup("; attitude {}").format(ev["ate_rotation"]) if ev.get("ate_rotation") else "",
                 asc["n_groundtruth_glitches_excluded"], asc.get("n_groundtruth_attitude_glitches_excluded", 0)))
        rrows = [[d, str(v["n_pairs"]), format_number(v["translation"]["rmse"]), format_number(v.get("translation_percent")),
                  format_number(v["rotation_deg"]["rmse"])] for d, v in ev.get("rpe", {}).items()]
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
        outside = None
        if mode in ("none", "position"):
            for i, c in enumerate("xyz"):
                ax2.plot(t, e[:, i], f"C{i}-", lw=0.8, label=f"e{c}")
                if sd is not None:
                    ax2.fill_between(t, -3 * sd[:, i], 3 * sd[:, i], color=f"C{i}", alpha=0.12, lw=0)
            if sd is not None:
                ok = np.isfinite(e).all(axis=1) & np.isfinite(sd).all(axis=1)
                outside = 100.0 * float(np.mean(np.abs(e[ok]) > 3 * sd[ok])) if ok.any() else None
            cap = f"Position error per axis with the {band}'s ±3σ bands."
            expected = "0.3 %"
        else:
            ax2.plot(t, np.linalg.norm(e, axis=1), "k-", lw=0.8, label="|e|")
            if sd is not None:
                ax2.plot(t, 3 * np.linalg.norm(sd, axis=1), "C3--", lw=0.8, label="3σ (norm)")
                ok = np.isfinite(e).all(axis=1) & np.isfinite(sd).all(axis=1)
                outside = (100.0 * float(np.mean(np.linalg.norm(e[ok], axis=1) > 3 * np.linalg.norm(sd[ok], axis=1)))
                           if ok.any() else None)
            cap = ("Position error norm (rotation-invariant after SE(3) alignment) against 3× the norm of the "
                   f"{band}'s position σ.")
            expected = "under 3 %"
        ax2.set_xlabel("t [s]")
        ax2.set_ylabel("error [m]")
        ax2.legend(fontsize=8, ncol=4)
        ax2.grid(True, alpha=0.3)
        if outside is not None:
            attrs["outside-band-pct"] = repr(outside)
            exceeds = outside > (1.0 if mode in ("none", "position") else 5.0)
            attrs["band-exceeded"] = "yes" if exceeds else "no"
            text = Markup("{} % of the error samples lie outside the {}'s ±3σ band (expected {} for a σ that "
                          "matches the errors){}").format(
                format_number(outside), band, expected,
                Markup(": the errors exceed the band — the stated position σ is too small for this run, or the "
                       "ground truth is not in the estimate's frame and clock.") if exceeds else ".")
            parts.append(_tagged("p", "warn" if exceeds else "note", {"outside-band-pct": repr(outside)}, text))
        else:
            attrs["band-exceeded"] = "unknown"
        parts.append(_fig("errors", fig2, cap))
        return _join(parts), attrs
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


#: error-state index of each calibration component (the repeatability parameters ``lx, ly, lz, time_offset``)
_REP_INDEX = {n: ERROR_STATE_NAMES.index(n) for n in calibration_components()}


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
        inp.warn("report_no_window_bound", f"no per-window Cramér-Rao bound for the repeatability windows: {exc}")
        return {}


def _repeatability_section(inp: ReportInputs) -> Markup:
    from matplotlib.figure import Figure

    rep = inp.repeatability
    if rep is None:
        return _missing(Markup("<code>repeatability.json</code> not found (run <code>uwbimu repeatability DATASET --out "
                               "OUT</code>)."))
    params = rep.get("parameters", {})
    bounds = _repeatability_bounds(inp, rep.get("windows", []))
    # the truth: repeatability.json's (the dataset it ran on), else the dataset given to the report
    truth_src = {}
    if inp.dataset is not None and inp.dataset.meta.truth is not None:
        tr = inp.dataset.meta.truth
        for b in CALIBRATION_BLOCKS:
            if getattr(tr, b.output_key, None) is not None:
                truth_src.update(zip(b.output_names, map(float, np.atleast_1d(getattr(tr, b.output_key)))))
    comp = calibration_components()
    rows, classes = [], []
    n_truth = 0
    for name in sorted(params, key=list(_REP_INDEX).index if set(params) <= set(_REP_INDEX) else str):
        p = params[name]
        scale, unit = comp[name][0].table if name in comp else (100.0, "cm")
        verdict = p.get("verdict", "")
        truth = p.get("truth", truth_src.get(name))
        mean, mean_sd = p.get("mean", np.nan), sd_or_none(p.get("mean_sd"))
        if truth is not None:
            n_truth += 1
            err = float(mean) - float(truth)
            z = err / mean_sd if mean_sd else None
            truth_cells = [format_number(float(truth) * scale), _same_place(err * scale, None if mean_sd is None else mean_sd * scale),
                           "–" if z is None else _span("bad" if abs(z) > 3 else "ok", f"{z:+.1f}")]
        else:
            truth_cells = ["–", "–", "–"]
        rows.append([f"{name} [{unit}]", str(p.get("n", "")),
                     format_value_sigma(None if mean is None else float(mean) * scale,
                                        None if mean_sd is None else mean_sd * scale)]
                    + truth_cells
                    + [format_number(p.get("std", np.nan) * scale), format_number(p.get("rms_sd", np.nan) * scale),
                       format_number(bounds[name] * scale) if name in bounds else "–", format_number(p.get("ratio")),
                       format_number(p.get("chi2")), str(p.get("dof", "")), format_number(p.get("p_value")),
                       _span("ok" if verdict == "consistent" else "bad", verdict)])
        classes.append("" if verdict == "consistent" else "flag")
    attrs = {"truth-shown": "yes" if n_truth else "no", "parameters": len(params)}
    parts = [Markup("<p>{} windows of {} s ({} calibrated).</p>").format(
                 rep.get("k", "?"), format_number(rep.get("window_s")), len(rep.get("windows", []))),
             _table(["parameter", "windows", "weighted mean ± σ", "truth", "mean − truth", "z", "spread (sd)",
                     "predicted σ (RMS)", "bound (PCRB, RMS)", "spread/σ", "χ²", "dof", "p", "verdict"], rows, classes),
             Markup('<p class="note">Truth: <code>truth</code> of dataset.yaml (simulation), shown when the dataset has '
                    "it; z = (mean − truth) / σ of the weighted mean. "
                    "χ² = Σ (x_k − x̄)² / σ_k² over windows, compared with χ²(K−1): a spread much larger "
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
            scale, unit = comp[name][0].plot if name in comp else (1.0, "m")
            xs = [w["t_mid"] for w in wins if name in w.get("values", {})]
            vs = np.array([w["values"][name] for w in wins if name in w.get("values", {})], float) * scale
            ss = np.array([w["sd"][name] for w in wins if name in w.get("values", {})], float) * scale
            ax.errorbar(xs, vs, yerr=3 * ss, fmt="o", ms=4, capsize=3)
            ax.axhline(params[name].get("mean", np.nan) * scale, color="k", lw=0.8)
            tv = params[name].get("truth", truth_src.get(name))
            if tv is not None:
                ax.axhline(float(tv) * scale, color="C3", ls="--", lw=0.9)
            ax.set_ylabel(f"{name} [{unit}]")
            ax.grid(True, alpha=0.3)
        fig.axes[-1].set_xlabel("window centre [s]")
        parts.append(_fig("repeatability", fig, "Per-window estimates with ±3σ error bars; the line is the mean"
                          + ("; dashed: the truth." if n_truth else ".")))
    return _join(parts), attrs


def _bound_vs_sigma(df: pd.DataFrame, cal: Optional[dict]) -> Markup:
    """The bound at the end of the log (last window of a chained PCRB) next to the filter's sigma."""
    if not cal or len(df) == 0:
        return Markup("")
    pairs = []
    for b in CALIBRATION_BLOCKS:
        pairs += [(n, s_f, *b.table) for n, s_f in zip(b.output_names, calibration_estimate(cal, b)[1])]
    cells, names = [], []
    for n, s_f, k, unit in pairs:
        col = f"sd_{n}"
        if s_f is None or col not in df.columns:
            continue
        b = pd.to_numeric(df[col], errors="coerce").to_numpy(float)[-1]
        if not np.isfinite(b) or b <= 0 or not np.isfinite(float(s_f)):
            continue
        cells.append(f"{n} {format_number(k * b)} vs {format_number(k * float(s_f))} {unit} "
                     f"(σ / bound {format_number(float(s_f) / b)})")
        names.append(n)
    if not cells:
        return Markup("")
    return _tagged("p", "note", {"bound-params": " ".join(names)}, Markup(
        "Bound at the end of the log (last window; with the chained posterior Cramér-Rao bound "
        "of <code>uwbimu observability log</code> this is the σ a matched filter should reach) vs the estimator's "
        "σ of the calibration section: {}. σ / bound well below 1 means an over-confident "
        "filter, well above 1 one that does not use all the information.").format("; ".join(cells)))


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
    for b in CALIBRATION_BLOCKS:  # one panel per calibration block
        series = [(f"sd {n}", col(f"sd_{n}")) for n in b.output_names if f"sd_{n}" in df.columns]
        if series:
            panels.append((f"CRLB {b.label} [{b.unit}]", series, f"{b.output_key}_excited"))
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


def _warnings_section(inp: ReportInputs):
    items = inp.warning_items()
    n_warn = sum(1 for w in items if w.severity != "info")
    attrs = {"warnings": n_warn, "events-info": len(items) - n_warn}
    if not items:
        return Markup('<p class="note">No warnings recorded (calibration.yaml <code>warnings</code> and '
                      "<code>events</code>, metrics.yaml, warnings.txt).</p>"), attrs
    return _join(_block("warning_item", w.kind, w.source, w.severity, w.text) for w in items), attrs


