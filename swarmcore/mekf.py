"""The cooperative Multiplicative EKF (dissertation chapter 4), one instance per satellite.

Each satellite ``own`` runs one filter over the WHOLE swarm (full order, 12 error states
per satellite, 12n in all), fed by its own gyro / star tracker / GPS and by every relative
pose measurement that any satellite broadcasts.

Error state of satellite ``b`` (block ``12b .. 12b+12``):

* own satellite (gyro "dynamic model replacement" mode): ``[a, Δβ, Δr, Δv]``; its rate is
  the bias-corrected gyro, not a state;
* every other satellite: ``[a, Δω, Δr, Δv]``.

``a`` is the attitude error in the body frame, ``q = δq(a) ⊗ q̂`` (see :mod:`quat`),
``Δβ = β − β̂``, ``Δω = ω − ω̂``, ``Δr = r − r̂`` (H frame, m), ``Δv = v − v̂`` (H, m/s).

Measurements (all residuals are "measured minus predicted", linearised at the prior):

* absolute (own satellite only): star tracker ``q̃_BI = δq(ν) ⊗ q_BI`` (residual
  ``local(q̃, q̂)``, H = I on ``a``) and GPS ``r̃_H = r_H + ν`` (H = I on ``Δr``).
* relative, observer ``i`` sees target ``j`` (both in the observer body frame B_i):
  ``q̃_BjBi = q_BjBi ⊗ δq(ν_Bi)`` with ``q_BjBi = q_j ⊗ q_i⁻¹``; residual
  ``err_from_dq(q̂_BjBi⁻¹ ⊗ q̃)`` with ``∂/∂a_i = −I``, ``∂/∂a_j = T(q̂_i) T(q̂_j)ᵀ``;
  ``r̃_ij_Bi = T(q_i) T_IH (r_j − r_i) + ν``, with ``∂/∂a_i = [r̂_ij_Bi ×]``,
  ``∂/∂r_i = −T(q̂_i) T_IH``, ``∂/∂r_j = T(q̂_i) T_IH``. Noise covariance ``R`` (6×6,
  ordered ``[attitude, position]``) is expressed in B_i.

Update forms (all equal in exact arithmetic, held equal to round-off by the tests):

* ``stacked`` — the dissertation's reference: one H for every measurement of the step, one
  block-diagonal R, ``K = P Hᵀ (H P Hᵀ + R)⁻¹``, Joseph form. O(m³); tests only.
* ``sequential`` — one 6-row Joseph update per measurement, all linearised at the prior
  (the running correction is carried in the residual), O(m N²).
* ``information`` — every measurement touches only the attitude and position errors
  (the "observed" 6n of the 12n states), so their information ``Λ = Σ Hᵀ R⁻¹ H`` is
  assembled block by block in that subspace and the whole step costs one pair of
  6n×6n Cholesky factorisations plus a few N×6n products, evaluated in Joseph form.
  Never inverts P itself (whose eigenvalues span ~20 decades).
* ``auto`` — sequential for a handful of measurements, information otherwise.

Gate: each relative measurement is tested against the prior, ``d² = νᵀ S⁻¹ ν`` with
``S = H P⁻ Hᵀ + R``, and rejected when ``d²`` exceeds the χ²(6) threshold.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import lru_cache, partial

import numpy as np
from scipy.linalg import blas

from . import kernels, quat
from .dynamics import T_IH, hcw_noise_cov, hcw_phi, rk4_attitude
from .linalg import chol, expm_batched

__all__ = [
    "FilterParams",
    "SwarmEstimate",
    "AbsoluteMeasurement",
    "RelativeMeasurements",
    "UpdateReport",
    "observed_indices",
    "stacked_problem",
    "init_estimate",
    "predict",
    "gate",
    "update",
    "relative_residuals",
    "absolute_residual",
    "absolute_residual_of",
    "absolute_rows",
    "Absolute",
    "linearize",
    "Linearized",
    "SOLVERS",
    "attitude_phi_q",
    "state_jacobian_blocks",
    "translation_step",
    "bearing_residuals_padded",
    "reframe",
    "apply_correction",
    "information_posterior",
    "propagate_blockdiag",
]

BLOCK = 12
A_SL = slice(0, 3)  # attitude error
W_SL = slice(3, 6)  # Δω (others) or Δβ (own)
R_SL = slice(6, 9)  # Δr
V_SL = slice(9, 12)  # Δv


@dataclass(frozen=True)
class FilterParams:
    """Numbers the filter needs; built from a scenario by the application layer.

    Noise densities: ``arw`` σ_v (rad/√s), ``rrw`` σ_u (rad/s/√s), ``torque`` σ_t
    (N·m/√s), ``accel`` σ_f (m/s^1.5); filter-only tuning random walks ``att_rw_other``
    (rad/√s, others' attitude) and ``pos_rw`` (m/√s, every position).
    """

    n: int
    own: int
    dt: float
    mean_motion: float
    J: np.ndarray
    arw: float
    rrw: float
    torque: float
    accel: float
    att_rw_other: float = 0.0
    pos_rw: float = 0.0
    gate_threshold: float | None = None
    update_method: str = "auto"
    rk4_substeps: int = 1
    max_iterations: int = 1
    iterate_above_rad: float = 0.01
    missing_gyro_rate_sigma: float = 1e-3  # rad/s: uncertainty of the held rate when a gyro sample is missing
    # The reference orbit (:class:`swarmcore.reference.Chief`): its Hill frame is H. None: the
    # uniformly turning HCW frame of ``mean_motion``.
    chief: object | None = None
    dynamics: str = "hcw"  # translation model: "hcw" (closed form) or "j2" (relmotion, exact STM)
    force: object | None = None  # orbit.ForceModel of the j2 model
    orbit_step_s: float = 10.0
    ballistic: np.ndarray | None = None  # (n_sats,) C_D A / m of the j2 model (None: no drag)
    chief_ballistic: float | None = None
    relative_kind: str = "pose"  # "pose" (6-dof relative pose) or "bearing" (unit line of sight, 2 dof)
    # Derived constants (filled in __post_init__).
    J_inv: np.ndarray = field(init=False, repr=False)
    phi_trans: np.ndarray = field(init=False, repr=False)
    q_trans: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not 0 <= self.own < self.n:
            raise ValueError(f"own satellite id {self.own} is not in 0..{self.n - 1}")
        if self.update_method not in ("auto", "information", "sequential", "stacked"):
            raise ValueError(f"unknown update method {self.update_method!r}")
        J = np.asarray(self.J, dtype=float)
        object.__setattr__(self, "J", J)
        object.__setattr__(self, "J_inv", np.linalg.inv(J))
        object.__setattr__(self, "phi_trans", hcw_phi(self.mean_motion, self.dt))
        object.__setattr__(self, "q_trans", hcw_noise_cov(self.mean_motion, self.dt, self.accel, self.pos_rw))
        if self.dynamics not in ("hcw", "j2"):
            raise ValueError(f"unknown translation model {self.dynamics!r}")
        if self.dynamics == "j2" and self.chief is None:
            raise ValueError("dynamics j2 needs the chief (swarmcore.reference.chief_of)")
        if self.relative_kind not in ("pose", "bearing"):
            raise ValueError(f"unknown relative measurement kind {self.relative_kind!r}")

    def T_IH(self, t: float) -> np.ndarray:
        """Hill → inertial at time ``t``: the chief's frame, or HCW's uniform turn."""
        return self.chief.T_IH(t) if self.chief is not None else T_IH(self.mean_motion, t)  # type: ignore[attr-defined]

    @property
    def rel_dof(self) -> int:
        """Degrees of freedom of one relative measurement (6: pose, 2: bearing)."""
        return 2 if self.relative_kind == "bearing" else 6

    def with_own(self, own: int) -> FilterParams:
        return replace(self, own=own)


@dataclass(frozen=True)
class SwarmEstimate:
    """One filter's estimate of the whole swarm at time ``t`` (after an update or predict).

    ``omega_BI_B[own]`` holds the bias-corrected gyro rate used in the last propagation.
    """

    step: int
    t: float
    q_BI: np.ndarray  # (n, 4)
    omega_BI_B: np.ndarray  # (n, 3) rad/s
    r_H: np.ndarray  # (n, 3) m
    v_H: np.ndarray  # (n, 3) m/s
    bias_B: np.ndarray  # (3,) own gyro bias, rad/s
    P: np.ndarray  # (12n, 12n)

    @property
    def n(self) -> int:
        return self.q_BI.shape[0]


@dataclass(frozen=True)
class AbsoluteMeasurement:
    """The own satellite's star tracker and GPS at one instant (either may be absent)."""

    q_BI: np.ndarray | None
    r_H: np.ndarray | None
    sigma_att_rad: float
    sigma_pos_m: float


@dataclass(frozen=True)
class RelativeMeasurements:
    """A batch of relative pose measurements (observer i sees target j), vectorised."""

    observer: np.ndarray  # (m,) int
    target: np.ndarray  # (m,) int
    q_BjBi: np.ndarray  # (m, 4)
    r_ij_Bi: np.ndarray  # (m, 3) m
    R_Bi: np.ndarray  # (m, 6, 6) [att rad, pos m] in B_i

    def __len__(self) -> int:
        return int(self.observer.shape[0])

    @classmethod
    def empty(cls) -> RelativeMeasurements:
        return cls(
            np.zeros(0, dtype=int),
            np.zeros(0, dtype=int),
            np.zeros((0, 4)),
            np.zeros((0, 3)),
            np.zeros((0, 6, 6)),
        )

    def subset(self, mask_or_idx) -> RelativeMeasurements:
        return RelativeMeasurements(
            self.observer[mask_or_idx],
            self.target[mask_or_idx],
            self.q_BjBi[mask_or_idx],
            self.r_ij_Bi[mask_or_idx],
            self.R_Bi[mask_or_idx],
        )

    def canonical(self) -> RelativeMeasurements:
        """Sorted by (observer, target): the order every filter applies them in."""
        order = np.lexsort((self.target, self.observer))
        return self.subset(order)

    @staticmethod
    def concat(batches) -> RelativeMeasurements:
        batches = [b for b in batches if len(b)]
        if not batches:
            return RelativeMeasurements.empty()
        return RelativeMeasurements(
            np.concatenate([b.observer for b in batches]),
            np.concatenate([b.target for b in batches]),
            np.concatenate([b.q_BjBi for b in batches]),
            np.concatenate([b.r_ij_Bi for b in batches]),
            np.concatenate([b.R_Bi for b in batches]),
        )


@dataclass(frozen=True)
class UpdateReport:
    """What an update did: gate statistics per relative measurement (input order)."""

    d2: np.ndarray  # (m,) squared Mahalanobis distance against the prior
    accepted: np.ndarray  # (m,) bool
    method: str
    nis: float = 0.0  # joint NIS of every measurement applied (absolute + accepted relative)
    nis_dof: int = 0
    iterations: int = 1

    @property
    def n_accepted(self) -> int:
        return int(np.count_nonzero(self.accepted))

    @property
    def n_rejected(self) -> int:
        return int(self.accepted.size - np.count_nonzero(self.accepted))


# --------------------------------------------------------------------------- helpers


@lru_cache(maxsize=64)
def observed_indices(n: int) -> np.ndarray:
    """Error-state indices of every attitude and position error, ordered [a_b, r_b] per b."""
    base = BLOCK * np.arange(n)[:, None]
    idx = (base + np.r_[0:3, 6:9][None, :]).ravel()
    idx.setflags(write=False)
    return idx


@lru_cache(maxsize=64)
def unobserved_indices(n: int) -> np.ndarray:
    """The other error states (rates or biases, velocities), ordered [Δω|Δβ_b, Δv_b] per b."""
    base = BLOCK * np.arange(n)[:, None]
    idx = (base + np.r_[3:6, 9:12][None, :]).ravel()
    idx.setflags(write=False)
    return idx


def init_estimate(
    step: int,
    t: float,
    q_BI: np.ndarray,
    omega_BI_B: np.ndarray,
    r_H: np.ndarray,
    v_H: np.ndarray,
    bias_B: np.ndarray,
    sigmas: dict,
    own: int,
) -> SwarmEstimate:
    """An estimate with a diagonal initial covariance.

    ``sigmas`` keys: ``att_rad``, ``rate_rad_s``, ``bias_rad_s``, ``pos_m``, ``vel_m_s``.
    """
    n = q_BI.shape[0]
    d = np.empty((n, BLOCK))
    d[:, A_SL] = sigmas["att_rad"] ** 2
    d[:, W_SL] = sigmas["rate_rad_s"] ** 2
    d[own, W_SL] = sigmas["bias_rad_s"] ** 2
    d[:, R_SL] = sigmas["pos_m"] ** 2
    d[:, V_SL] = sigmas["vel_m_s"] ** 2
    return SwarmEstimate(
        step=step,
        t=t,
        q_BI=quat.normalize(q_BI),
        omega_BI_B=np.array(omega_BI_B, dtype=float),
        r_H=np.array(r_H, dtype=float),
        v_H=np.array(v_H, dtype=float),
        bias_B=np.array(bias_B, dtype=float),
        P=np.diag(d.ravel()),
    )


# --------------------------------------------------------------------------- predict


def attitude_F(omega_hat: np.ndarray, J: np.ndarray, J_inv: np.ndarray, own_mask: np.ndarray) -> np.ndarray:
    """Continuous error dynamics of the attitude part ``[a, Δω|Δβ]`` per satellite (n, 6, 6).

    Others: ``ȧ = −[ω̂×] a + Δω``, ``Δω̇ = J⁻¹([Jω̂×] − [ω̂×]J) Δω``.
    Own (gyro mode): ``ȧ = −[ω̂×] a − Δβ``, ``Δβ̇ = 0``.
    """
    n = omega_hat.shape[0]
    F = np.zeros((n, 6, 6))
    F[:, 0:3, 0:3] = -quat.skew(omega_hat)
    F[:, 0:3, 3:6] = np.eye(3)
    F[:, 3:6, 3:6] = J_inv @ (quat.skew(omega_hat @ J.T) - quat.skew(omega_hat) @ J)
    F[own_mask, 0:3, 3:6] = -np.eye(3)
    F[own_mask, 3:6, 3:6] = 0.0
    return F


def attitude_phi_q(
    omega_hat: np.ndarray, params: FilterParams, own_mask: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Van Loan discretisation of every satellite's attitude block at once (n, 6, 6) ×2.

    ``expm([[−F, G Qc Gᵀ], [0, Fᵀ]] Δt) = [[…, Φ⁻¹Q], [0, Φᵀ]]`` — the same construction as
    ``filterpy.common.van_loan_discretization``, batched over satellites in one ``expm``.
    """
    n = omega_hat.shape[0]
    F = attitude_F(omega_hat, params.J, params.J_inv, own_mask)
    GQG = np.zeros((n, 6, 6))
    # Others: filter-only attitude random walk on a, torque noise through J⁻¹ on Δω.
    GQG[:, 0:3, 0:3] = params.att_rw_other**2 * np.eye(3)
    GQG[:, 3:6, 3:6] = params.torque**2 * (params.J_inv @ params.J_inv.T)
    # Own: gyro angle random walk on a (G = −I), rate random walk on Δβ (G = I).
    GQG[own_mask, 0:3, 0:3] = params.arw**2 * np.eye(3)
    GQG[own_mask, 3:6, 3:6] = params.rrw**2 * np.eye(3)
    A = np.zeros((n, 12, 12))
    A[:, :6, :6] = -F
    A[:, :6, 6:] = GQG
    A[:, 6:, 6:] = np.swapaxes(F, -1, -2)
    B = expm_batched(A * params.dt)
    phi = np.swapaxes(B[:, 6:, 6:], -1, -2)
    Q = phi @ B[:, :6, 6:]
    return phi, 0.5 * (Q + np.swapaxes(Q, -1, -2))


def translation_step(est: SwarmEstimate, params: FilterParams) -> tuple[np.ndarray, np.ndarray]:
    """Every satellite's ``[r_H, v_H]`` after ``dt`` (n, 6) and its transition (n, 6, 6) or (6, 6).

    ``hcw``: the closed form (one Φ for all). ``j2``: :func:`swarmcore.relmotion.propagate_relative`
    about the chief at step ``est.step`` (its state from :mod:`swarmcore.reference`), with each
    satellite's ballistic coefficient when the filter tracks the whole swarm (a filter of a
    subset — ci, pairwise, own — uses their mean: it does not know which ids it holds)."""
    if params.dynamics != "j2":
        return np.concatenate([est.r_H, est.v_H], axis=1) @ params.phi_trans.T, params.phi_trans
    from .relmotion import propagate_relative

    r_c, v_c = params.chief.state(est.step)  # type: ignore[attr-defined]
    bc: np.ndarray | float | None = params.ballistic
    if params.ballistic is not None and len(params.ballistic) != est.n:
        bc = float(np.mean(params.ballistic))
    st = propagate_relative(r_c, v_c, est.r_H, est.v_H, params.dt, params.force,  # type: ignore[arg-type]
                            step_s=params.orbit_step_s, ballistic_m2_kg=bc, chief_ballistic_m2_kg=params.chief_ballistic)
    return np.concatenate([st.r_H_m, st.v_H_m_s], axis=1), st.phi  # type: ignore[return-value]


def state_jacobian_blocks(est: SwarmEstimate, params: FilterParams, omega_own: np.ndarray,
                          phi_trans: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Φ and Q_k blocks (n, 12, 12) and the rates used (n, 3) for one propagation.
    ``phi_trans``: the translation's transition from :func:`translation_step`, when the caller has it."""
    n = est.n
    own_mask = np.zeros(n, dtype=bool)
    own_mask[params.own] = True
    omega_hat = est.omega_BI_B.copy()
    omega_hat[params.own] = omega_own
    phi_att, q_att = attitude_phi_q(omega_hat, params, own_mask)
    phi = np.zeros((n, BLOCK, BLOCK))
    Q = np.zeros((n, BLOCK, BLOCK))
    phi[:, 0:6, 0:6] = phi_att
    Q[:, 0:6, 0:6] = q_att
    if phi_trans is None:
        phi_trans = params.phi_trans if params.dynamics != "j2" else translation_step(est, params)[1]
    phi[:, 6:12, 6:12] = phi_trans
    Q[:, 6:12, 6:12] = params.q_trans
    return phi, Q, omega_hat


def propagate_blockdiag(P: np.ndarray, phi: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """``Φ P Φᵀ + Q`` for block-diagonal Φ and Q given as (n, 12, 12) blocks."""
    n = phi.shape[0]
    N = n * BLOCK
    left = (phi @ P.reshape(n, BLOCK, N)).reshape(N, N)  # Φ P
    # (Φ P) Φᵀ: act on column blocks.
    cols = left.reshape(N, n, BLOCK).transpose(1, 0, 2)  # (n, N, 12)
    right = (cols @ np.swapaxes(phi, -1, -2)).transpose(1, 0, 2).reshape(N, N)
    idx = np.arange(n)
    r4 = right.reshape(n, BLOCK, n, BLOCK)
    r4[idx, :, idx, :] += Q
    return 0.5 * (right + right.T)


def predict(est: SwarmEstimate, params: FilterParams, gyro_rate_B: np.ndarray | None) -> SwarmEstimate:
    """Propagate the whole-swarm estimate by one step ``dt``.

    ``gyro_rate_B``: the own gyro's mean rate over the step (rad/s, bias included); when
    absent (a missed sample), the last bias-corrected rate is held.
    """
    own = params.own
    dt = params.dt
    omega_own = est.omega_BI_B[own] if gyro_rate_B is None else np.asarray(gyro_rate_B, float) - est.bias_B
    rv, phi_trans = translation_step(est, params)
    phi, Q, _omega_hat = state_jacobian_blocks(est, params, omega_own, phi_trans)

    # States: others' attitude and rate by RK4 on Euler's equations (torque-free mean),
    # own attitude by the exact constant-rate step, translation by closed-form HCW (or the
    # J2 relative model, :func:`translation_step`).
    out = kernels.rk4_free(est.q_BI, est.omega_BI_B, params.J, params.J_inv, dt, params.rk4_substeps)
    q_new, w_new = rk4_attitude(est.q_BI, est.omega_BI_B, params.J, dt, params.rk4_substeps) if out is None else out
    q_own = kernels.propagate_constant_rate(est.q_BI[own], omega_own, dt)
    q_new[own] = quat.propagate_constant_rate(est.q_BI[own], omega_own, dt) if q_own is None else q_own
    w_new[own] = omega_own
    if gyro_rate_B is None:
        # No gyro sample: the held rate is uncertain, and so is the attitude it turns through.
        Q[own, 0:3, 0:3] += (params.missing_gyro_rate_sigma * dt) ** 2 * np.eye(3)
    P = propagate_blockdiag(est.P, phi, Q)
    return SwarmEstimate(
        step=est.step + 1,
        t=est.t + dt,
        q_BI=q_new,
        omega_BI_B=w_new,
        r_H=rv[:, 0:3],
        v_H=rv[:, 3:6],
        bias_B=est.bias_B.copy(),
        P=P,
    )


# --------------------------------------------------------------------------- residuals


def relative_residuals(est: SwarmEstimate, params: FilterParams, meas: RelativeMeasurements):
    """Residuals (m, 6) and Jacobian blocks w.r.t. [a_i, r_i] and [a_j, r_j], each (m, 6, 6).

    Column order of each block is ``[a (3), Δr (3)]`` of that satellite; the blocks for
    the Δω/Δβ and Δv columns are zero. Compiled (:func:`swarmcore.kernels.relative_residuals`)
    when numba is present; :func:`relative_residuals_numpy` is the same in numpy.
    """
    if params.relative_kind == "bearing":
        return bearing_residuals_padded(est, params, meas)
    out = kernels.relative_residuals(est.q_BI, est.r_H, params.T_IH(est.t), meas.observer, meas.target,
                                     meas.q_BjBi.reshape(-1, 4), meas.r_ij_Bi.reshape(-1, 3))
    return relative_residuals_numpy(est, params, meas) if out is None else out


def relative_residuals_numpy(est: SwarmEstimate, params: FilterParams, meas: RelativeMeasurements):
    """:func:`relative_residuals` in vectorised numpy (the compiled kernel's twin)."""
    i, j = meas.observer, meas.target
    T_all = quat.attitude_matrix(est.q_BI)  # (n,3,3) I→B per satellite, computed once
    T_i = T_all[i]
    T_j = T_all[j]
    C_all = T_all @ params.T_IH(est.t)  # H→B per satellite
    C = C_all[i]
    dr_H = est.r_H[j] - est.r_H[i]
    r_hat = (C @ dr_H[:, :, None])[:, :, 0]
    q_hat = quat.qmul(est.q_BI[j], quat.qconj(est.q_BI[i]))  # q_BjBi
    y_att = quat.err_from_dq(quat.qmul(quat.qconj(q_hat), meas.q_BjBi))
    y_pos = meas.r_ij_Bi - r_hat
    m = len(meas)
    Hi = np.zeros((m, 6, 6))
    Hj = np.zeros((m, 6, 6))
    Hi[:, 0:3, 0:3] = -np.eye(3)
    Hj[:, 0:3, 0:3] = T_i @ np.swapaxes(T_j, -1, -2)
    Hi[:, 3:6, 0:3] = quat.skew(r_hat)
    Hi[:, 3:6, 3:6] = -C
    Hj[:, 3:6, 3:6] = C
    return np.concatenate([y_att, y_pos], axis=1), Hi, Hj


def bearing_residuals_padded(est: SwarmEstimate, params: FilterParams, meas: RelativeMeasurements):
    """Angles-only measurements (``relative_kind: bearing``) in the 6-row layout of a pose.

    A bearing batch carries the measured unit line of sight ``ũ`` in the INERTIAL frame I in
    ``r_ij_Bi`` (the observer turned its camera's direction with its own attitude estimate,
    :func:`swarmcore.agent.inertial_bearings`; ``q_BjBi`` unused) and its 2×2 tangent-plane
    covariance in ``R_Bi[:2, :2]`` (identity below). The residual ``y = Eᵀ ũ`` and its
    Jacobians (:func:`swarmcore.bearing.bearing_residuals` with an identity attitude: on
    ``r_i`` and ``r_j`` only, no attitude) fill rows 0–1; rows 2–5 are zero residual
    with zero Jacobian and unit, uncorrelated noise, so they add no information, no gate
    distance and no NIS: every update form, the gate and the iterated update treat the
    bearing exactly as a 2-row measurement (the χ² threshold and NIS dof use 2)."""
    from .bearing import bearing_residuals

    i, j = meas.observer, meas.target
    m = len(meas)
    y = np.zeros((m, 6))
    Hi = np.zeros((m, 6, 6))
    Hj = np.zeros((m, 6, 6))
    if m == 0:
        return y, Hi, Hj
    ident = np.zeros((m, 4))
    ident[:, 3] = 1.0
    y2, _Ha, Hro, Hrt, _E = bearing_residuals(meas.r_ij_Bi, ident, params.T_IH(est.t), est.r_H[i], est.r_H[j])
    y[:, 0:2] = y2
    Hi[:, 0:2, 3:6] = Hro
    Hj[:, 0:2, 3:6] = Hrt
    return y, Hi, Hj


_H_ABS = np.eye(6)


def absolute_residual(est: SwarmEstimate, params: FilterParams, meas: AbsoluteMeasurement):
    """Residual, local Jacobian on the own [a, Δr] and (diagonal) R of the available parts."""
    return absolute_residual_of(est, params.own, meas)


def absolute_residual_of(est: SwarmEstimate, own: int, meas: AbsoluteMeasurement):
    """:func:`absolute_residual` of satellite ``own``'s reading (any satellite's: the
    centralized reference applies its peers' too)."""
    has_q, has_r = meas.q_BI is not None, meas.r_H is not None
    if not (has_q or has_r):
        return None
    y = np.empty(6)
    if has_q:
        y[:3] = quat.local(np.asarray(meas.q_BI, float), est.q_BI[own])
    if has_r:
        y[3:] = np.asarray(meas.r_H, float) - est.r_H[own]
    var = np.array([meas.sigma_att_rad**2] * 3 + [meas.sigma_pos_m**2] * 3)
    if has_q and has_r:
        return y, _H_ABS, np.diag(var)
    sl = slice(0, 3) if has_q else slice(3, 6)
    return y[sl], _H_ABS[sl], np.diag(var[sl])


# --------------------------------------------------------------------------- gate


def gate(est: SwarmEstimate, params: FilterParams, meas: RelativeMeasurements, P_OO: np.ndarray | None = None):
    """χ² validation gate against the prior. Returns (y, Hi, Hj, d2, accepted).

    ``d² = νᵀ S⁻¹ ν`` with ``S = H P⁻ Hᵀ + R`` for each measurement on its own (the
    stacked form's gate), computed by :func:`swarmcore.kernels.gate_d2`. ``P_OO``: the
    prior's observed block, when the caller already has it.
    """
    y, Hi, Hj = relative_residuals(est, params, meas)
    if len(meas) == 0:
        return y, Hi, Hj, np.zeros(0), np.zeros(0, dtype=bool)
    if P_OO is None:
        O = observed_indices(est.n)
        P_OO = est.P.take(O, 0).take(O, 1)
    d2 = kernels.gate_d2(P_OO, meas.observer, meas.target, y, Hi, Hj, meas.R_Bi)
    if params.gate_threshold is None:
        accepted = np.ones(len(meas), dtype=bool)
    else:
        accepted = d2 <= params.gate_threshold
    return y, Hi, Hj, d2, accepted


# --------------------------------------------------------------------------- update


@dataclass(frozen=True)
class Linearized:
    """Measurements of one step linearised at a point: what every solver consumes.

    Relative rows: ``y`` (m, 6), Jacobian blocks ``Hi``/``Hj`` (m, 6, 6) on the observer's and
    target's ``[a, Δr]``, noise ``R`` (m, 6, 6). Absolute rows of the own satellite:
    ``ya`` (k,), ``Ha`` (k, 6) on its ``[a, Δr]``, ``Ra`` (k, k); or None. ``peers_abs``:
    other satellites' absolute readings, ``(sat, y, H, R)`` each (the centralized reference,
    ``estimator: {kind: full, central: true}``; empty otherwise).
    """

    own: int
    observer: np.ndarray
    target: np.ndarray
    y: np.ndarray
    Hi: np.ndarray
    Hj: np.ndarray
    R: np.ndarray
    ya: np.ndarray | None = None
    Ha: np.ndarray | None = None
    Ra: np.ndarray | None = None
    peers_abs: tuple = ()

    @property
    def count(self) -> int:
        return int(self.observer.size) + (self.ya is not None) + len(self.peers_abs)

    def shifted(self, dx: np.ndarray, n: int) -> Linearized:
        """Residuals plus ``H δx_O`` (the iterated-EKF residual about the prior)."""
        dO = dx.reshape(n, BLOCK)[:, np.r_[0:3, 6:9]]  # (n, 6)
        y = self.y + (self.Hi @ dO[self.observer][:, :, None])[:, :, 0] + (self.Hj @ dO[self.target][:, :, None])[:, :, 0]
        ya = None if self.ya is None else self.ya + self.Ha @ dO[self.own]
        peers = tuple((i, yi + Hi @ dO[i], Hi, Ri) for i, yi, Hi, Ri in self.peers_abs)
        return replace(self, y=y, ya=ya, peers_abs=peers)


def linearize(est: SwarmEstimate, params: FilterParams, absolute: Absolute, relative: RelativeMeasurements) -> Linearized:
    """Residuals and Jacobians of the absolute reading(s) and the relative batch at ``est``."""
    y, Hi, Hj = relative_residuals(est, params, relative)
    ya, Ha, Ra, peers = absolute_rows(est, params, absolute)
    return Linearized(params.own, relative.observer, relative.target, y, Hi, Hj, relative.R_Bi, ya, Ha, Ra, peers)


#: What an update is given of absolute readings: the own satellite's (or None), or a mapping
#: ``{sat: reading}`` of every satellite's it applies (the centralized reference).
Absolute = AbsoluteMeasurement | Mapping[int, AbsoluteMeasurement] | None


def absolute_rows(est: SwarmEstimate, params: FilterParams, absolute: Absolute):
    """``(ya, Ha, Ra, peers_abs)`` of :class:`Linearized`: the own reading's rows and the
    other satellites' (``absolute`` a mapping ``{sat: reading}``), at ``est``."""
    peers: tuple = ()
    if isinstance(absolute, Mapping):
        readings = absolute
        absolute = readings.get(params.own)
        peers = tuple((i, *res) for i in sorted(readings) if i != params.own
                      and (res := absolute_residual_of(est, i, readings[i])) is not None)
    ya = Ha = Ra = None
    if absolute is not None:
        res = absolute_residual(est, params, absolute)
        if res is not None:
            ya, Ha, Ra = res
    return ya, Ha, Ra, peers


def apply_correction(est: SwarmEstimate, params: FilterParams, dx: np.ndarray, P: np.ndarray) -> SwarmEstimate:
    """Multiplicative attitude reset and additive corrections of every other state."""
    n = est.n
    d = dx.reshape(n, BLOCK)
    q = kernels.retract(est.q_BI, d[:, A_SL])
    if q is None:
        q = quat.retract(est.q_BI, d[:, A_SL])
    w = est.omega_BI_B + d[:, W_SL]
    own = params.own
    bias = est.bias_B + d[own, W_SL]
    w[own] = est.omega_BI_B[own] - d[own, W_SL]  # the corrected rate follows the bias
    return SwarmEstimate(
        step=est.step,
        t=est.t,
        q_BI=q,
        omega_BI_B=w,
        r_H=est.r_H + d[:, R_SL],
        v_H=est.v_H + d[:, V_SL],
        bias_B=bias,
        P=0.5 * (P + P.T),
    )


def _rows(lin: Linearized, n: int):
    """Measurements as (state indices, y, H, R) rows: absolute first, then relative."""
    O = observed_indices(n).reshape(n, 6)
    rows = []
    if lin.ya is not None:
        rows.append((O[lin.own], lin.ya, lin.Ha, lin.Ra))
    for i, yi, Hi, Ri in lin.peers_abs:
        rows.append((O[i], yi, Hi, Ri))
    for k in range(lin.observer.size):
        i, j = lin.observer[k], lin.target[k]
        rows.append((np.r_[O[i], O[j]], lin.y[k], np.concatenate([lin.Hi[k], lin.Hj[k]], axis=1), lin.R[k]))
    return rows


def stacked_problem(N: int, n: int, lin: Linearized) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(H, y, R)`` of every measurement of a step stacked (the dissertation's form):
    H (M, N), y (M,), block-diagonal R (M, M)."""
    rows = _rows(lin, n)
    sizes = [r[1].shape[0] for r in rows]
    tot = sum(sizes)
    H = np.zeros((tot, N))
    y = np.zeros(tot)
    R = np.zeros((tot, tot))
    r0 = 0
    for (idx, yk, Hk, Rk), k in zip(rows, sizes, strict=True):
        H[r0 : r0 + k, idx] = Hk
        y[r0 : r0 + k] = yk
        R[r0 : r0 + k, r0 : r0 + k] = Rk
        r0 += k
    return H, y, R


def _solve_stacked(P: np.ndarray, n: int, lin: Linearized):
    """Reference (dissertation): stack every measurement, one gain, Joseph form. O(m³)."""
    N = P.shape[0]
    if lin.count == 0:
        return np.zeros(N), P, 0.0
    H, y, R = stacked_problem(N, n, lin)
    S = H @ P @ H.T + R
    K = np.linalg.solve(S, H @ P).T
    A = np.eye(N) - K @ H
    nis = float(y @ np.linalg.solve(S, y))
    return K @ y, A @ P @ A.T + K @ R @ K.T, nis


def _solve_sequential(P: np.ndarray, n: int, lin: Linearized):
    """One Joseph update per measurement, all held at the same linearisation. O(m N²)."""
    N = P.shape[0]
    P = P.copy()
    dx = np.zeros(N)
    nis = 0.0
    for idx, yk, Hk, Rk in _rows(lin, n):
        PHt = P[:, idx] @ Hk.T  # (N, k)
        S = Hk @ PHt[idx] + Rk
        K = np.linalg.solve(S, PHt.T).T  # (N, k)
        innov = yk - Hk @ dx[idx]
        nis += float(innov @ np.linalg.solve(S, innov))  # sequential NIS terms sum to the joint NIS
        dx = dx + K @ innov
        # Joseph: (I − KH) P (I − KH)ᵀ + K R Kᵀ, with H sparse on idx.
        AP = P - K @ PHt.T
        P = AP - (AP[:, idx] @ Hk.T) @ K.T + K @ Rk @ K.T
    return dx, P, nis


def _solve_information(P: np.ndarray, n: int, lin: Linearized, blocks=None):
    """Square-root information form in the observed subspace O (attitude + position errors).

    Every measurement touches only the 6n attitude and position errors O, so with
    ``Λ = Σ H_Oᵀ R⁻¹ H_O`` and ``b = Σ H_Oᵀ R⁻¹ y`` (assembled block by block):

    1. ``P_OO = L Lᵀ`` and ``M = I + Lᵀ Λ L = U Uᵀ`` (eigenvalues ≥ 1, well conditioned);
    2. ``W = L U⁻ᵀ`` so that ``P⁺_OO = (P_OO⁻¹ + Λ)⁻¹ = W Wᵀ`` and ``δx_O = W Wᵀ b``;
    3. the other states U follow their regression on O, ``B = P_UO P_OO⁻¹``:
       ``δx_U = B δx_O``, ``P⁺_UO = B W Wᵀ`` and ``P⁺_UU = (P_UU − B P_OU) + (B W)(B W)ᵀ``, a
       Schur complement the update leaves alone plus a square-root term.

    Never inverts P, never forms ``P − P G P`` (whose cancellation loses every digit of the
    own attitude when the star tracker shrinks its variance a million-fold), and keeps P⁺
    positive semi-definite by construction — what the Joseph form buys the other two forms.

    Each step is one BLAS or LAPACK call on the matrix's own structure (triangular products
    and solves, symmetric rank-k updates that compute one triangle): about two thirds of
    the arithmetic of general products, and at n = 40 (6n = 240) these products are the
    agent's step. ``blocks``: :func:`swarmcore.kernels.split_observed` of ``P``, when the
    caller already has it (the gate reads the same ``P_OO``).
    """
    if lin.count == 0:
        return np.zeros(P.shape[0]), P, 0.0
    Lam, b, yRy = kernels.information(n, lin.observer, lin.target, lin.y, lin.Hi, lin.Hj, lin.R)
    if lin.ya is not None:
        assert lin.Ra is not None and lin.Ha is not None  # they come together
        w = 1.0 / np.diag(lin.Ra)  # the star tracker and GPS noise is diagonal
        oo = slice(6 * lin.own, 6 * lin.own + 6)
        Lam[oo, oo] += lin.Ha.T @ (lin.Ha * w[:, None])
        b[oo] += lin.Ha.T @ (w * lin.ya)
        yRy += float(np.sum(w * lin.ya * lin.ya))
    for i, yi, Hi, Ri in lin.peers_abs:
        w = 1.0 / np.diag(Ri)
        oo = slice(6 * i, 6 * i + 6)
        Lam[oo, oo] += Hi.T @ (Hi * w[:, None])
        b[oo] += Hi.T @ (w * yi)
        yRy += float(np.sum(w * yi * yi))
    return information_posterior(P, n, Lam, b, yRy, blocks)


def information_posterior(P: np.ndarray, n: int, Lam: np.ndarray, b: np.ndarray, yRy: float, blocks=None):
    """The second half of :func:`_solve_information`: given the information ``Λ`` (6n × 6n,
    in the observed subspace O, :func:`observed_indices`' order), ``b = Σ Hᵀ R⁻¹ y`` and
    ``yᵀ R⁻¹ y``, the correction, ``P⁺ = (P⁻¹ + Λ)⁻¹`` (on O, the rest by regression) and the
    joint NIS. Also the update step of the Cramér–Rao recursion (:mod:`swarmcore.crlb`, with
    ``b = 0``)."""
    P_OO, P_OU, P_UU = kernels.split_observed(P, n) if blocks is None else blocks
    # (Symmetric matrices in C order are their own transposes in Fortran order: .T hands
    # them to LAPACK and BLAS without a copy. Only lower triangles are read and written.)
    L = chol(P_OO.T)
    M = blas.dtrmm(1.0, L, blas.dtrmm(1.0, L, Lam.T, side=1, lower=1), lower=1, trans_a=1, overwrite_b=1)  # Lᵀ (Λ L)
    d = _diagonal(M.shape[0])
    M[d, d] += 1.0
    Uc = chol(M, overwrite=True)
    W = blas.dtrsm(1.0, Uc, L, side=1, lower=1, trans_a=1)  # L U⁻ᵀ: P⁺_OO = W Wᵀ
    # With B = P_UO P_OO⁻¹ = Xᵀ L⁻¹ and X = L⁻¹ P_OU: B P_OU = XᵀX and B W = (U⁻¹ X)ᵀ = Yᵀ.
    X = blas.dtrsm(1.0, L, P_OU, lower=1)
    Y = blas.dtrsm(1.0, Uc, X, lower=1)
    A_UU = P_UU - X.T @ X + Y.T @ Y
    A_OO = W @ W.T
    C_OU = W @ Y
    Wb = W.T @ b
    dx = np.empty(P.shape[0])
    O, U = _split_indices(n)
    dx[O] = W @ Wb
    dx[U] = Y.T @ Wb
    # Joint NIS yᵀ S⁻¹ y = yᵀ R⁻¹ y − bᵀ P⁺_OO b (matrix inversion lemma).
    return dx, kernels.join_observed(A_OO, C_OU, A_UU, n), yRy - float(Wb @ Wb)


@lru_cache(maxsize=64)
def _diagonal(size: int) -> np.ndarray:
    return np.arange(size)


@lru_cache(maxsize=64)
def _split_indices(n: int):
    return observed_indices(n), unobserved_indices(n)


SOLVERS = {"stacked": _solve_stacked, "sequential": _solve_sequential, "information": _solve_information}


def choose_method(method: str, n: int, m: int) -> str:
    """``auto``: sequential while its cost m·N² stays below the information form's ~N³/2."""
    if method != "auto":
        return method
    return "sequential" if (m + 1) * 8 <= BLOCK * n else "information"


def update(
    est: SwarmEstimate,
    params: FilterParams,
    absolute: Absolute,
    relative: RelativeMeasurements,
    method: str | None = None,
) -> tuple[SwarmEstimate, UpdateReport]:
    """Measurement update with the absolute reading and the (gated) relative batch of a step.

    ``absolute``: the own reading (or None), or ``{sat: reading}`` of every satellite whose
    reading this filter applies (:data:`Absolute`; the centralized reference).

    Relative measurements must already be in canonical order (see
    :meth:`RelativeMeasurements.canonical`); every form gives the same result to round-off.
    When ``params.max_iterations > 1`` and the first correction turns some attitude by
    more than ``params.iterate_above_rad``, the update is iterated (iterated EKF: re-linearise
    at the corrected state, same gated set, same prior), which keeps the first updates
    consistent when the initial attitude uncertainty is large.
    """
    n = est.n
    if len(relative):
        lo = min(relative.observer.min(), relative.target.min())
        hi = max(relative.observer.max(), relative.target.max())
        if lo < 0 or hi >= n or (relative.observer == relative.target).any():
            raise ValueError("relative measurement with an unknown or self satellite id")
    # The prior's observed/other blocks, taken once: the gate reads P_OO, the information
    # form all three (on every iteration).
    blocks = kernels.split_observed(est.P, n) if len(relative) else None
    y, Hi, Hj, d2, accepted = gate(est, params, relative, None if blocks is None else blocks[0])
    if accepted.all():  # the usual case: no copies
        kept = relative
    else:
        kept = relative.subset(accepted)
        y, Hi, Hj = y[accepted], Hi[accepted], Hj[accepted]
    ya, Ha, Ra, peers = absolute_rows(est, params, absolute)
    lin = Linearized(params.own, kept.observer, kept.target, y, Hi, Hj, kept.R_Bi, ya, Ha, Ra, peers)
    method = choose_method(method or params.update_method, n, lin.count)
    solve = SOLVERS[method]
    if method == "information" and blocks is not None:
        solve = partial(_solve_information, blocks=blocks)
    dx, P, nis = solve(est.P, n, lin)
    dof = (params.rel_dof * int(lin.observer.size) + (0 if lin.ya is None else int(lin.ya.size))
           + sum(int(p[1].size) for p in lin.peers_abs))
    iterations = 1
    for _ in range(params.max_iterations - 1):
        if np.max(np.abs(dx.reshape(n, BLOCK)[:, A_SL]), initial=0.0) <= params.iterate_above_rad:
            break
        point = apply_correction(est, params, dx, est.P)
        lin_i = linearize(point, params, absolute, kept).shifted(dx, n)
        dx_new, P, nis = solve(est.P, n, lin_i)  # the NIS at the last linearisation
        iterations += 1
        converged = np.max(np.abs(dx_new - dx)) < 1e-12
        dx = dx_new
        if converged:
            break
    report = UpdateReport(d2=d2, accepted=accepted, method=method, nis=nis, nis_dof=dof, iterations=iterations)
    return apply_correction(est, params, dx, P), report


def reframe(est: SwarmEstimate, old_own: int, new_own: int, sigma_bias_rad_s: float, sigma_rate_rad_s: float) -> SwarmEstimate:
    """Turn a peer's estimate (filter of ``old_own``) into a starting point for ``new_own``.

    A restarted agent has no filter of its own; it borrows a live peer's. The two rate
    sub-blocks change meaning: ``new_own`` switches to gyro mode (its bias is unknown: β̂ = 0
    with variance σ_bias², its rate will come from its gyro), ``old_own`` leaves gyro mode
    (its rate state starts at the peer's bias-corrected gyro rate with variance σ_rate²).
    Both sub-blocks lose their cross-covariances; everything else is kept as is.
    """
    if old_own == new_own:
        return est
    P = est.P.copy()
    w = est.omega_BI_B.copy()
    for b, var in ((new_own, sigma_bias_rad_s**2), (old_own, sigma_rate_rad_s**2)):
        idx = BLOCK * b + np.arange(3, 6)
        P[idx, :] = 0.0
        P[:, idx] = 0.0
        P[idx, idx] = var
    return SwarmEstimate(est.step, est.t, est.q_BI.copy(), w, est.r_H.copy(), est.v_H.copy(), np.zeros(3), P)
