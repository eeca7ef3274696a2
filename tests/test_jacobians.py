"""Every F and H block against numerical derivatives through the attitude-error retraction.

Errors are defined as in the filter: q = δq(a) ⊗ q̂, everything else additive. A state is
perturbed with ``x̂ ⊞ ε e_c`` and the nonlinear model is differentiated numerically (central
differences), the way GTSAM's numerical_derivative does on a manifold.
"""

import numpy as np
import pytest

from swarmcore import dynamics, quat
from swarmcore.mekf import (
    AbsoluteMeasurement,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    absolute_residual,
    attitude_F,
    relative_residuals,
)
from swarmcore.sensors import relative_pose

N_E = 1.08e-3
J = np.diag([1.67, 8.33, 3.67])


def _params(n=3, own=0):
    return FilterParams(n=n, own=own, dt=1.0, mean_motion=N_E, J=J, arw=3e-7, rrw=3e-10, torque=5e-6, accel=1e-8)


def _estimate(rng, n=3, t=321.0):
    q = quat.random_quaternion(rng, n)
    r = rng.uniform(-10, 10, (n, 3))
    return SwarmEstimate(0, t, q, rng.uniform(-0.01, 0.01, (n, 3)), r, np.zeros((n, 3)), np.zeros(3), np.eye(12 * n))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_relative_measurement_jacobians(seed):
    rng = np.random.default_rng(seed)
    est = _estimate(rng)
    p = _params()
    obs, tgt = np.array([0, 2, 1]), np.array([2, 1, 0])

    def meas(q, r):
        qm, rm = relative_pose(N_E, est.t, q, r, obs, tgt)
        return RelativeMeasurements(obs, tgt, qm, rm, np.tile(np.eye(6), (3, 1, 1)))

    y0, Hi, Hj = relative_residuals(est, p, meas(est.q_BI, est.r_H))
    np.testing.assert_allclose(y0, 0.0, atol=1e-12)
    eps = 1e-6
    for m in range(3):
        for sat, H in ((obs[m], Hi[m]), (tgt[m], Hj[m])):
            num = np.zeros((6, 6))
            for c in range(6):
                cols = []
                for s in (+1, -1):
                    d = np.zeros(6)
                    d[c] = s * eps
                    q, r = est.q_BI.copy(), est.r_H.copy()
                    q[sat] = quat.retract(q[sat], d[:3])
                    r[sat] = r[sat] + d[3:]
                    cols.append(relative_residuals(est, p, meas(q, r))[0][m])
                num[:, c] = (cols[0] - cols[1]) / (2 * eps)
            np.testing.assert_allclose(H, num, atol=1e-7)


def test_absolute_measurement_jacobian():
    rng = np.random.default_rng(5)
    est = _estimate(rng)
    p = _params(own=1)
    eps = 1e-6
    _, H, R = absolute_residual(est, p, AbsoluteMeasurement(est.q_BI[1], est.r_H[1], 1e-5, 1e-2))
    num = np.zeros((6, 6))
    for c in range(6):
        ys = []
        for s in (+1, -1):
            d = np.zeros(6)
            d[c] = s * eps
            m = AbsoluteMeasurement(quat.retract(est.q_BI[1], d[:3]), est.r_H[1] + d[3:], 1e-5, 1e-2)
            ys.append(absolute_residual(est, p, m)[0])
        num[:, c] = (ys[0] - ys[1]) / (2 * eps)
    np.testing.assert_allclose(H, num, atol=1e-8)
    np.testing.assert_allclose(np.diag(R), [1e-10] * 3 + [1e-4] * 3)


def _error_rate_numeric(f_err, x0_err, h=1e-3):
    """d/dt of the error at t=0 by central differences in time."""
    return (f_err(h) - f_err(-h)) / (2 * h)


def test_F_other_satellite_attitude_block():
    """ȧ = −[ω̂×]a + Δω, Δω̇ = J⁻¹([Jω̂×] − [ω̂×]J)Δω, from Euler's equations."""
    rng = np.random.default_rng(7)
    q_hat = quat.random_quaternion(rng)
    w_hat = np.array([0.02, -0.015, 0.01])
    F = attitude_F(w_hat[None], J, np.linalg.inv(J), np.array([False]))[0]
    eps = 1e-6
    num = np.zeros((6, 6))
    for c in range(6):
        d = np.zeros(6)
        d[c] = eps
        q_true = quat.retract(q_hat, d[:3])
        w_true = w_hat + d[3:]

        def err(h):
            qt, wt = dynamics.rk4_attitude(q_true, w_true, J, h, substeps=4)
            qe, we = dynamics.rk4_attitude(q_hat, w_hat, J, h, substeps=4)
            return np.r_[quat.local(qt, qe), wt - we]

        num[:, c] = _error_rate_numeric(err, d) / eps
    np.testing.assert_allclose(F, num, atol=2e-6)


def test_F_own_satellite_gyro_mode_block():
    """Gyro mode: ȧ = −[ω̂×]a − Δβ, Δβ̇ = 0 with ω̂ = ω̃ − β̂ and truth ω = ω̃ − β."""
    rng = np.random.default_rng(8)
    q_hat = quat.random_quaternion(rng)
    gyro = np.array([0.03, -0.02, 0.01])
    b_hat = np.array([1e-4, -2e-4, 5e-5])
    w_hat = gyro - b_hat
    F = attitude_F(w_hat[None], J, np.linalg.inv(J), np.array([True]))[0]
    eps = 1e-6
    num = np.zeros((6, 6))
    for c in range(6):
        d = np.zeros(6)
        d[c] = eps
        q_true = quat.retract(q_hat, d[:3])
        b_true = b_hat + d[3:]

        def err(h):
            qt = quat.propagate_constant_rate(q_true, gyro - b_true, h)
            qe = quat.propagate_constant_rate(q_hat, gyro - b_hat, h)
            return np.r_[quat.local(qt, qe), b_true - b_hat]

        num[:, c] = _error_rate_numeric(err, d) / eps
    np.testing.assert_allclose(F, num, atol=2e-6)


def test_translational_F_is_hcw_and_closed_form_phi_is_its_exponential():
    from scipy.linalg import expm

    A = dynamics.hcw_A(N_E)
    np.testing.assert_allclose(expm(A * 7.0), dynamics.hcw_phi(N_E, 7.0), atol=1e-12)
    # Numerical derivative of the closed form at 0 reproduces A.
    h = 1e-3
    np.testing.assert_allclose((dynamics.hcw_phi(N_E, h) - dynamics.hcw_phi(N_E, -h)) / (2 * h), A, atol=1e-9)
