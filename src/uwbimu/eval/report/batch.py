"""The ``uwbimu calibrate`` section of the report (batch calibration outputs)."""

from __future__ import annotations

from typing import Any, Optional, Sequence

import numpy as np
import pandas as pd
from markupsafe import Markup

from uwbimu.eval.files import EvalInputError
from uwbimu.eval.report.common import _as_bool, _block, _fig, _fmt, _join, _missing, _span, _table
from uwbimu.eval.report.inputs import ReportInputs
from uwbimu.formatting import format_number, format_value_sigma, natural_key
from uwbimu.models.blocks import CALIBRATION_BLOCKS


# --------------------------------------------------------------------------- batch calibration (uwbimu calibrate)
#: Files only ``uwbimu calibrate`` writes (``uwbimu.calibration.outputs.OUTPUT_FILES``).
BATCH_FILES = ("td_profile.csv", "anchors_estimated.csv")


def is_batch_output(inp: ReportInputs) -> bool:
    """Whether the folder holds ``uwbimu calibrate`` outputs: ``td_profile.csv`` or ``anchors_estimated.csv``, or a
    ``calibration.yaml`` of the batch (``estimator: batch``, or ``method: batch-...`` in files of schema 1)."""
    if inp.td_profile is not None or inp.anchors_estimated is not None:
        return True
    c = inp.calibration or {}
    return str(c.get("estimator", "")) == "batch" or str(c.get("method", "")).startswith("batch")


def _not_found_or_lacks(name: str, absent: bool, need: Sequence[str]) -> Markup:
    if absent:
        return Markup("<code>{}</code> not found.").format(name)
    return Markup("<code>{}</code> lacks the column(s) {}.").format(name, ", ".join(need))


def _part(key: str, title: str, content: Markup, **attrs: Any) -> Markup:
    return _block("part", key, title, content, [(k.replace("_", "-"), str(v)) for k, v in attrs.items()])


def _batch_td(cal: dict) -> dict:
    td = cal.get("time_offset")
    return td if isinstance(td, dict) else {}


def _at(x: Optional[float], sigma: Optional[float]) -> str:
    """``x`` to the decimal place of ``sigma`` (the one rounding rule), 3 significant digits without one."""
    if x is None:
        return "–"
    if sigma is None or not sigma > 0:
        return format_number(x)
    return format_value_sigma(x, sigma).split(" ± ")[0]


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
        lab = (f"held at prior {format_number(1000 * float(value))} ms" if held or sd is None
               else "t_d = " + format_value_sigma(1000 * float(value), 1000 * float(sd), "ms"))
        ax.axvline(1000 * float(value), color="C3", ls="--" if held else "-", lw=1.0, label=lab)
    ax.set_xlabel("time offset t_d [ms]")
    ax.set_ylabel("Δχ² (profile)")
    ax.set_title(f"verdict: {verdict}", fontsize=10)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)

    def ms(v):
        return None if v is None else 1000 * float(v)

    sd_m = ms(td.get("sd_marginal", sd))
    rows = [["verdict", _span("ok" if verdict == "identified" else "bad", verdict)],
            ["t_d ± σ (marginal) [ms]", "–" if value is None else format_value_sigma(ms(value), sd_m)],
            ["σ (profile curvature) [ms]", "–" if td.get("sd_curvature") is None else
             format_value_sigma(ms(td["sd_curvature"]), ms(td["sd_curvature"])).split(" ± ")[1]],
            ["profile interval [ms]", "–" if ci is None else
             f"{_at(ms(ci[0]), sd_m)} … {_at(ms(ci[1]), sd_m)}"],
            ["grid [ms]", f"{format_number(ms(np.nanmin(g)))} … {format_number(ms(np.nanmax(g)))} ({len(g)} points)"],
            ["held at prior", "yes" if held else "no"]]
    scale = ((inp.calibration or {}).get("imu_noise") or {}).get("scale") or {}
    if scale.get("method") == "variance_component":  # the IMU model the profile was computed under
        rows.append(["IMU noise scale (estimated)", format_value_sigma(float(scale["scale"]), scale.get("scale_sd"))])
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
    """Anchor ids in natural order (1, 2, ..., 10)."""
    return sorted(set(map(str, ids)), key=natural_key)


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
    from uwbimu.calibration.outputs import measured_minus_predicted

    e_all = 100 * measured_minus_predicted(data)
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
    cap = ("Residual (measured − predicted range, with the estimated range bias) per anchor against "
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
    a = a.iloc[sorted(range(len(a)), key=lambda k: natural_key(a["anchor"].iloc[k]))].reset_index(drop=True)
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
    from uwbimu.calibration.outputs import measured_minus_predicted, residual_without

    e = measured_minus_predicted(rr)  # the ESKF's sign, whatever the file's residual column holds
    aid = rr["anchor"].astype(str).to_numpy()
    drift = pd.to_numeric(rr["bias_drift"], errors="coerce").to_numpy(float) if "bias_drift" in rr.columns else None
    down = _as_bool(rr["outlier"]) if "outlier" in rr.columns else None
    before = None
    if bias is not None:  # the constant and the slowly varying bias (this part's "without")
        before = residual_without(rr, {str(k): v for k, v in bias.items()}, columns=("bias_drift",))
    rows = []
    ids = _anchor_order(aid)
    for a in ids + ["all"]:  # natural anchor order (_anchor_order)
        m = np.ones(len(aid), bool) if a == "all" else aid == a
        mb, sb = _med_mad(before[m]) if before is not None else (np.nan, np.nan)
        ma, sa = _med_mad(e[m])
        bv = bias.get(a) if (bias is not None and a != "all") else None
        rows.append([a, str(int(m.sum())), "–" if down is None else str(int(down[m].sum())),
                     "–" if bv is None else f"{100 * float(bv):+.1f} ± {_fmt(100 * float(bias_sd.get(a, np.nan)), 1)}",
                     _fmt(100 * mb, 2), _fmt(100 * sb, 2), _fmt(100 * ma, 2), _fmt(100 * sa, 2)])
    notes = [Markup("Residual = measured − predicted range (the sign of the ESKF's innovation; <code>residuals.csv</code> "
                    "<code>range − predicted</code>, with the estimated range bias); MAD = median |x − median|, "
                    "unscaled.")]
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
    idf = cal.get("identifiability") or {}
    sd, sd_m, verdict = {}, {}, {}
    for blk in CALIBRATION_BLOCKS:  # named as the block check names them: <output_key>[_<axis>]
        key, (scale, unit) = blk.output_key, blk.table
        if blk.verdict == "profile":  # the time offset: schema 2's {value, sd, sd_model, verdict}
            entry = cal.get(key) if isinstance(cal.get(key), dict) else {}
            sds, sdms, verdicts = [entry.get("sd")], [entry.get("sd_model")], [str(entry.get("verdict", "–"))]
        else:
            sds, sdms = cal.get(f"{key}_sd") or [], cal.get(f"{key}_sd_model") or []
            axes = idf.get(key) or {}
            axes = axes if set(axes) <= set(blk.axes) else next(iter(axes.values()), {})  # several tags: the first's
            verdicts = [(axes.get(c) or {}).get("verdict", "–") for c in blk.axes]
        for i, c in enumerate(blk.axes):
            n = "_".join(filter(None, (key, c)))
            verdict[n] = verdicts[i]
            if i < len(sds) and sds[i] is not None:
                sd[n] = (sds[i], scale, unit)
                if i < len(sdms):
                    sd_m[n] = sdms[i]
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


def _batch_estimators_part(inp: ReportInputs) -> Markup:
    """The batch checked against the ESKF it started from (calibration.yaml ``estimators``,
    :mod:`uwbimu.calibration.agreement`): attribute ``estimators`` = ``agree``, ``disagree`` or ``unknown`` (a file
    without the check); a warning line with :func:`~uwbimu.calibration.agreement.agreement_message` when they
    disagree."""
    from uwbimu.calibration.agreement import agreement_message

    title = "ESKF and batch"
    ev = (inp.calibration or {}).get("estimators")
    if not isinstance(ev, dict) or ev.get("kind") not in ("estimators_agree", "estimators_disagree"):
        return _part("estimators", title, _missing(Markup("<code>calibration.yaml</code> has no <code>estimators</code> "
                                                          "check (older output).")),
                     estimators="unknown")
    rows = [r for r in ev.get("parameters") or [] if isinstance(r, dict) and "z" in r]
    thr = ev.get("z_threshold", 3.0)
    if ev["kind"] == "estimators_disagree":
        # a distance written as null was infinite (zero combined sigma, different values)
        msg = agreement_message({"kind": ev["kind"], "parameters": [
            dict(r, z=float("inf") if r.get("z") is None else float(r["z"])) for r in rows]})
        body = _block("warn", msg or ev.get("message", ""))
    else:
        zmax = max((float(r["z"]) for r in rows if r.get("z") is not None), default=None)
        body = Markup("<p>The batch agrees with the initialising ESKF on every compared parameter (largest distance "
                      "{} combined σ; they disagree beyond {}).</p>").format(
            "–" if zmax is None else format_number(zmax), format_number(float(thr)))
    return _part("estimators", title, body, estimators="disagree" if ev["kind"] == "estimators_disagree" else "agree",
                 disagreeing=" ".join(str(n) for n in ev.get("disagreeing") or []))


def _batch_start_part(inp: ReportInputs) -> Markup:
    """Where the batch started (calibration.yaml ``start``, event ``calibration_start``) and which blocks it held
    at their priors (``held_at_prior``, event ``calibration_held``): attributes ``source`` (``eskf``,
    ``multilateration`` or ``unknown`` for an older file), ``reason`` and ``held`` (space-separated blocks)."""
    title = "Start and held blocks"
    cal = inp.calibration or {}
    st = cal.get("start") if isinstance(cal.get("start"), dict) else None
    held = cal.get("held_at_prior") if isinstance(cal.get("held_at_prior"), dict) else None
    blocks = [str(b) for b in (held or {}).get("blocks") or []]
    if st is None:
        return _part("start", title, _missing(Markup("<code>calibration.yaml</code> has no <code>start</code> "
                                                     "(older output).")), source="unknown", reason="",
                     held=" ".join(blocks))
    if st.get("source") == "multilateration":
        body = _block("warn", f"The initialising ESKF failed the health check ({st.get('reason')}): the batch "
                              "started from a robust multilateration of the log.")
    else:
        body = Markup("<p>The batch started from the initialising ESKF (health check: {}).</p>").format(
            str(st.get("reason")))
    if blocks:
        body += _block("warn", "Held at the prior (no element identified, residuals refute the noise model): "
                       + ", ".join(blocks) + ".")
    return _part("start", title, body, source=str(st.get("source")), reason=str(st.get("reason")),
                 held=" ".join(blocks))


def _batch_section(inp: ReportInputs) -> Optional[Markup]:
    """The ``uwbimu calibrate`` section, or None when the folder holds no batch-calibration output."""
    if not is_batch_output(inp):
        return None
    parts = []
    for key, title, fn in (("start", "Start and held blocks", _batch_start_part),
                           ("estimators", "ESKF and batch", _batch_estimators_part),
                           ("td-profile", "Time-offset profile", _batch_profile_part),
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


