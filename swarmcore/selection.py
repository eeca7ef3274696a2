"""Measurement selection (dissertation chapter 6): which m of the n(n−1) relative pose
measurements the swarm takes at step k.

Pure functions over values; :func:`select_for_scenario` is the thin adapter the simulator
calls. Every random draw comes from the ``rng`` passed in (the adapter uses
``stream(seed, "select", k)``), so runs are deterministic.

Strategies (``STRATEGIES``)
---------------------------
* ``complete`` — every candidate (the benchmark; the budget does not apply).
* ``random`` — ``m`` distinct directed candidates drawn uniformly without replacement; not
  necessarily connected. Needs no state knowledge.
* ``random_tree`` — a uniformly random spanning tree of the candidate graph (the complete
  graph when every pair is a candidate; one uniform tree per connected component otherwise),
  sampled with Aldous–Broder, each edge given a direction uniformly among its feasible
  directions. A tree has n−1 edges; when the budget is smaller, a uniformly random ``m`` of
  them are kept (a random sub-forest: still acyclic, still state-free).
* ``greedy`` — the dissertation's: minimise the weighted trace of the posterior covariance
  ``J = tr(W P⁺)``, ``W = diag(c)``, ``c = c_a ⊗ c_b`` (per-satellite ⊗ per-state weights), adding
  the best candidate one at a time until ``m`` are chosen (see "Scoring" below).
* ``swarm_greedy`` — ours: the same greedy with the *anchor-averaged* objective (see below).
* ``fast_swarm_greedy`` — ours: ``swarm_greedy`` made cheap: candidates pruned to each
  satellite's k nearest estimated neighbours (:func:`nearest_neighbor_mask`, before the
  visibility test) and lazy (Minoux) re-evaluation (:func:`lazy_greedy_select`).
* ``logdet_greedy`` — greedy D-optimal design, ``max log det(P) − log det(P⁺)``; an extra
  comparison point (it needs only the 12×12 prior blocks, but weighs every state alike).

Candidates
----------
A pair (i, j) is a candidate when it is feasible in the measurement graph ``G`` (off
diagonal), the observer has at least one healthy camera, and — with ``require_visible`` —
the target's extent (a cube of half size ``s``, corners placed with the *estimated* relative
pose) projects entirely inside the image of one of the observer's six 90° face cameras that
is healthy (:func:`swarmcore.cameras.visible_cameras`, batched over candidates). Without ``require_visible`` the camera whose
boresight is closest to the predicted line of sight must be healthy. Every strategy draws
from the same candidate set, so none ever picks an invisible or unhealthy camera and the
comparison is about the selection rule alone.

Scoring (the shortcut)
----------------------
Measurement e (i sees j) has Jacobian ``H_e = [H_i  H_j]`` (6×12, from
:func:`swarmcore.mekf.relative_residuals`) on the observed states ``l_e = [a_i, Δr_i, a_j, Δr_j]``
and noise ``R_e`` (:func:`swarmcore.world.relative_noise_cov` at the predicted ``r_ij_Bi``).
With ``C = P_{:,l} H_eᵀ`` (N×6) and ``S_e = H_e P_ll H_eᵀ + R_e`` the optimal-gain update is
``P⁺ = P − C S_e⁻¹ Cᵀ``, so

    ΔJ_e = tr(W P) − tr(W P⁺) = tr(S_e⁻¹ Cᵀ W C) = tr(S_e⁻¹ H_e M_ll H_eᵀ),
    M = P_{:,O}ᵀ W P_{:,O}   (6n×6n, O = every attitude and position error).

Only 12×12 blocks of ``P_OO`` and ``M`` enter a score, so a candidate costs O(12²·6) once ``M``
is formed (one O(N·(6n)²) product per step), never a full covariance update. After a pick e*
the working ``P_OO`` and ``M`` take the rank-6 downdate (``K = S*⁻¹``, ``C_O = P_{O,l*} H*ᵀ``,
``Z = M_{:,l*} H*ᵀ``, ``G* = H* M_l*l* H*ᵀ``):

    P_OO ← P_OO − C_O K C_Oᵀ
    M    ← M − C_O K Zᵀ − Z K C_Oᵀ + C_O K G* K C_Oᵀ

which is exactly ``P_{:,O}⁺ᵀ W P_{:,O}⁺``, and every candidate's ``S_e``, ``G_e`` follow by
projecting those downdates through ``H_e`` (:func:`greedy_select`) — the greedy never touches
the N×N matrix again. The tests hold every score and every pick against the filter's own
stacked update.

Our strategy: ``swarm_greedy`` (anchor-averaged weighted trace)
----------------------------------------------------------------
The selector plans with ONE filter's covariance (the reference filter, satellite 0), but every
satellite runs its own filter and the swarm's accuracy is the mean over all of them. Each
filter a knows its own satellite almost exactly (star tracker, GPS), so it is effectively
*anchored* at a: its error on satellite j is the error of j *relative to a*,

    e_j^(a) ≈ D_a e,   (D_a e)_j = e_j − A_ja e_a  (j ≠ a),   (D_a e)_a = 0,

with ``A_ja = diag(R_ja, R_ja, I, I)`` on ``[a, Δω, Δr, Δv]`` and ``R_ja = T(q̂_j) T(q̂_a)ᵀ``
(attitude errors live in the body frames, positions and velocities in H). The dissertation's
objective, evaluated on the reference filter, counts only errors relative to satellite 0, so
greedy favours measurements touching satellite 0 (see the heat maps). ``swarm_greedy``
minimises instead the swarm mean

    J̄ = (1/n) Σ_a tr(W D_a P⁺ D_aᵀ) = tr(W̄ P⁺),   W̄ = (1/n) Σ_a D_aᵀ W D_a,

a fixed (per step) symmetric PSD weight, so the same shortcut applies with
``M = P_{:,O}ᵀ W̄ P_{:,O}``. Every filter receives the same relative measurements, so the
relative covariances in filter 0's P are a fair (if approximate: each filter also has its own
absolute sensors and process noise) stand-in for what every other filter will see. For
positions alone and unit weights, ``W̄`` is the Laplacian of the complete graph,
``2(I − 11ᵀ/n)``: J̄ is then the mean squared *pairwise* error. Blocks of ``n W̄``:

    diag  (j, j): Σ_{a≠j} (W_j + A_ajᵀ W_a A_aj)
    off   (j, a): −(W_j A_ja + A_ajᵀ W_a).

``W̄`` is never formed in the selector: :func:`swarm_weighted` applies it in O(n·12²·6n), so
``swarm_greedy`` costs what ``greedy`` costs.

``fast_swarm_greedy`` adds two cost cuts that leave the picks (nearly) unchanged: the camera
noise variance grows as range⁴, so only pairs where one end is among the other's k nearest
estimated neighbours are considered (and only they pay for the visibility test and the
Jacobians), and the greedy re-scores lazily (:func:`lazy_greedy_select`).

Measured (``swarm compare scenarios/selection.yaml --runs 20``, seeds 600–619, paired; and
``swarm bench selection``; numbers live in the reports, nothing here is asserted): greedy's
share of measurements touching satellite 0 is 0.33 (0.20 would be unbiased), swarm_greedy's
0.22. Against greedy, swarm_greedy's mean errors are 0.99 / 0.98 (orientation, full / second
half) and 0.975 / 0.95 (position), fast_swarm_greedy's 0.98 / 0.975 and 0.98 / 0.955 — small
gains that are NOT significant at 5 % over 20 runs (Wilcoxon p 0.05–0.55; on the first 10
seeds alone swarm_greedy's position gains were 7 % and 12 %, p < 0.02). So: accuracy at least
matching greedy; fast_swarm_greedy needs 21 % of greedy's selection time at n = 50 (m = 5)
and 28 % at m = 49, but no less at n = 10 (pruning removes few pairs there).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse.csgraph import connected_components

from . import quat
from .cameras import Intrinsics, best_camera, visible_cameras
from .mekf import BLOCK, FilterParams, RelativeMeasurements, SwarmEstimate, observed_indices, relative_residuals
from .scenario import NEEDS_STATE as _NEEDS_STATE
from .scenario import STATE_FREE as _STATE_FREE
from .scenario import STRATEGIES as _STRATEGIES
from .sensors import relative_noise_cov, relative_pose_T

__all__ = [
    "STRATEGIES",
    "STATE_FREE",
    "SelectorConfig",
    "Candidates",
    "predicted_relative",
    "candidate_mask",
    "build_candidates",
    "weight_vector",
    "swarm_weight_matrix",
    "swarm_weighted",
    "trace_reductions",
    "logdet_reductions",
    "greedy_select",
    "nearest_neighbor_mask",
    "lazy_greedy_select",
    "random_select",
    "aldous_broder",
    "random_tree_select",
    "select",
    "select_for_scenario",
    "choose_pairs",
    "selector_prior",
    "mask_dead",
    "NEEDS_STATE",
]

#: Every strategy (their names are declared once, with the scenario's ``selection.strategy``).
STRATEGIES = _STRATEGIES
#: Strategies that need no state estimate (usable as a fallback by a selector without one).
STATE_FREE = _STATE_FREE
#: Strategies that plan from a filter's estimate (the selector fetches it).
NEEDS_STATE = _NEEDS_STATE


@dataclass(frozen=True)
class SelectorConfig:
    """Everything besides the estimate that a selector needs.

    ``rel``: the relative-sensor model (``scenario.Relative``; anything with the fields
    :func:`swarmcore.world.relative_noise_cov` reads). ``intr``: face-camera intrinsics.
    ``target_half_size_m``: half the target cube side; ``camera_offset_m``: boresight offset
    of each face camera from the body centre. ``sat_weights`` c_a (n,) and
    ``state_weights`` c_b (12,), None meaning ones. ``fallback``: a state-free strategy used when ``est`` is None.
    ``neighbors``: k of the nearest-neighbour pruning of ``fast_swarm_greedy``.
    """

    rel: object
    intr: Intrinsics
    target_half_size_m: float
    camera_offset_m: float
    sat_weights: np.ndarray | None = None
    state_weights: np.ndarray | None = None
    require_visible: bool = True
    near_m: float = 0.05
    fallback: str = "random_tree"
    neighbors: int = 5


@dataclass(frozen=True)
class Candidates:
    """Candidate measurements (canonical order) linearised at the estimate.

    ``Hi``/``Hj`` (c, 6, 6): Jacobians on the observer's / target's ``[a, Δr]``; ``R_Bi``
    (c, 6, 6): predicted noise covariance in B_i, ``[attitude rad, position m]``.
    """

    observer: np.ndarray
    target: np.ndarray
    Hi: np.ndarray
    Hj: np.ndarray
    R_Bi: np.ndarray

    def __len__(self) -> int:
        return int(self.observer.size)

    def subset(self, idx) -> Candidates:
        return Candidates(self.observer[idx], self.target[idx], self.Hi[idx], self.Hj[idx], self.R_Bi[idx])

    @property
    def H(self) -> np.ndarray:
        """(c, 6, 12) Jacobian on ``[a_i, Δr_i, a_j, Δr_j]``."""
        return np.concatenate([self.Hi, self.Hj], axis=2)


# --------------------------------------------------------------------------- candidates


def predicted_relative(est: SwarmEstimate, params: FilterParams, observer, target):
    """Predicted ``q_BjBi`` (m, 4) and ``r_ij_Bi`` (m, 3) m from the estimate (no noise)."""
    return relative_pose_T(params.T_IH(est.t), est.q_BI, est.r_H, np.asarray(observer), np.asarray(target))


def candidate_mask(
    G: np.ndarray,
    est: SwarmEstimate | None,
    params: FilterParams | None,
    camera_ok: np.ndarray,
    cfg: SelectorConfig,
    restrict: np.ndarray | None = None,
) -> np.ndarray:
    """(n, n) bool: pair (i, j) may be selected (see the module docstring).

    ``G`` off-diagonal = feasible measurements (diagonal ignored); ``camera_ok`` (n, 6) with
    False for an unhealthy camera (a dead satellite: all False). Without an estimate only
    the graph and observers with some healthy camera count (a state-free fallback).
    ``restrict`` (n, n) bool, optional: pairs outside it are dropped before the (costly)
    visibility test.
    """
    G = np.asarray(G, dtype=bool)
    n = G.shape[0]
    camera_ok = np.asarray(camera_ok, dtype=bool).reshape(n, 6)
    mask: np.ndarray = np.array(G, dtype=bool, copy=True)
    if restrict is not None:
        mask &= np.asarray(restrict, dtype=bool)
    np.fill_diagonal(mask, False)
    has_camera: np.ndarray = np.any(camera_ok, axis=1)
    mask &= has_camera[:, None]
    if est is None:
        return mask
    obs, tgt = np.nonzero(mask)
    if obs.size == 0:
        return mask
    if params is None:
        raise ValueError("candidate_mask: an estimate needs its filter parameters")
    q_pred, r_pred = predicted_relative(est, params, obs, tgt)
    if cfg.require_visible:
        vis = visible_cameras(r_pred, q_pred, cfg.intr, cfg.target_half_size_m, cfg.camera_offset_m, cfg.near_m)
        ok = np.any(vis & camera_ok[obs], axis=1)
    else:
        ok = camera_ok[obs, best_camera(r_pred)]
    mask[obs[~ok], tgt[~ok]] = False
    return mask


def build_candidates(est: SwarmEstimate, params: FilterParams, mask: np.ndarray, rel) -> Candidates:
    """Linearise every candidate of ``mask`` at the estimate (Jacobians from the filter)."""
    obs, tgt = np.nonzero(np.asarray(mask, dtype=bool))  # row-major: canonical order
    q_pred, r_pred = predicted_relative(est, params, obs, tgt)
    R = relative_noise_cov(rel, r_pred) if obs.size else np.zeros((0, 6, 6))
    meas = RelativeMeasurements(obs, tgt, q_pred, r_pred, R)
    _, Hi, Hj = relative_residuals(est, params, meas)
    return Candidates(obs, tgt, Hi, Hj, R)


# --------------------------------------------------------------------------- objectives


def weight_vector(n: int, sat_weights=None, state_weights=None) -> np.ndarray:
    """``c = c_a ⊗ c_b`` (12n,): per-satellite weights times per-state weights."""
    ca = np.ones(n) if sat_weights is None else np.asarray(sat_weights, dtype=float)
    cb = np.ones(BLOCK) if state_weights is None else np.asarray(state_weights, dtype=float)
    if ca.shape != (n,) or cb.shape != (BLOCK,):
        raise ValueError(f"weights: need c_a of {n} and c_b of {BLOCK} values, got {ca.shape} and {cb.shape}")
    if np.any(ca < 0) or np.any(cb < 0):
        raise ValueError("weights must be non-negative")
    return np.kron(ca, cb)


def swarm_weight_matrix(q_BI: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``W̄ = (1/n) Σ_a D_aᵀ diag(c) D_a`` (12n × 12n), the anchor-averaged weight.

    ``q_BI`` (n, 4) the estimated attitudes (they rotate attitude and rate errors between
    body frames), ``c`` (12n,) the weight vector of :func:`weight_vector`.
    """
    n = q_BI.shape[0]
    T = quat.attitude_matrix(q_BI)  # (n, 3, 3)
    Rja = T[:, None] @ np.swapaxes(T, -1, -2)[None, :]  # (n, n, 3, 3): B_a → B_j
    A = np.zeros((n, n, BLOCK, BLOCK))
    A[:, :, 0:3, 0:3] = Rja
    A[:, :, 3:6, 3:6] = Rja
    A[:, :, 6:9, 6:9] = np.eye(3)
    A[:, :, 9:12, 9:12] = np.eye(3)
    Wd = c.reshape(n, BLOCK)  # diagonal of W_j per satellite
    WA = Wd[:, None, :, None] * A  # W_j A_ja  (n, n, 12, 12)
    AtWA = np.swapaxes(A, -1, -2) @ WA  # A_jaᵀ W_j A_ja, indexed [j, a]
    off = WA + np.swapaxes(WA, 0, 1).swapaxes(-1, -2)  # W_j A_ja + (W_a A_aj)ᵀ
    Wbar = -off
    idx = np.arange(n)
    Wbar[idx, idx] = 0.0
    # diag (j, j): Σ_{a≠j} W_j + Σ_{a≠j} A_ajᵀ W_a A_aj
    AtWA[idx, idx] = 0.0
    diag = (n - 1) * np.einsum("jk,kl->jkl", Wd, np.eye(BLOCK)) + AtWA.sum(axis=0)
    Wbar[idx, idx] = diag
    Wbar = Wbar.transpose(0, 2, 1, 3).reshape(n * BLOCK, n * BLOCK) / n
    return 0.5 * (Wbar + Wbar.T)


def _local_index(n: int, observer: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(c, 12) indices into the observed subspace O of ``[a_i, Δr_i, a_j, Δr_j]``."""
    six = np.arange(6)
    return np.concatenate([6 * observer[:, None] + six, 6 * target[:, None] + six], axis=1)


def _blocks(A_OO: np.ndarray, n: int) -> np.ndarray:
    """(n, n, 6, 6) view of a 6n×6n matrix over O: ``[a, b]`` = rows of a, columns of b."""
    return A_OO.reshape(n, 6, n, 6).transpose(0, 2, 1, 3)


def _sandwich(A_OO: np.ndarray, n: int, cand: Candidates) -> np.ndarray:
    """``H_e A_ll H_eᵀ`` (c, 6, 6) for every candidate, from 6×6 blocks of ``A_OO``.

    With ``H = [H_i  H_j]``: ``H A_ll = [H_i A_ii + H_j A_ji,  H_i A_ij + H_j A_jj] = [T₁  T₂]``,
    ``H A_ll Hᵀ = T₁ H_iᵀ + T₂ H_jᵀ``.
    """
    B = _blocks(A_OO, n)
    i, j = cand.observer, cand.target
    T1 = cand.Hi @ B[i, i] + cand.Hj @ B[j, i]
    T2 = cand.Hi @ B[i, j] + cand.Hj @ B[j, j]
    return T1 @ np.swapaxes(cand.Hi, -1, -2) + T2 @ np.swapaxes(cand.Hj, -1, -2)


def _project_rows(X_O: np.ndarray, n: int, cand: Candidates) -> np.ndarray:
    """``H_e X_{l_e}`` (c, 6, k) for a (6n, k) matrix over O."""
    Xb = X_O.reshape(n, 6, -1)
    return cand.Hi @ Xb[cand.observer] + cand.Hj @ Xb[cand.target]


def swarm_weighted(X: np.ndarray, q_BI: np.ndarray, c: np.ndarray) -> np.ndarray:
    """``W̄ X`` for a (12n, k) matrix without forming W̄: O(n·12²·k) instead of O(n²·12²·k).

    With ``𝒯_j = diag(T_j, T_j, I, I)`` (so ``A_ja = 𝒯_j 𝒯_aᵀ``), ``W_j = diag(c_j)``,
    ``Y = Σ_a 𝒯_aᵀ X_a``, ``Y_W = Σ_a 𝒯_aᵀ W_a X_a`` and ``Q = Σ_a 𝒯_aᵀ W_a 𝒯_a``, the block
    formulas of :func:`swarm_weight_matrix` collapse to

        n (W̄ X)_j = n W_j X_j + 𝒯_j Q 𝒯_jᵀ X_j − W_j 𝒯_j Y − 𝒯_j Y_W.

    (Positions alone, unit weights: ``2 X_j − (2/n) Σ_a X_a``, the complete-graph Laplacian.)
    """
    n = q_BI.shape[0]
    k = X.shape[1]
    T = quat.attitude_matrix(q_BI)
    TT = np.zeros((n, BLOCK, BLOCK))
    TT[:, 0:3, 0:3] = T
    TT[:, 3:6, 3:6] = T
    TT[:, 6:12, 6:12] = np.eye(6)
    Xb = X.reshape(n, BLOCK, k)
    w = c.reshape(n, BLOCK)
    TtX = np.swapaxes(TT, -1, -2) @ Xb  # 𝒯_aᵀ X_a
    Y = TtX.sum(axis=0)
    Y_W = (np.swapaxes(TT, -1, -2) @ (w[:, :, None] * Xb)).sum(axis=0)
    Q = (np.swapaxes(TT, -1, -2) @ (w[:, :, None] * TT)).sum(axis=0)
    out = n * w[:, :, None] * Xb + TT @ (Q @ TtX) - w[:, :, None] * (TT @ Y) - TT @ Y_W
    return (out / n).reshape(n * BLOCK, k)


def _weighted(P_O: np.ndarray, W) -> np.ndarray:
    """``W P_{:,O}`` for a weight vector (diagonal), a dense matrix or a callable."""
    if callable(W):
        return W(P_O)
    W = np.asarray(W, dtype=float)
    return W[:, None] * P_O if W.ndim == 1 else W @ P_O


def _M_matrix(P: np.ndarray, n: int, W) -> tuple[np.ndarray, np.ndarray, float]:
    """``P_OO``, ``M = P_{:,O}ᵀ W P_{:,O}`` and ``J = tr(W P)``."""
    O = observed_indices(n)
    P_O = P[:, O]
    WP = _weighted(P_O, W)
    M = P_O.T @ WP
    if callable(W):
        J = float(np.nan)  # only differences matter to the greedy; tests use vector/matrix W
    else:
        Wa = np.asarray(W, dtype=float)
        J = float(Wa @ np.diag(P)) if Wa.ndim == 1 else float(np.sum(Wa * P))
    return P_O[O].copy(), 0.5 * (M + M.T), J


def trace_reductions(P: np.ndarray, cand: Candidates, W) -> np.ndarray:
    """``tr(W P) − tr(W P⁺_e)`` for each candidate e alone (c,), from columns of P only.

    ``W``: weight vector (12n,) for ``diag(c)``, a dense symmetric (12n, 12n) matrix, or a
    callable returning ``W X``.
    """
    n = P.shape[0] // BLOCK
    P_OO, M, _ = _M_matrix(P, n, W)
    S = _sandwich(P_OO, n, cand) + cand.R_Bi
    return np.trace(np.linalg.solve(S, _sandwich(M, n, cand)), axis1=-2, axis2=-1)


def logdet_reductions(P_OO: np.ndarray, n: int, cand: Candidates) -> np.ndarray:
    """``log det P − log det P⁺_e = log det S_e − log det R_e`` (determinant lemma)."""
    S = _sandwich(P_OO, n, cand) + cand.R_Bi
    return np.linalg.slogdet(S)[1] - np.linalg.slogdet(cand.R_Bi)[1]


def greedy_select(
    P: np.ndarray, cand: Candidates, budget: int, W=None, objective: str = "trace"
) -> tuple[np.ndarray, list[float]]:
    """Greedy: pick the candidate with the largest reduction, downdate, repeat ``budget`` times.

    ``objective``: ``"trace"`` (``W`` as in :func:`trace_reductions`) or ``"logdet"`` (``W``
    unused). Returns the chosen candidate indices in pick order and the objective after each
    pick (the weighted trace; for logdet, ``log det P⁺_OO − log det P_OO``). Ties go to the
    lowest index (canonical order).

    Per round every candidate's ``S_e`` and ``G_e = H_e M_ll H_eᵀ`` are not recomputed but
    downdated with the pick e* (``V_e = H_e C_{O,l_e}``, ``U_e = H_e Z_{l_e}``, ``K = S*⁻¹``):

        S_e ← S_e − V_e K V_eᵀ
        G_e ← G_e − V_e K U_eᵀ − U_e K V_eᵀ + V_e K G* K V_eᵀ

    the projections of the P_OO and M downdates of the module docstring.
    """
    n = P.shape[0] // BLOCK
    c = len(cand)
    k_max = min(int(budget), c)
    if k_max <= 0:
        return np.zeros(0, dtype=int), []
    if objective == "trace":
        P_OO, M, J = _M_matrix(P, n, W)
        Gm = _sandwich(M, n, cand)
    elif objective == "logdet":
        O = observed_indices(n)
        P_OO, M, J, Gm = P[np.ix_(O, O)].copy(), None, 0.0, None
    else:
        raise ValueError(f"unknown objective {objective!r}")
    S = _sandwich(P_OO, n, cand) + cand.R_Bi
    logdet_R = np.linalg.slogdet(cand.R_Bi)[1] if Gm is None else None
    loc = _local_index(n, cand.observer, cand.target)
    chosen: list[int] = []
    history: list[float] = []
    available = np.ones(c, dtype=bool)
    for r in range(k_max):
        if Gm is not None:
            # tr(S⁻¹ G) = Σ_ab (S⁻¹)_ab G_ab for symmetric S, G (one batched inverse per round).
            gain = np.sum(np.linalg.inv(S) * Gm, axis=(1, 2))
        else:
            gain = np.linalg.slogdet(S)[1] - logdet_R
        gain = np.where(available, gain, -np.inf)
        e = int(np.argmax(gain))
        chosen.append(e)
        available[e] = False
        J -= float(gain[e])
        history.append(J)
        if r == k_max - 1:
            break
        # Rank-6 downdate of the working P_OO (and M), and of every candidate's S_e (and G_e).
        l, He, Se = loc[e], cand.H[e], S[e].copy()
        K = np.linalg.inv(Se)
        K = 0.5 * (K + K.T)
        C_O = P_OO[:, l] @ He.T  # (6n, 6)
        X = K @ C_O.T  # S*⁻¹ C_Oᵀ
        V = _project_rows(C_O, n, cand)  # (c, 6, 6)
        VK = V @ K
        S = S - VK @ np.swapaxes(V, -1, -2)
        S = 0.5 * (S + np.swapaxes(S, -1, -2))
        if M is not None:
            assert Gm is not None  # the trace objective carries both
            Ge = Gm[e].copy()
            Z = M[:, l] @ He.T
            Y = K @ Z.T
            U = _project_rows(Z, n, cand)
            VKU = VK @ np.swapaxes(U, -1, -2)
            Gm = Gm - VKU - np.swapaxes(VKU, -1, -2) + VK @ Ge @ np.swapaxes(VK, -1, -2)
            Gm = 0.5 * (Gm + np.swapaxes(Gm, -1, -2))
            M = M - C_O @ Y - Z @ X + C_O @ (K @ Ge @ X)
            M = 0.5 * (M + M.T)
        P_OO = P_OO - C_O @ X
        P_OO = 0.5 * (P_OO + P_OO.T)
    return np.asarray(chosen, dtype=int), history


def nearest_neighbor_mask(r_H: np.ndarray, k: int) -> np.ndarray:
    """(n, n) bool: j is among the ``k`` nearest (estimated) neighbours of i, or i of j.

    The camera noise grows as range² (variance as range⁴), so a pair twice as far carries
    ~1/16 of the information: the greedy's picks are nearly always among close neighbours
    (in a sample Table 6.1 run, 97 % of greedy's picks had one end among the other's 5 nearest).
    Symmetric, so every satellite keeps at least ``k`` partners in both roles.
    """
    r = np.asarray(r_H, dtype=float)
    n = r.shape[0]
    D = np.linalg.norm(r[:, None, :] - r[None, :, :], axis=-1)
    np.fill_diagonal(D, np.inf)
    k = min(int(k), n - 1)
    near = np.zeros((n, n), dtype=bool)
    if k > 0:
        idx = np.argpartition(D, k - 1, axis=1)[:, :k]
        near[np.arange(n)[:, None], idx] = True
    return near | near.T


def lazy_greedy_select(P: np.ndarray, cand: Candidates, budget: int, W) -> tuple[np.ndarray, list[float], int]:
    """Greedy on the weighted trace with lazy (Minoux) re-evaluation.

    Every candidate is scored once (as in :func:`greedy_select`); afterwards the stale gains
    serve as priorities: the top candidate is re-scored against the current working P_OO and
    M (its 12×12 blocks only) and taken when it is still on top. Only the working P_OO and M
    are downdated, never the c per-candidate matrices. Exact when gains never grow after a
    pick (submodularity); the trace reduction is not submodular in general (a measurement
    can make another more useful), so this can differ from the plain greedy — in practice
    rarely, and the accuracy comparison is what counts. Returns (picks, objective after each
    pick, number of single re-scorings).
    """
    n = P.shape[0] // BLOCK
    c = len(cand)
    k_max = min(int(budget), c)
    if k_max <= 0:
        return np.zeros(0, dtype=int), [], 0
    P_OO, M, J = _M_matrix(P, n, W)
    S = _sandwich(P_OO, n, cand) + cand.R_Bi
    bound = np.sum(np.linalg.inv(S) * _sandwich(M, n, cand), axis=(1, 2))
    loc = _local_index(n, cand.observer, cand.target)
    fresh = np.ones(c, dtype=bool)
    available = np.ones(c, dtype=bool)
    chosen: list[int] = []
    history: list[float] = []
    evals = 0
    for r in range(k_max):
        while True:
            e = int(np.argmax(np.where(available, bound, -np.inf)))
            if fresh[e]:
                break
            l, He = loc[e], cand.H[e]
            Se = He @ P_OO[np.ix_(l, l)] @ He.T + cand.R_Bi[e]
            Ge = He @ M[np.ix_(l, l)] @ He.T
            bound[e] = float(np.trace(np.linalg.solve(Se, Ge)))
            fresh[e] = True
            evals += 1
        chosen.append(e)
        available[e] = False
        J -= float(bound[e])
        history.append(J)
        if r == k_max - 1:
            break
        l, He = loc[e], cand.H[e]
        Se = He @ P_OO[np.ix_(l, l)] @ He.T + cand.R_Bi[e]
        K = np.linalg.inv(Se)
        K = 0.5 * (K + K.T)
        C_O = P_OO[:, l] @ He.T
        Z = M[:, l] @ He.T
        Ge = He @ M[np.ix_(l, l)] @ He.T
        X = K @ C_O.T
        M = M - C_O @ (K @ Z.T) - Z @ X + C_O @ (K @ Ge @ X)
        M = 0.5 * (M + M.T)
        P_OO = P_OO - C_O @ X
        P_OO = 0.5 * (P_OO + P_OO.T)
        fresh[:] = False
    return np.asarray(chosen, dtype=int), history, evals


def random_select(count: int, budget: int, rng: np.random.Generator) -> np.ndarray:
    """``min(budget, count)`` distinct indices of ``range(count)``, uniformly, sorted."""
    k = min(int(budget), int(count))
    return np.sort(rng.choice(count, size=k, replace=False)) if k > 0 else np.zeros(0, dtype=int)


def aldous_broder(adj: np.ndarray, rng: np.random.Generator) -> list[tuple[int, int]]:
    """A uniformly random spanning tree of each connected component of an undirected graph.

    Aldous–Broder: walk at random from any vertex; the edge by which the walk first enters
    each vertex belongs to the tree. The tree is uniform over all spanning trees of the
    component (Aldous 1990, Broder 1989), whatever the start vertex. Written by hand rather
    than ``networkx.random_spanning_tree`` because that sampler contracts edges one by one
    and recomputes Kirchhoff determinants (O(E·n³) per tree, seconds at n = 50, every step),
    while the walk's cover time on the complete graph is about n ln n steps; it also keeps
    every draw on the passed-in Generator.

    ``adj`` (n, n) bool, symmetrised here, diagonal ignored. Returns edges (u, v), u entered
    the tree before v.
    """
    A = np.asarray(adj, dtype=bool)
    A = A | A.T
    np.fill_diagonal(A, False)
    n = A.shape[0]
    nbrs = [np.flatnonzero(A[u]) for u in range(n)]
    _, labels = connected_components(A, directed=False)
    edges: list[tuple[int, int]] = []
    for comp in np.unique(labels):
        nodes = np.flatnonzero(labels == comp)
        if nodes.size < 2:
            continue
        visited = np.zeros(n, dtype=bool)
        cur = int(nodes[rng.integers(nodes.size)])
        visited[cur] = True
        left = nodes.size - 1
        while left:
            u = rng.random(64)  # draws in batches: one Generator call per 64 steps
            for x in u:
                nb = nbrs[cur]
                nxt = int(nb[int(x * nb.size)])
                if not visited[nxt]:
                    visited[nxt] = True
                    edges.append((cur, nxt))
                    left -= 1
                    if not left:
                        break
                cur = nxt
    return edges


def random_tree_select(mask: np.ndarray, budget: int | None, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A uniform spanning tree of the candidate graph, each edge directed at random.

    An undirected edge {u, v} exists when either direction is a candidate; its direction is
    drawn uniformly among the feasible ones. With ``budget`` below the tree's size a
    uniformly random ``budget`` of its edges are kept. Returns (observer, target), canonical.
    """
    mask = np.asarray(mask, dtype=bool)
    edges = aldous_broder(mask | mask.T, rng)
    if budget is not None and len(edges) > budget:
        keep = np.sort(rng.choice(len(edges), size=int(budget), replace=False))
        edges = [edges[i] for i in keep]
    obs, tgt = [], []
    for u, v in edges:
        dirs = [(a, b) for a, b in ((u, v), (v, u)) if mask[a, b]]
        a, b = dirs[int(rng.integers(len(dirs)))] if len(dirs) > 1 else dirs[0]
        obs.append(a)
        tgt.append(b)
    return _canonical(np.asarray(obs, dtype=int), np.asarray(tgt, dtype=int))


def _canonical(obs: np.ndarray, tgt: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    order = np.lexsort((tgt, obs))
    return obs[order].astype(int), tgt[order].astype(int)


# --------------------------------------------------------------------------- entry points


def select(
    strategy: str,
    est: SwarmEstimate | None,
    params: FilterParams | None,
    budget: int,
    G: np.ndarray,
    camera_ok: np.ndarray,
    rng: np.random.Generator,
    cfg: SelectorConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs (observer, target) to measure, canonical order (by observer, then target).

    ``est``/``params``: the selector's predicted estimate for the step and its filter
    parameters (None: no estimate; state-based strategies then use ``cfg.fallback``). ``G``
    (n, n): feasible measurements off the diagonal. ``camera_ok`` (n, 6): camera health.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown selection strategy {strategy!r}; expected one of {STRATEGIES}")
    if (est is None or params is None) and strategy not in STATE_FREE:
        strategy = cfg.fallback
    restrict = nearest_neighbor_mask(est.r_H, cfg.neighbors) if strategy == "fast_swarm_greedy" and est is not None else None
    mask = candidate_mask(G, est, params, camera_ok, cfg, restrict)
    if strategy == "complete":
        obs, tgt = np.nonzero(mask)
        return obs, tgt
    if strategy == "random":
        obs, tgt = np.nonzero(mask)
        idx = random_select(obs.size, budget, rng)
        return obs[idx], tgt[idx]
    if strategy == "random_tree":
        return random_tree_select(mask, budget, rng)
    assert est is not None and params is not None  # state-free strategies returned above
    cand = build_candidates(est, params, mask, cfg.rel)
    n = est.n
    c = weight_vector(n, cfg.sat_weights, cfg.state_weights)
    if strategy == "greedy":
        idx, _ = greedy_select(est.P, cand, budget, c)
    elif strategy == "swarm_greedy":
        idx, _ = greedy_select(est.P, cand, budget, lambda X: swarm_weighted(X, est.q_BI, c))
    elif strategy == "fast_swarm_greedy":
        idx, _, _ = lazy_greedy_select(est.P, cand, budget, lambda X: swarm_weighted(X, est.q_BI, c))
    else:  # logdet_greedy
        idx, _ = greedy_select(est.P, cand, budget, objective="logdet")
    return _canonical(cand.observer[idx], cand.target[idx])


def config_for_scenario(sc) -> SelectorConfig:
    """The :class:`SelectorConfig` of a :class:`swarmcore.scenario.Scenario`."""
    s = sc.selection
    cam = sc.cameras
    half = sc.spacecraft.half_size_m
    return SelectorConfig(
        rel=sc.sensors.relative,
        intr=Intrinsics.from_fov(cam.width_px, cam.height_px, cam.fov_deg),
        target_half_size_m=half,
        camera_offset_m=half,
        sat_weights=None if s.sat_weights is None else np.asarray(s.sat_weights, dtype=float),
        state_weights=np.asarray(s.state_weights, dtype=float),
        require_visible=s.require_visible,
        fallback=s.fallback,
        neighbors=s.neighbors,
    )


def select_for_scenario(sc, k: int, G: np.ndarray, est_prior: SwarmEstimate | None, ref_params: FilterParams | None, camera_ok: np.ndarray):
    """Adapter for the simulator: ``select`` with the scenario's strategy, budget, weights and
    the deterministic stream ``stream(sc.seed, "select", k)``."""
    from .streams import stream

    rng = stream(sc.seed, "select", k)
    return select(sc.selection.strategy, est_prior, ref_params, sc.selection.budget, G, camera_ok, rng, config_for_scenario(sc))


def mask_dead(camera_ok: np.ndarray, live) -> np.ndarray:
    """Camera health with every camera of a satellite whose agent is not live switched
    off: a dead satellite measures nothing (it is still a target)."""
    out = np.array(camera_ok, dtype=bool, copy=True)
    dead = np.setdiff1d(np.arange(out.shape[0]), np.asarray(sorted(live), dtype=int))
    out[dead] = False
    return out


def selector_prior(est: SwarmEstimate, params: FilterParams, k: int) -> SwarmEstimate:
    """What the selector plans step k with: the reference filter's estimate at k−1 carried
    to k without its gyro (the selector never sees it), or the initial estimate at k = 0."""
    from .mekf import predict

    return est if est.step >= k else predict(est, params, None)


def choose_pairs(sc, k: int, G: np.ndarray, ref_est: SwarmEstimate | None, ref_params: FilterParams | None, camera_ok: np.ndarray):
    """The (observer, target) pairs measured at step k: the graph's edges when the scenario
    selects nothing, else the selector's choice from the reference filter's estimate
    (``ref_est`` None: only a state-free strategy can run)."""
    if sc.selection.strategy == "none":
        from .graphs import edges

        return edges(G)
    if ref_est is None or ref_params is None:
        return select_for_scenario(sc, k, G, None, None, camera_ok)
    return select_for_scenario(sc, k, G, selector_prior(ref_est, ref_params, k), ref_params, camera_ok)
