"""Pin the shared physics primitives of uwbimu.models.kernels to the reference model."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm

from uwbimu.estimation.jacobians import error_F
from uwbimu.models import kernels as MK
from uwbimu.models import reference as ref
from uwbimu.models.quaternion import quat_exp, quat_multiply, quat_normalize, quat_to_rotmat
from uwbimu.models.state import boxplus

from test_eskf_jacobians import _rand_state as _state  # same random state generator


def test_quaternion_primitives_match_numpy_reference():
    rng = np.random.default_rng(3)
    for _ in range(5):
        p, q = quat_normalize(rng.normal(size=4)), quat_normalize(rng.normal(size=4))
        out = np.empty(4)
        MK.quat_mul(p, q, out)
        np.testing.assert_allclose(out, quat_multiply(p, q), atol=1e-15)
        th = rng.normal(size=3)
        MK.quat_exp(th, out)
        np.testing.assert_allclose(out, quat_exp(th), atol=1e-15)
        R = np.empty((3, 3))
        MK.rotmat(p, R)
        np.testing.assert_allclose(R, quat_to_rotmat(p), atol=1e-15)


@pytest.mark.parametrize("dt", [0.005, 0.05])
def test_dense_error_transition_matches_expm_of_reference_F(dt):
    rng = np.random.default_rng(4)
    x = _state(rng, nb=2)
    u = np.concatenate([rng.normal(0, 2, 3) + [0, 0, 9.81], rng.normal(0, 1, 3)])
    Phi = np.empty((21, 21))
    MK.error_transition(x, u, dt, Phi)
    F = error_F(x[:20], u)
    expect = np.eye(21)
    expect[:19, :19] = expm(F * dt)
    # second-order series (exact attitude block): error O(|F|^3 dt^3)
    np.testing.assert_allclose(Phi, expect, atol=30 * dt**3)


def test_tdoa_jacobian_matches_finite_differences_of_reference():
    rng = np.random.default_rng(5)
    nb = 3
    x = _state(rng, nb)
    u = np.concatenate([rng.normal(0, 2, 3) + [0, 0, 9.81], rng.normal(0, 1, 3)])
    a, b = np.array([4.0, -3.0, 2.5]), np.array([-2.0, 1.0, 0.3])
    bias_idx = 19 + 2

    def h_ref(dx):
        xx = np.concatenate([boxplus(x[:20], dx[:19]), x[20:] + dx[19:]])
        return ref.tdoa_measurement(xx[:20], a, b) + xx[bias_idx + 1]

    h = np.empty(19 + nb)
    work = np.empty(19 + nb)
    pred = MK.tdoa_jacobian(x, u, a, b, bias_idx, 0.0, h, work)
    assert pred == pytest.approx(h_ref(np.zeros(19 + nb)), abs=1e-12)
    eps = 1e-6
    Hfd = np.array([(h_ref(eps * e) - h_ref(-eps * e)) / (2 * eps) for e in np.eye(19 + nb)])
    Hfd[18] = h[18]  # t_d enters through the time of the sample, tested for ranges in test_eskf_jacobians
    np.testing.assert_allclose(h, Hfd, atol=1e-7)


def test_stale_cache_is_flushed_when_dependency_sources_change(tmp_path, monkeypatch):
    import types
    dep = types.ModuleType("dep")
    src = tmp_path / "dep.py"
    src.write_text("A = 1\n")
    dep.__file__ = str(src)

    flushed = []

    class FakeCache:
        cache_path = str(tmp_path / "cache")

        def flush(self):
            flushed.append(1)

    class FakeDispatcher:
        _cache = FakeCache()
        __module__ = "fake.mod"

    g = {"__name__": "fake.mod", "k": FakeDispatcher()}
    assert MK.refresh_stale_cache(g, [dep]) is True      # first time: no stamp
    assert MK.refresh_stale_cache(g, [dep]) is False     # unchanged sources
    src.write_text("A = 2\n")
    assert MK.refresh_stale_cache(g, [dep]) is True      # edited dependency -> flush
    assert len(flushed) == 2


def test_quat_from_euler_is_zyx():
    from uwbimu.models.quaternion import quat_from_euler

    r, p, y = 0.3, -0.4, 2.0
    c, s = np.cos, np.sin
    Rz = np.array([[c(y), -s(y), 0], [s(y), c(y), 0], [0, 0, 1]])
    Ry = np.array([[c(p), 0, s(p)], [0, 1, 0], [-s(p), 0, c(p)]])
    Rx = np.array([[1, 0, 0], [0, c(r), -s(r)], [0, s(r), c(r)]])
    np.testing.assert_allclose(quat_to_rotmat(quat_from_euler(r, p, y)), Rz @ Ry @ Rx, atol=1e-14)
