"""``uwbimu estimate`` imports what it runs: not the batch calibrator's package (``uwbimu.calibration``: GTSAM
glue, scipy.stats, ...) nor the whole estimator registry (``uwbimu.estimators``), which cost over a second of
its start.  Checked in a fresh process (another test may have imported them here)."""

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
print(json.dumps({"code": code, "modules": sorted(m for m in sys.modules if m.startswith("uwbimu."))}))
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
    assert not {m for m in mods if m == "uwbimu.calibration" or m.startswith("uwbimu.calibration.")}
    assert "uwbimu.estimators" not in mods
