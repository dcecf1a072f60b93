"""Identifiability verdicts of the batch calibration (calibration.yaml ``identifiability``).

Each lever-arm axis (every tag) and each estimated constant anchor bias gets the verdict the ESKF uses for
its time offset (:func:`uwbimu.estimation.timeoffset.information_verdict`): the information gain of the
data over the parameter's prior, ``(sd_prior / sd)^2 - 1``, with the reported (honest) sigma.  It is
scale-free (a ratio of variances of the same parameter) and says how much of the answer is the prior's.
The time offset keeps its profile verdict (:mod:`uwbimu.calibration.profile`).

A lever-arm component is seen only through rotations that move the antenna along the lines of sight: the
component along body axis ``a`` through rotations about the two other axes (for a multirotor, z through
roll and pitch, i.e. tilt).  An axis that is not identified is named in an event with that advice.
"""

from __future__ import annotations

from uwbimu.estimation.timeoffset import GAIN_IDENTIFIED, information_verdict
from uwbimu.models.blocks import BLOCK, OUTPUT_ORDER, BlockSpec

#: The rotations that reveal each lever-arm component (body axes).
_ROTATIONS = {"x": "pitch and yaw (rotation about body y and z)", "y": "roll and yaw (rotation about body x and z)",
              "z": "roll and pitch (tilt about body x and y)"}
#: the motion that would pin each axis of a base block with an information-gain verdict (by block name)
_ADVICE = {"lever": _ROTATIONS}


def _prior_share(gain: float) -> str:
    """The prior's share of a parameter's information, ``1 / (1 + gain)``, in words."""
    return "all" if not gain == gain else f"{100.0 / (1.0 + max(gain, 0.0)):.2g} %"


def _entry(sd: float, prior_sd: float) -> dict:
    verdict, gain = information_verdict(float(sd), float(prior_sd))
    return {"verdict": verdict, "information_gain": round(gain, 4), "sd": float(sd), "prior_sd": float(prior_sd)}


def _verdict_blocks() -> tuple[BlockSpec, ...]:
    """The blocks with a batch identifiability verdict (``BlockSpec.verdict``), in output order: the lever arm
    (information gain per axis and tag), the time offset (profile), the anchor biases (information gain per
    anchor)."""
    return tuple(BLOCK[n] for n in OUTPUT_ORDER if BLOCK[n].verdict)


def _gain_entries(cal: dict, b: BlockSpec, options) -> dict:
    """Information-gain entries of block ``b``: ``{tag: {axis: entry}}`` (``""`` the tag of a one-tag
    calibration) for a base block, ``{anchor: entry}`` for a per-anchor one (those held at zero and those not
    estimated left out); the prior sd is the options' ``<output_key>_prior_sd``."""
    key = b.output_key
    prior_sd = getattr(options, f"{key}_prior_sd")
    if b.multiplicity == "per_anchor":
        if getattr(options, f"estimate_{key}", True) is False:
            return {}
        held = set((cal.get("anchors") or {}).get("bias_held_at_zero") or [])
        return {a: _entry(s, prior_sd) for a, s in cal[f"{key}_sd"].items() if str(a) not in held and s > 0}
    tags = cal.get("tags") or {"": {f"{key}_sd": cal[f"{key}_sd"]}}
    return {tag: {c: _entry(s, prior_sd) for c, s in zip(b.axes, t[f"{key}_sd"])} for tag, t in tags.items()}


def identifiability(cal: dict, options) -> tuple[dict, list[dict]]:
    """The ``identifiability`` section of calibration.yaml and the events of the axes not identified.

    Loops over the declared blocks with a verdict (:func:`_verdict_blocks`), keyed by their ``output_key``.

    Parameters
    ----------
    cal : the calibration dict of :func:`uwbimu.calibration.batch._report` (``lever_arm_sd``, ``tags``,
        ``anchor_bias_sd``, ``time_offset``).
    options : the :class:`~uwbimu.calibration.options.CalibrationOptions` (the priors' sd).

    Returns
    -------
    (section, events) with section ``{lever_arm: {TAG: {x|y|z: {verdict, information_gain, sd, prior_sd}}},
    time_offset: {verdict}, anchor_bias: {ID: {...}}}`` (anchor biases held at zero are left out).
    """
    section: dict = {"rule": "information gain (prior_sd / sd)^2 - 1 of the data over the prior: identified >= 99, "
                             "weakly identified >= 1, else not identified"}
    events = []
    for b in _verdict_blocks():
        key = b.output_key
        if b.verdict == "profile":
            section[key] = {"verdict": cal[key]["verdict"]}
            continue
        entries = _gain_entries(cal, b, options)
        if b.multiplicity != "one":
            section[key] = entries
            continue
        section[key] = entries if cal.get("tags") else entries[""]
        scale, unit = b.table
        for tag, axes in entries.items():  # a base block's axes not identified: an event with the motion advice
            weak = {c: e for c, e in axes.items() if e["verdict"] != "identified"}
            if not weak:
                continue
            name = f"tag {tag}'s {b.label}" if tag else b.label
            parts = [f"{c} {e['verdict']} (sd {scale * e['sd']:.1f} {unit} against the prior's "
                     f"{scale * e['prior_sd']:.0f} {unit}: the prior carries {_prior_share(e['information_gain'])} "
                     "of its information)" for c, e in weak.items()]
            events.append({"kind": f"{key}_not_identified", "severity": "warning", "tag": tag or None,
                           "axes": {c: e["verdict"] for c, e in weak.items()},
                           "message": f"{name}: " + "; ".join(parts) + "; more "
                                      + " and ".join(_ADVICE[b.name][c] for c in weak) + " while ranging would pin it"})
    return section, events


#: prior sd [m] of the lever arm while it is held (the re-solve's tight prior at the prior mean)
HOLD_SD = 1e-4
#: honest / model sigma of a lever-arm axis above which its residuals refute the white-noise model
REFUTED_RATIO = 1.1


def hold_rule(cal: dict, section: dict, events: list, options) -> dict:
    """The blocks the batch holds at their priors: the ESKF's rule (``hold_unidentified``), per block.

    A block (the lever arm of every tag; the constant anchor biases) is held when both: (1) none of its elements
    is ``identified`` by the information-gain verdict of ``section`` (:func:`identifiability`, with the honest
    sigma: gain below :data:`HOLD_GAIN`, the verdicts' own threshold); (2) the residuals refute the noise model:
    the IMU noise scale was raised significantly (event ``imu_noise_scaled`` with ``scale`` > 1) or the honest
    (sandwich) sigma of a lever-arm axis exceeds its model sigma by more than :data:`REFUTED_RATIO`.  Then
    unmodelled errors are there to be absorbed, and a block the log does not identify absorbs them and takes
    the trajectory with it: on the Crazyflie logs (TDoA, little rotation) "every position + c, lever arm - c"
    is nearly free and the lever arm moved 33 cm and the trajectory with it (cf16: z -36 +/- 10 cm, weakly
    identified 4.5 sigma from the nominal antenna offset, RMSE 0.66 m), and the biases of the upper and lower
    anchors traded against the height (trajectory 0.45 m too high).  A block with one identified element keeps
    its estimates (INRoL); a weakly identified one is held like the ESKF's (ISAS-Walk: lever-arm gains 45-74).

    Parameters
    ----------
    cal : the calibration dict (``lever_arm_sd``, ``lever_arm_sd_model``).
    section : the ``identifiability`` section of that dict.
    events : the calibration's events so far.
    options : the :class:`~uwbimu.calibration.options.CalibrationOptions` (whether anchor biases are estimated).

    Returns
    -------
    ``{block: {element: information gain}}`` for the blocks to hold (``lever_arm``: ``{x, y, z}``, per tag
    with several; ``anchor_bias``: per anchor), ``{}`` for none; with a block held, the key ``refuted`` says why:
    ``{imu_noise_scale, sd_ratio}``.
    """
    gain_blocks = [b for b in _verdict_blocks() if b.verdict == "information_gain"]
    scale = next((float(e["scale"]) for e in events if e.get("kind") == "imu_noise_scaled"), None)
    ratios = []  # honest / model sigma of every axis of a base block (the lever arm's)
    for b in gain_blocks:
        if b.multiplicity == "one":
            sd = [float(x) for x in cal[f"{b.output_key}_sd"]]
            sdm = [float(x) for x in cal.get(f"{b.output_key}_sd_model") or sd]
            ratios += [a / m for a, m in zip(sd, sdm) if m > 0]
    ratio = max(ratios, default=1.0)
    if not ((scale is not None and scale > 1.0) or ratio > REFUTED_RATIO):
        return {}

    def undetermined(entries) -> bool:
        gains = [e["information_gain"] for e in entries]
        return bool(gains) and all(not g >= HOLD_GAIN for g in gains)  # NaN gain: not identified

    out: dict = {}
    for b in gain_blocks:
        key = b.output_key
        entries = section.get(key) or {}
        if b.multiplicity == "one":  # per tag (one tag: the axes themselves)
            per_tag = {"": entries} if set(b.axes) & set(entries) else entries
            if undetermined([e for axes in per_tag.values() for e in axes.values()]):
                gains = {tag: {c: e["information_gain"] for c, e in axes.items()} for tag, axes in per_tag.items()}
                out[key] = gains[""] if "" in gains else gains
        elif getattr(options, f"estimate_{key}", True) is True and undetermined(entries.values()):
            out[key] = {a: e["information_gain"] for a, e in entries.items()}
    if out:
        out["refuted"] = {"imu_noise_scale": scale, "sd_ratio": ratio}
    return out


#: information gain from which an element is identified (the verdicts' threshold): a block none of whose
#: elements reaches it is held when the residuals refute the noise model
HOLD_GAIN = GAIN_IDENTIFIED
