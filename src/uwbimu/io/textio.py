"""Reading text files that must be UTF-8, with a refusal that names the file and the place.

Python's ``Path.read_text()`` decodes with the locale's encoding and raises a bare
:class:`UnicodeDecodeError` (exit 70 on the command line) on a byte that does not
decode.  Every text input of the toolkit (``dataset.yaml``, configuration files, importer
mappings) is read through :func:`read_text` instead, so such a file is refused as an
:class:`uwbimu.errors.InputError` (or the class the caller names) that says which file,
which byte offset and which line hold the first bad byte.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Union

from uwbimu.errors import InputError

__all__ = ["NotUtf8", "find_non_utf8", "decode_text", "read_text"]

ErrorFactory = Callable[[str], Exception]


@dataclass(frozen=True)
class NotUtf8:
    """Where the first byte that is not UTF-8 lies.

    Attributes
    ----------
    offset : 0-based byte offset in the file.
    line, column : 1-based line and column (in characters) of that byte.
    byte : the offending byte's value.
    """

    offset: int
    line: int
    column: int
    byte: int

    def describe(self) -> str:
        return f"byte 0x{self.byte:02x} at offset {self.offset} (line {self.line}, column {self.column})"


def find_non_utf8(data: bytes) -> Optional[NotUtf8]:
    """The first byte of ``data`` that is not valid UTF-8 (None when all of it decodes)."""
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        head = data[: exc.start]
        line_start = head.rfind(b"\n") + 1
        column = len(head[line_start:].decode("utf-8", errors="replace")) + 1
        return NotUtf8(offset=exc.start, line=head.count(b"\n") + 1, column=column, byte=data[exc.start])
    return None


def decode_text(data: bytes, source: str, *, what: str = "file", error: ErrorFactory = InputError) -> str:
    """``data`` decoded as UTF-8 (a leading byte-order mark dropped), else ``error`` naming ``source``.

    Parameters
    ----------
    data : the file's bytes.
    source : the file name used in the message.
    what : what the file holds, for the message ("dataset metadata", "calibration options", ...).
    error : exception class (or factory ``message -> exception``) raised on refusal.
    """
    bad = find_non_utf8(data)
    if bad is not None:
        raise error(f"{source}: the {what} is not UTF-8 text: {bad.describe()}; save it as UTF-8")
    text = data.decode("utf-8")
    return text[1:] if text.startswith("\ufeff") else text


def read_text(path: Union[str, os.PathLike], *, what: str = "file", error: ErrorFactory = InputError) -> str:
    """Read a UTF-8 text file; a missing, unreadable or non-UTF-8 file raises ``error`` naming it.

    Parameters
    ----------
    path : the file.
    what : what the file holds, for messages.
    error : exception class (or factory ``message -> exception``); default
        :class:`uwbimu.errors.InputError` (exit 1), pass :class:`uwbimu.errors.ConfigError`
        for configuration files (exit 2).

    Returns
    -------
    The text, with universal newlines as ``Path.read_text`` gives them.
    """
    path = Path(path)
    if not path.is_file():
        raise error(f"{path}: {what} file not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read the {what}: {exc.strerror or exc}") from None
    text = decode_text(data, str(path), what=what, error=error)
    # Path.read_text translates \r\n and \r to \n; keep that behaviour.
    return text.replace("\r\n", "\n").replace("\r", "\n")
