"""What a camera delivers (a :class:`View`) and what both sides of the vision chain share:
camera ids, intrinsics, the satellites' size as the pipelines see it, the Sun direction.

Camera ids: 0..5 the body-fixed face cameras (faces ``+z, +x, +y, −x, −y, −z``);
``STEREO_BASE + j`` the tracking stereo pair aimed at target j.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from swarmcore.cameras import Intrinsics
from swarmcore.dynamics import T_IH
from swarmcore.vision_config import VisionConfig

__all__ = ["View", "Observation", "STEREO_BASE", "face_intrinsics", "body_radius", "sun_direction_I"]

STEREO_BASE = 6  # stereo camera id = STEREO_BASE + target


def face_intrinsics(cfg: VisionConfig) -> Intrinsics:
    c = cfg.mono_camera
    if c.focal_px is None:
        return Intrinsics.from_fov(c.width_px, c.height_px, c.fov_deg)
    return Intrinsics(c.width_px, c.height_px, c.focal_px, c.focal_px, (c.width_px - 1) / 2.0, (c.height_px - 1) / 2.0)


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
