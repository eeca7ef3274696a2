"""What the world computes, built from a scenario: the truth side of each model choice.

The one place that decides which cameras a scenario's world simulates (the core's
synthetic detections, or rendered images, which import the vision stack only then).
Flight software never imports this module (an import contract holds it).
"""

from __future__ import annotations

from swarmcore.measurement import CameraModel
from swarmcore.scenario import Scenario

__all__ = ["camera_model"]


def camera_model(sc: Scenario) -> CameraModel:
    """The world-side half of the scenario's relative sensing: what each observer's cameras
    deliver (detections, or rendered images)."""
    if sc.vision.pipeline == "none":
        from swarmcore.world import SyntheticCameras, world_params

        return SyntheticCameras(world_params(sc))
    from swarmvision.camera_sim import RenderedCameras

    return RenderedCameras.from_scenario(sc)
