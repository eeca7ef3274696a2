"""What a camera delivers (a :class:`View`) and what both sides of the vision chain share:
camera ids, intrinsics, the satellites' size as the pipelines see it (together: a
:class:`CameraSetup`), the Sun direction.

Camera ids: 0..5 the body-fixed face cameras (faces ``+z, +x, +y, −x, −y, −z``);
``STEREO_BASE + j`` the tracking stereo pair aimed at target j.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Self

import numpy as np

from swarmcore.cameras import Intrinsics
from swarmcore.dynamics import T_IH
from swarmcore.vision_config import VisionConfig

__all__ = ["View", "Observation", "STEREO_BASE", "CameraSetup", "VisionSide", "face_intrinsics", "stereo_intrinsics", "pair_intrinsics",
           "body_radius", "sun_direction_I"]

STEREO_BASE = 6  # stereo camera id = STEREO_BASE + target


def face_intrinsics(cfg: VisionConfig) -> Intrinsics:
    c = cfg.mono_camera
    if c.focal_px is None:
        return Intrinsics.from_fov(c.width_px, c.height_px, c.fov_deg)
    return Intrinsics(c.width_px, c.height_px, c.focal_px, c.focal_px, (c.width_px - 1) / 2.0, (c.height_px - 1) / 2.0)


def stereo_intrinsics(width: int, height: int, focal_px: float) -> Intrinsics:
    return Intrinsics(width, height, focal_px, focal_px, (width - 1) / 2.0, (height - 1) / 2.0)


def pair_intrinsics(cfg: VisionConfig) -> Intrinsics:
    """Each camera of a tracking stereo pair (``vision.stereo_camera``)."""
    c = cfg.stereo_camera
    return stereo_intrinsics(c.width_px, c.height_px, c.focal_px)


def body_radius(cfg: VisionConfig, half_size_m: float) -> float:
    """Radius of the sphere that holds a target: the cube (mono) or the spacecraft model (stereo)."""
    if cfg.pipeline == "mono":
        return float(half_size_m * np.sqrt(3.0))
    from .models import model_radius, spacecraft_model

    return model_radius(spacecraft_model(0))


def sun_direction_I(cfg: VisionConfig, mean_motion: float, t: float) -> np.ndarray:
    """Unit vector to the Sun in the inertial frame at ``t`` (an ephemeris both the world's
    lighting and an agent's noise model know)."""
    s = np.asarray(cfg.lighting.sun_direction, float)
    s = s / np.linalg.norm(s)
    return T_IH(mean_motion, t) @ s if cfg.lighting.sun_frame == "H" else s


@dataclass(frozen=True)
class CameraSetup:
    """The cameras of a scenario's ``vision`` as both sides know them: the world renders
    through them, an agent's pipelines measure with them."""

    face: Intrinsics  # each body-fixed face camera (mono)
    pair: Intrinsics  # each camera of a tracking stereo pair
    body_radius: float  # the sphere that holds a target (m): what a frustum must reach, the stereo crop

    @classmethod
    def of(cls, cfg: VisionConfig, half_size_m: float) -> CameraSetup:
        return cls(face_intrinsics(cfg), pair_intrinsics(cfg), body_radius(cfg, half_size_m))


class VisionSide:
    """What each side of the vision chain (the world's :class:`~swarmvision.camera_sim.RenderedCameras`,
    an agent's :class:`~swarmvision.pose_estimator.VisionPoseEstimator`) is built from: the
    scenario's ``vision``, the swarm's size, the cube's half-size, the seed, the mean motion,
    and the cameras they give."""

    @classmethod
    def from_scenario(cls, sc) -> Self:
        """For a scenario (``vision``, swarm size, cube size, seed, mean motion)."""
        return cls(sc.vision, sc.n_sats, sc.spacecraft.half_size_m, sc.seed, sc.orbit.mean_motion_rad_s)

    def __init__(self, cfg: VisionConfig, n_sats: int, half_size_m: float, seed: int, mean_motion: float):
        if cfg.pipeline == "none":
            raise ValueError(f"{type(self).__name__} needs vision.pipeline 'mono' or 'stereo'")
        self.cfg = cfg
        self.n = n_sats
        self.half = half_size_m
        self.seed = seed
        self.mean_motion = mean_motion
        self.cameras = CameraSetup.of(cfg, half_size_m)


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


@dataclass
class Observation:
    """One observer's camera delivery at one step: its views and the targets it was
    scheduled to measure (a pipeline reports only those)."""

    views: list[View]
    targets: np.ndarray
