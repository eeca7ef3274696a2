"""Spacecraft models: tagged cube satellites (monocular) and a procedural asymmetric
spacecraft with its reference point cloud (stereo).

A model is a list of :class:`Part` s: triangle geometry in the body frame B (metres) with
per-vertex normals and texture coordinates, a texture and a PBR material. The renderer
turns parts into pyrender primitives; the stereo pipeline samples the same geometry for
its reference cloud (Open3D Poisson-disk sampling), so what is rendered and what is
registered against are one definition.

Boxes are built here face by face (flat normals, own UVs) because pyrender needs each
textured face as its own primitive with explicit UVs (the trimesh material path is broken
on new trimesh, stack notes); the dish comes from ``trimesh.creation``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from swarmcore.cameras import BORESIGHT_B
from swarmcore.streams import stream

from .tags import T_TB, face_texture

__all__ = ["Part", "cube_satellite", "spacecraft_model", "model_radius", "reference_cloud", "parts_to_trimesh"]


@dataclass
class Part:
    name: str
    positions: np.ndarray  # (N, 3) m, body frame
    normals: np.ndarray  # (N, 3)
    uv: np.ndarray  # (N, 2), glTF/OpenGL sense: v = 0 at the BOTTOM row (pyrender flips rows on upload)
    indices: np.ndarray  # (M, 3) counter-clockwise seen from outside
    texture: np.ndarray | None = None  # (H, W) or (H, W, 3) uint8
    base_color: tuple = (1.0, 1.0, 1.0, 1.0)
    metallic: float = 0.0
    roughness: float = 0.9
    nearest: bool = False  # nearest-neighbour magnification (crisp tag cells)
    repeat: bool = False
    extras: dict = field(default_factory=dict)


def _quad(center, ax_u, ax_v, half_u, half_v, uv_scale=None):
    """A rectangle centred at ``center`` spanned by unit axes ``ax_u`` (texture right) and
    ``ax_v`` (texture up); its normal ``ax_u × ax_v`` faces the viewer. Returns
    positions, normals, uv, indices (two CCW triangles)."""
    c = np.asarray(center, float)
    u = np.asarray(ax_u, float)
    v = np.asarray(ax_v, float)
    n = np.cross(u, v)
    # Corners: top-left, top-right, bottom-right, bottom-left (as seen from outside).
    corners = np.array(
        [c - half_u * u + half_v * v, c + half_u * u + half_v * v, c + half_u * u - half_v * v, c - half_u * u - half_v * v]
    )
    # pyrender uploads textures bottom row first (np.flip in Texture), so v = 1 is the top.
    if uv_scale is None:
        uv = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])
    else:  # metres → texture repeats
        su, sv = 2 * half_u / uv_scale, 2 * half_v / uv_scale
        uv = np.array([[0.0, sv], [su, sv], [su, 0.0], [0.0, 0.0]])
    idx = np.array([[0, 3, 2], [0, 2, 1]])  # CCW seen from +n
    return corners, np.tile(n, (4, 1)), uv, idx


def _box_faces(center, half_extents, R_BP=None, uv_scale=0.5):
    """Six quads of a box (centre, half extents along its own axes, rotation part→body)."""
    c = np.asarray(center, float)
    h = np.asarray(half_extents, float)
    R = np.eye(3) if R_BP is None else np.asarray(R_BP, float)
    ex, ey, ez = R[:, 0], R[:, 1], R[:, 2]
    quads = [
        (c + h[2] * ez, ex, ey, h[0], h[1]),  # +z
        (c - h[2] * ez, -ex, ey, h[0], h[1]),  # -z
        (c + h[0] * ex, ey, ez, h[1], h[2]),  # +x
        (c - h[0] * ex, -ey, ez, h[1], h[2]),  # -x
        (c + h[1] * ey, -ex, ez, h[0], h[2]),  # +y
        (c - h[1] * ey, ex, ez, h[0], h[2]),  # -y
    ]
    P: list[np.ndarray] = []
    N: list[np.ndarray] = []
    UV: list[np.ndarray] = []
    I: list[np.ndarray] = []
    for q in quads:
        p, n, uv, idx = _quad(*q, uv_scale=uv_scale)
        I.append(idx + 4 * len(P))
        P.append(p)
        N.append(n)
        UV.append(uv)
    return np.concatenate(P), np.concatenate(N), np.concatenate(UV), np.concatenate(I)


def cube_satellite(sat: int, half_size_m: float = 0.2, tag_size_m: float = 0.32, px_per_cell: int = 24) -> list[Part]:
    """A cube satellite (side ``2 half_size_m``) with tag ``6 sat + face`` centred on each face.

    Face ``f``'s image is laid out in that face's tag frame (``x_T`` right, ``y_T`` up,
    :data:`swarmvision.tags.T_TB`), so the tag corners are where
    :func:`swarmvision.tags.tag_corners_B` says. Matte white paint, black tag ink.
    """
    parts = []
    for f in range(6):
        ax_u, ax_v = T_TB[f, 0], T_TB[f, 1]
        p, n, uv, idx = _quad(half_size_m * BORESIGHT_B[f], ax_u, ax_v, half_size_m, half_size_m)
        tex = face_texture(sat, f, tag_size_m, 2 * half_size_m, px_per_cell)
        parts.append(Part(f"sat{sat}_face{f}", p, n, uv, idx, tex, roughness=0.9, nearest=True))
    return parts


# ------------------------------------------------------------------ procedural spacecraft


def _mli_texture(rng, size=256):
    """Crinkled multi-layer-insulation foil: smooth random blotches plus fine wrinkles."""
    import cv2

    coarse = cv2.resize(rng.random((16, 16)).astype(np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
    fine = cv2.GaussianBlur(rng.random((size, size)).astype(np.float32), (0, 0), 1.2)
    g = 0.45 * coarse + 0.55 * (fine - fine.min()) / (np.ptp(fine) + 1e-9)
    g = np.clip(0.35 + 0.65 * g, 0, 1)
    rgb = np.stack([g, 0.85 * g, 0.45 * g], axis=-1)  # gold-tinted
    return (255 * rgb).astype(np.uint8)


def _solar_texture(rng, cells=(8, 4), px=32):
    """Solar cells: dark blue cells, individual brightness, bright bus bars and gaps."""
    H, W = cells[1] * px, cells[0] * px
    img = np.zeros((H, W, 3), np.float32)
    for i in range(cells[1]):
        for j in range(cells[0]):
            b = 0.6 + 0.4 * rng.random()
            img[i * px + 2 : (i + 1) * px - 2, j * px + 2 : (j + 1) * px - 2] = np.array([0.10, 0.14, 0.35]) * b * 2
            img[i * px + px // 2, j * px + 2 : (j + 1) * px - 2] = [0.7, 0.7, 0.7]
    img[img.sum(axis=-1) == 0] = [0.8, 0.8, 0.8]
    noise = rng.normal(0, 0.03, img.shape[:2])[..., None]
    return (255 * np.clip(img + noise, 0, 1)).astype(np.uint8)


def _plain_texture(rng, level=0.8, size=64, amp=0.15):
    g = np.clip(level + amp * (rng.random((size, size)) - 0.5), 0, 1)
    return (255 * np.repeat(g[..., None], 3, axis=-1)).astype(np.uint8)


def _rot(axis, ang):
    from swarmcore import quat

    return quat.attitude_matrix(quat.rotvec_to_quat(np.asarray(axis, float) * ang)).T  # active rotation


@lru_cache(maxsize=4)
def spacecraft_model(seed: int = 0) -> tuple[Part, ...]:
    """A procedural, deliberately asymmetric spacecraft (about 5 m tip to tip).

    Bus 1.0 × 0.8 × 1.2 m in gold MLI; a long solar wing (2.4 m) on +y and a short tilted one
    (1.6 m, 30°) on −y; a high-gain dish on +z, off-centre; a magnetometer boom along −x; an
    instrument box under −z. Body frame B = bus centre, bus axes. Stands in for the
    dissertation's MAVEN CAD model: complex, and without symmetries that would make the
    registration ambiguous.
    """
    import trimesh

    rng = stream(seed, "vision_model_texture")
    parts: list[Part] = []

    def box(name, center, half, tex, R=None, uv_scale=0.5, **mat):
        p, n, uv, idx = _box_faces(center, half, R, uv_scale)
        parts.append(Part(name, p, n, uv, idx, tex, repeat=True, **mat))

    box("bus", (0, 0, 0), (0.5, 0.4, 0.6), _mli_texture(rng), uv_scale=0.6, metallic=0.3, roughness=0.55)
    solar = _solar_texture(rng)
    # +y wing: yoke then a 2.4 m × 0.9 m panel, cells facing +z.
    box("yoke_py", (0, 0.55, 0.2), (0.03, 0.15, 0.03), _plain_texture(rng, 0.6), roughness=0.6)
    box("wing_py", (0, 1.9, 0.2), (0.45, 1.2, 0.015), solar, uv_scale=0.9, metallic=0.2, roughness=0.35)
    # −y wing: shorter, tilted 30° about y.
    Rt = _rot((0, 1, 0), np.radians(30))
    box("yoke_my", (0, -0.55, -0.1), (0.03, 0.15, 0.03), _plain_texture(rng, 0.6), roughness=0.6)
    box("wing_my", (0, -1.5, -0.1), (0.45, 0.8, 0.015), solar, R=Rt, uv_scale=0.9, metallic=0.2, roughness=0.35)
    # Magnetometer boom along −x with its sensor box.
    box("boom", (-1.1, 0.1, 0.3), (0.6, 0.02, 0.02), _plain_texture(rng, 0.5), roughness=0.5)
    box("magnetometer", (-1.75, 0.1, 0.3), (0.07, 0.07, 0.07), _plain_texture(rng, 0.3), roughness=0.7)
    # Instrument box under −z, off-centre.
    box("instrument", (-0.2, 0.15, -0.75), (0.18, 0.15, 0.15), _plain_texture(rng, 0.25, amp=0.3), roughness=0.8)
    # High-gain antenna: mast and a shallow dish (cone) opening towards +z, off-centre in x.
    box("mast", (0.2, -0.1, 0.7), (0.04, 0.04, 0.1), _plain_texture(rng, 0.7), roughness=0.6)
    dish = trimesh.creation.cone(radius=0.55, height=0.18, sections=40)
    dish.apply_transform(np.diag([1.0, 1.0, -1.0, 1.0]))  # apex down
    dish.invert() if dish.volume < 0 else None  # keep outward normals after the mirror
    dish.apply_translation((0.2, -0.1, 0.98))
    vn = np.asarray(dish.vertex_normals, float)
    parts.append(
        Part(
            "dish",
            np.asarray(dish.vertices, float),
            vn,
            np.zeros((len(dish.vertices), 2)),
            np.asarray(dish.faces, int),
            None,
            base_color=(0.92, 0.92, 0.9, 1.0),
            roughness=0.4,
            metallic=0.0,
        )
    )
    return tuple(parts)


def model_radius(parts) -> float:
    """Largest distance of any vertex from the body origin (m)."""
    return float(max(np.linalg.norm(p.positions, axis=1).max() for p in parts))


def parts_to_trimesh(parts):
    import trimesh

    meshes = [trimesh.Trimesh(p.positions, p.indices, process=False) for p in parts]
    return trimesh.util.concatenate(meshes)


@lru_cache(maxsize=4)
def reference_cloud(n_points: int = 7500, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """The stereo pipeline's a-priori model cloud: (points (N, 3), normals (N, 3)) in B.

    Poisson-disk sampling of the rendered geometry (Open3D, Yuksel's sample elimination),
    triangle normals, as in dissertation §5.4.2 (~7,500 points).
    """
    import open3d as o3d

    tm = parts_to_trimesh(spacecraft_model(seed))
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(tm.vertices), o3d.utility.Vector3iVector(tm.faces))
    mesh.compute_triangle_normals()
    o3d.utility.random.seed(int(seed) + 1)
    pcd = mesh.sample_points_poisson_disk(int(n_points), use_triangle_normal=True)
    return np.asarray(pcd.points).copy(), np.asarray(pcd.normals).copy()
