"""Per-window information: kernel pinned to the reference model, end-to-end on simulated logs."""

from __future__ import annotations

import numpy as np
import pytest

from uwbimu.models import reference as ref
from uwbimu.models import state as S
from uwbimu.models.quaternion import quat_to_rotmat
from uwbimu.observability.models import sample_uwb_imu_state
from uwbimu.observability.window import (
    WindowOptions,
    _window_information,
    range_jacobians,
    transition_matrix,
    window_observability,
)


def _state20(rng):
    x = np.r_[sample_uwb_imu_state(rng), 0.0]
    x[S.Q] *= np.sign(x[6])
    return x


def _imu_stream(rng, n, dt):
    t = np.arange(n) * dt
    ph = rng.uniform(0, 2 * np.pi, 6)
    fr = rng.uniform(0.3, 1.5, 6)
    amp = np.r_[2.0, 2.0, 2.0, 0.8, 0.8, 0.8]
    base = np.r_[0.0, 0.0, 9.81, 0.0, 0.0, 0.0]
    return t, base + amp * np.sin(2 * np.pi * fr * t[:, None] + ph)


def test_range_jacobian_matches_reference():
    rng = np.random.default_rng(0)
    for _ in range(5):
        x = _state20(rng)
        a = rng.uniform(-5, 5, 3)
        u = rng.normal(size=6)
        w = u[3:] - x[S.BG]
        R = quat_to_rotmat(x[S.Q])
        h, H = range_jacobians(x[None, 0:3], x[None, 3:6], R[None], w[None], x[S.PIU], a[None])
        assert h[0] == pytest.approx(ref.range_measurement(x, a), rel=1e-12)
        eps = 1e-6
        for j in range(18):
            dx = np.zeros(19)
            dx[j] = eps
            fd = (ref.range_measurement(S.boxplus(x, dx), a) - ref.range_measurement(S.boxplus(x, -dx), a)) / (2 * eps)
            assert H[0, j] == pytest.approx(fd, abs=1e-7), j
        # t_d column: the range observes the motion at IMU time t + t_d
        e = 1e-5
        fwd = ref.range_measurement(ref.propagate(x, u, u, e), a)
        bwd = ref.range_measurement(ref.propagate(x, u, u, -e), a)
        assert H[0, 18] == pytest.approx((fwd - bwd) / (2 * e), abs=1e-6)


def test_transition_matches_reference_propagation():
    rng = np.random.default_rng(1)
    dt, n = 1 / 200, 201
    t, u = _imu_stream(rng, n, dt)
    x0 = _state20(rng)
    X = ref.integrate_imu(x0, t, u)
    R = quat_to_rotmat(X[:, S.Q])
    Phi = transition_matrix(R, u[:, :3] - X[:, S.BA], u[:, 3:] - X[:, S.BG], np.r_[np.diff(t), 0.0])
    eps = 1e-5
    fd = np.zeros((19, 19))
    for j in range(19):
        dx = np.zeros(19)
        dx[j] = eps
        xp = ref.integrate_imu(S.boxplus(x0, dx), t, u)[-1]
        xm = ref.integrate_imu(S.boxplus(x0, -dx), t, u)[-1]
        fd[:, j] = (S.boxminus(xp, X[-1]) - S.boxminus(xm, X[-1])) / (2 * eps)
    # first-order discretisation of p, v (dt = 5 ms over 1 s): ~1 % of each block
    scale = np.abs(fd).max(axis=1, keepdims=True) + 1e-12
    assert np.abs(Phi - fd).max() / 1.0 < 0.05
    assert (np.abs(Phi - fd) / scale).max() < 0.02


def _window_case(rng, n, dt):
    """A noise-free IMU window along the reference integration, ranges every 4th sample."""
    t, u = _imu_stream(rng, n, dt)
    x0 = _state20(rng)
    x0[S.TD] = 0.0
    anchors = rng.uniform(-5, 5, (4, 3))
    X = ref.integrate_imu(x0, t, u)
    ridx = np.arange(0, n, 4)
    aidx = np.arange(len(ridx)) % 4
    R = quat_to_rotmat(X[:, S.Q])
    w = u[:, 3:] - X[:, S.BG]
    _, H = range_jacobians(X[ridx, 0:3], X[ridx, 3:6], R[ridx], w[ridx], x0[S.PIU], anchors[aidx])
    return t, u, x0, anchors, X, ridx, aidx, R, w, H


def test_information_matches_brute_force_fisher():
    """Noise-free IMU: the kernel's information equals J^T J / sigma^2 from the reference."""
    rng = np.random.default_rng(2)
    dt, n = 1 / 200, 201
    t, u, x0, anchors, X, ridx, aidx, R, w, H = _window_case(rng, n, dt)
    sigma = 0.05
    info = _window_information(
        R, u[:, :3] - X[:, S.BA], w, np.r_[np.diff(t), 0.0], ridx, H,
        np.full(len(ridx), sigma**2), np.zeros(15), False,
    )  # fmt: skip
    # brute force on the reference: ranges as a function of the initial error state
    def ranges(dx):
        x = S.boxplus(x0, dx)
        Xp = ref.integrate_imu(x, t, u)
        out = []
        for k, i in zip(ridx, aidx):
            xk = Xp[k]
            # t_d shifts the observed IMU time: first-order via the state's own rate
            xk = ref.propagate(xk, u[k], u[k], x[S.TD]) if x[S.TD] != 0 else xk
            out.append(ref.range_measurement(xk, anchors[i]))
        return np.array(out)

    eps = 1e-6
    J = np.column_stack([(ranges(np.eye(19)[j] * eps) - ranges(-np.eye(19)[j] * eps)) / (2 * eps) for j in range(19)])
    brute = J.T @ J / sigma**2
    d = np.sqrt(np.diag(brute))
    rel = np.abs(info - brute) / np.outer(d, d)
    assert rel.max() < 0.03


@pytest.fixture(scope="module")
def sim_logs():
    sim = pytest.importorskip("uwbimu.sim")
    out = {}
    for name in ("calibration-flight", "translation", "hover"):
        sc = sim.builtin_scenario(name).model_copy(update={"duration": 40.0})
        out[name] = sim.simulate(sc)
    return out


def test_calibration_flight_windows_are_well_conditioned(sim_logs):
    ds = sim_logs["calibration-flight"]
    table, meta = window_observability(ds, options=WindowOptions(window=20.0))
    assert list(table.columns[:5]) == ["t_start", "t_end", "min_eigenvalue", "condition_number", "weakest_direction"]
    assert [c for c in table.columns if c.startswith("sd_")] == [f"sd_{n}" for n in S.ERROR_STATE_NAMES]
    assert len(table) == 2
    sd = table[[f"sd_{n}" for n in S.ERROR_STATE_NAMES]].to_numpy()
    assert np.isfinite(sd).all() and (sd > 0).all()
    assert table["lever_arm_excited"].all() and table["time_offset_excited"].all()
    assert (table["n_ranges"] > 500).all()
    assert meta["ranges_unknown_anchor"] == 0
    # IMU noise can only raise the bound
    noiseless, _ = window_observability(ds, options=WindowOptions(window=20.0, include_imu_noise=False))
    assert (noiseless["sd_lx"].to_numpy() <= table["sd_lx"].to_numpy() + 1e-12).all()


def test_translation_does_not_excite_lever_arm(sim_logs):
    """Pure translation: the ranges add no lever-arm information beyond the position /
    lever-arm coupling of the priors (sd_l -> prior / sqrt(2) = 0.21 m), flags off."""
    ds = sim_logs["translation"]
    opts = WindowOptions(window=20.0)
    table, meta = window_observability(ds, options=opts)
    assert meta["bound"] == "pcrb" and meta["prior_sd"]["l"] == opts.prior_sd["l"]
    assert not table["lever_arm_excited"].any()
    lever = table[["sd_lx", "sd_ly", "sd_lz"]].to_numpy()
    assert (lever > 0.65 * opts.prior_sd["l"]).all()
    assert (table["condition_number"] > 1e9).all()  # information gained is nearly singular
    # the accelerations still excite the time offset (Theorem 1 via T2)
    assert table["time_offset_excited"].all()
    # the former Gramian (no prior) shows the same as an unbounded lever arm
    gram, _ = window_observability(ds, options=WindowOptions(window=20.0, bound="gramian"))
    assert np.isinf(gram[["sd_lx", "sd_ly", "sd_lz"]].to_numpy()).all()
    assert all("lever-arm" in w for w in gram["weakest_direction"])


def test_hover_does_not_excite_the_lever_arm(sim_logs):
    """Near-hover (weak rates): the lever-arm bound stays above half its prior (flag off);
    the flags follow the information gained relative to the prior."""
    ds = sim_logs["hover"]
    opts = WindowOptions(window=20.0)
    table, _ = window_observability(ds, options=opts)
    assert len(table) == 2
    assert not table["lever_arm_excited"].any()
    lever_sd = table[["sd_lx", "sd_ly", "sd_lz"]].to_numpy().max(axis=1)
    assert (lever_sd > opts.excited_sd_ratio * opts.prior_sd["l"]).all()
    ratio = table["sd_time_offset"] / opts.prior_sd["time_offset"]
    assert (table["time_offset_excited"] == (ratio <= opts.excited_sd_ratio)).all()
    # the calibration flight gains far more: its lever-arm bound is < 1/4 of the hover's
    cal, _ = window_observability(sim_logs["calibration-flight"], options=opts)
    assert (cal[["sd_lx", "sd_ly", "sd_lz"]].to_numpy().max(axis=1) < 0.25 * lever_sd).all()


# --------------------------------------------------------------------------
# issue 16 item 1: posterior Cramer-Rao bound
# --------------------------------------------------------------------------
def test_pcrb_recursion_matches_independent_batch_conditioning():
    """The kernel's information recursion (covariance form) equals the batch Gaussian
    conditioning of the stacked states on all ranges, built independently: transitions by
    finite differences of ``reference.propagate``, process noise w_k ~ N(0, diag(q) dt)."""
    from uwbimu.observability.window import DEFAULT_PRIOR_SD, _scale_vector, _window_pcrb

    rng = np.random.default_rng(5)
    dt, n = 1 / 200, 101
    t, u, x0, anchors, X, ridx, aidx, R, w, H = _window_case(rng, n, dt)
    sigma = 0.05
    q = np.r_[np.zeros(3), np.full(3, 2.0**2), np.full(3, 0.2**2), np.full(3, 0.05**2), np.full(3, 5e-3**2)]
    P0 = np.diag(_scale_vector(DEFAULT_PRIOR_SD) ** 2)
    args = (R, u[:, :3] - X[:, S.BA], w, np.r_[np.diff(t), 0.0], ridx, H, np.full(len(ridx), sigma**2))
    P_end, _ = _window_pcrb(*args, q, P0)

    # independent: F_k by central differences of the reference propagation (error-state boxplus)
    eps = 1e-6
    F = []
    for k in range(n - 1):
        base = ref.propagate(X[k], u[k], u[k], dt)
        cols = []
        for j in range(19):
            e = np.eye(19)[j] * eps
            up = ref.propagate(S.boxplus(X[k], e), u[k], u[k], dt)
            dn = ref.propagate(S.boxplus(X[k], -e), u[k], u[k], dt)
            cols.append((S.boxminus(up, base) - S.boxminus(dn, base)) / (2 * eps))
        F.append(np.column_stack(cols))
    # x_k = Phi_k x_0 + sum_i Phi_{k,i+1} w_i: covariance of the stacked (x_{ridx}, x_{n-1})
    Phi = [np.eye(19)]
    for k in range(n - 1):
        Phi.append(F[k] @ Phi[-1])
    G = np.zeros((n, 19, 19 * (n - 1)))  # d x_k / d w_i
    for k in range(1, n):
        G[k] = F[k - 1] @ G[k - 1]
        G[k][:, 19 * (k - 1) : 19 * k] += np.eye(19)
    Qw = np.kron(np.eye(n - 1), np.diag(np.r_[q, np.zeros(4)]) * dt)
    idx = list(ridx) + [n - 1]
    A = np.vstack([Phi[k] for k in idx])
    B = np.vstack([G[k] for k in idx])
    C = A @ P0 @ A.T + B @ Qw @ B.T
    Hs = np.zeros((len(ridx), 19 * len(idx)))
    for m in range(len(ridx)):
        Hs[m, 19 * m : 19 * m + 19] = H[m]
    last = slice(19 * len(ridx), 19 * len(idx))
    Czz = Hs @ C @ Hs.T + sigma**2 * np.eye(len(ridx))
    Cxz = C[last] @ Hs.T
    P_batch = C[last, last] - Cxz @ np.linalg.solve(Czz, Cxz.T)
    sd_k, sd_b = np.sqrt(np.diag(P_end)), np.sqrt(np.diag(P_batch))
    assert np.abs(sd_k / sd_b - 1).max() < 0.03
    # the process noise matters here: without it the bound is clearly tighter
    P_nf, _ = _window_pcrb(*args, np.zeros(15), P0)
    assert (np.sqrt(np.diag(P_nf)) / sd_b).min() < 0.8


@pytest.fixture(scope="module")
def matched_eskf():
    sim = pytest.importorskip("uwbimu.sim")
    from uwbimu.estimation import run_eskf
    from uwbimu.estimation.options import EskfOptions

    ds = sim.simulate(sim.builtin_scenario("calibration-flight").model_copy(update={"duration": 30.0}))
    # the plain filter (no rotation gate, no robust loss, no supervisor), same noise as the data
    opts = EskfOptions.model_validate({"lever_arm": {"min_rotation_rate": 0.0}, "gating": {"probability": 1.0, "robust": "none"},
                                       "supervisor": {"enabled": False}})  # fmt: skip
    return ds, run_eskf(ds, opts)


def test_pcrb_agrees_with_the_matched_eskf_sigma(matched_eskf):
    """Whole-log PCRB from the filter's own covariance at its first output vs the filter's final
    sigma: within 5 % for the lever arm and the time offset (issue 16 item 1)."""
    from uwbimu.observability.window import posterior_crb

    ds, res = matched_eskf
    P_end, _ = posterior_crb(ds, t_start=float(res.t_imu[0]), prior_cov=res.covariances[0])
    sd_b, sd_e = np.sqrt(np.diag(P_end)), res.sd[-1]
    for i in (15, 16, 17, 18):
        assert sd_e[i] == pytest.approx(sd_b[i], rel=0.05), S.ERROR_STATE_NAMES[i]


def test_chained_windows_end_at_the_filter_sigma_and_flag_excitation(matched_eskf):
    """Chained per-window PCRB (5 s windows along the filter's own trajectory): the last
    window's bound is the filter's final sigma (the report's observability and calibration
    sections agree), and every window of the excited flight is flagged as exciting."""
    from uwbimu.observability.window import trajectory_from_result

    ds, res = matched_eskf
    table, meta = window_observability(ds, trajectory_from_result(res), WindowOptions(window=5.0))
    assert meta["chain"] is True
    last = table.iloc[-1]
    for i, n in enumerate(("lx", "ly", "lz")):
        assert last[f"sd_{n}"] == pytest.approx(res.calibration["lever_arm_sd"][i], rel=0.1), n
    assert last["sd_time_offset"] == pytest.approx(res.calibration["time_offset_sd"], rel=0.1)
    assert table["lever_arm_excited"].all() and table["time_offset_excited"].all()
    assert (table["lever_arm_info_gain"] >= 3).all()
    # the bound only shrinks along the chain
    assert (np.diff(table["sd_lx"].to_numpy()) < 1e-12).all()
