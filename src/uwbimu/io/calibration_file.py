"""The one schema of ``calibration.yaml``, written by every estimator (``uwbimu estimate``, ``uwbimu calibrate``).

Schema version 2 (``schema_version: 2``)::

    schema_version: 2
    estimator: eskf | batch        # who wrote it (``method`` says which batch variant)
    lever_arm: [x, y, z]           # [m], IMU frame, antenna of the first tag
    lever_arm_sd: [sx, sy, sz]     # [m], 1 sigma; null where not estimated
    lever_arm_mode: estimate | consider | fixed
    time_offset:                   # t_d [s]: t_uwb = t_imu - t_d
      value: 0.0299                # [s]
      sd: 0.0012                   # [s], 1 sigma; null where not estimated (then sd_status: not estimated)
      unit: s
      mode: estimate | consider | fixed   # how the run treated it (consider: held at its prior, not updated)
      configured_mode: estimate    # what the options asked for, when the run changed it
      verdict: identified | weakly identified | not identified | fixed
      verdict_reason: "..."        # optional
      ...                          # estimator-specific extras (ESKF: sd_filter, the filter's sigma before the
                                   # residuals widened it, value_filter before a clock correction; batch:
                                   # sd_marginal, sd_model, sd_curvature, profile interval, held_at_prior, advice)

    estimators:                    # batch only: the batch checked against the ESKF it started from
      kind: estimators_agree | estimators_disagree    # (uwbimu.calibration.agreement; also in ``events``)
      severity: info | warning
      message: "..."               # only when they disagree: which estimate the evidence favours, and why
      z_threshold: 3.0             # combined sigmas beyond which a parameter disagrees
      disagreeing: [time_offset]   # names of the parameters beyond it
      parameters:                  # one per compared parameter (lever_arm_x/y/z [m], time_offset [s])
        - {name, eskf, eskf_sd, batch, batch_sd, z, eskf_verdict, batch_verdict, favours, reason}

    smoothing:                     # ESKF smoothed forward-backward only (uwbimu estimate's default;
      method: forward_backward     # uwbimu.estimation.smoother): the lever arm / time offset above are the
      message: "..."               # mean of the two passes; the line the console printed
      time_offset: {forward, forward_sd, backward, backward_sd, value, sd}   # [s], when estimated
      lever_arm: {x: {forward, forward_sd, backward, backward_sd, value, sd}, y: ..., z: ...}   # [m]

Every other key (IMU biases, anchor biases, ``warnings``, ``events``, ``config``) is unchanged. A sigma is never
NaN: a quantity that was not estimated has ``sd: null``.

Version 1 (before this module; no ``schema_version``) held ``time_offset`` as a number with ``time_offset_sd``,
``time_offset_mode`` and ``time_offset_verdict`` next to it (ESKF), or as a mapping with a top-level copy
``time_offset_sd`` (batch). :func:`migrate` turns either into version 2; :func:`read_calibration` reads both.
"""

from __future__ import annotations
from uwbimu.formatting import finite_or_none

from pathlib import Path
from typing import Any, Optional

__all__ = ["SCHEMA_VERSION", "NOT_ESTIMATED", "effective_time_offset_mode", "migrate", "time_offset_held", "read_calibration", "sd_or_none", "time_offset_entry",
           "time_offset_sd", "time_offset_value"]

SCHEMA_VERSION = 2
NOT_ESTIMATED = "not estimated"
#: version-1 keys of the ESKF's time offset, folded into the ``time_offset`` mapping
_V1_TD_KEYS = {"time_offset_sd": "sd", "time_offset_mode": "mode", "time_offset_verdict": "verdict",
               "time_offset_verdict_reason": "verdict_reason"}
#: the ESKF's other top-level time-offset keys, folded into the mapping: the filter's own sigma before the residuals
#: widened it (``sigma_from_residuals``) and the filter's value before a clock-fault correction replaced it
_V1_TD_EXTRA = {"time_offset_sd_filter": "sd_filter", "time_offset_filter": "value_filter"}


def sd_or_none(x: Any) -> Optional[float]:
    """A 1-sigma value as written: a finite, non-negative float, else None (not estimated)."""
    v = finite_or_none(x)
    return v if v is not None and v >= 0 else None


def time_offset_entry(value: Any, sd: Any, mode: str, verdict: Optional[str] = None, *,
                      configured_mode: Optional[str] = None, verdict_reason: Optional[str] = None,
                      **extra: Any) -> dict[str, Any]:
    """The ``time_offset`` mapping of schema version 2.

    Parameters
    ----------
    value : float
        t_d [s].
    sd : float or None
        1 sigma [s]; None, NaN or negative is written as null with ``sd_status: not estimated``; a mode of
        ``fixed`` always has a null sd.
    mode : str
        How the run treated t_d: ``estimate``, ``consider`` (held at its prior, uncertainty kept) or ``fixed``.
    verdict : str, optional
        Identifiability verdict (``identified``, ``weakly identified``, ``not identified``, ``fixed``).
    configured_mode : str, optional
        The options' mode, written only when it differs from ``mode``.
    verdict_reason : str, optional
        Why the verdict.
    **extra
        Estimator-specific keys, kept after the common ones.
    """
    s = None if mode == "fixed" else sd_or_none(sd)
    v = None if value is None else float(value)
    out: dict[str, Any] = {"value": v, "sd": s, "unit": "s", "mode": str(mode)}
    if s is None:
        out["sd_status"] = NOT_ESTIMATED
    if configured_mode is not None and configured_mode != mode:
        out["configured_mode"] = str(configured_mode)
    if verdict is not None:
        out["verdict"] = str(verdict)
    if verdict_reason:
        out["verdict_reason"] = str(verdict_reason)
    for k, x in extra.items():
        if k not in out:
            out[k] = x
    return out


def time_offset_held(events: Any) -> bool:
    """Whether a run's events say it held t_d at its prior in consider mode: ``time_offset_held`` (the ESKF's
    initial search could not locate it) or ``calibration_held`` with ``time_offset`` in its ``blocks`` (the filter
    rerun with the blocks the log did not identify held)."""
    for e in events or []:
        if not isinstance(e, dict):
            continue
        if e.get("kind") == "time_offset_held":
            return True
        if e.get("kind") == "calibration_held" and "time_offset" in (e.get("blocks") or []):
            return True
    return False


def effective_time_offset_mode(configured: str, events: Any) -> tuple[str, str]:
    """``(mode, configured)``: how a run treated t_d, from its events (:func:`time_offset_held`).

    A held t_d is in consider mode although the options asked ``estimate`` (a ``calibration_held`` rerun already
    reports ``consider`` as its mode: the configured one was ``estimate``); otherwise the configured mode holds.
    """
    configured = str(configured or "estimate")
    if time_offset_held(events):
        return "consider", ("estimate" if configured == "consider" else configured)
    return configured, configured


def migrate(doc: Optional[dict]) -> Optional[dict]:
    """A ``calibration.yaml`` mapping of version 1 or 2 as version 2 (a new dict; the input is not changed).

    Version 1 of the ESKF (``time_offset`` a number, ``time_offset_sd`` / ``_mode`` / ``_verdict`` beside it)
    becomes the mapping; version 1 of the batch (a mapping with ``value, sd, verdict, held_at_prior``) gains
    ``unit`` and ``mode`` and loses the top-level ``time_offset_sd``. NaN sigmas become null.
    """
    if doc is None:
        return None
    out = dict(doc)
    td = out.get("time_offset")
    if isinstance(td, dict):
        entry = dict(td)
        if "mode" not in entry:  # version-1 batch: held at its prior means conditional on it (fixed)
            entry["mode"] = "fixed" if entry.get("held_at_prior") else "estimate"
        rest = {k: v for k, v in entry.items() if k not in ("value", "sd", "unit", "mode", "configured_mode",
                                                               "verdict", "verdict_reason", "sd_status")}
        out["time_offset"] = time_offset_entry(entry.get("value"), entry.get("sd", out.get("time_offset_sd")),
                                               entry["mode"], entry.get("verdict"),
                                               configured_mode=entry.get("configured_mode"),
                                               verdict_reason=entry.get("verdict_reason"), **rest)
    elif td is not None:
        v1 = {new: out.get(old) for old, new in _V1_TD_KEYS.items()}
        mode = v1["mode"] or "estimate"
        extra = {new: (sd_or_none(out[old]) if new.startswith("sd") else out[old])
                 for old, new in _V1_TD_EXTRA.items() if old in out}
        out["time_offset"] = time_offset_entry(td, v1["sd"], mode, v1["verdict"],
                                               verdict_reason=v1["verdict_reason"], **extra)
    for old in (*_V1_TD_KEYS, *_V1_TD_EXTRA):
        out.pop(old, None)
    if isinstance(out.get("lever_arm_sd"), list):
        out["lever_arm_sd"] = [sd_or_none(x) for x in out["lever_arm_sd"]]
    out["schema_version"] = SCHEMA_VERSION
    return out


def read_calibration(path: str | Path, error: type[Exception] = ValueError) -> Optional[dict]:
    """``calibration.yaml`` (a file, or a folder holding one) in schema version 2; None when absent.

    Raises ``error`` naming the file when it is not a YAML mapping.
    """
    from uwbimu.io.yamlconfig import read_yaml_mapping

    p = Path(path)
    if p.is_dir():
        p = p / "calibration.yaml"
    if not p.is_file():
        return None
    doc = read_yaml_mapping(p, what="calibration.yaml", error=error)[0]
    version = doc.get("schema_version", 1)
    if version not in (1, SCHEMA_VERSION):
        raise error(f"{p}: field 'schema_version': {version} is not a version this uwbimu reads (1 or 2)")
    return migrate(doc)


def time_offset_value(doc: dict) -> Optional[float]:
    """t_d [s] of a calibration mapping of either version (None when absent)."""
    td = doc.get("time_offset")
    if isinstance(td, dict):
        td = td.get("value")
    return None if td is None else float(td)


def time_offset_sd(doc: dict) -> Optional[float]:
    """1 sigma of t_d [s] of a calibration mapping of either version (None when not estimated)."""
    td = doc.get("time_offset")
    if isinstance(td, dict):
        return sd_or_none(td.get("sd"))
    return sd_or_none(doc.get("time_offset_sd"))
