"""How relative measurements come to be: a camera model on the world (truth) side and a
pose estimator on the agent (flight) side, handed to the simulators as values.

This module holds only the interfaces, so that flight software can name them without
importing the world. The synthetic models of chapters 4 and 6 implement them in the core
(:class:`swarmcore.world.SyntheticCameras`, :class:`swarmcore.agent.SyntheticPoseEstimator`;
both halves together: :mod:`swarmcore.synthetic`); rendered cameras and the AprilTag /
stereo pipelines (:mod:`swarmvision`) implement the same two interfaces; the runtime
picks the half each role needs (:func:`swarmrt.truth.camera_model` for the world,
:func:`swarmrt.flight.pose_estimator` for an agent). Observations cross from one side to the other
only as what a real camera would deliver (detections, or images): never the truth.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from .mekf import RelativeMeasurements, SwarmEstimate

__all__ = ["CameraModel", "PoseEstimator", "MeasurementModel"]


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
