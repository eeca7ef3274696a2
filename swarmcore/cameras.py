"""Body-fixed face cameras (OpenCV convention) and predicted visibility.

Each satellite carries six cameras, one per cube face, ordered ``+z, +x, +y, −x, −y, −z``
(dissertation Table 5.1). A camera frame C follows OpenCV: +z along the boresight, +x to
the image right, +y to the image bottom. ``T_CB[c]`` maps body coordinates to camera ``c``
coordinates; the camera sits at the face centre, ``half_size`` from the body centre.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import quat

FACE_NAMES = ("+z", "+x", "+y", "-x", "-y", "-z")

# Rows are the camera axes (x_C, y_C, z_C) written in body coordinates.
_AXES = {
    "+z": ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
    "+x": ((0, 1, 0), (0, 0, 1), (1, 0, 0)),
    "+y": ((0, 0, 1), (1, 0, 0), (0, 1, 0)),
    "-x": ((0, -1, 0), (0, 0, 1), (-1, 0, 0)),
    "-y": ((0, 0, -1), (1, 0, 0), (0, -1, 0)),
    "-z": ((-1, 0, 0), (0, 1, 0), (0, 0, -1)),
}

#: (6, 3, 3): body → camera attitude matrices, proper rotations (det = +1).
T_CB = np.array([np.array(_AXES[f], dtype=float) for f in FACE_NAMES])
#: (6, 3): unit boresights in the body frame.
BORESIGHT_B = T_CB[:, 2, :].copy()


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics of a square-pixel camera (pixels)."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float

    @classmethod
    def from_fov(cls, width: int, height: int, fov_deg: float) -> Intrinsics:
        """Horizontal field of view ``fov_deg`` across ``width`` pixels, centred principal point."""
        f = 0.5 * width / np.tan(np.radians(fov_deg) / 2.0)
        return cls(width, height, f, f, (width - 1) / 2.0, (height - 1) / 2.0)

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])


def cube_corners(half_size: float) -> np.ndarray:
    """(8, 3) corners of a cube of half-size ``half_size`` centred on the body origin."""
    s = half_size
    return np.array([[x, y, z] for x in (-s, s) for y in (-s, s) for z in (-s, s)], dtype=float)


def best_camera(r_ij_Bi: np.ndarray) -> np.ndarray:
    """Index of the face camera whose boresight is closest to the line of sight."""
    r = np.asarray(r_ij_Bi, dtype=float)
    return np.argmax(r @ BORESIGHT_B.T, axis=-1)


def visible_cameras(
    r_ij_Bi: np.ndarray,
    q_BjBi: np.ndarray,
    intr: Intrinsics,
    target_half_size: float,
    camera_offset: float,
    near: float = 0.05,
) -> np.ndarray:
    """Which cameras see the whole target: every corner in front of ``near`` and inside
    ``[0, W−1] × [0, H−1]`` pixels.

    ``r_ij_Bi``: target centre in the observer body frame (m), (3,) or (m, 3); ``q_BjBi``:
    rotation from B_i to B_j, (4,) or (m, 4). Returns a boolean (6,) or (m, 6) array.
    Batched because a selector for n = 50 checks 2450 pairs × 6 cameras every step.
    """
    single = np.ndim(r_ij_Bi) == 1
    r = np.atleast_2d(np.asarray(r_ij_Bi, dtype=float))
    T_BiBj = np.swapaxes(quat.attitude_matrix(np.atleast_2d(q_BjBi)), -1, -2)  # (m,3,3) B_j → B_i
    corners_Bi = r[:, None, :] + np.einsum("kb,mab->mka", cube_corners(target_half_size), T_BiBj)  # (m, 8, 3)
    out = np.zeros((r.shape[0], 6), dtype=bool)
    for c in range(6):
        p_C = (corners_Bi - camera_offset * BORESIGHT_B[c]) @ T_CB[c].T
        z = p_C[..., 2]
        front = np.all(z > near, axis=1)
        zs = np.where(z > near, z, 1.0)
        u = intr.fx * p_C[..., 0] / zs + intr.cx
        v = intr.fy * p_C[..., 1] / zs + intr.cy
        inside = np.all((u >= 0) & (u <= intr.width - 1) & (v >= 0) & (v <= intr.height - 1), axis=1)
        out[:, c] = front & inside
    return out[0] if single else out
