"""The 3-D scene of an in-process run (``swarm sim``) as an MCAP file, ``scene.mcap``.

The same channels as a recording's (:mod:`swarm.record.scene`), built by the same
:class:`~swarm.record.scene.SceneBuilder` from the simulator's values at each step
(:class:`swarmcore.sim.SimStep`), so the Foxglove layout that opens ``run.mcap`` and the
live view opens it too. Log times are the simulated time (ns from t = 0): the file plays
back at the simulation's pace, not the computer's.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from swarm.record.mcaplog import CheckpointWriter
from swarm.record.scene import LINK_COUNTERS, CameraRig, SceneBuilder, WriterSink
from swarmcore.scenario import Scenario
from swarmcore.sim import SimStep

__all__ = ["SceneFile", "SCENE_FILE"]

#: The scene's file name in a ``swarm sim`` folder.
SCENE_FILE = "scene.mcap"


class SceneFile:
    """Pass it as ``on_step`` to the simulator; :meth:`close` when the run is over.

    ``with SceneFile(sc, out / "scene.mcap") as scene: simulate_scenario(sc, on_step=scene)``"""

    def __init__(self, sc: Scenario, path: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.w = CheckpointWriter(self.path, library="swarm-coloc sim")
        self.builder = SceneBuilder(WriterSink(self.w), sc.n_sats, sc.orbit.mean_motion_rad_s, sc.spacecraft.half_size_m,
                                    CameraRig.of(sc))
        self.steps = 0

    def __call__(self, s: SimStep) -> None:
        b, ns = self.builder, round(s.t * 1e9)
        b.truth(s.k, s.t, s.q_BI, s.r_H, ns)
        for i in range(s.taken.shape[0]):
            b.measurements(i, s.k, np.nonzero(s.taken[i])[0].tolist(), ns)
        for v in s.views:
            b.estimate(v.own, s.k, s.t, v.ids, v.q_BI, v.r_H, v.P_pose, ns)
        if s.links is not None:
            b.links(s.k, {c: getattr(s.links, c) for c in LINK_COUNTERS}, ns)
        self.steps += 1
        if self.steps % 50 == 0:
            self.w.flush()

    def close(self) -> None:
        self.w.close(finalize=True)

    def __enter__(self) -> SceneFile:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
