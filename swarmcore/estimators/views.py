"""Building an :class:`~swarmcore.estimators.base.EstimateView` from what an estimator
keeps: the whole swarm with its cross-covariance (``full``), or its own satellite and
peers it holds apart (the decentralized estimators)."""

from __future__ import annotations

import numpy as np

from .. import quat
from ..mekf import SwarmEstimate, observed_indices
from .base import EstimateView

__all__ = ["full_view", "relative_pose_cov", "pose_block", "POSE", "ViewRows"]

#: The pose rows [a, Δr] of a satellite's 12-state error block.
POSE = np.r_[0:3, 6:9]


def pose_block(P12: np.ndarray) -> np.ndarray:
    """(…, 6, 6) the [a, Δr] block of (…, 12, 12) covariances."""
    return P12[..., POSE[:, None], POSE[None, :]]


def relative_pose_cov(q_own: np.ndarray, q_peers: np.ndarray, P_own: np.ndarray, P_peers: np.ndarray,
                      P_cross: np.ndarray | None = None) -> np.ndarray:
    """(m, 6, 6) covariance of each peer's pose relative to the own satellite.

    Relative error ``e = [a_j − T(q̂_BjBi) a_i, Δr_j − Δr_i]`` (see
    :class:`~swarmcore.estimators.base.EstimateView`): ``e = e_j + A e_i`` with
    ``A = diag(−T(q̂_BjBi), −I)``, so ``P_rel = P_jj + A P_ii Aᵀ + P_ji Aᵀ + A P_ij``.
    ``P_own`` (6, 6) and ``P_peers`` (m, 6, 6) are pose blocks; ``P_cross`` (m, 6, 6) the
    blocks ``P_ji`` (peer rows, own columns), None when the estimator keeps none (treated
    as uncorrelated: what it claims)."""
    m = q_peers.shape[0]
    T_ji = quat.attitude_matrix(quat.qmul(q_peers, quat.qconj(np.broadcast_to(q_own, (m, 4)))))
    A = np.zeros((m, 6, 6))
    A[:, 0:3, 0:3] = -T_ji
    A[:, 3:6, 3:6] = -np.eye(3)
    At = np.swapaxes(A, -1, -2)
    out = P_peers + A @ P_own @ At
    if P_cross is not None:
        cross = P_cross @ At
        out = out + cross + np.swapaxes(cross, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


class ViewRows:
    """The rows of a view that an estimator holding its own satellite apart from its peers
    fills one satellite at a time (``ci``, ``pairwise``): ids sorted, its own row set from
    its posterior, unset covariance diagonals NaN."""

    def __init__(self, own: int, peers: list[int], own_est: SwarmEstimate) -> None:
        self.own_est = own_est
        self.ids = np.array(sorted([own, *peers]))
        self.row = {int(s): r for r, s in enumerate(self.ids)}
        m = self.ids.size
        self.q, self.w, self.r_H, self.v_H = (np.zeros((m, 4)), np.zeros((m, 3)), np.zeros((m, 3)), np.zeros((m, 3)))
        self.P_pose = np.zeros((m, 6, 6))
        self.cross = np.zeros((m, 6, 6))
        self.diag = np.full((m, 12), np.nan)
        self.own = own
        e = own_est
        self.set(own, e.q_BI[0], e.omega_BI_B[0], e.r_H[0], e.v_H[0], P12=e.P)

    def set(self, sat: int, q_BI: np.ndarray, omega_BI_B: np.ndarray, r_H: np.ndarray, v_H: np.ndarray, *,
            P12: np.ndarray | None = None, P_pose: np.ndarray | None = None, P_cross: np.ndarray | None = None) -> None:
        """Satellite ``sat``'s row: its full 12×12 covariance ``P12`` or only its pose block
        ``P_pose``; ``P_cross`` the pose block P_ji (its rows, own columns)."""
        r = self.row[sat]
        self.q[r], self.w[r], self.r_H[r], self.v_H[r] = q_BI, omega_BI_B, r_H, v_H
        if P12 is not None:
            self.P_pose[r], self.diag[r] = pose_block(P12), np.diag(P12)
        elif P_pose is not None:
            self.P_pose[r] = P_pose
            self.diag[r, POSE] = np.diag(P_pose)
        if P_cross is not None:
            self.cross[r] = P_cross

    def view(self, with_cross: bool) -> EstimateView:
        """The view, relative covariances computed (with the cross blocks set, or as uncorrelated)."""
        o = self.row[self.own]
        P_rel = relative_pose_cov(self.q[o], self.q, self.P_pose[o], self.P_pose, self.cross if with_cross else None)
        P_rel[o] = 0.0
        e = self.own_est
        return EstimateView(step=e.step, t=e.t, own=self.own, ids=self.ids, q_BI=self.q, omega_BI_B=self.w, r_H=self.r_H,
                            v_H=self.v_H, bias_B=e.bias_B, P_pose=self.P_pose, P_rel_pose=P_rel, P_diag=self.diag.ravel())


def full_view(est: SwarmEstimate, own: int) -> EstimateView:
    """The view of a whole-swarm estimate: every satellite, pose blocks and relative
    covariances from the full covariance (cross terms included)."""
    n = est.n
    O = observed_indices(n)
    P4 = est.P[np.ix_(O, O)].reshape(n, 6, n, 6)
    idx = np.arange(n)
    P_pose = P4[idx, :, idx, :]
    P_cross = P4[:, :, own, :]  # (n, 6, 6): rows of each satellite j, columns of own
    P_rel = relative_pose_cov(est.q_BI[own], est.q_BI, P_pose[own], P_pose, P_cross)
    P_rel[own] = 0.0
    return EstimateView(step=est.step, t=est.t, own=own, ids=idx, q_BI=est.q_BI, omega_BI_B=est.omega_BI_B, r_H=est.r_H,
                        v_H=est.v_H, bias_B=est.bias_B, P_pose=P_pose, P_rel_pose=P_rel, P_diag=np.diag(est.P).copy(),
                        full=est)


