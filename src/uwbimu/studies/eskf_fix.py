"""Start the ESKF from a surveyed take-off point (Monte Carlo harness only).

The ESKF's own initialiser multilaterates the first ranges and needs at least
four anchors; with three anchors the fix is ambiguous (the solution mirrored
through the anchors' plane fits equally well).  For studies with three anchors
(the seed's experiment) the harness can instead hand the ESKF an initial state
built like the initialiser's, except for the position:

* position: a *surveyed take-off point* — the true initial position plus
  N(0, sd^2) noise per axis drawn from the run's ``init`` seed, with that sd in
  the covariance (the only quantity derived from the truth, and noisy);
* velocity zero (the simulated flights start at rest) with ``init.velocity_sd``;
* roll and pitch from the accelerometer (the initialiser's levelling);
* yaw from ``init.yaw`` (the known take-off heading; required here) with
  ``init.yaw_sd_deg``;
* calibration priors (lever arm, time offset, biases) exactly as the ESKF's
  own ``build_problem`` sets them.

It uses the ESKF's public building blocks (``build_problem``, ``Prior``,
``assemble``, ``level_attitude``, ``start_index``); if those change, runs fail
with a clear message instead of silently doing something else.
"""

from __future__ import annotations

from uwbimu.errors import ConfigError
import math

import numpy as np


def run_eskf_from_fix(ds, options: dict, p0: np.ndarray, position_sd: float):
    """Run the ESKF on ``ds`` from an initial state at position ``p0`` [m] (world)."""
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.estimation.eskf import build_problem
    from uwbimu.estimation.init import InitialState, Prior, assemble, level_attitude, start_index

    opts = EskfOptions.model_validate(options)
    if opts.init.yaw is None:
        raise ConfigError("starting the ESKF from a surveyed point needs the take-off heading: set init.yaw")
    prob, info = build_problem(ds, opts)
    pf = info["priors"]
    t0 = float(prob.uwb_t[0])
    td, td_sd = float(pf.t_d), float(pf.t_d_sd)
    k0 = start_index(prob, t0, td)
    roll, pitch = level_attitude(prob, k0, opts.init.window_s)
    pr = Prior(
        p=np.asarray(p0, float), v=np.zeros(3), roll=roll, pitch=pitch, lever=pf.lever, ba=pf.b_a,
        bg=pf.b_g, anchor_bias=pf.anchor_bias, sd_p=float(position_sd), sd_v=opts.init.velocity_sd,
        sd_rp=math.radians(opts.init.roll_pitch_sd_deg), sd_ba=pf.b_a_sd, sd_bg=pf.b_g_sd,
        sd_lever=pf.lever_sd, sd_bias=pf.anchor_bias_sd,
    )
    x0, P0 = assemble(prob, pr, float(opts.init.yaw), math.radians(opts.init.yaw_sd_deg), td, td_sd, k0, t0,
                      np.zeros(3))
    initial = InitialState(x=x0, P=P0, k=k0, j=0,
                           info={"source": "surveyed take-off point (Monte Carlo harness)", "roll": roll,
                                 "pitch": pitch, "yaw": float(opts.init.yaw)})
    return run_eskf(ds, opts, initial=initial)
