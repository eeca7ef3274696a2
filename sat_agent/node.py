"""``sat_agent``'s process shell: the bus presence of :class:`sat_agent.protocol.AgentProtocol`.

It subscribes to what satellite i may hear (the clock, its own sensors and cameras, what
the radio brings of its peers' batches, fault commands, agent liveliness; never the
truth), serves its full estimate on ``cov/<i>``, builds its pose estimator, compiles
the filter's kernels before it announces itself, and drives the protocol machine.
"""

from __future__ import annotations

import time
import uuid

from swarmcore import kernels
from swarmcore.scenario import Scenario
from swarmrt.estimators import estimator_for
from swarmrt.flight import pose_estimator
from swarmrt.node import Node

from .protocol import AgentProtocol

__all__ = ["Agent", "claim_id"]


class Agent(Node):
    def __init__(self, sc: Scenario, sat: int, run: str, bus, restart: bool = False):
        if not 0 <= sat < sc.n_sats:
            raise SystemExit(f"sat_agent: --id {sat} is not a satellite of this {sc.n_sats}-satellite swarm")
        super().__init__("agent", sat, run, sc.n_sats, bus, announce=False)
        pose = pose_estimator(sc)  # vision libraries only when the scenario renders
        self.machine = AgentProtocol(sc, sat, run, pose, estimator_for(sc, sat), restart=restart, malformed=lambda: self.malformed,
                                    key_mismatch=lambda: self.key_mismatch)
        # Peers' batches reach us only through the radio, which the world emulates: the
        # ideal radio's one message a step (batches: every peer's; batches/<i>: our graph
        # neighbours', radio "graph"), or with links what reached us (rx/<i>).
        ideal = self.keys.batches() if self.machine.hears is None else self.keys.batches(sat)
        peers = self.keys.rx(sat) if sc.links.enabled else ideal
        for key in (self.keys.clock(), self.keys.sensors(sat), self.keys.fault()):
            self.subscribe(key)
        # The ideal radio's message shallowly: each peer's estimator message is checked when
        # the estimator reads it (AgentProtocol._payload), not all n − 1 on arrival.
        self.subscribe(peers, shallow=not sc.links.enabled)
        self.subscribe(self.keys.img(sat) if sc.vision.pipeline != "none" else self.keys.cam(sat))
        self.watch_liveliness(self.keys.alive("agent"))
        self.watch_liveliness(self.keys.alive("world"))  # gone before the end: the run is broken
        self.watch_liveliness(self.keys.alive("recorder"))  # back after a bus gap: it is sent the step again
        self.watch_liveliness(self.keys.alive("selector"))  # back after a bus gap: its health reports again (it plans from them)
        self.set_bus_limits(sc.emulator, hold_world=True)
        self.queryable(self.keys.cov(sat), self.machine.serve_cov)
        warm = getattr(pose, "warm_up", None)
        if warm is not None:
            warm()  # build the pipeline now (tag detector, model cloud), not at step 0
        kernels.warm_up()  # compile before the world counts on our step times
        self.announce()

    @property
    def done(self) -> bool:
        return self.machine.done

    @property
    def finished(self) -> bool:
        return self.machine.done


_CLAIM_RETRY_S = 0.2  # the least time between two claims while no world answers


def claim_id(sc: Scenario, run: str, bus, timeout: float | None = None) -> tuple[int, bool, str]:
    """Ask the world for a satellite id (``--id auto``); returns (id, run already under way,
    the satellite's bus password or "" when the world has none to give)."""
    node = Node("claimant", uuid.uuid4().hex[:12], run, sc.n_sats, bus)
    token = str(node.ident)
    limit = timeout or sc.emulator.startup_timeout_s
    deadline = time.monotonic() + limit
    try:
        while time.monotonic() < deadline:
            asked = time.monotonic()
            msg = node.query(node.keys.claim(token), "claim", timeout=2.0)
            if msg is not None:
                node.log.info("world gave satellite %d (run under way: %s%s)", msg.sat, msg.running,
                              "; with its credential" if msg.password else "")
                return msg.sat, msg.running, msg.password
            # No world serving claims yet: the query came back at once. Ask again after a pause
            # (an event of the bus ends it sooner), not in a spin: seen, 574 queries of four
            # replicas waiting for the world, held back by the router's ingress gate.
            if (pause := asked + _CLAIM_RETRY_S - time.monotonic()) > 0:
                node.inbox.get(timeout=pause)
        raise SystemExit(f"no satellite id from the world within {limit:.0f} s")
    finally:
        node.close()
