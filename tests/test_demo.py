"""``uwbimu demo`` end to end: every stage runs and leaves its outputs."""

import io

import pytest
from rich.console import Console
from typer.testing import CliRunner

from uwbimu.cli.demo import DEMO_MARKER, run_demo
from uwbimu.cli.main import app
from uwbimu.errors import OutputError


@pytest.fixture(scope="module")
def demo_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo") / "out"
    buf = io.StringIO()
    figures = run_demo(out, Console(file=buf, width=160), duration=30.0)
    return out, figures, buf.getvalue()


def test_demo_writes_every_stage(demo_run):
    out, figures, text = demo_run
    for rel in ["dataset/imu.csv", "dataset/uwb.csv", "dataset/anchors.csv", "dataset/groundtruth.csv",
                "dataset/dataset.yaml", "estimate/trajectory.csv", "estimate/calibration.yaml",
                "estimate/residuals.csv", "estimate/observability.csv", "estimate/report.html", DEMO_MARKER]:
        assert (out / rel).is_file(), rel
    assert figures["observable"] and figures["td_identifiable"]
    assert figures["flags"] == []
    assert "Online calibration" in text and "report:" in text
    # The calibration the demo prints is the estimator's, and it is close to the truth.
    la = figures["calibration"]["lever_arm"]
    assert abs(la[2] - 0.14) < 0.05
    # Every repeatability window was calibrated (a window that fails is recorded, not raised).
    import json

    rep = json.loads((out / "estimate" / "repeatability.json").read_text())
    assert rep["n_failed"] == 0 and set(figures["repeatability"]) == {"lx", "ly", "lz", "time_offset"}


def test_demo_reruns_into_its_own_folder(demo_run, tmp_path):
    out, _, _ = demo_run
    # A folder written by the demo carries the marker and may be replaced ...
    assert (out / DEMO_MARKER).exists()
    # ... a user's folder may not.
    user = tmp_path / "mine"
    user.mkdir()
    (user / "precious.txt").write_text("keep me")
    with pytest.raises(OutputError, match="precious.txt"):  # the output rule: a file uwbimu did not write
        run_demo(user, Console(file=io.StringIO()), duration=5.0)
    assert (user / "precious.txt").read_text() == "keep me"


def test_help_lists_every_verb():
    res = CliRunner().invoke(app, ["--help"], terminal_width=200)
    assert res.exit_code == 0
    for verb in ["demo", "simulate", "check", "import", "estimate", "observability", "place", "plan",
                 "montecarlo", "evaluate", "report"]:
        assert verb in res.output, verb
