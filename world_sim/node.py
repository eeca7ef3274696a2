"""``world_sim``'s process shell: the bus presence of :class:`world_sim.protocol.WorldProtocol`.

It subscribes to what the world listens to (the agents' batches, which it carries as the
radio; estimates, health reports, the selector's choice, fault commands, liveliness), serves the priors (``init/<i>``) and satellite
claims (``claim/<token>``), builds the world-side camera model the scenario asks for, and
drives the protocol machine; the protocol itself has no bus in it.
"""

from __future__ import annotations

from swarmcore.scenario import Scenario
from swarmrt.estimators import check_estimator
from swarmrt.node import Node
from swarmrt.truth import camera_model

from .protocol import WorldProtocol

__all__ = ["World"]


class World(Node):
    def __init__(self, sc: Scenario, run: str, bus, expect_recorder: bool = True, expect_selector: bool | None = None,
                 agent_passwords: dict[int, str] | None = None):
        if (why := sc.vision.distributed_refusal()) is not None:
            raise SystemExit(f"world_sim: {why}")
        super().__init__("world", 0, run, sc.n_sats, bus, announce=False)
        self.sc = sc
        self.cameras = camera_model(sc)  # rendering only when the scenario renders
        est = check_estimator(sc)  # the agents' estimator: which satellites each one's prior covers
        self.machine = WorldProtocol(sc, run, self.cameras, expect_recorder, expect_selector, agent_passwords=agent_passwords,
                                     malformed=lambda: self.malformed, key_mismatch=lambda: self.key_mismatch,
                                     prior_ids=lambda i: est.prior_ids_for(sc, i), radio=est.radio,
                                     warm_rejoin=est.warm_rejoin)
        self.subscribe(self.keys.est(), shallow=True)  # who, which step, which phase: not the arrays
        self.subscribe(self.keys.health())
        self.subscribe(self.keys.select())
        self.subscribe(self.keys.faults())  # commands, and what others carried out
        self.subscribe(self.keys.meas())  # the world is the radio: it carries the agents' batches
        self.subscribe(self.keys.recorded())  # how far the recorder has got (the bounded recorder lag)
        self.watch_liveliness()
        self.set_bus_limits(sc.emulator)
        self.queryable(self.keys.init(), self.machine.serve_prior)
        self.queryable(self.keys.claim(), self.machine.serve_claim)
        self.queryable(self.keys.clock(), self.machine.serve_clock)
        self.queryable(self.keys.health(), self.machine.serve_health)
        if sc.links.enabled:
            self.queryable(self.keys.rejoin("*") + "/*/*", self.machine.serve_rejoin, notify=True)
        self.announce()

    def run_loop(self) -> None:
        self.run_steps()

    def run_steps(self, progress=None) -> None:
        m = self.machine
        m.progress = progress
        self.drive(m)
        if not m.finished:
            # Stopped early: still tell everyone the run is over.
            self.put(self.keys.clock(), m.done_clock())
        self.log.info("run finished at step %d (t = %.1f s), %d malformed messages dropped", m.k, m.truth.t, self.malformed)

    def close(self) -> None:
        self.cameras.close()
        super().close()
