"""Measurement models: analytic Jacobians against the finite-difference default (which is built on
the reference model), and the height / zero-velocity / user-defined models in the streaming filter."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.estimation import Eskf, EskfOptions
from uwbimu.estimation.metrics import truth_at
from uwbimu.models import reference as ref
from uwbimu.models import state as S
from uwbimu.models.measurements import (
    HeightModel, MeasurementModel, RangeModel, TdoaModel, ZeroVelocityModel, fd_jacobian,
)
from uwbimu.models.state import StateLayout
from uwbimu.sim import builtin_scenario, simulate

LAYOUT = StateLayout(n_anchor_bias=4, n_height_bias=1)


def _random_state(rng):
    x = np.zeros(LAYOUT.n_nom)
    x[S.P] = rng.normal(0, 2, 3)
    x[S.V] = rng.normal(0, 1, 3)
    q = rng.normal(size=4)
    x[S.Q] = q / np.linalg.norm(q)
    x[S.BA] = rng.normal(0, 0.1, 3)
    x[S.BG] = rng.normal(0, 0.02, 3)
    x[S.PIU] = rng.normal(0, 0.2, 3)
    x[S.TD] = rng.normal(0, 0.05)
    x[LAYOUT.nom("anchor_bias")] = rng.normal(0, 0.1, 4)
    x[LAYOUT.nom("height_bias")] = rng.normal(0, 0.5, 1)
    u = np.concatenate([rng.normal(0, 2, 3) + [0, 0, 9.81], rng.normal(0, 1, 3)])
    return x, u


MODELS = {
    "range": lambda: RangeModel([3.0, -2.0, 2.5], 0.1, bias_index=2),
    "range-no-bias": lambda: RangeModel([-1.0, 4.0, 0.5], 0.1),
    "tdoa": lambda: TdoaModel([3.0, -2.0, 2.5], [-1.0, 4.0, 0.5], 0.1, bias_a=0, bias_b=3),
    "height": lambda: HeightModel(0.1, LAYOUT),
    "zero-velocity": lambda: ZeroVelocityModel(0.01),
}


class TestJacobians:
    @pytest.mark.parametrize("name", sorted(MODELS))
    def test_analytic_jacobian_matches_finite_differences(self, name):
        rng = np.random.default_rng(11)
        for _ in range(5):
            x, u = _random_state(rng)
            m = MODELS[name]()
            H = m.jacobian(x, u, LAYOUT)
            H_fd = fd_jacobian(m, x, u, LAYOUT)
            assert H.shape == (m.dim, LAYOUT.n_err)
            np.testing.assert_allclose(H, H_fd, atol=1e-6, rtol=1e-5)

    def test_range_and_tdoa_predictions_are_the_reference_model(self):
        rng = np.random.default_rng(2)
        x, u = _random_state(rng)
        a, b = np.array([3.0, -2.0, 2.5]), np.array([-1.0, 4.0, 0.5])
        assert RangeModel(a, 0.1).evaluate(x, u)[0] == pytest.approx(ref.range_measurement(x[:20], a), abs=1e-12)
        assert TdoaModel(a, b, 0.1).evaluate(x, u)[0] == pytest.approx(ref.tdoa_measurement(x[:20], a, b), abs=1e-12)

    def test_time_offset_column_is_the_motion_derivative(self):
        """The finite-difference default's t_d column is d/dt of the prediction along the motion: for a
        range, -u^T (v + R [w]x p_IU) (seed 001); checked against a time step of the reference model."""
        rng = np.random.default_rng(5)
        x, u = _random_state(rng)
        m = RangeModel([3.0, -2.0, 2.5], 0.1)
        dt = 1e-5
        xp = ref.propagate(x[:20], u, u, dt)
        xm = ref.propagate(x[:20], u, u, -dt)
        d = (ref.range_measurement(xp, m.anchor) - ref.range_measurement(xm, m.anchor)) / (2 * dt)
        assert fd_jacobian(m, x, u, LAYOUT)[0, S.ETD] == pytest.approx(d, rel=1e-5)


def _flight(duration=60.0):
    return simulate(builtin_scenario("calibration-flight").model_copy(update={"duration": duration}))


def _feed(f: Eskf, ds, height_every: int = 0, height_fn=None, model_fn=None):
    """Push the log in arrival order; every ``height_every``-th IMU sample also an altimeter reading."""
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    uwb = ds.uwb
    tu, au, ru = uwb["t"].to_numpy(float), uwb["anchor"].astype(str).to_numpy(), uwb["range"].to_numpy(float)
    td = ds.meta.truth.time_offset or 0.0
    j = 0
    chunk = 50
    for i0 in range(0, len(imu), chunk):
        blk = imu[i0:i0 + chunk]
        while j < len(tu) and tu[j] + td <= blk[0, 0]:
            f.push_range(tu[j], au[j], ru[j])
            j += 1
        f.push_imu_chunk(blk[:, 0], blk[:, 1:4], blk[:, 4:7])
        if height_every and (i0 // chunk) % height_every == 0:
            t_h = blk[-1, 0]
            if model_fn is not None:
                f.push(t_h, model_fn(), [height_fn(t_h)])
            else:
                f.push_height(t_h, height_fn(t_h))
    for k in range(j, len(tu)):
        f.push_range(tu[k], au[k], ru[k])
    f.finish()
    return f


def test_altimeter_bias_is_estimated_and_height_tightens():
    ds = _flight()
    td = ds.meta.truth.time_offset or 0.0
    rng = np.random.default_rng(4)
    bias, sig = 0.5, 0.05

    def height(t_imu):
        p, _, _, _ = truth_at(ds, np.array([t_imu - td]))
        return float(p[0, 2]) + bias + rng.normal(0, sig)

    opts = EskfOptions(height={"bias": "estimate", "sigma": sig, "bias_random_walk": 0.0})
    f = _feed(Eskf.for_dataset(ds, opts), ds, height_every=2, height_fn=height)
    s = f.state()
    assert s.height_bias is not None and abs(s.height_bias - bias) < 3 * s.height_bias_sd
    assert s.height_bias_sd < 0.1
    assert s.cov("height_bias").shape == (1, 1)
    plain = _feed(Eskf.for_dataset(ds, EskfOptions()), ds).state()
    assert s.position_sd[2] < plain.position_sd[2]
    assert any(r[3] == 1.0 for r in f.records() if np.isfinite(r[2]))


class UserHeight(MeasurementModel):
    """A user-defined altimeter: only evaluate and covariance (finite-difference Jacobian)."""

    dim = 1
    clock = "imu"
    name = "user-height"

    def evaluate(self, x, u):
        return np.array([x[2]])

    def covariance(self):
        return np.array([[0.05**2]])


def test_user_model_with_finite_difference_jacobian_matches_builtin_height():
    ds = _flight(40.0)
    td = ds.meta.truth.time_offset or 0.0

    def height(t_imu):
        p, _, _, _ = truth_at(ds, np.array([t_imu - td]))
        return float(p[0, 2])

    opts = EskfOptions(height={"sigma": 0.05})
    a = _feed(Eskf.for_dataset(ds, opts), ds, 3, height).state()
    b = _feed(Eskf.for_dataset(ds, opts), ds, 3, height, model_fn=UserHeight).state()
    np.testing.assert_allclose(a.position, b.position, atol=1e-6)
    np.testing.assert_allclose(a.lever_arm, b.lever_arm, atol=1e-6)


def test_zero_velocity_updates_shrink_velocity_uncertainty():
    ds = simulate(builtin_scenario("hover").model_copy(update={"duration": 30.0}))
    base = _feed(Eskf.for_dataset(ds), ds).state()
    f = Eskf.for_dataset(ds)
    imu = ds.imu[["t", "ax", "ay", "az", "wx", "wy", "wz"]].to_numpy(float)
    f.push_ranges(ds.uwb["t"].to_numpy(float), ds.uwb["anchor"].astype(str), ds.uwb["range"].to_numpy(float))
    for i0 in range(0, len(imu), 100):
        blk = imu[i0:i0 + 100]
        f.push_imu_chunk(blk[:, 0], blk[:, 1:4], blk[:, 4:7])
        f.push_zero_velocity(blk[-1, 0], sigma=0.02)
    f.finish()
    s = f.state()
    # the hover scenario moves slightly; the test only needs the pseudo-measurement to act
    assert np.all(s.velocity_sd < base.velocity_sd)
