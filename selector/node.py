"""``selector``: publishes the measurements to take at the next step.

It plans step k from a reference agent's estimate — the lowest-numbered live agent —
exactly as the in-process simulator does (:func:`swarmcore.sim.choose_pairs`): the
agent's posterior at k−1 carried to k without its gyro (its prior at k = 0), fetched in
full from ``cov/<ref>``. Camera health (fault commands, agents' health reports) and dead
satellites (liveliness) remove candidates.
"""

from __future__ import annotations

import time

import numpy as np

from swarm.bus.convert import estimate_from_full, select_msg
from swarm.bus.messages import Fault
from swarm.node import Node
from swarmcore.scenario import Scenario
from swarmcore.sim import choose_pairs, scenario_graph
from swarmcore.world import filter_params

NEEDS_STATE = ("greedy", "swarm_greedy", "fast_swarm_greedy", "logdet_greedy")


class Selector(Node):
    def __init__(self, sc: Scenario, run: str, bus):
        super().__init__("selector", 0, run, sc.n_sats, bus, announce=False)
        self.sc = sc
        self.G = scenario_graph(sc)
        self.params = [filter_params(sc, i) for i in range(sc.n_sats)]
        self.camera_ok = np.ones((sc.n_sats, 6), dtype=bool)
        self.alive: set[int] = set()
        self.done = False
        self.planned: set[int] = set()
        self.next_plan: dict[int, int] = {}  # agent → the step its latest estimate lets us plan
        self.clock_seen = False  # the run has started
        self.subscribe(self.keys.est(), shallow=True)  # who, which step, which phase: not the arrays
        self.subscribe(self.keys.fault())
        self.subscribe(self.keys.health())
        self.subscribe(self.keys.clock())
        self.watch_liveliness(self.keys.alive("agent"))
        self.announce()

    def ref_agent(self) -> int | None:
        return min(self.alive) if self.alive else None

    def pump(self, timeout: float) -> bool:
        ev = self.next_event(timeout)
        if ev is None:
            return False
        if ev.kind == "alive" and ev.sat is not None:
            (self.alive.add if ev.alive else self.alive.discard)(ev.sat)
        elif ev.kind == "est":
            m = ev.msg
            plan_k = m.k if m.phase == "prior" else m.k + 1
            self.next_plan[m.own] = max(plan_k, self.next_plan.get(m.own, -1))
        elif ev.kind == "health":
            self.camera_ok[ev.msg.sat] = ev.msg.camera_ok
        elif ev.kind == "fault":
            f: Fault = ev.msg
            if f.action == "camera" and f.phase == "command" and f.target is not None and f.camera is not None:
                self.camera_ok[f.target, f.camera] = f.state == "on"
        elif ev.kind == "clock":
            self.clock_seen = True
            self.done = self.done or ev.msg.done
        return True

    def plan(self, k: int, ref: int, msg=None) -> None:
        sc = self.sc
        t0 = time.perf_counter()
        est = None
        if sc.selection.strategy in NEEDS_STATE:
            if msg is None:
                msg = self.query(self.keys.cov(ref), "full_est", timeout=sc.emulator.step_timeout_s)
            if msg is None:
                self.log.warning("step %d: agent %d did not serve its estimate", k, ref)
                return
            est = estimate_from_full(msg, self.n)
        cam_ok = self.camera_ok.copy()
        for i in range(self.n):
            if i not in self.alive:
                cam_ok[i] = False
        if est is None:
            from swarmcore.selection import select_for_scenario

            obs, tgt = select_for_scenario(sc, k, self.G, None, None, cam_ok)
        else:
            obs, tgt = choose_pairs(sc, k, self.G, est, self.params[ref], cam_ok)
        ms = (time.perf_counter() - t0) * 1e3
        self.put(
            self.keys.select(),
            select_msg(
                obs,
                tgt,
                run=self.run,
                sender=self.name,
                k=k,
                t_s=k * sc.dt_s,
                strategy=sc.selection.strategy,
                ref_agent=ref,
                select_ms=ms,
            ),
        )
        self.planned.add(k)

    def plan_first(self, ref: int) -> None:
        """Plan step 0 from the reference agent's prior, fetched rather than awaited: an
        agent publishes its prior once, when it initialises, and a selector that came up
        later (or whose subscription was still propagating) never sees it."""
        msg = self.query(self.keys.cov(ref), "full_est", timeout=2.0)
        if msg is None or msg.own != ref:
            return  # not initialised yet: its prior will arrive as an event, or we ask again
        if msg.k == 0 and not self.clock_seen:
            self.plan(0, ref, msg)

    def run_loop(self) -> None:
        if self.sc.selection.strategy == "none":
            self.log.info("the scenario takes every measurement of its graph: nothing to select")
        while not self.stop.is_set() and not self.done:
            if self.sc.selection.strategy == "none":
                self.pump(1.0)
                continue
            self.pump(0.5)
            # Plan from the reference agent's latest estimate only (the lowest live id).
            ref = self.ref_agent()
            if ref is not None and ref not in self.next_plan and not self.clock_seen and 0 not in self.planned:
                self.plan_first(ref)
                continue
            k = self.next_plan.get(ref, -1) if ref is not None else -1
            if 0 <= k < self.sc.steps and k not in self.planned:
                self.plan(k, ref)
