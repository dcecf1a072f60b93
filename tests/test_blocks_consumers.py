"""Diagnostics, observability windows and reports loop over the declared blocks (issue 31 item 1): the
calibration blocks (``BlockSpec.calibration``) drive the excitation monitor, the per-window flags, the
scales and the report tables, with the results of the former literal code (pinned here)."""

from __future__ import annotations

import ast
import inspect
import itertools
import json

import numpy as np
import pandas as pd
import pytest

from uwbimu.cli import report as cli_report
from uwbimu.estimation import diagnostics
from uwbimu.estimation.options import EskfOptions
from uwbimu.estimation.problem import block_mode, block_prior_sd, make_settings
from uwbimu.estimation.timeoffset import time_offset_prior_sd
from uwbimu.eval.report import common, sections
from uwbimu.eval.report.inputs import ReportInputs
from uwbimu.models import blocks as B
from uwbimu.models import state as S
from uwbimu.models.imu import ImuNoise
from uwbimu.models.quaternion import quat_exp
from uwbimu.observability import directions, window

NOISE = ImuNoise(accel_noise_density=0.01, gyro_noise_density=1e-3, accel_bias_rw=1e-4, gyro_bias_rw=1e-5)


def _settings(opts):
    return make_settings(opts, list("abcd"), np.arange(12.0).reshape(4, 3), NOISE, 0.1, None, [0.0, 0.0, 0.1])


def test_calibration_blocks_are_the_lever_arm_and_the_time_offset_in_output_order():
    assert [b.name for b in B.CALIBRATION_BLOCKS] == ["lever", "t_d"]
    assert common.CAL_COLUMNS == ("lx", "ly", "lz", "time_offset")
    # the report's repeatability bound reads these error-state indices (formerly a literal table)
    assert sections._REP_INDEX == {"lx": S.E_L, "ly": S.E_L + 1, "lz": S.E_L + 2, "time_offset": S.E_TD}


def test_observability_scales_and_priors_are_the_former_per_block_values():
    assert window.DEFAULT_SCALES == {"p": 1.0, "v": 1.0, "th": 1.0, "ba": 0.1, "bg": 0.01, "l": 0.1, "time_offset": 0.01}
    assert window.DEFAULT_PRIOR_SD == {"p": 0.3, "v": 0.5, "th": 0.1, "ba": 0.1, "bg": 0.01, "l": 0.3, "time_offset": 0.1}
    keys = ["p"] * 3 + ["v"] * 3 + ["th"] * 3 + ["ba"] * 3 + ["bg"] * 3 + ["l"] * 3 + ["time_offset"]
    scales = {k: float(i + 2) for i, k in enumerate(window.DEFAULT_SCALES)}  # distinct per block
    assert window._scale_vector(scales).tolist() == [scales[k] for k in keys]
    assert directions.BLOCK_LABELS["l"] == ("lever arm", "body") and directions.BLOCK_LABELS["time_offset"] == ("time offset", "")
    assert directions._blocks(S.ERROR_STATE_NAMES)["time_offset"] == [S.E_TD]


@pytest.mark.parametrize("mode,prior,grid,search", list(itertools.product(
    ("estimate", "consider", "fixed"), (None, 0.03), ([-0.2, 0.0, 0.2], [0.0], [-0.01, 0.01]), (True, False))))
def test_block_prior_sd_of_the_time_offset_is_time_offset_prior_sd(mode, prior, grid, search):
    opts = EskfOptions(time_offset={"mode": mode, "prior": prior, "prior_sd": 0.05},
                       init={"td_grid": grid, "search_time_offset": search})
    _, pr = _settings(opts)
    assert block_prior_sd(pr, opts, "t_d").tolist() == [time_offset_prior_sd(pr, opts)]
    assert np.array_equal(block_prior_sd(pr, opts, "lever"), pr.lever_sd)
    assert block_mode(opts, B.BLOCK["t_d"]) == mode and block_mode(opts, B.BLOCK["p"]) == "estimate"


def _legacy_excitation_warnings(prob, t_imu_out, X, sd, priors, opts):
    """The excitation monitor as it was written before the blocks drove it (lever arm and t_d by name)."""
    ex = opts.excitation
    warnings, events = [], []
    t, rot, acc = diagnostics.excitation_profile(prob, t_imu_out, X, ex.window_s)
    checks = []
    if opts.lever_arm.mode == "estimate":
        checks.append(("lever arm", "rotation", rot, ex.min_rotation_rate, "rad/s"))
    if opts.time_offset.mode == "estimate":
        checks.append(("time offset", "acceleration", acc, ex.min_acceleration, "m/s^2"))
    for name, what, sig, thr, unit in checks:
        low = sig < thr
        frac = float(np.mean(~low)) if len(sig) else 0.0
        for a, b in diagnostics._intervals(t, low, ex.window_s):
            events.append({"t": a, "kind": "low_excitation", "parameter": name, "t_end": b,
                           "measure": f"RMS {what}", "threshold": thr})
        if frac < 0.1:
            warnings.append(f"{name}: weak excitation, RMS {what} >= {thr} {unit} in only {100 * frac:.0f}% of the log "
                            f"(max {float(sig.max()):.3g} {unit}); the {name} is poorly observable from this motion")
    sd_end = sd[-1]
    if opts.lever_arm.mode == "estimate":
        prior = priors.lever_sd
        ratio = sd_end[S.EPIU] / np.where(prior > 0, prior, np.nan)
        if np.any(ratio > ex.sd_ratio_warn):
            warnings.append(f"lever arm not well determined: final sd {np.round(100 * sd_end[S.EPIU], 1).tolist()} cm "
                            f"vs prior {np.round(100 * prior, 1).tolist()} cm; excite rotations about all axes")
    if opts.time_offset.mode == "estimate" and priors.t_d_sd > 0:
        p = time_offset_prior_sd(priors, opts)
        if sd_end[S.ETD] > ex.sd_ratio_warn * p:
            warnings.append(f"time offset not well determined: final sd {1000 * sd_end[S.ETD]:.1f} ms vs prior "
                            f"{1000 * p:.1f} ms; move with changing velocity")
    return warnings, events


@pytest.mark.parametrize("lever_mode,td_mode,moving,sd_scale", list(itertools.product(
    ("estimate", "fixed"), ("estimate", "consider"), (False, True), (0.01, 1.0, 10.0))))
def test_excitation_monitor_loops_over_the_calibration_blocks(lever_mode, td_mode, moving, sd_scale):
    opts = EskfOptions(lever_arm={"mode": lever_mode}, time_offset={"mode": td_mode})
    prob, pr = _settings(opts)
    dt, n = 0.01, 3000
    t = np.arange(n) * dt
    rate = 0.8 * np.sin(0.5 * t) if moving else np.zeros(n)  # rotation (and acceleration) in the second half
    rate[: n // 2] = 0.0
    u = np.zeros((n, 6))
    u[:, 2] = 9.81 + (2.0 * np.cos(0.7 * t) if moving else 0.0) * (t > t[n // 2])
    u[:, 3] = rate
    prob.imu_t, prob.imu_u, prob.dt_nom = t, u, dt
    X = np.zeros((n, prob.layout.n_nom))
    X[:, S.Q] = quat_exp(np.zeros(3))  # level: the IMU's specific force minus gravity is the acceleration
    sd = np.tile(np.r_[np.full(S.ERROR_DIM - 4, 0.1), [0.3, 0.004, 0.3], [0.01]] * sd_scale, (5, 1))
    got = diagnostics.excitation_warnings(prob, t, X, sd, pr, opts)
    assert got == _legacy_excitation_warnings(prob, t, X, sd, pr, opts)
    estimated = {b.label for b in B.CALIBRATION_BLOCKS if block_mode(opts, b) == "estimate"}
    assert {e["parameter"] for e in got[1]} <= estimated
    if not moving:  # no motion at all: every estimated block has its low-excitation interval
        assert {e["parameter"] for e in got[1]} == estimated


CONSUMERS = (diagnostics, window, sections, common, cli_report)


@pytest.mark.parametrize("module", CONSUMERS, ids=lambda m: m.__name__)
def test_consumers_name_no_calibration_component_by_a_literal(module):
    """The calibration blocks' component names (``lx .. time_offset``, ``sd_time_offset``) come from the declarations."""
    names = set(B.calibration_components()) - {b.output_key for b in B.CALIBRATION_BLOCKS}  # time_offset: a key too
    names |= {f"sd_{n}" for n in names} | set(B.legacy_name_map())
    literals = {node.value for node in ast.walk(ast.parse(inspect.getsource(module)))
                if isinstance(node, ast.Constant) and isinstance(node.value, str)}
    assert not literals & names


def _write_run(folder, names: dict) -> None:
    """states.csv, observability.csv and repeatability.json of a run whose time offset is called names[...]."""
    folder.mkdir()
    td, sd_td = names["td"], names["sd_td"]
    pd.DataFrame({"t": [0.0, 1.0], "lx": [0.1, 0.11], "ly": [0.0, 0.0], "lz": [0.0, 0.0], td: [0.01, 0.012],
                  "sd_lx": [0.05, 0.01], "sd_ly": [0.05, 0.01], "sd_lz": [0.05, 0.01], sd_td: [0.05, 0.003]}).to_csv(
        folder / "states.csv", index=False)
    pd.DataFrame({"t_start": [0.0], "t_end": [1.0], "sd_lx": [0.01], sd_td: [0.002],
                  "time_offset_excited": [True]}).to_csv(folder / "observability.csv", index=False)
    (folder / "repeatability.json").write_text(json.dumps({
        "k": 2, "parameters": {"lx": {"mean": 0.1}, td: {"mean": 0.011}},
        "windows": [{"values": {"lx": 0.1, td: 0.011}, "sd": {"lx": 0.01, td: 0.001}}]}))


def test_a_legacy_named_output_is_read_under_the_current_names(tmp_path):
    """Files written before the time offset's columns took its one output name (``td``, ``sd_td``) read like
    current ones (``time_offset``, ``sd_time_offset``) in the report."""
    assert B.legacy_name_map() == {"td": "time_offset", "sd_td": "sd_time_offset"}
    _write_run(tmp_path / "old", {"td": "td", "sd_td": "sd_td"})
    _write_run(tmp_path / "new", {"td": "time_offset", "sd_td": "sd_time_offset"})
    old, new = ReportInputs(tmp_path / "old"), ReportInputs(tmp_path / "new")
    for attr in ("states", "observability"):
        pd.testing.assert_frame_equal(getattr(old, attr), getattr(new, attr))
    assert "sd_time_offset" in old.states.columns and "td" not in old.states.columns
    assert old.repeatability == new.repeatability and set(old.repeatability["parameters"]) == {"lx", "time_offset"}
    assert sections._calibration_history(old)[1] == {n: n for n in common.CAL_COLUMNS}


def test_an_older_states_csv_linearises_the_observability_analysis(tmp_path):
    """``uwbimu observability log --trajectory states.csv`` reads a file with the former ``td`` column."""
    n = 5
    cols = {"t": np.arange(n, dtype=float), **{c: np.zeros(n) for c in S.NOMINAL_STATE_NAMES}}
    cols["qw"], cols["lx"], cols["time_offset"] = np.ones(n), np.full(n, 0.1), np.full(n, 0.02)
    pd.DataFrame(cols).to_csv(tmp_path / "new.csv", index=False)
    pd.DataFrame(cols).rename(columns={"time_offset": "td"}).to_csv(tmp_path / "old.csv", index=False)
    new, old = window.trajectory_from_states_csv(tmp_path / "new.csv"), window.trajectory_from_states_csv(tmp_path / "old.csv")
    assert old.t_d == new.t_d == 0.02 and np.array_equal(old.lever_arm, new.lever_arm)
