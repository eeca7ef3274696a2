"""``gbp``: Gaussian belief propagation on the swarm's factor graph (a Robot Web).

After Murai, Ortiz, Saeedi, Kelly and Davison, "A Robot Web for Distributed Many-Device
Localisation" (IEEE T-RO 2024): each device holds its own variables and the factors that
touch them, and talks only to the devices it shares a factor with, by GBP messages. Here
the variable of satellite i at step k is its own 12 error states
``x_i = [a_i (rad, B_i), Δβ_i (rad/s), Δr_H,i (m), Δv_H,i (m/s)]`` (the own block of the
full filter: gyro in dynamic-model-replacement mode), everything older marginalised (in the
filter forms ``ci`` and ``kalman`` into the belief's Gaussian prior, a 12-state MEKF,
:class:`~swarmcore.estimators.own.OwnStateEstimator`; in ``joint``, the default, into the
pair potentials below). Its factors at k:

* the **dynamics/gyro factor** ``x_i^k = Φ_i x_i^{k−1} + w``, ``w ~ N(0, Q_i)`` — the
  prediction of the marginalised window, :func:`swarmcore.mekf.predict`;
* the **absolute factor** of its own star tracker and GPS (anchors only);
* one **relative factor** per relative pose measurement between i and a graph neighbour
  j (either observer): ``z_ij = h(x_i, x_j) + v``, ``v ~ N(0, R)``, linearised at the
  current means, ``y = z ⊟ h(x̂_i, x̂_j) ≈ H_i δx_i + H_j δx_j + v`` (Jacobian blocks of
  :func:`swarmcore.mekf.relative_residuals`, those of every filter of the project, stacked
  by :func:`stack_factors`).

**fusion: joint (the default): pair potentials, messages replaced.** Each agent keeps
the *pair potentials* of its factors as one Gaussian over ``[x_i, x_j …]`` (its own 12
states and those of each graph neighbour j): its own dynamics and readings and every
relative factor it shares with a neighbour, of every step, each neighbour's row carried
by that neighbour's dynamics (its attitude turned by the rate the neighbour broadcasts,
which is also a measurement of its row with the gyro bias prior's σ_b, the attitude
random-walking at σ_b √τ for the time τ that rate's error holds, :data:`_RATE_HOLD_S`; its
translation by the filter's model) and started wide at its first message — and *no neighbour's belief*:
what j's side knows never enters it, so nothing is counted twice through time. These are
Kalman updates (the camera, star tracker, GPS noises are independent), linearised at the
last fused estimate (the mean sits at ``d`` from it, residuals ``y − H d``;
:func:`joint_factors`). Each step the neighbours' messages — their cavities towards i,
pose marginals, ``m_{j→f}`` — are fused as measurements of their rows into a *copy*: the
belief is ``b_i = ∫ Π_j f_ij · own · Π_j m_{j→f_ij} dx_j`` (the joint's own marginal after
the fusion), the cavity towards j the same without j's message and with j's row
marginalised out (j's factors then carry, with j's row free, only what j's dynamics model
says about x_i's motion: the approximation of this mode). The copy is thrown away: the
next step fuses that step's messages into the pair potentials afresh — GBP's messages
replace, as in the Robot Web's window, where a filter that multiplies them into its prior
counts them again every step (plain GBP: NEES/dof 119 on the study, below). A neighbour
whose message of the step did not come is fused with its last one, carried to the step
through its row's dynamics (``z = M δx_j + n``, ``M = E Φ⁻¹ …``, its process noise added;
held for ``filter.history_s``). With a fixed link latency of L steps (``links.latency``,
``filter.late: replay``) every message is late: each cavity is then sent predicted L steps
(its held rate, the gyro bias prior's σ) and used at the step it arrives at, fresh. The
loops of the graph (triangles: ``i → l → j → i``) still correlate the messages with each
other and with the pair potentials. ``peers: common`` (``auto``, the default, with relative
pose measurements) takes each message's error as its own part plus a part common to all of
them — the swarm's absolute attitude and position, which every neighbour's estimate draws
from the same anchors — and fuses the stack with ``blockdiag(C_k) + (m − 1)/m · B G Bᵀ``
(:func:`_peer_noise`: at or above every covariance of that model), so the differences
between the neighbours keep their information and what they share counts once;
``peers: bound`` (``auto`` with bearings) fuses the m messages with their covariances times
m (for any mutual correlation), ``independent`` and ``sequential`` (the same thing for a
Kalman product) as they are — GBP's own assumption. The view claims the joint copy's own
row and each neighbour's with their cross-covariance. Costs: the joint's (1 + m)·12
states, m + 1 Kalman updates of a step; the message is the same as below.

**Messages** (``fusion: ci`` and ``kalman``, the filter forms kept beside it). Variable → factor: the belief of ``x_j`` with the factor's own incoming
message removed, ``m_{j→f}(x_j) = b_j(x_j) / m_{f→j}(x_j)``. Over a time window the
messages of ``f_ij`` of every earlier step reach ``x_j^k`` through the dynamics factors
too, so dividing out only the last one still double counts; what removes all of them is a
*cavity belief*: agent j runs, beside its belief ``b_j``, one belief per graph neighbour i
that takes every factor of j but the ``f_ij`` (of all steps), ``b_j^{∖i}``. Its pose
marginal (6×6: the relative factor touches only ``[a, Δr]``) is j's message to i; j
broadcasts one per neighbour each step (:class:`GbpMessage`). Factor → variable (computed
by i, which holds its copy of ``f_ij``): the factor times the incoming message, ``x_j``
marginalised out — for the linearised factor a pseudo-measurement of ``x_i`` alone,

    y ≈ H_i δx_i + n,      n ~ N(0, S),      S = R + H_j P_j^{∖i} H_jᵀ,

in information form ``Λ_{f→i} = H_iᵀ S⁻¹ H_i``, ``η_{f→i} = H_iᵀ S⁻¹ (y + H_i δx̂_i)``
(:func:`factor_message`; a pair's measurements of one step stacked, correlated through
``P_j^{∖i}``). The belief is the product of its prior and every factor message,
``Λ_i = Λ_prior + Σ_f Λ_{f→i}``, applied as the equivalent Kalman update (Joseph form,
multiplicative attitude reset). Each cavity ``b_i^{∖l}`` takes every message but those of
``f_il``. The factors are linearised once a step, at the belief's mean: a cavity that sits
at ``d = x_c ⊟ x_b`` from it gets the residual ``y − H_i d``; likewise the cavities are
predicted by the belief's dynamics factor, ``x_c⁺ = x_b⁺ ⊞ Φ d``, ``P_c⁺ = Φ P_c Φᵀ + Q``.
One GBP iteration per step: the factors of step k are new at k, and a second iteration
would need a second exchange in the step.

**Why a conservative device.** Unrolled in time the factor graph has a loop at every step
even when the measurement graph is a tree: ``x_i^{k−1} — f_ij^{k−1} — x_j^{k−1} — x_j^k —
f_ij^k — x_i^k — x_i^{k−1}``. j's cavity of step k still holds what j's side knew at k−1,
which i already received through ``f_ij^{k−1}``; on the study's graph (each satellite
measures its three nearest: triangles) information also goes round ``i → l → j → i``.
GBP's means are right on loopy Gaussian graphs but its covariances come out overconfident
(Weiss & Freeman, Neural Computation 2001), and in a filter that compounds step after
step. Measured with plain GBP (``fusion: kalman``) on ``scenarios/estimators.yaml``:
NEES/dof 119 (own position error 34 mm in the second half, seed 40), and 2.9 with the
graph made a chain (a tree).
The incoming factor messages are therefore fused by **split covariance intersection**
(Julier & Uhlmann 2001; :mod:`.ci`; ``fusion: ci``, the default):

    P⁺⁻¹ = ω P⁻¹ + (1 − ω) H_iᵀ C(ω)⁻¹ H_i,   C(ω) = R + H_j P_j^{∖i} H_jᵀ / (1 − ω),

ω minimising ``det P⁺`` for the belief (:func:`swarmcore.kernels.ci_det_weight`), and the
same ω for its cavities (CI is consistent for every ω in (0, 1]; the search only makes
it tight). It is consistent whatever the unknown correlation between ``b_i`` and the
incoming cavities; the camera noise R is independent and not inflated. The incoming
cavities carry less of i's own information than the beliefs ``ci`` fuses (no direct
echo of ``f_ij``): what ``gbp`` can gain over ``ci`` (measured: docs/estimators.md). The loops correlate
the neighbours' cavities with each other as well, which CI between the belief and their
stack does not cover: ``peers: bound`` (``auto``'s choice for the filter forms) bounds the
stacked covariance of the m neighbours' cavities by ``m · blockdiag(P_1, …, P_m)`` (for any
correlation, ``Var(Σ x_k) ≤ m Σ Var(x_k)``; as ``ci`` does), i.e. ``C(ω) = R + m H_j P_j H_jᵀ/(1 − ω)``;
``peers: sequential`` fuses one neighbour at a time, each by its own CI (consistent too,
less accurate on the study's graph); ``peers: independent`` takes them as independent of
each other, GBP's own assumption — consistent on the sparse study graph (NEES/dof 0.68)
but overconfident on a complete graph (``scenarios/baseline.yaml``, 250 s: NEES/dof 2.2). ``fusion: kalman`` is plain GBP (ω = 1),
kept to measure what the loops cost. Not chosen: message damping (it slows the means but
bounds no covariance), and a sliding window of several states with conservative
marginalisation (its iterations need more than one exchange a step, and a message per
state of the window); ``joint`` keeps the window's point — messages replace — at one
message a step.

**Why GBP and not ADMM/iMESA.** Consensus ADMM (MESA, iMESA, RSS 2024) reaches the
centralised MAP by iterating to consensus on shared variables — several exchanges a step,
with their dual variables — and gives no covariance without a further computation; the
lockstep radio gives one exchange a step, and every estimator here must claim a
covariance that NEES can hold it to. GBP gives a belief (mean and covariance) after every
single exchange, uses only the messages that arrive, and needs no global step size or
consensus schedule (Murai et al.).

**The view.** Its own row is its belief. A neighbour j whose factor it used at the step is
claimed from that factor's belief ``b_f(x_i, x_j) ∝ f_ij · m_{i→f} · m_{j→f}`` (BP's edge
marginal: its own cavity towards j and j's cavity towards i, uncorrelated, updated by the
pair's measurements): j's pose and covariance, claimed uncorrelated with its own belief
(as ``ci`` claims its peers).

**Wire.** :class:`GbpMessage` travels as bytes (:meth:`GbpEstimator.encode`, the plug-in
path: ``EstimatorMessage.opaque``): per target its cavity quaternion and position (float32) and
the lower Cholesky factor of its 6×6 pose covariance (so the receiver's covariance is PSD
by construction) as 21 float16 with a power-of-two scale per row and a float32 factor
κ ≥ 1 that keeps the rebuilt covariance at or above the sender's (:func:`pack_cholesky`);
the sender's rate and velocity once; 82 B per neighbour and 34 B a message. The payload
is quantised at :meth:`transmit`, so the in-process message is the decoded one, bit for
bit.

**Bearings** (``sensors.relative.model: bearing``): as in :mod:`.ci`, a line of sight shared
in I is a relative factor of the two positions alone (2 rows of the 6-row layout), linearised
by the same :func:`stack_factors`, fused into the belief, the cavities and the edge beliefs
like a pose.

**Late deliveries** (``filter.late: replay``, as ``ci``): each step's beliefs, readings,
measurements and what it heard are kept for ``filter.history_s``; a message of step s
arriving at k is filed under s and the beliefs (own and cavities) are re-run from s.
Older than the history, or with ``drop``: dropped. Counted either way (``late_used``,
``late_dropped``, over the measurements involving the agent).
"""

from __future__ import annotations

import dataclasses
import math
import struct
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import Field

from .. import kernels, quat
from ..graphs import scenario_graph
from ..mekf import (
    BLOCK,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    absolute_residual,
    apply_correction,
    gate,
    predict,
    propagate_blockdiag,
    state_jacobian_blocks,
)
from .base import EstimateView, EstimatorParams, IncompatibleScenario, StepInputs, StepReport
from .ci import _block_diag, _logdet_cost, _whitened, ci_weight, stack_factors
from .own import Kept, ReplayingEstimator, absolute_update
from .views import POSE, ViewRows, pose_block

__all__ = ["GbpEstimator", "GbpParams", "GbpMessage", "factor_message", "joint_factors", "stack_factors", "pack_cholesky",
           "unpack_cholesky"]

#: Variance of a peer's rate and velocity states in a joint linearisation (the relative
#: factor has zero Jacobian columns there: any positive value gives the same result).
_UNUSED_VAR = 1.0
_TRI = np.tril_indices(6)
_HEAD = struct.Struct("<iiH")  # sat, step, number of targets


class GbpParams(EstimatorParams):
    fusion: str = Field("joint", pattern="^(joint|ci|kalman)$",
                        description="joint (pair potentials with each graph neighbour, the neighbours' messages fused afresh each "
                        "step, never accumulated), ci (a filter that accumulates the messages by split covariance intersection) "
                        "or kalman (plain GBP in a filter, overconfident on loops)")
    peers: str = Field("auto", pattern="^(auto|sequential|bound|independent|common)$",
                       description="how the neighbours' messages' unknown mutual correlation is handled: auto (common with "
                       "relative pose measurements, bound with bearings), common (their errors taken as their own plus a part "
                       "common to all, the swarm's absolute attitude and position, counted once), bound (their stack bounded by "
                       "m × blockdiag: for any correlation), "
                       "sequential (one CI per neighbour, in id order; filter forms) or independent (taken as independent of "
                       "each other: overconfident on dense graphs)")


_TRI_ROW = _TRI[0]  # the row of each packed entry
#: How much wider than the scenario's initial σ a neighbour's row of the pair potentials
#: starts (``fusion: joint``): only the pair's own factors pin it.
_DIFFUSE = 10.0
#: ``fusion: joint``: how long (s) a neighbour's broadcast rate error is taken to hold (its
#: row's attitude random walk, σ_b √τ). Measured on scenarios/estimators.yaml (10 seeds,
#: ideal radio): τ = 1, 4, 15, 25 s gave own position 1.20×, 1.20×, 1.20×, 1.21× central,
#: relative (against central's RMS over all pairs; on the pairs both estimate 1.47× at 15 s)
#: 1.38×, 1.33×, 1.28×, 1.28×, attitude 1.43× at 4 s and 1.35× at 15 s, NEES/dof
#: 0.72, 0.61, 0.51, 0.49 (relative 1.00, 0.84, 0.69, 0.65); 0 s (the gyro's ARW alone)
#: 1.21×, 1.42×, 0.80 (relative 1.11, seeds up to 1.6).
_RATE_HOLD_S = 15.0
#: ``fusion: joint`` behind a fixed latency: the σ of the rate a cavity is predicted by over
#: the latency (held, no gyro for the steps ahead), in gyro bias prior σ_b per step. The rate
#: is held for all L steps, and the satellite's own rotation changes it meanwhile: white
#: noise of σ_b a step claimed too much. Measured on scenarios/estimators.yaml (10 seeds,
#: 3 s latency, with and without 20 % bursty loss): 1 σ_b gave NEES/dof 1.07 and 1.00 (a
#: seed 1.44 and 1.32), 5 σ_b 0.61 and 0.62 (largest 0.76 and 0.79) for own position 1.24× →
#: 1.25× and 1.17× → 1.19× central; 20 σ_b (seed 44) 0.54, own position 3.48 → 3.68 mm.
_LEAD_RATE_SIGMAS = 5.0


@dataclass(frozen=True)
class _Pairs:
    """``fusion: joint``: the agent's pair potentials over ``[x_i, x_j …]`` (own row 0, its
    graph neighbours after it): its own factors and every relative factor it shares, with
    no neighbour's belief in them, as a Gaussian whose mean sits at ``d`` from ``ref`` (the
    fused estimate of the last step: the linearisation point) with covariance ``P``."""

    ref: SwarmEstimate
    d: np.ndarray
    P: np.ndarray
    live: frozenset
    #: neighbour → its last message as a measurement of its row now: ``(z, M, C, age)``,
    #: ``z = M δx_j + n``, ``n ~ N(0, C)`` (M = [I on the pose] when it is of this step; an
    #: older one carried through the row's dynamics, its process noise added to C)
    held: dict


def pack_cholesky(P: np.ndarray) -> tuple[np.float32, np.ndarray, np.ndarray]:
    """A 6×6 covariance as ``(κ, e, u)``: the packed rows of its lower Cholesky factor,
    each row ``r`` scaled by ``2^−e_r`` (int8; its largest entry within [½, 1)) and rounded
    to float16 ``u``, and the float32 ``κ ≥ 1`` by which the rebuilt factor is multiplied so
    that the rebuilt covariance is at or above ``P`` (the largest generalised eigenvalue of
    ``P`` against the rounded one, rounded up): the rounding never makes a message claim more
    than its sender knows. :func:`unpack_cholesky` is its inverse."""
    tri = np.linalg.cholesky(P)[_TRI]
    rowmax = np.array([np.abs(tri[r == _TRI_ROW]).max() for r in range(6)])
    e = np.clip(np.ceil(np.log2(np.maximum(rowmax, 1e-300))), -127, 127).astype(np.int8)
    u = (tri * np.exp2(-e.astype(float))[_TRI_ROW]).astype(np.float16)
    Lt = _rebuild(np.float32(1.0), e, u)
    W = np.linalg.solve(Lt, np.linalg.solve(Lt, P).T)
    kappa = max(1.0, float(np.sqrt(np.linalg.eigvalsh(0.5 * (W + W.T)).max())))
    k32 = np.float32(kappa)
    if float(k32) < kappa * (1.0 + 1e-9):
        k32 = np.nextafter(np.float32(kappa * (1.0 + 1e-9)), np.float32(np.inf))
    return k32, e, u


def _rebuild(kappa: np.float32, e: np.ndarray, u: np.ndarray) -> np.ndarray:
    L = np.zeros((6, 6))
    L[_TRI] = u.astype(float) * np.exp2(e.astype(float))[_TRI_ROW] * float(kappa)
    return L


def unpack_cholesky(kappa: np.float32, e: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The covariance :func:`pack_cholesky` packed (PSD by construction, ⪰ the sender's)."""
    L = _rebuild(kappa, e, u)
    return L @ L.T


@dataclass(frozen=True, eq=False)
class GbpMessage:
    """What a ``gbp`` agent broadcasts at step k: for each graph neighbour (``targets``) its
    cavity belief's pose towards it (the variable → factor message).

    ``q_BI`` (p, 4) and ``r_H`` (p, 3) m in float32; the 6×6 ``[a, Δr]`` covariance as
    :func:`pack_cholesky` packs it: ``L_scale`` (p,) float32 κ, ``L_exp`` (p, 6) int8 row
    exponents, ``L_unit`` (p, 21) float16; ``omega_BI_B`` (3,) rad/s and ``v_H`` (3,) m/s of
    its own belief in float32. What :meth:`pose` rebuilds from these is what the
    receiver uses, in-process and across the bus alike."""

    sat: int
    step: int
    targets: np.ndarray  # (p,) int
    q_BI: np.ndarray  # (p, 4) float32
    r_H: np.ndarray  # (p, 3) float32
    L_scale: np.ndarray  # (p,) float32
    L_exp: np.ndarray  # (p, 6) int8
    L_unit: np.ndarray  # (p, 21) float16
    omega_BI_B: np.ndarray  # (3,) float32
    v_H: np.ndarray  # (3,) float32

    @staticmethod
    def size_of(p: int) -> int:
        """Encoded bytes for p targets."""
        return _HEAD.size + 2 * p + 4 * (8 * p + 6) + 6 * p + 2 * 21 * p

    def row(self, target: int) -> int | None:
        hit = np.nonzero(self.targets == target)[0]
        return int(hit[0]) if hit.size else None

    def pose(self, r: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row r's (q_BI, r_H, P_pose) in float64 (q normalised, P :func:`unpack_cholesky`)."""
        q = self.q_BI[r].astype(float)
        return q / np.linalg.norm(q), self.r_H[r].astype(float), unpack_cholesky(self.L_scale[r], self.L_exp[r], self.L_unit[r])

    def encode(self) -> bytes:
        p = int(self.targets.size)
        f32 = (np.ascontiguousarray(a, "<f4").tobytes() for a in (self.q_BI, self.r_H, self.L_scale, self.omega_BI_B, self.v_H))
        return b"".join([_HEAD.pack(self.sat, self.step, p), np.asarray(self.targets, "<u2").tobytes(), *f32,
                         np.ascontiguousarray(self.L_exp, "i1").tobytes(), np.ascontiguousarray(self.L_unit, "<f2").tobytes()])

    @classmethod
    def decode(cls, data: bytes) -> GbpMessage:
        if len(data) < _HEAD.size:
            raise ValueError(f"gbp message: {len(data)} bytes, shorter than its header")
        sat, step, p = _HEAD.unpack_from(data)
        if len(data) != cls.size_of(p):
            raise ValueError(f"gbp message: {len(data)} bytes for {p} targets, expected {cls.size_of(p)}")
        o = _HEAD.size
        targets = np.frombuffer(data, "<u2", p, o).astype(int)
        o += 2 * p
        f = np.frombuffer(data, "<f4", 8 * p + 6, o).astype(np.float32)
        o += 4 * (8 * p + 6)
        ex = np.frombuffer(data, "i1", 6 * p, o).astype(np.int8).reshape(p, 6)
        o += 6 * p
        h = np.frombuffer(data, "<f2", 21 * p, o).astype(np.float16).reshape(p, 21)
        if not (np.isfinite(f).all() and np.isfinite(h).all()):
            raise ValueError("gbp message: non-finite values")
        q, r, sc = f[: 4 * p].reshape(p, 4), f[4 * p : 7 * p].reshape(p, 3), f[7 * p : 8 * p].copy()
        if p and ((np.linalg.norm(q, axis=1) < 0.5).any() or (sc < 1).any()):
            raise ValueError("gbp message: a quaternion far from unit norm or a covariance scale below 1")
        return cls(int(sat), int(step), targets, q, r, sc, ex, h, f[8 * p : 8 * p + 3].copy(), f[8 * p + 3 :].copy())

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, GbpMessage):
            return NotImplemented
        return self.encode() == other.encode()

    __hash__ = None  # type: ignore[assignment]


def joint_factors(local: RelativeMeasurements, Hi: np.ndarray, Hj: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``fusion: joint``: the linearised relative factors on the pair potentials' joint of n
    satellites (the own row 0, its neighbours after it): ``y ≈ H δx + v``, ``H`` (6m × 12n)
    with the observer's block ``Hi`` and the target's ``Hj`` on their [a, Δr] columns, ``R``
    (6m × 6m) the camera noise (block diagonal)."""
    m = len(local)
    H = np.zeros((6 * m, BLOCK * n))
    for k in range(m):
        H[6 * k : 6 * k + 6, BLOCK * int(local.observer[k]) + POSE] = Hi[k]
        H[6 * k : 6 * k + 6, BLOCK * int(local.target[k]) + POSE] = Hj[k]
    return H, _block_diag(local.R_Bi)


def factor_message(Ho: np.ndarray, Hp: np.ndarray, R: np.ndarray, P_cav: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The factor → variable message of linearised relative factors in information form
    (module docstring): ``(Λ, S)`` with ``S = R + Hp P_cav Hpᵀ`` the noise of the
    pseudo-measurement of the own state and ``Λ = Hoᵀ S⁻¹ Ho`` its information (12×12)."""
    S = R + Hp @ P_cav @ Hp.T
    return Ho.T @ np.linalg.solve(S, Ho), S


class GbpEstimator(ReplayingEstimator):
    kind = "gbp"
    radio = "graph"  # factors only with graph neighbours, messages only from them
    accepts_bearings = True  # angles-only bearings in I (module docstring)
    Params = GbpParams

    @classmethod
    def check_scenario(cls, sc: Any, params: Any) -> None:
        super().check_scenario(sc, params)
        if params.peers == "common" and params.fusion != "joint":
            raise IncompatibleScenario(f"estimator.peers: common is a noise model of fusion: joint's message stack; with fusion: "
                                       f"{params.fusion} use bound, sequential or independent (or auto: bound)")

    @classmethod
    def encode(cls, message: Any) -> bytes:
        if not isinstance(message, GbpMessage):
            raise TypeError(f"gbp: cannot encode {type(message).__name__}")
        return message.encode()

    @classmethod
    def decode(cls, data: bytes) -> Any:
        return GbpMessage.decode(data)

    def __init__(self, sc, own: int, params: GbpParams | None = None):
        super().__init__(sc, own, params)
        G = scenario_graph(sc)
        self.neighbours = sorted(int(j) for j in np.nonzero(G[own] | G[:, own])[0] if j != own)
        self.cav: dict[int, SwarmEstimate] = {}
        self.unusable = 0
        self._joint_params: dict[int, FilterParams] = {}
        # peer → its pose from this step's edge belief (q_BI, r_H, P_pose) and its message
        self._edges: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray, GbpMessage]] = {}
        self._edge_prior: dict[int, SwarmEstimate] = {}
        self.last_omega = 1.0
        self._jrow = {j: r + 1 for r, j in enumerate(self.neighbours)}
        # fusion: joint. A neighbour's row: its rate measured by the rate it broadcasts (its
        # bias-corrected gyro) with the gyro bias prior's σ_b; that rate's error is the
        # neighbour's bias error, held for a while, which white measurements cannot say: the
        # row's attitude random-walks at σ_b·√τ, τ = 15 s (measured: :data:`_RATE_HOLD_S`).
        s0 = sc.filter.initial_sigma
        self._jfp = dataclasses.replace(self.fp, n=1 + len(self.neighbours), own=0, max_iterations=1,
                                        att_rw_other=s0.bias_rad_s * math.sqrt(_RATE_HOLD_S))
        self._rate_sigma = s0.bias_rad_s
        self._hold_steps = max(1, math.ceil(sc.filter.history_s / sc.dt_s))
        # The radio's fixed latency in steps (a message waits for the first step at or after
        # its arrival): each cavity is sent predicted to the step it is used at, the held rate
        # with the same σ (late replay only: it is filed and used under its step).
        lk = sc.links
        self._lead = 0
        if self.params.fusion == "joint" and lk.enabled and sc.filter.late == "replay":  # type: ignore[attr-defined]
            lat = lk.latency.fixed_s + (1e-6 if lk.latency.speed_of_light else 0.0)
            self._lead = min(math.ceil(lat / sc.dt_s - 1e-9), max(self.history_steps - 1, 0))
        self._pfp = dataclasses.replace(self.fp, missing_gyro_rate_sigma=_LEAD_RATE_SIGMAS * s0.bias_rad_s)
        # peers: auto: common when each link measures a relative pose, bound with bearings (:func:`_peer_noise`).
        self._peers = self.params.peers  # type: ignore[attr-defined]
        if self._peers == "auto":
            joint_pose = self.params.fusion == "joint" and sc.sensors.relative.model != "bearing"  # type: ignore[attr-defined]
            self._peers = "common" if joint_pose else "bound"
        self._diffuse = (_DIFFUSE * np.array([s0.att_rad] * 3 + [s0.rate_rad_s] * 3 + [s0.pos_m] * 3 + [s0.vel_m_s] * 3)) ** 2
        self.pairs: _Pairs | None = None
        self._view_peers: list[int] = []

    # -- state -----------------------------------------------------------------------
    def start(self, prior: SwarmEstimate, step_pending: bool = True) -> None:
        super().start(prior, step_pending)
        self.cav = dict.fromkeys(self.neighbours, prior)
        self._kept.clear()
        self._edges = {}
        self._view_peers = []
        self.pairs = None
        if self.params.fusion == "joint":  # type: ignore[attr-defined]
            n = 1 + len(self.neighbours)
            rep_ = lambda a: np.repeat(a[:1], n, axis=0)  # noqa: E731
            P = np.zeros((BLOCK * n, BLOCK * n))
            P[:BLOCK, :BLOCK] = prior.P
            for r in range(1, n):
                P[BLOCK * r : BLOCK * (r + 1), BLOCK * r : BLOCK * (r + 1)] = np.diag(self._diffuse)
            w = rep_(prior.omega_BI_B)
            w[1:] = 0.0
            ref = SwarmEstimate(prior.step, prior.t, rep_(prior.q_BI), w, rep_(prior.r_H), rep_(prior.v_H), prior.bias_B.copy(), P)
            self.pairs = _Pairs(ref, np.zeros(BLOCK * n), P.copy(), frozenset(), {})

    def snapshot(self) -> dict[int, Any]:
        """The own belief (key -1), every cavity (key: its neighbour) and, with ``fusion:
        joint``, the pair potentials (key -2)."""
        out: dict[int, Any] = {-1: self.e, **self.cav}
        if self.pairs is not None:
            out[-2] = self.pairs
        return out

    def restore(self, b: dict[int, Any]) -> None:
        self.est = b[-1]
        self.cav = {j: v for j, v in b.items() if j >= 0}
        if -2 in b:
            self.pairs = b[-2]

    def propagate(self, gyro_rate_B) -> None:
        """The dynamics/gyro factor: the own belief by the filter's prediction
        (:func:`swarmcore.mekf.predict`); each cavity by the same factor linearised at the
        belief's mean, ``x_c⁺ = x_b⁺ ⊞ Φ (x_c ⊟ x_b)``, ``P_c⁺ = Φ P_c Φᵀ + Q`` (one Φ, Q a step
        instead of one per cavity)."""
        e = self.e
        omega_own = e.omega_BI_B[0] if gyro_rate_B is None else np.asarray(gyro_rate_B, float) - e.bias_B
        phi, Q, _ = state_jacobian_blocks(e, self.fp, omega_own)
        F, Qo = phi[0], Q[0].copy()
        if gyro_rate_B is None:
            Qo[0:3, 0:3] += (self.fp.missing_gyro_rate_sigma * self.fp.dt) ** 2 * np.eye(3)
        if self.pairs is None:
            super().propagate(gyro_rate_B)
        else:
            pr = self.pairs
            phi, Qj, _ = state_jacobian_blocks(pr.ref, self._jfp, omega_own)
            if gyro_rate_B is None:
                Qj[0, 0:3, 0:3] += (self.fp.missing_gyro_rate_sigma * self.fp.dt) ** 2 * np.eye(3)
            ref = predict(pr.ref, self._jfp, gyro_rate_B)
            n = ref.n
            d = (phi @ pr.d.reshape(n, BLOCK, 1)).reshape(-1)
            held = {}
            for j, (z, M, C, age) in pr.held.items():
                if age + 1 > self._hold_steps:
                    continue
                rj = self._jrow[j]
                M1 = M @ np.linalg.inv(phi[rj])
                held[j] = (z, M1, C + M1 @ Qj[rj] @ M1.T, age + 1)
            self.pairs = _Pairs(ref, d, propagate_blockdiag(pr.P, phi, Qj), pr.live, held)
            self.est = _row(ref, 0)
        m = self.e
        self.cav = {j: apply_correction(m, self.fp, F @ _delta(c, e), F @ c.P @ F.T + Qo) for j, c in self.cav.items()}

    # -- radio -----------------------------------------------------------------------
    def transmit(self, k: int) -> GbpMessage:
        e = self.e
        if e.step != k:
            raise ValueError(f"gbp estimator of satellite {self.own}: transmit({k}) with its estimate at step {e.step}")
        t = sorted(self.cav)
        p = len(t)
        q = np.zeros((p, 4), np.float32)
        r = np.zeros((p, 3), np.float32)
        sc = np.zeros(p, np.float32)
        ex = np.zeros((p, 6), np.int8)
        L = np.zeros((p, 21), np.float16)
        for a, j in enumerate(t):
            c = self.cav[j]
            for _ in range(self._lead):  # predicted to the step it arrives at (fusion: joint)
                c = predict(c, self._pfp, None)
            q[a], r[a] = c.q_BI[0], c.r_H[0]
            sc[a], ex[a], L[a] = pack_cholesky(pose_block(c.P))
        return GbpMessage(self.own, k, np.array(t, dtype=int), q, r, sc, ex, L, e.omega_BI_B[0].astype(np.float32),
                          e.v_H[0].astype(np.float32))

    # -- step ------------------------------------------------------------------------
    def step(self, inputs: StepInputs) -> StepReport:
        rep = StepReport()
        kept = self.step_inputs(inputs, rep)  # (its replay gathers the peers' batch from what it heard)
        acc, rej, nis, dof = self._update(kept, count=True, peers_batch=inputs.peer_measurements)
        rep.gate_accepted, rep.gate_rejected = acc, rej
        rep.nis, rep.nis_dof = (nis, dof) if dof else (float("nan"), 0)
        rep.extra["unusable"] = self.unusable
        rep.extra["omega"] = self.last_omega
        self._pending = False
        return rep

    def _update(self, kept: Kept, count: bool, peers_batch: RelativeMeasurements | None = None) -> tuple[int, int, float, int]:
        """The factors of one step on the own belief and every cavity: absolute (Kalman),
        then the relative factors' messages (module docstring). Returns accepted,
        rejected, NIS and its dof (of the own belief)."""
        if self.pairs is not None:
            return self._update_joint(kept, count, peers_batch)
        b = self.snapshot()
        nis, dof = 0.0, 0
        if kept.absolute is not None:
            for j, e in b.items():
                b[j], d2, dd = absolute_update(e, self.fp, kept.absolute)
                if j == -1:
                    nis, dof = d2, dd
        self._edges = {}
        self._edge_prior = dict(b)  # the cavities before this step's factors: the edges' own side
        me = self.own
        if peers_batch is None:
            peers_batch = RelativeMeasurements.concat([kept.heard[j].measurements for j in sorted(kept.heard)])
        cand = RelativeMeasurements.concat([kept.own, peers_batch.subset(peers_batch.target == me)])
        msgs: dict[int, GbpMessage] = {}
        if len(cand):
            other = np.where(cand.observer == me, cand.target, cand.observer)
            for j in np.unique(other).tolist():
                r = kept.heard.get(j)
                if r is not None and isinstance(r.payload, GbpMessage) and r.payload.row(me) is not None:
                    msgs[j] = r.payload
            ok = np.isin(other, np.fromiter(msgs, dtype=int, count=len(msgs)))
            if count:
                self.unusable += int((~ok).sum())
            cand = cand.subset(ok).canonical()
        acc = 0
        if len(cand):
            b, acc, d2 = self._fuse_all(b, cand, msgs)
            nis, dof = nis + d2, dof + self.fp.rel_dof * acc
        self.restore(b)
        return acc, len(cand) - acc, nis, dof

    def _update_joint(self, kept: Kept, count: bool, peers_batch: RelativeMeasurements | None) -> tuple[int, int, float, int]:
        """``fusion: joint`` (module docstring): the step's own and relative factors into the
        pair potentials (Kalman: independent noise), then the neighbours' messages of the
        step into a copy of them — the belief and each cavity — replacing the last step's."""
        pr = self.pairs
        assert pr is not None
        ref, d, P, live = pr.ref, pr.d, pr.P, set(pr.live)
        jp = self._jfp
        N = P.shape[0]
        nis, dof = 0.0, 0
        if kept.absolute is not None:
            res = absolute_residual(ref, jp, kept.absolute)
            if res is not None:
                y, Hp, Ra = res
                H = np.zeros((y.size, N))
                H[:, POSE] = Hp
                d, P = _kalman(d, P, H, y, Ra)
                Sb = H @ ref.P @ H.T + Ra
                nis, dof = float(y @ np.linalg.solve(Sb, y)), int(y.size)
        me = self.own
        if peers_batch is None:
            peers_batch = RelativeMeasurements.concat([kept.heard[j].measurements for j in sorted(kept.heard)])
        cand = RelativeMeasurements.concat([kept.own, peers_batch.subset(peers_batch.target == me)])
        msgs: dict[int, GbpMessage] = {}
        src = kept.heard
        if self._lead:
            old = self._kept.get(ref.step - self._lead)
            src = old.heard if old is not None else {}
        for j in self.neighbours:
            r = src.get(j)
            if r is not None and isinstance(r.payload, GbpMessage) and r.payload.row(me) is not None:
                msgs[j] = r.payload
        for j in sorted(msgs):
            if j not in live:  # a neighbour's row starts at its first message, wide
                ref, d, P = self._open_row(ref, d, P, j, msgs[j])
                live.add(j)
        if self._rate_sigma > 0:  # each neighbour's rate of this step (its message of this step)
            for j in self.neighbours:
                r = kept.heard.get(j)
                if j not in live or r is None or not isinstance(r.payload, GbpMessage):
                    continue
                rj = self._jrow[j]
                H = np.zeros((3, N))
                H[:, BLOCK * rj + 3 : BLOCK * rj + 6] = np.eye(3)
                d, P = _kalman(d, P, H, r.payload.omega_BI_B.astype(float) - ref.omega_BI_B[rj], self._rate_sigma**2 * np.eye(3))
        acc = rej = 0
        if len(cand):
            other = np.where(cand.observer == me, cand.target, cand.observer)
            ok = np.isin(other, np.fromiter(sorted(live), dtype=int, count=len(live)))
            if count:
                self.unusable += int((~ok).sum())
            cand = cand.subset(ok).canonical()
        if len(cand):
            row = {me: 0, **self._jrow}
            local = RelativeMeasurements(np.array([row[int(i)] for i in cand.observer]), np.array([row[int(j)] for j in cand.target]),
                                         cand.q_BjBi, cand.r_ij_Bi, cand.R_Bi)
            y, Hi, Hj, d2, accepted = gate(ref, jp, local)
            a = np.nonzero(accepted)[0]
            acc, rej = int(a.size), int(len(cand) - a.size)
            if a.size:
                H, R = joint_factors(local.subset(a), Hi[a], Hj[a], ref.n)
                d, P = _kalman(d, P, H, y[a].ravel(), R)
                nis, dof = nis + float(d2[a].sum()), dof + self.fp.rel_dof * int(a.size)
        # The neighbours' messages of the step (their cavities towards it), as measurements of
        # their poses, into a copy of the pair potentials: the belief, and each cavity without
        # its own neighbour's.
        held = dict(pr.held)
        E = np.zeros((6, BLOCK))
        E[:, POSE] = np.eye(6)
        for j in sorted(msgs):
            s = msgs[j]
            q, rr, Pm = s.pose(s.row(me))  # type: ignore[arg-type]
            rj = self._jrow[j]
            held[j] = (np.r_[quat.local(q, ref.q_BI[rj]), rr - ref.r_H[rj]], E, Pm, 0)
        present = [j for j in sorted(held) if j in live]
        mode = self._peers
        zs, Cs, Hs, Ts = [], [], [], []  # Ts: each message's common modes (peers: common)
        for j in present:
            z, M, C, _ = held[j]
            rj = self._jrow[j]
            zs.append(z)
            Cs.append(C)
            Hm = np.zeros((6, N))
            Hm[:, BLOCK * rj : BLOCK * (rj + 1)] = M
            Hs.append(Hm)
            Ts.append(_common_modes(ref.q_BI[rj]))

        def noise(sel: list[int]) -> np.ndarray:
            return _peer_noise([Cs[k] for k in sel], [Ts[k] for k in sel], mode, len(present))

        own0 = _row(ref, 0)
        cav = {}
        for j in self.neighbours:
            sel = [k for k, l in enumerate(present) if l != j]
            if sel:
                H = np.vstack([Hs[k] for k in sel])
                dc, Pc = _kalman(d, P, H, np.concatenate([zs[k] for k in sel]), noise(sel), rows=BLOCK)
            else:
                dc, Pc = d[:BLOCK], P[:BLOCK, :BLOCK]
            cav[j] = apply_correction(own0, self.fp, dc, Pc)
        if present:
            dB, PB = _kalman(d, P, np.vstack(Hs), np.concatenate(zs), noise(list(range(len(present)))))
        else:
            dB, PB = d, P
        new_ref = apply_correction(ref, jp, dB, PB)
        for j in present:  # the held messages re-centred on the new reference
            z, M, C, age = held[j]
            rj = self._jrow[j]
            held[j] = (z - M @ dB[BLOCK * rj : BLOCK * (rj + 1)], M, C, age)
        self.pairs = _Pairs(new_ref, d - dB, P, frozenset(live), held)
        self.est = _row(new_ref, 0)
        self.cav = cav
        self._view_peers = present
        self._edges = {}
        self.last_omega = 1.0
        return acc, rej, nis, dof

    def _open_row(self, ref: SwarmEstimate, d: np.ndarray, P: np.ndarray, j: int, s: GbpMessage):
        """A neighbour's row of the pair potentials at its first message: its pose, rate and
        velocity as the linearisation point, its covariance wide and uncorrelated."""
        rj = self._jrow[j]
        q, rr, _ = s.pose(s.row(self.own))  # type: ignore[arg-type]
        qs, ws, rs, vs = ref.q_BI.copy(), ref.omega_BI_B.copy(), ref.r_H.copy(), ref.v_H.copy()
        qs[rj], ws[rj], rs[rj], vs[rj] = q, s.omega_BI_B.astype(float), rr, s.v_H.astype(float)
        sl = slice(BLOCK * rj, BLOCK * (rj + 1))
        P = P.copy()
        P[sl, :] = 0.0
        P[:, sl] = 0.0
        P[sl, sl] = np.diag(self._diffuse)
        Pr = ref.P.copy()
        Pr[sl, :] = 0.0
        Pr[:, sl] = 0.0
        Pr[sl, sl] = np.diag(self._diffuse)
        d = d.copy()
        d[sl] = 0.0
        return SwarmEstimate(ref.step, ref.t, qs, ws, rs, vs, ref.bias_B, Pr), d, P

    def _linearise(self, e: SwarmEstimate, rel: RelativeMeasurements, msgs: dict[int, GbpMessage], peers: list[int]):
        """The relative factors linearised at belief ``e`` and the incoming cavities: joint
        residuals, the own and peers' Jacobian blocks, and the joint estimate."""
        me = self.own
        m = 1 + len(peers)
        row = {me: 0, **{j: r + 1 for r, j in enumerate(peers)}}
        P = np.zeros((BLOCK * m, BLOCK * m))
        P[:BLOCK, :BLOCK] = e.P
        qs, rs = [e.q_BI[0]], [e.r_H[0]]
        ws, vs = [e.omega_BI_B[0]], [e.v_H[0]]
        for r, j in enumerate(peers, start=1):
            s = msgs[j]
            q, rr, Pp = s.pose(s.row(me))  # type: ignore[arg-type]
            blk = np.diag(np.full(BLOCK, _UNUSED_VAR))
            blk[np.ix_(POSE, POSE)] = Pp
            P[BLOCK * r : BLOCK * (r + 1), BLOCK * r : BLOCK * (r + 1)] = blk
            qs.append(q)
            rs.append(rr)
            ws.append(s.omega_BI_B.astype(float))
            vs.append(s.v_H.astype(float))
        joint = SwarmEstimate(e.step, e.t, np.array(qs), np.array(ws), np.array(rs), np.array(vs), e.bias_B, P)
        if m not in self._joint_params:
            self._joint_params[m] = dataclasses.replace(self.fp, n=m, own=0, max_iterations=1)
        jp = self._joint_params[m]
        local = RelativeMeasurements(np.array([row[int(i)] for i in rel.observer]), np.array([row[int(j)] for j in rel.target]),
                                     rel.q_BjBi, rel.r_ij_Bi, rel.R_Bi)
        return joint, jp, local

    def _fuse_all(self, b: dict[int, SwarmEstimate], rel: RelativeMeasurements, msgs: dict[int, GbpMessage]):
        """Gate the step's relative measurements against the own belief, linearise their
        factors once (at the own belief and the incoming cavities' means), and fuse their
        messages into the own belief (all) and each cavity (all but its target's). A cavity
        differs from the belief by ``d = x_c ⊟ x_b``: its residual is the belief's less
        ``Ho d`` (the factor linearised at one point, as GBP does). The cavities take the
        belief's ω (per message with ``peers: sequential``): CI is consistent for any ω in
        (0, 1], the search only makes it tight.
        Also keeps, for the view, each edge's factor belief of the neighbour."""
        peers = sorted(msgs)
        main = b[-1]
        joint, jp, local = self._linearise(main, rel, msgs, peers)
        y, Hi, Hj, d2, accepted = gate(joint, jp, local)
        if not accepted.any():
            return b, 0, 0.0
        a = np.nonzero(accepted)[0]
        local = local.subset(a)
        yv = y[a].ravel()
        Ho, Hp, R = stack_factors(local, Hi[a], Hj[a], len(peers))
        Pp = [pose_block(joint.P[BLOCK * r : BLOCK * (r + 1), BLOCK * r : BLOCK * (r + 1)]) for r in range(1, 1 + len(peers))]
        mode = self._peers
        ci = self.params.fusion == "ci"  # type: ignore[attr-defined]
        C_p = (float(len(peers)) if mode == "bound" else 1.0) * (Hp @ _block_diag(Pp) @ Hp.T)
        other = np.repeat(np.asarray(peers)[np.where(local.observer == 0, local.target, local.observer) - 1], 6)
        out = dict(b)
        if ci and mode == "sequential":
            order = [j for j in peers if (other == j).any()]
            ws: dict[int, float] = {}
            for key, e in b.items():  # the own belief first (-1): it sets each message's ω
                for j in order:
                    if j == key:
                        continue
                    rows = other == j
                    Hr, Rr, Cr = Ho[rows], R[np.ix_(rows, rows)], C_p[np.ix_(rows, rows)]
                    if key == -1:
                        ws[j] = _ci_weight(e.P, Hr, Rr, Cr)
                    e = _ci_update(e, self.fp, Hr, yv[rows] - Hr @ _delta(e, main), Rr, Cr, ws[j])
                out[key] = e
            self.last_omega = min(ws.values(), default=1.0)
        else:
            w = _ci_weight(main.P, Ho, R, C_p) if ci else 1.0
            self.last_omega = w
            for key, e in b.items():
                keep = other != key
                if not keep.any():
                    continue
                yk = yv[keep] - Ho[keep] @ _delta(e, main)
                out[key] = _ci_update(e, self.fp, Ho[keep], yk, R[np.ix_(keep, keep)], C_p[np.ix_(keep, keep)], w)
        self._edge_beliefs(out, main, msgs, peers, other, Ho, Hp, R, yv, Pp)
        return out, int(accepted.sum()), float(d2[accepted].sum())

    def _edge_beliefs(self, b: dict[int, SwarmEstimate], main: SwarmEstimate, msgs: dict[int, GbpMessage], peers: list[int],
                      other: np.ndarray, Ho: np.ndarray, Hp: np.ndarray, R: np.ndarray, yv: np.ndarray, Pp: list[np.ndarray]) -> None:
        """The factor belief of each edge of the step, ``f_ij · m_{i→f} · m_{j→f}`` (for the
        view): the own cavity towards j (its prior of the step, taken from the kept
        beliefs) and j's cavity towards the own satellite, uncorrelated, updated by the
        pair's rows (Kalman, Joseph form) over both poses; the neighbour's part is kept."""
        self._edges = {}
        for r, j in enumerate(peers):
            rows = other == j
            if not rows.any():
                continue
            c = self._edge_prior.get(j, main)
            Hr = np.hstack([Ho[np.ix_(rows, POSE)], Hp[rows, 6 * r : 6 * r + 6]])
            yr = yv[rows] - Ho[rows] @ _delta(c, main)
            P0 = _block_diag([pose_block(c.P), Pp[r]])
            PHt = P0 @ Hr.T
            S = Hr @ PHt + R[np.ix_(rows, rows)]
            K = np.linalg.solve(S, PHt.T).T
            A = np.eye(12) - K @ Hr
            P1 = A @ P0 @ A.T + K @ R[np.ix_(rows, rows)] @ K.T
            dx = K @ yr
            s = msgs[j]
            q, rr, _ = s.pose(s.row(self.own))  # type: ignore[arg-type]
            self._edges[j] = (quat.retract(q, dx[6:9]), rr + dx[9:12], P1[6:, 6:], s)

    def view(self) -> EstimateView:
        """Its own belief, and each neighbour whose factor it used this step from that
        edge's factor belief (module docstring), claimed uncorrelated with its own."""
        if self.pairs is not None:
            ref = self.pairs.ref
            rows = ViewRows(self.own, self._view_peers, self.e)
            for j in self._view_peers:
                rj = self._jrow[j]
                sl = BLOCK * rj + POSE
                rows.set(j, ref.q_BI[rj], ref.omega_BI_B[rj], ref.r_H[rj], ref.v_H[rj], P_pose=ref.P[np.ix_(sl, sl)],
                         P_cross=ref.P[np.ix_(sl, POSE)])
            return rows.view(with_cross=True)
        peers = sorted(self._edges)
        rows = ViewRows(self.own, peers, self.e)
        for j in peers:
            q, r, P, s = self._edges[j]
            rows.set(j, q, s.omega_BI_B.astype(float), r, s.v_H.astype(float), P_pose=P)
        return rows.view(with_cross=False)


def _row(e: SwarmEstimate, r: int) -> SwarmEstimate:
    """Row r of a joint estimate as a one-satellite estimate (row 0: the own, with its bias)."""
    sl = slice(BLOCK * r, BLOCK * (r + 1))
    return SwarmEstimate(e.step, e.t, e.q_BI[r : r + 1].copy(), e.omega_BI_B[r : r + 1].copy(), e.r_H[r : r + 1].copy(),
                         e.v_H[r : r + 1].copy(), e.bias_B.copy(), e.P[sl, sl].copy())


def _kalman(d: np.ndarray, P: np.ndarray, H: np.ndarray, y: np.ndarray, R: np.ndarray, rows: int | None = None
            ) -> tuple[np.ndarray, np.ndarray]:
    """A linear Kalman update of the Gaussian (d, P) by ``y = H x + v``, ``v ~ N(0, R)``
    (Joseph form); ``rows``: only the first that many states' posterior."""
    PHt = P @ H.T if rows is None else P[:rows] @ H.T
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, PHt.T).T
    dn = (d if rows is None else d[:rows]) + K @ (y - H @ d)
    if rows is None:
        A = np.eye(P.shape[0]) - K @ H
        Pn = A @ P @ A.T + K @ R @ K.T
    else:
        Pn = P[:rows, :rows] - K @ S @ K.T
    return dn, 0.5 * (Pn + Pn.T)


def _common_modes(q_BI: np.ndarray) -> np.ndarray:
    """``B_k`` of ``peers: common`` (6 × 6): how an error common to every neighbour's message
    enters message k's pose coordinates ``[a (rad, B_k), Δr (m, H)]`` — the same attitude
    error in I (turned into k's body frame by its attitude ``q_BI``) and the same position
    error in H."""
    B = np.eye(6)
    B[:3, :3] = quat.attitude_matrix(q_BI)
    return B


def _peer_noise(Cs: list[np.ndarray], Bs: list[np.ndarray], mode: str, m_all: int) -> np.ndarray:
    """The noise of a stack of the neighbours' messages (``fusion: joint``).

    ``bound``: each message's covariance times the number of messages of the step ``m_all``
    (for any correlation). ``independent`` and ``sequential``: as they are. ``common``: each
    message's error taken as a part of its own (independent of the others') plus a part
    common to all of them, ``e_k = u_k + B_k θ`` (:func:`_common_modes`), ``θ`` of unknown
    covariance Γ, at most what every message claims (``B_k Γ B_kᵀ ⪯ C_k``). Then

        Cov = blockdiag(C_k − B_k Γ B_kᵀ) + B Γ Bᵀ ⪯ blockdiag(C_k) + (m − 1)/m · B G Bᵀ

    for any ``G ⪰ Γ`` (the off-diagonal blocks: Σ_{k≠l} v_kᵀ B_k Γ B_lᵀ v_l ≤ (m − 1)/m ·
    vᵀ B Γ Bᵀ v by Cauchy–Schwarz), and ``G = m (Σ_k B_kᵀ C_k⁻¹ B_k)⁻¹`` — covariance
    intersection of the constraints, equal weights — is such a G: its ellipsoid holds their
    intersection, which holds Γ's. So the differences between the messages keep their own
    covariances and what they share counts once, where ``bound`` pays m for both. It holds
    as long as what the messages share is of this form: the swarm's absolute attitude and
    position (the anchors' readings, reaching every neighbour), which is what they share
    when every link measures a whole relative pose; with bearings (angles only) the
    formation's shape along the lines of sight is itself estimated from shared data, with
    correlations of either sign, and ``auto`` takes ``bound`` (measured: docs/estimators.md).
    Hand-written: no library fuses measurements under this correlation model."""
    m = len(Cs)
    D = _block_diag(Cs)
    if mode == "bound":
        return float(m_all) * D
    if mode != "common" or m < 2:
        return D
    try:
        G = float(m) * np.linalg.inv(sum(B.T @ np.linalg.solve(C, B) for C, B in zip(Cs, Bs)))
    except np.linalg.LinAlgError:  # a singular message covariance: bound for any correlation instead
        return float(m) * D
    B = np.vstack(Bs)
    return D + (m - 1) / m * (B @ G @ B.T)


def _delta(e: SwarmEstimate, ref: SwarmEstimate) -> np.ndarray:
    """``e ⊟ ref`` of two one-satellite beliefs in the 12 error states ``[a, Δβ, Δr, Δv]``."""
    d = np.empty(BLOCK)
    d[0:3] = quat.local(e.q_BI[0], ref.q_BI[0])
    d[3:6] = e.bias_B - ref.bias_B
    d[6:9] = e.r_H[0] - ref.r_H[0]
    d[9:12] = e.v_H[0] - ref.v_H[0]
    return d


def _ci_weight(P: np.ndarray, Ho: np.ndarray, R: np.ndarray, C_p: np.ndarray) -> float:
    """The split-CI ω minimising ``det P⁺`` (compiled search, or its numpy twin)."""
    W, lam = _whitened(P, Ho, R, C_p, True)
    w = kernels.ci_det_weight(W, lam, True)
    return w if w is not None else ci_weight(_logdet_cost(W, lam, True))


def _ci_update(e: SwarmEstimate, fp: FilterParams, Ho: np.ndarray, y: np.ndarray, R: np.ndarray, C_p: np.ndarray,
               w: float) -> SwarmEstimate:
    """The split-CI update of the module docstring with weight ω (ω = 1: the plain GBP
    product, a Kalman update): prior ``P/ω``, noise ``R + C_p/(1 − ω)``, Joseph form, the
    multiplicative attitude reset."""
    Pw = e.P / w
    Cw = R + C_p / (1.0 - w) if w < 1.0 else R + C_p
    PHt = Pw @ Ho.T
    S = Ho @ PHt + Cw
    K = np.linalg.solve(S, PHt.T).T
    A = np.eye(BLOCK) - K @ Ho
    return apply_correction(e, fp, K @ y, A @ Pw @ A.T + K @ Cw @ K.T)
