"""Point-mass EKF covariance honesty: the acceleration-error process noise and the
consider terms of the fixed lever arm / time offset (see docs/montecarlo.md)."""

import numpy as np
import pytest

from uwbimu.estimation import compute_metrics
from uwbimu.estimation.pointmass import acceleration_error_psd, run_pointmass
from uwbimu.models.quaternion import skew
from uwbimu.sim import builtin_scenario, simulate


def test_acceleration_error_psd_is_the_first_order_attitude_error_map():
    rng = np.random.default_rng(0)
    f = rng.normal(size=(50, 3)) * 4.0
    t = rng.uniform(0, 60, size=50)
    kw = dict(accel_noise_density=0.002, accel_bias_sd=0.05, extra_sd=0.03, tau=0.3, tilt0_sd=0.004,
              yaw0_sd=0.03, gyro_bias_sd=5e-4, gyro_noise_density=2.4e-4, gyro_bias_rw=2e-5)
    q = acceleration_error_psd(f, t, **kw)
    for k in range(50):
        grow = 5e-4**2 * t[k] ** 2 + 2.4e-4**2 * t[k] + 2e-5**2 * t[k] ** 3 / 3
        sig_th = np.diag([0.004**2 + grow, 0.004**2 + grow, 0.03**2 + grow])
        F = skew(f[k])
        cov = F @ sig_th @ F.T + (0.05**2 + 0.03**2) * np.eye(3)  # dtheta x f = -[f]x dtheta
        np.testing.assert_allclose(q[k], 0.002**2 + 2 * 0.3 * np.diag(cov), rtol=1e-12)
    # hover: only the horizontal axes see the tilt error, and it grows with time
    qh = acceleration_error_psd(np.array([[0.0, 0.0, 9.81]] * 2), np.array([0.0, 60.0]), **kw)
    assert qh[1, 0] > qh[0, 0] and qh[0, 2] == pytest.approx(qh[1, 2])


def _short(name, seed, **upd):
    sc = builtin_scenario(name)
    seeds = sc.seeds.model_copy(update={"truth": seed, "noise": seed + 100, "init": seed + 200})
    return simulate(sc.model_copy(update={"duration": 30.0, "seeds": seeds, **upd}))


@pytest.mark.parametrize("name", ["circle", "figure8", "calibration-flight"])
def test_nees_honest_on_simulated_builtins(name):
    """Lever arm (unknown to the dataset) and time offset are not estimated: the output
    covariance must cover them. Before that term the circle gave NEES ~85 (dof 6)."""
    nees = []
    for seed in (1, 2):
        ds = _short(name, seed)
        res = run_pointmass(ds)
        assert any("lever arm unknown" in w for w in res.warnings)
        m = compute_metrics(res, ds, skip_s=2.0)
        assert m["nees_dof"] == 6
        nees.append(m["nees_mean"])
    assert 3.0 < np.mean(nees) < 9.0, nees


def test_consider_terms_vanish_when_lever_arm_and_time_offset_are_known():
    ds = _short("circle", 3)
    lever = list(ds.meta.truth.lever_arm)
    known = run_pointmass(ds, {"lever_arm": lever, "time_offset": ds.meta.truth.time_offset,
                               "time_offset_sd": 0.0})
    unknown = run_pointmass(ds)
    assert known.extra["lever_arm_sd"] == 0.0 and unknown.extra["lever_arm_sd"] == pytest.approx(0.1)
    # the unknown lever arm adds ~0.1 m per axis to the position sd
    assert np.all(unknown.sd[100:, 0:3] >= 0.1 - 1e-9)
    assert np.median(known.sd[:, 0:3]) < 0.08
    mk = compute_metrics(known, ds, skip_s=2.0)
    assert mk["position_rmse"] < 0.1 and 3.0 < mk["nees_mean"] < 9.0, mk
