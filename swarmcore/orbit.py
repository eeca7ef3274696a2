"""Earth orbits: classical elements, the Hill (LVLH) frame, J2 + drag, a fixed-step propagator.

Frames and units (SI, radians):

* I — an Earth-centred quasi-inertial frame (ECI) whose z axis is the Earth's rotation and
  figure axis (precession, nutation and polar motion are ignored: the J2 field is
  symmetric about I's z and the atmosphere turns about it). Positions ``r_I_m``,
  velocities ``v_I_m_s``, accelerations ``a_I_m_s2``.
* H — the Hill / LVLH frame of a *chief* orbit: ``x̂ = r/|r|`` (radial), ``ẑ = h/|h|``
  (orbit normal, ``h = r × v``), ``ŷ = ẑ × x̂`` (along-track for a circular orbit). It is
  the frame of :mod:`swarmcore.dynamics` (x radial, y along-track, z orbit normal); there
  it turns at a constant rate, here it follows the chief's real orbit. ``T_IH`` maps H
  coordinates to I coordinates (columns x̂, ŷ, ẑ written in I).

Hill frame rate (Schaub & Junkins, *Analytical Mechanics of Space Systems*, §14.2; Alfriend
et al., *Spacecraft Formation Flying*, §4.1): with ``a`` the chief's acceleration,

    ω_HI_H = [ r (a·ẑ) / |h|,  0,  |h| / r² ]

(x̂ turns in the orbit plane at |h|/r²; an out-of-plane acceleration tilts the plane
about x̂). Two-body motion has ``a ∥ r`` and so ``ω = [0, 0, |h|/r²]``. A deputy at
``r_d = r_c + T_IH r_H`` has ``v_d = v_c + T_IH (v_H + ω × r_H)``: ``v_H`` is the rate of
``r_H`` seen in the turning frame (the "ω × r" transport term).

Forces (all in I):

* two-body ``a = −μ r / r³``;
* J2 (Vallado, *Fundamentals of Astrodynamics and Applications*, 4th ed., eq. 8-30;
  Montenbruck & Gill, *Satellite Orbits*, §3.2)::

      a_J2 = −(3/2) J2 μ R² / r⁵ · [x (1 − 5z²/r²),  y (1 − 5z²/r²),  z (3 − 5z²/r²)]

* drag of an exponential atmosphere (Vallado §8.6.2): ``a_D = −½ ρ(h) B |w| w`` with the
  ballistic coefficient in the ``C_D A / m`` form ``B`` (m²/kg, one per satellite; larger
  means more drag), altitude ``h = |r| − R`` over a *spherical* Earth,
  ``ρ(h) = ρ₀ exp(−(h − h₀)/H_s)`` and ``w`` the velocity relative to the air: with
  ``co_rotating=True`` (default) the atmosphere turns with the Earth,
  ``w = v − ω_E × r`` with ``ω_E = [0, 0, ω_E]``; otherwise ``w = v``.

Constants (SI): μ = 3.986004418e14 m³/s² (WGS 84 / IERS GM of the Earth with its
atmosphere), R = 6378137 m (WGS 84 equatorial radius), J2 = 1.08262668e-3 (the degree-2
zonal of the Earth, WGS 84 / EGM96 family, unnormalised), ω_E = 7.292115e-5 rad/s (IERS
nominal rotation rate). The default atmosphere is one band of Vallado's Table 8-4
(h₀ = 500 km, ρ₀ = 6.967e-13 kg/m³, H_s = 63.822 km), meant for 500–600 km.

Integrator: explicit Runge-Kutta with a fixed step (no error control, no step
adaptation), so the same inputs give the same sequence of floating-point operations on
every machine: ``"rk8"`` is the 12-stage, 8th-order formula of DOP853 (Hairer, Nørsett &
Wanner, *Solving ODEs I*, §II.10; coefficients as in scipy's ``dop853_coefficients``,
written out here), ``"rk4"`` the classical one. The force model is written with ``+ − × ÷``
and ``√`` only (IEEE-754 correctly rounded) plus an exponential for drag computed here
from those and ``ldexp`` (:func:`exp_det`), never BLAS nor the platform's ``exp``, so its
bits do not depend on CPU features or math libraries. It is vectorised over N
satellites; a numba-compiled loop (:data:`HAVE_NUMBA`) and its numpy twin execute the
same operations in the same order, and the tests hold them equal bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .kernels import HAVE_NUMBA

if HAVE_NUMBA:
    import numba

__all__ = [
    "MU_EARTH_M3_S2",
    "R_EARTH_M",
    "J2_EARTH",
    "OMEGA_EARTH_RAD_S",
    "HAVE_NUMBA",
    "OrbitalElements",
    "eccentric_anomaly",
    "mean_to_true_anomaly",
    "true_to_mean_anomaly",
    "coe_to_rv",
    "rv_to_coe",
    "orbital_period_s",
    "hill_T_IH",
    "hill_omega_HI_H",
    "eci_to_hill",
    "hill_to_eci",
    "ExponentialAtmosphere",
    "ForceModel",
    "TWO_BODY",
    "J2_ONLY",
    "exp_det",
    "acceleration",
    "acceleration_jacobians",
    "specific_energy",
    "Method",
    "substeps",
    "propagate",
    "propagate_grid",
    "j2_secular_rates",
    "warm_up",
]

MU_EARTH_M3_S2 = 3.986004418e14
R_EARTH_M = 6378137.0
J2_EARTH = 1.08262668e-3
OMEGA_EARTH_RAD_S = 7.292115e-5

_TWO_PI = 2.0 * math.pi


# --------------------------------------------------------------------------- elementwise helpers
# Matrix-vector products written as sums of elementwise products in a fixed order: no BLAS
# (whose kernels differ in the last bits between CPUs), the same bits everywhere.


def _mv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``M @ x`` over the last axes, (..., 3, 3) × (..., 3) → (..., 3)."""
    return M[..., :, 0] * x[..., None, 0] + M[..., :, 1] * x[..., None, 1] + M[..., :, 2] * x[..., None, 2]


def _mtv(M: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``Mᵀ @ x`` over the last axes."""
    return M[..., 0, :] * x[..., 0, None] + M[..., 1, :] * x[..., 1, None] + M[..., 2, :] * x[..., 2, None]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.stack(
        [a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1], a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2], a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]],
        axis=-1,
    )


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def _norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(_dot(a, a))


# --------------------------------------------------------------------------- Kepler


def eccentric_anomaly(M_rad: np.ndarray | float, e: np.ndarray | float) -> np.ndarray:
    """Solve Kepler's equation ``M = E − e sin E`` for ``E`` (elliptic orbits, 0 ≤ e < 1).

    Newton's iteration from ``E₀ = M + e sin M`` (``E₀ = π`` for e > 0.8; Vallado Algorithm
    2), to a change below 1e-15 rad; ``E`` in the same 2π-branch as ``M``.
    """
    M = np.asarray(M_rad, dtype=float)
    e_ = np.asarray(e, dtype=float)
    if np.any((e_ < 0.0) | (e_ >= 1.0)):
        raise ValueError("eccentric_anomaly: elliptic orbits only (0 <= e < 1)")
    base = np.floor(M / _TWO_PI) * _TWO_PI
    Mw = M - base
    E = np.where(e_ > 0.8, np.pi + 0.0 * Mw, Mw + e_ * np.sin(Mw))
    for _ in range(60):
        dE = (E - e_ * np.sin(E) - Mw) / (1.0 - e_ * np.cos(E))
        E = E - dE
        if np.all(np.abs(dE) < 1e-15):
            break
    return E + base


def mean_to_true_anomaly(M_rad: np.ndarray | float, e: np.ndarray | float) -> np.ndarray:
    """True anomaly ν from mean anomaly M (elliptic): ``tan(ν/2) = √((1+e)/(1−e)) tan(E/2)``."""
    E = eccentric_anomaly(M_rad, e)
    e_ = np.asarray(e, dtype=float)
    return 2.0 * np.arctan2(np.sqrt(1.0 + e_) * np.sin(0.5 * E), np.sqrt(1.0 - e_) * np.cos(0.5 * E))


def true_to_mean_anomaly(nu_rad: np.ndarray | float, e: np.ndarray | float) -> np.ndarray:
    """Mean anomaly M in [0, 2π) from true anomaly ν (elliptic): ``M = E − e sin E``."""
    nu = np.asarray(nu_rad, dtype=float)
    e_ = np.asarray(e, dtype=float)
    if np.any((e_ < 0.0) | (e_ >= 1.0)):
        raise ValueError("true_to_mean_anomaly: elliptic orbits only (0 <= e < 1)")
    E = 2.0 * np.arctan2(np.sqrt(1.0 - e_) * np.sin(0.5 * nu), np.sqrt(1.0 + e_) * np.cos(0.5 * nu))
    return np.mod(E - e_ * np.sin(E), _TWO_PI)


# --------------------------------------------------------------------------- elements ↔ state


@dataclass(frozen=True)
class OrbitalElements:
    """Classical (Keplerian) elements, SI units and radians.

    ``a_m`` semi-major axis (negative for a hyperbola), ``e`` eccentricity, ``i_rad``
    inclination, ``raan_rad`` right ascension of the ascending node Ω, ``argp_rad``
    argument of periapsis ω, ``nu_rad`` true anomaly ν.

    Degenerate orbits follow :func:`rv_to_coe`: equatorial ones have Ω = 0 (the node line is
    I's x axis), circular ones ω = 0 (ν counted from the node), so every state has elements
    and :func:`coe_to_rv` gives it back.
    """

    a_m: float
    e: float
    i_rad: float
    raan_rad: float
    argp_rad: float
    nu_rad: float

    @classmethod
    def from_mean_anomaly(cls, a_m: float, e: float, i_rad: float, raan_rad: float, argp_rad: float, M_rad: float) -> OrbitalElements:
        """Elements with the mean anomaly M given instead of ν (elliptic orbits)."""
        return cls(a_m, e, i_rad, raan_rad, argp_rad, float(mean_to_true_anomaly(M_rad, e)))

    @classmethod
    def from_array(cls, coe: np.ndarray) -> OrbitalElements:
        """From ``[a, e, i, Ω, ω, ν]``."""
        c = np.asarray(coe, dtype=float)
        return cls(*(float(x) for x in c))

    @classmethod
    def from_rv(cls, r_I_m: np.ndarray, v_I_m_s: np.ndarray, mu_m3_s2: float = MU_EARTH_M3_S2) -> OrbitalElements:
        return cls.from_array(rv_to_coe(r_I_m, v_I_m_s, mu_m3_s2))

    def as_array(self) -> np.ndarray:
        """``[a, e, i, Ω, ω, ν]`` (the layout of :func:`coe_to_rv` and :func:`rv_to_coe`)."""
        return np.array([self.a_m, self.e, self.i_rad, self.raan_rad, self.argp_rad, self.nu_rad])

    @property
    def M_rad(self) -> float:
        """Mean anomaly in [0, 2π) (elliptic orbits)."""
        return float(true_to_mean_anomaly(self.nu_rad, self.e))

    def to_rv(self, mu_m3_s2: float = MU_EARTH_M3_S2) -> tuple[np.ndarray, np.ndarray]:
        return coe_to_rv(self.as_array(), mu_m3_s2)


def coe_to_rv(coe: np.ndarray, mu_m3_s2: float = MU_EARTH_M3_S2) -> tuple[np.ndarray, np.ndarray]:
    """ECI position and velocity from elements ``coe = [a, e, i, Ω, ω, ν]`` (..., 6).

    Perifocal state (Curtis, *Orbital Mechanics for Engineering Students*, Algorithm 4.5;
    Vallado Algorithm 10): with ``p = a (1 − e²)``,

        r_P = p / (1 + e cos ν) [cos ν, sin ν, 0],   v_P = √(μ/p) [−sin ν, e + cos ν, 0],

    rotated to I by ``R3(−Ω) R1(−i) R3(−ω)``. Ellipses (a > 0, e < 1) and hyperbolas
    (a < 0, e > 1); parabolas (e = 1) have no finite a and are not represented.
    """
    c = np.asarray(coe, dtype=float)
    a, e, inc, raan, argp, nu = (c[..., k] for k in range(6))
    p = a * (1.0 - e * e)
    if np.any(p <= 0.0):
        raise ValueError("coe_to_rv: need p = a (1 − e²) > 0 (a > 0 with e < 1, or a < 0 with e > 1)")
    cn, sn = np.cos(nu), np.sin(nu)
    rp = p / (1.0 + e * cn)
    sq = np.sqrt(mu_m3_s2 / p)
    r_P = np.stack([rp * cn, rp * sn, np.zeros_like(rp)], axis=-1)
    v_P = np.stack([-sq * sn, sq * (e + cn), np.zeros_like(rp)], axis=-1)
    cO, sO, ci, si, cw, sw = np.cos(raan), np.sin(raan), np.cos(inc), np.sin(inc), np.cos(argp), np.sin(argp)
    # Columns of R3(−Ω) R1(−i) R3(−ω): the perifocal axes P̂, Q̂, Ŵ written in I.
    Q = np.stack(
        [
            np.stack([cO * cw - sO * sw * ci, -cO * sw - sO * cw * ci, sO * si], axis=-1),
            np.stack([sO * cw + cO * sw * ci, -sO * sw + cO * cw * ci, -cO * si], axis=-1),
            np.stack([sw * si, cw * si, ci], axis=-1),
        ],
        axis=-2,
    )
    return _mv(Q, r_P), _mv(Q, v_P)


def rv_to_coe(r_I_m: np.ndarray, v_I_m_s: np.ndarray, mu_m3_s2: float = MU_EARTH_M3_S2, tol: float = 1e-11) -> np.ndarray:
    """Elements ``[a, e, i, Ω, ω, ν]`` (..., 6) of ECI states (Curtis Algorithm 4.2,
    Vallado Algorithm 9), every angle from ``atan2`` and in [0, 2π) (i in [0, π]).

    ``h = r × v``, ``e = v × h / μ − r̂``, ``a = −μ / (2 ε)`` with ``ε = v²/2 − μ/r``, node
    line ``n̂ = ẑ × h / |ẑ × h|``. Degenerate cases, chosen so that :func:`coe_to_rv`
    returns the same state:

    * equatorial (``|ẑ × ĥ| < tol``): Ω = 0 and the node line is I's x axis;
    * circular (``e < tol``): ω = 0, ν is the argument of latitude (from the node line).

    Then ``ω = atan2(ê · (ĥ × n̂), ê · n̂)`` and ``ν = atan2(r · (ĥ × ê), r · ê)``.
    """
    r = np.asarray(r_I_m, dtype=float)
    v = np.asarray(v_I_m_s, dtype=float)
    h = _cross(r, v)
    hn = _norm(h)
    h_hat = h / hn[..., None]
    rn = _norm(r)
    e_vec = _cross(v, h) / mu_m3_s2 - r / rn[..., None]
    e = _norm(e_vec)
    energy = 0.5 * _dot(v, v) - mu_m3_s2 / rn
    a = -mu_m3_s2 / (2.0 * energy)
    inc = np.arccos(np.clip(h_hat[..., 2], -1.0, 1.0))
    node = np.stack([-h_hat[..., 1], h_hat[..., 0], np.zeros_like(hn)], axis=-1)  # ẑ × ĥ
    node_n = _norm(node)
    equatorial = node_n < tol
    x_axis = np.broadcast_to(np.array([1.0, 0.0, 0.0]), node.shape)
    n_hat = np.where(equatorial[..., None], x_axis, node / np.where(equatorial, 1.0, node_n)[..., None])
    raan = np.mod(np.arctan2(n_hat[..., 1], n_hat[..., 0]), _TWO_PI)
    circular = e < tol
    e_hat = np.where(circular[..., None], n_hat, e_vec / np.where(circular, 1.0, e)[..., None])
    m_hat = _cross(h_hat, n_hat)
    argp = np.mod(np.arctan2(_dot(e_hat, m_hat), _dot(e_hat, n_hat)), _TWO_PI)
    argp = np.where(circular, 0.0, argp)
    q_hat = _cross(h_hat, e_hat)
    nu = np.mod(np.arctan2(_dot(r, q_hat), _dot(r, e_hat)), _TWO_PI)
    return np.stack([a, np.where(circular, 0.0, e), inc, raan, argp, nu], axis=-1)


def orbital_period_s(a_m: float, mu_m3_s2: float = MU_EARTH_M3_S2) -> float:
    """Keplerian period ``2π √(a³/μ)``."""
    return _TWO_PI * math.sqrt(a_m**3 / mu_m3_s2)


# --------------------------------------------------------------------------- Hill frame


def hill_T_IH(r_I_m: np.ndarray, v_I_m_s: np.ndarray) -> np.ndarray:
    """``T_IH`` (..., 3, 3) of the chief state: columns ``x̂ = r̂``, ``ŷ = ẑ × x̂``, ``ẑ = ĥ``
    written in I (maps Hill coordinates to inertial ones; its transpose the other way)."""
    r = np.asarray(r_I_m, dtype=float)
    v = np.asarray(v_I_m_s, dtype=float)
    x = r / _norm(r)[..., None]
    h = _cross(r, v)
    z = h / _norm(h)[..., None]
    y = _cross(z, x)
    return np.stack([x, y, z], axis=-1)


def hill_omega_HI_H(r_I_m: np.ndarray, v_I_m_s: np.ndarray, a_I_m_s2: np.ndarray | None = None) -> np.ndarray:
    """Angular velocity of the Hill frame w.r.t. I, in H (rad/s), (..., 3):
    ``[r (a·ẑ)/|h|, 0, |h|/r²]``, so that ``d T_IH / dt = T_IH [ω×]``.

    ``a_I_m_s2`` is the chief's total acceleration; without it the frame rate of two-body
    motion (``a ∥ r``, no x component) is returned, which is exact only for two-body orbits.
    """
    r = np.asarray(r_I_m, dtype=float)
    v = np.asarray(v_I_m_s, dtype=float)
    h = _cross(r, v)
    hn = _norm(h)
    r2 = _dot(r, r)
    wz = hn / r2
    if a_I_m_s2 is None:
        wx = np.zeros_like(wz)
    else:
        a_n = _dot(np.asarray(a_I_m_s2, dtype=float), h) / hn
        wx = np.sqrt(r2) * a_n / hn
    return np.stack([wx, np.zeros_like(wz), wz], axis=-1)


def eci_to_hill(
    r_chief_I_m: np.ndarray,
    v_chief_I_m_s: np.ndarray,
    r_I_m: np.ndarray,
    v_I_m_s: np.ndarray,
    a_chief_I_m_s2: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Deputies' ECI states → relative position and velocity in the chief's Hill frame:
    ``r_H = T_IHᵀ (r − r_c)``, ``v_H = T_IHᵀ (v − v_c) − ω × r_H`` (the rate of ``r_H``
    seen in the turning frame). Chief (3,) or broadcastable, deputies (..., 3).
    ``a_chief_I_m_s2``: see :func:`hill_omega_HI_H`."""
    T = hill_T_IH(r_chief_I_m, v_chief_I_m_s)
    w = hill_omega_HI_H(r_chief_I_m, v_chief_I_m_s, a_chief_I_m_s2)
    r_H = _mtv(T, np.asarray(r_I_m, dtype=float) - r_chief_I_m)
    v_H = _mtv(T, np.asarray(v_I_m_s, dtype=float) - v_chief_I_m_s) - _cross(w, r_H)
    return r_H, v_H


def hill_to_eci(
    r_chief_I_m: np.ndarray,
    v_chief_I_m_s: np.ndarray,
    r_H_m: np.ndarray,
    v_H_m_s: np.ndarray,
    a_chief_I_m_s2: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`eci_to_hill`: ``r = r_c + T_IH r_H``, ``v = v_c + T_IH (v_H + ω × r_H)``."""
    T = hill_T_IH(r_chief_I_m, v_chief_I_m_s)
    w = hill_omega_HI_H(r_chief_I_m, v_chief_I_m_s, a_chief_I_m_s2)
    r_H = np.asarray(r_H_m, dtype=float)
    v_H = np.asarray(v_H_m_s, dtype=float)
    return np.asarray(r_chief_I_m) + _mv(T, r_H), np.asarray(v_chief_I_m_s) + _mv(T, v_H + _cross(w, r_H))


# --------------------------------------------------------------------------- force model


@dataclass(frozen=True)
class ExponentialAtmosphere:
    """``ρ(h) = rho0 exp(−(h − h0)/scale_height)`` over a spherical Earth (h = |r| − R).

    Defaults: Vallado (2013) Table 8-4, the band from 500 km (use another band's numbers
    outside roughly 450–650 km). ``co_rotating``: the air turns with the Earth at ω_E about
    I's z (``w = v − ω_E × r``); otherwise it is at rest in I.
    """

    rho0_kg_m3: float = 6.967e-13
    h0_m: float = 500e3
    scale_height_m: float = 63.822e3
    co_rotating: bool = True
    omega_earth_rad_s: float = OMEGA_EARTH_RAD_S

    def density_kg_m3(self, altitude_m: np.ndarray | float) -> np.ndarray:
        return self.rho0_kg_m3 * exp_det(-(np.asarray(altitude_m, dtype=float) - self.h0_m) / self.scale_height_m)


@dataclass(frozen=True)
class ForceModel:
    """Point mass + J2 (``j2 = 0`` switches it off) + optional drag (``atmosphere``).

    Drag needs each satellite's ballistic coefficient ``B = C_D A / m`` (m²/kg), given to
    :func:`acceleration` and the propagators; without an atmosphere it is ignored.
    """

    mu_m3_s2: float = MU_EARTH_M3_S2
    r_earth_m: float = R_EARTH_M
    j2: float = J2_EARTH
    atmosphere: ExponentialAtmosphere | None = None

    def _params(self) -> tuple[float, float, float, float, float, float, float]:
        """Flat parameters of the compiled kernels: μ, (3/2) J2 μ R², ρ₀ (0: no drag), h₀,
        1/H_s, ω_E (0: air at rest), R."""
        atm = self.atmosphere
        j2c = 1.5 * self.j2 * self.mu_m3_s2 * self.r_earth_m * self.r_earth_m
        if atm is None:
            return self.mu_m3_s2, j2c, 0.0, 0.0, 0.0, 0.0, self.r_earth_m
        we = atm.omega_earth_rad_s if atm.co_rotating else 0.0
        return self.mu_m3_s2, j2c, atm.rho0_kg_m3, atm.h0_m, 1.0 / atm.scale_height_m, we, self.r_earth_m


TWO_BODY = ForceModel(j2=0.0)
J2_ONLY = ForceModel()


# Deterministic exponential: Cody-Waite reduction x = k ln2 + r (|r| ≤ ln2/2), a degree-13
# Taylor polynomial of e^r (truncation < 1e-17 relative) and an exact scaling by 2^k.
_LN2_HI = 6.93147180369123816490e-01  # fdlibm's split of ln 2: k · _LN2_HI is exact for |k| < 2^20
_LN2_LO = 1.90821492927058770002e-10
_INV_LN2 = 1.44269504088896338700e00
_EXP_C = tuple(1.0 / math.factorial(j) for j in range(14))


def _exp_poly(r):
    p = _EXP_C[13]
    for j in range(12, -1, -1):
        p = p * r + _EXP_C[j]
    return p


def exp_det(x: np.ndarray | float) -> np.ndarray:
    """``exp(x)`` from ``+ − ×`` and ``ldexp`` only: the same bits on every machine (within
    2 ulp of the correctly rounded value; arguments clipped to [−700, 700])."""
    x = np.clip(np.asarray(x, dtype=float), -700.0, 700.0)
    k = np.rint(x * _INV_LN2)
    r = (x - k * _LN2_HI) - k * _LN2_LO
    return np.ldexp(_exp_poly(r), k.astype(np.int64))


def _exp_det_scalar(x):
    x = min(max(x, -700.0), 700.0)
    k = np.rint(x * _INV_LN2)
    r = (x - k * _LN2_HI) - k * _LN2_LO
    p = _EXP_C[13]
    for j in range(12, -1, -1):
        p = p * r + _EXP_C[j]
    return np.ldexp(p, int(k))


def _make_accel(exp_fn):
    """The force model written once, for numpy arrays (the twin) and for numba scalars:
    only ``+ − × ÷ √`` and ``exp_fn``, in one fixed order."""

    def accel(x, y, z, vx, vy, vz, bc, mu, j2c, rho0, h0, inv_hs, we, re):
        r2 = x * x + y * y + z * z
        r = np.sqrt(r2)
        ir2 = 1.0 / r2
        ir3 = ir2 / r
        g = -mu * ir3
        ax = g * x
        ay = g * y
        az = g * z
        if j2c != 0.0:
            k = -j2c * ir3 * ir2  # −(3/2) J2 μ R² / r⁵
            s = 5.0 * z * z * ir2
            ax = ax + k * x * (1.0 - s)
            ay = ay + k * y * (1.0 - s)
            az = az + k * z * (3.0 - s)
        if rho0 > 0.0:
            wx = vx + we * y  # w = v − ω_E × r, ω_E × r = [−ω_E y, ω_E x, 0]
            wy = vy - we * x
            wz = vz
            w = np.sqrt(wx * wx + wy * wy + wz * wz)
            f = -0.5 * (rho0 * exp_fn(-(r - re - h0) * inv_hs)) * bc * w
            ax = ax + f * wx
            ay = ay + f * wy
            az = az + f * wz
        return ax, ay, az

    return accel


_accel_numpy = _make_accel(exp_det)


def acceleration(
    r_I_m: np.ndarray, v_I_m_s: np.ndarray, model: ForceModel = J2_ONLY, ballistic_m2_kg: np.ndarray | float | None = None
) -> np.ndarray:
    """Total acceleration (..., 3) in I of satellites at ``r_I_m``, ``v_I_m_s`` (..., 3)."""
    r = np.asarray(r_I_m, dtype=float)
    v = np.asarray(v_I_m_s, dtype=float)
    bc = np.zeros(r.shape[:-1]) if ballistic_m2_kg is None else np.broadcast_to(np.asarray(ballistic_m2_kg, dtype=float), r.shape[:-1])
    ax, ay, az = _accel_numpy(r[..., 0], r[..., 1], r[..., 2], v[..., 0], v[..., 1], v[..., 2], bc, *model._params())
    return np.stack([ax, ay, az], axis=-1)


def acceleration_jacobians(
    r_I_m: np.ndarray, v_I_m_s: np.ndarray, model: ForceModel = J2_ONLY, ballistic_m2_kg: np.ndarray | float | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """``(∂a/∂r, ∂a/∂v)``, each (..., 3, 3), of :func:`acceleration` (the variational equations'
    blocks; Montenbruck & Gill §7.2).

    * two-body: ``∂a/∂r = −μ/r³ (I − 3 r̂ r̂ᵀ)``;
    * J2, with ``a_i = k r⁻⁵ r_i c_i``, ``k = −(3/2) J2 μ R²``, ``s = z²/r²``,
      ``c = [1 − 5s, 1 − 5s, 3 − 5s]``:
      ``∂a_i/∂r_j = k r⁻⁵ [δ_ij c_i − 5 r_i r_j c_i / r² − 10 r_i (z δ_jz − s r_j) / r²]``
      (symmetric, as the Hessian of a potential must be);
    * drag, ``a = −½ ρ B |w| w``, ``w = v − ω_E × r``, ``∂ρ/∂r = −ρ r̂ᵀ / H_s``:
      ``∂a/∂v = −½ ρ B (|w| I + w wᵀ / |w|)``, ``∂a/∂r = ½ ρ B |w| w r̂ᵀ / H_s − ∂a/∂v [ω_E×]``.
    """
    r = np.asarray(r_I_m, dtype=float)
    v = np.asarray(v_I_m_s, dtype=float)
    mu, j2c, rho0, h0, inv_hs, we, re = model._params()
    rn = _norm(r)
    ir2 = 1.0 / (rn * rn)
    u = r / rn[..., None]
    eye = np.eye(3)
    uu = u[..., :, None] * u[..., None, :]
    G = (-mu * ir2 / rn)[..., None, None] * (eye - 3.0 * uu)
    if j2c != 0.0:
        k = -j2c * ir2 * ir2 / rn
        z = r[..., 2]
        s = z * z * ir2
        c = np.stack([1.0 - 5.0 * s, 1.0 - 5.0 * s, 3.0 - 5.0 * s], axis=-1)
        ez = np.array([0.0, 0.0, 1.0])
        term = (
            eye * c[..., :, None]
            - 5.0 * (r[..., :, None] * r[..., None, :]) * (c * ir2[..., None])[..., :, None]
            - 10.0 * r[..., :, None] * ((z[..., None] * ez - s[..., None] * r) * ir2[..., None])[..., None, :]
        )
        G = G + k[..., None, None] * term
    D = np.zeros(G.shape)
    if rho0 > 0.0 and ballistic_m2_kg is not None:
        bc = np.broadcast_to(np.asarray(ballistic_m2_kg, dtype=float), r.shape[:-1])
        w = np.stack([v[..., 0] + we * r[..., 1], v[..., 1] - we * r[..., 0], v[..., 2]], axis=-1)  # v − ω_E × r
        wn = _norm(w)
        rho = rho0 * exp_det(-(rn - re - h0) * inv_hs)
        f = -0.5 * rho * bc
        D = f[..., None, None] * (wn[..., None, None] * eye + (w[..., :, None] * w[..., None, :]) / wn[..., None, None])
        # D [ω_E×] with [ω_E×] = [[0, −ω_E, 0], [ω_E, 0, 0], [0, 0, 0]]
        DW = np.stack([we * D[..., :, 1], -we * D[..., :, 0], np.zeros(D.shape[:-1])], axis=-1)
        G = G + (-f * wn * inv_hs)[..., None, None] * (w[..., :, None] * u[..., None, :]) - DW
    return G, D


def specific_energy(r_I_m: np.ndarray, v_I_m_s: np.ndarray, model: ForceModel = J2_ONLY) -> np.ndarray:
    """``v²/2 − U`` with the gravity potential ``U = μ/r [1 − (J2/2)(R/r)² (3z²/r² − 1)]``
    (conserved without drag)."""
    r = np.asarray(r_I_m, dtype=float)
    v = np.asarray(v_I_m_s, dtype=float)
    rn = _norm(r)
    s = r[..., 2] ** 2 / rn**2
    U = model.mu_m3_s2 / rn * (1.0 - 0.5 * model.j2 * (model.r_earth_m / rn) ** 2 * (3.0 * s - 1.0))
    return 0.5 * _dot(v, v) - U


# --------------------------------------------------------------------------- Runge-Kutta tableaus

_RK4_A = ((), (0.5,), (0.0, 0.5), (0.0, 0.0, 1.0))
_RK4_B = (1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0)

# DOP853's 12-stage 8th-order formula (Hairer, Nørsett & Wanner; the values of scipy's
# scipy/integrate/_ivp/dop853_coefficients.py, the error estimators and dense output left out).
_DOP853_A = (
    (),
    (0.05260015195876773,),
    (0.0197250569845379, 0.0591751709536137),
    (0.02958758547680685, 0.0, 0.08876275643042054),
    (0.2413651341592667, 0.0, -0.8845494793282861, 0.924834003261792),
    (0.037037037037037035, 0.0, 0.0, 0.17082860872947386, 0.12546768756682242),
    (0.037109375, 0.0, 0.0, 0.17025221101954405, 0.06021653898045596, -0.017578125),
    (0.03709200011850479, 0.0, 0.0, 0.17038392571223998, 0.10726203044637328, -0.015319437748624402, 0.008273789163814023),
    (0.6241109587160757, 0.0, 0.0, -3.3608926294469414, -0.868219346841726, 27.59209969944671, 20.154067550477894, -43.48988418106996),
    (
        0.47766253643826434, 0.0, 0.0, -2.4881146199716677, -0.590290826836843, 21.230051448181193, 15.279233632882423,
        -33.28821096898486, -0.020331201708508627,
    ),
    (
        -0.9371424300859873, 0.0, 0.0, 5.186372428844064, 1.0914373489967295, -8.149787010746927, -18.52006565999696,
        22.739487099350505, 2.4936055526796523, -3.0467644718982196,
    ),
    (
        2.273310147516538, 0.0, 0.0, -10.53449546673725, -2.0008720582248625, -17.9589318631188, 27.94888452941996,
        -2.8589982771350235, -8.87285693353063, 12.360567175794303, 0.6433927460157636,
    ),
)
_DOP853_B = (
    0.054293734116568765, 0.0, 0.0, 0.0, 0.0, 4.450312892752409, 1.8915178993145003, -5.801203960010585,
    0.3111643669578199, -0.1521609496625161, 0.20136540080403034, 0.04471061572777259,
)

Method = Literal["rk8", "rk4"]
_TABLEAUS: dict[str, tuple[tuple[tuple[float, ...], ...], tuple[float, ...]]] = {
    "rk8": (_DOP853_A, _DOP853_B),
    "rk4": (_RK4_A, _RK4_B),
}


def _tableau_arrays(method: str) -> tuple[np.ndarray, np.ndarray]:
    if method not in _TABLEAUS:
        raise ValueError(f"unknown method {method!r}: one of {sorted(_TABLEAUS)}")
    A_rows, B = _TABLEAUS[method]
    S = len(B)
    A = np.zeros((S, S))
    for s, row in enumerate(A_rows):
        A[s, : len(row)] = row
    return A, np.array(B)


def substeps(dt_s: float, step_s: float) -> int:
    """Number of equal substeps over ``dt_s`` with none longer than ``step_s``."""
    if step_s <= 0.0:
        raise ValueError("step_s must be positive")
    return max(1, math.ceil(abs(dt_s) / step_s - 1e-9))


# --------------------------------------------------------------------------- propagators


def _integrate_numpy(Y: np.ndarray, bc: np.ndarray, n_steps: int, h: float, A: np.ndarray, B: np.ndarray, p: tuple) -> np.ndarray:
    """Twin of the compiled kernel: ``Y`` (6, N) = [x, y, z, vx, vy, vz] rows."""
    S = B.size
    Ys = [Y[c].copy() for c in range(6)]
    for _ in range(n_steps):
        K: list[tuple] = []
        for s in range(S):
            if s == 0:
                st = Ys
            else:
                st = []
                for c in range(6):
                    acc = A[s, 0] * K[0][c]
                    for j in range(1, s):
                        acc = acc + A[s, j] * K[j][c]
                    st.append(Ys[c] + h * acc)
            ax, ay, az = _accel_numpy(st[0], st[1], st[2], st[3], st[4], st[5], bc, *p)
            K.append((st[3], st[4], st[5], ax, ay, az))
        new = []
        for c in range(6):
            acc = B[0] * K[0][c]
            for j in range(1, S):
                acc = acc + B[j] * K[j][c]
            new.append(Ys[c] + h * acc)
        Ys = new
    return np.stack(Ys)


if HAVE_NUMBA:
    _exp_nb = numba.njit(cache=True, fastmath=False)(_exp_det_scalar)
    _accel_nb = numba.njit(cache=True, fastmath=False, inline="always")(_make_accel(_exp_nb))

    @numba.njit(cache=True, fastmath=False)
    def _integrate_nb(Y, bc, n_steps, h, A, B, mu, j2c, rho0, h0, inv_hs, we, re):
        S = B.size
        N = Y.shape[1]
        out = np.empty((6, N))
        K = np.empty((S, 6))
        st = np.empty(6)
        y = np.empty(6)
        for n in range(N):
            for c in range(6):
                y[c] = Y[c, n]
            for _ in range(n_steps):
                for s in range(S):
                    if s == 0:
                        for c in range(6):
                            st[c] = y[c]
                    else:
                        for c in range(6):
                            acc = A[s, 0] * K[0, c]
                            for j in range(1, s):
                                acc = acc + A[s, j] * K[j, c]
                            st[c] = y[c] + h * acc
                    ax, ay, az = _accel_nb(st[0], st[1], st[2], st[3], st[4], st[5], bc[n], mu, j2c, rho0, h0, inv_hs, we, re)
                    K[s, 0] = st[3]
                    K[s, 1] = st[4]
                    K[s, 2] = st[5]
                    K[s, 3] = ax
                    K[s, 4] = ay
                    K[s, 5] = az
                for c in range(6):
                    acc = B[0] * K[0, c]
                    for j in range(1, S):
                        acc = acc + B[j] * K[j, c]
                    y[c] = y[c] + h * acc
            for c in range(6):
                out[c, n] = y[c]
        return out


def propagate(
    r_I_m: np.ndarray,
    v_I_m_s: np.ndarray,
    dt_s: float,
    model: ForceModel = J2_ONLY,
    *,
    step_s: float = 30.0,
    method: Method = "rk8",
    ballistic_m2_kg: np.ndarray | float | None = None,
    backend: Literal["auto", "numba", "numpy"] = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """Propagate N satellites (``(N, 3)`` or ``(3,)`` states) over ``dt_s`` (may be negative)
    in :func:`substeps` equal fixed steps of the chosen Runge-Kutta formula.

    ``backend``: ``"numba"`` (compiled loop), ``"numpy"`` (its vectorised twin) or
    ``"auto"`` (numba when installed). Both give the same bits.
    """
    r = np.asarray(r_I_m, dtype=float)
    v = np.asarray(v_I_m_s, dtype=float)
    single = r.ndim == 1
    r2, v2 = np.atleast_2d(r), np.atleast_2d(v)
    N = r2.shape[0]
    bc = np.zeros(N) if ballistic_m2_kg is None else np.ascontiguousarray(np.broadcast_to(np.asarray(ballistic_m2_kg, dtype=float), (N,)))
    Y = np.ascontiguousarray(np.concatenate([r2, v2], axis=1).T)
    n = substeps(dt_s, step_s)
    h = dt_s / n
    A, B = _tableau_arrays(method)
    p = model._params()
    use_nb = HAVE_NUMBA if backend == "auto" else backend == "numba"
    if use_nb and not HAVE_NUMBA:
        raise RuntimeError("numba is not installed")
    out = _integrate_nb(Y, bc, n, h, A, B, *p) if use_nb else _integrate_numpy(Y, bc, n, h, A, B, p)
    r_out, v_out = out[0:3].T.copy(), out[3:6].T.copy()
    return (r_out[0], v_out[0]) if single else (r_out, v_out)


def propagate_grid(
    r_I_m: np.ndarray,
    v_I_m_s: np.ndarray,
    t_s: np.ndarray,
    model: ForceModel = J2_ONLY,
    *,
    step_s: float = 30.0,
    method: Method = "rk8",
    ballistic_m2_kg: np.ndarray | float | None = None,
    backend: Literal["auto", "numba", "numpy"] = "auto",
) -> tuple[np.ndarray, np.ndarray]:
    """States at every time of ``t_s`` (K,), counted from the initial state's epoch (t = 0;
    ``t_s[0]`` may be 0 or later): positions and velocities (K, N, 3) (or (K, 3) for one
    satellite). Each interval is propagated on its own with :func:`propagate`."""
    t = np.asarray(t_s, dtype=float)
    r, v = np.asarray(r_I_m, dtype=float), np.asarray(v_I_m_s, dtype=float)
    rs, vs = [], []
    t_prev = 0.0
    for tk in t:
        if tk != t_prev:
            r, v = propagate(r, v, float(tk - t_prev), model, step_s=step_s, method=method, ballistic_m2_kg=ballistic_m2_kg, backend=backend)
            t_prev = float(tk)
        rs.append(r)
        vs.append(v)
    return np.stack(rs), np.stack(vs)


def j2_secular_rates(
    a_m: float, e: float, i_rad: float, mu_m3_s2: float = MU_EARTH_M3_S2, r_earth_m: float = R_EARTH_M, j2: float = J2_EARTH
) -> tuple[float, float, float]:
    """First-order secular rates (rad/s) of Ω, ω and M under J2 (Vallado eq. 9-41;
    Curtis eqs. 4.52-4.53), with ``n = √(μ/a³)``, ``p = a (1 − e²)``:

        Ω̇ = −(3/2) n J2 (R/p)² cos i
        ω̇ = (3/4) n J2 (R/p)² (5 cos² i − 1)
        Ṁ = n + (3/4) n J2 (R/p)² √(1 − e²) (3 cos² i − 1)
    """
    n = math.sqrt(mu_m3_s2 / a_m**3)
    p = a_m * (1.0 - e * e)
    k = n * j2 * (r_earth_m / p) ** 2
    c = math.cos(i_rad)
    return -1.5 * k * c, 0.75 * k * (5.0 * c * c - 1.0), n + 0.75 * k * math.sqrt(1.0 - e * e) * (3.0 * c * c - 1.0)


def warm_up() -> None:
    """Compile (or load from numba's cache) the propagator now, so that a process's first
    step is not also its compile step (no-op without numba)."""
    if HAVE_NUMBA:
        r = np.array([[R_EARTH_M + 500e3, 0.0, 0.0]])
        v = np.array([[0.0, 7600.0, 0.0]])
        propagate(r, v, 1.0, ForceModel(atmosphere=ExponentialAtmosphere()), step_s=1.0, ballistic_m2_kg=0.01, backend="numba")
