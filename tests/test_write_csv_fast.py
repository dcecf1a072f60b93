"""``atomic.write_csv`` formats float columns itself (speed); the file must be byte-identical to pandas'."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from uwbimu.io import atomic


def _pandas_bytes(df, tmp_path, **kw):
    p = tmp_path / "ref.csv"
    kw.setdefault("index", False)
    df.to_csv(p, **kw)
    return p.read_bytes()


FRAMES = {
    "mixed": lambda: pd.DataFrame({
        "t": np.linspace(0, 1, 7),
        "x": [1e-300, -0.0, np.nan, np.inf, -np.inf, 123456789.123456, 1 / 3],
        "n": np.arange(7),
        "ok": [True, False] * 3 + [True],
        "anchor": ["A1", "B,2", 'q"uote', "", "x", "y", "z"],
        "f32": np.arange(7, dtype=np.float32) / 3,
    }),
    "plain_text": lambda: pd.DataFrame({
        "t": [0.1, np.nan, 2.0, -0.0],
        "anchor": pd.Series(["A1", None, "", " sp "], dtype=object),
        "kind": pd.Series(["range", "tdoa", np.nan, "range"], dtype="str"),
        "ok": np.array([True, False, True, False]),
        "u": np.array([0, 1, 2, 2 ** 40], dtype=np.uint64),
        "i": np.array([-1, 0, 1, 2], dtype=np.int32),
    }),
    "object_numbers": lambda: pd.DataFrame({"a": pd.Series([1, "x"], dtype=object), "b": [1.5, 2.5]}),
    "single_nan_column": lambda: pd.DataFrame({"v": [np.nan, 1.0, np.nan]}),
    "duplicate_names": lambda: pd.DataFrame(np.random.default_rng(1).normal(size=(5, 3)), columns=["a", "a", "b"]),
    "empty": lambda: pd.DataFrame({"t": np.array([], float), "s": np.array([], object)}),
    "no_floats": lambda: pd.DataFrame({"i": [1, 2], "s": ["a", "b"]}),
    "random": lambda: pd.DataFrame(np.random.default_rng(0).standard_cauchy(size=(200, 4)) * 10.0 ** np.arange(-6, 6, 3)),
}


@pytest.mark.parametrize("name", sorted(FRAMES))
@pytest.mark.parametrize("fmt", ["%.9g", "%.6g", "%.3f"])
def test_byte_identical_to_pandas_float_format(tmp_path, name, fmt):
    df = FRAMES[name]()
    before = df.copy()
    out = atomic.write_csv(tmp_path / "fast.csv", df, float_format=fmt)
    assert out.read_bytes() == _pandas_bytes(df, tmp_path, float_format=fmt)
    pd.testing.assert_frame_equal(df, before)  # the caller's frame is not modified


def test_na_rep_and_other_arguments_fall_back_or_match(tmp_path):
    df = FRAMES["mixed"]()
    out = atomic.write_csv(tmp_path / "a.csv", df, float_format="%.9g", na_rep="NaN")
    assert out.read_bytes() == _pandas_bytes(df, tmp_path, float_format="%.9g", na_rep="NaN")
    # an argument the fast path does not handle goes to pandas unchanged
    out = atomic.write_csv(tmp_path / "b.csv", df, float_format="%.9g", quoting=2)
    assert out.read_bytes() == _pandas_bytes(df, tmp_path, float_format="%.9g", quoting=2)


@pytest.mark.parametrize("name,fast", [("plain_text", True), ("random", False), ("duplicate_names", True),
                                       ("mixed", False), ("object_numbers", False), ("single_nan_column", False)])
def test_which_frames_take_the_column_wise_writer(name, fast):
    # the byte-identity tests above cover both writers only if both are taken
    df = FRAMES[name]()
    if name == "random":
        df.columns = [f"c{i}" for i in range(df.shape[1])]
        fast = True
    assert (atomic._csv_text(df, "%.9g", "") is not None) is fast
