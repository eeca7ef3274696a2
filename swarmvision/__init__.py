"""Rendered cameras and vision pipelines (dissertation chapter 5).

Truth side: :mod:`camera_sim` (``RenderedCameras``: what each camera sees, rendered
headless by :mod:`render` with the camera noise of :mod:`noise`, of the bodies in
:mod:`models`). Flight side: :mod:`pose_estimator` (``VisionPoseEstimator``: AprilTag +
PnP in :mod:`mono` with the tag ids of :mod:`tags`, stereo + ICP in :mod:`stereo`, each
measurement's R from :mod:`covariance`). Shared: :mod:`views`. Studies: :mod:`characterize`
(Monte Carlo error statistics), :mod:`bench`. The configuration model is the scenario's
(:mod:`swarmcore.vision_config`). Heavy imports (OpenGL, OpenCV, Open3D) happen inside the
modules that need them.
"""

from __future__ import annotations

from swarmcore.measurement import MeasurementModel
from swarmcore.scenario import Scenario

__all__ = ["measurement_model"]


def measurement_model(sc: Scenario) -> MeasurementModel:
    """Rendered cameras (world side) and the pose pipelines (agent side) of a scenario: both
    halves, for whatever runs both (the in-process simulator, benchmarks). A role builds
    only its own half (:mod:`swarmrt.truth`, :mod:`swarmrt.flight`)."""
    from .camera_sim import RenderedCameras
    from .pose_estimator import VisionPoseEstimator

    return MeasurementModel(cameras=lambda: RenderedCameras.from_scenario(sc), estimator=lambda: VisionPoseEstimator.from_scenario(sc))
