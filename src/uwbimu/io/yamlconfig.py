"""One way to read a YAML configuration into a strict pydantic model.

Every configuration loader of the toolkit (scenarios, estimator and calibration
options, observability configs, Monte Carlo studies, trajectory-design configs,
rosbag mappings) goes through :func:`load_yaml_model`, so a bad file is refused
the same way everywhere: the message names the file, the 1-based line and the
field, for example::

    scenario.yaml: invalid scenario (1 error(s))
      line 7, field 'uwb.sigma': Input should be greater than 0

and the exception is a :class:`uwbimu.errors.ConfigError` (or the subclass the
caller names), exit code 2 on the command line.  The refusal carries the first
problem's place as attributes too: ``file``, ``line`` (or None) and ``field``
(dotted, e.g. ``'lever_arm.prior.0'``).

A configuration holds finite numbers only: NaN and infinity (``.nan``, ``.inf``,
or the strings ``nan`` / ``inf`` that pydantic would read as floats) are refused
for every field, before and after validation (:func:`find_non_finite`), and a
file that is not UTF-8 text is refused naming the byte and line
(:func:`uwbimu.io.textio.read_text`).
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any, Callable, Optional, TypeVar, Union

import yaml
from pydantic import BaseModel, ValidationError

from uwbimu.errors import ConfigError
from uwbimu.io.textio import read_text

__all__ = ["load_yaml_model", "read_yaml_mapping", "validate_model", "format_validation_error", "yaml_line",
           "find_non_finite"]

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
    text = read_text(path, what=what, error=error)
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


def find_non_finite(data: Any, loc: tuple = ()) -> Optional[tuple[tuple, float]]:
    """Location and value of the first NaN or infinite float in nested mappings / sequences (None: all finite)."""
    if isinstance(data, dict):
        items = data.items()
    elif isinstance(data, (list, tuple)):
        items = enumerate(data)
    else:
        if isinstance(data, float) and not math.isfinite(data):  # np.float64 is a float too
            return loc, float(data)
        return None
    for k, v in items:
        found = find_non_finite(v, loc + (k,))
        if found is not None:
            return found
    return None


def _field_loc(loc) -> tuple:
    """A pydantic error location without its union-branch tags (``literal['adaptive']``, ``list[float]``,
    ``constrained-float``): the path of the field in the document."""
    return tuple(x for x in loc if not (isinstance(x, str) and ("[" in x or re.fullmatch(r"[a-z]+(-[a-z]+)+", x))))


def _refusal(error: ErrorFactory, message: str, source: str, line: Optional[int], field: Optional[str]) -> Exception:
    exc = error(message)
    # the place as attributes, for callers and tests that must not parse the message
    for name, value in (("file", source), ("line", line), ("field", field)):
        try:
            setattr(exc, name, value)
        except AttributeError:  # an exception type with slots: the message still names the place
            pass
    return exc


def _refuse_non_finite(data: Any, source: str, what: str, text: Optional[str], error: ErrorFactory) -> None:
    found = find_non_finite(data)
    if found is None:
        return
    loc, value = found
    name = ".".join(str(x) for x in loc) or "(top level)"
    line = yaml_line(text, loc) if text is not None and loc else None
    raise _refusal(error, f"{source}: invalid {what} (1 error(s))\n  {f'line {line}, ' if line else ''}field "
                          f"'{name}': {value} is not a finite number (NaN and infinity are refused)",
                   source, line, name)


def validate_model(data: Any, model: type[M], *, source: str = "<dict>", what: str = "configuration",
                   text: Optional[str] = None, error: ErrorFactory = ConfigError) -> M:
    """``model.model_validate(data)`` with a refusal raised as ``error`` (see :func:`format_validation_error`).

    NaN and infinite numbers are refused in the input and in the validated model (strings such as
    ``"inf"`` that the model reads as floats), naming the field.
    """
    _refuse_non_finite(data, source, what, text, error)
    try:
        out = model.model_validate(data)
    except ValidationError as err:
        first = _field_loc(err.errors()[0]["loc"]) if err.error_count() else ()
        raise _refusal(error, format_validation_error(err, source, what, text), source,
                       yaml_line(text, first) if text is not None and first else None,
                       ".".join(str(x) for x in first) or None) from None
    _refuse_non_finite(out.model_dump(), source, what, text, error)
    return out


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
