"""``selector``'s process shell: the bus presence of :class:`selector.protocol.SelectorProtocol`."""

from __future__ import annotations

from swarmcore.scenario import Scenario
from swarmrt.estimators import check_estimator
from swarmrt.node import Node

from .protocol import SelectorProtocol

__all__ = ["Selector"]


class Selector(Node):
    def __init__(self, sc: Scenario, run: str, bus):
        super().__init__("selector", 0, run, sc.n_sats, bus, announce=False)
        self.machine = SelectorProtocol(sc, run, plans_from_estimate=check_estimator(sc).provides_swarm_covariance)
        self.subscribe(self.keys.est(), shallow=True)  # who, which step, which phase: not the arrays
        for key in (self.keys.fault(), self.keys.health(), self.keys.clock()):
            self.subscribe(key)
        self.watch_liveliness(self.keys.alive("agent"))
        self.watch_liveliness(self.keys.alive("world"))  # gone before the end: the run is broken
        self.watch_liveliness(self.keys.alive("recorder"))  # back after a bus gap: it is sent the selection again
        self.set_bus_limits(sc.emulator, hold_world=True)
        self.announce()

