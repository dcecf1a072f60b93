"""Atomic output writing: a file appears whole or not at all.

Every output the toolkit writes (CSV, YAML, JSON, PNG, HTML) goes through
these helpers: data is written to a temporary file in the same folder and
renamed into place with :func:`os.replace`, which is atomic on POSIX.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import yaml


@contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it onto ``path`` on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=suffix or path.suffix, dir=path.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp creates 0600 files; give outputs the usual permissions of a new file.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, path)
    except BaseException:
        tmp_path.unlink(missing_ok=True)
        raise


def write_text(path: str | os.PathLike, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def write_yaml(path: str | os.PathLike, obj: Any) -> Path:
    return write_text(path, yaml.safe_dump(obj, sort_keys=False))


def write_json(path: str | os.PathLike, obj: Any) -> Path:
    return write_text(path, json.dumps(obj, indent=2, default=_json_default) + "\n")


def write_csv(path: str | os.PathLike, df, **kwargs) -> Path:
    """Write a pandas DataFrame atomically (``index=False`` by default).

    A printf-style ``float_format`` (e.g. ``"%.9g"``) is applied here, column by column, before pandas
    writes the frame: pandas applies it through a Python closure and two NA checks per cell (about 5 µs a
    cell, 2 s for the million cells of a 10-minute run's outputs); here it is one ``%`` per cell (the same
    operator on the same numbers, so the file is byte-identical: ``tests/test_write_csv_fast.py``).
    """
    kwargs.setdefault("index", False)
    fmt = kwargs.get("float_format")
    if isinstance(fmt, str) and _plain_csv_call(kwargs):
        na_rep = kwargs.get("na_rep", "")
        if set(kwargs) <= {"index", "float_format", "na_rep"}:
            text = _csv_text(df, fmt, na_rep)
            if text is not None:
                return write_bytes(path, text.encode("utf-8"))
        df = _format_float_columns(df, fmt, na_rep)
        kwargs.pop("float_format")
    with atomic_path(path) as tmp:
        df.to_csv(tmp, **kwargs)
    return Path(path)


_CSV_SPECIAL = (",", '"', "\n", "\r")


def _csv_text(df, fmt: str, na_rep: str):
    """The text ``df.to_csv(index=False, float_format=fmt, na_rep=na_rep)`` writes, built row-wise, or None
    for a frame this does not cover (then pandas writes it): columns of NumPy float, int or bool, or text
    (str cells, NaN / None read as ``na_rep``) that needs no CSV quoting, at least two columns (a
    one-column row of an empty cell is quoted by the csv module), string column names needing no quoting.

    Each row is one ``%`` of a row format (``fmt`` for a float column, ``%s`` for the others' text, the
    literal ``na_rep`` for an all-NaN column): the same ``fmt % value`` per float cell as a cell-by-cell
    build, with one Python operation per row instead of one per cell (a 10-minute run's outputs: 1 M cells).
    A row holding a NaN in a column that is not all-NaN is built cell by cell (``na_rep`` for the NaN).
    """
    import numpy as np

    if df.shape[1] < 2 or not all(isinstance(c, str) for c in df.columns):
        return None
    if any(any(ch in c for ch in _CSV_SPECIAL) for c in df.columns) or any(ch in na_rep for ch in _CSV_SPECIAL):
        return None
    n = len(df)
    specs: list[str] = []  # per column: its part of the row format
    args: list[list] = []  # per column with a conversion: its cells (floats, or text for %s)
    float_arg: list[bool] = []  # per entry of args: a float column (fmt, NaN -> na_rep)
    converts: list[bool] = []  # per column: takes a cell from args (False: the literal na_rep)
    nan_rows = np.zeros(n, dtype=bool)
    for i, dtype in enumerate(df.dtypes):
        ser = df.iloc[:, i]
        if isinstance(dtype, np.dtype) and dtype.kind == "f":
            vals = ser.to_numpy()
            nan = np.isnan(vals)
            if n and nan.all():
                specs.append(na_rep.replace("%", "%%"))  # a column of empty cells: no conversion at all
                converts.append(False)
                continue
            nan_rows |= nan
            specs.append(fmt)
            args.append(vals.tolist())
            float_arg.append(True)
            converts.append(True)
            continue
        if isinstance(dtype, np.dtype) and dtype.kind in "iub":
            text = list(map(str, ser.to_numpy().tolist()))
        elif dtype == object or str(dtype) in ("str", "string"):
            vals = ser.to_numpy(dtype=object, na_value=None) if dtype != object else ser.to_numpy()
            text = []
            for v in vals.tolist():
                if isinstance(v, str):
                    text.append(v)
                elif v is None or (isinstance(v, float) and v != v):
                    text.append(na_rep)
                else:
                    return None
            if any(any(ch in v for ch in _CSV_SPECIAL) for v in set(text)):
                return None
        else:
            return None
        specs.append("%s")
        args.append(text)
        float_arg.append(False)
        converts.append(True)
    row_fmt = ",".join(specs)
    if args:
        lines = [row_fmt % t for t in zip(*args)]
    else:  # every column all-NaN: the same row n times
        lines = [row_fmt % ()] * n
    for k in np.flatnonzero(nan_rows).tolist():
        # a NaN cell is na_rep (pandas), not fmt's "nan": this row cell by cell
        cells = iter([na_rep if (is_f and v != v) else (fmt % v if is_f else v)
                      for is_f, v in zip(float_arg, [a[k] for a in args])])
        lines[k] = ",".join(next(cells) if conv else na_rep for conv in converts)
    lines.insert(0, ",".join(df.columns))
    return os.linesep.join(lines) + os.linesep


# to_csv arguments under which preformatting the float columns changes nothing but the speed
_PLAIN_CSV_KEYS = {"index", "float_format", "na_rep", "header", "columns", "sep", "lineterminator", "encoding"}


def _plain_csv_call(kwargs: dict) -> bool:
    return (set(kwargs) <= _PLAIN_CSV_KEYS and kwargs.get("index") is False
            and kwargs.get("columns") is None)


def _format_float_columns(df, fmt: str, na_rep: str):
    """``df`` with its NumPy float columns replaced by their text under ``fmt`` (``na_rep`` for NaN), as
    pandas' ``float_format`` writes them (``fmt % value`` for every non-NaN cell, infinities included)."""
    import numpy as np
    import pandas as pd

    out = None
    for i, dtype in enumerate(df.dtypes):
        if not (isinstance(dtype, np.dtype) and dtype.kind == "f"):
            continue
        vals = df.iloc[:, i].to_numpy()
        text = np.array([fmt % v for v in vals.tolist()], dtype=object)
        nan = np.isnan(vals)
        if nan.any():
            text[nan] = na_rep
        if out is None:
            out = df.copy(deep=False)
        # an object Series: pandas would otherwise convert the texts to its string dtype and back
        out.isetitem(i, pd.Series(text, index=df.index, dtype=object, copy=False))
    return df if out is None else out


def save_figure(path: str | os.PathLike, fig, **kwargs) -> Path:
    """Save a matplotlib figure atomically."""
    kwargs.setdefault("dpi", 110)
    kwargs.setdefault("bbox_inches", "tight")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, **kwargs)
    return Path(path)


def to_plain(obj: Any, nonfinite: Any = None) -> Any:
    """``obj`` as plain Python for YAML / JSON: NumPy arrays and scalars, tuples and the typed
    results (:class:`uwbimu.typed.MappingResult`) become lists, floats, ints, bools and dicts
    (string keys).  A NaN or infinite float becomes ``nonfinite`` (default None; ``str`` gives
    ``"nan"`` / ``"inf"`` text)."""
    import numpy as np
    from collections.abc import Mapping

    if isinstance(obj, Mapping):
        return {str(k): to_plain(v, nonfinite) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_plain(v, nonfinite) for v in obj]
    if isinstance(obj, np.ndarray):
        return to_plain(obj.tolist(), nonfinite)
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, (np.floating, float)):
        f = float(obj)
        if math.isfinite(f):
            return f
        return str(f) if nonfinite is str else nonfinite
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def _json_default(o):
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if hasattr(o, "to_dict"):  # the typed results (uwbimu.typed.MappingResult)
        return o.to_dict()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# ---------------------------------------------------------------------------
# The output rule: one folder of outputs, written whole or not at all
# ---------------------------------------------------------------------------
#: Record of the files uwbimu verbs wrote into a folder (name -> sha256); only
#: files listed here, and unchanged since, may be replaced without ``force``.
MANIFEST = ".uwbimu-outputs.json"
#: File names that make a folder a dataset folder (its input files).
DATASET_FILES = tuple(f"{t}.{ext}" for t in ("imu", "uwb", "tdoa", "anchors", "anchor_ranges", "groundtruth")
                      for ext in ("csv", "parquet")) + ("dataset.yaml", "dataset.yml")


def _sha256(path: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_manifest(folder: Path) -> dict[str, str]:
    """Files (name -> sha256) that uwbimu wrote into ``folder`` (empty when none or unreadable)."""
    try:
        data = json.loads((Path(folder) / MANIFEST).read_text())
        return {str(k): str(v) for k, v in data.get("files", {}).items()}
    except (OSError, ValueError, AttributeError):
        return {}


def is_dataset_folder(folder: Path) -> bool:
    """True when ``folder`` holds dataset input files (imu.csv, uwb.csv, dataset.yaml, ...)."""
    return folder.is_dir() and any((folder / n).exists() for n in DATASET_FILES)


def _input_files(folder: Path) -> set[str]:
    """Dataset input files in ``folder`` (imu.csv, anchors.csv, ...): never overwritten, whoever wrote them.

    A folder is a dataset when it holds a stream (imu, uwb, tdoa) or a dataset.yaml -- also one that
    ``simulate`` or ``import`` wrote; a lone anchors.csv (``place`` writes one) is an ordinary output.
    """
    folder = Path(folder)
    if not folder.is_dir():
        return set()
    present = {n for n in DATASET_FILES if (folder / n).is_file()}
    core = {n for n in present if n.split(".")[0] in ("imu", "uwb", "tdoa", "dataset")}
    return present if core else set()


def _inside(a: Path, b: Path) -> bool:
    """``a`` is ``b`` or lies below it (both resolved)."""
    return a == b or b in a.parents


def _output_error(message: str, hint: str | None = None):
    from uwbimu.errors import OutputError

    return OutputError(message, hint=hint)


def check_output_target(out: Path, names=(), force: bool = False, protect=(), replace: bool = False) -> None:
    """Refuse an output folder before any work (see :func:`output_folder`); raises OutputError."""
    out = Path(out)
    res = out.resolve()
    if out.exists() and not out.is_dir():
        raise _output_error(f"{out} is a file, not a folder", hint="give a folder for the outputs")
    for p in protect:
        if p is None:
            continue
        pr = Path(p).resolve()
        if pr.is_file():  # an input file: never the output itself, never inside a replaced folder
            if res == pr or (replace and _inside(pr, res)):
                raise _output_error(f"{out} would overwrite the input {p}", hint="choose another output")
            continue
        pr_dir = pr
        if _inside(res, pr_dir) and not force:
            raise _output_error(f"{out} is inside the input dataset folder {p}; outputs are never written into "
                                f"a dataset folder", hint="choose another output folder (or --force)")
        if replace and _inside(pr_dir, res):
            raise _output_error(f"replacing {out} would delete the input {p}", hint="choose another output folder")
    if out.is_dir():
        inputs = _input_files(out)
        clash = sorted(inputs & {str(n) for n in names}) if not replace else []
        if clash:  # never, --force or not: no --force hint
            raise _output_error(f"{out / clash[0]} is an input file of a dataset; it is never overwritten",
                                hint="choose another output folder")
        if inputs and not force and not replace:
            raise _output_error(f"{out} holds a dataset ({', '.join(sorted(inputs))}); outputs are not written into a "
                                f"dataset folder", hint="choose another output folder (or --force)")
        if replace:
            others = foreign_files(out)
            if others and not force:
                raise _output_error(f"refusing to replace {out}: it holds files uwbimu did not write or that "
                                    f"changed since ({', '.join(others[:5])})", hint="use --force or another folder")
        else:
            _refuse_foreign(out, names, force)
        if not os.access(out, os.W_OK | os.X_OK):
            raise _output_error(f"{out} is not writable", hint="choose a writable output folder")
    else:
        parent = next((q for q in res.parents if q.exists()), None)
        if parent is None or not parent.is_dir() or not os.access(parent, os.W_OK | os.X_OK):
            raise _output_error(f"cannot create {out}: {parent} is not a writable folder",
                                hint="choose a writable output folder")


def foreign_files(out: Path) -> list[str]:
    """Files below ``out`` (sorted, relative) that its manifest does not list with their current content.

    Empty when the folder holds only outputs uwbimu wrote there, unchanged: such a folder may be
    replaced whole without ``force`` (the rule of :func:`output_folder`).
    """
    out = Path(out)
    manifest = read_manifest(out)
    bad = []
    for q in sorted(out.rglob("*")):
        if not q.is_file() or q.name == MANIFEST or q.name.startswith(".uwbimu-tmp") or ".uwbimu-tmp-" in str(q):
            continue
        rel = str(q.relative_to(out))
        if manifest.get(rel) != _sha256(q):
            bad.append(rel)
    return bad


def _refuse_foreign(out: Path, names, force: bool) -> None:
    """Refuse to replace files in ``out`` that uwbimu did not write (or that changed since)."""
    manifest = read_manifest(out)
    inputs = _input_files(out)
    for name in names:
        target = out / name
        if not target.exists():
            continue
        if target.is_dir():
            raise _output_error(f"{target} is a folder; an output file of that name cannot be written")
        if name in inputs:
            raise _output_error(f"{target} is an input file of a dataset; it is never overwritten",
                                hint="choose another output folder")
        if not force and manifest.get(name) != _sha256(target):
            why = "was changed since uwbimu wrote it" if name in manifest else "was not written by uwbimu"
            raise _output_error(f"{target} exists and {why}; refusing to overwrite it",
                                hint="use --force to replace it, or another output folder")


def record_outputs(out: str | os.PathLike, paths) -> None:
    """Record files a verb wrote straight into ``out`` (not through :func:`output_folder`) in its manifest.

    For verbs whose writers take a folder (``plan``, ``place``): they call
    :func:`check_output_target` first and this after writing, so a rerun may replace its own
    unchanged outputs and nothing else without ``force`` -- the rule of :func:`output_folder`.

    Parameters
    ----------
    out : the output folder.
    paths : the files written (absolute, or relative to ``out``); folders are walked.
    """
    out = Path(out)
    manifest = read_manifest(out)
    for p in paths:
        p = Path(p) if Path(p).is_absolute() else out / p
        files = [q for q in p.rglob("*") if q.is_file()] if p.is_dir() else [p] if p.is_file() else []
        for q in files:
            try:
                rel = q.resolve().relative_to(out.resolve())
            except ValueError:
                continue  # not inside out
            manifest[str(rel)] = _sha256(q)
    write_json(out / MANIFEST, {"files": manifest})


def existing_files(out: str | os.PathLike, names) -> list[str]:
    """``names`` relative to ``out``, with every file below a named folder that exists (for the checks)."""
    out = Path(out)
    found = []
    for n in names:
        p = out / n
        if p.is_dir():
            found += [str(q.relative_to(out)) for q in p.rglob("*") if q.is_file()]
        else:
            found.append(str(n))
    return found


def nonfinite_values(path: Path) -> str | None:
    """Describe the first NaN/inf in an output table or document (None when all values are finite)."""
    import math

    suffix = path.suffix.lower()
    if suffix == ".csv":
        import numpy as np
        import pandas as pd

        try:
            df = pd.read_csv(path)
        except (ValueError, OSError):
            return None
        for col in df.columns:
            if pd.api.types.is_numeric_dtype(df[col]):
                v = df[col].to_numpy(float)
                # A column that is NaN throughout is a quantity not estimated (documented, e.g. the
                # attitude sd of a point-mass filter); inf anywhere, or NaN among numbers, is not.
                bad = np.isinf(v) if np.isnan(v).all() else ~np.isfinite(v)
                if bad.any():
                    return f"{path.name}, line {int(np.argmax(bad)) + 2}, column '{col}': {v[np.argmax(bad)]}"
        return None
    if suffix in (".yaml", ".yml", ".json"):
        try:
            obj = yaml.safe_load(path.read_text()) if suffix != ".json" else json.loads(path.read_text())
        except (ValueError, yaml.YAMLError, OSError):
            return None
        stack = [("", obj)]
        while stack:
            key, o = stack.pop()
            if isinstance(o, float) and not math.isfinite(o):
                return f"{path.name}, key '{key.lstrip('.')}': {o}"
            if isinstance(o, dict):
                stack.extend((f"{key}.{k}", v) for k, v in o.items())
            elif isinstance(o, list):
                stack.extend((f"{key}[{i}]", v) for i, v in enumerate(o))
    return None


@contextmanager
def output_folder(out: str | os.PathLike, force: bool = False, protect=(), names=(), replace: bool = False,
                  finite: bool | tuple = True) -> Iterator[Path]:
    """Write a set of outputs into ``out`` whole or not at all (the toolkit's output rule).

    Checks the target before any work, yields an empty temporary folder for the
    outputs and, when the block ends without an exception, moves them into ``out``.
    An exception leaves ``out`` as it was.

    Parameters
    ----------
    out : the output folder (created if missing).
    force : allow writing into a dataset folder or over files uwbimu did not write
        (never over a dataset's input files, never over a protected input).
    protect : input paths (dataset folders, files); ``out`` may not lie inside one unless
        ``force``, and a ``replace`` may never delete one.
    names : output file names known in advance, checked before any work.
    replace : the outputs replace the folder as a whole (a dataset written by
        ``simulate`` / ``import``); an existing non-empty ``out`` needs ``force``.
    finite : refuse (:class:`uwbimu.errors.EstimationError`) outputs holding NaN or inf;
        a tuple names files exempt from the check (documented NaN columns).

    Raises
    ------
    uwbimu.errors.OutputError : the target is refused or not writable (nothing written).
    uwbimu.errors.EstimationError : an output holds NaN / inf (nothing written).
    """
    import shutil

    out = Path(out)
    check_output_target(out, names, force, protect, replace)
    exists = out.is_dir()
    parent = out if exists and not replace else out.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.uwbimu-tmp-", dir=parent))
    except OSError as exc:
        raise _output_error(f"cannot write into {parent}: {exc.strerror or exc}",
                            hint="choose a writable output folder") from None
    try:
        yield tmp
        files = sorted(p.relative_to(tmp) for p in tmp.rglob("*") if p.is_file())
        exempt = finite if isinstance(finite, tuple) else ()
        if finite is not False:
            for rel in files:
                if rel.name in exempt:
                    continue
                bad = nonfinite_values(tmp / rel)
                if bad is not None:
                    from uwbimu.errors import EstimationError

                    raise EstimationError(f"an output holds a non-finite value ({bad}); nothing was written",
                                          hint="the estimate diverged: check the dataset with `uwbimu check`")
        umask = os.umask(0)
        os.umask(umask)
        for rel in files:
            os.chmod(tmp / rel, 0o666 & ~umask)
        if replace or not exists:
            manifest = {str(rel): _sha256(tmp / rel) for rel in files}
            (tmp / MANIFEST).write_text(json.dumps({"files": manifest}, indent=1) + "\n")
            os.chmod(tmp, 0o777 & ~umask)
            if exists:
                backup = Path(tempfile.mkdtemp(prefix=f".{out.name}.uwbimu-old-", dir=out.parent))
                backup.rmdir()
                out.rename(backup)
                tmp.rename(out)
                shutil.rmtree(backup, ignore_errors=True)
            else:
                tmp.rename(out)
            return
        _refuse_foreign(out, [str(rel) for rel in files], force)
        manifest = read_manifest(out)
        for rel in files:
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            manifest[str(rel)] = _sha256(tmp / rel)
            os.replace(tmp / rel, out / rel)
        write_json(out / MANIFEST, {"files": manifest})
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
