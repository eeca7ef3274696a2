"""``ci``: decentralized cooperative localization by covariance intersection.

Each agent keeps only its own satellite's state (12 error states: ``[a, Δβ, Δr, Δv]``,
its own gyro in dynamic-model-replacement mode, as the full filter's own block) and
broadcasts its prior pose each step (:class:`CiState`: attitude, position, velocity and
the 6×6 pose covariance). A relative measurement that involves it — one it took of a
peer, or one a peer took of it — together with that peer's broadcast estimate is a
measurement of its own pose. Its error is correlated with the agent's own estimate in an
unknown way (both may descend from the same earlier measurements), so it is fused by
covariance intersection (Julier & Uhlmann 1997), which is consistent whatever the
correlation: with prior ``(x, P)`` and the measurement's pseudo-estimate ``(z, C)``,

    P⁺⁻¹ = ω P⁻¹ + (1 − ω) Hᵀ C⁻¹ H,      ω ∈ (0, 1) minimising det P⁺

— the Kalman update of the prior inflated to ``P / ω`` by a measurement whose noise is
inflated to ``C / (1 − ω)``. Carrillo-Arce, Nerurkar, Gordillo and Roumeliotis (IROS 2013,
"Decentralized multi-robot cooperative localization using covariance intersection") fuse
each peer's estimate this way; here every measurement of a step that involves the agent is
fused at once (one ω per step, so the unobserved states — bias, velocity — are inflated
once a step, not once per measurement), with two conservative choices:

* ``split: true`` (default; split CI, Julier & Uhlmann 2001, used for cooperative
  localization by Li & Nashashibi 2013): the camera noise ``R`` is independent of
  everything and is not inflated; only the part that may be correlated — the peers'
  estimates projected into the measurement, ``Hp Pp Hpᵀ`` — is: ``C = R + Hp Pp Hpᵀ / (1 − ω)``.
  ``split: false``: plain CI, ``C = (R + Hp Pp Hpᵀ) / (1 − ω)``.
* The peers' estimates may be correlated with each other too: their stacked covariance is
  bounded by ``m · blockdiag(Pp_1, …, Pp_m)`` for m peers (for any correlation,
  ``Var(Σ xₖ) ≤ m Σ Var(xₖ)``), which the fused measurement uses.

Own absolute readings (star tracker, GPS) are independent of the peers and update the
prior first, with a plain Kalman update. Each relative measurement is gated against the
covariance the estimator claims (``S = Hᵢ Pᵢ Hᵢᵀ + Hp Pp Hpᵀ + R``, χ²(6)). A measurement
whose peer's estimate did not arrive (lost, late) cannot be used and is counted.

Late deliveries (``filter.late``): with ``replay`` (the default, as the full filter) the
agent keeps, for the last ``filter.history_s`` seconds, each step's prior, its own
readings and measurements, what it heard and its gyro sample; a peer's batch and estimate
of step s that arrive at step k > s join what step s heard, and the own state is
re-run from s to k — its 12 states cost a few updates a step, where the full filter
re-runs the whole swarm. A late peer estimate is the peer's prior of step s, so the fusion
at s is the same CI update as had it come on time. Older than the history, or with
``drop``, they are dropped. Counted either way (``late_used``, ``late_dropped``, over the
measurements that involve the agent). History does not cross steps the agent missed
(stalled, cut off): it restarts after such a gap.
Its view of a peer (one it fused with at the step) is the peer's broadcast prior, with no
cross-covariance (that is what it claims about the relative pose).

Bearings (``sensors.relative.model: bearing``, the angles-only camera): the observer turns
each line of sight into I with its own prior (:meth:`prediction`, its own satellite alone;
:func:`swarmcore.agent.inertial_bearings`, which adds the mean variance of that attitude to
R), and ``ũ_I`` is a 2-row measurement of the two positions
(:func:`swarmcore.mekf.bearing_residuals_padded`: the 6-row layout, four rows empty). It is
fused like a pose: the same gate (χ²(2)), the same CI, the Jacobian on the own and the
peer's positions only (:func:`stack_factors`; ``tests/test_bearing_estimators.py``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field
from scipy.linalg.lapack import dpotrf as _potrf

from .. import kernels
from ..mekf import (
    BLOCK,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    apply_correction,
    gate,
)
from .base import EstimateView, EstimatorParams, Received, StepInputs, StepReport
from .own import Kept, ReplayingEstimator
from .views import POSE, ViewRows, pose_block

__all__ = ["CIEstimator", "CIParams", "CiState", "ci_weight", "stack_factors"]

#: Variance given to a peer's rate and velocity states in the joint update: the relative
#: measurement's Jacobian has zero columns there and the peer carries no cross-covariance,
#: so they cannot reach the own posterior; any positive value gives the same result.
_UNUSED_VAR = 1.0


class CIParams(EstimatorParams):
    split: bool = Field(True, description="split CI: inflate only the peers' part of each measurement, not the camera noise")
    criterion: Literal["det", "trace"] = Field("det", description="what ω minimises: the posterior's determinant or its pose trace")
    correlated_peers: bool = Field(
        True, description="bound the peers' mutual correlation (their stacked covariance × number of peers); false: treat peers' "
        "estimates as independent of each other")


@dataclass(frozen=True)
class CiState:
    """What a ``ci`` agent broadcasts each step: its prior pose at the step."""

    sat: int
    step: int
    q_BI: np.ndarray  # (4,)
    omega_BI_B: np.ndarray  # (3,) rad/s
    r_H: np.ndarray  # (3,) m
    v_H: np.ndarray  # (3,) m/s
    P_pose: np.ndarray  # (6, 6) over [a, Δr]


def stack_factors(local: RelativeMeasurements, Hi: np.ndarray, Hj: np.ndarray, n_peers: int
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The linearised relative factors of one belief (row 0 of the joint ``local`` is the own
    satellite, rows 1… its neighbours): ``y ≈ Ho δx_i + Hp δp + v``, with ``Ho`` (6m × 12)
    on the own 12 error states, ``Hp`` (6m × 6 n_peers) on the neighbours' ``[a, Δr]`` and
    ``R`` (6m × 6m) the camera noise, from the Jacobian blocks of
    :func:`swarmcore.mekf.relative_residuals` (``Hi`` on the observer, ``Hj`` on the target).
    ``ci`` and ``gbp`` both linearise this way; with bearings (``relative_kind: bearing``)
    each measurement keeps the 6-row layout, its rows 2–5 zero with unit noise, and only
    the positions' columns are non-zero (module docstring)."""
    mine_obs = local.observer == 0
    Ho6 = np.where(mine_obs[:, None, None], Hi, Hj)
    Hq6 = np.where(mine_obs[:, None, None], Hj, Hi)
    peer_row = np.where(mine_obs, local.target, local.observer) - 1
    k = len(local)
    Ho = np.zeros((6 * k, BLOCK))
    Hp = np.zeros((6 * k, 6 * n_peers))
    for r in range(k):
        rows = slice(6 * r, 6 * r + 6)
        Ho[rows, POSE] = Ho6[r]
        Hp[rows, 6 * peer_row[r] : 6 * peer_row[r] + 6] = Hq6[r]
    return Ho, Hp, _block_diag(local.R_Bi)


def _block_diag(blocks) -> np.ndarray:
    """The block-diagonal matrix of square blocks of one size (scipy's costs more at 6×6)."""
    m = len(blocks)
    if not m:
        return np.zeros((0, 0))
    b = blocks[0].shape[0]
    out = np.zeros((m * b, m * b))
    for r, blk in enumerate(blocks):
        out[r * b : (r + 1) * b, r * b : (r + 1) * b] = blk
    return out


def ci_weight(logdet_of, lo: float = 1e-4, hi: float = 1.0 - 1e-4) -> float:
    """The ω in [lo, hi] minimising ``logdet_of(ω)`` (convex in ω for CI): bounded Brent
    (scipy), deterministic for the same inputs."""
    from scipy.optimize import minimize_scalar

    res = minimize_scalar(logdet_of, bounds=(lo, hi), method="bounded", options={"xatol": 1e-6})
    return float(res.x)


def _whitened(P: np.ndarray, Ho: np.ndarray, R: np.ndarray, C_p: np.ndarray, split: bool) -> tuple[np.ndarray, np.ndarray]:
    """``(Ŵ, Λ)`` of :func:`_logdet_cost`: ``Hₒ chol(P)`` whitened by a factor of the
    ω-independent part of ``C(ω)``, and the eigenvalues that make ``C̃(ω)`` diagonal
    (zeros for plain CI)."""
    from scipy.linalg import solve_triangular

    HL = Ho @ np.linalg.cholesky(P)  # (6m, 12)
    if split:
        L = np.linalg.cholesky(R)
        Qt = solve_triangular(L, solve_triangular(L, C_p, lower=True).T, lower=True)
        lam, U = np.linalg.eigh(0.5 * (Qt + Qt.T))
        return U.T @ solve_triangular(L, HL, lower=True), np.clip(lam, 0.0, None)
    L = np.linalg.cholesky(R + C_p)
    W = solve_triangular(L, HL, lower=True)
    return W, np.zeros(W.shape[0])


def _logdet_cost(W: np.ndarray, lam: np.ndarray, split: bool):
    """``cost(ω) = log det P⁺(ω) − log det P`` of the CI update, evaluated in 12×12, of the
    whitened ``(Ŵ, Λ)`` of :func:`_whitened`.

    With ``C(ω)`` the fused measurement's noise (split: ``R + C_p/(1−ω)``; plain:
    ``(R + C_p)/(1−ω)``), Sylvester's identity gives
    ``log det P⁺ = log det(P/ω) + log det C − log det(C + Hₒ P Hₒᵀ/ω)
    = log det P − 12 log ω − log det(I₁₂ + Ŵᵀ C̃(ω)⁻¹ Ŵ / ω)``, where ``Ŵ`` is
    ``Hₒ chol(P)`` whitened by a factor of the ω-independent part and ``C̃(ω)`` is diagonal
    in that basis (split: ``R = L Lᵀ``, ``L⁻¹ C_p L⁻ᵀ = U Λ Uᵀ``, ``C̃ = I + Λ/(1−ω)``; plain:
    ``C̃ = I/(1−ω)``). The same function of ω as the 6m×6m form, at a 12×12 Cholesky a
    call (the search calls it ~30 times a step). :func:`swarmcore.kernels.ci_det_weight`
    is the same cost and search compiled; this is its numpy twin."""
    eye = np.eye(W.shape[1])

    def cost(w: float) -> float:
        d = (1.0 - w) / (1.0 - w + lam) if split else np.full(lam.shape, 1.0 - w)
        G = (W.T * d) @ W / w
        return -W.shape[1] * np.log(w) - _logdet(eye + G)

    return cost


def _logdet(S: np.ndarray) -> float:
    """log det of an SPD matrix by its Cholesky factor (LAPACK dpotrf directly: numpy's
    wrapper costs more than the factorisation at these sizes, and ω's search calls it ~60
    times a step)."""
    c, info = _potrf(S, lower=1, clean=0)
    if info != 0:
        raise np.linalg.LinAlgError(f"not positive-definite (dpotrf info {info})")
    return float(2.0 * np.log(np.diagonal(c)).sum())


class CIEstimator(ReplayingEstimator):
    kind = "ci"
    radio = "graph"  # it fuses only measurements involving its satellite, with their other end's estimate
    accepts_bearings = True  # angles-only bearings in I (module docstring)
    Params = CIParams

    def __init__(self, sc, own: int, params: CIParams | None = None):
        super().__init__(sc, own, params)
        self.threshold = self.fp.gate_threshold
        self._peers: dict[int, CiState] = {}  # the estimates of the peers it fuses with at the current step
        self._heard: dict[int, Received] = {}  # what the radio brought of the current step
        self._used: list[int] = []  # the peers whose measurements it fused at the current step
        self.unusable = 0  # measurements whose peer estimate did not come
        self._joint_params: dict[int, FilterParams] = {}  # satellites in the joint → its parameters

    def transmit(self, k: int) -> CiState:
        e = self.e
        if e.step != k:
            raise ValueError(f"ci estimator of satellite {self.own}: transmit({k}) with its estimate at step {e.step}")
        return CiState(self.own, k, e.q_BI[0].copy(), e.omega_BI_B[0].copy(), e.r_H[0].copy(), e.v_H[0].copy(),
                       pose_block(e.P))

    def step(self, inputs: StepInputs) -> StepReport:
        rep = StepReport()
        kept = self.step_inputs(inputs, rep, inputs.peer_measurements)
        acc, rej, nis, dof = self._update(kept, count=True)
        rep.gate_accepted, rep.gate_rejected = acc, rej
        rep.nis, rep.nis_dof = (nis, dof) if dof else (float("nan"), 0)
        rep.extra["unusable"] = self.unusable
        self._pending = False
        return rep

    def _update(self, kept: Kept, count: bool) -> tuple[int, int, float, int]:
        """One step's update from what it was given: the own readings (Kalman), then every
        relative measurement involving it whose peer's estimate came (CI). Returns accepted,
        rejected, NIS and its degrees of freedom. ``count``: the live pass (not a replay)
        counts unusable measurements."""
        nis, dof = self.update_absolute(kept.absolute)
        self._heard = kept.heard
        self._used = []
        peers_rel = kept.peers_batch
        if peers_rel is None:
            peers_rel = RelativeMeasurements.concat([kept.heard[j].measurements for j in sorted(kept.heard)])
        rel = self._involving_me(kept.own, peers_rel, count)
        acc = 0
        if len(rel):
            acc, d2 = self._fuse(rel)
            nis, dof = nis + d2, dof + self.fp.rel_dof * acc
        return acc, len(rel) - acc, nis, dof

    def _involving_me(self, own: RelativeMeasurements, peers_rel: RelativeMeasurements, count: bool) -> RelativeMeasurements:
        """Every measurement of the step that involves the own satellite and whose peer's
        estimate came, canonical order (the peers' batches gathered once: at n = 100 a
        test per peer cost more than the fusion)."""
        me = self.own
        cand = RelativeMeasurements.concat([own, peers_rel.subset(peers_rel.target == me)])
        if not len(cand):
            return cand
        other = np.where(cand.observer == me, cand.target, cand.observer)
        self._peers = {}
        for j in np.unique(other).tolist():
            r = self._heard.get(j)
            if r is not None and isinstance(r.payload, CiState):
                self._peers[j] = r.payload
        ok = np.isin(other, np.fromiter(self._peers, dtype=int, count=len(self._peers)))
        if count:
            self.unusable += int((~ok).sum())
        return cand.subset(ok).canonical()

    def _fuse(self, rel: RelativeMeasurements) -> tuple[int, float]:
        """Gate, choose ω and apply the CI update of the module docstring. Returns the
        number accepted and their summed d² (the NIS it claims).

        The measurements are linearised on the joint [own, peers] estimate
        (:func:`swarmcore.mekf.gate`: residuals, Jacobian blocks and the gate's d²); the
        update is then the Kalman update of the own state with the prior ``P/ω`` and the
        measurement noise ``C(ω)`` of the module docstring, in Joseph form, with the
        multiplicative attitude reset — the own block of the joint update with those
        covariances, computed without the peers' (unobserved) states."""
        peers = sorted({int(x) for x in np.r_[rel.observer, rel.target]} - {self.own})
        self._used = peers
        row = {self.own: 0, **{j: r + 1 for r, j in enumerate(peers)}}
        e = self.e
        m = 1 + len(peers)
        st = [self._peers[j] for j in peers]
        P = np.zeros((BLOCK * m, BLOCK * m))
        P[:BLOCK, :BLOCK] = e.P
        for r, s in enumerate(st, start=1):
            blk = np.diag(np.full(BLOCK, _UNUSED_VAR))
            blk[np.ix_(POSE, POSE)] = s.P_pose
            P[BLOCK * r : BLOCK * (r + 1), BLOCK * r : BLOCK * (r + 1)] = blk
        joint = SwarmEstimate(e.step, e.t, np.vstack([e.q_BI, *[s.q_BI for s in st]]),
                              np.vstack([e.omega_BI_B, *[s.omega_BI_B for s in st]]), np.vstack([e.r_H, *[s.r_H for s in st]]),
                              np.vstack([e.v_H, *[s.v_H for s in st]]), e.bias_B, P)
        if m not in self._joint_params:
            self._joint_params[m] = dataclasses.replace(self.fp, n=m, own=0, max_iterations=1)
        jp = self._joint_params[m]
        local = RelativeMeasurements(np.array([row[int(i)] for i in rel.observer]), np.array([row[int(j)] for j in rel.target]),
                                     rel.q_BjBi, rel.r_ij_Bi, rel.R_Bi).canonical()
        y, Hi, Hj, d2, accepted = gate(joint, jp, local)
        if not accepted.any():
            return 0, 0.0
        # The accepted rows: Jacobian on the own 12 states and on the peers' [a, Δr], noise R.
        a = np.nonzero(accepted)[0]
        k = a.size
        Ho, Hp, R = stack_factors(local.subset(a), Hi[a], Hj[a], len(peers))
        Pp = np.zeros((6 * len(peers), 6 * len(peers)))
        for r, s in enumerate(st):
            Pp[6 * r : 6 * r + 6, 6 * r : 6 * r + 6] = s.P_pose
        bound = float(len(peers)) if self.params.correlated_peers else 1.0  # type: ignore[attr-defined]
        C_p = bound * (Hp @ Pp @ Hp.T)
        split = self.params.split  # type: ignore[attr-defined]

        def C(w: float) -> np.ndarray:
            return R + C_p / (1.0 - w) if split else (R + C_p) / (1.0 - w)

        if self.params.criterion == "det":  # type: ignore[attr-defined]
            W, lam = _whitened(e.P, Ho, R, C_p, split)
            w_c = kernels.ci_det_weight(W, lam, split)
            w = w_c if w_c is not None else ci_weight(_logdet_cost(W, lam, split))
        else:
            def trace_cost(w: float) -> float:
                Pw = e.P / w
                S = Ho @ Pw @ Ho.T + C(w)
                K = np.linalg.solve(S, Ho @ Pw).T
                return float(np.trace(pose_block(Pw - K @ S @ K.T)))
            w = ci_weight(trace_cost)
        Pw, Cw = e.P / w, C(w)
        PHt = Pw @ Ho.T
        S = Ho @ PHt + Cw
        K = np.linalg.solve(S, PHt.T).T
        A = np.eye(BLOCK) - K @ Ho
        P_post = A @ Pw @ A.T + K @ Cw @ K.T
        self.est = apply_correction(e, self.fp, K @ y[a].ravel(), P_post)
        self.last_omega = w
        return int(k), float(d2[accepted].sum())

    def view(self) -> EstimateView:
        """Its own posterior and the peers it fused with this step (their broadcast priors:
        what it knows of them), without cross-covariance."""
        rows = ViewRows(self.own, list(self._used), self.e)
        for j in self._used:
            s = self._peers[j]
            rows.set(j, s.q_BI, s.omega_BI_B, s.r_H, s.v_H, P_pose=s.P_pose)
        return rows.view(with_cross=False)


