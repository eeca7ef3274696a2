"""Truth dynamics: Hill-Clohessy-Wiltshire translation and rigid-body attitude.

Frames: I inertial; H the HCW frame (x radial, y along-track, z orbit normal), aligned
with I at t = 0 and turning at the mean motion ``n`` about z, so ``T_IH(t)`` (H
coordinates to I coordinates) is a rotation about z by ``n t``.

Translation (per satellite, state ``[r_H, v_H]`` in m and m/s)::

    ẍ = 3n² x + 2n ẏ,   ÿ = −2n ẋ,   z̈ = −n² z   (+ white acceleration noise)

Attitude: ``q̇ = ½ [ω; 0] ⊗ q``, ``ω̇ = −J⁻¹ (ω × Jω) + J⁻¹ τ`` (Euler's equations,
integrated with RK4; never linearised for truth).
"""

from __future__ import annotations

import numpy as np

from . import quat

__all__ = [
    "hcw_A",
    "hcw_phi",
    "hcw_noise_cov",
    "T_IH",
    "euler_rate",
    "rk4_attitude",
]


def hcw_A(n: float) -> np.ndarray:
    """Continuous HCW system matrix for ``[r, v]`` (6×6), Coriolis terms included."""
    A = np.zeros((6, 6))
    A[0:3, 3:6] = np.eye(3)
    A[3, 0] = 3.0 * n * n
    A[3, 4] = 2.0 * n
    A[4, 3] = -2.0 * n
    A[5, 2] = -n * n
    return A


def hcw_phi(n: float, dt: float) -> np.ndarray:
    """Closed-form HCW state transition over ``dt`` for ``[r, v]`` (6×6)."""
    c, s = np.cos(n * dt), np.sin(n * dt)
    nt = n * dt
    phi = np.zeros((6, 6))
    phi[0:3, 0:3] = [[4 - 3 * c, 0, 0], [6 * (s - nt), 1, 0], [0, 0, c]]
    phi[0:3, 3:6] = [
        [s / n, 2 * (1 - c) / n, 0],
        [2 * (c - 1) / n, (4 * s - 3 * nt) / n, 0],
        [0, 0, s / n],
    ]
    phi[3:6, 0:3] = [[3 * n * s, 0, 0], [6 * n * (c - 1), 0, 0], [0, 0, -n * s]]
    phi[3:6, 3:6] = [[c, 2 * s, 0], [-2 * s, 4 * c - 3, 0], [0, 0, c]]
    return phi


def hcw_noise_cov(n: float, dt: float, sigma_acc: float, sigma_pos: float = 0.0) -> np.ndarray:
    """Discrete process noise of HCW over ``dt`` driven by white acceleration noise
    (density ``sigma_acc²``, m²/s³) and optional white position noise (density
    ``sigma_pos²``, m²/s), by Van Loan's method.

    The construction of ``filterpy.common.van_loan_discretization``, step for step (held
    equal to it, bit for bit, by ``tests/test_dynamics.py``), on ``scipy.linalg.expm``:
    importing filterpy imports every filterpy module and with them ``scipy.stats``, about
    0.6 s of CPU in every process that builds a filter (25 s of a 40-agent swarm's start
    on 2 cores), for this one function."""
    from scipy.linalg import expm

    # Unit-intensity noise through G: G Gᵀ = G Qc Gᵀ.
    G = np.diag([sigma_pos] * 3 + [sigma_acc] * 3)
    F = hcw_A(n)
    m = F.shape[0]
    A = np.zeros((2 * m, 2 * m))
    A[0:m, 0:m] = -F.dot(dt)
    A[0:m, m : 2 * m] = G.dot(G.T).dot(dt)
    A[m : 2 * m, m : 2 * m] = F.T.dot(dt)
    B = expm(A)
    Q = B[m : 2 * m, m : 2 * m].T.dot(B[0:m, m : 2 * m])
    return 0.5 * (Q + Q.T)


def T_IH(n: float, t: float) -> np.ndarray:
    """Matrix taking H coordinates to I coordinates at time ``t`` (rotation about z)."""
    c, s = np.cos(n * t), np.sin(n * t)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def euler_rate(omega: np.ndarray, J: np.ndarray, J_inv: np.ndarray, torque: np.ndarray | None = None) -> np.ndarray:
    """``ω̇ = J⁻¹ (τ − ω × Jω)`` for ``(..., 3)`` rates."""
    Jw = omega @ J.T
    rhs = -quat.cross(omega, Jw)
    if torque is not None:
        rhs = rhs + torque
    return rhs @ J_inv.T


def _att_rhs(q, w, J, J_inv, torque):
    # q̇ = ½ [ω;0] ⊗ q
    wq = np.concatenate([w, np.zeros((*w.shape[:-1], 1))], axis=-1)
    return 0.5 * quat.qmul(wq, q), euler_rate(w, J, J_inv, torque)


def rk4_attitude(
    q: np.ndarray,
    omega: np.ndarray,
    J: np.ndarray,
    dt: float,
    substeps: int = 10,
    torques: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Integrate quaternion and body rate over ``dt`` with RK4 (vectorised over satellites).

    ``torques`` (optional) has shape ``(substeps, ..., 3)``: a torque held constant over
    each substep (zero-order hold), which is how white torque noise enters the truth.
    """
    J = np.asarray(J, dtype=float)
    J_inv = np.linalg.inv(J)
    h = dt / substeps
    q = np.array(q, dtype=float)
    w = np.array(omega, dtype=float)
    for k in range(substeps):
        tau = None if torques is None else torques[k]
        k1q, k1w = _att_rhs(q, w, J, J_inv, tau)
        k2q, k2w = _att_rhs(q + 0.5 * h * k1q, w + 0.5 * h * k1w, J, J_inv, tau)
        k3q, k3w = _att_rhs(q + 0.5 * h * k2q, w + 0.5 * h * k2w, J, J_inv, tau)
        k4q, k4w = _att_rhs(q + h * k3q, w + h * k3w, J, J_inv, tau)
        q = q + (h / 6.0) * (k1q + 2 * k2q + 2 * k3q + k4q)
        w = w + (h / 6.0) * (k1w + 2 * k2w + 2 * k3w + k4w)
        q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return quat.normalize(q), w
