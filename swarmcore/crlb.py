"""The posterior Cramér–Rao bound of a run (Tichavský, Muravchik and Nehorai, IEEE TSP 1998).

For ``x_{k+1} = f(x_k) + w_k`` (``w ~ N(0, Q_k)``) and ``z = h(x) + v`` (``v ~ N(0, R)``)
the information matrix of the state obeys

    J_{k+1} = D22 − D21 (J_k + D11)⁻¹ D12,   D11 = Fᵀ Q⁻¹ F,  D12 = D21ᵀ = −Fᵀ Q⁻¹,
    D22 = Q⁻¹ + Σ Hᵀ R⁻¹ H,

with ``F``, ``H`` the Jacobians at the TRUE state (for these near-linear models the
expectations over the truth reduce to the one true trajectory the run flew). By the
matrix inversion lemma this is ``J_{k+1} = (Q + F J_k⁻¹ Fᵀ)⁻¹ + Σ Hᵀ R⁻¹ H``: the covariance
recursion of a Kalman filter linearised at the truth, ``P⁻ = F P Fᵀ + Q``,
``P⁺ = (P⁻⁻¹ + Λ)⁻¹`` — which is how it is computed here (``Q`` may be singular: a
disturbance switched off), with the full-swarm MEKF's own pieces
(:mod:`swarmcore.mekf`): the Van Loan attitude blocks, the translation transition, the
relative and absolute measurement Jacobians and the square-root information update
(:func:`swarmcore.mekf.information_posterior`). ``E[|e|²] ≥ trace(J⁻¹)`` for any
unbiased estimator of the state from the same measurements.

What the bound counts (:func:`posterior_crlb`):

* the truth's process noise (``disturbances``, the gyro's ``arw``/``rrw``), never the
  filter's tuning random walks (``filter.att_rw_other_rad_sqrt_s``, ``pos_rw_m_sqrt_s``);
* the gyros given (every satellite's, for the centralized bound): a satellite with its
  gyro has ``[a, Δβ]`` attitude states driven by the gyro noise, one without has
  ``[a, Δω]`` driven by the torque disturbance through Euler's equations;
* the absolute readings given (star tracker, GPS where the scenario has them);
* the relative measurements given, each with the covariance attached to it;
* the prior: the world's initial estimate error (``filter.initial_sigma``).

Nothing here reads an estimate: only the truth and which measurements were taken.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from . import kernels
from .mekf import (
    BLOCK,
    AbsoluteMeasurement,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    absolute_residual_of,
    attitude_phi_q,
    information_posterior,
    observed_indices,
    propagate_blockdiag,
    relative_residuals,
    translation_step,
)

__all__ = ["BoundArrays", "bound_params", "prior_covariance", "crlb_step", "posterior_crlb", "bound_of_covariance"]


@dataclass
class BoundArrays:
    """The bound at each step (K steps, n satellites): the smallest mean squared error any
    unbiased estimator fed the same measurements can have."""

    att_rad2: np.ndarray  # (K, n) trace of each satellite's 3×3 attitude-error block (rad²)
    pos_m2: np.ndarray  # (K, n) trace of each satellite's 3×3 position block (m², H)
    rel_pos_m2: np.ndarray  # (K, n, n) [i, j]: trace of the bound on r_j − r_i (m²); 0 on the diagonal
    kind: str  # "central" (every gyro and absolute reading) or "filter <f>"
    att_axes_rad2: np.ndarray | None = None  # (K, n, 3) per axis (body frame): the diagonal of the attitude block
    pos_axes_m2: np.ndarray | None = None  # (K, n, 3) per axis (H): the diagonal of the position block


def bound_params(sc) -> FilterParams:
    """The full-swarm filter's parameters with the TRUTH's noise: the world's disturbances
    and gyro (zero when switched off), no filter-only tuning, no gate, the truth's
    translation model (``orbit.model``)."""
    from .agent import filter_params
    from .world import world_params

    sc_truth = sc.model_copy(update={"filter": sc.filter.model_copy(update={"dynamics": "auto"})})
    fp = filter_params(sc_truth, 0)
    wp = world_params(sc)
    from dataclasses import replace

    return replace(fp, arw=wp.arw, rrw=wp.rrw, torque=wp.torque_sigma, accel=wp.accel_sigma, att_rw_other=0.0, pos_rw=0.0,
                   gate_threshold=None)


def prior_covariance(sc, gyro_mask: np.ndarray) -> np.ndarray:
    """(12n, 12n) the covariance of the world's initial estimate error
    (:func:`swarmcore.world.initial_estimate`): ``filter.initial_sigma``, the bias σ on the
    rate-block of the satellites whose gyro is counted, the rate σ on the others."""
    s = sc.filter.initial_sigma
    n = sc.n_sats
    d = np.empty((n, BLOCK))
    d[:, 0:3] = s.att_rad**2
    d[:, 3:6] = np.where(gyro_mask[:, None], s.bias_rad_s**2, s.rate_rad_s**2)
    d[:, 6:9] = s.pos_m**2
    d[:, 9:12] = s.vel_m_s**2
    return np.diag(d.ravel())


def _truth_estimate(truth, k: int, dt: float) -> SwarmEstimate:
    """The truth of step k (t_k = k dt) as a full-swarm estimate: where every Jacobian is
    evaluated (no covariance: the recursion carries its own)."""
    return SwarmEstimate(step=k, t=k * dt, q_BI=truth.q_BI[k], omega_BI_B=truth.omega_BI_B_rad_s[k], r_H=truth.r_H_m[k],
                         v_H=truth.v_H_m_s[k], bias_B=truth.bias_B_rad_s[k, 0], P=np.zeros((0, 0)))


def crlb_step(P: np.ndarray, n: int, phi: np.ndarray | None, Q: np.ndarray | None, Lam: np.ndarray | None) -> np.ndarray:
    """One step of the recursion in covariance form: ``P⁻ = Φ P Φᵀ + Q`` (block-diagonal
    Φ, Q as (n, 12, 12) blocks; None: no propagation), then ``P⁺ = (P⁻⁻¹ + Λ)⁻¹`` with the
    measurement information ``Λ`` (6n × 6n on the attitude and position errors,
    :func:`swarmcore.mekf.observed_indices`' order; None: nothing measured)."""
    if phi is not None:
        assert Q is not None
        P = propagate_blockdiag(P, phi, Q)
    if Lam is not None and np.any(Lam):
        P = information_posterior(P, n, Lam, np.zeros(6 * n), 0.0)[1]
    return P


def measurement_information(est: SwarmEstimate, params: FilterParams, relative: RelativeMeasurements | None,
                            absolute_of: Sequence[int] | np.ndarray, star_sigma_rad: float | None,
                            gps_sigma_m: Sequence[float | None], absolute_info: dict | None = None) -> np.ndarray | None:
    """``Λ = Σ Hᵀ R⁻¹ H`` (6n × 6n) of a step's relative batch and the absolute readings of
    the satellites ``absolute_of`` (star tracker of σ ``star_sigma_rad``, GPS of σ
    ``gps_sigma_m[i]``; None: no such sensor), with the filter's Jacobians at ``est`` (the
    truth); None when nothing was measured. ``absolute_info``: a cache of each satellite's
    absolute information block ``Haᵀ Ra⁻¹ Ha`` (its Jacobian is constant: rows of the identity
    on its ``[a, Δr]``, whatever the state)."""
    n = est.n
    absolute_info = {} if absolute_info is None else absolute_info
    Lam = None
    if relative is not None and len(relative):
        _y, Hi, Hj = relative_residuals(est, params, relative)
        Lam = kernels.information(n, relative.observer, relative.target, np.zeros((len(relative), 6)), Hi, Hj,
                                  relative.R_Bi)[0]
    for i in absolute_of:
        if i not in absolute_info:
            g = gps_sigma_m[i]
            meas = AbsoluteMeasurement(q_BI=None if star_sigma_rad is None else est.q_BI[i],
                                       r_H=None if g is None else est.r_H[i], sigma_att_rad=star_sigma_rad or 0.0,
                                       sigma_pos_m=g or 0.0)
            res = absolute_residual_of(est, int(i), meas)
            absolute_info[i] = None if res is None else res[1].T @ np.linalg.solve(res[2], res[1])
        info = absolute_info[i]
        if info is None:
            continue
        if Lam is None:
            Lam = np.zeros((6 * n, 6 * n))
        oo = slice(6 * i, 6 * i + 6)
        Lam[oo, oo] += info
    return Lam


def posterior_crlb(sc, truth, relative: Sequence[RelativeMeasurements | None], absolute: np.ndarray,
                   gyros: Sequence[int] | None = None, kind: str = "central") -> BoundArrays:
    """The bound along the run's truth (:class:`swarmcore.result.TruthArrays`, K steps: the
    truth's, ``sc.steps`` for a whole run, fewer for the steps an interrupted one recorded).

    ``relative[k]``: the relative measurements counted at step k (each with its R);
    ``absolute`` (K, n) bool: whose absolute reading is counted at step k (its star tracker
    and GPS as the scenario has them); ``gyros``: the satellites whose gyro drives their
    attitude (None: every one)."""
    from .world import world_params

    n, K = sc.n_sats, int(truth.q_BI.shape[0])
    params = bound_params(sc)
    wp = world_params(sc)
    star = wp.star_sigma if wp.star_enabled else None
    gps = [wp.gps_sigma if wp.gps_enabled and (wp.gps_sats is None or i in wp.gps_sats) else None for i in range(n)]
    gyro_mask = np.ones(n, dtype=bool) if gyros is None else np.isin(np.arange(n), list(gyros))
    P = prior_covariance(sc, gyro_mask)
    absolute_info: dict[int, np.ndarray | None] = {}
    att, pos, rel = np.full((K, n), np.nan), np.full((K, n), np.nan), np.full((K, n, n), np.nan)
    att_ax, pos_ax = np.full((K, n, 3), np.nan), np.full((K, n, 3), np.nan)
    for k in range(K):
        phi = Q = None
        if k > 0:
            prev = _truth_estimate(truth, k - 1, sc.dt_s)
            phi_att, q_att = attitude_phi_q(prev.omega_BI_B, params, gyro_mask)
            phi_trans = params.phi_trans if params.dynamics != "j2" else translation_step(prev, params)[1]
            phi = np.zeros((n, BLOCK, BLOCK))
            Q = np.zeros((n, BLOCK, BLOCK))
            phi[:, 0:6, 0:6], Q[:, 0:6, 0:6] = phi_att, q_att
            phi[:, 6:12, 6:12] = phi_trans
            Q[:, 6:12, 6:12] = params.q_trans
        now = _truth_estimate(truth, k, sc.dt_s)
        Lam = measurement_information(now, params, relative[k] if k < len(relative) else None,
                                      np.flatnonzero(absolute[k]), star, gps, absolute_info)
        P = crlb_step(P, n, phi, Q, Lam)
        att[k], pos[k], rel[k] = bound_of_covariance(P, n)
        d = np.diag(P).reshape(n, BLOCK)
        att_ax[k], pos_ax[k] = d[:, 0:3], d[:, 6:9]
    return BoundArrays(att_rad2=att, pos_m2=pos, rel_pos_m2=rel, kind=kind, att_axes_rad2=att_ax, pos_axes_m2=pos_ax)


def bound_of_covariance(P: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per satellite the traces of the attitude and position blocks of a 12n × 12n
    covariance, and per pair (i, j) the trace of the covariance of ``r_j − r_i``."""
    O = observed_indices(n)
    P_OO = P[np.ix_(O, O)].reshape(n, 6, n, 6)
    idx = np.arange(n)
    diag = P_OO[idx, :, idx, :]  # (n, 6, 6)
    att = np.trace(diag[:, 0:3, 0:3], axis1=1, axis2=2)
    pos = np.trace(diag[:, 3:6, 3:6], axis1=1, axis2=2)
    cross = np.trace(P_OO[:, 3:6, :, 3:6], axis1=1, axis2=3)  # (n, n) tr P_{r_i r_j}
    rel = pos[:, None] + pos[None, :] - cross - cross.T
    rel[idx, idx] = 0.0
    return att, pos, rel
