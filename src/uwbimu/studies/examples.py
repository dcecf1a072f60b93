"""Built-in Monte Carlo studies (``uwbimu montecarlo --example NAME``).

``seed-anchor-planes`` reproduces seed 002, section IX (figures 2 and 3): three
anchors at different heights against three anchors in one horizontal plane,
a horizontal circle with vertical motion, the same noises (paired seeds), the
6-state point-mass EKF and the 19-state ESKF.  The same study is in
``examples/montecarlo/seed_anchor_planes.yaml`` (a test keeps them equal).

Choices (the seed gives no numbers): a 10 x 8 m room; anchors at the same
(x, y) in both layouts, heights 0.3 / 2.7 / 1.0 m against 1.5 m for all three;
the circle (r = 2 m, 10 s per lap, centre height 1.5 m, +-0.3 m at 0.1 Hz,
fixed heading) flies through the horizontal anchors' plane, where the seed's
analysis says the height is not observable from the ranges alone.  With three
anchors the multilateration fix is ambiguous (mirror solution), so both
estimators start from a surveyed take-off point (true position + N(0, 0.1^2)
per axis, from the run's init seed) and the ESKF from the known take-off
heading ``init.yaw = 0``; see :mod:`uwbimu.studies.eskf_fix`.  The
point-mass EKF is told the (zero) lever arm and an exact time offset
(``time_offset_sd: 0``): both are known in this experiment, so no consider
terms inflate its covariance.
"""

from __future__ import annotations

import copy

_ANCHOR_XY = [("A", 0.3, 1.0), ("B", 1.0, 4.0), ("C", 0.5, 7.0)]


def _scenario(heights: list[float]) -> dict:
    return {
        "duration": 60.0,
        "trajectory": {
            "type": "circle",
            "center": [5.0, 4.0, 1.5],
            "radius": 2.0,
            "period": 10.0,
            "z_amplitude": 0.3,
            "z_frequency": 0.1,
            "heading": "fixed",
        },
        "imu": {"rate_hz": 200.0, "noise": "bmi088"},
        "uwb": {"rate_hz": 50.0, "schedule": "round_robin", "sigma": 0.05},
        "anchors": [{"id": a, "position": [x, y, z]} for (a, x, y), z in zip(_ANCHOR_XY, heights)],
        "lever_arm": [0.0, 0.0, 0.0],
        "time_offset": 0.0,
    }


EXAMPLES: dict[str, dict] = {
    "seed-anchor-planes": {
        "name": "seed-anchor-planes",
        "description": "Seed 002 sec. IX: 3 anchors at different heights vs in one horizontal plane",
        "runs": 100,
        "seed_base": 2002,
        "skip_initial_s": 0.0,
        "trace_rate_hz": 5.0,
        "scenarios": [
            {"name": "different-heights", "scenario": _scenario([0.3, 2.7, 1.0])},
            {"name": "horizontal-plane", "scenario": _scenario([1.5, 1.5, 1.5])},
        ],
        "estimators": [
            {
                "name": "pointmass",
                "kind": "pointmass",
                # antenna at the IMU and clocks aligned, known in this experiment: no consider terms
                "options": {"initial_yaw": 0.0, "lever_arm": [0.0, 0.0, 0.0], "time_offset_sd": 0.0},
                "initial_position_sd": 0.1,
            },
            {
                "name": "eskf",
                "kind": "eskf",
                "options": {"init": {"yaw": 0.0}},
                "initial_position_sd": 0.1,
            },
        ],
    },
}


def example_config(name: str) -> dict:
    """A copy of a built-in study as a plain dict (``MonteCarloConfig`` fields)."""
    if name not in EXAMPLES:
        raise KeyError(f"unknown example {name!r}; choose one of {', '.join(map(str, sorted(EXAMPLES)))}")
    return copy.deepcopy(EXAMPLES[name])
