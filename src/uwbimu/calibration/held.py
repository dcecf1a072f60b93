"""The batch's held re-solve: the blocks :func:`uwbimu.calibration.identifiability.hold_rule` names (the log does
not determine them and the residuals refute the noise model) at their prior means, solved again, and reported in
consider mode (a held lever arm with its prior's sd)."""

from __future__ import annotations

import numpy as np

from uwbimu.calibration import keys
from uwbimu.calibration.identifiability import HOLD_SD
from uwbimu.calibration.profile_walk import solve
from uwbimu.calibration.stages import Built


def first_pass(cal: dict, hold: dict) -> dict:
    """The held blocks' values and sd [m] from the solve before the hold (the ``calibration_held`` event)."""
    out = {}
    if "lever_arm" in hold:
        out["lever_arm"] = list(cal["lever_arm"])
        out["lever_arm_sd"] = list(cal["lever_arm_sd"])
        if cal.get("tags"):
            out["tags"] = {t: {"lever_arm": v["lever_arm"], "lever_arm_sd": v["lever_arm_sd"]}
                           for t, v in cal["tags"].items()}
    if "anchor_bias" in hold:
        out["anchor_bias"] = dict(cal["anchor_bias"])
        out["anchor_bias_sd"] = dict(cal["anchor_bias_sd"])
    return out


def hold_blocks(built, profiled, hold: dict, engine: str) -> tuple:
    """The final solve again with the blocks of ``hold`` at their prior means (:func:`~uwbimu.calibration.identifiability.hold_rule`): the lever arm
    under a :data:`HOLD_SD` prior, the anchor biases at 0 (``estimate_anchor_bias: false``); t_d as the
    profile's verdict had it (free from its value, or at its prior)."""
    import dataclasses

    import gtsam

    pb = built.problem
    upd = {}
    if "lever_arm" in hold:
        upd["lever_arm_prior_sd"] = HOLD_SD
    if "anchor_bias" in hold:
        upd["estimate_anchor_bias"] = False
    pb2 = dataclasses.replace(pb, options=pb.options.model_copy(update=upd))
    s = profiled.solved
    values = gtsam.Values(s.values)
    if "lever_arm" in hold:
        for i in range(pb.n_tags):
            prior = pb.lever_prior[i] if pb.lever_prior is not None else pb.options.lever_arm_prior
            values.update(keys.lever_arm(i), np.asarray(prior, float))
    if "anchor_bias" in hold:
        for j in range(len(pb.anchor_ids)):
            values.update(keys.anchor_bias(j), np.zeros(1))
    if profiled.td_free:
        new = solve(pb2, built.imu_factors, values, s.time_offset(), None, engine=engine)
    else:
        td = pb.options.time_offset_prior
        new = solve(pb2, built.imu_factors, values, td, td, engine=engine)
    return Built(problem=pb2, imu_factors=built.imu_factors), dataclasses.replace(profiled, solved=new)


def consider_sd(cal: dict, hold: dict, o) -> None:
    """A held lever arm is reported with its prior's sd (consider mode: the data did not determine it, so its
    uncertainty is the prior's), so that its verdict reads ``not identified``; the anchor biases held at 0 are
    listed in ``anchors.bias_held_at_zero`` by the report itself."""
    if "lever_arm" not in hold:
        return
    sd = [float(o.lever_arm_prior_sd)] * 3
    cal["lever_arm_sd"] = list(sd)
    cal["lever_arm_sd_model"] = list(sd)
    cal["lever_arm_held"] = True
    for t in (cal.get("tags") or {}).values():
        t["lever_arm_sd"] = list(sd)
