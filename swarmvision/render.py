"""Headless rendering with pyrender on the CPU (Mesa llvmpipe through EGL, OSMesa fallback).

One :class:`SceneRenderer` holds one pyrender scene (every satellite, the Sun, one camera
node) and one offscreen context per image size, reused across frames: only node poses
change between renders.

Frames and conventions (pinned by ``tests/test_vision_render.py``):

* Satellites are placed in the inertial frame I: node pose ``[T(q_BI)ᵀ, r_I]`` (B → I).
* Cameras are given as OpenCV frames C (+z boresight, +x image right, +y image down) by
  ``T_CI`` (I → C) and their centre ``p_I``. pyrender's camera is an OpenGL camera (looks
  down −z, +y up), so its node pose is ``[T_CIᵀ · diag(1, −1, −1), p_I]``.
* OpenCV puts pixel centres at integer coordinates, OpenGL at half-integers, so pyrender
  gets ``c + 0.5`` for an OpenCV principal point ``c``.
* The Sun is a directional light whose node z axis points at the Sun (light travels along
  −z of the node).

The platform has to be chosen before anything imports OpenGL; :func:`select_platform`
probes EGL in a throw-away subprocess (a failed EGL init cannot be undone in-process) and
falls back to OSMesa.
"""

from __future__ import annotations

import atexit
import contextlib
import os
import subprocess
import sys
from typing import Any

import numpy as np
import numpy.typing as npt

__all__ = ["select_platform", "SceneRenderer", "gl_camera_pose", "cv_to_gl_principal"]

_PROBE = (
    "import numpy as np\n"
    "np.infty = np.inf\n"
    "import pyrender\n"
    "r = pyrender.OffscreenRenderer(8, 8)\n"
    "s = pyrender.Scene()\n"
    "s.add(pyrender.IntrinsicsCamera(4.0, 4.0, 4.0, 4.0))\n"
    "r.render(s)\n"
    "r.delete()\n"
)


def select_platform(preference: str = "auto") -> str:
    """Set ``PYOPENGL_PLATFORM`` (if not set yet) and return it.

    ``auto``: EGL when a probe renders, else OSMesa. An explicit ``PYOPENGL_PLATFORM`` in
    the environment always wins (it is also how the choice reaches child processes).
    """
    cur = os.environ.get("PYOPENGL_PLATFORM")
    if cur:
        return cur
    if "OpenGL" in sys.modules:
        # Too late to choose; PyOpenGL already picked (GLX on a desktop, usually).
        return "preloaded"
    if preference in ("egl", "osmesa"):
        os.environ["PYOPENGL_PLATFORM"] = preference
        return preference
    for plat in ("egl", "osmesa"):
        env = dict(os.environ, PYOPENGL_PLATFORM=plat, LP_NUM_THREADS=os.environ.get("LP_NUM_THREADS", "1"))
        try:
            ok = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True, timeout=120).returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            ok = False
        if ok:
            os.environ["PYOPENGL_PLATFORM"] = plat
            return plat
    raise RuntimeError(
        "no headless OpenGL: neither EGL nor OSMesa could render. Install the Mesa packages in "
        "scripts/apt-packages.txt (libegl1 libegl-mesa0 libgl1-mesa-dri libosmesa6)."
    )


def _import_pyrender():
    # pyrender 0.1.45 still uses np.infty (removed in NumPy 2): restore the alias before
    # importing it (it is read at call time in Mesh.bounds, so the alias must stay).
    if not hasattr(np, "infty"):
        # NumPy 2's stubs no longer declare the alias: setting it is the point.
        np.infty = np.inf  # type: ignore[attr-defined]  # noqa: NPY201 - the very alias pyrender reads
    import pyrender

    return pyrender


GL_FROM_CV = np.diag([1.0, -1.0, -1.0])

# Every live OffscreenRenderer, held until closed explicitly. pyrender deletes a context
# in ``__del__``, which also un-binds whatever context is current: were a renderer left to
# the garbage collector, a collection during another renderer's frame would pull the
# context from under it (seen as GLError 1282 in glBindVertexArray). So contexts are only
# released by :meth:`SceneRenderer.close`, never by garbage collection.
_LIVE_CONTEXTS: list = []


def _release_all() -> None:
    """Delete every live context while the interpreter is still whole (at exit, PyOpenGL's
    lazy imports fail and pyrender's own ``__del__`` would print errors)."""
    while _LIVE_CONTEXTS:
        r = _LIVE_CONTEXTS.pop()
        with contextlib.suppress(Exception):  # best effort at exit
            r.delete()


atexit.register(_release_all)


def gl_camera_pose(T_CI: np.ndarray, p_I: np.ndarray) -> np.ndarray:
    """4×4 pyrender (OpenGL) camera node pose of an OpenCV camera ``T_CI`` at ``p_I``."""
    M = np.eye(4)
    M[:3, :3] = np.asarray(T_CI, float).T @ GL_FROM_CV
    M[:3, 3] = p_I
    return M


def cv_to_gl_principal(cx: float, cy: float) -> tuple[float, float]:
    return cx + 0.5, cy + 0.5


class SceneRenderer:
    """One scene of ``n`` bodies built from :class:`swarmvision.models.Part` lists.

    ``bodies[k]`` is the list of parts of body k. ``render`` returns an 8-bit grayscale
    image (a monochrome sensor, before the noise model) and optionally the z-depth (m).
    """

    def __init__(self, bodies, ambient: float = 0.0, sun_intensity: float = 4.0, shadows: bool = True,
                 znear: float = 0.05, zfar: float = 200.0, platform: str = "auto"):
        self._renderers: dict[tuple[int, int], Any] = {}  # pyrender.OffscreenRenderer (untyped)
        self.platform = select_platform(platform)
        pr = _import_pyrender()
        self._pr = pr
        self.scene = pr.Scene(ambient_light=np.full(3, float(ambient)), bg_color=np.zeros(4))
        self.znear, self.zfar = znear, zfar
        self.shadows = shadows
        self.nodes = []
        for parts in bodies:
            mesh = pr.Mesh([self._primitive(p) for p in parts])
            self.nodes.append(self.scene.add(mesh, pose=np.eye(4)))
        self.light = pr.DirectionalLight(color=np.ones(3), intensity=float(sun_intensity))
        self.light_node = self.scene.add(self.light, pose=np.eye(4))
        self.cam = pr.IntrinsicsCamera(1.0, 1.0, 0.5, 0.5, znear=znear, zfar=zfar)
        self.cam_node = self.scene.add(self.cam, pose=np.eye(4))
        self.frames = 0

    # -------------------------------------------------------------- scene building
    def _primitive(self, part):
        pr = self._pr
        from OpenGL.GL import GL_LINEAR, GL_LINEAR_MIPMAP_LINEAR, GL_NEAREST

        tex = None
        if part.texture is not None:
            img = part.texture
            if img.ndim == 2:
                img = np.repeat(img[..., None], 3, axis=-1)
            sampler = pr.Sampler(
                magFilter=GL_NEAREST if part.nearest else GL_LINEAR,
                minFilter=GL_LINEAR_MIPMAP_LINEAR,
                wrapS=10497 if part.repeat else 33071,  # GL_REPEAT / GL_CLAMP_TO_EDGE
                wrapT=10497 if part.repeat else 33071,
            )
            tex = pr.Texture(source=np.ascontiguousarray(img), source_channels="RGB", sampler=sampler)
        mat = pr.MetallicRoughnessMaterial(
            baseColorFactor=np.asarray(part.base_color, float),
            baseColorTexture=tex,
            metallicFactor=float(part.metallic),
            roughnessFactor=float(part.roughness),
        )
        return pr.Primitive(
            positions=np.asarray(part.positions, np.float32),
            normals=np.asarray(part.normals, np.float32),
            texcoord_0=np.asarray(part.uv, np.float32),
            indices=np.asarray(part.indices, np.uint32),
            material=mat,
        )

    # -------------------------------------------------------------- per-frame state
    def set_bodies(self, q_BI: np.ndarray, r_I: np.ndarray) -> None:
        """Body poses in I: ``q_BI`` (n, 4) and positions ``r_I`` (n, 3) m."""
        from swarmcore import quat

        T = quat.attitude_matrix(np.asarray(q_BI, float))
        for k, node in enumerate(self.nodes):
            M = np.eye(4)
            M[:3, :3] = T[k].T  # B → I
            M[:3, 3] = r_I[k]
            self.scene.set_pose(node, M)

    def set_sun(self, sun_I: npt.ArrayLike) -> None:
        """Sun direction (unit vector towards the Sun) in I."""
        z = np.asarray(sun_I, float)
        z = z / np.linalg.norm(z)
        a = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        x = np.cross(a, z)
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        M = np.eye(4)
        M[:3, :3] = np.stack([x, y, z], axis=1)
        self.scene.set_pose(self.light_node, M)

    def set_visible(self, visible) -> None:
        for node, v in zip(self.nodes, visible):
            node.mesh.is_visible = bool(v)

    def _renderer(self, w: int, h: int):
        key = (int(w), int(h))
        r = self._renderers.get(key)
        if r is None:
            r = self._pr.OffscreenRenderer(key[0], key[1])
            self._renderers[key] = r
            _LIVE_CONTEXTS.append(r)
        return r

    def render(self, T_CI: np.ndarray, p_I: np.ndarray, intr, depth: bool = False):
        """Render what OpenCV camera (``T_CI``, centre ``p_I``, ``swarmcore.cameras.Intrinsics``) sees."""
        pr = self._pr
        cam = self.cam
        cam.fx, cam.fy = float(intr.fx), float(intr.fy)
        cam.cx, cam.cy = cv_to_gl_principal(intr.cx, intr.cy)
        self.scene.set_pose(self.cam_node, gl_camera_pose(T_CI, p_I))
        flags = pr.RenderFlags.NONE
        if self.shadows:
            flags |= pr.RenderFlags.SHADOWS_DIRECTIONAL
        r = self._renderer(intr.width, intr.height)
        color, z = r.render(self.scene, flags=flags)
        self.frames += 1
        import cv2

        gray = cv2.cvtColor(color, cv2.COLOR_RGB2GRAY)
        return (gray, z) if depth else gray

    def close(self) -> None:
        """Release the GL contexts (explicitly; see ``_LIVE_CONTEXTS``)."""
        for r in self._renderers.values():
            with contextlib.suppress(Exception):  # context teardown is best effort
                r.delete()
            if r in _LIVE_CONTEXTS:
                _LIVE_CONTEXTS.remove(r)
        self._renderers.clear()
