"""TDoA in the user interface (issue 28 item 5): ``check`` diagnoses tdoa.csv, the estimate summary
counts TDoA rows and prints TDoA (not range) residual tables, and no sigma prints as "nan".

One 8 s simulated TDoA2 flight (8 anchors, consecutive pairs, 400 Hz) serves every test.
"""

from __future__ import annotations

import numpy as np
import pytest
from rich.console import Console
from typer.testing import CliRunner

from uwbimu.cli.main import app
from uwbimu.errors import CheckFlagged
from uwbimu.io.check import CheckOptions, check_dataset
from uwbimu.io.check_tdoa import tdoa_pairs
from uwbimu.io.dataset import write_dataset
from uwbimu.sim import builtin_scenario, simulate_full

runner = CliRunner()


def _clipped_table_lines(text: str) -> list[str]:
    from test_cli_conventions import _clipped_table_lines as clipped

    return clipped(text)


@pytest.fixture(scope="module")
def tdoa_ds():
    sc = builtin_scenario("crazyflie-tdoa2").updated(duration=8.0, imu={"rate_hz": 200.0})
    ds = simulate_full(sc).dataset
    assert len(ds.uwb) == 0 and ds.tdoa is not None and len(ds.tdoa) > 1000
    return ds


@pytest.fixture(scope="module")
def tdoa_folder(tdoa_ds, tmp_path_factory):
    path = tmp_path_factory.mktemp("tdoa") / "ds"
    write_dataset(tdoa_ds, path)
    return path


def _copy(ds):
    import copy

    out = copy.copy(ds)
    out.tdoa = ds.tdoa.copy()
    return out


# ---------------------------------------------------------------------------
# check: streams, pairs, residuals, flags
# ---------------------------------------------------------------------------
def test_check_reports_the_tdoa_stream_and_per_pair_rates(tdoa_ds):
    r = check_dataset(tdoa_ds)
    td = tdoa_ds.tdoa
    row = r.streams.loc["tdoa"]
    assert row["samples"] == len(td)
    assert row["t_start"] == pytest.approx(td["t"].min()) and row["t_end"] == pytest.approx(td["t"].max())
    assert row["rate_hz"] == pytest.approx((len(td) - 1) / (td["t"].max() - td["t"].min()))
    assert "uwb" not in r.streams.index  # no empty range stream on a TDoA-only log
    # TDoA2: consecutive slots 0-1, 1-2, ..., 6-7 and the wrap 7-0 (folded into 0-7)
    assert set(r.tdoa_pairs.index) == {"0-1", "1-2", "2-3", "3-4", "4-5", "5-6", "6-7", "0-7"}
    assert r.tdoa_pairs["samples"].sum() == len(td)
    span = td["t"].max() - td["t"].min()
    np.testing.assert_allclose(r.tdoa_pairs["rate_hz"], r.tdoa_pairs["samples"] / span)
    # every anchor takes part in TDoA: none is "without any range"
    assert (r.anchors["tdoa"] > 0).all() and (r.anchors["ranges"] == 0).all()
    assert not any("without any range" in n for n in r.notes)


def test_tdoa_residuals_match_the_simulated_noise_and_flag_nothing(tdoa_ds):
    r = check_dataset(tdoa_ds)
    sigma = float(tdoa_ds.meta.extra["tdoa_sigma"])
    assert r.n_tdoa_compared + r.n_tdoa_outside_truth == len(tdoa_ds.tdoa)
    assert r.n_tdoa_compared > 0.95 * len(tdoa_ds.tdoa)
    tab = r.tdoa_table
    # measured - predicted from the true pose + the documented lever arm: unbiased, sd = the sim's sigma
    assert np.all(np.abs(tab["median"]) < 4 * sigma / np.sqrt(tab["n"]) * 1.26 + 0.01)
    np.testing.assert_allclose(tab["robust_sigma"], sigma, rtol=0.2)
    assert (tab["outlier_frac"] == 0).all()
    assert r.flags == []


def test_a_biased_anchor_flags_its_pairs_and_itself(tdoa_ds):
    ds = _copy(tdoa_ds)
    # a +0.6 m range offset on anchor 3 (antenna delay): +0.6 where it is b, -0.6 where it is a
    td = ds.tdoa
    td.loc[td["anchor_b"] == "3", "tdoa"] += 0.6
    td.loc[td["anchor_a"] == "3", "tdoa"] -= 0.6
    r = check_dataset(ds, CheckOptions(bias_threshold=0.3))
    by_kind = {}
    for f in r.flags:
        by_kind.setdefault(f.kind, set()).add(f.anchor)
    assert by_kind.get("tdoa_bias") == {"2-3", "3-4"}
    assert by_kind.get("tdoa_anchor_offset") == {"3"}
    assert r.tdoa_offsets["3"] == pytest.approx(0.6 * 7 / 8, abs=0.05)  # mean-zero gauge over 8 anchors
    assert r.tdoa_table.loc["2-3", "median"] == pytest.approx(0.6, abs=0.05)
    assert r.tdoa_table.loc["3-4", "median"] == pytest.approx(-0.6, abs=0.05)


def test_reversed_rows_fold_into_one_pair_with_the_sign_flipped(tdoa_ds):
    ds = _copy(tdoa_ds)
    td = ds.tdoa
    flip = (td["anchor_a"] == "4") & (td["anchor_b"] == "5")
    td.loc[flip, ["anchor_a", "anchor_b"]] = td.loc[flip, ["anchor_b", "anchor_a"]].to_numpy()
    td.loc[flip, "tdoa"] *= -1.0
    ref, r = check_dataset(tdoa_ds), check_dataset(ds)
    assert list(r.tdoa_table.index) == list(ref.tdoa_table.index)
    np.testing.assert_allclose(r.tdoa_table["median"], ref.tdoa_table["median"], atol=1e-12)
    first, second, sign = tdoa_pairs(td[flip])
    assert set(first) == {"4"} and set(second) == {"5"} and (sign == -1).all()


def test_outliers_on_one_pair_are_flagged(tdoa_ds):
    ds = _copy(tdoa_ds)
    td = ds.tdoa
    rows = np.flatnonzero(((td["anchor_a"] == "5") & (td["anchor_b"] == "6")).to_numpy())
    td.iloc[rows[::4], td.columns.get_loc("tdoa")] += 2.5  # 25 % gross errors (NLOS)
    r = check_dataset(ds)
    assert [(f.kind, f.anchor) for f in r.flags] == [("tdoa_outliers", "5-6")]
    assert r.flags[0].details["outlier_frac"] == pytest.approx(0.25, abs=0.01)


def test_cli_check_prints_tdoa_tables_and_strict_exits_3(tdoa_ds, tdoa_folder, tmp_path):
    res = runner.invoke(app, ["check", str(tdoa_folder), "--csv", str(tmp_path / "res.csv")],
                        env={"COLUMNS": "80"})
    assert res.exit_code == 0, res.output
    assert "TDoA pairs" in res.output and "anchors without any range" not in res.output
    assert "no anchor or TDoA pair flagged" in res.output
    # the tables fit 80 columns without cutting numbers (the conventions' rule)
    assert max(len(ln) for ln in res.stdout.splitlines()) <= 80
    assert not _clipped_table_lines(res.stdout)
    lines = [ln for ln in res.output.splitlines() if ln.strip().strip("│").strip().startswith("tdoa")]
    assert lines and str(len(tdoa_ds.tdoa)) in lines[0]  # the stream row with its row count
    written = (tmp_path / "res_tdoa.csv").read_text().splitlines()
    assert written[0].startswith("pair,anchor_a,anchor_b,n,median") and len(written) == 1 + 8
    # a biased anchor: --strict exits with CheckFlagged's code
    ds = _copy(tdoa_ds)
    ds.tdoa.loc[ds.tdoa["anchor_b"] == "3", "tdoa"] += 0.6
    ds.tdoa.loc[ds.tdoa["anchor_a"] == "3", "tdoa"] -= 0.6
    bad = tmp_path / "bad"
    write_dataset(ds, bad)
    res = runner.invoke(app, ["check", str(bad), "--strict"], env={"COLUMNS": "80"})
    assert res.exit_code == CheckFlagged.exit_code, res.output


# ---------------------------------------------------------------------------
# estimate summary: counts, residual tables, no NaN sigma
# ---------------------------------------------------------------------------
def test_estimate_summary_counts_tdoa_and_prints_no_range_table(tdoa_ds, tdoa_folder, tmp_path):
    res = runner.invoke(app, ["estimate", str(tdoa_folder), "-o", str(tmp_path / "est"), "--no-plots",
                              "--no-clock-faults"], env={"COLUMNS": "100"})
    assert res.exit_code == 0, res.output
    out = res.output
    assert f"{len(tdoa_ds.imu)} IMU samples, 0 ranges, {len(tdoa_ds.tdoa)} TDoA" in out
    assert "Range residuals per anchor" not in out
    assert "TDoA residuals per anchor pair" in out
    assert "nan" not in out.lower()
    # the TDoA table has one row per unordered pair, counting every TDoA row of residuals.csv
    import pandas as pd

    resid = pd.read_csv(tmp_path / "est" / "residuals.csv", dtype={"anchor": str, "anchor_b": str})
    assert (resid["kind"] == "tdoa").all() and len(resid) == len(tdoa_ds.tdoa)
    for pair in ("0-1", "6-7", "0-7"):
        a, b = pair.split("-")
        n = int((((resid["anchor"] == a) & (resid["anchor_b"] == b))
                 | ((resid["anchor"] == b) & (resid["anchor_b"] == a))).sum())
        assert any(ln.split("│")[1:3] and ln.split("│")[1].strip() == pair and ln.split("│")[2].strip() == str(n)
                   for ln in out.splitlines()), pair


def _render(renderable) -> str:
    con = Console(record=True, width=120)
    con.print(renderable)
    return con.export_text()


def test_no_nan_sigma_in_the_estimate_calibration_table(tdoa_ds):
    from types import SimpleNamespace

    from uwbimu.cli.estimate import calibration_table

    cal = {"lever_arm": [0.1, 0.0, 0.05], "lever_arm_sd": [0.01, float("nan"), 0.02],
           "time_offset": 0.35552, "time_offset_sd": float("nan"),
           "accel_bias": [0.0, 0.0, 0.0], "accel_bias_sd": [0.01, float("nan"), 0.01],
           "gyro_bias": [0.0, 0.0, 0.0], "gyro_bias_sd": [1e-3, 1e-3, float("inf")],
           "anchor_bias": {"3": 0.1}, "anchor_bias_sd": {"3": float("nan")}}
    text = _render(calibration_table(SimpleNamespace(calibration=cal), tdoa_ds))
    assert "nan" not in text.lower() and "inf" not in text.lower()
    assert "355.52 (σ not estimated)" in text
    assert text.count("not estimated") == 5


def test_no_nan_sigma_in_the_calibrate_summary():
    from uwbimu.cli.calibrate import calibration_summary

    cal = {"lever_arm": [0.1, 0.0, 0.05], "lever_arm_sd": [0.01, float("nan"), 0.02],
           "time_offset": {"value": 0.35552, "sd": float("nan"), "sd_curvature": None, "held_at_prior": False,
                           "verdict": "weakly identified"},
           "anchor_bias": {"3": 0.1}, "anchor_bias_sd": {"3": float("nan")}}
    text = _render(calibration_summary(cal))
    assert "nan" not in text.lower()
    assert "355.5 (σ not estimated)" in text and text.count("not estimated") == 3


def test_value_sd():
    from uwbimu.cli.conventions import value_sd

    assert value_sd(0.01234, 0.0021, 1000) == "12.34 ± 2.10"
    assert value_sd(0.01234, None, 1000) == value_sd(0.01234, float("nan"), 1000) == "12.34 (σ not estimated)"


def test_residual_tables_follow_the_kinds_of_the_run():
    """Ranges only: the range table; TDoA only: the pair table; both: both (counts per kind)."""
    from types import SimpleNamespace

    import pandas as pd

    from uwbimu.cli.estimate import print_residual_tables

    rng = pd.DataFrame({"t": [0.0, 0.1, 0.2], "anchor": ["0", "1", "0"], "innovation": [0.01, -0.02, 0.03],
                        "accepted": [True, True, False], "kind": "range", "anchor_b": ""})
    tdoa = pd.DataFrame({"t": [0.0, 0.1, 0.2], "anchor": ["0", "1", "2"], "innovation": [0.05, -0.04, 0.02],
                         "accepted": [True, True, True], "kind": "tdoa", "anchor_b": ["1", "0", "3"]})

    def text(res):
        con = Console(record=True, width=120)
        print_residual_tables(con, SimpleNamespace(residuals=res))
        return con.export_text()

    only_ranges = text(rng.drop(columns=["kind", "anchor_b"]))
    assert "Range residuals per anchor" in only_ranges and "TDoA" not in only_ranges
    only_tdoa = text(tdoa)
    assert "Range residuals" not in only_tdoa and "TDoA residuals per anchor pair" in only_tdoa
    rows = {ln.split("│")[1].strip(): ln.split("│")[2].strip() for ln in only_tdoa.splitlines() if ln.count("│") > 3}
    assert rows == {"0-1": "2", "2-3": "1"}  # (1, 0) folded into 0-1
    both = text(pd.concat([rng, tdoa], ignore_index=True))
    assert "Range residuals per anchor" in both and "TDoA residuals per anchor pair" in both
