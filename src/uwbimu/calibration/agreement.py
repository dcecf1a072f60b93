"""One answer: the batch calibration checked against the ESKF it started from.

The two estimators see the same log through different models (a causal filter with a Gaussian noise
model; a smoother with robust loss, honest HAC sigmas and range-error models). When they disagree beyond
3 combined sigma on a calibration parameter, the batch output says so, with which estimate the evidence
favours, by this stated rule:

* the ESKF held the parameter at its prior (consider mode) and the batch identifies it: the batch (the ESKF
  made no estimate of its own);
* the ESKF's residuals refute its noise model (its variance factor ``sigma_scale`` > 1) and the batch
  identifies the parameter: the batch (its robust loss and range models absorb what the filter's cannot);
* the batch does not identify it and the ESKF does with residuals that agree with its model: the ESKF;
* otherwise: neither - the log does not settle the parameter and both sigmas are too small for it.
"""

from __future__ import annotations

import math
from typing import Any, Optional

#: combined-sigma distance beyond which the two estimates disagree
Z_DISAGREE = 3.0


def _batch_time_offset(cal: dict) -> tuple[Optional[float], Optional[float], Optional[str]]:
    td = cal.get("time_offset")
    if isinstance(td, dict):
        return td.get("value"), td.get("sd"), td.get("verdict")
    return td, cal.get("time_offset_sd"), cal.get("time_offset_verdict")


def _batch_lever_verdicts(cal: dict) -> dict[str, Optional[str]]:
    ident = (cal.get("identifiability") or {}).get("lever_arm") or {}
    # one tag: {x|y|z: {...}}; several: {TAG: {x|y|z: {...}}} (the first tag's is the top-level lever arm)
    first = ident if "x" in ident else next((v for v in ident.values() if isinstance(v, dict)), {})
    return {c: (first.get(c) or {}).get("verdict") for c in "xyz"}


def _identified(verdict: Optional[str]) -> bool:
    return verdict == "identified"


def estimator_agreement(eskf_cal: dict, batch_cal: dict, eskf_modes: Optional[dict] = None) -> dict[str, Any]:
    """Compare the ESKF's and the batch's calibration parameters.

    Parameters
    ----------
    eskf_cal : the ESKF result's ``calibration`` (lever arm [m], time offset [s], their sds and verdicts,
        ``sigma_scale``).
    batch_cal : the batch calibration (``time_offset`` as a number or a ``{value, sd, verdict}`` mapping).
    eskf_modes : the modes the ESKF ran with (``config.resolved.modes``); a block in ``consider`` was held.

    Returns
    -------
    An event ``{kind: estimators_agree | estimators_disagree, parameters: [{name, eskf, eskf_sd, batch,
    batch_sd, z, favours, reason}], z_threshold}``; values in m and s.
    """
    modes = eskf_modes or {}
    refuted = float(eskf_cal.get("sigma_scale", 1.0) or 1.0) > 1.0
    rows: list[dict[str, Any]] = []
    e_lv = eskf_cal.get("lever_arm_verdict") or {}
    b_lv = _batch_lever_verdicts(batch_cal)
    cand = []
    for i, c in enumerate("xyz"):
        try:
            cand.append((f"lever_arm_{c}", eskf_cal["lever_arm"][i], eskf_cal["lever_arm_sd"][i],
                         batch_cal["lever_arm"][i], batch_cal["lever_arm_sd"][i], e_lv.get(c), b_lv.get(c),
                         modes.get("lever_arm") == "consider"))
        except (KeyError, IndexError, TypeError):
            break
    b_td, b_td_sd, b_td_v = _batch_time_offset(batch_cal)
    cand.append(("time_offset", eskf_cal.get("time_offset"), eskf_cal.get("time_offset_sd"), b_td, b_td_sd,
                 eskf_cal.get("time_offset_verdict"), b_td_v, modes.get("time_offset") == "consider"))
    for name, a, sa, b, sb, va, vb, held in cand:
        if None in (a, sa, b, sb) or not all(math.isfinite(float(v)) for v in (a, sa, b, sb)):
            continue
        sc = math.hypot(float(sa), float(sb))
        z = abs(float(a) - float(b)) / sc if sc > 0 else (0.0 if a == b else math.inf)
        row = {"name": name, "eskf": float(a), "eskf_sd": float(sa), "batch": float(b), "batch_sd": float(sb),
               "z": z, "eskf_verdict": va, "batch_verdict": vb, "favours": None, "reason": ""}
        if z > Z_DISAGREE:
            if held and _identified(vb):
                row["favours"], row["reason"] = ("batch", "the ESKF held it at its prior (no estimate of its own); "
                                                 "the batch identifies it")
            elif refuted and _identified(vb):
                row["favours"], row["reason"] = ("batch", "the ESKF's residuals refute its noise model "
                                                 "(sigma_scale > 1); the batch identifies it")
            elif not held and not _identified(vb) and _identified(va) and not refuted:
                row["favours"], row["reason"] = ("eskf", "the batch does not identify it; the ESKF does, with "
                                                 "residuals that agree with its model")
            else:
                row["favours"], row["reason"] = ("neither", "the log does not settle it: both sigmas are too "
                                                 "small for the distance between the estimates")
        rows.append(row)
    bad = [r for r in rows if r["z"] > Z_DISAGREE]
    return {"kind": "estimators_disagree" if bad else "estimators_agree", "parameters": rows,
            "disagreeing": [r["name"] for r in bad], "z_threshold": Z_DISAGREE}


def agreement_message(event: dict[str, Any]) -> Optional[str]:
    """One line for the console and the report when the estimators disagree (None when they agree)."""
    if event["kind"] != "estimators_disagree":
        return None
    parts = []
    for r in event["parameters"]:
        if r["z"] <= Z_DISAGREE:
            continue
        f, u = (1e3, "ms") if r["name"] == "time_offset" else (1e2, "cm")
        parts.append(f"{r['name'].replace('_', ' ')}: ESKF {r['eskf'] * f:.1f} ± {r['eskf_sd'] * f:.1f} {u}, batch "
                     f"{r['batch'] * f:.1f} ± {r['batch_sd'] * f:.1f} {u} ({r['z']:.1f} combined sd; the evidence "
                     f"favours {r['favours']}: {r['reason']})")
    return "the ESKF and the batch disagree: " + "; ".join(parts)
