"""The world's cameras (truth side): rendered images of what each observer's cameras see.

For the scheduled (observer, target) pairs, :class:`RenderedCameras` renders only the
cameras that have a scheduled target in view —

* ``pipeline: mono``: the observer's body-fixed face cameras (ids 0..5, faces
  ``+z, +x, +y, −x, −y, −z``) whose field of view reaches a scheduled target;
* ``pipeline: stereo``: one tracking stereo pair per scheduled target (camera id
  ``6 + target``), boresight along the line of sight (eq. 5.1), the observer's own body
  not drawn (the dissertation's virtual camera frame at the centre of mass).

Images are uint8 arrays, noisy per :mod:`swarmvision.noise` with draws from
``stream(seed, "camera", step, observer, camera)``. Scene frame: inertial (``r_I = T_IH r_H``).
What leaves this module is only what a camera delivers (:class:`swarmvision.views.View`).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import numpy as np

from swarmcore import quat
from swarmcore.cameras import BORESIGHT_B, T_CB
from swarmcore.dynamics import T_IH
from swarmcore.sensors import relative_pose
from swarmcore.streams import stream
from swarmcore.vision_config import VisionConfig

from .noise import apply_noise
from .views import STEREO_BASE, Observation, View, VisionSide, sun_direction_I

if TYPE_CHECKING:
    from .render import SceneRenderer

__all__ = ["RenderedCameras"]


class RenderedCameras(VisionSide):
    """World side of the vision chain: implements :class:`swarmcore.measurement.CameraModel`."""

    def __init__(self, cfg: VisionConfig, n_sats: int, half_size_m: float, seed: int, mean_motion: float):
        super().__init__(cfg, n_sats, half_size_m, seed, mean_motion)
        self._renderer: SceneRenderer | None = None  # made at the first render
        self.render_ms: list[float] = []

    def _bodies(self):
        from .models import cube_satellite, spacecraft_model

        if self.cfg.pipeline == "mono":
            m = self.cfg.mono
            return [cube_satellite(i, self.half, m.tag_size_m, self.cfg.render.texture_px_per_cell) for i in range(self.n)]
        parts = list(spacecraft_model(0))
        return [parts for _ in range(self.n)]

    @property
    def renderer(self) -> SceneRenderer:
        if self._renderer is None:
            from .render import SceneRenderer

            L = self.cfg.lighting
            r = self.cfg.render
            self._renderer = SceneRenderer(self._bodies(), ambient=L.ambient, sun_intensity=L.sun_intensity,
                                           shadows=L.shadows, znear=r.znear_m, zfar=r.zfar_m, platform=r.platform)
        return self._renderer

    def close(self) -> None:
        """Release the renderer's GL contexts (they are otherwise kept until exit)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    def observe(self, truth, observer, target, camera_ok=None, predicted=None) -> dict[int, Observation]:
        """Every scheduled observer's views (possibly none) and scheduled targets.

        ``predicted`` (stereo with ``vision.aim: predicted``, in-process only): each
        observer's predicted estimate, along whose line of sight it points its tracking
        camera (an agent's command to its gimbal)."""
        obs, tgt = np.asarray(observer, dtype=int), np.asarray(target, dtype=int)
        aim = None
        if self.cfg.pipeline == "stereo" and self.cfg.aim == "predicted" and predicted is not None:
            aim = {}
            for i in sorted(set(obs.tolist())):
                p = predicted[i]
                tg = np.array(sorted(set(tgt[obs == i].tolist())), dtype=int)
                _q, r = relative_pose(self.mean_motion, p.t, p.q_BI, p.r_H, np.full(tg.size, i), tg)
                for k, j in enumerate(tg):
                    aim[(i, int(j))] = r[k]
        views = self.render_views(truth.step, truth.t, truth.q_BI, truth.r_H, (obs, tgt), aim_B=aim, camera_ok=camera_ok)
        return {
            int(i): Observation([v for (o, _c), v in sorted(views.items()) if o == i], tgt[obs == i])
            for i in sorted(set(obs.tolist()))
        }

    def cameras_seeing(self, r_ij_Bi: np.ndarray) -> list[int]:
        """Face cameras whose frustum reaches a body of radius ``body_radius`` at ``r_ij_Bi``."""
        intr = self.cameras.face
        rad = self.cameras.body_radius
        out = []
        for c in range(6):
            p = T_CB[c] @ (r_ij_Bi - self.half * BORESIGHT_B[c])
            if p[2] <= -rad:
                continue
            # Half-angles of the frustum; the sphere is in view if its centre is within the
            # frustum widened by the sphere's angular radius.
            hx = np.arctan2(max(intr.cx, intr.width - 1 - intr.cx) + 0.5, intr.fx)
            hy = np.arctan2(max(intr.cy, intr.height - 1 - intr.cy) + 0.5, intr.fy)
            dist = float(np.linalg.norm(p))
            ang_r = np.arcsin(min(1.0, rad / max(dist, 1e-9)))
            ax = np.arctan2(abs(p[0]), p[2])
            ay = np.arctan2(abs(p[1]), p[2])
            if ax <= hx + ang_r and ay <= hy + ang_r:
                out.append(c)
        return out

    def render_views(self, step: int, t: float, q_BI: np.ndarray, r_H: np.ndarray, pairs,
                     aim_B: dict | None = None, camera_ok: np.ndarray | None = None) -> dict[tuple[int, int], View]:
        """Render every camera a scheduled pair needs; ``pairs``: (observer, target) arrays.

        ``aim_B`` (stereo, optional): (observer, target) → line of sight in B_i to point
        the tracking camera along (an agent's command); default: the true line of sight.
        ``camera_ok`` (n, 6) bool (mono, optional): failed face cameras deliver nothing.
        """
        obs, tgt = (np.asarray(a, dtype=int) for a in pairs)
        views: dict[tuple[int, int], View] = {}
        if obs.size == 0:
            return views
        q_BI = np.asarray(q_BI, float)
        C_IH = T_IH(self.mean_motion, t)
        r_I = np.asarray(r_H, float) @ C_IH.T
        rend = self.renderer
        rend.set_bodies(q_BI, r_I)
        rend.set_sun(sun_direction_I(self.cfg, self.mean_motion, t))
        _q_rel, r_rel = relative_pose(self.mean_motion, t, q_BI, np.asarray(r_H, float), obs, tgt)
        T_BI = quat.attitude_matrix(q_BI)
        noise = self.cfg.noise
        if self.cfg.pipeline == "mono":
            need: dict[int, set] = {}
            for k, i in enumerate(obs):
                need.setdefault(int(i), set()).update(self.cameras_seeing(r_rel[k]))
            for i in sorted(need):
                for c in sorted(need[i]):
                    if camera_ok is not None and not camera_ok[i, c]:
                        continue
                    T_CI = T_CB[c] @ T_BI[i]
                    r_C_B = self.half * BORESIGHT_B[c]
                    p_I = r_I[i] + T_BI[i].T @ r_C_B
                    t0 = time.perf_counter()
                    img = rend.render(T_CI, p_I, self.cameras.face)
                    img = apply_noise(img, noise, stream(self.seed, "camera", step, i, c))
                    ms = 1e3 * (time.perf_counter() - t0)
                    self.render_ms.append(ms)
                    views[(i, c)] = View(i, c, step, t, (img,), T_CB[c].copy(), r_C_B, self.cameras.face, render_ms=ms)
            return views
        # stereo: one tracking pair per scheduled target, own body hidden
        from .stereo import tracking_camera_T_CB

        b = self.cfg.stereo_camera.baseline_m
        for k, (i, j) in enumerate(zip(obs, tgt)):
            i, j = int(i), int(j)
            los = r_rel[k] if aim_B is None or (i, j) not in aim_B else np.asarray(aim_B[(i, j)], float)
            Tcb = tracking_camera_T_CB(los)
            T_CI = Tcb @ T_BI[i]
            vis = np.ones(self.n, dtype=bool)
            vis[i] = False
            rend.set_visible(vis)
            t0 = time.perf_counter()
            left = rend.render(T_CI, r_I[i], self.cameras.pair)
            right = rend.render(T_CI, r_I[i] + T_CI.T @ np.array([b, 0.0, 0.0]), self.cameras.pair)
            rng = stream(self.seed, "camera", step, i, STEREO_BASE + j)
            left = apply_noise(left, noise, rng)
            right = apply_noise(right, noise, rng)
            ms = 1e3 * (time.perf_counter() - t0)
            self.render_ms.append(ms / 2)
            views[(i, STEREO_BASE + j)] = View(i, STEREO_BASE + j, step, t, (left, right), Tcb, np.zeros(3),
                                               self.cameras.pair, target=j, baseline_m=b, render_ms=ms)
        rend.set_visible(np.ones(self.n, dtype=bool))
        return views
