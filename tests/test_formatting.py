"""The one rounding rule for printed figures and the natural anchor order (issue 30 item 2)."""

from __future__ import annotations

import math

import pytest

from uwbimu.formatting import finite_or_none, format_number, format_value_sigma, natural_key, sigma_decimals


@pytest.mark.parametrize("value, sigma, unit, expected", [
    (0.02994, 0.00123, "s", "0.0299 ± 0.0012 s"),
    (-16.04, 3.0, "cm", "-16.0 ± 3.0 cm"),
    (29.94, 6.66, "ms", "29.9 ± 6.7 ms"),
    (123.4, 9.96, "", "123 ± 10"),           # σ rounds up to the next power of ten: still 2 digits
    (12345.0, 1234.0, "", "12300 ± 1200"),
    (-0.0001, 0.01, "m", "0.000 ± 0.010 m"),   # no negative zero
])
def test_value_sigma_kalibr_style(value, sigma, unit, expected):
    assert format_value_sigma(value, sigma, unit) == expected


@pytest.mark.parametrize("sigma", [None, math.nan, math.inf, -1.0, 0.0])
def test_sigma_not_estimated(sigma):
    assert format_value_sigma(1.5, sigma, "m") == "1.50 m (σ not estimated)"


def test_value_missing():
    assert format_value_sigma(None, 0.1, "m") == "n/a"
    assert format_number(math.nan) == "n/a"


def test_sigma_decimals():
    assert sigma_decimals(0.0123) == 3
    assert sigma_decimals(9.96) == 0
    assert sigma_decimals(150.0) == -1
    with pytest.raises(ValueError):
        sigma_decimals(0.0)


@pytest.mark.parametrize("x, unit, expected", [
    (1200.0, "", "1200"), (0.06884, "m", "0.0688 m"), (44.19, "", "44.2"), (12345.6, "", "12346"),
    (3, "", "3"), (True, "", "True"), (0.0, "m", "0 m"), (9.996, "s", "10.0 s"),
])
def test_format_number(x, unit, expected):
    assert format_number(x, unit) == expected


def test_finite_or_none():
    assert finite_or_none("1.5") == 1.5
    assert finite_or_none(math.nan) is None and finite_or_none("x") is None and finite_or_none(None) is None


def test_natural_key():
    assert sorted(["1", "3", "10", "2", "8"], key=natural_key) == ["1", "2", "3", "8", "10"]
    assert sorted(["A10", "a2", "A1"], key=natural_key) == ["A1", "a2", "A10"]
    assert sorted([3, "10", 1.0, "2"], key=natural_key) == [1.0, "2", 3, "10"]
    assert sorted(["3-10", "10-3", "3-2"], key=natural_key) == ["3-2", "3-10", "10-3"]
