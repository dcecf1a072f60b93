"""Anchor files an importer accepts: ``anchors.csv`` and the UTIL survey files (``.npz``, ``_survey.txt``).

* ``anchors.csv`` in the dataset format (``anchor, x, y, z`` [+ ``qw, qx, qy, qz``]);
* a UTIL survey ``.npz`` with ``an_pos`` (N, 3) m and optionally ``an_quat`` (N, 4),
  the anchor antenna frame -> Vicon frame;
* its text form ``..._survey.txt`` (lines ``anI_p,x,y,z`` and ``anI_quat,q1,q2,q3,q4``).

The order of ``an_quat`` depends on the survey file's version (the UTIL authors'
``scripts/survey/anchor_survey.py``):

* the 2021 surveys, named by date (``anchor_0425.npz``; repository commit ``bc0ebe2``),
  were saved as ``[qw, qx, qy, qz]``;
* the released constellations (``anchor_constN.npz`` / ``anchor_constN_survey.txt``,
  IJRR 2024 release) are saved as ``[qx, qy, qz, qw]``.

:func:`survey_quat_order` picks the order from the file name; ``quat_order="wxyz"``
or ``"xyzw"`` overrides it.  A name of neither form is read as the released
``[qx, qy, qz, qw]``, and the import changes say that it was assumed.
The raw total-station survey (``anchor_0425.txt``: marker points, not anchor poses)
is refused with a pointer to the files that hold the anchor poses.
"""

from __future__ import annotations

from uwbimu.errors import UsageError
import os
import re
import zipfile
from pathlib import Path
from typing import Literal, Optional, Union

import numpy as np
import pandas as pd

from uwbimu.io.importers import check_complete, read_csv_source, source_text
from uwbimu.io.loader import DatasetError

__all__ = ["QuatOrder", "QUAT_ORDERS", "read_anchors", "read_anchors_csv", "read_survey", "survey_quat_order"]

QuatOrder = Literal["auto", "wxyz", "xyzw"]
QUAT_ORDERS = ("auto", "wxyz", "xyzw")

_DATED = re.compile(r"anchor_\d{4}(\D|$)")  # the 2021 surveys: anchor_MMDD
_RELEASED = re.compile(r"anchor_const\d+(\D|$)")  # the IJRR release: anchor_constN
_RAW_SURVEY = re.compile(r"(anchorAnt\d+|anchor\d+_\d+|uwbDatasetFrame\d+|landmark\d+)\s*,")


def survey_quat_order(path: Path, quat_order: QuatOrder = "auto") -> tuple[str, str]:
    """``("wxyz" | "xyzw", why)``: the ``an_quat`` order of a UTIL survey file."""
    if quat_order not in QUAT_ORDERS:
        raise UsageError(f"quat_order must be one of {', '.join(QUAT_ORDERS)}, got '{quat_order}'")
    if quat_order != "auto":
        return quat_order, "given (--survey-quat-order)"
    if _DATED.match(path.name):
        return "wxyz", "a 2021 survey named by date: saved as [qw, qx, qy, qz]"
    if _RELEASED.match(path.name):
        return "xyzw", "a released constellation survey (anchor_constN): saved as [qx, qy, qz, qw]"
    return "xyzw", ("ASSUMED [qx, qy, qz, qw] (the released format): the name is neither anchor_MMDD (2021, "
                    "[qw, qx, qy, qz]) nor anchor_constN; pass --survey-quat-order if that is wrong")


def read_anchors_csv(path: Union[str, os.PathLike]) -> pd.DataFrame:
    """An anchors file in the dataset format (``anchor, x, y, z`` [+ ``qw, qx, qy, qz``]), ids as text."""
    path = Path(path)
    df = read_csv_source(path, what="anchors file")
    missing = [c for c in ("anchor", "x", "y", "z") if c not in df.columns]
    if missing:
        raise DatasetError(f"{path.name}, line 1: missing column(s) {', '.join(missing)}; expected anchor, x, y, z "
                           f"[, qw, qx, qy, qz], the header has {', '.join(map(str, df.columns))}", file=path.name, row=1,
                           column=missing[0])
    df["anchor"] = df["anchor"].str.strip()
    for c in [c for c in ("x", "y", "z", "qw", "qx", "qy", "qz") if c in df.columns]:
        vals = pd.to_numeric(df[c], errors="coerce").to_numpy(float)
        bad = ~np.isfinite(vals)
        if bad.any():
            i = int(np.argmax(bad))
            raise DatasetError(f"{path.name}, line {i + 2}, column '{c}': not a finite number ('{df[c].iloc[i]}')",
                               file=path.name, row=i + 2, column=c)
        df[c] = vals
    return df


def _read_npz(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    try:
        with np.load(path, allow_pickle=False) as z:
            if "an_pos" not in z.files:
                raise DatasetError(f"{path.name}: no 'an_pos' array (holds {z.files})", file=path.name,
                                   column="an_pos")
            pos = np.asarray(z["an_pos"], float)
            quat = np.asarray(z["an_quat"], float) if "an_quat" in z.files else None
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:  # a cut or foreign file
        raise DatasetError(f"{path.name}: not a readable .npz survey ({exc})", file=path.name) from None
    return pos, quat


def _read_survey_txt(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    text = source_text(path, what="anchor survey")
    if _RAW_SURVEY.search(text):
        raise DatasetError(f"{path.name}: this is a raw total-station survey (marker points such as "
                           "'anchorAnt0', 'anchor0_1'), not anchor poses", file=path.name,
                           hint="pass the survey's .npz (an_pos, an_quat) or an anchors.csv; the UTIL authors' "
                                "anchor_survey.py converts the raw survey into the .npz")
    check_complete(text, path.name, ",", what="anchor survey", fields=False)  # anI_p and anI_quat differ
    pos_rows: dict[int, list[float]] = {}
    quat_rows: dict[int, list[float]] = {}
    for ln, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        parts = [p.strip() for p in line.split(",")]
        m = re.fullmatch(r"an(\d+)_(p|quat)", parts[0])
        want = 3 if m and m.group(2) == "p" else 4
        if m is None or len(parts) != want + 1:
            raise DatasetError(f"{path.name}, line {ln}: expected 'anI_p,x,y,z' or 'anI_quat,q1,q2,q3,q4', got "
                               f"{line!r}", file=path.name, row=ln)
        try:
            vals = [float(v) for v in parts[1:]]
        except ValueError:
            raise DatasetError(f"{path.name}, line {ln}: not a number in {line!r}", file=path.name,
                               row=ln) from None
        (pos_rows if m.group(2) == "p" else quat_rows)[int(m.group(1))] = vals
    if not pos_rows or sorted(pos_rows) != list(range(len(pos_rows))):
        raise DatasetError(f"{path.name}: anchor positions an0_p .. anN_p expected, got ids {', '.join(str(k) for k in sorted(pos_rows))}",
                           file=path.name)
    pos = np.array([pos_rows[i] for i in range(len(pos_rows))])
    quat = np.array([quat_rows[i] for i in range(len(pos_rows))]) if len(quat_rows) == len(pos_rows) else None
    return pos, quat


def read_survey(path: Union[str, os.PathLike], quat_order: QuatOrder = "auto",
                changes: Optional[list[str]] = None) -> pd.DataFrame:
    """UTIL anchor survey (``.npz`` with ``an_pos``/``an_quat``, or the ``_survey.txt``) -> anchors frame.

    Anchor ids are ``0..N-1`` as text; orientations become ``qw, qx, qy, qz``
    (normalised) in the order :func:`survey_quat_order` gives; the order used
    and why is appended to ``changes``.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: anchor survey not found", file=path.name)
    pos, quat = _read_npz(path) if path.suffix == ".npz" else _read_survey_txt(path)
    if pos.ndim != 2 or pos.shape[1] != 3 or not np.all(np.isfinite(pos)):
        raise DatasetError(f"{path.name}: an_pos must be a finite (N, 3) array, got shape {pos.shape}",
                           file=path.name, column="an_pos")
    df = pd.DataFrame({"anchor": [str(i) for i in range(len(pos))], "x": pos[:, 0], "y": pos[:, 1], "z": pos[:, 2]})
    if quat is not None:
        if quat.shape != (len(pos), 4) or not np.all(np.isfinite(quat)) or np.any(np.linalg.norm(quat, axis=1) == 0):
            raise DatasetError(f"{path.name}: an_quat must be a finite non-zero ({len(pos)}, 4) array, got shape "
                               f"{quat.shape}", file=path.name, column="an_quat")
        order, why = survey_quat_order(path, quat_order)
        quat = quat / np.linalg.norm(quat, axis=1, keepdims=True)
        wxyz = quat if order == "wxyz" else quat[:, [3, 0, 1, 2]]
        df["qw"], df["qx"], df["qy"], df["qz"] = wxyz.T
        if changes is not None:
            changes.append(f"{path.name}: anchor orientations read as {'[qw, qx, qy, qz]' if order == 'wxyz' else '[qx, qy, qz, qw]'} "
                           f"({why}), written as qw, qx, qy, qz (anchor frame -> world)")
    return df


def read_anchors(path: Union[str, os.PathLike], quat_order: QuatOrder = "auto",
                 changes: Optional[list[str]] = None) -> pd.DataFrame:
    """Anchors from ``anchors.csv``, a survey ``.npz`` or a ``_survey.txt`` (chosen by the suffix).

    Raises
    ------
    DatasetError : a missing or unreadable file, a raw survey or an unknown format.
    """
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: anchors file not found", file=path.name)
    if path.suffix.lower() == ".csv":
        df = read_anchors_csv(path)
        if changes is not None:
            changes.append(f"anchors from {path.name}: ids {', '.join(df['anchor'])}")
        return df
    if path.suffix.lower() in (".npz", ".txt"):
        df = read_survey(path, quat_order, changes)
        if changes is not None:
            changes.append(f"anchors from the survey {path.name}: ids 0..{len(df) - 1} (the survey's row order)")
        return df
    raise DatasetError(f"{path.name}: unknown anchors file type {path.suffix!r}", file=path.name,
                       hint="give anchors.csv (anchor, x, y, z [, qw, qx, qy, qz]), a survey .npz (an_pos, an_quat) "
                            "or a _survey.txt (anI_p / anI_quat lines)")
