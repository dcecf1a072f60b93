"""``uwbimu estimate`` imports what it runs: not the batch calibrator's package (``uwbimu.calibration``: GTSAM
glue, scipy.stats, ...) nor the whole estimator registry (``uwbimu.estimators``), which cost over a second of
its start; not matplotlib with ``--no-plots``, nor typer's rich help machinery (``typer.rich_utils``: rich.markdown,
markdown_it, pygments) when no help or error is printed.  Checked in a fresh process (another test may have
imported them here).  The plain-text help patch still applies when typer imports its rich helpers later."""

from __future__ import annotations

import json
import subprocess
import sys

from uwbimu.io.dataset import write_dataset
from uwbimu.sim import builtin_scenario, simulate

_CHILD = r"""
import json, sys
from uwbimu.cli.main import app
sys.argv = ["uwbimu", "estimate", sys.argv[1], "-o", sys.argv[2], "--no-plots"]
try:
    app()
except SystemExit as exc:
    code = exc.code
else:
    code = 0
print(json.dumps({"code": code, "modules": sorted(m for m in sys.modules
                                                  if m.startswith(("uwbimu.", "matplotlib", "typer.", "scipy.")))}))
"""


def test_estimate_does_not_import_the_batch_calibrator(tmp_path):
    ds = simulate(builtin_scenario("calibration-flight").updated(duration=20.0))
    folder = write_dataset(ds, tmp_path / "log")
    out = subprocess.run([sys.executable, "-c", _CHILD, str(folder), str(tmp_path / "out")], capture_output=True,
                         text=True, check=True)
    rec = json.loads(out.stdout.strip().splitlines()[-1])
    assert rec["code"] in (0, None)
    assert (tmp_path / "out" / "trajectory.csv").exists()
    mods = set(rec["modules"])
    assert "uwbimu.estimation.eskf" in mods  # the child did run the filter
    assert "uwbimu.estimation.outputs" in mods  # ... and wrote its outputs
    assert not {m for m in mods if m == "uwbimu.calibration" or m.startswith("uwbimu.calibration.")}
    assert "uwbimu.estimators" not in mods
    assert not {m for m in mods if m == "matplotlib" or m.startswith("matplotlib.")}
    assert "typer.rich_utils" not in mods


_PACKAGE_CHILD = r"""
import json, sys
from uwbimu.estimation import write_outputs, EskfOptions
print(json.dumps(sorted(m for m in sys.modules if m.startswith(("uwbimu.estimation", "scipy.stats", "numba")))))
"""


def test_estimation_package_resolves_names_on_use():
    out = subprocess.run([sys.executable, "-c", _PACKAGE_CHILD], capture_output=True, text=True, check=True)
    mods = set(json.loads(out.stdout.strip().splitlines()[-1]))
    assert {"uwbimu.estimation.outputs", "uwbimu.estimation.options"} <= mods
    # the writer and the options need neither the filter, the point-mass EKF, numba nor scipy.stats
    assert not mods & {"uwbimu.estimation.eskf", "uwbimu.estimation.pointmass", "uwbimu.estimation.streaming",
                       "scipy.stats", "numba"}


def test_every_public_estimation_name_resolves():
    import uwbimu.estimation as E

    for name in E.__all__:
        assert getattr(E, name) is not None
    assert set(E.__all__) <= set(dir(E))


_HELP_CHILD = r"""
import sys
from uwbimu.cli.main import app
sys.argv = ["uwbimu", "estimate", "--help"]
try:
    app()
except SystemExit:
    pass
print("typer.rich_utils" in sys.modules)
"""


def test_help_units_survive_the_deferred_rich_patch():
    # "[s]" in a help text would be read as rich markup and dropped without the patch; typer imports its rich
    # helpers only now (the help), after uwbimu.cli.main was imported
    out = subprocess.run([sys.executable, "-c", _HELP_CHILD], capture_output=True, text=True, check=True,
                         env={**__import__("os").environ, "COLUMNS": "300"})
    lines = out.stdout.strip().splitlines()
    assert lines[-1] == "True"
    assert any("stamp [s]" in line for line in lines)
