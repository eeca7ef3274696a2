"""In-process vision chain for tests: the world's rendered cameras and one pose estimator,
as the simulator wires them (render what the pairs need, then each observer measures its
own views with its own prediction)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from swarmcore.mekf import RelativeMeasurements
from swarmvision.camera_sim import RenderedCameras
from swarmvision.pose_estimator import VisionPoseEstimator


class VisionChain:
    def __init__(self, cfg, n: int, half_size_m: float, seed: int, mean_motion: float):
        self.cameras = RenderedCameras(cfg, n, half_size_m, seed, mean_motion)
        self.estimator = VisionPoseEstimator(cfg, n, half_size_m, seed, mean_motion)

    @property
    def mono(self):
        return self.estimator.mono

    def render_views(self, step, t, q_BI, r_H, pairs, **kw):
        return self.cameras.render_views(step, t, q_BI, r_H, pairs, **kw)

    def relative_measurements(self, step, t, q_BI, r_H, pairs, predicted=None) -> RelativeMeasurements:
        """Every scheduled observer's measurements, canonical; ``predicted``: observer → estimate."""
        obs, tgt = (np.asarray(a, dtype=int) for a in pairs)
        truth = SimpleNamespace(step=step, t=t, q_BI=np.asarray(q_BI, float), r_H=np.asarray(r_H, float))
        seen = self.cameras.observe(truth, obs, tgt)
        pred = predicted or {}
        batches = [self.estimator.measure(i, seen[i], pred.get(i), step)[0] for i in sorted(seen)]
        return RelativeMeasurements.concat(batches).canonical()
