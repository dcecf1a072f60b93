"""Error classes of the toolkit, each with the exit code the command line returns for it.

Every refusal the library raises derives from :class:`UwbimuError`; the
command-line wrapper (:func:`uwbimu.cli.main.main`) turns one into a single
line on stderr (plus a hint when the error carries one) and exits with its
``exit_code``:

====  =====================  ==============================================
code  class                  meaning
====  =====================  ==============================================
0     -                      success
1     :class:`InputError`    refused input (dataset or data file content)
2     :class:`UsageError`    bad command-line usage (option values, paths);
                             :class:`ConfigError`: a configuration file that cannot be used
3     :class:`CheckFlagged`  ``uwbimu check --strict`` flagged the dataset
4     :class:`OutputError`   output refused or not writable (nothing written)
5     :class:`EstimationError`  the estimator failed or produced non-finite values
====  =====================  ==============================================
"""

from __future__ import annotations

from typing import Optional

__all__ = [
    "UwbimuError",
    "InputError",
    "StreamInputError",
    "ConfigError",
    "UsageError",
    "CheckFlagged",
    "OutputError",
    "EstimationError",
    "EXIT_CODES",
    "column_list",
]


class UwbimuError(Exception):
    """Base of every error the toolkit raises on purpose.

    Attributes
    ----------
    exit_code : int
        Exit status of the command line for this error (class attribute).
    hint : str or None
        One-line suggestion of a repair that exists (printed after the message).
    """

    exit_code: int = 1

    def __init__(self, message: str = "", *args, hint: Optional[str] = None):
        super().__init__(message, *args)
        self.hint = hint


class InputError(UwbimuError, ValueError):
    """Input refused: a dataset, configuration or file whose content cannot be used (exit 1)."""

    exit_code = 1


class StreamInputError(InputError):
    """A push to the streaming filter (:class:`uwbimu.estimation.Eskf`) refused: wrong shape, not numeric,
    a bad noise sd (exit 1).  ``field`` names the argument, ``reason`` the check that failed."""

    def __init__(self, message: str = "", *args, field: Optional[str] = None, reason: Optional[str] = None,
                 hint: Optional[str] = None):
        super().__init__(message, *args, hint=hint)
        self.field = field
        self.reason = reason


class ConfigError(InputError):
    """A configuration file or mapping that cannot be used; the message names file, line and field (exit 2).

    Raised by :func:`uwbimu.io.yamlconfig.load_yaml_model`, the one YAML configuration loader.  A
    configuration is part of how the command was called, so the command line exits with the usage
    code 2, as for a bad option value.
    """

    exit_code = 2


class UsageError(UwbimuError, ValueError):
    """Command-line usage error: a bad option value or an impossible combination (exit 2)."""

    exit_code = 2


class CheckFlagged(UwbimuError):
    """``uwbimu check --strict`` found a flagged anchor or dataset (exit 3)."""

    exit_code = 3


class OutputError(UwbimuError, OSError):
    """An output that must not or cannot be written; nothing was written (exit 4)."""

    exit_code = 4


class EstimationError(UwbimuError, RuntimeError):
    """The estimator failed, or its result holds NaN or infinite values (exit 5)."""

    exit_code = 5


def column_list(names) -> str:
    """Names for a message, without Python list syntax: ``"column innovation"`` or
    ``"columns qw, qx"`` (no brackets or quotes, whatever the container)."""
    names = [str(n) for n in names]
    return ("column " if len(names) == 1 else "columns ") + ", ".join(names)


#: Exit code -> meaning, for documentation and ``--help`` texts.
EXIT_CODES = {
    0: "success",
    1: "refused input (dataset or data file content)",
    2: "usage error (bad option value, path or configuration file)",
    3: "check flagged the dataset (--strict)",
    4: "output refused or not writable (nothing written)",
    5: "estimation failed or produced non-finite values",
}
