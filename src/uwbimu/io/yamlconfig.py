"""One way to read a YAML configuration into a strict pydantic model.

Every configuration loader of the toolkit (scenarios, estimator and calibration
options, observability configs, Monte Carlo studies, trajectory-design configs,
rosbag mappings) goes through :func:`load_yaml_model`, so a bad file is refused
the same way everywhere: the message names the file, the 1-based line and the
field, for example::

    scenario.yaml: invalid scenario (1 error(s))
      line 7, field 'uwb.sigma': Input should be greater than 0

and the exception is a :class:`uwbimu.errors.ConfigError` (or the subclass the
caller names), exit code 2 on the command line.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Callable, Optional, TypeVar, Union

import yaml
from pydantic import BaseModel, ValidationError

from uwbimu.errors import ConfigError

__all__ = ["load_yaml_model", "read_yaml_mapping", "validate_model", "format_validation_error", "yaml_line"]

M = TypeVar("M", bound=BaseModel)
ErrorFactory = Callable[[str], Exception]


def yaml_line(text: str, loc: tuple) -> Optional[int]:
    """1-based line of the node at ``loc`` (a pydantic error location) in a YAML text.

    Location parts that are not keys of the document (pydantic's union tags, model
    names) are skipped; the line of the deepest key found is returned (None when the
    text does not parse or the first key is absent).
    """
    try:
        node = yaml.compose(text)
    except yaml.YAMLError:
        return None
    line = None
    for key in loc:
        if isinstance(node, yaml.MappingNode):
            for k, v in node.value:
                if k.value == str(key):
                    node, line = v, k.start_mark.line + 1
                    break
        elif isinstance(node, yaml.SequenceNode) and isinstance(key, int):
            if key >= len(node.value):
                return line
            node = node.value[key]
            line = node.start_mark.line + 1
    return line


def read_yaml_mapping(path: Union[str, os.PathLike], *, what: str = "configuration",
                      error: ErrorFactory = ConfigError, empty: bool = True) -> tuple[dict, str]:
    """Read a YAML file whose top level is a mapping.

    Parameters
    ----------
    path : the file.
    what : what the file holds, for messages ("scenario", "estimator options", ...).
    error : exception class (or factory ``message -> exception``) raised on refusal.
    empty : an empty file reads as ``{}`` (else it is refused).

    Returns
    -------
    (data, text) : the mapping and the file's text (for :func:`yaml_line`).
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: {what} file not found")
    text = path.read_text()
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f", line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise error(f"{path}{where}: not valid YAML: {problem}") from None
    if data is None and empty:
        data = {}
    if not isinstance(data, dict):
        raise error(f"{path}: expected a mapping of {what} fields at the top level, got {type(data).__name__}")
    return data, text


def format_validation_error(err: ValidationError, source: str, what: str = "configuration",
                            text: Optional[str] = None) -> str:
    """A pydantic error as ``SOURCE: invalid WHAT (N error(s))`` plus one line per field.

    Each field line reads ``line L, field 'a.b': message`` (the line only when ``text``,
    the YAML the data came from, is given and holds the field).
    """
    lines = [f"{source}: invalid {what} ({err.error_count()} error(s))"]
    for e in err.errors():
        loc = tuple(e["loc"])
        name = ".".join(str(x) for x in loc) or "(top level)"
        msg = "unknown field (not allowed here)" if e["type"] == "extra_forbidden" else e["msg"]
        line = yaml_line(text, loc) if text is not None and loc else None
        lines.append(f"  {f'line {line}, ' if line else ''}field '{name}': {msg}")
    return "\n".join(lines)


def validate_model(data: Any, model: type[M], *, source: str = "<dict>", what: str = "configuration",
                   text: Optional[str] = None, error: ErrorFactory = ConfigError) -> M:
    """``model.model_validate(data)`` with a refusal raised as ``error`` (see :func:`format_validation_error`)."""
    try:
        return model.model_validate(data)
    except ValidationError as err:
        raise error(format_validation_error(err, source, what, text)) from None


def load_yaml_model(path: Union[str, os.PathLike], model: type[M], *, what: str = "configuration",
                    error: ErrorFactory = ConfigError,
                    prepare: Optional[Callable[[dict], dict]] = None) -> M:
    """Read a YAML file into the strict pydantic ``model``; errors name file, line and field.

    Parameters
    ----------
    path : the YAML file (an empty file gives the model's defaults).
    model : the pydantic model class.
    what : what the file holds, for messages.
    error : exception class (or factory ``message -> exception``) raised on refusal;
        default :class:`uwbimu.errors.ConfigError` (exit code 2).
    prepare : optional ``data -> data`` applied before validation (e.g. resolve paths
        relative to the file); it must keep the keys so line numbers stay right.

    Returns
    -------
    The validated model.
    """
    data, text = read_yaml_mapping(path, what=what, error=error)
    if prepare is not None:
        data = prepare(data)
    return validate_model(data, model, source=str(path), what=what, text=text, error=error)
