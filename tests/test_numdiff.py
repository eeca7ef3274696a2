"""The numerical-Jacobian helper itself: closed forms it must recover, and its order."""

import numpy as np
import pytest
from numdiff import ATTITUDE, EUCLIDEAN, numerical_generator, numerical_jacobian, product, swarm_state
from scipy.linalg import expm

from swarmcore import quat
from swarmcore.mekf import FilterParams, SwarmEstimate, apply_correction


@pytest.fixture
def rng():
    return np.random.default_rng(11)


def test_linear_map_is_recovered_exactly_for_any_step(rng):
    # Central differences of an affine map have no truncation error, whatever ε.
    A = rng.normal(size=(4, 7))
    b = rng.normal(size=4)
    x = rng.normal(size=7)
    for eps in (1e-6, 1e-2, 0.5):
        np.testing.assert_allclose(numerical_jacobian(lambda z: A @ z + b, x, eps=eps), A, rtol=0, atol=1e-9)
    # Array-shaped inputs and outputs are flattened in C order: 2 Xᵀ moves X[i, j] to row 2j + i.
    X = rng.normal(size=(2, 3))
    expect = np.zeros((6, 6))
    for i in range(2):
        for j in range(3):
            expect[2 * j + i, 3 * i + j] = 2.0
    np.testing.assert_allclose(numerical_jacobian(lambda Z: 2.0 * Z.T, X), expect, atol=1e-9)


def test_rotation_action_on_a_vector(rng):
    """``v_B = T(q) v_I``: ``∂/∂a = [v_B×]`` (since ``T(δq(a)) = I − [a×] + O(a²)``) and ``∂/∂v_I = T(q)``."""
    for _ in range(5):
        q, v = quat.random_quaternion(rng), rng.normal(size=3)
        T = quat.attitude_matrix(q)
        J_a = numerical_jacobian(lambda p, v=v: quat.attitude_matrix(p) @ v, q, domain=ATTITUDE)
        np.testing.assert_allclose(J_a, quat.skew(T @ v), atol=1e-9)
        J_v = numerical_jacobian(lambda w, T=T: T @ w, v)
        np.testing.assert_allclose(J_v, T, atol=1e-9)


def test_quaternion_product_and_inverse_on_the_manifold(rng):
    """With ``q = δq(a) ⊗ q̂`` everywhere: ``q₁ ⊗ q₂`` has error ``a₁ + T(q̂₁) a₂``, because
    ``q̂₁ ⊗ δq(a₂) ⊗ q̂₁⁻¹ = δq(T(q̂₁) a₂)`` to first order; ``q⁻¹`` has error ``−T(q̂)ᵀ a``."""
    pair = product(ATTITUDE, ATTITUDE)
    for _ in range(5):
        q1, q2 = quat.random_quaternion(rng, 2)
        J = numerical_jacobian(lambda x: quat.qmul(x[0], x[1]), (q1, q2), domain=pair, codomain=ATTITUDE)
        np.testing.assert_allclose(J, np.hstack([np.eye(3), quat.attitude_matrix(q1)]), atol=1e-9)
        J_inv = numerical_jacobian(quat.qconj, q1, domain=ATTITUDE, codomain=ATTITUDE)
        np.testing.assert_allclose(J_inv, -quat.attitude_matrix(q1).T, atol=1e-9)
    # A batch of quaternions is one manifold with 3 numbers per quaternion, blocks independent.
    qs = quat.random_quaternion(rng, 3)
    J = numerical_jacobian(quat.qconj, qs, domain=ATTITUDE, codomain=ATTITUDE)
    expect = np.zeros((9, 9))
    for b in range(3):
        expect[3 * b : 3 * b + 3, 3 * b : 3 * b + 3] = -quat.attitude_matrix(qs[b]).T
    np.testing.assert_allclose(J, expect, atol=1e-9)


def test_central_differences_are_second_order_until_round_off(rng):
    """The error of the rotation-action Jacobian falls as ε² (a slope of 2 on log-log)
    while truncation dominates, and grows again once round-off (≈ u/ε) does."""
    q, v = quat.random_quaternion(rng), rng.normal(size=3)
    exact = quat.skew(quat.attitude_matrix(q) @ v)

    def err(eps):
        J = numerical_jacobian(lambda p: quat.attitude_matrix(p) @ v, q, domain=ATTITUDE, eps=eps)
        return np.abs(J - exact).max()

    steps = np.array([1e-1, 3e-2, 1e-2, 3e-3, 1e-3])
    errs = np.array([err(e) for e in steps])
    slopes = np.diff(np.log(errs)) / np.diff(np.log(steps))
    np.testing.assert_allclose(slopes, 2.0, atol=0.1)
    # Halving ε quarters the error.
    assert err(2e-3) / err(1e-3) == pytest.approx(4.0, rel=0.02)
    # Round-off: far below the optimum the error grows again, like 1/ε.
    assert err(1e-11) > 10 * err(1e-6)
    assert err(1e-6) < 1e-9


def test_generator_of_a_linear_flow_is_its_matrix(rng):
    """For ``x(τ) = e^{Aτ} x₀`` the generator is A; the central difference in time leaves
    exactly ``A³h²/6`` (the odd terms of ``(e^{Ah} − e^{−Ah}) / 2h``) plus O(h⁴)."""
    A = rng.normal(size=(4, 4)) * 0.3
    x = rng.normal(size=4)

    def flow(z, t):
        return expm(A * t) @ z

    np.testing.assert_allclose(numerical_generator(flow, x, EUCLIDEAN, eps=1e-3, h=1e-4), A, atol=2e-9)
    h = 1e-2
    np.testing.assert_allclose(numerical_generator(flow, x, EUCLIDEAN, eps=1e-3, h=h), A + A @ A @ A * h**2 / 6, atol=2e-9)


def _estimate(rng, n=3):
    return SwarmEstimate(
        step=4,
        t=17.0,
        q_BI=quat.random_quaternion(rng, n),
        omega_BI_B=rng.uniform(-0.01, 0.01, (n, 3)),
        r_H=rng.uniform(-10, 10, (n, 3)),
        v_H=rng.uniform(-0.01, 0.01, (n, 3)),
        bias_B=rng.uniform(-1e-4, 1e-4, 3),
        P=np.eye(12 * n),
    )


@pytest.mark.parametrize("own", [0, 2])
def test_swarm_state_retract_and_local_are_inverses_and_match_the_filter_reset(rng, own):
    """The 12-per-satellite error state: local undoes retract, a zero step changes nothing,
    and the filter's own multiplicative reset is exactly this retraction."""
    M = swarm_state(own)
    est = _estimate(rng)
    assert M.dim(est) == 36
    # Zero up to round-off: q ⊗ q⁻¹ leaves ~1e-17 with some BLAS kernels (Haswell), none with others.
    np.testing.assert_allclose(M.local(est, est), np.zeros(36), rtol=0, atol=1e-15)
    d = rng.normal(scale=0.05, size=36)
    moved = M.retract(est, d)
    np.testing.assert_allclose(M.local(moved, est), d, atol=1e-13)
    # The own rate is the bias-corrected gyro: it moves against the bias, by Δβ.
    np.testing.assert_allclose(moved.omega_BI_B[own] - est.omega_BI_B[own], -d[12 * own + 3 : 12 * own + 6], atol=1e-15)
    np.testing.assert_allclose(moved.bias_B - est.bias_B, d[12 * own + 3 : 12 * own + 6], atol=1e-15)
    p = FilterParams(n=3, own=own, dt=1.0, mean_motion=1.08e-3, J=np.diag([1.0, 2.0, 3.0]), arw=1e-7, rrw=1e-10, torque=1e-6, accel=1e-8)
    reset = apply_correction(est, p, d, est.P)
    for field in ("q_BI", "omega_BI_B", "r_H", "v_H", "bias_B"):
        np.testing.assert_allclose(getattr(reset, field), getattr(moved, field), rtol=0, atol=1e-15, err_msg=field)
