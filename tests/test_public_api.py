"""The README's "Python API" example runs, and the public names resolve."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

import uwbimu

ROOT = Path(__file__).resolve().parents[1]


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## Python API", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_every_public_name_resolves():
    for name in uwbimu.__all__:
        assert getattr(uwbimu, name) is not None, name


def test_errors_share_one_base():
    from uwbimu.io.loader import DatasetError

    assert issubclass(DatasetError, uwbimu.UwbimuError)


def test_readme_example_runs_and_calibrates(monkeypatch):
    monkeypatch.chdir(ROOT)
    scope: dict = {}
    exec(compile(_readme_example(), "README.md (Python API)", "exec"), scope)
    cal, ds = scope["cal"], scope["ds"]
    truth = ds.meta.truth
    err = np.asarray(cal["lever_arm"]) - np.asarray(truth.lever_arm)
    assert np.all(np.abs(err) < 4 * np.asarray(cal["lever_arm_sd"]))
    assert abs(cal["time_offset"] - truth.time_offset) < 4 * cal["time_offset_sd"]
    assert scope["verdict"]["observable"] is True


def test_typed_results_read_as_attributes_and_as_the_former_dicts():
    """Issue 15 item 1: dataclasses for calibration, verdicts and events; dict access still works."""
    import json

    from uwbimu.estimation.result import CalibrationEstimate, Event

    v = uwbimu.structural_verdict({"anchors": [[0, 0, 0], [5, 0, 0.5], [0, 5, 1.0]], "lever_arm": [0.1, 0.05, 0.2],
                                   "random_points": 2, "seed": 0})
    assert isinstance(v, uwbimu.StructuralVerdict)
    assert v.observable is v["observable"] is True and v.rank == v["rank"] == v.dimension
    assert "singular_values" in v and v.get("nope") is None and dict(v)["verdict"] == v.verdict
    assert json.loads(json.dumps(v.to_dict(), default=str))["rank"] == v.rank
    d = uwbimu.delay_verdict({"anchors": [[0, 0, 0], [5, 0, 0.5], [0, 5, 1.0]], "lever_arm": [0.1, 0.05, 0.2],
                              "time_offset": 0.02, "random_points": 2, "seed": 0})
    assert isinstance(d, uwbimu.DelayVerdict) and d.identifiable == d["identifiable"]

    cal = CalibrationEstimate.from_dict({"time_offset": 0.01, "lever_arm": [0.1, 0, 0], "anchor_bias": {"A0": 0.1}})
    assert cal.time_offset == cal["time_offset"] == 0.01 and cal["anchor_bias"] == {"A0": 0.1}
    assert list(cal) == ["time_offset", "lever_arm", "anchor_bias"]  # the original keys, in order
    assert "gyro_bias" not in cal and cal.gyro_bias is None
    cal["tags"] = {"t": 1}
    assert cal.to_dict() == {"time_offset": 0.01, "lever_arm": [0.1, 0, 0], "anchor_bias": {"A0": 0.1}, "tags": {"t": 1}}
    assert cal == cal.to_dict()
    ev = Event.from_dict({"t": 1.5, "kind": "divergence", "reason": "nis"})
    assert ev.kind == "divergence" and ev["reason"] == "nis" and ev.get("kind") == "divergence"


def test_estimation_result_calibration_is_typed(tmp_path):
    from uwbimu.estimation.result import CalibrationEstimate, Event

    ds = uwbimu.simulate(uwbimu.builtin_scenario("calibration-flight").model_copy(update={"duration": 20.0}))
    res = uwbimu.run_eskf(ds, uwbimu.EskfOptions())
    assert isinstance(res.calibration, CalibrationEstimate)
    assert res.calibration.lever_arm == res.calibration["lever_arm"] and len(res.calibration.lever_arm_sd) == 3
    assert all(isinstance(e, Event) and e.kind for e in res.event_log())
    out = uwbimu.write_estimate(res, ds, tmp_path / "est")
    import yaml

    written = yaml.safe_load((tmp_path / "est" / "calibration.yaml").read_text())
    assert written["lever_arm"] == res.calibration.lever_arm and out is not None
