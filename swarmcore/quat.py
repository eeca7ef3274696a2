"""Quaternions, scalar LAST, Shuster / Crassidis-Junkins convention.

Conventions (pinned by ``tests/test_quat.py``):

* ``q = [e sin(theta/2), cos(theta/2)]``: vector part first, scalar last, unit norm.
* ``T(q)`` is the *attitude matrix*: it maps coordinates from the "from" frame to
  the "to" frame, ``T(q_BI) @ v_I == v_B``.
* Composition ``qa ⊗ qb`` is ordered like the matrices: ``T(qa ⊗ qb) = T(qa) T(qb)``
  (Shuster's "natural" order; Hamilton's product with the sign of the cross term
  flipped).
* ``scipy.spatial.transform.Rotation.from_quat(q)`` (also scalar last) represents the
  *active* rotation ``R = T(q).T``; its product is Hamilton's, so ``qa ⊗ qb`` here is
  ``Rotation(qb) * Rotation(qa)`` there.
* Attitude error: ``q = δq(a) ⊗ q̂`` with the error expressed in the "to" frame.
  ``δq(a) = normalise([a/2, 1])`` and its exact inverse ``a = 2 vec(δq) / δq4`` (twice
  the Gibbs vector; equal to twice the vector part to first order, as in the MEKF
  literature, and defined for any angle below 180°).
* Kinematics: ``q̇ = ½ [ω; 0] ⊗ q`` with ω the body rate (of B w.r.t. I) in B, so a step
  at constant rate is ``q_{k+1} = rotvec_to_quat(ω Δt) ⊗ q_k``.

All functions broadcast over leading axes (``(..., 4)`` and ``(..., 3)`` arrays).
Written by hand (rather than through scipy's Rotation) because the filter needs the
Shuster product and error parameterisation directly, vectorised over thousands of
measurements, and scipy's conventions differ in both order and matrix sense.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "IDENTITY",
    "normalize",
    "qmul",
    "qconj",
    "attitude_matrix",
    "from_attitude_matrix",
    "rotvec_to_quat",
    "quat_to_rotvec",
    "dq_from_err",
    "err_from_dq",
    "retract",
    "local",
    "propagate_constant_rate",
    "random_quaternion",
    "skew",
    "cross",
    "angle_between",
]

IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def _cross_ref(a, b):
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _skew_ref(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _qmul_ref(a, b):
    """Shuster product, written out: [a4 b_v + b4 a_v − a_v × b_v, a4 b4 − a_v·b_v]."""
    return np.r_[a[3] * b[:3] + b[3] * a[:3] - _cross_ref(a[:3], b[:3]), a[3] * b[3] - a[:3] @ b[:3]]


def _attitude_ref(q):
    """T(q) = (q4² − |e|²) I + 2 e eᵀ − 2 q4 [e×], written out."""
    e, w = q[:3], q[3]
    return (w * w - e @ e) * np.eye(3) + 2.0 * np.outer(e, e) - 2.0 * w * _skew_ref(e)


# The products below are bilinear (or quadratic) in their inputs, so each is one outer
# product and one matmul with a constant tensor read off the written-out reference forms
# above: a few numpy calls instead of dozens, whatever the batch shape.
_E4 = np.eye(4)
_E3 = np.eye(3)
_QMUL = np.array([[_qmul_ref(_E4[i], _E4[j]) for j in range(4)] for i in range(4)]).reshape(16, 4)
_ATT = np.array(
    [[0.25 * (_attitude_ref(_E4[i] + _E4[j]) - _attitude_ref(_E4[i] - _E4[j])).ravel() for j in range(4)] for i in range(4)]
).reshape(16, 9)
_CROSS = np.array([[_cross_ref(_E3[i], _E3[j]) for j in range(3)] for i in range(3)]).reshape(9, 3)
_SKEW = np.array([_skew_ref(_E3[i]).ravel() for i in range(3)])  # (3, 9)


def _outer(a, b, k):
    shape = np.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    return (a[..., :, None] * b[..., None, :]).reshape((*shape, k))


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a × b`` over the last axis (same as ``np.cross``)."""
    return _outer(np.asarray(a, dtype=float), np.asarray(b, dtype=float), 9) @ _CROSS


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix ``[v×]`` so that ``skew(v) @ w == np.cross(v, w)``."""
    v = np.asarray(v, dtype=float)
    return (v @ _SKEW).reshape((*v.shape[:-1], 3, 3))


def normalize(q: np.ndarray) -> np.ndarray:
    """Unit quaternion with non-negative scalar part (a canonical sign)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Shuster product ``a ⊗ b`` with ``T(a ⊗ b) = T(a) @ T(b)``."""
    return _outer(np.asarray(a, dtype=float), np.asarray(b, dtype=float), 16) @ _QMUL


def qconj(q: np.ndarray) -> np.ndarray:
    """Inverse of a unit quaternion: ``T(qconj(q)) = T(q).T``."""
    q = np.asarray(q, dtype=float)
    return np.concatenate([-q[..., :3], q[..., 3:4]], axis=-1)


def attitude_matrix(q: np.ndarray) -> np.ndarray:
    """``T(q) = (q4² − |e|²) I + 2 e eᵀ − 2 q4 [e×]`` (maps "from" to "to" coordinates)."""
    q = np.asarray(q, dtype=float)
    return (_outer(q, q, 16) @ _ATT).reshape((*q.shape[:-1], 3, 3))


def from_attitude_matrix(T: np.ndarray) -> np.ndarray:
    """Inverse of :func:`attitude_matrix` (Shepperd's method, via the transpose in scipy)."""
    from scipy.spatial.transform import Rotation

    T = np.asarray(T, dtype=float)
    flat = T.reshape(-1, 3, 3)
    q = Rotation.from_matrix(np.swapaxes(flat, -1, -2)).as_quat()
    return normalize(q.reshape((*T.shape[:-2], 4)))


def rotvec_to_quat(theta: np.ndarray) -> np.ndarray:
    """Quaternion of a rotation vector θ (axis × angle): ``[sin(|θ|/2) θ/|θ|, cos(|θ|/2)]``.

    ``T(rotvec_to_quat(θ)) ≈ I − [θ×]`` for small θ.
    """
    theta = np.asarray(theta, dtype=float)
    ang = np.linalg.norm(theta, axis=-1, keepdims=True)
    half = 0.5 * ang
    # sin(x/2)/x with a series for tiny angles (avoids 0/0).
    small = ang < 1e-8
    safe = np.where(small, 1.0, ang)
    k = np.where(small, 0.5 - ang**2 / 48.0, np.sin(half) / safe)
    return np.concatenate([k * theta, np.cos(half)], axis=-1)


def quat_to_rotvec(q: np.ndarray) -> np.ndarray:
    """Rotation vector (axis × angle in [0, π]) of a unit quaternion."""
    q = normalize(q)
    v = q[..., :3]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, q[..., 3:4])
    small = s < 1e-12
    k = np.where(small, 2.0, ang / np.where(small, 1.0, s))
    return k * v


def dq_from_err(a: np.ndarray) -> np.ndarray:
    """Error quaternion ``δq(a) = normalise([a/2, 1])`` (retraction of the MEKF)."""
    a = np.asarray(a, dtype=float)
    q = np.concatenate([0.5 * a, np.ones((*a.shape[:-1], 1))], axis=-1)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def err_from_dq(dq: np.ndarray) -> np.ndarray:
    """Inverse of :func:`dq_from_err`: ``a = 2 vec(δq) / δq4`` (sign-independent)."""
    dq = np.asarray(dq, dtype=float)
    return 2.0 * dq[..., :3] / dq[..., 3:4]


def retract(q_hat: np.ndarray, a: np.ndarray) -> np.ndarray:
    """``q = δq(a) ⊗ q̂``: apply an attitude error expressed in the "to" frame."""
    return normalize(qmul(dq_from_err(a), q_hat))


def local(q: np.ndarray, q_hat: np.ndarray) -> np.ndarray:
    """Attitude error ``a`` with ``q = δq(a) ⊗ q̂`` (inverse of :func:`retract`)."""
    return err_from_dq(qmul(q, qconj(q_hat)))


def propagate_constant_rate(q: np.ndarray, omega_B: np.ndarray, dt: float) -> np.ndarray:
    """Exact attitude step at constant body rate: ``Ω(ωΔt) q = rotvec(ωΔt) ⊗ q``."""
    return normalize(qmul(rotvec_to_quat(np.asarray(omega_B) * dt), q))


def random_quaternion(rng: np.random.Generator, size: int | tuple | None = None) -> np.ndarray:
    """Uniformly distributed unit quaternions (normalised 4-D Gaussian)."""
    shape = (() if size is None else (size,) if isinstance(size, int) else tuple(size)) + (4,)
    return normalize(rng.standard_normal(shape))


def angle_between(qa: np.ndarray, qb: np.ndarray) -> np.ndarray:
    """Rotation angle (rad, in [0, π]) of ``qa ⊗ qb⁻¹``."""
    d = qmul(qa, qconj(qb))
    v = np.linalg.norm(d[..., :3], axis=-1)
    return 2.0 * np.arctan2(v, np.abs(d[..., 3]))
