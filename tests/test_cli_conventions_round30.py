"""CLI conventions of issue 30 (items 1, 3, 4) and typed errors of issue 31 item 3.

* the one-time kernel compilation is announced and timed apart from the run (compile_notice);
* console comparisons with ground truth only when the frames agree (else the aligned figure);
* one output rule for every verb that writes (own unchanged outputs replaced, anything else --force);
* usage errors exit 2, refused input 1, never a relabelled ValueError; --force hinted only where it helps;
* no bare ``raise ValueError(`` for input checks in the modules that own input handling (AST scan).
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from uwbimu.cli.main import app

runner = CliRunner()
SRC = Path(__file__).resolve().parents[1] / "src" / "uwbimu"


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """A 20-s simulated flight written as a dataset, and the ESKF's outputs on it."""
    root = tmp_path_factory.mktemp("r30")
    sc = root / "s.yaml"
    sc.write_text("duration: 20\n")
    ds, est = root / "ds", root / "est"
    r = runner.invoke(app, ["simulate", str(sc), "-o", str(ds)])
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, ["estimate", str(ds), "-o", str(est), "--no-plots"])
    assert r.exit_code == 0, r.output
    return ds, est


# --- compile notice ---------------------------------------------------------------------------
def test_compile_notice_cold_and_warm(monkeypatch):
    from uwbimu.cli import compile_notice as cn

    calls = []
    monkeypatch.setattr(cn, "warm_up", lambda group="eskf": calls.append(group))
    monkeypatch.setattr(cn, "kernels_cold", lambda group="eskf": True)
    n = cn.ensure_compiled(None)
    assert n.cold and n.seconds >= 0.0 and n.error is None and calls == ["eskf"]
    monkeypatch.setattr(cn, "kernels_cold", lambda group="eskf": False)
    assert cn.ensure_compiled(None) == cn.CompileNotice(cold=False) and calls == ["eskf"]


def test_kernels_cold_reads_the_cache_index(monkeypatch):
    from types import SimpleNamespace

    from uwbimu.cli import compile_notice as cn

    def disp(index, signatures=()):
        return SimpleNamespace(signatures=list(signatures),
                               _cache=SimpleNamespace(_cache_file=SimpleNamespace(_load_index=lambda: index)))

    monkeypatch.setattr(cn, "_dispatchers", lambda group="eskf": [disp({})])
    assert cn.kernels_cold()  # an empty (or stale: numba empties it) index
    monkeypatch.setattr(cn, "_dispatchers", lambda group="eskf": [disp({"sig": "entry"})])
    assert not cn.kernels_cold()
    monkeypatch.setattr(cn, "_dispatchers", lambda group="eskf": [disp({}, signatures=["compiled"])])
    assert not cn.kernels_cold()  # compiled in this process already
    monkeypatch.setattr(cn, "_dispatchers", lambda group="eskf": [SimpleNamespace(signatures=[], _cache=None)])
    assert cn.kernels_cold()  # unreadable: cold
    monkeypatch.setattr(cn, "_dispatchers", lambda group="eskf": [lambda x: x])
    assert not cn.kernels_cold()  # NUMBA_DISABLE_JIT=1: plain functions, nothing to compile


def test_every_kernel_group_names_real_dispatchers():
    from uwbimu.cli import compile_notice as cn

    for group in cn.GROUPS:
        ds = cn._dispatchers(group)
        assert ds and all(hasattr(d, "signatures") and hasattr(d, "_cache") for d in ds), group


def test_warm_up_failure_is_recorded_not_raised(monkeypatch):
    from uwbimu.cli import compile_notice as cn

    def boom(group="eskf"):
        raise RuntimeError("x")

    monkeypatch.setattr(cn, "kernels_cold", lambda group="eskf": True)
    monkeypatch.setattr(cn, "warm_up", boom)
    n = cn.ensure_compiled(None)
    assert n.cold and n.error == "RuntimeError: x"


def test_estimate_compiles_before_the_run_and_times_them_apart(small, tmp_path, monkeypatch):
    from uwbimu.cli import compile_notice as cn

    order = []
    monkeypatch.setattr(cn, "kernels_cold", lambda group="eskf": True)
    monkeypatch.setattr(cn, "warm_up", lambda group="eskf": order.append("compile"))
    import uwbimu.cli.estimate as est_mod

    real = est_mod.run_with_progress
    monkeypatch.setattr(est_mod, "run_with_progress", lambda *a, **k: (order.append("run"), real(*a, **k))[1])
    ds, _ = small
    r = runner.invoke(app, ["estimate", str(ds), "-o", str(tmp_path / "e"), "--no-plots", "--no-clock-faults"])
    assert r.exit_code == 0, r.output
    assert order == ["compile", "run"]


# --- console comparison only when the frames agree --------------------------------------------
def test_truth_comparison_follows_the_frame_rule(small):
    from uwbimu.cli.estimate import truth_comparison
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.io.loader import load_dataset

    ds = load_dataset(small[0])
    res = run_eskf(ds, EskfOptions())
    same = truth_comparison(res, ds)
    assert same["frames_agree"] and same["align"] == "none" and np.isfinite(same["position_rmse"])
    ds.meta.extra = {**(ds.meta.extra or {}), "groundtruth_align": "se3", "groundtruth_attitude_comparable": False}
    other = truth_comparison(res, ds)
    assert not other["frames_agree"] and other["align"] == "se3"
    assert "position_rmse" not in other and "nees_mean" not in other  # raw figures are not offered
    assert 0 < other["ate_position_rmse"] < same["position_rmse"] + 1e-9  # the aligned fit can only be closer
    assert other["ate_rotation_rmse_deg"] is None and other["n_scored"] > 100 and other["error"] is None


def test_estimate_on_isas_walk_prints_only_the_aligned_comparison(tmp_path, monkeypatch):
    """The ISAS-Walk excerpt (ground truth in a Vive frame): the console gets the se3-aligned ATE, never the raw
    RMSE/NEES (issue 30 item 3, console side)."""
    import uwbimu.cli.estimate as est_mod

    excerpt = Path(__file__).parent / "data" / "isas_walk_excerpt"
    ds = tmp_path / "isas"
    r = runner.invoke(app, ["import", "isas-walk", str(excerpt), str(ds)])
    assert r.exit_code == 0, r.output
    shown = []
    real = est_mod.print_truth_comparison
    monkeypatch.setattr(est_mod, "print_truth_comparison", lambda c, cmp: (shown.append(cmp), real(c, cmp)))
    r = runner.invoke(app, ["estimate", str(ds), "-o", str(tmp_path / "e"), "--preset", "isas-walk", "--no-plots"])
    assert r.exit_code == 0, r.output
    (cmp,) = shown
    assert not cmp["frames_agree"] and cmp["align"] == "se3" and cmp["error"] is None
    assert np.isfinite(cmp["ate_position_rmse"]) and cmp["ate_rotation_rmse_deg"] is None  # body frames differ
    assert not {"position_rmse", "orientation_rmse_deg", "nees_mean"} & set(cmp)


def test_groundtruth_frame_rule():
    from uwbimu.errors import InputError
    from uwbimu.metrics.align import groundtruth_frame

    assert groundtruth_frame(None).frames_agree
    f = groundtruth_frame({"groundtruth_align": "se3", "groundtruth_attitude_comparable": False})
    assert not f.frames_agree and not f.attitude_comparable
    with pytest.raises(InputError):
        groundtruth_frame({"groundtruth_align": "sim3"})


# --- one output rule ----------------------------------------------------------------------------
def _verb_runs(ds, est, out):
    return {
        "estimate": (["estimate", str(ds), "-o", str(out), "--no-plots", "--no-clock-faults"], "trajectory.csv"),
        "evaluate": (["evaluate", str(est), "-g", str(ds), "-o", str(out), "--no-plots"], "evaluation.json"),
        "observability log": (["observability", "log", str(ds), "-o", str(out), "--window", "10"], "observability.csv"),
        "report": (["report", str(est), "-o", str(out)], "report.html"),
    }


@pytest.mark.parametrize("verb", ["estimate", "evaluate", "observability log", "report"])
def test_one_output_rule(small, tmp_path, verb):
    """A rerun replaces the verb's own unchanged outputs; a file it did not write (or one edited since) needs
    --force (exit 4, hint naming --force, nothing replaced); --force replaces it."""
    ds, est = small
    out = tmp_path / "out"
    args, name = _verb_runs(ds, est, out)[verb]
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output
    r = runner.invoke(app, args)
    assert r.exit_code == 0, r.output  # its own earlier outputs
    (out / name).write_text("edited by the user")
    r = runner.invoke(app, args)
    assert r.exit_code == 4 and "--force" in r.stderr, r.output
    assert (out / name).read_text() == "edited by the user"
    r = runner.invoke(app, args + ["--force"])
    assert r.exit_code == 0, r.output and (out / name).read_text() != "edited by the user"


def test_replacing_verbs_follow_the_same_rule(tmp_path):
    """simulate replaces a folder whole: allowed over its own unchanged dataset, refused over a user's file."""
    sc = tmp_path / "s.yaml"
    sc.write_text("duration: 5\n")
    out = tmp_path / "ds"
    assert runner.invoke(app, ["simulate", str(sc), "-o", str(out)]).exit_code == 0
    r = runner.invoke(app, ["simulate", str(sc), "-o", str(out)])
    assert r.exit_code == 0, r.output
    (out / "notes.txt").write_text("mine")
    r = runner.invoke(app, ["simulate", str(sc), "-o", str(out)])
    assert r.exit_code == 4 and "notes.txt" in r.stderr and "--force" in r.stderr
    assert (out / "notes.txt").read_text() == "mine"


# --- exit codes and hints -----------------------------------------------------------------------
def test_report_on_a_dataset_folder_hints_estimate_not_force(small):
    ds, _ = small
    r = runner.invoke(app, ["report", str(ds)])
    assert r.exit_code == 2 and r.stdout == ""
    assert "--force" not in r.stderr and "uwbimu estimate" in r.stderr


@pytest.mark.parametrize("args", [
    ["montecarlo", "--example", "seed-anchor-planes", "--runs", "0", "-o", "o"],
    ["montecarlo", "--example", "seed-anchor-planes", "--workers", "0", "-o", "o"],
    ["evaluate", "est", "-g", "ds", "--align", "sim3"],
    ["observability", "log", "d", "-o", "o", "--bound", "fisher"],
    ["evaluate", "est", "-g", "ds", "--distances", "1,x"],
    ["repeatability", "ds", "-o", "o", "-k", "1"],
    ["repeatability", "ds", "-o", "o", "--workers", "0"],
    ["repeatability", "ds", "-o", "o", "--level", "2"],
    ["report", "no-such-folder"],
])
def test_option_value_errors_exit_2(tmp_path, monkeypatch, args):
    monkeypatch.chdir(tmp_path)
    r = runner.invoke(app, args)
    assert r.exit_code == 2, r.output
    assert r.stderr.startswith("uwbimu: usage error: ")


def test_bad_input_through_the_entry_points_exits_1(small, tmp_path):
    """Typed errors end to end: refused input is exit 1 (not 5, not 70)."""
    ds, est = small
    # observability log --trajectory with a states file lacking columns (InputError from the library)
    bad = tmp_path / "states.csv"
    bad.write_text("t,px\n0,1\n")
    r = runner.invoke(app, ["observability", "log", str(ds), "-o", str(tmp_path / "o"), "--trajectory", str(bad)])
    assert r.exit_code == 1, r.output
    # evaluate against a ground truth on another clock (no overlap): InputError from metrics
    gt = pd.read_csv(ds / "groundtruth.csv")
    gt["t"] += 1e4
    gt.to_csv(tmp_path / "gt.csv", index=False)
    r = runner.invoke(app, ["evaluate", str(est), "-g", str(tmp_path / "gt.csv"), "-o", str(tmp_path / "ev"),
                            "--no-plots"])
    assert r.exit_code == 1, r.output
    assert "internal error" not in r.stderr and "estimation failed" not in r.stderr


def test_library_raises_typed_errors():
    from uwbimu.errors import ConfigError, InputError, UsageError
    from uwbimu.metrics.align import align_trajectories
    from uwbimu.metrics.trajectory import evaluate_trajectory

    with pytest.raises(UsageError):
        align_trajectories(np.zeros((3, 3)), np.zeros((3, 3)), "sim3")
    with pytest.raises(InputError):
        align_trajectories(np.zeros((0, 3)), np.zeros((0, 3)), "se3")
    traj = pd.DataFrame({"t": [0.0, 1, 2], "px": 0.0, "py": 0.0, "pz": 0.0})
    gt = traj.assign(t=traj["t"] + 100)
    with pytest.raises(InputError):
        evaluate_trajectory(traj, gt, align="none")
    from uwbimu.design.run import builtin_example

    with pytest.raises(UsageError):
        builtin_example("ship")
    assert issubclass(ConfigError, ValueError) and issubclass(UsageError, ValueError)  # old callers keep working


def test_groundtruth_without_attitude_is_named_in_a_warning(small, tmp_path):
    from uwbimu.eval.evaluate import evaluate_output

    ds, est = small
    gt = pd.read_csv(ds / "groundtruth.csv").drop(columns=["qw", "qx", "qy", "qz"])
    gt.to_csv(tmp_path / "gt.csv", index=False)
    out = tmp_path / "ev"
    out.mkdir()
    s = evaluate_output(out, tmp_path / "gt.csv", align="none", plots=False, trajectory=est / "trajectory.csv")
    (w,) = s["warnings"]
    assert w["code"] == "groundtruth_without_attitude" and w["missing_columns"] == ["qw", "qx", "qy", "qz"]
    assert "ate_rotation_deg" not in s
    s = evaluate_output(out, ds / "groundtruth.csv", align="none", plots=False, trajectory=est / "trajectory.csv")
    assert s["warnings"] == []


# --- messages and tables ------------------------------------------------------------------------
def test_column_list_has_no_python_syntax():
    from uwbimu.errors import column_list

    assert column_list(["innovation"]) == "column innovation"
    assert column_list(("qw", "qx")) == "columns qw, qx"


def test_natural_anchor_order():
    from uwbimu.cli.conventions import natural_key
    from uwbimu.cli.estimate import residual_rich_table

    assert sorted(["10", "2", "1", "A10", "A2"], key=natural_key) == ["1", "2", "10", "A2", "A10"]
    df = pd.DataFrame({"anchor": ["1", "10", "2"], "ranges": 1, "accepted": 1, "rejected_pct": 0.0,
                       "median": 0.0, "mad": 0.0})
    t = residual_rich_table(df)
    assert list(t.columns[0]._cells) == ["1", "2", "10"]


# --- no bare ValueError for input checks ----------------------------------------------------------
#: Modules whose input checks must raise the typed errors (issue 31 item 3).
TYPED_ERROR_MODULES = ["design", "observability", "sim", "metrics", "models", "io", "studies", "eval/evaluate.py",
                       "eval/files.py", "errors.py", "cli", "calibration"]
#: Not input handling: studies' executor/worker (the pool).
NOT_SCANNED = {"studies/executors.py", "studies/worker.py"}
#: ``raise ValueError`` kept on purpose, with the reason.
ALLOWED = {
    ("models/state.py", "__init__"): "StateLayout's internal contract: only code builds a layout; a violation is a bug",
    ("models/state.py", "process_noise"): "internal contract: make_settings gives every declared block's noise; a bug",
    ("models/blocks.py", "__post_init__"): "a block declaration is code, not input: a malformed one is a bug",
    ("design/placement.py", "info6_from_sums"): "internal array contract between two kernels: a violation is a bug",
}
#: pydantic turns a ValueError raised in a validator into a ValidationError, which the one
#: configuration loader reports as a ConfigError naming file, line and field.
VALIDATORS = {"field_validator", "model_validator", "validator", "root_validator"}


def _bare_value_errors():
    found = []
    for part in TYPED_ERROR_MODULES:
        p = SRC / part
        for f in [p] if p.is_file() else sorted(p.rglob("*.py")):
            rel = str(f.relative_to(SRC))
            if rel in NOT_SCANNED:
                continue

            def visit(node, stack):
                for ch in ast.iter_child_nodes(node):
                    st = stack + [ch] if isinstance(ch, (ast.FunctionDef, ast.AsyncFunctionDef)) else stack
                    if isinstance(ch, ast.Raise) and ch.exc is not None:
                        e = ch.exc.func if isinstance(ch.exc, ast.Call) else ch.exc
                        if getattr(e, "id", None) == "ValueError":
                            decos = {getattr(d.func if isinstance(d, ast.Call) else d, "attr", None)
                                     or getattr(d.func if isinstance(d, ast.Call) else d, "id", None)
                                     for fn in st for d in fn.decorator_list}
                            if not decos & VALIDATORS:
                                found.append((rel, st[-1].name if st else "<module>", ch.lineno))
                    visit(ch, st)

            visit(ast.parse(f.read_text()), [])
    return found


def test_no_bare_value_error_for_input_checks():
    bare = [(f, fn, ln) for f, fn, ln in _bare_value_errors() if (f, fn) not in ALLOWED]
    assert not bare, "raise InputError / ConfigError / UsageError (uwbimu.errors) instead: " + ", ".join(
        f"{f}:{ln} ({fn})" for f, fn, ln in bare)
    assert {(f, fn) for f, fn, _ in _bare_value_errors()} <= set(ALLOWED)


def test_console_warnings_are_the_reports_list():
    """estimate/demo print run_warning_items (the list the report shows), each text once."""
    import io
    from types import SimpleNamespace

    from rich.console import Console

    from uwbimu.cli.estimate import print_run_warnings
    from uwbimu.eval.report.inputs import run_warning_items

    res = SimpleNamespace(warnings=["w [s] one", "w [s] one"],
                          events=[{"kind": "range_errors_correlated_over_blocks", "message": "blocks"},
                                  {"kind": "initialised", "t": 0.0}])
    shown = print_run_warnings(Console(file=io.StringIO(), width=200), res)
    expected = run_warning_items(res.warnings, res.events)
    assert [(i.kind, i.text) for i in shown] == list(dict.fromkeys((i.kind, i.text) for i in expected))
    assert [i.kind for i in shown] == ["estimator_warning", "range_errors_correlated_over_blocks"]


def test_force_is_not_hinted_over_a_datasets_input_file(small, tmp_path):
    """place -o DATASET would overwrite anchors.csv, an input file: refused without a --force hint (it would not help)."""
    import shutil

    ds = tmp_path / "ds"
    shutil.copytree(small[0], ds)
    r = runner.invoke(app, ["place", "--example", "room", "-o", str(ds), "--no-plots"])
    assert r.exit_code == 4 and "anchors.csv" in r.stderr and "--force" not in r.stderr
    r = runner.invoke(app, ["place", "--example", "room", "-o", str(ds), "--no-plots", "--force"])
    assert r.exit_code == 4 and "--force" not in r.stderr


def test_position_only_groundtruth_is_accepted_with_a_structured_warning(small, tmp_path):
    """A ground truth without qw..qz loads (positions only) with a warning naming the columns; estimate then
    scores the position only; half a quaternion is refused, naming what is missing."""
    import shutil

    from uwbimu.cli.estimate import truth_comparison
    from uwbimu.errors import InputError
    from uwbimu.estimation import EskfOptions, run_eskf
    from uwbimu.io.loader import load_dataset

    ds_dir = tmp_path / "ds"
    shutil.copytree(small[0], ds_dir)
    gt = pd.read_csv(ds_dir / "groundtruth.csv")
    gt.drop(columns=["qw", "qx", "qy", "qz"]).to_csv(ds_dir / "groundtruth.csv", index=False)
    with pytest.warns(Warning):
        ds = load_dataset(ds_dir)
    (w,) = [w for w in ds.report.warnings if w["code"] == "groundtruth_without_attitude"]
    assert w["file"] == "groundtruth.csv" and w["missing_columns"] == ["qw", "qx", "qy", "qz"]
    assert "qw" not in ds.groundtruth.columns
    cmp = truth_comparison(run_eskf(ds, EskfOptions()), ds)
    assert cmp["frames_agree"] and np.isfinite(cmp["position_rmse"]) and cmp["orientation_rmse_deg"] is None
    gt.drop(columns=["qz"]).to_csv(ds_dir / "groundtruth.csv", index=False)
    with pytest.raises(InputError) as exc:
        load_dataset(ds_dir)
    assert exc.value.column == "qz"


def _entry_point_cases(tmp_path):
    from uwbimu.design.metrics import measurement_information
    from uwbimu.design.run import builtin_example
    from uwbimu.io.dataset import write_dataset
    from uwbimu.io.importers.anchors import survey_quat_order
    from uwbimu.metrics.trajectory import detect_glitches
    from uwbimu.models.imu import imu_preset
    from uwbimu.models.quaternion import quat_normalize
    from uwbimu.observability.window import trajectory_from_states_csv
    from uwbimu.sim.trajfile import write_trajectory_file

    return [
        ("design: unknown example", lambda: builtin_example("ship"), 2),
        ("design: unknown measurement", lambda: measurement_information(np.zeros((1, 3)), np.zeros((4, 3)), "aoa"), 2),
        ("io: unknown table format", lambda: write_dataset(None, tmp_path / "x", fmt="xlsx"), 2),
        ("io: unknown quaternion order", lambda: survey_quat_order(tmp_path / "a.txt", "zyxw"), 2),
        ("metrics: t and p of different length", lambda: detect_glitches(np.zeros(3), np.zeros((2, 3))), 1),
        ("models: zero quaternion", lambda: quat_normalize(np.zeros(4)), 1),
        ("models: non-positive IMU period", lambda: imu_preset("bmi088").discrete_sigmas(0.0), 2),
        ("observability: missing states file", lambda: trajectory_from_states_csv(tmp_path / "none.csv"), 1),
        ("sim: q and yaw together", lambda: write_trajectory_file(tmp_path / "t.csv", [0, 1], np.zeros((2, 3)),
                                                                   q=np.tile([1.0, 0, 0, 0], (2, 1)), yaw=[0, 0]), 2),
    ]


def test_library_entry_points_raise_typed_errors_with_their_exit_codes(tmp_path, capsys):
    """A representative bad input per package whose raises were typed: the class the CLI wrapper maps to the
    documented exit code (1 refused input, 2 usage/configuration); never a plain ValueError (70)."""
    from uwbimu.cli.main import report_error
    from uwbimu.errors import UwbimuError

    for name, call, code in _entry_point_cases(tmp_path):
        with pytest.raises(UwbimuError) as exc:
            call()
        assert report_error(exc.value) == code, name
    capsys.readouterr()
