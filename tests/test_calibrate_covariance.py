"""HAC sandwich covariance of the calibration parameters (uwbimu.calibration.covariance)."""

from __future__ import annotations

import numpy as np
import pytest

gtsam = pytest.importorskip("gtsam")

from uwbimu.calibration import CalibrationOptions, calibrate  # noqa: E402
from uwbimu.calibration import covariance as CV  # noqa: E402
from uwbimu.calibration.profile import confidence_interval, profile_verdict  # noqa: E402
from uwbimu.sim import builtin_scenario, simulate  # noqa: E402

N, DT, SIG = 600, 0.1, 0.1
T_LIN = np.arange(N) * DT
F_LIN = np.column_stack([np.ones(N), np.sin(0.5 * T_LIN)])
KEY = gtsam.symbol("h", 0)


def _ar1(rng, n, rho, sig):
    w = rng.standard_normal(n) * sig * np.sqrt(1.0 - rho**2)
    e = np.empty(n)
    e[0] = rng.standard_normal() * sig
    for i in range(1, n):
        e[i] = rho * e[i - 1] + w[i]
    return e


def _linear_sandwich(y, blocks: int = 0, bin_s: float = DT):
    """Sandwich of y = F theta + e through a GTSAM graph of one CustomFactor per row (time stamps T_LIN);
    with ``blocks``, the block check too (``info.block``)."""
    noise = gtsam.noiseModel.Isotropic.Sigma(1, SIG)
    g = gtsam.NonlinearFactorGraph()
    for i in range(N):
        def err(this, v, H, i=i):
            if H is not None:
                H[0] = F_LIN[i:i + 1].copy()
            return np.array([F_LIN[i] @ v.atVector(KEY) - y[i]])
        g.add(gtsam.CustomFactor(noise, [KEY], err))
    g.add(gtsam.PriorFactorVector(KEY, np.zeros(2), gtsam.noiseModel.Isotropic.Sigma(2, 100.0)))
    v = gtsam.Values()
    v.insert(KEY, np.linalg.lstsq(F_LIN, y, rcond=None)[0])
    slots = np.column_stack([np.arange(N), np.zeros(N, int)])
    return CV.sandwich_covariance(g, v, [KEY], slots, T_LIN, bin_s, blocks=blocks)


@pytest.mark.parametrize("rho", [0.8, 0.0])
def test_sandwich_matches_monte_carlo_with_ar1_noise(rho):
    # Monte Carlo spread of the least-squares estimate under AR(1) noise (the truth of the covariance)
    mc = np.array([np.linalg.lstsq(F_LIN, _ar1(np.random.default_rng(s), N, rho, SIG), rcond=None)[0]
                   for s in range(1500)])
    sd_mc = mc.std(axis=0)
    sds, infos = [], []
    for s in range(8):
        cov, cov_model, info = _linear_sandwich(_ar1(np.random.default_rng(10_000 + s), N, rho, SIG))
        sds.append(np.sqrt(np.diag(cov)))
        infos.append(info)
    sd_model = np.sqrt(np.diag(cov_model))
    sd_sand = np.mean(sds, axis=0)
    if rho > 0:
        assert np.all(sd_model < 0.5 * sd_mc), (sd_model, sd_mc)  # the white model is over-confident (3x)
    else:
        np.testing.assert_allclose(sd_model, sd_mc, rtol=0.1)
    np.testing.assert_allclose(sd_sand, sd_mc, rtol=0.15)
    assert all(i.bandwidth_bins >= 1.0 and i.n_bins == N for i in infos)


def test_andrews_bandwidth_grows_with_autocorrelation():
    rng = np.random.default_rng(3)
    white = rng.standard_normal((2000, 1))
    red = _ar1(rng, 2000, 0.9, 1.0)[:, None]
    bw_w, rho_w = CV.andrews_bandwidth(white)
    bw_r, rho_r = CV.andrews_bandwidth(red)
    assert bw_w < 3.0 and abs(rho_w[0]) < 0.1
    assert bw_r > 20.0 and rho_r[0] > 0.8


def _flight(seed, duration, ar=0.0):
    sc = builtin_scenario("calibration-flight")
    sc = sc.model_copy(update={"duration": duration, "seeds": sc.seeds.model_copy(update={"noise": seed})})
    ds = simulate(sc)
    if ar:
        # correlated range errors: one AR(1) per anchor (per-range coefficient ar, sd 0.1 m) on top of the white
        rng = np.random.default_rng(100 + seed)
        u = ds.uwb
        for a in u["anchor"].unique():
            m = (u["anchor"] == a).to_numpy()
            u.loc[m, "range"] = u.loc[m, "range"].to_numpy() + _ar1(rng, int(m.sum()), ar, 0.1)
    return ds


def _errors_and_sds(ds, res):
    cal, truth = res.calibration, ds.meta.truth
    err = np.append(np.subtract(cal["lever_arm"], truth.lever_arm), cal["time_offset"]["value"] - truth.time_offset)
    sd = np.append(cal["lever_arm_sd"], cal["time_offset"]["sd"])
    sd_model = np.append(cal["lever_arm_sd_model"], cal["time_offset"]["sd_model"])
    return err, sd, sd_model


def test_white_simulation_sandwich_close_to_model_sigma():
    ds = _flight(1, 30.0)
    # the HAC sandwich alone (the block check, which may widen it, has its own tests below)
    res = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False},
                                                           "block_check": {"blocks": 0}}))
    _err, sd, sd_model = _errors_and_sds(ds, res)
    ratio = sd / sd_model
    assert np.all((ratio > 0.8) & (ratio < 1.25)), ratio
    c = res.calibration["covariance"]
    assert c["method"] == "sandwich" and c["bandwidth_s"] >= c["bin_s"] > 0
    # model option: sd is the GTSAM marginal, identical to sd_model
    res_m = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False}, "covariance": "model"}),
                      eskf=res.eskf)
    np.testing.assert_allclose(res_m.calibration["lever_arm_sd"], sd_model[:3], rtol=1e-6)
    assert res_m.calibration["covariance"]["method"] == "model"


def test_sandwich_never_below_the_model_sigma():
    """An overstated range sd (3x the simulated noise) makes the raw sandwich smaller than the model; the
    reported sigma is floored at the model's, the profile scale at 1, the correlations stay the sandwich's."""
    ds = _flight(2, 12.0)
    noise = float(ds.meta.range_sigma or 0.1)
    res = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False},
                                                           "range_sigma": 3.0 * noise}))
    _err, sd, sd_model = _errors_and_sds(ds, res)
    np.testing.assert_allclose(sd, sd_model, rtol=1e-9)
    c = res.calibration["covariance"]
    assert c["floored_at_model"] >= 4
    corr = np.array(res.calibration["correlations"]["matrix"])
    assert np.allclose(np.diag(corr), 1.0) and np.all(np.abs(corr) <= 1.0 + 1e-6)


def test_correlated_range_errors_sandwich_closer_to_the_seed_spread():
    # the white range model's sigmas on correlated errors: pinned (select: given), since by default the range
    # model is chosen on the log (issue 27 item 7) and here it would model the correlation itself
    opts = CalibrationOptions.model_validate({"td_profile": {"enabled": False}, "range_model": {"select": "given"}})
    z_s, z_m = [], []
    for seed in (1, 2, 3):
        ds = _flight(seed, 12.0, ar=0.9)
        err, sd, sd_model = _errors_and_sds(ds, calibrate(ds, opts))
        assert np.all(sd > sd_model)  # correlated errors: the sandwich widens every sigma
        z_s.append(err / sd)
        z_m.append(err / sd_model)
    rms_s, rms_m = float(np.sqrt(np.mean(np.square(z_s)))), float(np.sqrt(np.mean(np.square(z_m))))
    assert rms_m > 1.5  # the white model is over-confident here
    assert abs(np.log(rms_s)) < abs(np.log(rms_m)), (rms_s, rms_m)


def test_profile_chi2_scale_widens_the_confidence_set_and_the_curvature_sigma():
    grid = np.round(np.arange(-0.2, 0.2001, 0.02), 6)
    chi2 = ((grid - 0.01) / 0.01) ** 2 + 5.0
    v1, _b1, _x1, s1 = profile_verdict(grid, chi2, 9.0)
    v2, _b2, _x2, s2 = profile_verdict(grid, chi2, 9.0, chi2_scale=0.25)
    assert v1 == v2 == "identified"
    assert s2 == pytest.approx(2.0 * s1, rel=1e-6)
    lo1, hi1 = confidence_interval(grid, chi2, 9.0)
    lo2, hi2 = confidence_interval(grid, chi2, 9.0, chi2_scale=0.25)
    assert lo2 < lo1 and hi2 > hi1


def _gauss_markov(rng, tau, sd):
    """First-order Gauss-Markov series on the T_LIN grid: correlation time ``tau`` [s], sd ``sd``."""
    return _ar1(rng, N, np.exp(-DT / tau), sd)


@pytest.mark.parametrize("tau, sd_slow", [(10.0, 0.1), (0.0, 0.0)])
def test_block_check_sees_slow_errors_the_hac_misses(tau, sd_slow):
    """White noise plus an error correlated over 10 s (a sixth of the 60 s log): the HAC's few-second
    bandwidth misses most of it, the 6 time blocks see it; on white noise both match the Monte Carlo spread."""
    def noise(seed):
        rng = np.random.default_rng(seed)
        e = SIG * rng.standard_normal(N)
        return e + (_gauss_markov(rng, tau, sd_slow) if sd_slow else 0.0)

    sd_mc = np.array([np.linalg.lstsq(F_LIN, noise(s), rcond=None)[0] for s in range(2000)]).std(axis=0)
    var_h, var_b = [], []
    for s in range(10):
        cov, _cm, info = _linear_sandwich(noise(90_000 + s), 6)
        var_h.append(np.diag(cov))
        var_b.append(np.diag(info.block.cov))
        assert info.block.blocks == 6 and info.block.block_s == pytest.approx(N * DT / 6)
    sd_h, sd_b = np.sqrt(np.mean(var_h, axis=0)), np.sqrt(np.mean(var_b, axis=0))
    if sd_slow:
        assert sd_h[0] < 0.3 * sd_mc[0], (sd_h, sd_mc)  # the HAC is 5x over-confident on the constant
        assert np.all((sd_b > 0.5 * sd_mc) & (sd_b < 2.0 * sd_mc)), (sd_b, sd_mc)
        assert np.all(sd_b > sd_h)
    else:
        np.testing.assert_allclose(sd_h, sd_mc, rtol=0.15)
        np.testing.assert_allclose(sd_b, sd_mc, rtol=0.2)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # one bin: the HAC's AR(1) fit has no pairs (floored at the model)
def test_block_check_needs_two_bins():
    """Every row in one score bin (bin as long as the log): no block check, the HAC sandwich unchanged."""
    y = SIG * np.random.default_rng(7).standard_normal(N)
    cov6, _m, info6 = _linear_sandwich(y, 6, bin_s=100.0)
    cov0, _m, info0 = _linear_sandwich(y, 0, bin_s=100.0)
    assert info6.n_bins == 1 and info6.block is None and info0.block is None
    np.testing.assert_allclose(cov6, cov0)


def test_block_check_null_distribution_with_unequal_blocks():
    """Under the HAC (white scores), Satterthwaite's chi-square gives calibrated p-values even when a few blocks
    carry most of the information, and the block leverage correction makes the variance ratio unbiased."""
    rng = np.random.default_rng(4)
    V = np.array([1.0, 1.0, 4.0, 0.5, 2.0, 0.2])[:, None] * np.array([1.0, 3.0])  # (K, p)
    M = V * np.array([0.6, 0.3])  # the trajectory absorbs 40 % / 70 % of each block's score sum
    omega = np.diag(V.sum(axis=0))
    ratios, p = [], []
    for _ in range(4000):
        C = rng.standard_normal(V.shape) * np.sqrt(M)
        bc = CV.block_check(C, V, M, omega, np.zeros((2, 2)), 0.1, 600, 0.01)
        ratios.append(bc.ratio)
        p.append(bc.p_value)
    ratios, p = np.array(ratios), np.array(p)
    np.testing.assert_allclose(ratios.mean(axis=0), 1.0, atol=0.05)
    assert np.all(np.mean(p < 0.01, axis=0) < 0.02) and np.all(np.mean(p < 0.05, axis=0) < 0.08)
    assert np.all(np.mean(p < 0.05, axis=0) > 0.02)
    # equal blocks: Satterthwaite's dof is the number of blocks; unequal ones have fewer
    assert CV.block_check(C, np.ones((6, 2)), np.ones((6, 2)), np.eye(2) * 6, np.zeros((2, 2)), 0.1, 600,
                          0.01).dof == pytest.approx([6.0, 6.0])
    assert np.all(bc.dof < 4.0)


def test_block_check_only_widens_and_is_reported_per_parameter():
    """Same ESKF, blocks 0 against the default: no sigma shrinks, every sigma the blocks widen is the blocks',
    calibration.yaml names each parameter's ratio, dof and p-value, and the event lists the significant ones."""
    ds = _flight(5, 20.0, ar=0.995)
    on = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False}}))
    off = calibrate(ds, CalibrationOptions.model_validate({"td_profile": {"enabled": False},
                                                           "block_check": {"blocks": 0}}), eskf=on.eskf)
    _e, sd_on, _m = _errors_and_sds(ds, on)
    _e, sd_off, _m = _errors_and_sds(ds, off)
    assert "block_check" not in off.calibration["covariance"]
    bc = on.calibration["covariance"]["block_check"]
    assert bc["blocks"] == 6 and bc["level"] == 0.01
    names = on.calibration["correlations"]["names"]
    assert list(bc["parameters"]) == names
    par = [bc["parameters"][n] for n in ("lever_arm_x", "lever_arm_y", "lever_arm_z", "time_offset")]
    assert np.all(sd_on >= sd_off * (1 - 1e-9))
    for p, a, b in zip(par, sd_on, sd_off):
        assert p["widened"] == (p["variance_ratio"] > 1.0)
        if not p["widened"]:
            assert a == pytest.approx(b, rel=1e-9)
    assert any(p["widened"] for p in par)
    ev = [e for e in on.events if e["kind"] == "range_errors_correlated_over_blocks"]
    sig = sorted(n for n, p in bc["parameters"].items() if p["significant"])
    assert (ev[0]["parameters"] if ev else []) == sig
    assert not ev or "range_bias_drift" in ev[0]["advice"]  # the drift model is off here: it is what to try


def test_block_event_advice_depends_on_the_range_model():
    from uwbimu.calibration.batch import _block_event

    bc = {"blocks": 6, "level": 0.01, "parameters": {
        "lever_arm_x": {"variance_ratio": 3.0, "significant": True}, "time_offset": {"variance_ratio": 0.9,
                                                                                     "significant": False}}}
    off, on = _block_event(bc), _block_event(bc, drift_on=True)
    assert off["parameters"] == on["parameters"] == ["lever_arm_x"]
    assert "range_bias_drift" in off["advice"] and "range_model.direction" in on["advice"]
    assert _block_event({**bc, "parameters": {"time_offset": {"variance_ratio": 0.9, "significant": False}}}) is None


def test_block_check_options():
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        CalibrationOptions.model_validate({"block_check": {"blocks": 1}})
    assert CalibrationOptions().block_check.blocks == 6
