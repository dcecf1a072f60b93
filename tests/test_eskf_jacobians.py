"""Pin the ESKF kernels to the reference model (uwbimu.models.reference) by finite differences."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.estimation import kernels as K
from uwbimu.estimation.jacobians import error_F, error_G, van_loan
from uwbimu.models import reference as ref
from uwbimu.models.quaternion import quat_exp, quat_normalize
from uwbimu.models.state import StateLayout, boxminus, boxplus


def _rand_state(rng, nb=0):
    x = np.zeros(20 + nb)
    x[0:3] = rng.uniform(-3, 3, 3)
    x[3:6] = rng.normal(0, 1, 3)
    x[6:10] = quat_normalize(rng.normal(size=4))
    x[10:13] = rng.normal(0, 0.1, 3)
    x[13:16] = rng.normal(0, 0.02, 3)
    x[16:19] = rng.normal(0, 0.2, 3)
    x[19] = rng.normal(0, 0.05)
    x[20:] = rng.normal(0, 0.1, nb)
    return x


def _rand_u(rng):
    return np.concatenate([rng.normal(0, 2, 3) + [0, 0, 9.81], rng.normal(0, 1, 3)])


def _phi_dense(x, u, dt):
    B = np.empty((7, 3, 3))
    K.phi_blocks(x, u, dt, B)
    Phi = np.eye(19)
    for i in range(19):
        col = np.zeros(19)
        col[i] = 1.0
        K._phi_vec(B, dt, col)
        Phi[:, i] = col
    return Phi


def test_gravity_constant_matches_reference():
    assert K.GRAVITY == ref.GRAVITY


@pytest.mark.parametrize("dt", [0.005, -0.004, 0.2])
def test_rk4_kernel_matches_reference_propagate(dt):
    rng = np.random.default_rng(1)
    for _ in range(5):
        x = _rand_state(rng, nb=2)
        u0, u1 = _rand_u(rng), _rand_u(rng)
        out = np.empty_like(x)
        K.rk4_step(x, u0, u1, dt, out)
        expect = ref.propagate(x[:20], u0, u1, dt)
        np.testing.assert_allclose(out[:20], expect, rtol=0, atol=1e-12)
        np.testing.assert_array_equal(out[20:], x[20:])


def test_rk4_with_mid_input_and_cubic_match_reference():
    rng = np.random.default_rng(13)
    t = np.cumsum(rng.uniform(0.004, 0.006, 12))
    u = rng.normal(size=(12, 6))
    um = ref.midpoint_inputs(t, u)
    for i in (0, 5, 10):
        out = np.empty(6)
        K.cubic_at(t, u, i, 0.5 * (t[i] + t[i + 1]), out)
        np.testing.assert_allclose(out, um[i], atol=1e-12)
        K.cubic_at(t, u, i, t[i], out)  # the cubic passes through the samples
        np.testing.assert_allclose(out, u[i], atol=1e-12)
    x = _rand_state(rng)
    out = np.empty_like(x)
    K.rk4_step_mid(x, u[3], um[3], u[4], t[4] - t[3], out)
    np.testing.assert_allclose(out, ref.propagate(x, u[3], u[4], t[4] - t[3], um=um[3]), atol=1e-12)


def test_derivative_kernel_matches_continuous_dynamics():
    rng = np.random.default_rng(2)
    x = _rand_state(rng)
    u = _rand_u(rng)
    out = np.empty(10)
    K._deriv(x, u, out)
    np.testing.assert_allclose(out, ref.continuous_dynamics(x, u)[:10], atol=1e-13)


def test_propagate_interval_substeps_match_reference_chain():
    rng = np.random.default_rng(3)
    x = _rand_state(rng)
    u0, u1 = _rand_u(rng), _rand_u(rng)
    out = np.empty_like(x)
    K.propagate_interval(x, u0, u1, 0.5, 0.1, out)
    xr = x.copy()
    for s in range(5):
        ua = u0 + s / 5 * (u1 - u0)
        ub = u0 + (s + 1) / 5 * (u1 - u0)
        xr = ref.propagate(xr, ua, ub, 0.1)
    np.testing.assert_allclose(out, xr, atol=1e-12)


def test_continuous_F_matches_finite_differences_of_reference():
    """F from jacobians.error_F against d/dt of the error between perturbed reference flows."""
    rng = np.random.default_rng(4)
    x = _rand_state(rng)
    u = _rand_u(rng)
    F = error_F(x, u)
    h = 1e-4  # short flow so that (Phi - I)/h -> F; error O(h)
    eps = 1e-6
    Ffd = np.zeros((19, 19))
    x1 = ref.propagate(x, u, u, h)
    for i in range(19):
        e = np.zeros(19)
        e[i] = eps
        xp = ref.propagate(boxplus(x, e), u, u, h)
        xm = ref.propagate(boxplus(x, -e), u, u, h)
        col = (boxminus(xp, x1) - boxminus(xm, x1)) / (2 * eps)
        Ffd[:, i] = (col - np.eye(19)[:, i]) / h
    np.testing.assert_allclose(Ffd, F, atol=5e-3 * max(1.0, np.abs(F).max()))


@pytest.mark.parametrize("dt", [0.005, 0.02])
def test_transition_kernel_matches_reference_and_expm(dt):
    """Block-sparse Phi against finite differences of reference.propagate and against expm(F dt)."""
    rng = np.random.default_rng(5)
    x = _rand_state(rng)
    u = _rand_u(rng)
    Phi = _phi_dense(x, u, dt)
    Phi_exact, _ = van_loan(error_F(x, u), error_G(x), np.eye(12), dt)
    # second-order series: error O((|F| dt)^3)
    scale = (np.abs(error_F(x, u)).max() * dt) ** 3
    np.testing.assert_allclose(Phi, Phi_exact, atol=10 * scale + 1e-12)
    eps = 1e-6
    x1 = ref.propagate(x, u, u, dt)
    Pfd = np.zeros((19, 19))
    for i in range(19):
        e = np.zeros(19)
        e[i] = eps
        Pfd[:, i] = (boxminus(ref.propagate(boxplus(x, e), u, u, dt), x1)
                     - boxminus(ref.propagate(boxplus(x, -e), u, u, dt), x1)) / (2 * eps)
    np.testing.assert_allclose(Phi, Pfd, atol=10 * scale + 1e-6)


def test_noise_jacobian_G_matches_input_finite_differences():
    """A constant input perturbation of the IMU reading acts as -G n over the step (first order)."""
    rng = np.random.default_rng(6)
    x = _rand_state(rng)
    u = _rand_u(rng)
    dt = 1e-3
    G = error_G(x)
    eps = 1e-5
    x1 = ref.propagate(x, u, u, dt)
    for i in range(6):
        du = np.zeros(6)
        du[i] = eps
        col = (boxminus(ref.propagate(x, u + du, u + du, dt), x1)
               - boxminus(ref.propagate(x, u - du, u - du, dt), x1)) / (2 * eps)
        # the reading is a_m = a + n_a: increasing the reading is like a noise of -eps
        np.testing.assert_allclose(col[3:9], -G[3:9, i] * dt, atol=5e-3 * dt)
    # bias random walks enter the bias states directly
    np.testing.assert_array_equal(G[9:15, 6:12], np.eye(6))


def test_cov_step_equals_dense_phi_p_phit_plus_vanloan_q():
    rng = np.random.default_rng(7)
    nb = 3
    N = 19 + nb
    x = _rand_state(rng, nb)
    u = _rand_u(rng)
    A = rng.normal(size=(N, N))
    P = A @ A.T / N
    dt = 0.002
    s = np.array([2e-3, 3e-4, 3e-4, 2e-5, 1e-3, 1e-4])  # densities
    noise = s**2
    P1 = P.copy()
    K.cov_step(P1, x, u, dt, noise)
    Phi = np.eye(N)
    Phi[:19, :19] = _phi_dense(x, u, dt)
    Qc = np.diag(np.concatenate([np.full(3, noise[0]), np.full(3, noise[1]), np.full(3, noise[2]),
                                 np.full(3, noise[3])]))
    F = error_F(x, u, N)
    _, Qd = van_loan(F, error_G(x, N), Qc, dt)
    Qd[15:18, 15:18] += np.eye(3) * noise[4] * dt
    Qd[18, 18] += noise[5] * dt
    expect = Phi @ P @ Phi.T + Qd
    # Q keeps the leading term of each block; neglected terms are O(dt^2 s^2)
    np.testing.assert_allclose(P1, expect, atol=1e-9, rtol=1e-6)
    np.testing.assert_allclose(P1, P1.T, atol=1e-15)


def _imu_stream(rng, n=40, dt=0.005):
    t = np.arange(n) * dt + 10.0
    base = _rand_u(rng)
    u = base + 0.3 * np.sin(np.outer(t, np.ones(6)) * 3.0 + rng.uniform(0, 6, 6))
    return t, u


def _cubic(t, u, i, tt):
    """Cubic through the 4 samples around interval i (numpy polyfit, independent of the kernel)."""
    f = min(max(i - 1, 0), len(t) - 4)
    return np.array([np.polyval(np.polyfit(t[f:f + 4] - t[i], u[f:f + 4, c], 3), tt - t[i]) for c in range(6)])


def _ref_state_at(x_k, t, u, k, tau):
    """State at ``tau <= t[k]`` with reference.propagate only (backward over the samples,
    cubic mid-interval inputs of reference.midpoint_inputs)."""
    x = x_k.copy()
    j = k
    if tau > t[k]:  # past the newest sample: held input (as the kernel does)
        return ref.propagate(x, u[k], u[k], tau - t[k])
    um = ref.midpoint_inputs(t, u)
    while j > 0 and t[j - 1] >= tau:
        x = ref.propagate(x, u[j], u[j - 1], t[j - 1] - t[j], um=um[j - 1])
        j -= 1
    if tau < t[j]:
        ut = _cubic(t, u, j - 1, tau)
        x = ref.propagate(x, u[j], ut, tau - t[j], um=_cubic(t, u, j - 1, 0.5 * (tau + t[j])))
    return x


def test_state_at_matches_reference_backward_integration():
    rng = np.random.default_rng(8)
    t, u = _imu_stream(rng)
    x = _rand_state(rng)
    k = 30
    for tau in (t[k], t[k] - 0.0013, t[k] - 0.0371, t[k - 7]):
        xt = np.empty_like(x)
        ut = np.empty(6)
        assert K.state_at(x, t, u, ref.midpoint_inputs(t, u), k, tau, 0.0, xt, ut) == K.UPD_OK
        np.testing.assert_allclose(xt, _ref_state_at(x, t, u, k, tau), atol=1e-12)
    um = ref.midpoint_inputs(t, u)
    assert K.state_at(x, t, u, um, k, t[0] - 1.0, 0.0, np.empty_like(x), np.empty(6)) == K.UPD_BEFORE_IMU


@pytest.mark.parametrize("lag_samples", [0.0, 0.6, 3.4])
def test_range_jacobian_all_blocks_against_reference(lag_samples):
    """H w.r.t. every error component (p, v, theta, b_a, b_g, p_IU, t_d, bias) at filter time.

    The predicted range as a function of the error state at filter time t_k is
    computed with reference functions only: x_k ⊞ dx, integrated backward with
    reference.propagate to tau = t_uwb + t_d, then reference.range_measurement.
    """
    rng = np.random.default_rng(9)
    t, u = _imu_stream(rng)
    nb = 2
    x = _rand_state(rng, nb)
    anchor = np.array([4.0, -3.0, 2.5])
    k = 30
    dt = t[1] - t[0]
    t_uwb = t[k] - lag_samples * dt - x[19]  # so that tau lies lag_samples periods before t_k

    def h_ref(dx):
        xx = np.concatenate([boxplus(x[:20], dx[:19]), x[20:] + dx[19:]])
        tau = t_uwb + xx[19]
        xs = _ref_state_at(xx[:20], t, u, k, tau)
        return ref.range_measurement(xs, anchor) + xx[20 + 1]

    tau = t_uwb + x[19]
    xt = np.empty_like(x)
    ut = np.empty(6)
    K.state_at(x, t, u, ref.midpoint_inputs(t, u), k, tau, 0.0, xt, ut)
    h = np.empty(19 + nb)
    pred = K.range_jacobian(xt, ut, anchor, 19 + 1, t[k] - tau, h)
    assert pred == pytest.approx(h_ref(np.zeros(19 + nb)), abs=1e-12)
    eps = 1e-6
    Hfd = np.array([(h_ref(eps * e) - h_ref(-eps * e)) / (2 * eps) for e in np.eye(19 + nb)])
    delta = t[k] - tau
    # blocks exact at tau (p, p_IU, t_d, bias) and the first-order time mapping (error O(delta^2))
    tol = 1e-6 + 20.0 * delta**2  # |F|^2 delta^2 with |w| ~ 3 rad/s
    np.testing.assert_allclose(h, Hfd, atol=tol)
    assert h[19] == 0.0 and h[20] == 1.0


def test_range_update_joseph_with_consider_mask():
    rng = np.random.default_rng(10)
    t, u = _imu_stream(rng)
    x = _rand_state(rng)
    N = 19
    A = rng.normal(size=(N, N))
    P = A @ A.T / N * 0.01
    k = 30
    anchor = np.array([3.0, 2.0, 1.0])
    tau = t[k] - 0.002
    xt = np.empty_like(x)
    ut = np.empty(6)
    K.state_at(x, t, u, ref.midpoint_inputs(t, u), k, tau, 0.0, xt, ut)
    h = np.empty(N)
    pred = K.range_jacobian(xt, ut, anchor, -1, t[k] - tau, h)
    z = pred + 0.05
    mask = np.ones(N)
    mask[15:19] = 0.0  # lever arm and t_d as consider parameters
    x1 = x.copy()
    P1 = P.copy()
    out = np.empty(7)
    r_var = 0.05**2
    K.range_update(x1, P1, t, u, ref.midpoint_inputs(t, u), k, tau, anchor, -1, z, r_var, -1.0, False,
                   K.ROBUST_NONE, 1.0, mask, 0.0, out)
    S = h @ P @ h + r_var
    Kg = P @ h / S * mask
    I_KH = np.eye(N) - np.outer(Kg, h)
    expect = I_KH @ P @ I_KH.T + np.outer(Kg, Kg) * r_var
    np.testing.assert_allclose(P1, expect, atol=1e-12)
    assert out[3] == 1.0 and out[2] == pytest.approx(0.05**2 / S)
    # consider parameters are not corrected, their covariance is unchanged
    np.testing.assert_array_equal(x1[16:20], x[16:20])
    np.testing.assert_allclose(P1[15:19, 15:19], P[15:19, 15:19], atol=1e-15)
    # the corrected state is x ⊞ K r
    np.testing.assert_allclose(boxminus(x1, x), Kg * 0.05, atol=1e-12)


def test_gate_rejects_and_force_accepts():
    rng = np.random.default_rng(11)
    t, u = _imu_stream(rng)
    x = _rand_state(rng)
    P = np.eye(19) * 1e-4
    anchor = np.array([3.0, 2.0, 1.0])
    out = np.empty(7)
    x1, P1 = x.copy(), P.copy()
    K.range_update(x1, P1, t, u, ref.midpoint_inputs(t, u), 30, t[30], anchor, -1, 100.0, 0.01, 10.0, False,
                   K.ROBUST_HUBER, 2.5,
                   np.ones(19), 0.0, out)
    assert out[3] == 0.0 and out[2] > 10.0
    np.testing.assert_array_equal(x1, x)
    K.range_update(x1, P1, t, u, ref.midpoint_inputs(t, u), 30, t[30], anchor, -1, 100.0, 0.01, 10.0, True,
                   K.ROBUST_HUBER, 2.5,
                   np.ones(19), 0.0, out)
    assert out[3] == 1.0 and 0 < out[4] < 0.1  # accepted with a small Huber weight
    assert np.all(np.linalg.eigvalsh(P1) > 0)


def test_inject_matches_boxplus():
    rng = np.random.default_rng(12)
    x = _rand_state(rng, 2)
    dx = rng.normal(0, 0.1, 21)
    x1 = x.copy()
    K.inject(x1, dx)
    np.testing.assert_allclose(x1[:20], boxplus(x[:20], dx[:19]), atol=1e-14)
    np.testing.assert_allclose(x1[20:], x[20:] + dx[19:], atol=1e-15)
    assert quat_exp(np.zeros(3))[0] == 1.0


def test_cov_step_gauss_markov_anchor_biases_match_dense_transition():
    """Range biases as first-order Gauss-Markov processes: Phi_bb = exp(-dt/tau) I and
    Q_bb = var (1 - exp(-2 dt/tau)) on top of the constant-bias step; the nominal mean decays alike."""
    rng = np.random.default_rng(11)
    nb = 3
    N = 19 + nb
    x = _rand_state(rng, nb)
    u = _rand_u(rng)
    A = rng.normal(size=(N, N))
    P = A @ A.T / N
    dt, var_b, tau = 0.01, 0.1**2, 2.0
    s = np.array([2e-3, 3e-4, 3e-4, 2e-5, 1e-3, 1e-4])
    P_const = P.copy()
    K.cov_step(P_const, x, u, dt, s**2)  # constant biases (6-entry noise vector)
    P_gm = P.copy()
    # the declared blocks' tables: anchor biases Gauss-Markov (var_b, 1 / tau), lever and t_d random walks
    pn = StateLayout(nb).process_noise(s[:4] ** 2, {"lever": (s[4] ** 2, 0.0), "t_d": (s[5] ** 2, 0.0),
                                                     "anchor_bias": (var_b, 1.0 / tau)})
    K.cov_step_blocks(P_gm, x, u, dt, pn)
    f = np.exp(-dt / tau)
    D = np.diag(np.r_[np.ones(19), np.full(nb, f)])
    expect = D @ P_const @ D
    expect[19:, 19:] += np.eye(nb) * var_b * (1 - f**2)
    np.testing.assert_allclose(P_gm, expect, rtol=1e-12, atol=1e-15)
    xb = x.copy()
    K.decay_biases(xb, dt, pn)
    np.testing.assert_allclose(xb[20:], x[20:] * f)
    np.testing.assert_array_equal(xb[:20], x[:20])
    xc = x.copy()
    pn_const = StateLayout(nb).process_noise(s[:4] ** 2, {"lever": (s[4] ** 2, 0.0), "t_d": (s[5] ** 2, 0.0),
                                                           "anchor_bias": (var_b, 0.0)})
    K.decay_biases(xc, dt, pn_const)  # constant biases (1 / tau = 0): untouched
    np.testing.assert_array_equal(xc, x)
