"""The relative-measurement model a scenario asks for: the one place that decides between
the core's synthetic cameras and the rendered ones (which import the vision stack)."""

from __future__ import annotations

from swarmcore.measurement import MeasurementModel, synthetic_model
from swarmcore.scenario import Scenario

__all__ = ["measurement_model"]


def measurement_model(sc: Scenario) -> MeasurementModel:
    """Synthetic (``vision.pipeline: none``) or rendered (mono, stereo) relative sensing.
    Vision libraries are imported only when the scenario renders."""
    if sc.vision.pipeline == "none":
        return synthetic_model(sc)
    import swarmvision

    return swarmvision.measurement_model(sc)


def batch_wire_size(run: str = "sim"):
    """``wire_size(observer, k, t, rel, cameras)``: the bytes of an observer's measurement
    batch on the radio (:func:`swarm.bus.convert.radio_bytes`: as its agent publishes it,
    less the run id; so ``run`` does not change it)."""
    from .bus.convert import batch_msg, radio_bytes

    def size(observer: int, k: int, t: float, rel, cameras) -> int:
        return radio_bytes(batch_msg(rel, cameras, run=run, sender=f"agent-{observer}", k=k, t_s=t, observer=observer))

    return size


#: The run id of the in-process simulator's batches (their radio size does not depend on it).
SIM_RUN_ID = "sim"


def simulate_scenario(sc: Scenario, progress=None, run: str = SIM_RUN_ID, measurements: list | None = None):
    """``swarmcore.sim.simulate`` with everything a scenario may need from outside the core:
    its measurement model (rendered cameras when it renders) and, with links, the size of
    each batch on the bus. ``measurements`` (a list; rendered scenarios): receives one
    record per vision measurement (:attr:`swarmvision.pose_estimator.VisionPoseEstimator.record`)."""
    from swarmcore.sim import simulate

    model = measurement_model(sc)
    if measurements is not None and sc.vision.pipeline != "none":
        est = model.estimator()
        est.record = measurements  # type: ignore[attr-defined]
        model = MeasurementModel(cameras=model.cameras, estimator=lambda: est)
    return simulate(sc, model, progress=progress, wire_size=batch_wire_size(run) if sc.links.enabled else None)
