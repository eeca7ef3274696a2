"""Numerical Jacobians on a manifold: central differences through retract and local.

The idea of GTSAM's ``numericalDerivative`` (python/gtsam/utils/numerical_derivative.py),
written here for this project's states: a map ``f: M → N`` between manifolds has, at
``x``, the Jacobian in local coordinates

    J[:, c] = ( (f(x ⊞ ε e_c) ⊟ f(x)) − (f(x ⊞ −ε e_c) ⊟ f(x)) ) / 2ε,

where ``x ⊞ δ`` is the retraction of the input manifold and ``y ⊟ y₀`` its inverse (the
"local" map, the δ with ``y = y₀ ⊞ δ``) on the output manifold. With
``g(s) = f(x ⊞ s e_c) ⊟ f(x)`` smooth and ``g(0) = 0``, the quotient is
``g'(0) + g'''(0) ε²/6 + O(ε⁴)``: second order, until round-off (≈ u/ε, u the unit
round-off) takes over. ε ≈ 1e-6 balances the two for O(1) curvature and values.

The manifolds of the filter (see :mod:`swarmcore.mekf` and :mod:`swarmcore.quat`):

* :data:`EUCLIDEAN` — any array, ``x ⊞ δ = x + δ``;
* :data:`ATTITUDE` — unit quaternions (scalar last, Shuster product, any leading shape),
  ``q = δq(a) ⊗ q̂`` with the error ``a`` in the body ("to") frame, 3 per quaternion;
* :func:`product` — tuples of the above, their tangent vectors concatenated;
* :func:`swarm_state` — the whole-swarm :class:`~swarmcore.mekf.SwarmEstimate`, 12 per
  satellite ``[a, Δω|Δβ, Δr, Δv]``: others carry a rate error ``Δω = ω − ω̂``; the own
  satellite (gyro mode) carries its bias error ``Δβ = β − β̂`` and its rate is the
  bias-corrected gyro, so it moves with the bias, ``ω = ω̂ − Δβ``.

Written by hand because numdifftools and scipy's ``approx_fprime`` differentiate in a
flat vector space only; a quaternion perturbed additively leaves the unit sphere and its
error is not the filter's error.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from swarmcore import quat
from swarmcore.mekf import BLOCK, SwarmEstimate

__all__ = [
    "Manifold",
    "EUCLIDEAN",
    "ATTITUDE",
    "product",
    "swarm_state",
    "numerical_jacobian",
    "numerical_generator",
]


@dataclass(frozen=True)
class Manifold:
    """A retraction ``x ⊞ δ``, its inverse ``y ⊟ x`` and the tangent dimension at ``x``.

    ``retract(x, δ)`` takes a flat δ of ``dim(x)`` numbers; ``local(y, x)`` returns the flat
    δ with ``y = x ⊞ δ`` (the argument order of :func:`swarmcore.quat.local`).
    """

    retract: Callable[[Any, np.ndarray], Any]
    local: Callable[[Any, Any], np.ndarray]
    dim: Callable[[Any], int]


def _vec_retract(x, d):
    x = np.asarray(x, dtype=float)
    return x + np.reshape(d, x.shape)


def _vec_local(y, x):
    return (np.asarray(y, dtype=float) - np.asarray(x, dtype=float)).ravel()


def _att_retract(q, d):
    q = np.asarray(q, dtype=float)
    return quat.retract(q, np.reshape(d, (*q.shape[:-1], 3)))


def _att_local(q, q_hat):
    return quat.local(np.asarray(q, dtype=float), np.asarray(q_hat, dtype=float)).ravel()


EUCLIDEAN = Manifold(_vec_retract, _vec_local, lambda x: int(np.size(x)))
ATTITUDE = Manifold(_att_retract, _att_local, lambda q: 3 * (int(np.size(q)) // 4))


def product(*parts: Manifold) -> Manifold:
    """The product manifold of ``parts``: points are tuples, tangent vectors concatenated."""

    def split(x, d):
        cuts = np.cumsum([m.dim(xi) for m, xi in zip(parts, x, strict=True)])[:-1]
        return np.split(np.asarray(d, dtype=float), cuts)

    def retract(x, d):
        return tuple(m.retract(xi, di) for m, xi, di in zip(parts, x, split(x, d), strict=True))

    def local(y, x):
        return np.concatenate([m.local(yi, xi) for m, yi, xi in zip(parts, y, x, strict=True)])

    def dim(x):
        return sum(m.dim(xi) for m, xi in zip(parts, x, strict=True))

    return Manifold(retract, local, dim)


def swarm_state(own: int) -> Manifold:
    """The filter's error state of a :class:`SwarmEstimate` whose own satellite is ``own``.

    Written from the error definitions in :mod:`swarmcore.mekf`, not from the filter's
    reset, so the tests can hold the reset to it. The covariance ``P`` is carried along
    unchanged (it is not part of the state).
    """

    def retract(est: SwarmEstimate, d) -> SwarmEstimate:
        n = est.n
        d = np.reshape(d, (n, BLOCK))
        w = est.omega_BI_B + d[:, 3:6]
        w[own] = est.omega_BI_B[own] - d[own, 3:6]  # ω = ω̃ − β: the rate follows the bias
        return SwarmEstimate(
            step=est.step,
            t=est.t,
            q_BI=quat.retract(est.q_BI, d[:, 0:3]),
            omega_BI_B=w,
            r_H=est.r_H + d[:, 6:9],
            v_H=est.v_H + d[:, 9:12],
            bias_B=est.bias_B + d[own, 3:6],
            P=est.P,
        )

    def local(est: SwarmEstimate, ref: SwarmEstimate) -> np.ndarray:
        d = np.empty((ref.n, BLOCK))
        d[:, 0:3] = quat.local(est.q_BI, ref.q_BI)
        d[:, 3:6] = est.omega_BI_B - ref.omega_BI_B
        d[own, 3:6] = est.bias_B - ref.bias_B
        d[:, 6:9] = est.r_H - ref.r_H
        d[:, 9:12] = est.v_H - ref.v_H
        return d.ravel()

    return Manifold(retract, local, lambda est: BLOCK * est.n)


def numerical_jacobian(
    f: Callable[[Any], Any],
    x: Any,
    domain: Manifold = EUCLIDEAN,
    codomain: Manifold = EUCLIDEAN,
    eps: float = 1e-6,
) -> np.ndarray:
    """``∂(f(x ⊞ δ) ⊟ f(x)) / ∂δ`` at ``δ = 0`` by central differences, shape (dim f(x), dim x).

    A scalar ``x`` on :data:`EUCLIDEAN` is a 1-vector (so a time derivative is a column).
    """
    y0 = f(x)
    k = domain.dim(x)
    cols = []
    for c in range(k):
        e = np.zeros(k)
        e[c] = eps
        plus = codomain.local(f(domain.retract(x, e)), y0)
        minus = codomain.local(f(domain.retract(x, -e)), y0)
        cols.append((plus - minus) / (2.0 * eps))
    return np.stack(cols, axis=-1)


def numerical_generator(
    flow: Callable[[Any, float], Any],
    x: Any,
    manifold: Manifold,
    eps: float = 1e-4,
    h: float = 1e-3,
) -> np.ndarray:
    """The continuous error dynamics ``F`` of a flow, ``δ̇ = F δ``, at ``x``.

    ``Φ(τ) = ∂(flow(x ⊞ δ, τ) ⊟ flow(x, τ)) / ∂δ`` is the error transition over a time τ
    (:func:`numerical_jacobian`, step ``eps``) and ``F = dΦ/dτ`` at ``τ = 0`` (central
    differences again, step ``h``). Both differences are second order, with truncation
    errors ∝ eps² and h²; round-off grows like ``u / (eps h)``, hence the larger default
    ``eps`` than for a single differentiation.
    """
    k = manifold.dim(x)

    def phi(tau):
        return numerical_jacobian(lambda z: flow(z, float(tau[0])), x, manifold, manifold, eps).ravel()

    return numerical_jacobian(phi, np.zeros(1), eps=h).reshape(k, k)
