"""Forward-backward smoothing of the ESKF (uwbimu.estimation.smoother): the time reversal, the fusion, the
combined calibration, and what it buys on a simulated flight."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import yaml

from uwbimu.estimation import EskfOptions, run_eskf
from uwbimu.estimation.smoother import (combine, fuse_trajectory, reverse_dataset, reversal_time,
                                        unreverse)
from uwbimu.metrics.filter import compute_metrics
from uwbimu.models import state as S
from uwbimu.sim import builtin_scenario, simulate


@pytest.fixture(scope="module")
def flights():
    """Three noise seeds of 30 s of the calibration flight, each run smoothed (forward pass kept in extra)."""
    out = []
    for seed in (1, 2, 3):
        sc = builtin_scenario("calibration-flight").updated(duration=30.0,
                                                             seeds={"truth": 0, "noise": seed, "init": seed + 1})
        ds = simulate(sc)
        out.append((ds, run_eskf(ds, EskfOptions(smoother="forward_backward"))))
    return out


def test_reversal_is_an_involution_and_maps_the_clocks(flights):
    ds = flights[0][0]
    T = reversal_time(ds)
    r = reverse_dataset(ds)
    assert np.allclose(r.imu_t, T - ds.imu_t[::-1]) and np.all(np.diff(r.imu_t) > 0)
    assert np.allclose(r.imu[["wx", "wy", "wz"]].to_numpy(), -ds.imu[["wx", "wy", "wz"]].to_numpy()[::-1])
    assert np.allclose(r.imu[["ax", "ay", "az"]].to_numpy(), ds.imu[["ax", "ay", "az"]].to_numpy()[::-1])
    assert np.allclose(r.uwb["t"].to_numpy(), T - ds.uwb["t"].to_numpy()[::-1])
    assert r.meta.truth.time_offset == -ds.meta.truth.time_offset
    back = reverse_dataset(r, T)
    for a, b in ((back.imu, ds.imu), (back.uwb, ds.uwb), (back.groundtruth, ds.groundtruth)):
        assert np.allclose(a.select_dtypes("number").to_numpy(), b.select_dtypes("number").to_numpy())


def test_the_filter_on_the_reversed_log_recovers_the_motion_and_the_negated_time_offset(flights):
    """The reversal's sign rules are physics, not bookkeeping: a wrong one (gyro not negated, t_d kept)
    leaves no trajectory the reversed filter could track."""
    ds = flights[0][0]
    r = reverse_dataset(ds)
    b = run_eskf(r)
    m = compute_metrics(b, r)  # the reversed log's own truth (its velocities and t_d negated)
    assert m["position_rmse"] < 0.2
    assert abs(b.calibration["time_offset"] + ds.meta.truth.time_offset) < 3 * b.calibration["time_offset_sd"]
    # mapped back: the velocity is the forward flight's
    X, _, _ = unreverse(b.states[::-1], None, b.sd[::-1])
    t = reversal_time(ds) - np.asarray(b.t)[::-1]
    v_true = np.column_stack([np.interp(t, ds.groundtruth["t"], ds.groundtruth[c]) for c in ("vx", "vy", "vz")])
    assert np.sqrt(np.mean(np.sum((X[:, S.V] - v_true) ** 2, axis=1))) < 0.3
    assert abs(X[0, S.TD] - ds.meta.truth.time_offset) < 3 * b.calibration["time_offset_sd"]  # its final one


def test_fusion_is_the_information_combination_block_by_block():
    rng = np.random.default_rng(4)
    n, k = S.ERROR_DIM, 5
    x_true = S.make_state(p=[1.0, 2.0, 3.0])
    X = np.tile(x_true, (k, 1))
    A = rng.normal(size=(k, n, n))
    Cf = A @ np.swapaxes(A, 1, 2) * 0.01 + 1e-3 * np.eye(n)
    B = rng.normal(size=(k, n, n))
    Cb = B @ np.swapaxes(B, 1, 2) * 0.01 + 1e-3 * np.eye(n)
    Xb = X.copy()
    Xb[:, S.P] += 0.1
    Xb[:, S.V] -= 0.05
    t = np.arange(k, dtype=float)
    mask = np.ones(n)
    mask[S.EPIU] = 0.0  # a consider block: never corrected
    Xs, Cs, cover, agree = fuse_trajectory(t, X, Cf, t, Xb, Cb, mask)
    assert cover.all()
    for i in range(k):
        for name, sl, nom in (("position", S.EP, S.P), ("velocity", S.EV, S.V)):
            Pf, Pb = Cf[i][sl, sl], Cb[i][sl, sl]
            info = np.linalg.inv(Pf) + np.linalg.inv(Pb)
            want = np.linalg.solve(info, np.linalg.solve(Pf, X[i, nom]) + np.linalg.solve(Pb, Xb[i, nom]))
            assert np.allclose(Xs[i, nom], want, atol=1e-12)
            # the covariance: the information combination times the passes' agreement factor 1 + |1 - r|
            d = Xb[i, nom] - X[i, nom]
            assert agree[name]["factor"] == pytest.approx(1.0 + abs(1.0 - agree[name]["r"]))
            assert np.allclose(Cs[i][sl, sl], agree[name]["factor"] * np.linalg.inv(info), atol=1e-12)
        assert "lever_arm" not in agree  # blocks outside the trajectory are not fused
        assert np.allclose(Xs[i, S.PIU], X[i, S.PIU]) and np.allclose(Cs[i][S.EPIU, S.EPIU], Cf[i][S.EPIU, S.EPIU])
        assert np.linalg.eigvalsh(Cs[i]).min() > -1e-12
    # stamps the backward run does not cover keep the forward estimate
    Xs2, _, cover2, _ = fuse_trajectory(t, X, Cf, t[2:], Xb[2:], Cb[2:], mask)
    assert not cover2[:2].any() and np.array_equal(Xs2[:2], X[:2])


def test_the_combined_constant_carries_the_passes_disagreement():
    assert combine(0.01, 0.002, 0.01, 0.002) == pytest.approx((0.01, 0.002))
    v, sd = combine(-0.075, 0.024, 0.013, 0.024)
    assert v == pytest.approx(-0.031) and sd == pytest.approx(np.hypot(0.024, 0.044))
    assert combine(1.0, 0.1, 2.0, 0.3) == combine(2.0, 0.3, 1.0, 0.1)


def test_smoothing_beats_the_filter_and_stays_consistent(flights):
    nees = []
    for ds, r in flights:
        m = compute_metrics(r, ds)
        f = dataclasses.replace(r, states=r.extra["filtered"]["states"], sd=r.extra["filtered"]["sd"],
                                covariances=None)
        mf = compute_metrics(f, ds)
        # measured 0.091 -> 0.027, 0.103 -> 0.050, 0.118 -> 0.047 m
        assert m["position_rmse"] < 0.7 * mf["position_rmse"]
        nees.append(m["nees_position_mean"])
        # the calibration of a smoothed run is one constant: the combined value at every fused stamp
        fb = r.extra["forward_backward"]
        td = fb["calibration"]["time_offset"]
        assert r.calibration["time_offset"] == pytest.approx(0.5 * (td["forward"] + td["backward"]))
        same = np.isclose(r.states[:, S.TD], r.calibration["time_offset"], rtol=0, atol=1e-12)
        assert same.sum() == fb["outputs_fused"] >= len(same) - 4  # every stamp both passes cover
        assert np.allclose(np.asarray(r.t) + r.states[:, S.TD], r.t_imu) and np.all(np.diff(r.t) > 0)
        assert abs(r.calibration["time_offset"] - ds.meta.truth.time_offset) < 3 * r.calibration["time_offset_sd"]
    # position NEES (3 dof) of the smoothed trajectory, mean over the seeds: measured 3.42 (filter 3.45)
    assert 1.0 < np.mean(nees) < 6.0


def test_cli_estimate_smooths_unless_told_not_to(tmp_path, flights):
    from typer.testing import CliRunner

    from uwbimu.cli.main import app
    from uwbimu.eval.report.inputs import ReportInputs
    from uwbimu.io.dataset import write_dataset

    ds = flights[0][0]
    src = tmp_path / "ds"
    write_dataset(ds, src)
    runner = CliRunner()
    kinds = {}
    for flag in ([], ["--no-smooth"]):
        out = tmp_path / ("out" + "".join(flag))
        r = runner.invoke(app, ["estimate", str(src), "-o", str(out), "--no-plots", *flag])
        assert r.exit_code == 0, r.output
        kinds[tuple(flag)] = {e["kind"] for e in yaml.safe_load((out / "events.yaml").read_text())}
        cal = yaml.safe_load((out / "calibration.yaml").read_text())
        notes = [w for w in ReportInputs(out).warning_items() if w.kind == "forward_backward"]
        if flag:
            assert "smoothing" not in cal and not notes
        else:
            # one voice: the console's note, calibration.yaml's record and the report's item say the same
            assert cal["smoothing"]["method"] == "forward_backward"
            assert cal["time_offset"]["value"] == pytest.approx(cal["smoothing"]["time_offset"]["value"])
            assert [n.text for n in notes] == [cal["smoothing"]["message"]]
            assert " ".join(cal["smoothing"]["message"].split()[:3]) in " ".join(r.output.split())
    assert "forward_backward" in kinds[()] and "forward_backward" not in kinds[("--no-smooth",)]


def test_a_failed_reversed_pass_leaves_the_causal_run_and_says_so(flights):
    """The reversed pass can fail where the forward one did not (too few anchors heard at the end of a log):
    the causal result stands, with a warning event, not an exit 5."""
    from uwbimu.errors import EstimationError
    from uwbimu.estimation.eskf import build_problem
    from uwbimu.estimation.smoother import smooth_result

    ds = flights[0][0]
    opts = EskfOptions()
    forward = run_eskf(ds, opts)
    states = forward.states.copy()
    _, info = build_problem(ds, opts)

    def failing(dataset, options):
        raise EstimationError("not enough data to initialise")

    r = smooth_result(forward, ds, opts, info, np.ones(forward.covariances.shape[1]), failing)
    assert np.array_equal(r.states, states) and "forward_backward" not in r.extra
    ev = [e for e in r.events if e["kind"] == "forward_backward_skipped"]
    assert len(ev) == 1 and ev[0]["severity"] == "warning" and ev[0]["error"] == "EstimationError"


def test_the_clock_fault_check_reads_the_causal_track_of_a_smoothed_run():
    """The clock-fault check differences the filter's information window by window; a smoothed run carries
    one t_d everywhere, so it must read the causal track (uwbimu estimate smooths, then checks the clock).
    Before: a -0.2 s UWB clock jump went unseen on the smoothed run and t_d came out 126 ms (truth 30)."""
    from uwbimu.eval.clock_faults import handle_clock_faults
    from uwbimu.estimation.smoother import causal_view

    ds = simulate(builtin_scenario("calibration-flight").updated(duration=60.0, seeds={"noise": 1}))
    u = ds.uwb.copy()
    t = u["t"].to_numpy().copy()
    keep = ~((t >= 30.0) & (t < 30.2))  # a backward jump: a dropout of its length, invisible in the stamps
    u, t = u[keep].copy(), t[keep]
    t[t >= 30.0] -= 0.2
    u["t"] = t
    bad = dataclasses.replace(ds, uwb=u.reset_index(drop=True))
    opts = EskfOptions(smoother="forward_backward")
    res = run_eskf(bad, opts)
    view = causal_view(res)
    assert np.array_equal(view.states, res.extra["filtered"]["states"]) and view.states is not res.states
    fixed, _ = handle_clock_faults(res, bad, lambda d: run_eskf(d, opts))
    kinds = [e["kind"] for e in fixed.events if str(e.get("kind", "")).startswith("clock_")]
    assert kinds == ["clock_jump"]
    assert abs(fixed.calibration["time_offset"] - 0.03) < 3 * fixed.calibration["time_offset_sd"]


@pytest.mark.parametrize("case", ["independent", "shared", "overconfident"])
def test_the_fused_covariance_follows_the_passes_agreement(case):
    """Monte Carlo of the rule: the fused position's covariance is right (NEES near 3) whether the two passes'
    errors are independent, share half their error, or are both twice their stated sd; the plain information
    combination is right only in the first case."""
    rng = np.random.default_rng(7)
    k, n = 4000, S.ERROR_DIM
    P = np.eye(n) * 0.01
    x_true = S.make_state()
    X = np.tile(x_true, (k, 1))
    common = rng.normal(size=(k, 3)) * 0.1
    own_f, own_b = rng.normal(size=(k, 3)) * 0.1, rng.normal(size=(k, 3)) * 0.1
    if case == "independent":
        ef, eb = own_f, own_b
    elif case == "shared":  # half of each pass's error variance is common
        ef, eb = (common + own_f) / np.sqrt(2), (common + own_b) / np.sqrt(2)
    else:  # both passes' errors twice their stated sd
        ef, eb = 2 * own_f, 2 * own_b
    Xf, Xb = X.copy(), X.copy()
    Xf[:, S.P] += ef
    Xb[:, S.P] += eb
    C = np.broadcast_to(P, (k, n, n)).copy()
    t = np.arange(k, dtype=float)
    Xs, Cs, _, agree = fuse_trajectory(t, Xf, C, t, Xb, C, np.ones(n))
    e = Xs[:, S.P]
    nees = np.einsum("ki,ki->k", e, np.linalg.solve(Cs[:, S.EP, S.EP], e[..., None])[..., 0]).mean()
    r = agree["position"]["r"]
    assert {"independent": 0.9 < r < 1.1, "shared": 0.4 < r < 0.6, "overconfident": 3.6 < r < 4.4}[case]
    assert 2.6 < nees < 3.4, (case, nees)
    naive = np.einsum("ki,ki->k", e, e).mean() / 0.005  # the information combination's covariance 0.005 I
    assert (2.6 < naive < 3.4) == (case == "independent")


def test_fusion_in_chunks_is_the_fusion_at_once():
    """Long logs are fused a chunk of stamps at a time (bounded temporaries); the result is the same."""
    rng = np.random.default_rng(3)
    k, n = 50, S.ERROR_DIM
    A = rng.normal(size=(k, n, n))
    Cf = A @ np.swapaxes(A, 1, 2) * 0.01 + 1e-3 * np.eye(n)
    B = rng.normal(size=(k, n, n))
    Cb = B @ np.swapaxes(B, 1, 2) * 0.01 + 1e-3 * np.eye(n)
    X = np.tile(S.make_state(), (k, 1))
    Xb = X.copy()
    Xb[:, S.P] += rng.normal(size=(k, 3)) * 0.1
    t = np.arange(k, dtype=float)
    whole = fuse_trajectory(t, X, Cf, t + 0.3, Xb, Cb, np.ones(n))
    parts = fuse_trajectory(t, X, Cf, t + 0.3, Xb, Cb, np.ones(n), chunk=7)
    for a, b in zip(whole[:3], parts[:3]):
        assert np.allclose(a, b, rtol=1e-12, atol=1e-15)
    assert whole[3].keys() == parts[3].keys()
    for name in whole[3]:
        assert whole[3][name] == pytest.approx(parts[3][name], rel=1e-12)
