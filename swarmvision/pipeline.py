"""``VisionSystem``: the world renders what cameras see, each agent turns its own images
into relative pose measurements. Pure of buses and files.

World side, :meth:`VisionSystem.render_views`: for the scheduled (observer, target) pairs,
renders only the cameras that have a scheduled target in view —

* ``pipeline: mono``: the observer's body-fixed face cameras (ids 0..5, faces
  ``+z, +x, +y, −x, −y, −z``) whose field of view reaches a scheduled target;
* ``pipeline: stereo``: one tracking stereo pair per scheduled target (camera id
  ``6 + target``), boresight along the line of sight (eq. 5.1), the observer's own body
  not drawn (the dissertation's virtual camera frame at the centre of mass).

Images are uint8 arrays, noisy per :mod:`swarmvision.noise` with draws from
``stream(seed, "camera", step, observer, camera)``. Scene frame: inertial (``r_I = T_IH r_H``).

Agent side, :meth:`VisionSystem.measure`: one observer's views (and its own predicted
estimate, used to resolve tag ambiguities and to seed ICP) →
:class:`swarmcore.mekf.RelativeMeasurements` in canonical order, covariance attached.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

import numpy as np

from swarmcore import quat
from swarmcore.cameras import BORESIGHT_B, T_CB, Intrinsics
from swarmcore.dynamics import T_IH
from swarmcore.mekf import RelativeMeasurements, SwarmEstimate
from swarmcore.streams import stream
from swarmcore.world import relative_truth

from .config import VisionConfig
from .covariance import CharacterizedNoise, camera_to_body, default_table_path, fixed_cov_C, load_table, sun_angle_deg
from .noise import apply_noise

__all__ = ["View", "VisionSystem", "STEREO_BASE", "encode_view", "decode_view", "face_intrinsics"]

STEREO_BASE = 6  # stereo camera id = STEREO_BASE + target


def face_intrinsics(cfg: VisionConfig) -> Intrinsics:
    c = cfg.mono_camera
    if c.focal_px is None:
        return Intrinsics.from_fov(c.width_px, c.height_px, c.fov_deg)
    return Intrinsics(c.width_px, c.height_px, c.focal_px, c.focal_px, (c.width_px - 1) / 2.0, (c.height_px - 1) / 2.0)


@dataclass
class View:
    """What one camera of one observer delivered at one step.

    ``images``: (gray,) for a face camera, (left, right) for the stereo pair; ``T_CB`` body →
    camera attitude; ``r_C_B`` the (left) camera centre in the body frame (m); ``target``:
    the tracked target of a stereo pair (−1 for face cameras).
    """

    observer: int
    camera: int
    step: int
    t: float
    images: tuple
    T_CB: np.ndarray
    r_C_B: np.ndarray
    intrinsics: Intrinsics
    target: int = -1
    baseline_m: float = 0.0
    render_ms: float = 0.0


def encode_view(v: View) -> bytes:
    """A view as bytes for a bus: a JSON header line, then the raw uint8 images."""
    hdr = {
        "observer": v.observer,
        "camera": v.camera,
        "step": v.step,
        "t": v.t,
        "T_CB": np.asarray(v.T_CB).tolist(),
        "r_C_B": np.asarray(v.r_C_B).tolist(),
        "intrinsics": [v.intrinsics.width, v.intrinsics.height, v.intrinsics.fx, v.intrinsics.fy, v.intrinsics.cx, v.intrinsics.cy],
        "target": v.target,
        "baseline_m": v.baseline_m,
        "shapes": [list(im.shape) for im in v.images],
    }
    return json.dumps(hdr).encode() + b"\n" + b"".join(np.ascontiguousarray(im, dtype=np.uint8).tobytes() for im in v.images)


def decode_view(data: bytes) -> View:
    head, _, body = data.partition(b"\n")
    h = json.loads(head)
    ims, off = [], 0
    for shp in h["shapes"]:
        n = int(np.prod(shp))
        ims.append(np.frombuffer(body, dtype=np.uint8, count=n, offset=off).reshape(shp).copy())
        off += n
    w, hh, fx, fy, cx, cy = h["intrinsics"]
    return View(h["observer"], h["camera"], h["step"], h["t"], tuple(ims), np.array(h["T_CB"]), np.array(h["r_C_B"]),
                Intrinsics(int(w), int(hh), fx, fy, cx, cy), h["target"], h["baseline_m"])


@dataclass
class MeasureReport:
    """Diagnostics of one observer's :meth:`VisionSystem.measure` call."""

    decoded: list = field(default_factory=list)  # targets measured
    missed: list = field(default_factory=list)  # targets expected but not measured
    ms: float = 0.0
    details: dict = field(default_factory=dict)


class VisionSystem:
    """Rendering (world side) and pose pipelines (agent side) of one scenario."""

    def __init__(self, cfg: VisionConfig, n_sats: int, half_size_m: float, seed: int, mean_motion: float):
        if cfg.pipeline == "none":
            raise ValueError("VisionSystem needs vision.pipeline 'mono' or 'stereo'")
        from . import tags

        if cfg.pipeline == "mono" and n_sats > tags.max_satellites():
            raise ValueError(f"n_sats={n_sats}: the 36h11 family tags at most {tags.max_satellites()} satellites")
        if cfg.pipeline == "mono" and cfg.mono.tag_size_m >= 2 * half_size_m:
            raise ValueError("vision.mono.tag_size_m: must be smaller than the cube face (2 · half_size_m)")
        self.cfg = cfg
        self.n = n_sats
        self.half = half_size_m
        self.seed = seed
        self.mean_motion = mean_motion
        self.face_intr = face_intrinsics(cfg)
        sc = cfg.stereo_camera
        from .stereo import stereo_intrinsics

        self.stereo_intr = stereo_intrinsics(sc.width_px, sc.height_px, sc.focal_px)
        self._renderer = None
        self._mono = None
        self._stereo = None
        self._char = None
        self.last_reports: dict[int, MeasureReport] = {}
        self.timing = {"render_ms": [], "mono_ms": [], "stereo_ms": []}
        if cfg.covariance.source == "characterized":
            self._cov_C(5.0, None, None)  # load the table now: a missing or mismatched one fails early

    # ------------------------------------------------------------------ models
    @property
    def body_radius(self) -> float:
        if self.cfg.pipeline == "mono":
            return float(self.half * np.sqrt(3.0))
        from .models import model_radius, spacecraft_model

        return model_radius(spacecraft_model(0))

    def _bodies(self):
        from .models import cube_satellite, spacecraft_model

        if self.cfg.pipeline == "mono":
            m = self.cfg.mono
            return [cube_satellite(i, self.half, m.tag_size_m, self.cfg.render.texture_px_per_cell) for i in range(self.n)]
        parts = list(spacecraft_model(0))
        return [parts for _ in range(self.n)]

    @property
    def renderer(self):
        if self._renderer is None:
            from .render import SceneRenderer

            L = self.cfg.lighting
            r = self.cfg.render
            self._renderer = SceneRenderer(self._bodies(), ambient=L.ambient, sun_intensity=L.sun_intensity,
                                           shadows=L.shadows, znear=r.znear_m, zfar=r.zfar_m, platform=r.platform)
        return self._renderer

    @property
    def mono(self):
        if self._mono is None:
            from .mono import MonoPipeline

            self._mono = MonoPipeline(self.cfg.mono, self.face_intr, self.half, self.n)
        return self._mono

    @property
    def stereo(self):
        if self._stereo is None:
            from .models import reference_cloud
            from .stereo import StereoPipeline

            pts, nrm = reference_cloud(self.cfg.stereo.model_points)
            self._stereo = StereoPipeline(self.cfg.stereo, self.stereo_intr, self.cfg.stereo_camera.baseline_m, pts, nrm,
                                          self.body_radius)
        return self._stereo

    def sun_I(self, t: float) -> np.ndarray:
        s = np.asarray(self.cfg.lighting.sun_direction, float)
        s = s / np.linalg.norm(s)
        return T_IH(self.mean_motion, t) @ s if self.cfg.lighting.sun_frame == "H" else s

    # ------------------------------------------------------------------ world side
    def cameras_seeing(self, r_ij_Bi: np.ndarray) -> list[int]:
        """Face cameras whose frustum reaches a body of radius ``body_radius`` at ``r_ij_Bi``."""
        intr = self.face_intr
        rad = self.body_radius
        out = []
        for c in range(6):
            p = T_CB[c] @ (r_ij_Bi - self.half * BORESIGHT_B[c])
            if p[2] <= -rad:
                continue
            # Half-angles of the frustum; the sphere is in view if its centre is within the
            # frustum widened by the sphere's angular radius.
            hx = np.arctan2(max(intr.cx, intr.width - 1 - intr.cx) + 0.5, intr.fx)
            hy = np.arctan2(max(intr.cy, intr.height - 1 - intr.cy) + 0.5, intr.fy)
            dist = np.linalg.norm(p)
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
        rend.set_sun(self.sun_I(t))
        _q_rel, r_rel = relative_truth(self.mean_motion, t, q_BI, np.asarray(r_H, float), obs, tgt)
        T_BI = quat.attitude_matrix(q_BI)
        noise = self.cfg.noise
        if self.cfg.pipeline == "mono":
            need: dict[int, set] = {}
            for k, (i, j) in enumerate(zip(obs, tgt)):
                need.setdefault(int(i), set()).update(self.cameras_seeing(r_rel[k]))
            for i in sorted(need):
                for c in sorted(need[i]):
                    if camera_ok is not None and not camera_ok[i, c]:
                        continue
                    T_CI = T_CB[c] @ T_BI[i]
                    r_C_B = self.half * BORESIGHT_B[c]
                    p_I = r_I[i] + T_BI[i].T @ r_C_B
                    t0 = time.perf_counter()
                    img = rend.render(T_CI, p_I, self.face_intr)
                    img = apply_noise(img, noise, stream(self.seed, "camera", step, i, c))
                    ms = 1e3 * (time.perf_counter() - t0)
                    self.timing["render_ms"].append(ms)
                    views[(i, c)] = View(i, c, step, t, (img,), T_CB[c].copy(), r_C_B, self.face_intr, render_ms=ms)
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
            left = rend.render(T_CI, r_I[i], self.stereo_intr)
            right = rend.render(T_CI, r_I[i] + T_CI.T @ np.array([b, 0.0, 0.0]), self.stereo_intr)
            rng = stream(self.seed, "camera", step, i, STEREO_BASE + j)
            left = apply_noise(left, noise, rng)
            right = apply_noise(right, noise, rng)
            ms = 1e3 * (time.perf_counter() - t0)
            self.timing["render_ms"].append(ms / 2)
            views[(i, STEREO_BASE + j)] = View(i, STEREO_BASE + j, step, t, (left, right), Tcb, np.zeros(3),
                                               self.stereo_intr, target=j, baseline_m=b, render_ms=ms)
        rend.set_visible(np.ones(self.n, dtype=bool))
        return views

    # ------------------------------------------------------------------ agent side
    def _predicted_rel(self, observer: int, predicted: SwarmEstimate | None, targets):
        """Predicted (q_BjBi, r_ij_Bi) per target from the observer's own estimate."""
        if predicted is None:
            return {}
        tg = np.array(sorted(targets), dtype=int)
        if tg.size == 0:
            return {}
        q, r = relative_truth(self.mean_motion, predicted.t, predicted.q_BI, predicted.r_H, np.full(tg.size, observer), tg)
        return {int(j): (q[k], r[k]) for k, j in enumerate(tg)}

    def _cov_C(self, range_m: float, sun_deg: float | None, pnp_cov_C: np.ndarray | None) -> np.ndarray:
        cc = self.cfg.covariance
        if cc.source == "pnp" and pnp_cov_C is not None:
            from .covariance import _floor

            return _floor(pnp_cov_C, cc)
        if cc.source == "characterized":
            if self._char is None:
                from .characterize import camera_signature

                cam = camera_signature(self.cfg, self.cfg.pipeline)
                path = cc.table or str(default_table_path(self.cfg.pipeline, cam))
                from pathlib import Path

                if not Path(path).is_file():
                    raise ValueError(
                        f"vision.covariance: no characterization table {path} for this camera {cam}. Run "
                        f"`swarm characterize --pipeline {self.cfg.pipeline} --scenario <file> --out DIR` and set "
                        "vision.covariance.table to the JSON it writes, or use covariance.source fixed|pnp"
                    )
                illum = "global" if self.cfg.lighting.ambient > 0 else "solar"
                self._char = CharacterizedNoise(load_table(path), cc, illum, cam)
            return self._char.cov_C(range_m, sun_deg)
        return fixed_cov_C(cc, range_m)

    def measure(self, observer: int, views, predicted: SwarmEstimate | None, step: int | None = None,
                targets=None) -> RelativeMeasurements:
        """One observer's relative measurements from its own views.

        ``views``: iterable of :class:`View` (or a dict of them) of this observer;
        ``predicted``: the observer's predicted estimate (before this step's update), or None;
        ``targets``: restrict to these targets (default: every decoded satellite).
        """
        t0 = time.perf_counter()
        if isinstance(views, dict):
            views = list(views.values())
        views = [v for v in views if v.observer == observer]
        rep = MeasureReport()
        if not views:
            self.last_reports[observer] = rep
            return RelativeMeasurements.empty()
        step = views[0].step if step is None else step
        t = views[0].t
        allowed = None if targets is None else {int(x) for x in targets}
        candidates = set(range(self.n)) - {observer} if allowed is None else allowed - {observer}
        pred = self._predicted_rel(observer, predicted, candidates)
        sun_B = None
        if predicted is not None:
            sun_B = quat.attitude_matrix(predicted.q_BI[observer]) @ self.sun_I(t)
        rows = []  # (target, q, r, R_Bi)
        if self.cfg.pipeline == "mono":
            rows = self._measure_mono(observer, views, pred, step, allowed, sun_B, rep)
        else:
            rows = self._measure_stereo(observer, views, pred, step, allowed, sun_B, rep)
        rep.ms = 1e3 * (time.perf_counter() - t0)
        self.last_reports[observer] = rep
        if not rows:
            return RelativeMeasurements.empty()
        rows.sort(key=lambda x: x[0])
        m = len(rows)
        meas = RelativeMeasurements(
            np.full(m, observer, dtype=int),
            np.array([x[0] for x in rows], dtype=int),
            np.array([x[1] for x in rows]),
            np.array([x[2] for x in rows]),
            np.array([x[3] for x in rows]),
        )
        return meas.canonical()

    def _sun_deg(self, sun_B, r_B):
        return None if sun_B is None else sun_angle_deg(r_B, sun_B)

    def _measure_mono(self, observer, views, pred, step, allowed, sun_B, rep):
        from .mono import camera_pose_from_truth, to_body

        mp = self.mono
        best: dict[int, tuple] = {}
        for v in views:
            if v.camera >= 6:
                continue
            predicted_R = {}
            for j in range(self.n):
                ref = pred.get(j) or mp.tracked_pose(observer, j, step)
                if ref is not None:
                    predicted_R[j] = camera_pose_from_truth(ref[0], ref[1], v.T_CB, v.r_C_B)[0]
            t0 = time.perf_counter()
            poses = mp.poses_in_image(v.images[0], v.camera, observer, predicted_R)
            self.timing["mono_ms"].append(1e3 * (time.perf_counter() - t0))
            for j, P in poses.items():
                if allowed is not None and j not in allowed:
                    continue
                if j not in best or P.area_px > best[j][0].area_px:
                    best[j] = (P, v)
        rows, seen = [], {}
        for j, (P, v) in best.items():
            q, r = to_body(P.R_CBj, P.p_C, v.T_CB, v.r_C_B)
            cov_C = self._cov_C(float(np.linalg.norm(P.p_C)), self._sun_deg(sun_B, r), P.cov_C)
            rows.append((j, q, r, camera_to_body(cov_C, v.T_CB)))
            seen[j] = (q, r)
            rep.details[j] = {"camera": P.camera, "tags": P.n_tags, "rms_px": P.reproj_rms_px, "ambiguous": P.ambiguous,
                              "chosen_by": P.info.get("chosen_by")}
        mp.update_tracks(step, observer, seen)
        rep.decoded = sorted(seen)
        if allowed is not None:
            rep.missed = sorted(allowed - set(seen) - {observer})
        return rows

    def _measure_stereo(self, observer, views, pred, step, allowed, sun_B, rep):
        from .mono import camera_pose_from_truth, to_body

        sp = self.stereo
        rows = []
        for v in views:
            j = v.target
            if v.camera < STEREO_BASE or j < 0 or (allowed is not None and j not in allowed):
                continue
            ref = pred.get(j)
            if ref is None:
                rep.missed.append(j)
                continue  # ICP needs a starting pose (the dissertation assumes one)
            R_pred, p_pred = camera_pose_from_truth(ref[0], ref[1], v.T_CB, v.r_C_B)
            t0 = time.perf_counter()
            res = sp.measure(v.images[0], v.images[1], R_pred, p_pred, stream(self.seed, "stereo_sample", step, observer, j))
            self.timing["stereo_ms"].append(1e3 * (time.perf_counter() - t0))
            if res is None:
                rep.missed.append(j)
                continue
            q, r = to_body(res.R_CBj, res.p_C, v.T_CB, v.r_C_B)
            cov_C = self._cov_C(float(np.linalg.norm(res.p_C)), self._sun_deg(sun_B, r), None)
            rows.append((j, q, r, camera_to_body(cov_C, v.T_CB)))
            rep.decoded.append(j)
            rep.details[j] = {"fitness": res.fitness, "rmse_m": res.rmse_m, "points": res.n_points}
        return rows

    def close(self) -> None:
        """Release the renderer's GL contexts (they are otherwise kept until exit)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None

    # ------------------------------------------------------------------ both
    def relative_measurements(self, step: int, t: float, q_BI, r_H, pairs, predicted_by_observer=None) -> RelativeMeasurements:
        """In-process convenience: render the views the pairs need, then let each observer
        measure its scheduled targets with its own prediction (``predicted_by_observer``:
        observer → SwarmEstimate, or None)."""
        obs, tgt = (np.asarray(a, dtype=int) for a in pairs)

        def pred_of(i):
            if predicted_by_observer is None:
                return None
            if isinstance(predicted_by_observer, dict):
                return predicted_by_observer.get(i)
            return predicted_by_observer[i]

        aim = None
        if self.cfg.pipeline == "stereo" and self.cfg.aim == "predicted":
            aim = {}
            for i in sorted(set(obs.tolist())):
                p = pred_of(i)
                if p is not None:
                    for j, (_q, r) in self._predicted_rel(i, p, tgt[obs == i]).items():
                        aim[(i, j)] = r
        views = self.render_views(step, t, q_BI, r_H, (obs, tgt), aim_B=aim)
        batches = []
        for i in sorted(set(obs.tolist())):
            mine = [v for (o, _c), v in views.items() if o == i]
            batches.append(self.measure(i, mine, pred_of(i), step, targets=tgt[obs == i]))
        return RelativeMeasurements.concat(batches).canonical()
