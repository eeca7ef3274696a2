"""Every F and H block against numerical derivatives on the filter's error-state manifold.

Errors are defined as in the filter: ``q = δq(a) ⊗ q̂``, everything else additive, the own
satellite's rate following its bias (``tests/numdiff.py``). A state is perturbed with
``x̂ ⊞ ε e_c`` and the nonlinear model is differentiated by central differences through
retract / local, the way GTSAM's numerical_derivative does on a manifold. Every Jacobian
is checked whole — the blocks the filter fills and the zeros it leaves — over the full
12-per-satellite state.
"""

import numpy as np
import pytest
from numdiff import ATTITUDE, EUCLIDEAN, numerical_generator, numerical_jacobian, product, swarm_state
from scipy.linalg import block_diag, expm

from swarmcore import dynamics, quat
from swarmcore.mekf import (
    AbsoluteMeasurement,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    absolute_residual,
    attitude_F,
    predict,
    relative_residuals,
    state_jacobian_blocks,
)
from swarmcore.sensors import relative_pose

N_E = 1.08e-3
J = np.diag([1.67, 8.33, 3.67])
OBSERVED = np.r_[0:3, 6:9]  # [a, Δr] inside a satellite's 12-block


def _params(n=3, own=0, dt=1.0):
    return FilterParams(n=n, own=own, dt=dt, mean_motion=N_E, J=J, arw=3e-7, rrw=3e-10, torque=5e-6, accel=1e-8)


def _estimate(rng, n=3, t=321.0):
    q = quat.random_quaternion(rng, n)
    r = rng.uniform(-10, 10, (n, 3))
    return SwarmEstimate(
        0, t, q, rng.uniform(-0.01, 0.01, (n, 3)), r, rng.uniform(-0.01, 0.01, (n, 3)), rng.uniform(-1e-4, 1e-4, 3), np.eye(12 * n)
    )


def _cols(sat):
    """Columns of satellite ``sat``'s attitude and position errors in the 12n state."""
    return 12 * sat + OBSERVED


def _relative_model(x: SwarmEstimate, obs, tgt):
    """The measurement model as documented in swarmcore.mekf: ``q_BjBi = q_j ⊗ q_i⁻¹``,
    ``r_ij_Bi = T(q_i) T_IH (r_j − r_i)``."""
    q = quat.qmul(x.q_BI[tgt], quat.qconj(x.q_BI[obs]))
    r = np.einsum("mab,mb->ma", quat.attitude_matrix(x.q_BI[obs]) @ dynamics.T_IH(N_E, x.t), x.r_H[tgt] - x.r_H[obs])
    return q, r


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_relative_measurement_jacobians(seed):
    """y = measured − predicted, with the measurement generated from the true state x̂ ⊞ δ:
    ``∂y/∂δ`` is the full H (6m × 12n): Hi on the observer's [a, Δr], Hj on the target's,
    zero on every rate, bias and velocity error and on every other satellite."""
    rng = np.random.default_rng(seed)
    est = _estimate(rng)
    p = _params()
    obs, tgt = np.array([0, 2, 1]), np.array([2, 1, 0])

    def meas(x):
        q, r = _relative_model(x, obs, tgt)
        return RelativeMeasurements(obs, tgt, q, r, np.tile(np.eye(6), (3, 1, 1)))

    # The truth side generates the same measurements as the documented model.
    q_t, r_t = relative_pose(N_E, est.t, est.q_BI, est.r_H, obs, tgt)
    q_m, r_m = _relative_model(est, obs, tgt)
    np.testing.assert_allclose(quat.local(q_t, q_m), 0.0, atol=1e-14)
    np.testing.assert_allclose(r_t, r_m, atol=1e-12)

    y0, Hi, Hj = relative_residuals(est, p, meas(est))
    np.testing.assert_allclose(y0, 0.0, atol=1e-12)
    H = np.zeros((18, 36))
    for m in range(3):
        H[6 * m : 6 * m + 6, _cols(obs[m])] = Hi[m]
        H[6 * m : 6 * m + 6, _cols(tgt[m])] = Hj[m]
    # ε = 1e-5 balances truncation (the model's curvature) against round-off on ~10 m values.
    num = numerical_jacobian(lambda x: relative_residuals(est, p, meas(x))[0].ravel(), est, swarm_state(p.own), EUCLIDEAN, eps=1e-5)
    np.testing.assert_allclose(num, H, rtol=0, atol=5e-9)


@pytest.mark.parametrize("parts", ["both", "star tracker", "gps"])
def test_absolute_measurement_jacobian(parts):
    """Star tracker and GPS of the own satellite: H = I on its [a, Δr], zero elsewhere;
    with one sensor missing, the rows of the other."""
    rng = np.random.default_rng(5)
    est = _estimate(rng)
    p = _params(own=1)
    use_q, use_r = parts in ("both", "star tracker"), parts in ("both", "gps")

    def reading(x):
        return AbsoluteMeasurement(x.q_BI[1] if use_q else None, x.r_H[1] if use_r else None, 1e-5, 1e-2)

    y0, H, R = absolute_residual(est, p, reading(est))
    np.testing.assert_allclose(y0, 0.0, atol=1e-12)
    rows = np.r_[0:3] if parts == "star tracker" else np.r_[3:6] if parts == "gps" else np.r_[0:6]
    H_full = np.zeros((rows.size, 36))
    H_full[:, _cols(1)] = H
    np.testing.assert_array_equal(H, np.eye(6)[rows])
    # local undoes retract exactly, so the residual is linear in δ: a large ε, tiny round-off.
    num = numerical_jacobian(lambda x: absolute_residual(est, p, reading(x))[0], est, swarm_state(p.own), EUCLIDEAN, eps=1e-4)
    np.testing.assert_allclose(num, H_full, rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.diag(R), np.array([1e-10] * 3 + [1e-4] * 3)[rows])


def test_F_other_satellite_attitude_block():
    """ȧ = −[ω̂×]a + Δω, Δω̇ = J⁻¹([Jω̂×] − [ω̂×]J)Δω, from Euler's equations: the generator
    of the error of the torque-free RK4 flow on (q, ω)."""
    rng = np.random.default_rng(7)
    q_hat = quat.random_quaternion(rng)
    w_hat = np.array([0.02, -0.015, 0.01])
    F = attitude_F(w_hat[None], J, np.linalg.inv(J), np.array([False]))[0]

    def flow(x, tau):
        return dynamics.rk4_attitude(x[0], x[1], J, tau, substeps=4)

    num = numerical_generator(flow, (q_hat, w_hat), product(ATTITUDE, EUCLIDEAN))
    np.testing.assert_allclose(num, F, rtol=0, atol=1e-8)


def test_F_own_satellite_gyro_mode_block():
    """Gyro mode: ȧ = −[ω̂×]a − Δβ, Δβ̇ = 0 with ω̂ = ω̃ − β̂ and truth ω = ω̃ − β: the
    generator of the error of the constant-rate flow on (q, β)."""
    rng = np.random.default_rng(8)
    q_hat = quat.random_quaternion(rng)
    gyro = np.array([0.03, -0.02, 0.01])
    b_hat = np.array([1e-4, -2e-4, 5e-5])
    F = attitude_F((gyro - b_hat)[None], J, np.linalg.inv(J), np.array([True]))[0]

    def flow(x, tau):
        q, b = x
        return quat.propagate_constant_rate(q, gyro - b, tau), b

    num = numerical_generator(flow, (q_hat, b_hat), product(ATTITUDE, EUCLIDEAN))
    np.testing.assert_allclose(num, F, rtol=0, atol=1e-8)


def test_translational_F_is_hcw_and_closed_form_phi_is_its_exponential():
    A = dynamics.hcw_A(N_E)
    np.testing.assert_allclose(expm(A * 7.0), dynamics.hcw_phi(N_E, 7.0), atol=1e-12)
    # The generator of the closed-form flow reproduces A. The flow is linear in the state,
    # so a large ε costs no truncation and keeps round-off (≈ u|x|/(ε h)) near 1e-14; the
    # time step leaves |A³|h²/6 ≈ 8e-13 at h = 1 ms.
    x = np.array([3.0, -7.0, 2.0, 0.01, -0.02, 0.005])
    num = numerical_generator(lambda z, tau: dynamics.hcw_phi(N_E, tau) @ z, x, EUCLIDEAN, eps=1.0, h=1e-3)
    np.testing.assert_allclose(num, A, rtol=0, atol=1e-11)


@pytest.mark.parametrize("own", [0, 2])
def test_predict_is_linearised_by_its_transition_blocks(own):
    """One whole-swarm ``predict`` differentiated on the 12n manifold equals block-diagonal
    Φ from ``state_jacobian_blocks`` (zeros between satellites included): to round-off for
    the own satellite (constant gyro rate over the step) and every translational block
    (linear HCW). Another satellite's attitude block differs by the change of ω̂ within the
    step — Φ = e^{F(ω̂₀)Δt} holds the rate of the step's start — that is, by ``½ Ḟ Δt²``
    with ``Ḟ = ∂F/∂ω · ω̇`` (from ``Φ̇ = F(t) Φ``), plus a third-order rest."""
    rng = np.random.default_rng(9 + own)
    est = _estimate(rng)
    gyro = np.array([0.03, -0.02, 0.01])
    M = swarm_state(own)
    others = [b for b in range(3) if b != own]
    exact = np.ones((36, 36), dtype=bool)
    for b in others:
        exact[12 * b : 12 * b + 6, 12 * b : 12 * b + 6] = False
    rest = {}
    for dt in (1.0, 0.2, 0.1):
        p = _params(own=own, dt=dt)
        num = numerical_jacobian(lambda x, p=p: predict(x, p, gyro), est, M, M, eps=1e-5)
        phi, _Q, _w = state_jacobian_blocks(est, p, gyro - est.bias_B)
        err = num - block_diag(*phi)
        assert np.abs(err[exact]).max() < 1e-9, (dt, np.abs(err[exact]).max())
        for b in others:
            w = est.omega_BI_B[b]
            w_dot = dynamics.euler_rate(w, J, p.J_inv)
            F_dot = numerical_jacobian(lambda s, w=w, w_dot=w_dot, p=p: attitude_F((w + s * w_dot)[None], J, p.J_inv, np.array([False]))[0], np.zeros(1))
            lead = 0.5 * F_dot.reshape(6, 6) * dt**2
            rest[dt, b] = np.abs(err[12 * b : 12 * b + 6, 12 * b : 12 * b + 6] - lead).max()
            if dt < 1.0:
                assert rest[dt, b] < dt * np.abs(lead).max(), (dt, b, rest[dt, b], np.abs(lead).max())
    for b in others:  # the rest is third order: halving Δt divides it by 8
        assert rest[0.2, b] / rest[0.1, b] == pytest.approx(8.0, rel=0.05)
