"""What an agent flies, built from a scenario: the flight side of each model choice.

The one place that decides which pose estimator a scenario's agent runs (the synthetic
one of the core, or a vision pipeline, which imports the vision stack only then). Nothing
here, nor anything it imports, reads truth: an import contract in ``pyproject.toml``
holds this module, ``sat_agent`` and the pose estimators apart from the world, the
channel model, the simulator, the renderer and the camera simulator.
"""

from __future__ import annotations

from swarmcore.measurement import PoseEstimator
from swarmcore.scenario import Scenario

__all__ = ["pose_estimator"]


def pose_estimator(sc: Scenario) -> PoseEstimator:
    """The agent-side half of the scenario's relative sensing: detections (synthetic
    cameras) or images (mono, stereo) in, relative measurements with their R out."""
    if sc.vision.pipeline == "none":
        from swarmcore.agent import SyntheticPoseEstimator

        return SyntheticPoseEstimator(sc)
    from swarmvision.pose_estimator import VisionPoseEstimator

    return VisionPoseEstimator.from_scenario(sc)
