"""Truth dynamics against independent references."""

import numpy as np
from filterpy.common import van_loan_discretization
from scipy.integrate import quad_vec, solve_ivp
from scipy.linalg import expm

from swarmcore import dynamics, quat
from swarmcore.mekf import FilterParams, attitude_F, attitude_phi_q

N_E = 1.08e-3


def test_hcw_closed_form_matches_numerical_integration():
    rng = np.random.default_rng(1)
    A = dynamics.hcw_A(N_E)
    for dt in (1.0, 60.0, 3000.0):
        x0 = np.r_[rng.uniform(-10, 10, 3), rng.uniform(-0.01, 0.01, 3)]
        sol = solve_ivp(lambda t, x: A @ x, (0, dt), x0, rtol=1e-12, atol=1e-14, method="DOP853")
        np.testing.assert_allclose(dynamics.hcw_phi(N_E, dt) @ x0, sol.y[:, -1], rtol=1e-9, atol=1e-9)


def test_hcw_system_matrix_has_coriolis_terms():
    A = dynamics.hcw_A(N_E)
    assert A[3, 4] == 2 * N_E and A[4, 3] == -2 * N_E and A[3, 0] == 3 * N_E**2 and A[5, 2] == -(N_E**2)


def test_hcw_noise_cov_matches_quadrature():
    # Q = ∫₀^Δt Φ(s) G Qc Gᵀ Φ(s)ᵀ ds, computed independently by adaptive quadrature.
    dt, sa, sp = 5.0, 1e-3, 2e-4
    GQG = np.diag([sp**2] * 3 + [sa**2] * 3)
    ref, _ = quad_vec(lambda s: dynamics.hcw_phi(N_E, s) @ GQG @ dynamics.hcw_phi(N_E, s).T, 0, dt, epsabs=1e-20)
    np.testing.assert_allclose(dynamics.hcw_noise_cov(N_E, dt, sa, sp), ref, rtol=1e-8, atol=1e-22)


def test_hcw_noise_cov_is_filterpys_van_loan_bit_for_bit():
    """Written out to spare every process filterpy's import (and scipy.stats with it); the
    numbers are filterpy's own."""
    for dt, sa, sp in ((1.0, 1e-3, 0.0), (5.0, 1e-3, 2e-4), (0.1, 3e-6, 1e-5)):
        _, Q = van_loan_discretization(dynamics.hcw_A(N_E), np.diag([sp] * 3 + [sa] * 3), dt)
        assert np.array_equal(dynamics.hcw_noise_cov(N_E, dt, sa, sp), 0.5 * (Q + Q.T))


def test_a_filter_does_not_import_filterpy_or_scipy_stats():
    """Start-up: a process that builds a filter imports neither (checked in a fresh interpreter)."""
    import subprocess
    import sys

    code = ("import sys\nfrom swarmcore.agent import filter_params\nfrom swarmcore.scenario import Scenario\n"
            "filter_params(Scenario(n_sats=3), 0)\nprint(sorted(m for m in ('filterpy', 'scipy.stats') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]", out.stdout


def test_T_IH_rotates_about_z_at_mean_motion():
    t = 1234.0
    T = dynamics.T_IH(N_E, t)
    np.testing.assert_allclose(T @ [1, 0, 0], [np.cos(N_E * t), np.sin(N_E * t), 0], atol=1e-15)
    np.testing.assert_allclose(T.T @ T, np.eye(3), atol=1e-15)


def test_rk4_attitude_conserves_momentum_and_energy_without_torque():
    J = np.diag([1.67, 5.0, 3.67])
    q0 = quat.normalize(np.array([0.2, 0.1, -0.4, 0.8]))
    w0 = np.array([0.05, -0.03, 0.08])
    q, w = dynamics.rk4_attitude(q0, w0, J, 50.0, substeps=500)
    def h_I(q, w):
        return quat.attitude_matrix(q).T @ (J @ w)  # inertial angular momentum
    np.testing.assert_allclose(h_I(q, w), h_I(q0, w0), rtol=1e-9)
    np.testing.assert_allclose(w @ J @ w, w0 @ J @ w0, rtol=1e-10)


def test_rk4_attitude_matches_scipy_integration():
    J = np.diag([1.67, 8.33, 3.67])
    Ji = np.linalg.inv(J)
    q0 = quat.normalize(np.array([0.3, -0.1, 0.2, 0.9]))
    w0 = np.array([0.006, -0.004, 0.005])

    def rhs(t, x):
        q, w = x[:4], x[4:]
        return np.r_[0.5 * quat.qmul(np.r_[w, 0.0], q), -Ji @ np.cross(w, J @ w)]

    sol = solve_ivp(rhs, (0, 10.0), np.r_[q0, w0], rtol=1e-12, atol=1e-14, method="DOP853")
    q, w = dynamics.rk4_attitude(q0, w0, J, 10.0, substeps=10)
    np.testing.assert_allclose(q, quat.normalize(sol.y[:4, -1]), atol=1e-10)
    np.testing.assert_allclose(w, sol.y[4:, -1], atol=1e-12)


def _params(own=0, n=3):
    return FilterParams(
        n=n, own=own, dt=1.0, mean_motion=N_E, J=np.diag([1.67, 8.33, 3.67]),
        arw=3.16e-7, rrw=3.16e-10, torque=5e-6, accel=1e-8, att_rw_other=5e-4, pos_rw=5e-5,
    )


def test_batched_van_loan_matches_filterpy_block_by_block():
    p = _params()
    rng = np.random.default_rng(3)
    w = rng.uniform(-0.01, 0.01, (3, 3))
    own = np.array([True, False, False])
    phi, Q = attitude_phi_q(w, p, own)
    F = attitude_F(w, p.J, p.J_inv, own)
    for b in range(3):
        if own[b]:
            G = np.diag([p.arw] * 3 + [p.rrw] * 3)  # G Gᵀ = diag(σ_v² I, σ_u² I)
        else:
            G = np.zeros((6, 6))
            G[0:3, 0:3] = p.att_rw_other * np.eye(3)
            G[3:6, 3:6] = p.torque * p.J_inv
        phi_ref, Q_ref = van_loan_discretization(F[b], G, p.dt)
        np.testing.assert_allclose(phi[b], phi_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(Q[b], Q_ref, rtol=1e-9, atol=1e-24)
        np.testing.assert_allclose(phi[b], expm(F[b] * p.dt), rtol=1e-12, atol=1e-15)
