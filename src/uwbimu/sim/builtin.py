"""Built-in named scenarios (``uwbimu simulate --list``).

All fly in the ``room8`` layout (10 x 8 x 3 m, 8 anchors at two heights) with
a BMI088-class IMU at 200 Hz, 50 Hz round-robin ranging (sigma 5 cm), lever
arm ``[0.12, -0.08, 0.14]`` m and time offset 0.03 s, unless stated.  Motion
stays within small-drone limits (speed <= 2 m/s, acceleration <= 3 m/s^2,
body rate <= 2 rad/s; checked by ``tests/test_sim_builtin.py``).
"""

from __future__ import annotations

import copy

from uwbimu.sim.scenario import Scenario

#: The demo default's common part.
_BASE: dict = {
    "duration": 60.0,
    "imu": {"rate_hz": 200.0, "noise": "bmi088"},
    "uwb": {"rate_hz": 50.0, "schedule": "round_robin", "sigma": 0.05},
    "anchors": "room8",
    "lever_arm": [0.12, -0.08, 0.14],
    "time_offset": 0.03,
    "seeds": {"truth": 0, "noise": 1, "init": 2},
}

_LISSAJOUS = {"type": "lissajous"}  # defaults of LissajousSpec: the excited calibration flight

_BUILTINS: dict[str, dict] = {
    "calibration-flight": {
        "description": "Demo default: 60 s 3-D Lissajous with attitude excitation, room8, BMI088, 50 Hz UWB",
        "trajectory": _LISSAJOUS,
    },
    "excited-90s": {
        # The accuracy-target flight of the ESKF (docs/estimator.md): a 1:2 Lissajous (figure-8-like,
        # not a circle: a constant-speed circle makes a time shift look like a yaw rotation) at
        # 0.15/0.30 Hz for the time offset (rms speed 1.4 m/s, rms acceleration 1.9 m/s^2), and
        # roll/pitch oscillations of 0.42 rad (24 deg each, tilt <= 34 deg) at 0.45/0.37 Hz plus a
        # steady 0.5 rad/s yaw spin for the lever arm.  Peaks: speed 1.72 m/s, acceleration
        # 2.62 m/s^2, body rate 1.95 rad/s.
        "description": "Strongly excited 90 s calibration flight (1:2 Lissajous, 34 deg tilt, yaw spin)",
        "duration": 90.0,
        "trajectory": {
            "type": "lissajous",
            "amplitude": [1.7, 0.6, 0.35],
            "frequency": [0.15, 0.30, 0.13],
            "phase": [0.0, 1.5708, 0.0],
            "attitude": {"amplitude": [0.42, 0.42, 0.6], "frequency": [0.45, 0.37, 0.15], "yaw_rate": 0.5},
        },
    },
    "lissajous": {
        "description": "3-D Lissajous with stronger roll/pitch/yaw excitation",
        "trajectory": {
            "type": "lissajous",
            "amplitude": [2.5, 2.0, 0.7],
            "frequency": [0.08, 0.11, 0.15],
            "attitude": {"amplitude": [0.45, 0.45, 1.0], "frequency": [0.35, 0.27, 0.07]},
        },
    },
    "hover": {"description": "Near-hover at the room centre (weak excitation)", "trajectory": {"type": "hover"}},
    "circle": {"description": "Horizontal circle r = 2 m, 10 s per lap, heading along the path", "trajectory": {"type": "circle"}},
    "figure8": {"description": "Horizontal figure-8, 6 x 3 m, 20 s period, gentle attitude motion", "trajectory": {"type": "figure8"}},
    "random": {"description": "Seeded random smooth motion (sum of sinusoids, seeds.truth)", "trajectory": {"type": "random"}},
    "translation": {
        "description": "Pure translation, constant attitude (angular velocity exactly zero)",
        "trajectory": {"type": "translation"},
    },
    "rotation": {"description": "Pure rotation about a fixed point (roll, pitch, yaw)", "trajectory": {"type": "rotation"}},
    "nlos": {
        "description": "Calibration flight with NLOS: 2 % background, bursts on A1 and A6",
        "trajectory": _LISSAJOUS,
        "uwb": {
            "nlos_prob": 0.02,
            "nlos_scale": 0.4,
            "nlos_bursts": [
                {"t0": 15.0, "t1": 25.0, "anchor": "A1", "prob": 0.8},
                {"t0": 35.0, "t1": 42.0, "anchor": "A6", "prob": 0.8},
            ],
        },
    },
    "outage": {
        "description": "Calibration flight with anchor A2 out for 10 s (20-30 s)",
        "trajectory": _LISSAJOUS,
        "uwb": {"outages": [[20.0, 30.0, "A2"]]},
    },
    "two-tags": {
        "description": "Calibration flight with two tags (front/back lever arms), ranges carry a tag column",
        "trajectory": _LISSAJOUS,
        "lever_arm": None,
        "tags": [
            {"name": "front", "lever_arm": [0.12, -0.08, 0.14]},
            {"name": "back", "lever_arm": [-0.15, 0.06, 0.10]},
        ],
    },
    "ideal": {
        "description": "Calibration flight with a noise-free, bias-free IMU and exact ranges (for tests)",
        "trajectory": _LISSAJOUS,
        "imu": {"noise": "ideal", "accel_bias": [0, 0, 0], "gyro_bias": [0, 0, 0]},
        "uwb": {"sigma": 0.0},
    },
}


# A Crazyflie-class quadrotor (BMI088 at 500 Hz, Loco deck antenna 9 cm above the IMU, as in the
# UTIL dataset's platform) flying a 3-D Lissajous inside the Bitcraze 8-anchor box (4 x 4 x 2.4 m),
# Loco Positioning TDoA3 at 400 packets/s (about 50 per anchor), tag timestamp noise 4 cm and anchor
# clock noise 3 cm per packet, i.e. a difference sd of sqrt(2 (0.04^2 + 0.03^2)) = 7.1 cm.
_QUAD: dict = {
    "duration": 60.0,
    "imu": {"rate_hz": 500.0, "noise": "bmi088"},
    "uwb": {"mode": "tdoa3", "rate_hz": 400.0, "sigma": 0.04, "clock_sigma": 0.03},
    "anchors": "bitcraze8",
    "lever_arm": [-0.012, 0.001, 0.091],
    "time_offset": 0.01,
    "trajectory": {
        "type": "lissajous",
        "center": [2.0, 2.0, 1.3],
        "amplitude": [1.3, 1.2, 0.5],
        "frequency": [0.11, 0.15, 0.13],
        "attitude": {"amplitude": [0.3, 0.3, 0.8], "frequency": [0.45, 0.37, 0.07]},
    },
}
_BUILTINS["crazyflie-tdoa3"] = {
    "description": "Small quadrotor in the Bitcraze 8-anchor box, Loco TDoA3 (400 packets/s), BMI088 at 500 Hz",
    **_QUAD,
}
_BUILTINS["crazyflie-tdoa2"] = {
    "description": "As crazyflie-tdoa3 with Loco TDoA2 (fixed slot order, consecutive-slot differences)",
    **_QUAD,
    "uwb": {**_QUAD["uwb"], "mode": "tdoa2"},
}
_BUILTINS["crazyflie-twr"] = {
    "description": "As crazyflie-tdoa3 with two-way ranging (round robin, 400 ranges/s, sigma 5 cm)",
    **_QUAD,
    "uwb": {"mode": "twr", "rate_hz": 400.0, "sigma": 0.05},
}


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if v is None:
            out.pop(k, None)
        elif isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def list_scenarios() -> dict[str, str]:
    """Built-in scenario names mapped to their one-line descriptions."""
    return {name: spec["description"] for name, spec in _BUILTINS.items()}


def builtin_scenario(name: str) -> Scenario:
    """A fresh :class:`Scenario` for a built-in name (see :func:`list_scenarios`)."""
    if name not in _BUILTINS:
        raise KeyError(f"unknown built-in scenario {name!r}; choose one of {', '.join(map(str, sorted(_BUILTINS)))}")
    data = _merge(_BASE, _BUILTINS[name])
    data["name"] = name
    return Scenario.model_validate(data)
