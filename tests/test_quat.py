"""The quaternion convention, pinned before anything builds on it."""

import numpy as np
import pytest
from numdiff import numerical_jacobian
from scipy.spatial.transform import Rotation

from swarmcore import quat


@pytest.fixture
def rng():
    return np.random.default_rng(42)


def test_attitude_matrix_is_transpose_of_scipy_active_rotation(rng):
    # scipy is scalar-last too, but as_matrix() is the ACTIVE rotation R = T(q)ᵀ.
    q = quat.random_quaternion(rng, 50)
    T = quat.attitude_matrix(q)
    R = Rotation.from_quat(q).as_matrix()
    np.testing.assert_allclose(T, np.swapaxes(R, -1, -2), atol=1e-14)


def test_composition_order_matches_matrices_and_is_reversed_in_scipy(rng):
    qa, qb = quat.random_quaternion(rng, (2, 30))
    T_ab = quat.attitude_matrix(quat.qmul(qa, qb))
    np.testing.assert_allclose(T_ab, quat.attitude_matrix(qa) @ quat.attitude_matrix(qb), atol=1e-13)
    # qa ⊗ qb here is Rotation(qb) * Rotation(qa) there (Hamilton product, active sense).
    sc = (Rotation.from_quat(qb) * Rotation.from_quat(qa)).as_quat()
    np.testing.assert_allclose(quat.normalize(sc), quat.normalize(quat.qmul(qa, qb)), atol=1e-13)


def test_scalar_last_and_small_rotation_about_z():
    # 90° about z: T maps I coordinates into a frame turned +90° about z, so x_I → −y_B.
    q = np.array([0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    T = quat.attitude_matrix(q)
    np.testing.assert_allclose(T @ [1.0, 0, 0], [0, -1.0, 0], atol=1e-15)
    a = np.array([1e-4, -2e-4, 3e-4])
    np.testing.assert_allclose(quat.attitude_matrix(quat.dq_from_err(a)), np.eye(3) - quat.skew(a), atol=1e-7)


def test_retract_and_local_are_inverses(rng):
    q_hat = quat.random_quaternion(rng, 40)
    a = rng.normal(0, 0.5, (40, 3))
    q = quat.retract(q_hat, a)
    np.testing.assert_allclose(quat.local(q, q_hat), a, atol=1e-12)
    # The error lives in the "to" frame: q = δq(a) ⊗ q̂.
    np.testing.assert_allclose(
        quat.attitude_matrix(q), quat.attitude_matrix(quat.dq_from_err(a)) @ quat.attitude_matrix(q_hat), atol=1e-12
    )


def test_rotvec_roundtrip_and_conjugate(rng):
    th = rng.normal(0, 1.0, (20, 3))
    q = quat.rotvec_to_quat(th)
    np.testing.assert_allclose(quat.quat_to_rotvec(q), th, atol=1e-12)
    np.testing.assert_allclose(quat.qmul(q, quat.qconj(q)), np.tile(quat.IDENTITY, (20, 1)), atol=1e-14)
    # Tiny angles take the series branch.
    np.testing.assert_allclose(quat.rotvec_to_quat(np.array([1e-10, 0, 0]))[:3], [5e-11, 0, 0], rtol=1e-9)


def test_kinematics_sign_constant_rate_step_matches_integration():
    # q̇ = ½ [ω; 0] ⊗ q integrated with many tiny steps equals the closed-form step.
    q0 = quat.normalize(np.array([0.1, -0.3, 0.2, 0.9]))
    w = np.array([0.3, -0.2, 0.5])
    dt = 2.0
    q = q0.copy()
    h = dt / 20000
    for _ in range(20000):
        q = q + h * 0.5 * quat.qmul(np.r_[w, 0.0], q)
        q = q / np.linalg.norm(q)
    np.testing.assert_allclose(quat.normalize(q), quat.propagate_constant_rate(q0, w, dt), atol=1e-6)
    # And the body frame turns by +ω: a vector fixed in I seen from B turns by −ω,
    # d/dt (T(q(t)) v_I) = −ω × T(q) v_I (central differences in time).
    v_I = np.array([0.3, 1.0, -0.5])
    dv_B = numerical_jacobian(lambda t: quat.attitude_matrix(quat.propagate_constant_rate(q0, w, t)) @ v_I, 0.0, eps=1e-5)
    np.testing.assert_allclose(dv_B[:, 0], -np.cross(w, quat.attitude_matrix(q0) @ v_I), atol=1e-10)


def test_cross_and_skew_match_numpy(rng):
    a, b = rng.normal(size=(2, 10, 3))
    np.testing.assert_allclose(quat.cross(a, b), np.cross(a, b), atol=1e-14)
    np.testing.assert_allclose(quat.skew(a) @ b[..., None], np.cross(a, b)[..., None], atol=1e-14)


def test_angle_between(rng):
    q = quat.random_quaternion(rng, 10)
    th = rng.uniform(0, np.pi, 10)
    axis = rng.normal(size=(10, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    q2 = quat.qmul(quat.rotvec_to_quat(axis * th[:, None]), q)
    np.testing.assert_allclose(quat.angle_between(q2, q), th, atol=1e-12)


def test_fast_products_equal_written_out_forms(rng):
    q = quat.random_quaternion(rng, (7, 3))
    p = quat.random_quaternion(rng, (7, 3))
    flat_q, flat_p = q.reshape(-1, 4), p.reshape(-1, 4)
    np.testing.assert_allclose(quat.qmul(q, p).reshape(-1, 4), [quat._qmul_ref(a, b) for a, b in zip(flat_q, flat_p, strict=True)], atol=1e-15)
    np.testing.assert_allclose(quat.attitude_matrix(q).reshape(-1, 3, 3), [quat._attitude_ref(a) for a in flat_q], atol=1e-15)
    # Broadcasting: one quaternion against many.
    np.testing.assert_allclose(quat.qmul(q[0, 0], p), quat.qmul(np.broadcast_to(q[0, 0], p.shape), p), atol=0)
