"""An agent's pose estimator (flight side): its own images → relative pose measurements.

:class:`VisionPoseEstimator` implements :class:`swarmcore.measurement.PoseEstimator` for
the monocular AprilTag + PnP pipeline and the stereo + ICP pipeline. It starts from the
agent's own predicted estimate (to resolve tag ambiguities and to seed ICP) and attaches
each measurement's covariance (:mod:`swarmvision.covariance`), rotated into B_i.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from swarmcore import quat
from swarmcore.mekf import RelativeMeasurements, SwarmEstimate
from swarmcore.sensors import camera_to_body, relative_pose
from swarmcore.streams import stream
from swarmcore.vision_config import VisionConfig

from .covariance import CharacterizedNoise, default_table_path, fixed_cov_C, floor_cov, load_table, sun_angle_deg
from .error_model import quantities
from .views import STEREO_BASE, Observation, VisionSide, sun_direction_I

if TYPE_CHECKING:
    from .error_model import ErrorModel
    from .mono import MonoPipeline
    from .stereo import StereoPipeline

__all__ = ["VisionPoseEstimator", "MeasureReport"]


@dataclass
class MeasureReport:
    """Diagnostics of one observer's :meth:`VisionSystem.measure` call."""

    decoded: list = field(default_factory=list)  # targets measured
    missed: list = field(default_factory=list)  # targets expected but not measured
    ms: float = 0.0
    details: dict = field(default_factory=dict)


class VisionPoseEstimator(VisionSide):
    """Agent side of the vision chain (one per agent; in-process, one for all observers:
    its per-observer state — tag tracks — is keyed by observer)."""

    needs_prediction = True

    def __init__(self, cfg: VisionConfig, n_sats: int, half_size_m: float, seed: int, mean_motion: float):
        super().__init__(cfg, n_sats, half_size_m, seed, mean_motion)
        from . import tags

        if cfg.pipeline == "mono" and n_sats > tags.max_satellites():
            raise ValueError(f"n_sats={n_sats}: the 36h11 family tags at most {tags.max_satellites()} satellites")
        if cfg.pipeline == "mono" and cfg.mono.tag_size_m >= 2 * half_size_m:
            raise ValueError("vision.mono.tag_size_m: must be smaller than the cube face (2 · half_size_m)")
        # Built when first needed (the tag detector, the model cloud, the noise tables).
        self._mono: MonoPipeline | None = None
        self._stereo: StereoPipeline | None = None
        self._char: CharacterizedNoise | None = None
        self._fitted: ErrorModel | None = None
        #: When a list: one dict per measurement (step, observer, target, camera pose, the
        #: quantities the error model reads, the variances attached) — ``swarm sim
        #: --measurements`` turns them into residuals against the truth.
        self.record: list | None = None
        self.last_reports: dict[int, MeasureReport] = {}
        self.timing: dict[str, list[float]] = {"mono_ms": [], "stereo_ms": []}
        if cfg.covariance.source == "characterized":
            self._cov_C(5.0, None, None)  # load the table now: a missing or mismatched one fails early
        if cfg.covariance.source == "fitted":
            _ = self.fitted  # likewise the error model

    @property
    def mono(self) -> MonoPipeline:
        if self._mono is None:
            from .mono import MonoPipeline

            self._mono = MonoPipeline(self.cfg.mono, self.cameras.face, self.half, self.n)
        return self._mono

    @property
    def stereo(self) -> StereoPipeline:
        if self._stereo is None:
            from .models import reference_cloud
            from .stereo import StereoPipeline

            pts, nrm = reference_cloud(self.cfg.stereo.model_points)
            self._stereo = StereoPipeline(self.cfg.stereo, self.cameras.pair, self.cfg.stereo_camera.baseline_m, pts, nrm,
                                          self.cameras.body_radius)
        return self._stereo

    def warm_up(self) -> None:
        """Build the pipeline now (tag detector; stereo: the model cloud), not at step 0."""
        _ = self.stereo if self.cfg.pipeline == "stereo" else self.mono

    def measure(self, observer: int, observation: Observation | None, predicted: SwarmEstimate | None,
                step: int | None = None) -> tuple[RelativeMeasurements, np.ndarray]:
        """One observer's relative measurements from its own views (and the camera of each)."""
        if observation is None or not observation.views:
            self.last_reports[observer] = MeasureReport()
            return RelativeMeasurements.empty(), np.zeros(0, dtype=int)
        rel = self.measure_views(observer, observation.views, predicted, step, targets=observation.targets)
        if self.cfg.pipeline == "stereo":
            return rel, STEREO_BASE + rel.target
        rep = self.last_reports[observer]
        return rel, np.array([int(rep.details.get(int(j), {}).get("camera", 0)) for j in rel.target], dtype=int)

    def _predicted_rel(self, observer: int, predicted: SwarmEstimate | None, targets):
        """Predicted (q_BjBi, r_ij_Bi) per target from the observer's own estimate."""
        if predicted is None:
            return {}
        tg = np.array(sorted(targets), dtype=int)
        if tg.size == 0:
            return {}
        q, r = relative_pose(self.mean_motion, predicted.t, predicted.q_BI, predicted.r_H, np.full(tg.size, observer), tg)
        return {int(j): (q[k], r[k]) for k, j in enumerate(tg)}

    @property
    def fitted(self) -> ErrorModel:
        """The fitted error model (``covariance.source: fitted``), loaded once."""
        if self._fitted is None:
            from .catalogue import camera_signature
            from .covariance import resolve_model_path
            from .error_model import load_model

            cam = camera_signature(self.cfg, self.cfg.pipeline)
            path = resolve_model_path(self.cfg.covariance.model, self.cfg.pipeline, cam)
            m = load_model(path)
            if m.pipeline != self.cfg.pipeline or any(abs(float(m.camera[k]) - float(cam[k])) > 1e-6 for k in cam if k in m.camera):
                raise ValueError(f"vision.covariance.model {path}: fitted for {m.pipeline} camera {m.camera}, the scenario's "
                                 f"is {self.cfg.pipeline} {cam}: run `swarm characterize` for this camera")
            self._fitted = m
        return self._fitted

    def _cov_C(self, range_m: float, sun_deg: float | None, pnp_cov_C: np.ndarray | None, q: dict | None = None) -> np.ndarray:
        cc = self.cfg.covariance
        if cc.source == "fitted" and q is not None:
            return floor_cov(self.fitted.cov_C(q), cc)
        if cc.source == "pnp" and pnp_cov_C is not None:
            return floor_cov(pnp_cov_C, cc)
        if cc.source == "characterized":
            if self._char is None:
                from .catalogue import camera_signature

                cam = camera_signature(self.cfg, self.cfg.pipeline)
                path = cc.table or str(default_table_path(self.cfg.pipeline, cam))
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

    def measure_views(self, observer: int, views, predicted: SwarmEstimate | None, step: int | None = None,
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
            sun_B = quat.attitude_matrix(predicted.q_BI[observer]) @ sun_direction_I(self.cfg, self.mean_motion, t)
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

    def _record(self, step, observer, target, view, R_CBj, p_C, qty, cov_C) -> None:
        if self.record is not None:
            self.record.append({"step": int(step), "observer": int(observer), "target": int(target), "camera": int(view.camera),
                                "R_CBj": np.array(R_CBj, float), "p_C": np.array(p_C, float), "T_CB": np.array(view.T_CB, float),
                                "r_C_B": np.array(view.r_C_B, float), "q": qty, "var_C": np.diag(cov_C).copy()})

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
            qty = quantities(P.R_CBj, P.p_C, None if sun_B is None else v.T_CB @ sun_B, rms_px=P.reproj_rms_px,
                             n_tags=P.n_tags)
            cov_C = self._cov_C(float(np.linalg.norm(P.p_C)), self._sun_deg(sun_B, r), P.cov_C, qty)
            rows.append((j, q, r, camera_to_body(cov_C, v.T_CB)))
            self._record(step, observer, j, v, P.R_CBj, P.p_C, qty, cov_C)
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
            qty = quantities(res.R_CBj, res.p_C, None if sun_B is None else v.T_CB @ sun_B, fitness=res.fitness,
                             rmse_m=res.rmse_m, n_points=res.n_points)
            cov_C = self._cov_C(float(np.linalg.norm(res.p_C)), self._sun_deg(sun_B, r), None, qty)
            rows.append((j, q, r, camera_to_body(cov_C, v.T_CB)))
            self._record(step, observer, j, v, res.R_CBj, res.p_C, qty, cov_C)
            rep.decoded.append(j)
            rep.details[j] = {"fitness": res.fitness, "rmse_m": res.rmse_m, "points": res.n_points}
        return rows
