"""Relative pose sensing: the measurement model ``h(x)`` and its noise model.

Both sides use these: the world (truth side) draws camera noise with them, an agent
(flight side) reports the covariance of what it measured, the selector predicts what a
measurement would bring. One home for the camera noise model:

* camera frame C (OpenCV: +z along the boresight), error vector ``[a_C, e_C]``;
* per camera axis σ at a reference range, growing as ``(range / ref) ** exponent``
  (:func:`camera_axis_variances`, dissertation chapter 6; the vision pipelines'
  ``covariance.source: fixed`` uses the same law with its own σ and a floor);
* rotated into the observer's body frame by :func:`camera_to_body`:
  ``R_Bi = diag(T_BC, T_BC) Σ_C diag(T_BC, T_BC)ᵀ``.
"""

from __future__ import annotations

import numpy as np

from . import quat
from .cameras import T_CB, best_camera
from .dynamics import T_IH

__all__ = ["relative_pose", "relative_pose_T", "camera_axis_variances", "camera_to_body", "relative_noise_cov"]


def relative_pose(mean_motion: float, t: float, q_BI, r_H, observer, target) -> tuple[np.ndarray, np.ndarray]:
    """``h(x)``: ``q_BjBi`` (m, 4) and ``r_ij_Bi`` (m, 3) of the given (observer, target) pairs.

    ``q_BjBi = q_Bj ⊗ q_Biᶜ`` (rotation from B_i to B_j); ``r_ij_Bi = T(q_Bi) T_IH(t) (r_j − r_i)``.
    Evaluated on the truth by the world, on an estimate by an agent or the selector.
    """
    return relative_pose_T(T_IH(mean_motion, t), q_BI, r_H, observer, target)


def relative_pose_T(T_IH_: np.ndarray, q_BI, r_H, observer, target) -> tuple[np.ndarray, np.ndarray]:
    """:func:`relative_pose` with the Hill → inertial matrix given (the chief's frame,
    :mod:`swarmcore.reference`)."""
    T_i = quat.attitude_matrix(q_BI[observer])
    C = T_i @ T_IH_
    r = np.einsum("mab,mb->ma", C, r_H[target] - r_H[observer])
    q = quat.qmul(q_BI[target], quat.qconj(q_BI[observer]))
    return quat.normalize(q), r


def camera_axis_variances(sigma_att_C, sigma_pos_C, range_m, reference_range_m: float, range_exponent: float) -> np.ndarray:
    """(…, 6) variances ``[att x y z, pos x y z]`` along the camera axes at ``range_m``:
    ``σ² · ((range / reference_range) ** range_exponent)²``."""
    scale = (np.asarray(range_m, dtype=float) / reference_range_m) ** range_exponent
    sig2 = np.r_[np.asarray(sigma_att_C, dtype=float) ** 2, np.asarray(sigma_pos_C, dtype=float) ** 2]
    return sig2 * (scale**2)[..., None]


def camera_to_body(cov_C: np.ndarray, T_CB_: np.ndarray) -> np.ndarray:
    """(…, 6, 6) camera-frame covariance of ``[a_C, e_C]`` → B_i (``T_CB_``: body → camera)."""
    G = np.zeros((*np.shape(T_CB_)[:-2], 6, 6))
    T_BC = np.swapaxes(T_CB_, -1, -2)
    G[..., :3, :3] = T_BC
    G[..., 3:, 3:] = T_BC
    out = G @ cov_C @ np.swapaxes(G, -1, -2)
    return 0.5 * (out + np.swapaxes(out, -1, -2))


def relative_noise_cov(rel, r_ij_Bi: np.ndarray) -> np.ndarray:
    """Noise covariance (m, 6, 6) in B_i, ``[attitude, position]``, of relative measurements.

    ``rel`` is the scenario's ``sensors.relative``. ``isotropic`` (chapter 4):
    ``diag(σ_q² I, σ_p² I)``. ``camera`` (chapter 6): :func:`camera_axis_variances` in the
    frame of the face camera that sees the target, rotated into B_i (face cameras are
    signed axis permutations of the body, so the rotation is exact).
    """
    r = np.atleast_2d(np.asarray(r_ij_Bi, dtype=float))
    m = r.shape[0]
    if rel.model == "isotropic":
        R = np.zeros((m, 6, 6))
        R[:, 0:3, 0:3] = rel.sigma_att_rad**2 * np.eye(3)
        R[:, 3:6, 3:6] = rel.sigma_pos_m**2 * np.eye(3)
        return R
    var = camera_axis_variances(
        rel.sigma_att_camera_rad, rel.sigma_pos_camera_m, np.linalg.norm(r, axis=1), rel.reference_range_m, rel.range_exponent
    )
    cov_C = np.zeros((m, 6, 6))
    cov_C[:, np.arange(6), np.arange(6)] = var
    return camera_to_body(cov_C, T_CB[best_camera(r)])
