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
