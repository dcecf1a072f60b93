"""Quaternion / SO(3) utilities against scipy.spatial.transform.Rotation."""

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from uwbimu.models import quaternion as Q

finite = st.floats(min_value=-10, max_value=10, allow_nan=False, allow_infinity=False)
quats = arrays(float, 4, elements=finite).filter(lambda q: np.linalg.norm(q) > 1e-3)
rotvecs = arrays(float, 3, elements=st.floats(min_value=-3.0, max_value=3.0, allow_nan=False))
vecs = arrays(float, 3, elements=finite)


def to_scipy(q):
    q = np.asarray(q)
    return Rotation.from_quat(q[..., [1, 2, 3, 0]])


def from_scipy(r):
    return Q.quat_normalize(r.as_quat()[..., [3, 0, 1, 2]])


@given(quats)
def test_rotmat_matches_scipy(q):
    qn = Q.quat_normalize(q)
    np.testing.assert_allclose(Q.quat_to_rotmat(qn), to_scipy(qn).as_matrix(), atol=1e-12)


@given(quats)
def test_rotmat_roundtrip(q):
    qn = Q.quat_normalize(q)
    back = Q.rotmat_to_quat(Q.quat_to_rotmat(qn))
    # q and -q are the same rotation; with qw = 0 the canonical sign is not unique.
    assert abs(np.dot(back, qn)) == pytest.approx(1.0, abs=1e-9)


@given(quats, quats)
def test_multiply_is_composition(p, q):
    p, q = Q.quat_normalize(p), Q.quat_normalize(q)
    expected = from_scipy(to_scipy(p) * to_scipy(q))
    np.testing.assert_allclose(Q.quat_normalize(Q.quat_multiply(p, q)), expected, atol=1e-9)
    np.testing.assert_allclose(
        Q.quat_to_rotmat(Q.quat_multiply(p, q)), Q.quat_to_rotmat(p) @ Q.quat_to_rotmat(q), atol=1e-12
    )


@given(rotvecs)
def test_exp_matches_scipy(phi):
    np.testing.assert_allclose(Q.so3_exp(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(Q.quat_normalize(Q.quat_exp(phi)), from_scipy(Rotation.from_rotvec(phi)), atol=1e-12)


@given(rotvecs)
def test_log_inverts_exp(phi):
    if np.linalg.norm(phi) >= np.pi - 1e-6:
        return  # log picks the angle in [0, pi]; the antipodal branch is ambiguous
    np.testing.assert_allclose(Q.quat_log(Q.quat_exp(phi)), phi, atol=1e-9)
    np.testing.assert_allclose(Q.so3_log(Q.so3_exp(phi)), phi, atol=1e-9)


@given(quats)
def test_log_matches_scipy(q):
    qn = Q.quat_normalize(q)
    phi = Q.quat_log(qn)
    assert np.linalg.norm(phi) <= np.pi + 1e-12
    if np.linalg.norm(phi) < np.pi - 1e-6:
        np.testing.assert_allclose(phi, to_scipy(qn).as_rotvec(), atol=1e-9)
    else:  # angle pi: phi and -phi are the same rotation
        np.testing.assert_allclose(Q.so3_exp(phi), to_scipy(qn).as_matrix(), atol=1e-9)


@given(vecs, vecs)
def test_skew_is_cross(a, b):
    np.testing.assert_allclose(Q.skew(a) @ b, np.cross(a, b), atol=1e-9)


@given(quats, vecs)
def test_rotate(q, v):
    qn = Q.quat_normalize(q)
    np.testing.assert_allclose(Q.quat_rotate(qn, v), to_scipy(qn).apply(v), atol=1e-9)


def test_batched_shapes():
    rng = np.random.default_rng(1)
    q = Q.quat_normalize(rng.normal(size=(5, 7, 4)))
    R = Q.quat_to_rotmat(q)
    assert R.shape == (5, 7, 3, 3)
    np.testing.assert_allclose(Q.rotmat_to_quat(R), q, atol=1e-9)
    phi = rng.normal(size=(11, 3))
    assert Q.quat_exp(phi).shape == (11, 4)
    assert Q.quat_log(Q.quat_exp(phi)).shape == (11, 3)


def test_small_angle_exp_is_smooth():
    phi = np.array([1e-12, -2e-12, 3e-12])
    np.testing.assert_allclose(Q.quat_exp(phi), [1.0, *(0.5 * phi)], atol=1e-15)
    np.testing.assert_allclose(Q.quat_log(Q.quat_exp(phi)), phi, atol=1e-20)


def test_omega_matrix_matches_quaternion_product():
    rng = np.random.default_rng(2)
    q = Q.quat_normalize(rng.normal(size=4))
    w = rng.normal(size=3)
    # q' = 0.5 q ⊗ [0, w] for a body rate w.
    np.testing.assert_allclose(Q.omega_matrix(w) @ q, Q.quat_multiply(q, np.r_[0.0, w]), atol=1e-12)


def test_slerp_endpoints_and_midpoint():
    q0 = Q.quat_exp(np.array([0.1, 0.2, -0.3]))
    q1 = Q.quat_exp(np.array([-0.4, 0.5, 0.2]))
    np.testing.assert_allclose(Q.quat_slerp(q0, q1, 0.0), q0, atol=1e-12)
    np.testing.assert_allclose(Q.quat_normalize(Q.quat_slerp(q0, q1, 1.0)), Q.quat_normalize(q1), atol=1e-12)
    mid = Q.quat_slerp(q0, q1, 0.5)
    d0 = Q.quat_log(Q.quat_multiply(Q.quat_conjugate(q0), mid))
    d1 = Q.quat_log(Q.quat_multiply(Q.quat_conjugate(mid), q1))
    np.testing.assert_allclose(d0, d1, atol=1e-12)


def test_zero_quaternion_refused():
    with pytest.raises(ValueError, match="zero quaternion"):
        Q.quat_normalize(np.zeros(4))


@given(quats)
def test_rotmat_to_quat_matches_scipy(q):
    R = to_scipy(Q.quat_normalize(q)).as_matrix()
    got = Q.rotmat_to_quat(R)
    expected = from_scipy(Rotation.from_matrix(R))
    # Same rotation up to the sign ambiguity at qw = 0.
    assert abs(np.dot(got, expected)) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose(Q.quat_to_rotmat(got), R, atol=1e-12)


@given(quats)
def test_so3_log_matches_scipy(q):
    R = to_scipy(Q.quat_normalize(q)).as_matrix()
    phi = Q.so3_log(R)
    if np.linalg.norm(phi) < np.pi - 1e-6:
        np.testing.assert_allclose(phi, Rotation.from_matrix(R).as_rotvec(), atol=1e-9)
    else:  # angle pi: phi and -phi are the same rotation
        np.testing.assert_allclose(Q.so3_exp(phi), R, atol=1e-9)


@given(rotvecs)
def test_skew_generates_scipy_rotation(phi):
    # Exp is the matrix exponential of the skew matrix: ties skew() to scipy's rotvec map.
    from scipy.linalg import expm

    np.testing.assert_allclose(expm(Q.skew(phi)), Rotation.from_rotvec(phi).as_matrix(), atol=1e-10)
    np.testing.assert_allclose(Q.skew(phi), -Q.skew(phi).T, atol=0)


@given(rotvecs, rotvecs)
def test_exp_compose_matches_scipy(a, b):
    composed = Q.quat_multiply(Q.quat_exp(a), Q.quat_exp(b))
    expected = Rotation.from_rotvec(a) * Rotation.from_rotvec(b)
    np.testing.assert_allclose(Q.quat_to_rotmat(composed), expected.as_matrix(), atol=1e-12)


@settings(max_examples=200)
@given(st.floats(min_value=0.0, max_value=1e-6), st.integers(min_value=0, max_value=2), st.booleans())
def test_log_is_warning_free_and_correct_near_pi(w, axis, flip):
    # Tiny scalar parts (angle ~ pi) used to overflow in the unused small-angle branch.
    import warnings

    q = np.zeros(4)
    q[0] = -w if flip else w
    q[1 + axis] = 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        phi = Q.quat_log(q)
        batch = Q.quat_log(np.stack([q, [1.0, 1e-12, 0.0, 0.0], [1e-310, 0.0, 1.0, 0.0]]))
    assert np.all(np.isfinite(phi))
    np.testing.assert_allclose(np.linalg.norm(phi), 2 * np.arctan2(1.0, w), atol=1e-12)
    np.testing.assert_allclose(Q.so3_exp(phi), to_scipy(q).as_matrix(), atol=1e-12)
    np.testing.assert_allclose(batch[0], phi, atol=0)
    np.testing.assert_allclose(batch[1], [2e-12, 0.0, 0.0], atol=1e-24)
    np.testing.assert_allclose(np.abs(batch[2]), [0.0, np.pi, 0.0], atol=1e-12)


def test_rotmat_to_quat_every_branch_batched():
    # Identity (w branch) and half-turns about x, y, z (x, y, z branches), plus scipy randoms, in one batch.
    rots = Rotation.concatenate([Rotation.identity(), Rotation.from_rotvec(np.pi * np.eye(3)),
                                 Rotation.from_rotvec(0.999 * np.pi * np.eye(3)), Rotation.random(51, random_state=3)])
    R = rots.as_matrix().reshape(2, 29, 3, 3)
    q = Q.rotmat_to_quat(R)
    assert q.shape == (2, 29, 4)
    expected = from_scipy(rots).reshape(2, 29, 4)
    np.testing.assert_allclose(np.abs(np.sum(q * expected, axis=-1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(Q.quat_to_rotmat(q), R, atol=1e-12)
