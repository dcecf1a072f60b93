"""One YAML loader (issue 15 item 4): load_yaml_model names file, line and field; one error base."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest
from pydantic import BaseModel, ConfigDict, Field

from uwbimu.errors import EXIT_CODES, ConfigError, InputError, UwbimuError
from uwbimu.io.yamlconfig import load_yaml_model, yaml_line

SRC = Path(__file__).resolve().parents[1] / "src" / "uwbimu"


class _Inner(BaseModel):
    model_config = ConfigDict(extra="forbid")
    sigma: float = Field(0.1, gt=0)


class _Cfg(BaseModel):
    model_config = ConfigDict(extra="forbid")
    name: str = "x"
    uwb: _Inner = Field(default_factory=_Inner)
    points: list[list[float]] = []


def test_errors_name_file_line_and_field(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("name: a\n# a comment\nuwb:\n  sigma: -1\npoints:\n  - [0, 0]\n  - [1, 'x']\nextra_key: 3\n")
    with pytest.raises(ConfigError) as e:
        load_yaml_model(p, _Cfg, what="test config")
    msg = str(e.value)
    assert msg.startswith(f"{p}: invalid test config (3 error(s))")
    assert "line 4, field 'uwb.sigma': Input should be greater than 0" in msg
    assert "line 7, field 'points.1.1'" in msg
    assert "line 8, field 'extra_key': unknown field" in msg
    assert e.value.exit_code == 2 and isinstance(e.value, UwbimuError)


def test_missing_empty_and_malformed_files(tmp_path):
    with pytest.raises(ConfigError, match="configuration file not found"):
        load_yaml_model(tmp_path / "none.yaml", _Cfg)
    (tmp_path / "empty.yaml").write_text("")
    assert load_yaml_model(tmp_path / "empty.yaml", _Cfg) == _Cfg()
    (tmp_path / "bad.yaml").write_text("name: a\nuwb: {sigma: [1,\n")
    with pytest.raises(ConfigError, match=r"bad.yaml, line \d+: not valid YAML"):
        load_yaml_model(tmp_path / "bad.yaml", _Cfg)
    (tmp_path / "list.yaml").write_text("- 1\n")
    with pytest.raises(ConfigError, match="expected a mapping .* got list"):
        load_yaml_model(tmp_path / "list.yaml", _Cfg)


def test_custom_error_class_and_prepare(tmp_path):
    class MyError(InputError):
        pass

    p = tmp_path / "c.yaml"
    p.write_text("uwb:\n  sigma: 0\n")
    with pytest.raises(MyError, match="line 2"):
        load_yaml_model(p, _Cfg, error=MyError)
    cfg = load_yaml_model(p, _Cfg, prepare=lambda d: {**d, "uwb": {"sigma": 0.5}})
    assert cfg.uwb.sigma == 0.5


def test_yaml_line_skips_union_tags():
    text = "trajectory:\n  type: circle\n  radius: 0\n"
    assert yaml_line(text, ("trajectory", "circle", "radius")) == 3
    assert yaml_line(text, ("nothing",)) is None


@pytest.mark.parametrize("loader", ["scenario", "estimator", "calibration", "observability", "study"])
def test_every_config_loader_reports_the_line(tmp_path, loader):
    p = tmp_path / "c.yaml"
    if loader == "scenario":
        from uwbimu.sim import load_scenario as load

        p.write_text("duration: 10\nuwb:\n  sigma: -1\n")
        line = 3
    elif loader == "estimator":
        from uwbimu.estimation import EskfOptions

        load = EskfOptions.from_yaml
        p.write_text("output_rate_hz: 10\ngating:\n  probabilty: 0.99\n")
        line = 3
    elif loader == "calibration":
        from uwbimu.calibration import CalibrationOptions

        load = CalibrationOptions.from_yaml
        p.write_text("keyframe_hz: -1\n")
        line = 1
    elif loader == "observability":
        from uwbimu.observability.config import load_config as load

        p.write_text("anchors: [[0, 0, 0]]\nlie_order: -3\n")
        line = 2
    else:
        from uwbimu.studies import load_config as load

        p.write_text("runs: 1\nscenarios:\n  - name: a\n    builtin: calibration-flight\nestimators:\n  - kind: ukf\n")
        line = 6
    with pytest.raises(ConfigError) as e:
        load(p)
    assert str(p) in str(e.value) and f"line {line}, field" in str(e.value), str(e.value)


def test_no_other_yaml_config_loader_in_src():
    """yaml.safe_load only in the loader itself and the places listed (data files, not configurations)."""
    allowed = {
        "io/yamlconfig.py",  # the one loader
        "io/loader.py",  # dataset.yaml: a dataset's file, refusals are DatasetError(file, row, column)
        "io/importers/inrol.py",  # a recording's parameter file (import format)
        "io/atomic.py",  # scans written outputs for NaN
        "design/config.py",  # placement config: owned elsewhere this session (listed in CONTRIBUTING.md)
    }
    found = set()
    for path in SRC.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Attribute) and node.attr in ("safe_load", "load") and \
                    isinstance(node.value, ast.Name) and node.value.id == "yaml":
                found.add(str(path.relative_to(SRC)))
    assert found <= allowed, found - allowed


def test_error_classes_share_the_base_and_codes_are_documented():
    from uwbimu.errors import CheckFlagged, EstimationError, OutputError, UsageError
    from uwbimu.estimation.init import InitialisationError
    from uwbimu.eval.files import EvalInputError
    from uwbimu.io.importers.rosbag import RosbagImportError
    from uwbimu.observability.config import ConfigError as ObsConfigError
    from uwbimu.sim import ScenarioError, TrajectoryFileError
    from uwbimu.studies import MonteCarloError, StudyConfigError

    for cls in (InitialisationError, EvalInputError, RosbagImportError, ObsConfigError, ScenarioError,
                TrajectoryFileError, MonteCarloError, StudyConfigError):
        assert issubclass(cls, UwbimuError), cls
    assert StudyConfigError.exit_code == ScenarioError.exit_code == ConfigError.exit_code == 2
    assert issubclass(InitialisationError, RuntimeError)  # callers catching RuntimeError still do
    for cls in (InputError, UsageError, CheckFlagged, OutputError, EstimationError, ConfigError):
        assert cls.exit_code in EXIT_CODES and cls.__doc__ and f"exit {cls.exit_code}" in cls.__doc__.replace(
            "exit code", "exit"), cls
