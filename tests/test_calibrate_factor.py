"""The batch calibrator's range factor: Jacobians vs finite differences, residual vs the reference model."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.calibration.range_factor import imu_deltas, make_gtsam_factor, range_error, so3_exp
from uwbimu.models import reference as ref


def _imu(rng, n=41, rate=200.0):
    t = np.arange(n) / rate
    u = np.empty((n, 6))
    u[:, :3] = [0.3, -0.2, 9.81] + 1.5 * np.sin(2 * np.pi * np.outer(t, [1.1, 0.7, 1.3]) + rng.uniform(0, 6, 3))
    u[:, 3:] = 0.8 * np.sin(2 * np.pi * np.outer(t, [0.9, 1.2, 0.5]) + rng.uniform(0, 6, 3))
    return t, u


#: three anchors of the synthetic group tests (world, m)
GROUP_ANCHORS = np.array([[4.0, -1.0, 2.5], [-3.0, 2.0, 0.3], [0.5, 5.0, -1.0]])


def group_inputs(rng, n: int):
    """(deltas, col, rho) of ``n`` ranges 0.01-0.18 s after one keyframe, row m to anchor ``m % 3`` of
    ``GROUP_ANCHORS`` (shared by the grouped-factor tests)."""
    from uwbimu.calibration.range_factor import imu_deltas

    t, u = _imu(rng)
    s0 = np.sort(rng.uniform(0.01, 0.18, n))
    _k, deltas = imu_deltas(t, u, np.array([0.05, -0.03, 0.02]), np.array([0.01, -0.02, 0.005]),
                            np.array([0.0]), s0)
    col = np.arange(n) % 3
    rho = np.linalg.norm(GROUP_ANCHORS[col] - [1.0, 2.0, 1.5], axis=1) + rng.normal(0, 0.05, n)
    return deltas, col, rho


def retraction_differences(f, vals, keys, dims, h=1e-6):
    """Central differences of a GTSAM factor's unwhitened error through ``vals.retract`` along every tangent
    direction of ``keys`` (dimensions ``dims``): the columns its linearised Jacobian must match."""
    import gtsam

    cols = []
    for k, dim in zip(keys, dims):
        for i in range(dim):
            out = []
            for sgn in (1, -1):
                dx = gtsam.VectorValues()
                for kk, dd in zip(keys, dims):
                    dx.insert(kk, sgn * h * np.eye(dd)[i] if kk == k else np.zeros(dd))
                out.append(f.unwhitenedError(vals.retract(dx)))
            cols.append((out[0] - out[1]) / (2 * h))
    return np.array(cols).T


def group_values(rng, td_fixed, n_anchors: int = 3, n_dir: int = 5):
    """GTSAM values, keys and tangent dimensions of one keyframe's group factor with tag-side direction
    coefficients: pose, velocity, lever arm, t_d (unless ``td_fixed``), ``n_anchors`` biases and direction
    vectors of ``n_dir`` coefficients (drawn from ``rng``).  Returns ``(vals, keys, dims)``."""
    import gtsam
    from gtsam.symbol_shorthand import A, L, T, V, X

    from uwbimu.calibration.graph import dir_key

    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(gtsam.Rot3(so3_exp(np.array([0.2, -0.4, 1.1]))), np.array([1.0, 2.0, 1.5])))
    vals.insert(V(0), np.array([0.4, -0.3, 0.2]))
    vals.insert(L(0), np.array([0.12, -0.08, 0.14]))
    keys, dims = [X(0), V(0), L(0)], [6, 3, 3]
    if td_fixed is None:
        vals.insert(T(0), np.array([0.027]))
        keys, dims = keys + [T(0)], dims + [1]
    for j in range(n_anchors):
        vals.insert(A(j), np.array([0.01 * j]))
        keys, dims = keys + [A(j)], dims + [1]
    for j in range(n_anchors):
        vals.insert(dir_key(j), rng.normal(0, 0.05, n_dir))
        keys, dims = keys + [dir_key(j)], dims + [n_dir]
    return vals, keys, dims


def assert_state_jacobians(f, jac, R, p, v, lev, td, h=1e-6, atol=1e-6):
    """Central differences of ``f(R=, p=, v=, lev=, td=)`` against ``jac = (J_pose, J_vel, J_lever, J_td)`` on
    the GTSAM tangents (attitude right-perturbed, position along the body axes)."""
    from uwbimu.calibration.range_factor import so3_exp

    Jp, Jv, Jl, Jt = jac
    for i in range(3):
        dx = np.zeros(3)
        dx[i] = h
        np.testing.assert_allclose(Jp[:, i], (f(R=R @ so3_exp(dx)) - f(R=R @ so3_exp(-dx))) / 2 / h, atol=atol)
        np.testing.assert_allclose(Jp[:, 3 + i], (f(p=p + R @ dx) - f(p=p - R @ dx)) / 2 / h, atol=atol)
        np.testing.assert_allclose(Jv[:, i], (f(v=v + dx) - f(v=v - dx)) / 2 / h, atol=atol)
        np.testing.assert_allclose(Jl[:, i], (f(lev=lev + dx) - f(lev=lev - dx)) / 2 / h, atol=atol)
    np.testing.assert_allclose(Jt, (f(td=td + h) - f(td=td - h)) / 2 / h, atol=atol)


@pytest.fixture(scope="module")
def case():
    rng = np.random.default_rng(7)
    t, u = _imu(rng)
    b_a, b_g = np.array([0.05, -0.03, 0.02]), np.array([0.01, -0.02, 0.005])
    s0 = 0.1337
    k, (d,) = imu_deltas(t, u, b_a, b_g, np.array([0.0]), np.array([s0]))
    R = so3_exp(rng.normal(size=3))
    state = dict(R_k=R, p_k=np.array([1.0, 2.0, 1.5]), v_k=np.array([0.4, -0.3, 0.2]),
                 lever=np.array([0.12, -0.08, 0.14]), bias=0.03)
    return dict(t=t, u=u, b_a=b_a, b_g=b_g, s0=s0, d=d, k=k, anchor=np.array([4.0, -1.0, 2.5]), **state)


def _reference_range(c, s):
    """Reference model: RK4 (cubic midpoint) integration of the 20-state from t_k = 0 to IMU time s."""
    t, u = c["t"], c["u"]
    keep = t < s
    ts = np.append(t[keep], s)
    us = np.vstack([u[keep], [np.interp(s, t, u[:, j]) for j in range(6)]])
    x0 = np.zeros(20)
    x0[0:3], x0[3:6] = c["p_k"], c["v_k"]
    from scipy.spatial.transform import Rotation

    qx, qy, qz, qw = Rotation.from_matrix(c["R_k"]).as_quat()
    x0[6:10] = [qw, qx, qy, qz]
    x0[10:13], x0[13:16], x0[16:19] = c["b_a"], c["b_g"], c["lever"]
    xs = ref.integrate_imu(x0, ts, us)
    return float(ref.range_measurement(xs[-1], c["anchor"]))


@pytest.mark.parametrize("delta", [0.0, 0.004, -0.006])
def test_residual_matches_reference_model(case, delta):
    """e(t_d0 + delta) = reference range at IMU time s0 + delta, plus the anchor bias, minus rho."""
    c = case
    rho = 5.0
    e = range_error(c["R_k"], c["p_k"], c["v_k"], c["lever"], 0.02 + delta, c["bias"], c["anchor"], rho, c["d"], 0.02)
    expected = _reference_range(c, c["s0"] + delta) + c["bias"] - rho
    # Delta extrapolation is second order: the jerk term (~|j| delta^3 / 6) stays far below 0.1 mm here.
    assert abs(e - expected) < 1e-4


def test_jacobians_match_finite_differences(case):
    c = case
    td0, td = 0.02, 0.027
    args = (c["R_k"], c["p_k"], c["v_k"], c["lever"], td, c["bias"])

    def f(R, p, v, lever, t_d, bias):
        return range_error(R, p, v, lever, t_d, bias, c["anchor"], 5.0, c["d"], td0)

    _, J_pose, J_vel, J_lever, J_td = range_error(
        *args, c["anchor"], 5.0, c["d"], td0, jacobians=True)
    h = 1e-6
    num_pose = np.empty(6)
    for i in range(6):
        dx = np.zeros(6)
        dx[i] = h
        Rp, pp = c["R_k"] @ so3_exp(dx[:3]), c["p_k"] + c["R_k"] @ dx[3:]
        dx[i] = -h
        Rm, pm = c["R_k"] @ so3_exp(dx[:3]), c["p_k"] + c["R_k"] @ dx[3:]
        num_pose[i] = (f(Rp, pp, *args[2:]) - f(Rm, pm, *args[2:])) / (2 * h)
    np.testing.assert_allclose(J_pose, num_pose, atol=1e-6)
    for J, slot in ((J_vel, 2), (J_lever, 3)):
        num = np.empty(3)
        for i in range(3):
            a_p, a_m = list(args), list(args)
            a_p[slot] = args[slot] + h * np.eye(3)[i]
            a_m[slot] = args[slot] - h * np.eye(3)[i]
            num[i] = (f(*a_p) - f(*a_m)) / (2 * h)
        np.testing.assert_allclose(J, num, atol=1e-6)
    num_td = (f(*args[:4], td + h, args[5]) - f(*args[:4], td - h, args[5])) / (2 * h)
    assert J_td == pytest.approx(num_td, abs=1e-5)


def test_gtsam_factor_wraps_the_residual(case):
    """The CustomFactor returns the same residual and a linearisation with the same Jacobians."""
    gtsam = pytest.importorskip("gtsam")
    from gtsam.symbol_shorthand import A, L, T, V, X

    c = case
    noise = gtsam.noiseModel.Isotropic.Sigma(1, 0.1)
    f = make_gtsam_factor([X(0), V(0), L(0), T(0), A(0)], c["anchor"], 5.0, c["d"], 0.02, noise)
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(gtsam.Rot3(c["R_k"]), c["p_k"]))
    vals.insert(V(0), c["v_k"])
    vals.insert(L(0), c["lever"])
    vals.insert(T(0), np.array([0.027]))
    vals.insert(A(0), np.array([c["bias"]]))
    e, Jp, Jv, Jl, Jt = range_error(c["R_k"], c["p_k"], c["v_k"], c["lever"], 0.027, c["bias"], c["anchor"], 5.0,
                                    c["d"], 0.02, jacobians=True)
    assert f.unwhitenedError(vals)[0] == pytest.approx(e, abs=1e-12)
    Ab, _b = f.linearize(vals).jacobian()
    np.testing.assert_allclose(Ab[0] * 0.1, np.concatenate([Jp, Jv, Jl, [Jt, 1.0]]), atol=1e-9)


def _reference_tdoa(c, s, anchor_a, anchor_b):
    """Reference TDoA at IMU time s (same integration as :func:`_reference_range`)."""
    ca = dict(c, anchor=anchor_a)
    cb = dict(c, anchor=anchor_b)
    return _reference_range(cb, s) - _reference_range(ca, s)


def test_tdoa_factor_matches_reference_and_finite_differences(case):
    """The TDoA factor: residual = reference TDoA (+ b_b - b_a - z) at IMU time s0 + delta, and its
    Jacobians (pose, velocity, lever arm, t_d, both biases) against central finite differences."""
    from uwbimu.calibration.tdoa_factor import tdoa_error

    c = case
    a, b = c["anchor"], np.array([-2.0, 3.0, 0.4])
    z = 0.7
    for delta in (0.0, 0.004):
        e = tdoa_error(c["R_k"], c["p_k"], c["v_k"], c["lever"], 0.02 + delta, 0.03, -0.05, a, b, z, c["d"], 0.02)
        assert abs(e - (_reference_tdoa(c, c["s0"] + delta, a, b) - 0.05 - 0.03 - z)) < 1e-4

    def f(x):
        R = c["R_k"] @ so3_exp(x[0:3])
        p = c["p_k"] + c["R_k"] @ x[3:6]
        return tdoa_error(R, p, c["v_k"] + x[6:9], c["lever"] + x[9:12], 0.02 + x[12], 0.03 + x[13], -0.05 + x[14],
                          a, b, z, c["d"], 0.02)

    _, Jp, Jv, Jl, Jt = tdoa_error(c["R_k"], c["p_k"], c["v_k"], c["lever"], 0.02, 0.03, -0.05, a, b, z, c["d"],
                                   0.02, jacobians=True)
    eps = 1e-6
    num = np.array([(f(np.eye(15)[i] * eps) - f(-np.eye(15)[i] * eps)) / (2 * eps) for i in range(15)])
    np.testing.assert_allclose(num[0:6], Jp, atol=1e-6)
    np.testing.assert_allclose(num[6:9], Jv, atol=1e-6)
    np.testing.assert_allclose(num[9:12], Jl, atol=1e-6)
    assert num[12] == pytest.approx(Jt, abs=1e-5)
    assert num[13] == pytest.approx(-1.0, abs=1e-9) and num[14] == pytest.approx(1.0, abs=1e-9)

def test_anchor_jacobian_matches_finite_differences(case):
    """Self-survey: d e / d p_anchor (world, m) against central differences of the residual."""
    c = case
    args = (c["R_k"], c["p_k"], c["v_k"], c["lever"], 0.027, c["bias"])
    res = range_error(*args, c["anchor"], 5.0, c["d"], 0.02, jacobians=True, with_anchor=True)
    assert len(res) == 6
    h = 1e-6
    num = np.array([(range_error(*args, c["anchor"] + h * np.eye(3)[i], 5.0, c["d"], 0.02)
                     - range_error(*args, c["anchor"] - h * np.eye(3)[i], 5.0, c["d"], 0.02)) / (2 * h)
                    for i in range(3)])
    np.testing.assert_allclose(res[5], num, atol=1e-7)
    # The other Jacobians are unchanged by the flag.
    for a, b in zip(res[1:5], range_error(*args, c["anchor"], 5.0, c["d"], 0.02, jacobians=True)[1:]):
        np.testing.assert_allclose(a, b)


def test_gtsam_factor_with_anchor_variable(case):
    """The CustomFactor with the anchor as a Point3 key: same residual, numerical Jacobian of the whole factor."""
    gtsam = pytest.importorskip("gtsam")
    from gtsam.symbol_shorthand import A, L, P, T, V, X

    c = case
    noise = gtsam.noiseModel.Isotropic.Sigma(1, 0.1)
    keys = [X(0), V(0), L(0), T(0), A(0), P(0)]
    f = make_gtsam_factor(keys, np.zeros(3), 5.0, c["d"], 0.02, noise, anchor_variable=True)
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(gtsam.Rot3(c["R_k"]), c["p_k"]))
    vals.insert(V(0), c["v_k"])
    vals.insert(L(0), c["lever"])
    vals.insert(T(0), np.array([0.027]))
    vals.insert(A(0), np.array([c["bias"]]))
    vals.insert(P(0), c["anchor"])
    e = range_error(c["R_k"], c["p_k"], c["v_k"], c["lever"], 0.027, c["bias"], c["anchor"], 5.0, c["d"], 0.02)
    assert f.unwhitenedError(vals)[0] == pytest.approx(e, abs=1e-12)
    Ab, _b = f.linearize(vals).jacobian()
    # Numerical Jacobian through GTSAM's own retraction of every key (pose on the manifold).
    h, num = 1e-6, []
    for k, dim in zip(keys, (6, 3, 3, 1, 1, 3)):
        for i in range(dim):
            dx = gtsam.VectorValues()
            for kk, dd in zip(keys, (6, 3, 3, 1, 1, 3)):
                dx.insert(kk, h * np.eye(dd)[i] if kk == k else np.zeros(dd))
            ep = f.unwhitenedError(vals.retract(dx))[0]
            dx2 = gtsam.VectorValues()
            for kk, dd in zip(keys, (6, 3, 3, 1, 1, 3)):
                dx2.insert(kk, -h * np.eye(dd)[i] if kk == k else np.zeros(dd))
            num.append((ep - f.unwhitenedError(vals.retract(dx2))[0]) / (2 * h))
    np.testing.assert_allclose(Ab[0] * 0.1, num, atol=1e-6)


def test_inter_anchor_factor_jacobians():
    from uwbimu.calibration.graph import pair_error

    rng = np.random.default_rng(3)
    pa, pb, h = rng.normal(size=3) * 3, rng.normal(size=3) * 3, 1e-6
    e, Ja, Jb = pair_error(pa, pb, 4.0, jacobians=True)
    assert e == pytest.approx(np.linalg.norm(pa - pb) - 4.0)
    for J, which in ((Ja, 0), (Jb, 1)):
        num = []
        for i in range(3):
            d = h * np.eye(3)[i]
            plus = pair_error(pa + d, pb, 4.0) if which == 0 else pair_error(pa, pb + d, 4.0)
            minus = pair_error(pa - d, pb, 4.0) if which == 0 else pair_error(pa, pb - d, 4.0)
            num.append((plus - minus) / (2 * h))
        np.testing.assert_allclose(J, num, atol=1e-8)


def _group_case(rng, n=7):
    """Several ranges after one keyframe (two anchors), their deltas and a GTSAM Values."""
    t, u = _imu(rng)
    b_a, b_g = np.array([0.05, -0.03, 0.02]), np.array([0.01, -0.02, 0.005])
    s0 = np.sort(rng.uniform(0.01, 0.18, n))
    _k, deltas = imu_deltas(t, u, b_a, b_g, np.array([0.0]), s0)
    anchors = np.array([[4.0, -1.0, 2.5], [-3.0, 2.0, 0.3]])
    col = np.arange(n) % 2
    rho = np.linalg.norm(anchors[col] - [1.0, 2.0, 1.5], axis=1) + rng.normal(0, 0.05, n)
    return deltas, anchors, col, rho


@pytest.mark.parametrize("td_fixed", [None, 0.031])
def test_group_factor_equals_the_per_range_factors(td_fixed):
    """The vectorised per-keyframe factor: same residuals as range_error, same whitened Jacobians and the same
    error (sum of Huber losses) as one Robust(Huber) CustomFactor per range, with an outlier among the rows."""
    gtsam = pytest.importorskip("gtsam")
    from gtsam.symbol_shorthand import A, L, T, V, X

    from uwbimu.calibration.range_factor import RangeGroup, make_gtsam_group_factor

    rng = np.random.default_rng(3)
    deltas, anchors, col, rho = _group_case(rng)
    sigma, k, td0 = 0.1, 1.345, 0.02
    R = so3_exp(np.array([0.2, -0.4, 1.1]))
    td = 0.027 if td_fixed is None else td_fixed
    state = (R, np.array([1.0, 2.0, 1.5]), np.array([0.4, -0.3, 0.2]), np.array([0.12, -0.08, 0.14]), td,
             np.array([0.03, -0.05]))
    # ranges consistent with the state up to 0.5 sigma, and one outlier (|z| > 6 > huber_k)
    rho = RangeGroup(deltas, anchors[col], np.zeros(len(col)), col, td0).evaluate(*state)
    rho += rng.uniform(-0.05, 0.05, len(rho))
    rho[3] += 0.6
    vals = gtsam.Values()
    vals.insert(X(0), gtsam.Pose3(gtsam.Rot3(R), np.array([1.0, 2.0, 1.5])))
    vals.insert(V(0), np.array([0.4, -0.3, 0.2]))
    vals.insert(L(0), np.array([0.12, -0.08, 0.14]))
    if td_fixed is None:
        vals.insert(T(0), np.array([0.027]))
    vals.insert(A(0), np.array([0.03]))
    vals.insert(A(1), np.array([-0.05]))
    tkey = [T(0)] if td_fixed is None else []
    grp = RangeGroup(deltas, anchors[col], rho, col, td0)
    fg = make_gtsam_group_factor([X(0), V(0), L(0)] + tkey + [A(0), A(1)], grp, sigma, k, td_fixed=td_fixed)
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(k),
                                           gtsam.noiseModel.Isotropic.Sigma(1, sigma))
    singles = [make_gtsam_factor([X(0), V(0), L(0)] + tkey + [A(int(c))], anchors[c], r, d, td0, noise,
                                 td_fixed=td_fixed) for d, c, r in zip(deltas, col, rho)]
    e = grp.evaluate(*state)
    assert np.sum(np.abs(e) / sigma > k) == 1
    np.testing.assert_allclose(e, [f.unwhitenedError(vals)[0] for f in singles], atol=1e-12)
    assert fg.error(vals) == pytest.approx(sum(f.error(vals) for f in singles), rel=1e-12)
    Ag, bg = fg.linearize(vals).jacobian()
    for i, f in enumerate(singles):
        A1, b1 = f.linearize(vals).jacobian()
        row = np.concatenate([A1[0][:-1], np.zeros(2)])
        row[len(row) - 2 + col[i]] = A1[0][-1]
        if i == 3:  # the outlier: same gradient J^T b, Gauss-Newton weight k/(2|z|-k) instead of k/|z|
            np.testing.assert_allclose(Ag[i] * bg[i], row * b1[0], rtol=1e-9)
            continue
        np.testing.assert_allclose(Ag[i], row, atol=1e-9)
        assert bg[i] == pytest.approx(b1[0], abs=1e-12)


def test_group_factor_jacobians_match_finite_differences():
    from uwbimu.calibration.range_factor import RangeGroup

    rng = np.random.default_rng(5)
    deltas, anchors, col, rho = _group_case(rng)
    grp = RangeGroup(deltas, anchors[col], rho, col, 0.02)
    R, p, v = so3_exp(np.array([0.3, 0.1, -0.7])), np.array([1.0, 2.0, 1.5]), np.array([0.4, -0.3, 0.2])
    lev, td, b = np.array([0.12, -0.08, 0.14]), 0.033, np.array([0.03, -0.05])
    _e, Jp, Jv, Jl, Jt = grp.evaluate(R, p, v, lev, td, b, jacobians=True)
    h = 1e-6
    for i in range(3):
        dx = np.zeros(3)
        dx[i] = h
        fd = (grp.evaluate(R @ so3_exp(dx), p, v, lev, td, b) - grp.evaluate(R @ so3_exp(-dx), p, v, lev, td, b)) / 2 / h
        np.testing.assert_allclose(Jp[:, i], fd, atol=1e-6)
        fd = (grp.evaluate(R, p + R @ dx, v, lev, td, b) - grp.evaluate(R, p - R @ dx, v, lev, td, b)) / 2 / h
        np.testing.assert_allclose(Jp[:, 3 + i], fd, atol=1e-6)
        fd = (grp.evaluate(R, p, v + dx, lev, td, b) - grp.evaluate(R, p, v - dx, lev, td, b)) / 2 / h
        np.testing.assert_allclose(Jv[:, i], fd, atol=1e-6)
        fd = (grp.evaluate(R, p, v, lev + dx, td, b) - grp.evaluate(R, p, v, lev - dx, td, b)) / 2 / h
        np.testing.assert_allclose(Jl[:, i], fd, atol=1e-6)
    fd = (grp.evaluate(R, p, v, lev, td + h, b) - grp.evaluate(R, p, v, lev, td - h, b)) / 2 / h
    np.testing.assert_allclose(Jt, fd, atol=1e-6)


def _three_keyframes(rng):
    """Nine rows after three keyframes (0, 0.06, 0.12 s), their deltas, three anchors and the keyframes' states."""
    t, u = _imu(rng)
    t_key = np.array([0.0, 0.06, 0.12])
    s0 = np.sort(rng.uniform(0.0, 0.19, 9))
    kk, deltas = imu_deltas(t, u, np.zeros(3), np.zeros(3), t_key, s0)
    anchors = np.array([[4.0, -1.0, 2.5], [-3.0, 2.0, 0.3], [0.5, 5.0, 2.8]])
    R = np.array([so3_exp(rng.normal(size=3) * 0.5) for _ in range(3)])
    P = np.array([[1.0, 2.0, 1.5]]) + 0.05 * np.arange(3)[:, None]
    Vv = np.array([[0.4, -0.3, 0.2]]) * (1 + 0.1 * np.arange(3))[:, None]
    return kk, deltas, anchors, R, P, Vv


def _three_keyframe_factor(grp, R, P, Vv, lev, td, b):
    """The group factor of ``grp`` on keys X0..2, V0..2, L0, T0, A0..2, a GTSAM Values at the given state, and the
    Robust(Huber 1.345, sd 0.1) noise of the equivalent per-row factors."""
    import gtsam
    from gtsam.symbol_shorthand import A, L, T, V, X

    from uwbimu.calibration.range_factor import make_gtsam_group_factor

    keys = [X(0), V(0), X(1), V(1), X(2), V(2), L(0), T(0), A(0), A(1), A(2)]
    fg = make_gtsam_group_factor(keys, grp, 0.1, 1.345)
    vals = gtsam.Values()
    for i in range(3):
        vals.insert(X(i), gtsam.Pose3(gtsam.Rot3(R[i]), P[i]))
        vals.insert(V(i), Vv[i])
        vals.insert(A(i), np.array([b[i]]))
    vals.insert(L(0), lev)
    vals.insert(T(0), np.array([td]))
    noise = gtsam.noiseModel.Robust.Create(gtsam.noiseModel.mEstimator.Huber.Create(1.345),
                                           gtsam.noiseModel.Isotropic.Sigma(1, 0.1))
    return fg, vals, noise


def test_group_factor_over_several_keyframes():
    """Rows attached to three keyframes in one factor: each row's pose/velocity Jacobian lands on its own
    keyframe's keys, and residuals, error and whitened Jacobians equal one factor per range."""
    pytest.importorskip("gtsam")
    from gtsam.symbol_shorthand import A, L, T, V, X

    from uwbimu.calibration.range_factor import RangeGroup

    rng = np.random.default_rng(11)
    kk, deltas, anchors, R, P, Vv = _three_keyframes(rng)
    col = np.arange(9) % 3
    lev, td, td0, b = np.array([0.12, -0.08, 0.14]), 0.027, 0.02, np.array([0.03, -0.05, 0.01])
    grp0 = RangeGroup(deltas, anchors[col], np.zeros(9), col, td0, kf=kk)
    rho = grp0.evaluate(np.array(R), np.array(P), np.array(Vv), lev, td, b) + rng.uniform(-0.05, 0.05, 9)
    grp = RangeGroup(deltas, anchors[col], rho, col, td0, kf=kk)
    fg, vals, noise = _three_keyframe_factor(grp, R, P, Vv, lev, td, b)
    singles = [make_gtsam_factor([X(int(k)), V(int(k)), L(0), T(0), A(int(c))], anchors[c], r, d, td0, noise)
               for k, d, c, r in zip(kk, deltas, col, rho)]
    assert fg.error(vals) == pytest.approx(sum(f.error(vals) for f in singles), rel=1e-12)
    Ag, _ = fg.linearize(vals).jacobian()
    dims = [6, 3] * 3 + [3, 1, 1, 1, 1]
    starts = np.concatenate([[0], np.cumsum(dims)])
    for i, f in enumerate(singles):
        A1, _ = f.linearize(vals).jacobian()
        row = np.zeros(Ag.shape[1])
        k, c = int(kk[i]), int(col[i])
        for blk, (lo, n) in enumerate([(starts[2 * k], 6), (starts[2 * k + 1], 3), (starts[6], 3), (starts[7], 1),
                                       (starts[8 + c], 1)]):
            row[lo:lo + n] = A1[0][[0, 6, 9, 12, 13][blk]:[0, 6, 9, 12, 13][blk] + n]
        np.testing.assert_allclose(Ag[i], row, atol=1e-9)
    assert set(kk) == {0, 1, 2}


def test_tdoa_group_equals_the_per_row_tdoa_factors():
    """The grouped TDoA rows (two range groups on the same deltas, signed bias matrix) over three keyframes:
    residuals and Jacobians equal tdoa_error row by row, and the GTSAM factor's error equals one Robust(Huber)
    TDoA CustomFactor per row."""
    pytest.importorskip("gtsam")
    from gtsam.symbol_shorthand import A, L, T, V, X

    from uwbimu.calibration.tdoa_factor import TdoaGroup, make_gtsam_tdoa_factor, tdoa_error

    rng = np.random.default_rng(13)
    kk, deltas, anchors, R, P, Vv = _three_keyframes(rng)
    ja, jb = np.arange(9) % 3, (np.arange(9) + 1) % 3
    lev, td, td0, b = np.array([0.12, -0.08, 0.14]), 0.027, 0.02, np.array([0.03, -0.05, 0.01])
    z = rng.uniform(-1.0, 1.0, 9)
    bmat = np.zeros((9, 3))
    bmat[np.arange(9), jb] += 1.0
    bmat[np.arange(9), ja] -= 1.0
    grp = TdoaGroup(deltas, anchors[ja], anchors[jb], z, bmat, td0, kf=kk)
    e, Jp, Jv, Jl, Jt = grp.evaluate(R, P, Vv, lev, td, b, jacobians=True)
    for i in range(9):
        k = kk[i]
        ref = tdoa_error(R[k], P[k], Vv[k], lev, td, b[ja[i]], b[jb[i]], anchors[ja[i]], anchors[jb[i]], z[i],
                         deltas[i], td0, jacobians=True)
        assert e[i] == pytest.approx(ref[0], abs=1e-12)
        for got, want in zip((Jp[i], Jv[i], Jl[i], Jt[i]), ref[1:]):
            np.testing.assert_allclose(got, want, atol=1e-10)
    fg, vals, noise = _three_keyframe_factor(grp, R, P, Vv, lev, td, b)
    singles = [make_gtsam_tdoa_factor([X(int(k)), V(int(k)), L(0), T(0), A(int(a)), A(int(c))], anchors[a], anchors[c],
                                      zz, d, td0, noise) for k, d, a, c, zz in zip(kk, deltas, ja, jb, z)]
    assert fg.error(vals) == pytest.approx(sum(f.error(vals) for f in singles), rel=1e-12)
