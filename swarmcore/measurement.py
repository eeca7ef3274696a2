"""How relative measurements come to be: a camera model on the world (truth) side and a
pose estimator on the agent (flight) side, handed to the simulators as values.

The core knows only these interfaces and the synthetic models of chapters 4 and 6
(:class:`swarmcore.world.SyntheticCameras`, :class:`swarmcore.agent.SyntheticPoseEstimator`);
rendered cameras and the AprilTag / stereo pipelines (:mod:`swarmvision`) implement the
same two interfaces, and the application layer picks the pair a scenario asks for
(:func:`swarm.models.measurement_model`). Observations cross from one side to the other
only as what a real camera would deliver (detections, or images): never the truth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from .mekf import RelativeMeasurements, SwarmEstimate
from .scenario import Scenario

__all__ = ["CameraModel", "PoseEstimator", "MeasurementModel", "synthetic_model", "synthetic_batch"]


class CameraModel(Protocol):
    """World side: what each observer's cameras deliver at a step."""

    def observe(self, truth, observer: np.ndarray, target: np.ndarray, camera_ok: np.ndarray | None = None,
                predicted=None) -> dict[int, Any]:
        """``observer → observation`` for the scheduled (observer, target) pairs.

        ``camera_ok`` (n, 6): failed face cameras deliver nothing. ``predicted`` (in-process
        only): each observer's predicted estimate, for cameras an agent points itself."""
        ...

    def close(self) -> None: ...


class PoseEstimator(Protocol):
    """Agent side: one observer's observation → its relative measurements (with R)."""

    #: True when :meth:`measure` needs this step's prediction (tag ambiguity, ICP seed):
    #: the agent then predicts before measuring.
    needs_prediction: bool

    def measure(self, observer: int, observation: Any, predicted: SwarmEstimate | None,
                step: int | None = None) -> tuple[RelativeMeasurements, np.ndarray]:
        """``(measurements, camera id of each)``; camera ids 0..5 face, 6 + j stereo on j."""
        ...


@dataclass(frozen=True)
class MeasurementModel:
    """The two halves of a scenario's relative sensing, each built where it runs."""

    cameras: Callable[[], CameraModel]
    estimator: Callable[[], PoseEstimator]


def synthetic_model(sc: Scenario) -> MeasurementModel:
    """The synthetic camera model (``vision.pipeline: none``)."""
    from .agent import SyntheticPoseEstimator
    from .world import SyntheticCameras, world_params

    if sc.vision.pipeline != "none":
        raise ValueError(
            f"vision.pipeline: {sc.vision.pipeline!r} renders images; build its measurement model with "
            "swarm.models.measurement_model(scenario)"
        )
    return MeasurementModel(cameras=lambda: SyntheticCameras(world_params(sc)), estimator=lambda: SyntheticPoseEstimator(sc))


def synthetic_batch(wp, truth, observer, target) -> RelativeMeasurements:
    """Every observer's synthetic relative measurements of the given pairs, with the
    covariance each agent attaches, in canonical order: the two halves of the synthetic
    model in one call (benchmarks and tests)."""
    from .agent import SyntheticPoseEstimator
    from .world import SyntheticCameras

    seen = SyntheticCameras(wp).observe(truth, observer, target)
    est = SyntheticPoseEstimator.from_relative(wp.rel)
    return RelativeMeasurements.concat([est.measure(i, seen[i])[0] for i in sorted(seen)]).canonical()
