"""The synthetic relative-sensing model of chapters 4 and 6, both halves together: the
world's :class:`swarmcore.world.SyntheticCameras` and the agent's
:class:`swarmcore.agent.SyntheticPoseEstimator`. For the in-process simulator, benchmarks
and tests, which run both sides; a role builds only its own half (:mod:`swarmrt.truth`,
:mod:`swarmrt.flight`).
"""

from __future__ import annotations

from .agent import SyntheticPoseEstimator
from .measurement import MeasurementModel
from .mekf import RelativeMeasurements
from .scenario import Scenario
from .world import SyntheticCameras, world_params

__all__ = ["synthetic_model", "synthetic_batch"]


def synthetic_model(sc: Scenario) -> MeasurementModel:
    """The synthetic camera model (``vision.pipeline: none``)."""
    if sc.vision.pipeline != "none":
        raise ValueError(
            f"vision.pipeline: {sc.vision.pipeline!r} renders images; build its measurement model with "
            "swarm.simulation.measurement_model(scenario)"
        )
    return MeasurementModel(cameras=lambda: SyntheticCameras(world_params(sc)), estimator=lambda: SyntheticPoseEstimator(sc))


def synthetic_batch(wp, truth, observer, target) -> RelativeMeasurements:
    """Every observer's synthetic relative measurements of the given pairs, with the
    covariance each agent attaches, in canonical order: the two halves of the synthetic
    model in one call (benchmarks and tests)."""
    seen = SyntheticCameras(wp).observe(truth, observer, target)
    est = SyntheticPoseEstimator.from_relative(wp.rel)
    return RelativeMeasurements.concat([est.measure(i, seen[i])[0] for i in sorted(seen)]).canonical()
