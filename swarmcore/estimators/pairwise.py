"""``pairwise``: recursive decentralized localization with pairwise cross-covariance factors.

After Luft, Schubert, Roumeliotis and Burgard, "Recursive decentralized localization for
multi-robot systems with asynchronous pairwise communication" (IJRR 2018; ICRA 2016).
Each agent i keeps its own state ``x_i`` (12 error states, its gyro in
dynamic-model-replacement mode) with ``P_ii``, and for every peer j a factor ``σ_ij``
(12×12) of their cross-covariance, ``P_ij ≈ σ_ij σ_jiᵀ``, of which each side holds one half:

* **Propagation** (no communication): ``x_i, P_ii`` by the own model; ``σ_ij ← Φ_i σ_ij``
  for every j (so that ``Φ_i P_ij Φ_jᵀ = (Φ_i σ_ij)(Φ_j σ_ji)ᵀ``).
* **Encounter** of i and j (a relative measurement between them, either direction):
  the joint prior ``[[P_ii, σ_ij σ_jiᵀ], [σ_ji σ_ijᵀ, P_jj]]`` is updated by an EKF with
  the measurement(s); i keeps ``x_i⁺, P_ii⁺``; the cross-covariance ``P_ij⁺`` is stored
  whole on the side with the lower id (``σ = P_ij⁺``) and as the identity on the other;
  with every other peer l, ``σ_il ← P_ii⁺ (P_ii⁻)⁻¹ σ_il`` (Luft et al.'s approximation:
  the correlation with absent robots follows the change of the own covariance).

How the encounters fit a lockstep swarm: each agent broadcasts its prior of the step
(:class:`PairwiseState`: state, ``P_ii`` and its factors toward its graph neighbours).
Luft et al.'s robot that measures sends the joint result to the other; here both ends of
an encounter compute the same joint update from the same broadcast priors and factors and
each keeps its own half, which needs no second message in the step. That works only when
both ends start from the same priors, so — as in the paper, where a robot talks with one
partner at a time — an agent meets at most one peer per step: the pairs that meet at step
k are the edges of colour ``k mod C`` of a proper edge colouring of the measurement graph
(:func:`swarmcore.graphs.encounter_schedule`, a matching every agent computes alike), and
both directions' measurements of the pair are used together. Measurements of pairs not
scheduled at their step are not used (counted ``unscheduled``): the price of consistency
in this method. A peer whose prior did not arrive cannot be met; its measurements are
counted ``unusable``. Late deliveries are dropped and counted. The factors' product can imply a correlation
above one (the approximation of absent robots' correlations); such a cross-covariance is
shrunk until the joint prior is a covariance, and counted (``shrunk``).

``absent``: what an encounter of i and j does to i's factors toward the other peers l.
``scale`` (the default, Luft et al.): ``σ_il ← P_ii⁺ (P_ii⁻)⁻¹ σ_il``, exact when the
update touches i alone (its own star tracker and GPS, where it is always applied), an
approximation after an encounter: the exact ``P_il⁺ = P_il − K_i (H_i P_il + H_j P_jl)``
needs ``P_jl``, which i does not have, and the rule amounts to ``P_jl ≈ P_ji P_ii⁻¹ P_il``.
``keep``: the factors are left as they are, i.e. ``P_jl ≈ P_il`` on the measured states: a
relative measurement is blind to the error that i and j share (``H_i + H_j`` vanishes on
the positions), and in a swarm localised through its neighbours the error a third peer
shares with i it largely shares with j too. Measured: docs/estimators.md (item 5 of
issue 33: ``scale`` is overconfident on held-out seeds).

Bearings (``sensors.relative.model: bearing``): the encounter's joint update is
:func:`swarmcore.mekf.update` with ``relative_kind: bearing``, so a line of sight shared in
I (the observer turned it with its own prior, :meth:`prediction`) is a 2-row measurement
of the two positions, gated with χ²(2), as in ``full``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from pydantic import Field

from ..graphs import encounter_schedule, scenario_graph
from ..mekf import BLOCK, RelativeMeasurements, SwarmEstimate, predict, state_jacobian_blocks, update
from .base import EstimateView, EstimatorParams, StepInputs, StepReport
from .own import OwnStateEstimator
from .views import POSE, ViewRows

__all__ = ["PairwiseEstimator", "PairwiseParams", "PairwiseState"]


class PairwiseParams(EstimatorParams):
    absent: str = Field(
        "scale", pattern="^(scale|keep)$",
        description="what an encounter with j does to the factors toward the other peers l: scale (Luft et al.: "
        "σ_il ← P_ii⁺ (P_ii⁻)⁻¹ σ_il) or keep (unchanged: a relative measurement is blind to the error i and j share with l)")
    neighbours: str = Field(
        "graph", pattern="^(graph|all)$",
        description="whose factors an agent broadcasts: graph (its measurement graph's neighbours, in and out; bounded "
        "traffic) or all (every peer it has met)")


@dataclass(frozen=True)
class PairwiseState:
    """What a ``pairwise`` agent broadcasts each step: its prior and its cross-covariance
    factors toward the peers it may meet."""

    sat: int
    step: int
    q_BI: np.ndarray  # (4,)
    omega_BI_B: np.ndarray  # (3,) rad/s
    r_H: np.ndarray  # (3,) m
    v_H: np.ndarray  # (3,) m/s
    bias_B: np.ndarray  # (3,) rad/s
    P: np.ndarray  # (12, 12)
    partners: np.ndarray  # (p,) int, ascending
    sigma: np.ndarray  # (p, 12, 12): σ_{sat, partner}


class PairwiseEstimator(OwnStateEstimator):
    kind = "pairwise"
    radio = "graph"  # it meets only graph neighbours and reads only their messages
    accepts_bearings = True  # angles-only bearings in I (module docstring)
    Params = PairwiseParams

    def __init__(self, sc, own: int, params: PairwiseParams | None = None):
        super().__init__(sc, own, params)
        self.jp = dataclasses.replace(self.fp, n=2, own=0, max_iterations=1)
        self.sigma: dict[int, np.ndarray] = {}  # σ_{own, j}
        G = scenario_graph(sc)
        nb = np.nonzero(G[own] | G[:, own])[0]
        self.neighbours = sorted(int(j) for j in nb if j != own)
        self.colour, self.colours = encounter_schedule(G)
        self.unscheduled = 0
        self.shrunk = 0  # encounters whose factors gave a joint prior that was not positive-definite
        self._heard: dict[int, PairwiseState] = {}
        self._met: dict[int, tuple[SwarmEstimate, np.ndarray]] = {}  # this step's joint posterior with j, and P_ij⁺
        self.unusable = 0

    def propagate(self, gyro_rate_B) -> None:
        """The own prediction, and every factor with it: ``σ_ij ← Φ_i σ_ij``."""
        e = self.e
        omega_own = e.omega_BI_B[0] if gyro_rate_B is None else np.asarray(gyro_rate_B, float) - e.bias_B
        phi = state_jacobian_blocks(e, self.fp, omega_own)[0][0]
        self.est = predict(e, self.fp, gyro_rate_B)
        for j in self.sigma:
            self.sigma[j] = phi @ self.sigma[j]

    def _partners(self) -> list[int]:
        if self.params.neighbours == "all":  # type: ignore[attr-defined]
            return sorted(self.sigma)
        return [j for j in self.neighbours if j in self.sigma]

    def transmit(self, k: int) -> PairwiseState:
        e = self.e
        if e.step != k:
            raise ValueError(f"pairwise estimator of satellite {self.own}: transmit({k}) with its estimate at step {e.step}")
        partners = self._partners()
        sig = np.stack([self.sigma[j] for j in partners]) if partners else np.zeros((0, BLOCK, BLOCK))
        return PairwiseState(self.own, k, e.q_BI[0].copy(), e.omega_BI_B[0].copy(), e.r_H[0].copy(), e.v_H[0].copy(),
                             e.bias_B.copy(), e.P.copy(), np.array(partners, dtype=int), sig)

    def _cross(self, j: int, s: PairwiseState) -> np.ndarray:
        """``P_ij = σ_ij σ_jiᵀ`` from our factor and the one j broadcast (zero if either
        side has none: never met)."""
        mine = self.sigma.get(j)
        hit = np.nonzero(s.partners == self.own)[0]
        if mine is None or not hit.size:
            return np.zeros((BLOCK, BLOCK))
        return mine @ s.sigma[hit[0]].T

    def step(self, inputs: StepInputs) -> StepReport:
        k = inputs.step
        self.begin_step(k, inputs.gyro_rate_B)
        rep = StepReport(late_dropped=sum(len(r.measurements) for r in inputs.late()))
        before = self.e.P
        nis, dof = self.update_absolute(inputs.absolute)
        if dof:
            self._scale_factors(self.e.P, before, skip=None)
        self._met = {}
        by_partner: dict[int, list[RelativeMeasurements]] = {}
        own = inputs.own
        for j in sorted({int(t) for t in own.target}):
            by_partner.setdefault(j, []).append(own.subset(own.target == j))
        peers = inputs.on_time_measurements()
        of_me = peers.subset(peers.target == self.own)
        for j in sorted({int(o) for o in of_me.observer}):
            by_partner.setdefault(j, []).append(of_me.subset(of_me.observer == j))
        # Only the messages of the step's partners and graph neighbours are read (the view
        # shows the neighbours heard).
        wanted = set(self.neighbours) | set(by_partner)
        self._heard = {r.sender: r.payload for r in inputs.on_time() if r.sender in wanted and isinstance(r.payload, PairwiseState)}
        active = k % self.colours
        for j in sorted(by_partner):
            meas = RelativeMeasurements.concat(by_partner[j])
            if self.colour[self.own, j] != active:
                self.unscheduled += len(meas)
                continue
            s = self._heard.get(j)
            if s is None:
                self.unusable += len(meas)
                continue
            acc, rej, d2 = self._encounter(j, s, meas)
            rep.gate_accepted += acc
            rep.gate_rejected += rej
            nis, dof = nis + d2, dof + self.fp.rel_dof * acc
        rep.nis, rep.nis_dof = (nis, dof) if dof else (float("nan"), 0)
        rep.extra["unusable"] = self.unusable
        rep.extra["unscheduled"] = self.unscheduled
        rep.extra["shrunk"] = self.shrunk
        self._pending = False
        return rep

    def _scale_factors(self, P_new: np.ndarray, P_old: np.ndarray, skip: int | None) -> None:
        """``σ_il ← P_ii⁺ (P_ii⁻)⁻¹ σ_il`` for every peer l but ``skip``."""
        ls = [j for j in self.sigma if j != skip]
        if not ls:
            return
        cf = sla.cho_factor(P_old, lower=True)
        for j in ls:
            self.sigma[j] = P_new @ sla.cho_solve(cf, self.sigma[j])

    def _bounded_cross(self, Pi: np.ndarray, Pj: np.ndarray, Pij: np.ndarray, count: bool = True) -> np.ndarray:
        """The cross-covariance the factors give, shrunk if need be so that the joint prior
        is a covariance: the factors are an approximation (Luft et al.), and their product
        can imply a correlation above one. With ``C = L_i⁻¹ P_ij L_j⁻ᵀ`` (``P = L Lᵀ``), the
        joint is positive-definite iff ‖C‖₂ < 1; above 0.999 it is scaled back to it."""
        if not Pij.any():
            return Pij
        Li, Lj = np.linalg.cholesky(Pi), np.linalg.cholesky(Pj)
        C = np.linalg.solve(Li, np.linalg.solve(Lj, Pij.T).T)
        s = float(np.linalg.norm(C, 2))
        if s < 0.999:
            return Pij
        if count:
            self.shrunk += 1
        return Pij * (0.999 / s)

    def _encounter(self, j: int, s: PairwiseState, meas: RelativeMeasurements) -> tuple[int, int, float]:
        """The joint update with peer j (module docstring). Returns accepted, rejected, Σ d²."""
        e = self.e
        me = self.own
        P = np.zeros((2 * BLOCK, 2 * BLOCK))
        P[:BLOCK, :BLOCK] = e.P
        P[BLOCK:, BLOCK:] = s.P
        Pij = self._bounded_cross(e.P, s.P, self._cross(j, s))
        P[:BLOCK, BLOCK:] = Pij
        P[BLOCK:, :BLOCK] = Pij.T
        # The peer in "other" mode: its rate state is its bias-corrected gyro rate; its bias
        # sub-block stands in for the rate's uncertainty (unobserved by the measurement).
        joint = SwarmEstimate(e.step, e.t, np.vstack([e.q_BI, s.q_BI]), np.vstack([e.omega_BI_B, s.omega_BI_B]),
                              np.vstack([e.r_H, s.r_H]), np.vstack([e.v_H, s.v_H]), e.bias_B, P)
        row = {me: 0, j: 1}
        local = RelativeMeasurements(np.array([row[int(x)] for x in meas.observer]), np.array([row[int(x)] for x in meas.target]),
                                     meas.q_BjBi, meas.r_ij_Bi, meas.R_Bi).canonical()
        post, urep = update(joint, self.jp, None, local)
        acc = urep.n_accepted
        if acc == 0:
            return 0, urep.n_rejected, 0.0
        P_old = e.P
        self.est = SwarmEstimate(e.step, e.t, post.q_BI[:1].copy(), post.omega_BI_B[:1].copy(), post.r_H[:1].copy(),
                                 post.v_H[:1].copy(), post.bias_B.copy(), post.P[:BLOCK, :BLOCK].copy())
        if self.params.absent == "scale":  # type: ignore[attr-defined]
            self._scale_factors(self.e.P, P_old, skip=j)
        self.sigma[j] = post.P[:BLOCK, BLOCK:].copy() if me < j else np.eye(BLOCK)
        self._met[j] = (post, post.P[:BLOCK, BLOCK:].copy())
        return acc, urep.n_rejected, float(urep.d2[urep.accepted].sum())

    def view(self) -> EstimateView:
        """Its own posterior, the peer it met this step (the joint posterior of that
        encounter) and the graph neighbours it heard (their broadcast priors, with the
        cross-covariance of the factors)."""
        peers = sorted(j for j in self._heard if j in self._met or j in self.neighbours)
        rows = ViewRows(self.own, peers, self.e)
        for j in peers:
            if j in self._met:  # what the encounter of this step made of j (later encounters of ours move only us)
                post, Pij = self._met[j]
                rows.set(j, post.q_BI[1], post.omega_BI_B[1], post.r_H[1], post.v_H[1], P12=post.P[BLOCK:, BLOCK:],
                         P_cross=Pij.T[np.ix_(POSE, POSE)])
            else:
                s = self._heard[j]
                Pij = self._cross(j, s)
                if self.params.absent == "keep":  # type: ignore[attr-defined]
                    # Unscaled factors imply larger correlations: claim a joint that is a covariance.
                    Pij = self._bounded_cross(self.e.P, s.P, Pij, count=False)
                rows.set(j, s.q_BI, s.omega_BI_B, s.r_H, s.v_H, P12=s.P,
                         P_cross=Pij.T[np.ix_(POSE, POSE)])  # P_ji: peer rows, own columns
        return rows.view(with_cross=True)
