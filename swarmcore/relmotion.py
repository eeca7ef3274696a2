"""Relative motion about a known chief orbit, for the filter at long range (J2, drag).

The filter's reference point is a *chief* whose ECI state it knows at every time (it is
propagated with the same force model, :mod:`swarmcore.orbit`). Each deputy's state is
``x = [r_H, v_H]``: position and velocity relative to the chief in the chief's Hill frame
H (x radial, y along-track, z orbit normal; ``v_H`` the rate of ``r_H`` seen in H), as in
:mod:`swarmcore.dynamics`, but exact at any separation and under J2 and drag, where the
Hill-Clohessy-Wiltshire model is linear, circular and two-body.

Propagation over ``dt`` (:func:`propagate_relative`), batched over N deputies:

1. into I: ``ρ = T_IH r_H``, ``ρ̇ = T_IH (v_H + ω × r_H)`` (ρ = r_deputy − r_chief in I;
   ω the Hill frame's rate with the chief's full acceleration, :func:`orbit.hill_omega_HI_H`);
2. integrate the differenced equations together with the chief,

       r̈_c = a(r_c, v_c),        ρ̈ = a(r_c + ρ, v_c + ρ̇) − a(r_c, v_c),

   (the deputy is chief + relative), with the fixed-step Runge-Kutta formulas of
   :mod:`swarmcore.orbit`; the chief's state comes out bit for bit as :func:`orbit.propagate`
   gives it over the same ``dt`` and ``step_s``. ρ is accumulated in its own variable
   (no cancellation between two 7e6 m coordinates when it is read); the force difference
   is evaluated at ``r_c + ρ``, whose ~1e-9 m grain resolves it to ~1e-15 m/s², i.e. an
   absolute error of ~1e-8 m after an orbit at any separation (measured in the tests);
3. back into the Hill frame of the chief at ``t + dt``.

State transition matrix (6×6 per deputy, ``∂x(t+dt)/∂x(t)``), exact for the discrete
propagation (no linearisation beyond that of the derivative itself):

    Φ_H = G(t+dt)⁻¹ Φ_I G(t),   G = ∂[ρ, ρ̇]/∂[r_H, v_H] = [[T_IH, 0], [T_IH [ω×], T_IH]],
    G⁻¹ = [[T_IHᵀ, 0], [−[ω×] T_IHᵀ, T_IHᵀ]],

where ``Φ_I = ∂[ρ, ρ̇](t+dt)/∂[ρ, ρ̇](t)`` solves the variational equations along the
deputy's trajectory, ``Φ̇_I = [[0, I], [∂a/∂r, ∂a/∂v]] Φ_I``, ``Φ_I(t) = I`` (the chief does
not depend on the deputy, and G on the chief only). They are integrated with the same
Runge-Kutta formula in the same steps as the state, so Φ_H is the exact derivative of the
computed map (explicit Runge-Kutta methods commute with differentiation: Bock's "internal
numerical differentiation"), which the tests hold against central differences.

For a circular two-body chief and small separations this reduces to the closed-form HCW
transition (:func:`swarmcore.dynamics.hcw_phi`); the tests measure how HCW's error grows with
separation while this model's does not.

Arithmetic: elementwise only, in a fixed order (no BLAS), like :mod:`swarmcore.orbit`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .orbit import (
    J2_ONLY,
    ForceModel,
    Method,
    _tableau_arrays,
    acceleration,
    acceleration_jacobians,
    hill_omega_HI_H,
    hill_T_IH,
    substeps,
)

__all__ = [
    "RelativeStep",
    "hill_state_jacobian",
    "hill_state_jacobian_inverse",
    "propagate_relative",
]


def _mm(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``A @ B`` over the last two axes as a fixed-order sum of elementwise products."""
    acc = A[..., :, 0, None] * B[..., None, 0, :]
    for k in range(1, A.shape[-1]):
        acc = acc + A[..., :, k, None] * B[..., None, k, :]
    return acc


def _skew(w: np.ndarray) -> np.ndarray:
    z = np.zeros(w.shape[:-1])
    return np.stack(
        [np.stack([z, -w[..., 2], w[..., 1]], -1), np.stack([w[..., 2], z, -w[..., 0]], -1), np.stack([-w[..., 1], w[..., 0], z], -1)],
        axis=-2,
    )


def hill_state_jacobian(T_IH: np.ndarray, omega_HI_H: np.ndarray) -> np.ndarray:
    """``G = ∂[ρ, ρ̇]/∂[r_H, v_H] = [[T, 0], [T [ω×], T]]`` (..., 6, 6)."""
    G = np.zeros((*T_IH.shape[:-2], 6, 6))
    G[..., 0:3, 0:3] = T_IH
    G[..., 3:6, 3:6] = T_IH
    G[..., 3:6, 0:3] = _mm(T_IH, _skew(omega_HI_H))
    return G


def hill_state_jacobian_inverse(T_IH: np.ndarray, omega_HI_H: np.ndarray) -> np.ndarray:
    """``G⁻¹ = [[Tᵀ, 0], [−[ω×] Tᵀ, Tᵀ]]`` (..., 6, 6)."""
    Tt = np.swapaxes(T_IH, -1, -2)
    G = np.zeros((*T_IH.shape[:-2], 6, 6))
    G[..., 0:3, 0:3] = Tt
    G[..., 3:6, 3:6] = Tt
    G[..., 3:6, 0:3] = -_mm(_skew(omega_HI_H), Tt)
    return G


@dataclass(frozen=True)
class RelativeStep:
    """Result of :func:`propagate_relative` at ``t + dt``.

    ``r_H_m``, ``v_H_m_s`` (N, 3): the deputies in the chief's Hill frame; ``phi`` (N, 6, 6)
    the transition ``∂[r_H, v_H](t+dt)/∂[r_H, v_H](t)`` (None when not asked for);
    ``r_chief_I_m``, ``v_chief_I_m_s`` (3,) the chief propagated along.
    """

    r_H_m: np.ndarray
    v_H_m_s: np.ndarray
    phi: np.ndarray | None
    r_chief_I_m: np.ndarray
    v_chief_I_m_s: np.ndarray


def _rhs(y, model, bc_c, bc_d):
    """Derivatives of ``(chief, ρ)`` or ``(chief, ρ, Φ_I)``."""
    c, rho = y[0], y[1]
    r_c, v_c = c[0:3], c[3:6]
    a_c = acceleration(r_c, v_c, model, bc_c)
    r_d = r_c + rho[:, 0:3]
    v_d = v_c + rho[:, 3:6]
    a_d = acceleration(r_d, v_d, model, bc_d)
    dc = np.concatenate([v_c, a_c])
    drho = np.concatenate([rho[:, 3:6], a_d - a_c], axis=1)
    if len(y) == 2:
        return dc, drho
    Phi = y[2]
    G, D = acceleration_jacobians(r_d, v_d, model, bc_d)
    dPhi = np.empty_like(Phi)
    dPhi[:, 0:3, :] = Phi[:, 3:6, :]
    dPhi[:, 3:6, :] = _mm(G, Phi[:, 0:3, :]) + _mm(D, Phi[:, 3:6, :])
    return dc, drho, dPhi


def _rk(y, n_steps, h, A, B, f):
    """The Runge-Kutta loop of :func:`swarmcore.orbit._integrate_numpy` (same operations in
    the same order, so the chief's bits are those of :func:`swarmcore.orbit.propagate`) on a
    tuple of arrays."""
    S = B.size
    m = len(y)
    for _ in range(n_steps):
        K: list = []
        for s in range(S):
            if s == 0:
                st = y
            else:
                parts = []
                for c in range(m):
                    acc = A[s, 0] * K[0][c]
                    for j in range(1, s):
                        acc = acc + A[s, j] * K[j][c]
                    parts.append(y[c] + h * acc)
                st = tuple(parts)
            K.append(f(st))
        new = []
        for c in range(m):
            acc = B[0] * K[0][c]
            for j in range(1, S):
                acc = acc + B[j] * K[j][c]
            new.append(y[c] + h * acc)
        y = tuple(new)
    return y


def propagate_relative(
    r_chief_I_m: np.ndarray,
    v_chief_I_m_s: np.ndarray,
    r_H_m: np.ndarray,
    v_H_m_s: np.ndarray,
    dt_s: float,
    model: ForceModel = J2_ONLY,
    *,
    step_s: float = 30.0,
    method: Method = "rk8",
    ballistic_m2_kg: np.ndarray | float | None = None,
    chief_ballistic_m2_kg: float | None = None,
    with_stm: bool = True,
) -> RelativeStep:
    """Propagate deputies' Hill states ``r_H_m``, ``v_H_m_s`` ((N, 3) or (3,)) over ``dt_s``
    about the chief at ``r_chief_I_m``, ``v_chief_I_m_s`` (its ECI state at the same time),
    with their transition matrices (see the module's docstring).

    ``ballistic_m2_kg``: the deputies' ``C_D A / m`` (scalar or (N,)),
    ``chief_ballistic_m2_kg`` the chief's; both matter only with an atmosphere. The Hill
    frame rate uses the chief's model acceleration at each end (its J2 and drag included).
    """
    single = np.ndim(r_H_m) == 1
    r_H = np.atleast_2d(np.asarray(r_H_m, dtype=float))
    v_H = np.atleast_2d(np.asarray(v_H_m_s, dtype=float))
    N = r_H.shape[0]
    r_c = np.asarray(r_chief_I_m, dtype=float)
    v_c = np.asarray(v_chief_I_m_s, dtype=float)
    bc_d = None if ballistic_m2_kg is None else np.broadcast_to(np.asarray(ballistic_m2_kg, dtype=float), (N,))
    bc_c = chief_ballistic_m2_kg

    T0 = hill_T_IH(r_c, v_c)
    w0 = hill_omega_HI_H(r_c, v_c, acceleration(r_c, v_c, model, bc_c))
    G0 = hill_state_jacobian(T0, w0)
    rho0 = (G0[None] * np.concatenate([r_H, v_H], axis=1)[:, None, :])
    rho = rho0[..., 0]
    for k in range(1, 6):
        rho = rho + rho0[..., k]  # G0 x, a fixed-order sum
    Phi = np.broadcast_to(np.eye(6), (N, 6, 6)).copy()  # Φ_I(t) = I

    n = substeps(dt_s, step_s)
    A, B = _tableau_arrays(method)
    y0 = (np.concatenate([r_c, v_c]), rho, Phi) if with_stm else (np.concatenate([r_c, v_c]), rho)
    y1 = _rk(y0, n, dt_s / n, A, B, lambda y: _rhs(y, model, bc_c, bc_d))
    c, rho1 = y1[0], y1[1]

    r_c1, v_c1 = c[0:3], c[3:6]
    T1 = hill_T_IH(r_c1, v_c1)
    w1 = hill_omega_HI_H(r_c1, v_c1, acceleration(r_c1, v_c1, model, bc_c))
    Gi1 = hill_state_jacobian_inverse(T1, w1)
    x1 = Gi1[None, :, 0] * rho1[:, None, 0]
    for k in range(1, 6):
        x1 = x1 + Gi1[None, :, k] * rho1[:, None, k]
    phi = _mm(_mm(np.broadcast_to(Gi1, (N, 6, 6)), y1[2]), np.broadcast_to(G0, (N, 6, 6))) if with_stm else None
    r1, v1 = x1[:, 0:3].copy(), x1[:, 3:6].copy()
    if single:
        return RelativeStep(r1[0], v1[0], None if phi is None else phi[0], r_c1, v_c1)
    return RelativeStep(r1, v1, phi, r_c1, v_c1)
