"""swarmcore.relmotion: relative motion about a known chief under J2 (and drag).

* the state matches absolute propagation of chief and deputy; the chief comes out with the
  bits of :func:`swarmcore.orbit.propagate`;
* the transition matrix is the derivative of the propagation (central differences);
* for a circular two-body chief and small separations it is HCW's closed form;
* HCW's error grows with separation (and with J2), this model's does not: both against an
  independent absolute propagation by scipy's DOP853 (the numbers are printed, ``-s``).
"""

import math

import numpy as np
import pytest
from numdiff import numerical_jacobian
from scipy.integrate import solve_ivp

from swarmcore import orbit as o
from swarmcore.dynamics import hcw_phi
from swarmcore.relmotion import hill_state_jacobian, hill_state_jacobian_inverse, propagate_relative

A_LEO = o.R_EARTH_M + 550e3
DEG = math.pi / 180.0
CHIEF = o.OrbitalElements(A_LEO, 0.001, 97.6 * DEG, 30 * DEG, 45 * DEG, 10 * DEG)
DRAG = o.ForceModel(atmosphere=o.ExponentialAtmosphere())


def _deputies(n_mean, scale):
    """Three deputies around the chief, ``scale`` metres away, on near-periodic HCW orbits."""
    r = np.array([[0.3, -1.0, 0.2], [-0.2, 0.5, -0.6], [0.05, 1.0, 0.0]]) * scale
    v = np.zeros_like(r)
    v[:, 0] = 0.1 * n_mean * scale
    v[:, 1] = -2.0 * n_mean * r[:, 0]
    v[:, 2] = 0.3 * n_mean * scale
    return r, v


def _truth(rc, vc, r_H, v_H, T, model, bc_c=None, bc_d=None):
    """Chief and deputies as absolute ECI orbits, one solve_ivp (DOP853, rtol 1e-13), then into
    the chief's Hill frame at T."""
    ac = o.acceleration(rc, vc, model, bc_c)
    rd, vd = o.hill_to_eci(rc, vc, r_H, v_H, ac)
    R = np.vstack([rc, rd])
    V = np.vstack([vc, vd])
    bc = np.zeros(len(R)) if bc_d is None else np.r_[0.0 if bc_c is None else bc_c, np.broadcast_to(bc_d, len(rd))]

    def f(_t, y):
        Y = y.reshape(-1, 6)
        return np.concatenate([Y[:, 3:], o.acceleration(Y[:, :3], Y[:, 3:], model, bc)], axis=1).ravel()

    sol = solve_ivp(f, (0.0, T), np.concatenate([R, V], axis=1).ravel(), method="DOP853", rtol=1e-13, atol=1e-10)
    Y = sol.y[:, -1].reshape(-1, 6)
    c1 = Y[0]
    return o.eci_to_hill(c1[:3], c1[3:], Y[1:, :3], Y[1:, 3:], o.acceleration(c1[:3], c1[3:], model, bc_c))


def test_hill_state_jacobian_and_inverse():
    rc, vc = CHIEF.to_rv()
    T = o.hill_T_IH(rc, vc)
    w = o.hill_omega_HI_H(rc, vc, o.acceleration(rc, vc))
    G = hill_state_jacobian(T, w)
    np.testing.assert_allclose(hill_state_jacobian_inverse(T, w) @ G, np.eye(6), atol=1e-15)
    # G is the derivative of hill_to_eci (relative part).
    x = np.array([100.0, -300.0, 50.0, 0.1, 0.2, -0.05])

    def rel_eci(z):
        rd, vd = o.hill_to_eci(rc, vc, z[:3], z[3:], o.acceleration(rc, vc))
        return np.r_[rd - rc, vd - vc]

    np.testing.assert_allclose(numerical_jacobian(rel_eci, x, eps=10.0), G, rtol=0, atol=1e-9)


@pytest.mark.parametrize("model", [o.J2_ONLY, DRAG], ids=["J2", "J2+drag"])
def test_state_matches_absolute_propagation_and_chief_bits(model):
    rc, vc = CHIEF.to_rv()
    n = math.sqrt(o.MU_EARTH_M3_S2 / A_LEO**3)
    r_H, v_H = _deputies(n, 2000.0)
    bc_d = np.array([0.01, 0.03, 0.02])
    step = propagate_relative(rc, vc, r_H, v_H, 600.0, model, ballistic_m2_kg=bc_d, chief_ballistic_m2_kg=0.015)
    rc1, vc1 = o.propagate(rc, vc, 600.0, model, ballistic_m2_kg=0.015)
    assert np.array_equal(step.r_chief_I_m, rc1) and np.array_equal(step.v_chief_I_m_s, vc1)
    ac = o.acceleration(rc, vc, model, 0.015)
    rd, vd = o.hill_to_eci(rc, vc, r_H, v_H, ac)
    rd1, vd1 = o.propagate(rd, vd, 600.0, model, ballistic_m2_kg=bc_d)
    r_ref, v_ref = o.eci_to_hill(rc1, vc1, rd1, vd1, o.acceleration(rc1, vc1, model, 0.015))
    np.testing.assert_allclose(step.r_H_m, r_ref, rtol=0, atol=1e-8)  # ECI differencing resolves ~1e-9 m
    np.testing.assert_allclose(step.v_H_m_s, v_ref, rtol=0, atol=1e-11)
    one = propagate_relative(rc, vc, r_H[1], v_H[1], 600.0, model, ballistic_m2_kg=bc_d[1], chief_ballistic_m2_kg=0.015)
    np.testing.assert_allclose(one.r_H_m, step.r_H_m[1], rtol=0, atol=1e-12)
    assert one.phi is not None and one.phi.shape == (6, 6)


@pytest.mark.parametrize(("model", "scale", "dt"), [(o.J2_ONLY, 1e3, 60.0), (o.J2_ONLY, 5e4, 900.0), (DRAG, 1e4, 300.0)])
def test_stm_is_the_derivative_of_the_propagation(model, scale, dt):
    rc, vc = CHIEF.to_rv()
    n = math.sqrt(o.MU_EARTH_M3_S2 / A_LEO**3)
    r_H, v_H = _deputies(n, scale)
    bc = np.array([0.01, 0.03, 0.02])
    step = propagate_relative(rc, vc, r_H, v_H, dt, model, ballistic_m2_kg=bc, chief_ballistic_m2_kg=0.02)
    assert step.phi is not None
    S = np.r_[np.ones(3), np.full(3, 1e-3)]  # x = S z: a step of 1 m in position, 1 mm/s in velocity
    for k in range(3):
        x0 = np.r_[r_H[k], v_H[k]]

        def f(z, k=k, x0=x0):
            x = x0 + S * z
            s = propagate_relative(rc, vc, x[:3], x[3:], dt, model, ballistic_m2_kg=bc[k], chief_ballistic_m2_kg=0.02, with_stm=False)
            return np.r_[s.r_H_m, s.v_H_m_s]

        num = numerical_jacobian(f, np.zeros(6), eps=1.0) / S[None, :]
        scale_cols = np.abs(num).max(axis=0)
        np.testing.assert_allclose(step.phi[k], num, rtol=0, atol=1e-7 * scale_cols.max())
        np.testing.assert_allclose(step.phi[k] / scale_cols, num / scale_cols, rtol=0, atol=1e-7)


@pytest.mark.parametrize("dt", [10.0, 100.0, 1000.0, 5700.0])
def test_reduces_to_hcw_for_a_circular_two_body_chief(dt):
    """Φ is taken at the deputy; at zero separation it is HCW's (the linearisation about a
    circular two-body chief). The gap is linear in the separation (second-order terms,
    growing with n dt): ≤ 1e-8 of each column's size at 0.1 mm, ≤ 1e-7 at 1 mm."""
    a = A_LEO
    n = math.sqrt(o.MU_EARTH_M3_S2 / a**3)
    rc, vc = o.coe_to_rv(np.array([a, 0.0, 0.9, 0.3, 0.0, 0.5]))
    P = hcw_phi(n, dt)
    scale = np.abs(P).max(axis=0)
    gaps = []
    for sep in (1e-4, 1e-3):
        r_H = np.array([0.5, -1.0, 0.3]) * sep
        v_H = np.array([1e-4, -1e-3, 2e-4]) * sep
        step = propagate_relative(rc, vc, r_H, v_H, dt, o.TWO_BODY, step_s=30.0)
        assert step.phi is not None
        gaps.append(np.abs((step.phi - P) / scale).max())
        x1 = P @ np.r_[r_H, v_H]
        # the relative force is resolved to ~1e-15 m/s² (r_c + ρ has the ~1e-9 m grain of a
        # 7e6 m coordinate): ~1e-8 m after an orbit
        np.testing.assert_allclose(step.r_H_m, x1[:3], rtol=0, atol=2e-8)
        np.testing.assert_allclose(step.v_H_m_s, x1[3:], rtol=0, atol=2e-11)
    assert gaps[0] < 1e-8 and gaps[1] < 1e-7


def test_hcw_error_grows_with_separation_this_model_does_not():
    """One orbit from deputies 10 m … 50 km away: position error of HCW's closed form and of
    this model against an independent absolute propagation (solve_ivp DOP853, rtol 1e-13)."""
    rows = []
    for label, model, chief in [
        ("circular, two-body", o.TWO_BODY, o.OrbitalElements(A_LEO, 0.0, 97.6 * DEG, 0.5, 0.0, 0.3)),
        ("e=0.001, J2", o.J2_ONLY, CHIEF),
    ]:
        rc, vc = chief.to_rv()
        n = math.sqrt(o.MU_EARTH_M3_S2 / chief.a_m**3)
        T = 2 * math.pi / n
        P = hcw_phi(n, T)
        for scale in [10.0, 100.0, 1e3, 1e4, 5e4]:
            r_H, v_H = _deputies(n, scale)
            r_true, _ = _truth(rc, vc, r_H, v_H, T, model)
            ours = propagate_relative(rc, vc, r_H, v_H, T, model, step_s=30.0, with_stm=False)
            hcw = (P @ np.concatenate([r_H, v_H], axis=1).T).T[:, :3]
            e_ours = np.linalg.norm(ours.r_H_m - r_true, axis=1).max()
            e_hcw = np.linalg.norm(hcw - r_true, axis=1).max()
            rows.append((label, scale, e_hcw, e_ours))
    print("\none orbit, max position error over 3 deputies:")
    print(f"  {'case':<20} {'separation':>10} {'HCW':>10} {'this model':>11}")
    for label, scale, e_hcw, e_ours in rows:
        print(f"  {label:<20} {scale:>10.0f} {e_hcw:>10.3g} {e_ours:>11.3g}")
    for label in ("circular, two-body", "e=0.001, J2"):
        mine = [r for r in rows if r[0] == label]
        e_hcw = np.array([r[2] for r in mine])
        e_ours = np.array([r[3] for r in mine])
        assert np.all(np.diff(e_hcw) > 0)  # HCW's error grows with separation …
        assert e_hcw[-1] > 100.0 * e_hcw[0]
        assert np.all(e_ours < 1e-5)  # … this model's stays at the integrator's round-off
        assert np.all(e_ours < 1e-3 * e_hcw)
