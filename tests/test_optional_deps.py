"""Optional dependencies: a missing extra is a clear usage error naming the extra."""

from __future__ import annotations

import builtins

import pandas as pd
import pytest

from uwbimu.errors import UsageError
from uwbimu.optional import require


def test_require_returns_the_module():
    assert require("numpy", "none", "test").__name__ == "numpy"


def test_missing_module_names_the_extra():
    with pytest.raises(UsageError) as e:
        require("surely_not_installed_pkg", "dask", "a Dask study")
    assert e.value.hint == 'pip install "uwbimu[dask]"'
    assert e.value.exit_code == 2


def test_parquet_without_pyarrow_is_refused(tmp_path, monkeypatch):
    from uwbimu.io.dataset import _write_table

    real_import = builtins.__import__

    def no_pyarrow(name, *a, **k):
        if name == "pyarrow" or name.startswith("pyarrow."):
            raise ImportError(name)
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_pyarrow)
    monkeypatch.delitem(__import__("sys").modules, "pyarrow", raising=False)
    with pytest.raises(UsageError):
        _write_table(pd.DataFrame({"t": [0.0]}), tmp_path / "imu.parquet")
    assert not (tmp_path / "imu.parquet").exists()
