"""swarmcore.bearing: the angles-only camera model.

Line of sight and its Jacobians against numerical derivatives through the attitude
retraction (tests/numdiff.py), the tangent-plane residual and its noise (Monte Carlo of
pixel noise through a pinhole), and the detection functions on hand-made geometries.
"""

import math

import numpy as np
import pytest
from numdiff import ATTITUDE, EUCLIDEAN, numerical_jacobian, product

from swarmcore import bearing as b
from swarmcore import cameras, quat
from swarmcore import orbit as o

DEG = math.pi / 180.0


def _pairs(rng, m=6, scale=1000.0):
    q = quat.random_quaternion(rng, m)
    r_i = rng.uniform(-scale, scale, (m, 3))
    r_j = r_i + rng.normal(size=(m, 3)) * scale
    # an orthonormal T_IH per pair (Hill → inertial at the image time)
    T_IH = quat.attitude_matrix(quat.random_quaternion(rng, m))
    return q, r_i, r_j, T_IH


def _look_at(T_CB, los_I):
    """An observer attitude q_BI whose camera (T_CB) boresight points along ``los_I``."""
    z = los_I / np.linalg.norm(los_I)
    x = np.cross([0.0, 0.0, 1.0], z)
    x /= np.linalg.norm(x)
    T_CI = np.stack([x, np.cross(z, x), z])  # rows: camera axes in I
    return quat.from_attitude_matrix(T_CB.T @ T_CI)


@pytest.mark.parametrize("cam", [None, 1, 4])
def test_line_of_sight_is_the_documented_model(cam):
    rng = np.random.default_rng(0)
    q, r_i, r_j, T_IH = _pairs(rng)
    T_CB = None if cam is None else cameras.T_CB[cam]
    u, rng_m = b.line_of_sight(q, T_IH, r_i, r_j, T_CB)
    C = quat.attitude_matrix(q) @ T_IH
    if T_CB is not None:
        C = T_CB @ C
    rho = np.einsum("mab,mb->ma", C, r_j - r_i)
    np.testing.assert_allclose(u, rho / np.linalg.norm(rho, axis=1)[:, None], atol=1e-15)
    np.testing.assert_allclose(rng_m, np.linalg.norm(r_j - r_i, axis=1), rtol=1e-14)


@pytest.mark.parametrize(("seed", "cam"), [(1, None), (2, 0), (3, 5)])
def test_line_of_sight_jacobians_numerically(seed, cam):
    """∂u/∂[a_i, r_i, r_j] through ``q = δq(a) ⊗ q̂`` and additive positions."""
    rng = np.random.default_rng(seed)
    q, r_i, r_j, T_IH = _pairs(rng, m=4)
    T_CB = None if cam is None else cameras.T_CB[cam]
    u, Ja, Jri, Jrj = b.line_of_sight_jacobians(q, T_IH, r_i, r_j, T_CB)
    space = product(ATTITUDE, EUCLIDEAN, EUCLIDEAN)
    for k in range(4):
        x = (q[k], r_i[k], r_j[k])
        num = numerical_jacobian(lambda z, k=k: b.line_of_sight(z[0], T_IH[k], z[1], z[2], T_CB)[0], x, space, EUCLIDEAN, eps=1e-6)
        np.testing.assert_allclose(np.hstack([Ja[k], Jri[k], Jrj[k]]), num, rtol=0, atol=1e-9)
        # the range is not observed: moving both satellites together, or along u, does nothing
        np.testing.assert_allclose(Jri[k] + Jrj[k], 0.0, atol=1e-18)
        los_H = r_j[k] - r_i[k]
        np.testing.assert_allclose(Jrj[k] @ los_H, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-15)


def test_tangent_basis():
    rng = np.random.default_rng(4)
    u = rng.normal(size=(200, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    u[0] = [1.0, 0.0, 0.0]
    u[1] = [-1.0, 1e-9, 0.0]
    u[1] /= np.linalg.norm(u[1])
    E = b.tangent_basis(u)
    np.testing.assert_allclose(np.swapaxes(E, 1, 2) @ E, np.broadcast_to(np.eye(2), (200, 2, 2)), atol=1e-14)
    np.testing.assert_allclose(np.einsum("mi,mik->mk", u, E), 0.0, atol=1e-15)
    np.testing.assert_allclose(np.cross(E[:, :, 0], E[:, :, 1]), u, atol=1e-14)  # right-handed: e₁ × e₂ = u
    Eb = b.tangent_basis(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(Eb, [[1, 0], [0, 1], [0, 0]], atol=1e-16)  # the image axes on the boresight


@pytest.mark.parametrize("seed", [5, 6])
def test_residual_jacobians_numerically(seed):
    """y = Eᵀ ũ with ũ made from the true state x̂ ⊞ δ and E at the prediction: ∂y/∂δ = H."""
    rng = np.random.default_rng(seed)
    q, r_i, r_j, T_IH = _pairs(rng, m=3)
    T_CB = cameras.T_CB[2]
    u_hat, _ = b.line_of_sight(q, T_IH, r_i, r_j, T_CB)
    y0, Ha, Hri, Hrj, E = b.bearing_residuals(u_hat, q, T_IH, r_i, r_j, T_CB)
    np.testing.assert_allclose(y0, 0.0, atol=1e-15)
    assert y0.shape == (3, 2) and Ha.shape == (3, 2, 3) and E.shape == (3, 3, 2)
    space = product(ATTITUDE, EUCLIDEAN, EUCLIDEAN)
    for k in range(3):

        def y(z, k=k):
            u_true = b.line_of_sight(z[0], T_IH[k], z[1], z[2], T_CB)[0]
            return b.bearing_residuals(u_true, q[k], T_IH[k], r_i[k], r_j[k], T_CB)[0]

        num = numerical_jacobian(y, (q[k], r_i[k], r_j[k]), space, EUCLIDEAN, eps=1e-6)
        np.testing.assert_allclose(np.hstack([Ha[k], Hri[k], Hrj[k]]), num, rtol=0, atol=1e-9)
    # Small errors: y is the rotation of û into ũ, in radians.
    a = np.array([2e-5, -1e-5, 3e-5])
    u_true = b.line_of_sight(quat.retract(q[0], a), T_IH[0], r_i[0], r_j[0], T_CB)[0]
    y = b.bearing_residuals(u_true, q[0], T_IH[0], r_i[0], r_j[0], T_CB)[0]
    assert np.linalg.norm(y) == pytest.approx(math.acos(np.clip(u_true @ u_hat[0], -1, 1)), rel=1e-6)


def test_pixels_round_trip():
    rng = np.random.default_rng(7)
    px = rng.uniform(-800, 800, (50, 2))
    u = b.pixels_to_line_of_sight(px, 2000.0, (1000.0, 1000.0))
    np.testing.assert_allclose(b.project_to_pixels(u, 2000.0, (1000.0, 1000.0)), px, atol=1e-10)
    np.testing.assert_allclose(np.linalg.norm(u, axis=1), 1.0, atol=1e-15)


@pytest.mark.parametrize("off_axis_deg", [0.0, 20.0, 40.0])
def test_noise_covariance_against_pixel_noise(off_axis_deg):
    """Pixel noise σ_px through the pinhole into the tangent-plane residual: the sample
    covariance matches the exact map (cos²θ radially, cos θ across) and the isotropic
    (σ_px/f)² bounds it, equal on the boresight."""
    f, sigma = 1500.0, 0.8
    th = off_axis_deg * DEG
    u = np.array([math.sin(th) * math.cos(0.7), math.sin(th) * math.sin(0.7), math.cos(th)])
    px0 = b.project_to_pixels(u, f)
    rng = np.random.default_rng(8)
    k = 40000
    u_meas = b.pixels_to_line_of_sight(px0 + sigma * rng.standard_normal((k, 2)), f)
    E = b.tangent_basis(u)
    y = u_meas @ E
    R_mc = np.cov(y.T)
    R = b.bearing_noise_cov(u, sigma, f)
    np.testing.assert_allclose(R_mc, R, rtol=0, atol=0.03 * (sigma / f) ** 2)
    np.testing.assert_allclose(np.linalg.eigvalsh(R), np.sort([math.cos(th) ** 4, math.cos(th) ** 2]) * (sigma / f) ** 2, rtol=1e-10)
    bound = b.bearing_noise_cov(u, sigma, f, exact=False)
    assert np.all(np.linalg.eigvalsh(bound - R) >= -1e-30)
    assert b.BearingCamera(f_px=f, sigma_px=sigma).sigma_rad == sigma / f


def test_field_of_view_image_and_size():
    u = np.array([[0.0, 0.0, 1.0], [math.sin(9 * DEG), 0, math.cos(9 * DEG)], [0, math.sin(11 * DEG), math.cos(11 * DEG)], [0, 0, -1.0]])
    np.testing.assert_array_equal(b.in_field_of_view(u, 10 * DEG), [True, True, False, False])
    f = 1000.0
    np.testing.assert_array_equal(b.in_image(u, f, 400, 300), [True, True, False, False])  # tan 9° · 1000 = 158 ≤ 200
    np.testing.assert_array_equal(b.in_image(u[1:2], f, 300, 400), [False])
    assert b.apparent_size_px(0.3, 1000.0, 3000.0) == pytest.approx(0.9)


def test_earth_occultation_against_brute_force():
    rng = np.random.default_rng(9)
    R = o.R_EARTH_M
    m = 3000
    ro = rng.normal(size=(m, 3))
    ro *= (R + rng.uniform(3e5, 3e6, (m, 1))) / np.linalg.norm(ro, axis=1)[:, None]
    rt = rng.normal(size=(m, 3))
    rt *= (R + rng.uniform(3e5, 3e6, (m, 1))) / np.linalg.norm(rt, axis=1)[:, None]
    t = np.linspace(0.0, 1.0, 4001)
    pts = ro[:, None, :] + t[None, :, None] * (rt - ro)[:, None, :]
    brute = np.min(np.linalg.norm(pts, axis=2), axis=1) < R
    got = b.earth_occulted(ro, rt)
    margin = np.abs(np.min(np.linalg.norm(pts, axis=2), axis=1) - R) > 2e3  # away from grazing
    np.testing.assert_array_equal(got[margin], brute[margin])
    assert 0.2 < got.mean() < 0.9
    # Close formation never occulted; opposite sides always.
    r = np.array([R + 550e3, 0, 0])
    assert not b.earth_occulted(r, r + np.array([0, 50e3, 0])) and b.earth_occulted(r, -r)


def test_earth_background_and_shadow_and_sun():
    R = o.R_EARTH_M
    obs = np.array([R + 600e3, 0.0, 0.0])
    below = np.array([R + 500e3, 1e3, 0.0])  # looking down (nadir-ish): Earth behind the target
    above = np.array([R + 700e3, 1e3, 0.0])  # looking up: space behind
    ahead = np.array([R + 600e3, 50e3, 0.0])  # along-track at the same altitude: limb far below?
    got = b.earth_in_background(np.stack([obs] * 3), np.stack([below, above, ahead]))
    assert got[0] and not got[1]
    # along-track from 600 km the line of sight misses the Earth (tangent height ≈ 600 km)
    assert not got[2]
    sun = np.array([1.0, 0.0, 0.0])
    np.testing.assert_array_equal(b.in_earth_shadow(np.array([[-(R + 5e5), 0, 0], [R + 5e5, 0, 0], [-(R + 5e5), R * 1.01, 0]]), sun), [True, False, False])
    los = np.array([[math.cos(20 * DEG), math.sin(20 * DEG), 0.0], [math.cos(40 * DEG), math.sin(40 * DEG), 0.0]]) * 1e4
    np.testing.assert_array_equal(b.sun_excluded(los, sun, 30 * DEG), [True, False])


def test_diffuse_sphere_brightness():
    R = o.R_EARTH_M
    sun = np.array([0.0, 1.0, 0.0])
    tgt = np.array([R + 550e3, 0.0, 0.0])
    obs_full = tgt + 1e6 * sun  # observer on the Sun side: φ = 0
    f0 = b.diffuse_sphere_flux_ratio(obs_full, tgt, sun, 1.0, 0.2)
    assert f0 == pytest.approx(2 * 0.2 / (3 * math.pi**2 * 1e12) * math.pi, rel=1e-12)
    m0 = b.visual_magnitude(obs_full, tgt, sun, 1.0, 0.2)
    assert m0 == pytest.approx(b.SUN_MAGNITUDE - 2.5 * math.log10(f0), rel=1e-12)
    # inverse square and area: +5 log10 2 per doubling of range, −2.5 log10 2 per doubling of area
    assert b.visual_magnitude(tgt + 2e6 * sun, tgt, sun, 1.0, 0.2) - m0 == pytest.approx(5 * math.log10(2), rel=1e-9)
    assert b.visual_magnitude(obs_full, tgt, sun, 2.0, 0.2) - m0 == pytest.approx(-2.5 * math.log10(2), rel=1e-9)
    # phase: dimmer as φ grows, dark at φ = π (backlit)
    obs = tgt + 1e6 * np.array([[0, math.cos(p), math.sin(p)] for p in np.linspace(0, math.pi, 7)])
    f = b.diffuse_sphere_flux_ratio(obs, np.broadcast_to(tgt, obs.shape), sun, 1.0, 0.2)
    assert np.all(np.diff(f) < 0) and f[-1] == pytest.approx(0.0, abs=1e-30)
    # in the Earth's shadow: dark
    assert b.diffuse_sphere_flux_ratio(obs_full, -np.array([0, R + 5e5, 0]), sun, 1.0, 0.2) == 0.0


def test_visibility_of_a_starfox_like_pair():
    """Chief at 550 km (SSO), a deputy 50 km ahead along-track, the camera looking along-track;
    a 30 cm CubeSat at 50 km is unresolved (0.2 px), detected by brightness when lit, not with
    the Sun in the field, behind the Earth, or in eclipse."""
    el = o.OrbitalElements(o.R_EARTH_M + 550e3, 0.001, 97.6 * DEG, 30 * DEG, 45 * DEG, 10 * DEG)
    rc, vc = el.to_rv()
    el2 = o.OrbitalElements(el.a_m, el.e, el.i_rad, el.raan_rad, el.argp_rad, el.nu_rad + 50e3 / el.a_m)
    rt, _ = el2.to_rv()
    T_CB = cameras.T_CB[0]  # camera along body +z
    q = _look_at(T_CB, rt - rc)
    cam = b.BearingCamera(f_px=3000.0, sigma_px=0.5, half_fov_rad=10 * DEG, T_CB=T_CB, min_size_px=3.0, limiting_magnitude=7.0)
    sun_side = np.cross(vc, np.cross(rc, vc))  # ⊥ the line of sight, roughly: φ ≈ 90°
    sun_side /= np.linalg.norm(sun_side)
    v = b.visibility(cam, q, rc, rt, sun_side, size_m=0.3, area_m2=0.06, albedo=0.2)
    assert v.in_fov and not v.resolved and v.bright and v.lit and not v.occulted and not v.sun_excluded and v.detected
    m = b.visual_magnitude(rc, rt, sun_side, 0.06, 0.2)
    assert 3.0 < m < 6.0
    # the Sun 5° from the line of sight
    los = (rt - rc) / np.linalg.norm(rt - rc)
    sun_near = los * math.cos(5 * DEG) + sun_side * math.sin(5 * DEG)
    assert b.visibility(cam, q, rc, rt, sun_near).sun_excluded and not b.visibility(cam, q, rc, rt, sun_near).detected
    # the target in eclipse: Sun behind the Earth as seen from the target
    dark = b.visibility(cam, q, rc, rt, -rt / np.linalg.norm(rt))
    assert not dark.lit and not dark.bright and not dark.detected
    # camera turned away
    q_away = _look_at(T_CB, -(rt - rc))
    assert not b.visibility(cam, q_away, rc, rt, sun_side).detected
    # behind the Earth
    assert b.visibility(cam, q, rc, -rc, sun_side).occulted
    # resolved when close (30 cm at 100 m: 9 px), whatever the light
    near = rc + 100.0 * los
    vn = b.visibility(cam, q, rc, near, -near / np.linalg.norm(near), size_m=0.3)
    assert vn.resolved and vn.detected
    # vectorised over pairs
    vv = b.visibility(cam, np.stack([q, q_away]), np.stack([rc, rc]), np.stack([rt, rt]), sun_side)
    np.testing.assert_array_equal(vv.detected, [True, False])
