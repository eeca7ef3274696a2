"""AprilTag 36h11 fiducials: one unique tag per face of each cube satellite.

``tag id = 6 * satellite + face`` with faces ordered like the cameras
(``+z, +x, +y, −x, −y, −z``, :data:`swarmcore.cameras.FACE_NAMES`). The 36h11 family has
587 codes, so up to 97 satellites carry unique tags.

Tag frame T (per face): origin at the face centre, ``z_T`` the outward face normal
(towards a viewer), ``x_T`` to the right and ``y_T`` *up* in the printed image. This is
the marker convention of ``cv2.aruco`` and ``SOLVEPNP_IPPE_SQUARE``: corners top-left,
top-right, bottom-right, bottom-left at ``(−s/2, s/2, 0)``, ``(s/2, s/2, 0)``,
``(s/2, −s/2, 0)``, ``(−s/2, −s/2, 0)``. Each face's tag frame has the attitude of that
face's camera frame, ``T_TB = cameras.T_CB[face]`` (right-handed, z outward).
"""

from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

from swarmcore.cameras import BORESIGHT_B, T_CB

__all__ = [
    "N_CODES",
    "DICTIONARY",
    "tag_id",
    "sat_face",
    "max_satellites",
    "tag_image",
    "face_texture",
    "T_TB",
    "tag_corners_T",
    "tag_corners_B",
    "dictionary",
]

DICTIONARY = cv2.aruco.DICT_APRILTAG_36h11
#: Tag layout: 6×6 data cells inside a one-cell black border → 8 cells across the black square.
CELLS_BLACK = 8


@lru_cache(maxsize=1)
def dictionary():
    return cv2.aruco.getPredefinedDictionary(DICTIONARY)


N_CODES = int(dictionary().bytesList.shape[0])

#: (6, 3, 3) body → tag-frame attitude of each face (the face camera's orientation).
T_TB = T_CB.copy()


def tag_id(sat: int | np.ndarray, face: int | np.ndarray):
    """Tag id of ``face`` (0..5) on satellite ``sat``."""
    return 6 * np.asarray(sat) + np.asarray(face)


def sat_face(tag: int | np.ndarray):
    """Inverse of :func:`tag_id`: ``(satellite, face)``."""
    tag = np.asarray(tag)
    return tag // 6, tag % 6


def max_satellites() -> int:
    return N_CODES // 6


def tag_image(tag: int, px_per_cell: int = 24, quiet_cells: float | None = None, face_cells: float = 10.0) -> np.ndarray:
    """Grayscale uint8 image of a whole face: the tag's black square centred in a white quiet zone.

    ``face_cells``: face width in tag cells (a 40 cm face with a 32 cm black square is 10
    cells, i.e. one white cell of quiet zone each side). Drawn by ``cv2.aruco``.
    """
    if not 0 <= tag < N_CODES:
        raise ValueError(f"tag id {tag} outside the 36h11 family (0..{N_CODES - 1})")
    if quiet_cells is not None:
        face_cells = CELLS_BLACK + 2 * quiet_cells
    side = round(face_cells * px_per_cell)
    black = CELLS_BLACK * px_per_cell
    marker = cv2.aruco.generateImageMarker(dictionary(), int(tag), black, borderBits=1)
    img = np.full((side, side), 255, dtype=np.uint8)
    o = (side - black) // 2
    img[o : o + black, o : o + black] = marker
    return img


def face_texture(sat: int, face: int, tag_size_m: float, face_size_m: float, px_per_cell: int = 24) -> np.ndarray:
    """The face image of ``(sat, face)`` for a face ``face_size_m`` wide with a ``tag_size_m`` tag."""
    return tag_image(int(tag_id(sat, face)), px_per_cell, face_cells=CELLS_BLACK * face_size_m / tag_size_m)


def tag_corners_T(tag_size_m: float) -> np.ndarray:
    """(4, 3) corners of the black square in the tag frame, OpenCV marker order
    (top-left, top-right, bottom-right, bottom-left); ``y_T`` points up the image."""
    s = tag_size_m / 2.0
    return np.array([[-s, s, 0.0], [s, s, 0.0], [s, -s, 0.0], [-s, -s, 0.0]])


def tag_corners_B(face: int, tag_size_m: float, half_size_m: float) -> np.ndarray:
    """(4, 3) corners of face ``face``'s tag in the body frame (same order as :func:`tag_corners_T`)."""
    return tag_corners_T(tag_size_m) @ T_TB[face] + half_size_m * BORESIGHT_B[face]
