"""Angles-only camera measurements (StarFOX-like): line of sight, noise, Jacobians, detection.

Measurement. Observer i sees target j as a point in its camera; what the image gives is the
direction, the unit line of sight in the camera frame C,

    u_C = ρ_C / |ρ_C|,   ρ_C = T_CB T(q_BI,i) T_IH (r_j − r_i),

with ``r`` the satellites' positions in H (the filter's Hill frame, :mod:`swarmcore.orbit`),
``T_IH`` Hill → inertial at the time of the image, ``q_BI,i`` the observer's attitude
(Shuster, scalar last, :mod:`swarmcore.quat`) and ``T_CB`` the fixed body → camera rotation
(camera +z along the boresight, +x/+y the image axes, as in :mod:`swarmcore.cameras`).

Residual, and why a unit vector: the measurement is the unit vector ``ũ`` and the residual
is its 2-vector in the tangent plane at the prediction û,

    y = Eᵀ ũ   (≈ Eᵀ (ũ − û), radians),   E = [e₁ e₂] (3×2) orthonormal, ⊥ û,

the "QUEST measurement model" of Shuster (J. Astronaut. Sci. 38(3), 1990) used by star
trackers. Unlike two angles (azimuth/elevation) it has no singularity at the poles of the
angle pair and no ±π wrap, and unlike image-plane coordinates it is defined for any
direction (a wide or body-fixed camera, a target near 90° off the boresight). The basis is
tied to the image axes: ``e₁`` is the camera x axis with its û component removed,
``e₂ = û × e₁`` (:func:`tangent_basis`), so near the boresight ``y`` is the centroid error
in pixels divided by the focal length.

Noise: a centroid with isotropic pixel noise σ_px (1σ per image axis) behind a pinhole of
focal length f_px gives normalised image coordinates ``m = [x/z, y/z]`` with noise σ_px/f_px.
Mapped into the tangent plane (``δu = (I − uuᵀ)[δm; 0] cos θ``, θ the angle off the
boresight) the angular noise is σ_px/f_px · cos²θ radially and · cos θ across: the common
σ_angle ≈ σ_px / f_px is exact on the boresight and an upper bound elsewhere.
:func:`bearing_noise_cov` gives both (``exact=False``: the isotropic bound).

Jacobians (attitude error ``q = δq(a) ⊗ q̂`` in the body frame, so ``T(q) ≈ (I − [a×]) T(q̂)``
and ``ρ_B = ρ̂_B + [ρ̂_B×] a``; with ``P = (I − ûûᵀ)/|ρ|`` and ``C = T_CB T(q̂_i) T_IH``):

    ∂u/∂a_i = P T_CB [ρ̂_B×],   ∂u/∂r_i = −P C,   ∂u/∂r_j = P C,

and those of ``y`` are ``Eᵀ`` times these (the range is not observed: ``P ρ = 0``).

Detection (pure functions on ECI positions, vectorised over pairs; :func:`visibility`
combines them for a :class:`BearingCamera`):

* field of view: a cone of half-angle α about the boresight (``u_z ≥ cos α``), or a
  rectangular sensor (:func:`in_image`);
* apparent size ``f_px · D / range`` (pinhole, on-axis) against a minimum in pixels — a
  resolved target;
* brightness of an unresolved target: a diffuse (Lambertian) sphere of cross-section A and
  albedo p, phase angle φ (Sun–target–observer), receives the flux fraction

      F / F_sun = 2 p A / (3 π² d²) · [(π − φ) cos φ + sin φ],

  i.e. visual magnitude ``m = −26.74 − 2.5 log10(F/F_sun)`` (e.g. McCue, Williams & Morford,
  Planet. Space Sci. 19, 1971; Hejduk, AMOS 2011), detected when ``m ≤ m_lim``; a target
  in the Earth's cylindrical shadow is dark;
* Earth occlusion: the segment observer → target passes within ``R`` of the Earth's centre
  (``R`` = R_E plus a margin for the atmosphere if wanted);
* Earth in the background: the ray beyond the target meets that sphere (a bright, cluttered
  background; rejected only if the camera asks);
* Sun exclusion: the angle between the line of sight and the Sun direction below the
  exclusion half-angle.

Comparisons are made on cosines and flux ratios, thresholds computed once in Python, so a
decision does not hinge on a platform's ``acos`` or ``log10``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from . import quat
from .orbit import R_EARTH_M

__all__ = [
    "SUN_MAGNITUDE",
    "BearingCamera",
    "line_of_sight",
    "line_of_sight_jacobians",
    "tangent_basis",
    "bearing_residuals",
    "bearing_noise_cov",
    "project_to_pixels",
    "pixels_to_line_of_sight",
    "in_field_of_view",
    "in_image",
    "apparent_size_px",
    "phase_angle_cos",
    "diffuse_sphere_flux_ratio",
    "visual_magnitude",
    "in_earth_shadow",
    "earth_occulted",
    "earth_in_background",
    "sun_excluded",
    "Visibility",
    "visibility",
]

#: Apparent visual magnitude of the Sun (V band).
SUN_MAGNITUDE = -26.74


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _mv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    return M[..., :, 0] * x[..., None, 0] + M[..., :, 1] * x[..., None, 1] + M[..., :, 2] * x[..., None, 2]


@dataclass(frozen=True)
class BearingCamera:
    """A camera that sees other satellites as points (angles only).

    ``f_px`` focal length in pixels, ``sigma_px`` centroid noise (1σ per image axis, px),
    ``half_fov_rad`` half-angle of its conical field of view, ``T_CB`` body → camera rotation
    (identity: the camera looks along the body +z). Detection: ``min_size_px`` (a resolved
    target at least this many pixels across) and/or ``limiting_magnitude`` (an unresolved
    one at least this bright); a target passes if it meets either configured criterion,
    every target if neither is set. ``sun_exclusion_rad`` keeps the Sun away from the line
    of sight, ``earth_radius_m`` is the occluding sphere, and ``reject_earth_background``
    drops targets seen against the Earth.
    """

    f_px: float
    sigma_px: float = 1.0
    half_fov_rad: float = math.radians(10.0)
    T_CB: np.ndarray = field(default_factory=lambda: np.eye(3))
    min_size_px: float | None = None
    limiting_magnitude: float | None = None
    sun_exclusion_rad: float = math.radians(30.0)
    earth_radius_m: float = R_EARTH_M
    reject_earth_background: bool = False

    @property
    def sigma_rad(self) -> float:
        """Angular noise on the boresight, ``σ_px / f_px`` (rad)."""
        return self.sigma_px / self.f_px


# --------------------------------------------------------------------------- measurement model


def _frames(q_BI: np.ndarray, T_IH: np.ndarray, T_CB: np.ndarray | None):
    """``(T_BH, C = T_CB T_BH)`` per pair."""
    T_BI = quat.attitude_matrix(np.asarray(q_BI, dtype=float))
    T_BH = T_BI @ np.asarray(T_IH, dtype=float)
    C = T_BH if T_CB is None else np.asarray(T_CB, dtype=float) @ T_BH
    return T_BH, C


def line_of_sight(
    q_BI: np.ndarray, T_IH: np.ndarray, r_obs_H_m: np.ndarray, r_tgt_H_m: np.ndarray, T_CB: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Unit line of sight ``u_C`` (..., 3) from observer to target in the camera frame (the
    body frame when ``T_CB`` is None), and the range (m). ``q_BI`` is the observer's attitude,
    ``T_IH`` (3, 3) or (..., 3, 3)."""
    _, C = _frames(q_BI, T_IH, T_CB)
    rho = _mv(C, np.asarray(r_tgt_H_m, dtype=float) - np.asarray(r_obs_H_m, dtype=float))
    rng = np.sqrt(_dot(rho, rho))
    return rho / rng[..., None], rng


def line_of_sight_jacobians(
    q_BI: np.ndarray, T_IH: np.ndarray, r_obs_H_m: np.ndarray, r_tgt_H_m: np.ndarray, T_CB: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``(u, ∂u/∂a_obs, ∂u/∂r_obs, ∂u/∂r_tgt)``, the Jacobians (..., 3, 3) of the unit vector
    w.r.t. the observer's attitude error (body frame) and the two positions (H frame)."""
    T_BH, C = _frames(q_BI, T_IH, T_CB)
    d = np.asarray(r_tgt_H_m, dtype=float) - np.asarray(r_obs_H_m, dtype=float)
    rho_B = _mv(T_BH, d)
    rho_C = _mv(C, d)
    rng = np.sqrt(_dot(rho_C, rho_C))
    u = rho_C / rng[..., None]
    P = (np.eye(3) - u[..., :, None] * u[..., None, :]) / rng[..., None, None]
    T_CB_ = np.eye(3) if T_CB is None else np.asarray(T_CB, dtype=float)
    du_da = P @ T_CB_ @ quat.skew(rho_B)
    du_dr_tgt = P @ C
    return u, du_da, -du_dr_tgt, du_dr_tgt


def tangent_basis(u: np.ndarray) -> np.ndarray:
    """Orthonormal basis ``E = [e₁ e₂]`` (..., 3, 2) of the plane ⊥ ``u`` (camera frame):
    ``e₁`` is the camera x axis less its ``u`` component, normalised (the y axis if ``u`` is
    within 1e-3 rad of ±x), ``e₂ = u × e₁``. Near the boresight ``e₁ ≈ x̂``, ``e₂ ≈ ŷ``: the
    image axes."""
    u = np.asarray(u, dtype=float)
    ex = np.zeros(u.shape)
    ex[..., 0] = 1.0
    ey = np.zeros(u.shape)
    ey[..., 1] = 1.0
    ref = np.where((np.abs(u[..., 0]) > 1.0 - 5e-7)[..., None], ey, ex)
    e1 = ref - _dot(ref, u)[..., None] * u
    e1 = e1 - _dot(e1, u)[..., None] * u  # Gram-Schmidt twice: orthogonal to round-off near the switch
    e1 = e1 / np.sqrt(_dot(e1, e1))[..., None]
    e2 = quat.cross(u, e1)
    return np.stack([e1, e2], axis=-1)


def bearing_residuals(
    u_meas_C: np.ndarray,
    q_BI: np.ndarray,
    T_IH: np.ndarray,
    r_obs_H_m: np.ndarray,
    r_tgt_H_m: np.ndarray,
    T_CB: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Residuals ``y = Eᵀ ũ`` (..., 2) of measured unit vectors ``u_meas_C`` against the
    prediction, and the Jacobians (..., 2, 3) of ``y`` w.r.t. the observer's attitude error,
    the observer's position and the target's position (measured minus predicted, linearised
    at the estimate: the measurement ``ũ = u(x̂ ⊞ δ)`` gives ``y ≈ H δ``). Also returns the
    basis ``E`` (..., 3, 2) the residual is expressed in (that of the noise covariance)."""
    u, du_da, du_dro, du_drt = line_of_sight_jacobians(q_BI, T_IH, r_obs_H_m, r_tgt_H_m, T_CB)
    E = tangent_basis(u)
    Et = np.swapaxes(E, -1, -2)
    um = np.asarray(u_meas_C, dtype=float)
    y = E[..., 0, :] * um[..., 0, None] + E[..., 1, :] * um[..., 1, None] + E[..., 2, :] * um[..., 2, None]  # Eᵀ ũ
    return y, Et @ du_da, Et @ du_dro, Et @ du_drt, E


def bearing_noise_cov(u_C: np.ndarray, sigma_px: float, f_px: float, exact: bool = True, E: np.ndarray | None = None) -> np.ndarray:
    """Covariance (..., 2, 2) of the tangent-plane residual for centroid noise σ_px per image
    axis: ``(σ_px/f_px)² M Mᵀ`` with ``M = Eᵀ[:, 0:2] cos θ`` (``cos θ = u_z``), exact for a
    pinhole camera; ``exact=False``: the isotropic ``(σ_px/f_px)² I``, its upper bound."""
    u = np.asarray(u_C, dtype=float)
    s2 = (sigma_px / f_px) ** 2
    if not exact:
        return s2 * np.broadcast_to(np.eye(2), (*u.shape[:-1], 2, 2)).copy()
    E_ = tangent_basis(u) if E is None else np.asarray(E, dtype=float)
    M = np.swapaxes(E_[..., 0:2, :], -1, -2) * u[..., 2, None, None]  # (..., 2, 2)
    return s2 * (M @ np.swapaxes(M, -1, -2))


def project_to_pixels(u_C: np.ndarray, f_px: float, c_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Pinhole image coordinates ``[f x/z + c_x, f y/z + c_y]`` (..., 2) of directions in front
    of the camera (z > 0)."""
    u = np.asarray(u_C, dtype=float)
    return np.stack([f_px * u[..., 0] / u[..., 2] + c_px[0], f_px * u[..., 1] / u[..., 2] + c_px[1]], axis=-1)


def pixels_to_line_of_sight(px: np.ndarray, f_px: float, c_px: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """Unit direction (..., 3) of image points: ``normalise([(p_x − c_x)/f, (p_y − c_y)/f, 1])``
    (how a centroid with pixel noise becomes a measured ``ũ``)."""
    p = np.asarray(px, dtype=float)
    v = np.stack([(p[..., 0] - c_px[0]) / f_px, (p[..., 1] - c_px[1]) / f_px, np.ones(p.shape[:-1])], axis=-1)
    return v / np.sqrt(_dot(v, v))[..., None]


# --------------------------------------------------------------------------- detection


def in_field_of_view(u_C: np.ndarray, half_fov_rad: float) -> np.ndarray:
    """Inside the cone of half-angle ``half_fov_rad`` about the camera +z axis."""
    return np.asarray(u_C, dtype=float)[..., 2] >= math.cos(half_fov_rad)


def in_image(u_C: np.ndarray, f_px: float, width_px: int, height_px: int) -> np.ndarray:
    """In front of the camera and inside a ``width × height`` sensor centred on the axis."""
    u = np.asarray(u_C, dtype=float)
    z = u[..., 2]
    front = z > 0.0
    zs = np.where(front, z, 1.0)
    return front & (np.abs(f_px * u[..., 0]) <= 0.5 * width_px * zs) & (np.abs(f_px * u[..., 1]) <= 0.5 * height_px * zs)


def apparent_size_px(size_m: np.ndarray | float, range_m: np.ndarray | float, f_px: float) -> np.ndarray:
    """Image extent (px) of a target ``size_m`` across at ``range_m``: ``f · D / range`` (pinhole,
    on-axis, a face square to the line of sight)."""
    return f_px * np.asarray(size_m, dtype=float) / np.asarray(range_m, dtype=float)


def phase_angle_cos(r_obs_I_m: np.ndarray, r_tgt_I_m: np.ndarray, sun_dir_I: np.ndarray) -> np.ndarray:
    """Cosine of the phase angle φ (Sun–target–observer) for a distant Sun along ``sun_dir_I``."""
    to_obs = np.asarray(r_obs_I_m, dtype=float) - np.asarray(r_tgt_I_m, dtype=float)
    s = np.asarray(sun_dir_I, dtype=float)
    return _dot(to_obs, s) / np.sqrt(_dot(to_obs, to_obs) * _dot(s, s))


def diffuse_sphere_flux_ratio(
    r_obs_I_m: np.ndarray, r_tgt_I_m: np.ndarray, sun_dir_I: np.ndarray, area_m2: np.ndarray | float, albedo: np.ndarray | float
) -> np.ndarray:
    """``F/F_sun = 2 p A (π²·3 d²)⁻¹ [(π − φ) cos φ + sin φ]`` of a Lambertian sphere (see the
    module's docstring); zero for a target in the Earth's shadow."""
    d = np.asarray(r_obs_I_m, dtype=float) - np.asarray(r_tgt_I_m, dtype=float)
    d2 = _dot(d, d)
    c = np.clip(phase_angle_cos(r_obs_I_m, r_tgt_I_m, sun_dir_I), -1.0, 1.0)
    phi = np.arccos(c)
    f = 2.0 * np.asarray(albedo, dtype=float) * np.asarray(area_m2, dtype=float) / (3.0 * np.pi**2 * d2) * ((np.pi - phi) * c + np.sqrt(1.0 - c * c))
    return np.where(in_earth_shadow(r_tgt_I_m, sun_dir_I), 0.0, f)


def visual_magnitude(
    r_obs_I_m: np.ndarray, r_tgt_I_m: np.ndarray, sun_dir_I: np.ndarray, area_m2: np.ndarray | float, albedo: np.ndarray | float
) -> np.ndarray:
    """Apparent visual magnitude ``−26.74 − 2.5 log10(F/F_sun)`` (+inf in the Earth's shadow)."""
    f = diffuse_sphere_flux_ratio(r_obs_I_m, r_tgt_I_m, sun_dir_I, area_m2, albedo)
    with np.errstate(divide="ignore"):
        return SUN_MAGNITUDE - 2.5 * np.log10(f)


def in_earth_shadow(r_I_m: np.ndarray, sun_dir_I: np.ndarray, radius_m: float = R_EARTH_M) -> np.ndarray:
    """Cylindrical shadow (Montenbruck & Gill, *Satellite Orbits*, §3.4.2): behind the Earth
    (``r·ŝ < 0``) and within ``radius_m`` of the Earth–Sun line."""
    r = np.asarray(r_I_m, dtype=float)
    s = np.asarray(sun_dir_I, dtype=float)
    s = s / np.sqrt(_dot(s, s))[..., None]
    along = _dot(r, s)
    perp2 = _dot(r, r) - along * along
    return (along < 0.0) & (perp2 < radius_m * radius_m)


def earth_occulted(r_obs_I_m: np.ndarray, r_tgt_I_m: np.ndarray, radius_m: float = R_EARTH_M) -> np.ndarray:
    """The segment observer → target passes closer than ``radius_m`` to the Earth's centre:
    closest point ``r_o + t d``, ``t = clip(−r_o·d / |d|², 0, 1)``."""
    ro = np.asarray(r_obs_I_m, dtype=float)
    d = np.asarray(r_tgt_I_m, dtype=float) - ro
    t = np.clip(-_dot(ro, d) / _dot(d, d), 0.0, 1.0)
    p = ro + t[..., None] * d
    return _dot(p, p) < radius_m * radius_m


def earth_in_background(r_obs_I_m: np.ndarray, r_tgt_I_m: np.ndarray, radius_m: float = R_EARTH_M) -> np.ndarray:
    """The ray from the observer through the target, beyond the target, meets the sphere of
    ``radius_m``: the target is seen against the Earth (points beyond it: ``t ≥ 1``)."""
    ro = np.asarray(r_obs_I_m, dtype=float)
    d = np.asarray(r_tgt_I_m, dtype=float) - ro
    # |ro + t d|² = R² ⇔ a t² + 2 b t + c = 0
    a = _dot(d, d)
    b = _dot(ro, d)
    c = _dot(ro, ro) - radius_m * radius_m
    disc = b * b - a * c
    t_far = (-b + np.sqrt(np.maximum(disc, 0.0))) / a
    return (disc > 0.0) & (t_far >= 1.0)


def sun_excluded(los_I: np.ndarray, sun_dir_I: np.ndarray, exclusion_rad: float) -> np.ndarray:
    """The Sun is within ``exclusion_rad`` of the line of sight (``cos∠ > cos exclusion``)."""
    u = np.asarray(los_I, dtype=float)
    s = np.asarray(sun_dir_I, dtype=float)
    return _dot(u, s) > math.cos(exclusion_rad) * np.sqrt(_dot(u, u) * _dot(s, s))


@dataclass(frozen=True)
class Visibility:
    """Per pair: each condition and the verdict ``detected``."""

    in_fov: np.ndarray
    resolved: np.ndarray
    bright: np.ndarray
    lit: np.ndarray
    occulted: np.ndarray
    earth_background: np.ndarray
    sun_excluded: np.ndarray
    detected: np.ndarray


def visibility(
    camera: BearingCamera,
    q_BI_obs: np.ndarray,
    r_obs_I_m: np.ndarray,
    r_tgt_I_m: np.ndarray,
    sun_dir_I: np.ndarray,
    size_m: np.ndarray | float = 0.3,
    area_m2: np.ndarray | float = 0.06,
    albedo: np.ndarray | float = 0.2,
) -> Visibility:
    """Can the observer's camera detect the target? All positions ECI, (..., 3) per pair;
    ``q_BI_obs`` the observer's attitude; the target's ``size_m`` (for the resolved test),
    ``area_m2`` and ``albedo`` (for the brightness test).

    ``detected = in_fov ∧ ¬occulted ∧ ¬sun_excluded ∧ (¬earth_background if rejected) ∧
    (resolved ∨ (lit ∧ bright))`` over the configured criteria (see :class:`BearingCamera`).
    """
    ro = np.asarray(r_obs_I_m, dtype=float)
    rt = np.asarray(r_tgt_I_m, dtype=float)
    los_I = rt - ro
    rng = np.sqrt(_dot(los_I, los_I))
    u_C = _mv(np.asarray(camera.T_CB, dtype=float) @ quat.attitude_matrix(np.asarray(q_BI_obs, dtype=float)), los_I / rng[..., None])
    fov = in_field_of_view(u_C, camera.half_fov_rad)
    lit = ~in_earth_shadow(rt, sun_dir_I, camera.earth_radius_m)
    occ = earth_occulted(ro, rt, camera.earth_radius_m)
    bg = earth_in_background(ro, rt, camera.earth_radius_m)
    sun = sun_excluded(los_I, sun_dir_I, camera.sun_exclusion_rad)
    shape = rng.shape
    resolved = (
        apparent_size_px(size_m, rng, camera.f_px) >= camera.min_size_px if camera.min_size_px is not None else np.zeros(shape, dtype=bool)
    )
    if camera.limiting_magnitude is not None:
        threshold = 10.0 ** (-0.4 * (camera.limiting_magnitude - SUN_MAGNITUDE))  # F/F_sun at m_lim
        bright = lit & (diffuse_sphere_flux_ratio(ro, rt, sun_dir_I, area_m2, albedo) >= threshold)
    else:
        bright = np.zeros(shape, dtype=bool)
    if camera.min_size_px is None and camera.limiting_magnitude is None:
        seen = np.ones(shape, dtype=bool)
    else:
        seen = resolved | bright
    detected = fov & ~occ & ~sun & seen
    if camera.reject_earth_background:
        detected = detected & ~bg
    return Visibility(fov, resolved, bright, lit, occ, bg, sun, detected)
