"""The selector's side of the protocol, as a bus-free state machine.

It plans step k from a reference agent's estimate — the lowest-numbered live agent —
exactly as the in-process simulator does (:func:`swarmcore.selection.choose_pairs`): the
agent's posterior at k−1 carried to k without its gyro (its prior at k = 0), fetched in
full from ``cov/<ref>``. Camera health and dead satellites remove candidates
(:func:`swarmcore.selection.mask_dead`).

In lockstep it plans step k when the world's clock of k comes, from what is fixed by the
steps themselves: the live agents of step k (the clock; the reference is the lowest of them,
every other satellite's cameras are off), and the cameras of each agent live at k − 1 and k
as its health report of step k − 1 gives them (the world's camera state at that step, which
the agent takes from its camera delivery); it waits for those reports. A selector started
during step k (a restart) plans from k + 1 (the world falls back at k): it heard neither the
clock nor the reports of k − 1. Planned earlier, on the reference's estimate of k − 1 and
with whatever commands and liveliness had arrived, a selection of k was made before or after
the faults of step k had been heard (a camera switched off, the reference killed, the
selector itself killed with its plan of k already sent or not; a command missed in a
failover and sent again later), and a chaos campaign's two runs differed (issue 35).
Whether its plan reaches the world in time must not depend on timing either: the plan of a
step is dropped as soon as the clock of a later step is in (taken in between the asks of the
reference, which block the loop), and a selector that (re)starts, whose bus or world comes
back, or that has heard no clock for ``CATCH_UP_S``, reads the world's last two clocks and
the agents' health reports of those steps (its ``clock`` and ``health/*`` queryables) rather
than wait for messages that went by while it was away (a clock will not come before its
selection); so does it every ``CATCH_UP_S`` while it waits for the reports of k − 1.
The reference of step k is always the lowest agent the clock of k lists live, asked again
until it serves or the world goes on, never whoever answers first.
Free-running, where nothing waits, it plans as soon as the reference's estimate or health
of k − 1 comes, with what it knows then (liveliness, commands and health reports).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np

from swarmcore.agent import filter_params
from swarmcore.graphs import scenario_graph
from swarmcore.scenario import Scenario
from swarmcore.selection import choose_pairs, mask_dead
from swarmrt.bus.convert import estimate_from_full, select_msg
from swarmrt.bus.messages import Fault, Keys
from swarmrt.protocol import Event, Outbox, Query, Send, Wait, WorldLost, outbox_steps, world_wait_s

__all__ = ["SelectorProtocol", "CATCH_UP_S"]

log = logging.getLogger("selector")

#: Lockstep: with no new clock for this long (s), the selector reads the world's latest
#: clocks (a clock lost on its way costs this, not the world's 20 s wait and a fallback).
CATCH_UP_S = 2.0
CATCH_UP_QUERY_S = 2.0


class SelectorProtocol:
    def __init__(self, sc: Scenario, run: str, clock: Callable[[], float] = time.monotonic, plans_from_estimate: bool = True):
        self.sc = sc
        # With an estimator that keeps no whole-swarm estimate (the decentralized ones fly
        # only state-free strategies), the selector plans without one, as the simulator does.
        self.plans_from_estimate = plans_from_estimate
        self.clock = clock
        self._startup_deadline = clock() + sc.emulator.startup_timeout_s
        self.n = sc.n_sats
        self.run_id = run
        self.keys = Keys(run)
        self.G = scenario_graph(sc)
        self.params = [filter_params(sc, i) for i in range(sc.n_sats)]
        self.camera_ok = np.ones((sc.n_sats, 6), dtype=bool)
        self.alive: set[int] = set()
        self.done = False
        self.planned: set[int] = set()
        self.next_plan: dict[int, int] = {}  # agent → the step its latest estimate lets us plan
        self.clock_seen = False  # the run has started
        self._asked_first: int | None = None  # the agent last asked for its step-0 prior
        self.world_seen = False
        self.outbox = Outbox(keep=outbox_steps(sc.emulator))  # the latest selections, sent again when the bus comes back
        self._clock_only: set[int] = set()  # steps known plannable from the world's clock alone (lockstep)
        self.lockstep = sc.emulator.time_mode == "lockstep"
        # Lockstep: each clock's live agents, and each step's health reports' cameras.
        self.steps: dict[int, list[int]] = {}
        self.cams_at: dict[int, dict[int, np.ndarray]] = {}
        # Lockstep: read the world's latest clocks (serve_clock) at once: at start (a restart),
        # when the bus or the world comes back, and when no clock has come for CATCH_UP_S.
        self._catch_up = self.lockstep
        self._clock_at = clock()  # when the latest new clock came

    def ref_agent(self) -> int | None:
        return min(self.alive) if self.alive else None

    def handle(self, ev: Event) -> list[Send]:
        if ev.kind in ("bus", "resync", "again"):
            if ev.kind == "again" or (ev.kind == "bus" and ev.alive) or (ev.kind == "resync" and ev.role == "world"):
                self._catch_up = self.lockstep  # a clock may have gone by meanwhile
            return self.outbox.again(ev)
        if ev.kind == "alive" and ev.role == "world":
            if ev.alive:
                self.world_seen = True
                self._catch_up = self.lockstep
            elif self.world_seen and not self.done:
                raise WorldLost("selector: the world is gone before the end of the run")
        elif ev.kind == "alive" and ev.role in (None, "agent") and ev.sat is not None:
            (self.alive.add if ev.alive else self.alive.discard)(ev.sat)
        elif ev.kind == "est":
            m = ev.msg
            plan_k = m.k if m.phase == "prior" else m.k + 1
            self.next_plan[m.own] = max(plan_k, self.next_plan.get(m.own, -1))
            self._clock_only.discard(plan_k)
        elif ev.kind == "health":
            self.camera_ok[ev.msg.sat] = ev.msg.camera_ok
            self.cams_at.setdefault(int(ev.msg.k), {})[int(ev.msg.sat)] = np.array(ev.msg.camera_ok, dtype=bool)
            # An agent's health report follows its update of step k (a drop fault loses its
            # estimate, never its health): step k + 1 can be planned from what it serves. With
            # the estimate alone a dropped one left the world waiting a step timeout for a plan.
            self.next_plan[ev.msg.sat] = max(int(ev.msg.k) + 1, self.next_plan.get(ev.msg.sat, -1))
            self._clock_only.discard(int(ev.msg.k) + 1)
        elif ev.kind == "fault":
            f: Fault = ev.msg
            if f.action == "camera" and f.phase == "command" and f.target is not None and f.camera is not None:
                self.camera_ok[f.target, f.camera] = f.state == "on"
        elif ev.kind == "clock":
            self.clock_seen = True
            self.done = self.done or ev.msg.done
            k = int(ev.msg.k)
            if self.lockstep and not ev.msg.done:
                # The step's own state: the selection of k is planned from it (the module's docstring).
                if k not in self.steps and (not self.steps or k > max(self.steps)):
                    self._clock_at = self.clock()
                self.steps.setdefault(k, sorted(int(i) for i in ev.msg.live_agents))
                for old in [s for s in self.steps if s < k - 2]:
                    del self.steps[old]
                for old in [s for s in self.cams_at if s < k - 2]:
                    del self.cams_at[old]
                return []
            ref = self.ref_agent()
            lockstep = self.sc.emulator.time_mode == "lockstep" and not ev.msg.done
            if lockstep and k >= 1 and ref is not None and self.next_plan.get(ref, -1) < k:
                # Lockstep: the world puts the clock of k only once every live agent has finished
                # k − 1, and then waits for the selection of k. So the clock alone says step k can
                # be planned from what the reference agent serves, even when its estimate and
                # health of k − 1 never reached us (sent into a router's restart and resent
                # before our subscriptions were back: CI saw the world wait 30 s and fall back).
                # What it serves must then be of k − 1 at least (see plan).
                self.next_plan[ref] = k
                self._clock_only.add(k)
        return []

    def plan(self, k: int, ref: int, msg=None, live=None, cams=None):
        """Plan step k from agent ``ref``'s estimate (``msg``, or asked for), masking the
        satellites not in ``live`` with cameras ``cams`` (default: what this selector knows
        now: liveliness, commands and health reports)."""
        sc = self.sc
        live = self.alive if live is None else live
        cams = self.camera_ok if cams is None else cams
        behind = k in self._clock_only or (self.lockstep and k in self.steps)
        t0 = time.perf_counter()
        est = None
        # Every strategy plans from the reference estimate when there is one, as in the
        # simulator: a state-free one (random, random_tree) still uses it to keep only the
        # pairs the estimate says are visible. Only the world's fallback plans without.
        # Asked again after a short timeout rather than once for long: a query whose way
        # went with a router (killed, a client failing over) never gets its reply, and the
        # world takes the selection only select_timeout_s after the bus is back.
        em = sc.emulator
        if not self.plans_from_estimate:
            obs, tgt = choose_pairs(sc, k, self.G, None, None, mask_dead(cams, live))
            self.outbox.clear()
            yield Send(self.keys.select(), select_msg(obs, tgt, run=self.run_id, sender="selector", k=k, t_s=k * sc.dt_s,
                                                      strategy=sc.selection.strategy, ref_agent=ref,
                                                      select_ms=(time.perf_counter() - t0) * 1e3))
            self.planned.add(k)
            return
        deadline = self.clock() + em.step_timeout_s
        while msg is None:
            # What arrived meanwhile is taken in between asks (a query blocks the loop): a
            # clock of a later step means the world has left k, and the plan of k is dropped.
            # (Seen: a restarted selector asked a reference that had been stopped for a step
            # the world had left, again and again, the clocks of the next steps unread in its
            # inbox; the world waited 20 s and fell back, in one run of a campaign: issue 35.)
            if self._newer(k):
                log.info("step %d: the world has gone on to step %d; not planned", k, max(self.steps, default=k))
                return
            msg = yield Query(self.keys.cov(ref), "full_est", min(em.step_timeout_s, max(0.5, em.select_timeout_s / 2)))
            if msg is not None and behind and msg.k < k - 1:
                # Planned on the clock alone, and the reference is still behind (a world that
                # moved on without its estimate: stalled, say): not its estimate of k − 1 yet.
                msg = None
                yield Wait(lambda: self._newer(k) or not (k in self._clock_only or (self.lockstep and k in self.steps)), 0.2)
            elif msg is None:
                # Not served (the reference stalled, or gone: a query with no queryable comes
                # back at once): asked again shortly, the same agent (the step's reference is
                # the world's choice, not whoever answers first).
                yield Wait(lambda: self._newer(k), 0.2)
            if msg is None and (self.clock() >= deadline or self.done):
                break
        if msg is None:
            if not self._newer(k):
                log.warning("step %d: agent %d did not serve its estimate", k, ref)
            return
        est = estimate_from_full(msg, self.n)
        obs, tgt = choose_pairs(sc, k, self.G, est, self.params[ref], mask_dead(cams, live))
        ms = (time.perf_counter() - t0) * 1e3
        self.outbox.clear()
        yield Send(self.keys.select(), select_msg(obs, tgt, run=self.run_id, sender="selector", k=k, t_s=k * sc.dt_s,
                                                  strategy=sc.selection.strategy, ref_agent=ref, select_ms=ms))
        self.planned.add(k)

    def plan_first(self, ref: int):
        """Plan step 0 from the reference agent's prior, fetched rather than awaited: an
        agent publishes its prior once, when it initialises, and a selector that came up
        later (or whose subscription was still propagating) never sees it."""
        self._asked_first = ref
        if not self.plans_from_estimate:
            if not self.clock_seen:
                yield from self.plan(0, ref)
            return
        msg = yield Query(self.keys.cov(ref), "full_est", 2.0)
        if msg is None or msg.own != ref:
            return  # not initialised yet: its prior will arrive as an event, or we ask again
        if msg.k == 0 and not self.clock_seen:
            yield from self.plan(0, ref, msg)

    def _newer(self, k: int) -> bool:
        """Lockstep: whether the world has put the clock of a step after k (or the run is over)."""
        return self.done or (self.lockstep and bool(self.steps) and max(self.steps) > k)

    def _catch_up_due(self) -> bool:
        if not self.lockstep or self.done:
            return False
        return self._catch_up or (bool(self.steps) and self.clock() - self._clock_at >= CATCH_UP_S)

    def catch_up(self):
        """Read the world's last two clocks (its ``clock`` queryable) and the agents' health
        reports of those steps (``health/*``, which the world keeps) as if they had come: a
        selector that (re)started, or whose bus or world came back, has the step the world
        waits for it to plan, and what it plans it from, without waiting for messages that
        went by while it was away (the next clock would never come: the world waits for this
        step's selection; nor would reports put while it failed over to another router)."""
        self._catch_up = False
        self._clock_at = self.clock()
        for m in (yield Query(self.keys.clock(), "clock", CATCH_UP_QUERY_S, every=True)) or []:
            self.handle(Event(self.keys.clock(), "clock", None, msg=m))
        for h in (yield Query(self.keys.health(), "health", CATCH_UP_QUERY_S, every=True)) or []:
            self.handle(Event(self.keys.health(int(h.sat)), "health", int(h.sat), msg=h))

    def run(self):
        return self.outbox.wrap(self._run())

    def _run(self):
        if self.sc.selection.strategy == "none":
            log.info("the scenario takes every measurement of its graph: nothing to select")
            yield Wait(lambda: self.done, float("inf"))
            return
        while not self.done:
            if self._catch_up_due():
                yield from self.catch_up()
            # Wake for work, or for step 0 once a new reference agent appears (asking the same
            # one again is paced by the timeout), or to read the world's clock.
            yield Wait(lambda: self.done or self._work() is not None or (self._first_pending() and self.ref_agent() != self._asked_first)
                       or self._catch_up, 0.5)
            if self.lockstep and self.steps:
                # The run is under way: plan the step of the latest clock, from its own state.
                k = self._work()
                if k is None:
                    continue
                live = self.steps[k]
                if not live:
                    self.planned.add(k)  # no live agent to plan from: the world falls back
                    continue
                if k == 0:
                    yield from self.plan(0, min(live), live=live, cams=np.ones((self.n, 6), dtype=bool))
                    continue
                need = [i for i in live if i in self.steps[k - 1]]

                def reported(k: int = k, need: list[int] = need) -> bool:
                    return self.done or max(self.steps) > k or all(i in self.cams_at.get(k - 1, {}) for i in need)

                # Waited for as the world waits (world_wait_s), in spans of CATCH_UP_S with the
                # world's reports read in between: one missed (put while this selector failed
                # over) is read from the world rather than waited for until the world falls back.
                got, waited, total = False, 0.0, world_wait_s(self.sc.emulator)
                while True:
                    span = min(CATCH_UP_S, total - waited)
                    got = yield Wait(reported, span)
                    if got or self.done or max(self.steps) > k:
                        break
                    waited += span  # (a span that timed out: the node stretches it while the bus is down)
                    if waited >= total:
                        break
                    yield from self.catch_up()
                if self.done or max(self.steps) > k:
                    continue  # a newer step to plan
                if not got:
                    log.warning("step %d: no health report of step %d from %s; their cameras taken as on", k, k - 1,
                                [i for i in need if i not in self.cams_at.get(k - 1, {})])
                cams = np.ones((self.n, 6), dtype=bool)
                for i, ok in self.cams_at.get(k - 1, {}).items():
                    if i in need:
                        cams[i] = ok
                yield from self.plan(k, min(live), live=live, cams=cams)
                continue
            # Plan from the reference agent's latest estimate only (the lowest live id).
            ref = self.ref_agent()
            if ref is None:
                continue
            if self._first_pending():
                yield from self.plan_first(ref)
                continue
            k = self._work()
            if k is not None:
                yield from self.plan(k, ref)

    def _first_pending(self) -> bool:
        """Step 0 is still to plan, the reference agent's prior has not been heard, and the
        reference is settled: every agent is up (so it is the one the in-process simulator
        plans with), or the start-up allowance is over."""
        ref = self.ref_agent()
        settled = len(self.alive) == self.n or self.clock() > self._startup_deadline
        return ref is not None and settled and ref not in self.next_plan and not self.clock_seen and 0 not in self.planned

    def _work(self):
        """The step there is something to plan for now, if any (step 0 only once the
        reference is settled, as for :meth:`_first_pending`; in lockstep, once the run is
        under way, the step of the latest clock)."""
        if self.lockstep and self.steps:
            k = max(self.steps)
            if k == 0 and 0 not in self.planned:
                return 0  # (step 0 not planned before its clock: from the reference's prior)
            return k if 0 < k < self.sc.steps and k - 1 in self.steps and k not in self.planned else None
        ref = self.ref_agent()
        if ref is None:
            return None
        k = self.next_plan.get(ref, -1)
        if k == 0 and not (len(self.alive) == self.n or self.clock() > self._startup_deadline or self.clock_seen):
            return None
        if self.lockstep and k != 0:
            return None  # lockstep: a step after the first only from its clock (a restarted selector that missed one waits)
        return k if 0 <= k < self.sc.steps and k not in self.planned else None
