"""The in-process simulator with everything a scenario may need from outside the core:
both halves of its relative sensing (rendered cameras when it renders) and, with links,
the size of each batch on the bus."""

from __future__ import annotations

from swarmcore.measurement import MeasurementModel
from swarmcore.result import RunResult
from swarmcore.scenario import Scenario
from swarmcore.sim import simulate
from swarmrt.bus.convert import batch_wire_size
from swarmrt.estimators import codec_for, estimator_factory
from swarmrt.flight import pose_estimator
from swarmrt.truth import camera_model

__all__ = ["measurement_model", "simulate_scenario", "SIM_RUN_ID"]

#: The run id of the in-process simulator's batches (their radio size does not depend on it).
SIM_RUN_ID = "sim"


def measurement_model(sc: Scenario) -> MeasurementModel:
    """Both halves of the scenario's relative sensing, each built when asked for: the
    world's cameras (:func:`swarmrt.truth.camera_model`) and the agents' pose estimator
    (:func:`swarmrt.flight.pose_estimator`)."""
    return MeasurementModel(cameras=lambda: camera_model(sc), estimator=lambda: pose_estimator(sc))


def simulate_scenario(sc: Scenario, progress=None, run: str = SIM_RUN_ID, measurements: list | None = None,
                      on_step=None) -> RunResult:
    """:func:`swarmcore.sim.simulate` of a scenario. ``measurements`` (a list; rendered
    scenarios): receives one record per vision measurement
    (:attr:`swarmvision.pose_estimator.VisionPoseEstimator.record`). ``on_step``: called with
    each step's :class:`swarmcore.sim.SimStep` (the 3-D scene: :mod:`swarm.record.scene_file`)."""
    model = measurement_model(sc)
    if measurements is not None and sc.vision.pipeline != "none":
        est = model.estimator()
        est.record = measurements  # type: ignore[attr-defined]
        model = MeasurementModel(cameras=model.cameras, estimator=lambda: est)
    codec = codec_for(sc)
    return simulate(sc, model, progress=progress, wire_size=batch_wire_size(run, codec.to_msg), estimator_factory=estimator_factory(sc),
                    on_step=on_step)
