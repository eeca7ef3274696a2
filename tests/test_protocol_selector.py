"""The selector's protocol, driven without a bus."""

from __future__ import annotations

from protocol_driver import Driver, FakeClock

from selector.protocol import SelectorProtocol
from swarmcore.scenario import Scenario
from swarmcore.world import initial_estimate, initial_truth
from swarmrt.bus.convert import estimate_msg, full_estimate_msg
from swarmrt.bus.messages import Clock, Keys
from swarmrt.protocol import Event, Query

RUN = "t"
K = Keys(RUN)


def scenario(time_mode: str = "lockstep") -> Scenario:
    return Scenario.model_validate({"name": "sel", "seed": 2, "n_sats": 4, "duration_s": 3, "emulator": {"time_mode": time_mode},
                                    "selection": {"strategy": "greedy", "budget": 3}})


def alive(i: int, up: bool = True) -> Event:
    return Event(K.alive("agent", i), "alive", i, alive=up, role="agent")


def test_step_zero_is_planned_from_agent_zero_once_every_agent_is_up():
    """In-process, step 0 is planned from satellite 0's prior; the selector must not plan
    it from whichever agent happened to come up first."""
    sc = scenario()
    truth = initial_truth(sc)
    priors = {i: initial_estimate(sc, truth, i) for i in range(4)}
    clock = FakeClock()

    def answer(q: Query):
        i = int(q.key.rsplit("/", 1)[1])
        return full_estimate_msg(priors[i], run=RUN, sender=f"agent-{i}", own=i)

    s = SelectorProtocol(sc, RUN, clock=clock)
    d = Driver(s, clock, answer=answer)
    d.feed(alive(3), Event(K.est(3), "est", 3, msg=estimate_msg(priors[3], run=RUN, sender="agent-3", own=3, phase="prior")))
    d.elapse(1.0)
    assert not d.sent_on(K.select()), "agent 3 alone is not the reference of step 0"
    d.feed(alive(0), alive(1), alive(2))
    (sel,) = d.sent_on(K.select())
    assert sel.k == 0 and sel.ref_agent == 0 and len(sel.observer) == 3
    assert [q.key for q in d.queries][-1] == K.cov(0)


def _running_selector(sc: Scenario | None = None):
    """A selector of the four agents, past step 0's clock, every agent serving its initial
    estimate: (driver, what each agent serves: replace an entry to serve another)."""
    sc = sc or scenario()
    truth = initial_truth(sc)
    post = {i: initial_estimate(sc, truth, i) for i in range(4)}
    clock = FakeClock()
    s = SelectorProtocol(sc, RUN, clock=clock)
    d = Driver(s, clock, answer=lambda q: full_estimate_msg(post[int(q.key[-1])], run=RUN, sender="x", own=int(q.key[-1])))
    d.feed(alive(0), alive(1), alive(2), alive(3))
    d.feed(Event(K.clock(), "clock", None, msg=Clock(run=RUN, sender="world", k=0, t_s=0.0, live_agents=[0, 1, 2, 3])))
    d.take()
    return d, post


def clock(k: int, live) -> Event:
    return Event(K.clock(), "clock", None, msg=Clock(run=RUN, sender="world", k=k, t_s=float(k), live_agents=list(live)))


def test_next_step_planned_from_the_lowest_live_agent_and_dead_observers_masked():
    """Lockstep: step k is planned when its clock comes, from the agents it lists live (the
    reference is the lowest of them; the others' cameras are off)."""
    d, post = _running_selector()
    d.feed(alive(0, up=False))
    d.feed(Event(K.est(1), "est", 1, msg=estimate_msg(post[1], run=RUN, sender="agent-1", own=1)))
    d.feed(*(_health(i, 0) for i in range(4)))
    assert not d.sent_on(K.select()), "lockstep: nothing is planned before the step's clock"
    d.feed(clock(1, [1, 2, 3]))
    (sel,) = d.sent_on(K.select())
    assert sel.k == 1 and sel.ref_agent == 1 and [q.key for q in d.queries][-1] == K.cov(1)
    assert all(o != 0 for o in sel.observer), "a dead satellite measures nothing"


def _health(i: int, k: int, off=()) -> Event:
    from swarmrt.bus.messages import Health

    cams = [c not in off for c in range(6)]
    return Event(K.health(i), "health", i, msg=Health(run=RUN, sender=f"agent-{i}", k=k, t_s=float(k), sat=i, camera_ok=cams, host="h"))


def _plan_of_step_1(order: str):
    """Agent 0 (the reference) killed at step 1; camera 2 of satellite 1 off at step 0, as its
    health report of step 0 says; a camera command of step 1 and a stale one sent again: the
    selection of step 1, the events in ``order``."""
    from swarmrt.bus.messages import Fault

    d, post = _running_selector()
    est = Event(K.est(0), "est", 0, msg=estimate_msg(post[0], run=RUN, sender="agent-0", own=0))
    cam = Event(K.fault(), "fault", None, msg=Fault(run=RUN, sender="world", k=1, t_s=1.0, phase="command", action="camera",
                                                    target=3, camera=1, state="off"))
    stale = Event(K.fault(), "fault", None, msg=Fault(run=RUN, sender="world", k=0, t_s=0.0, phase="command", action="camera",
                                                      target=2, camera=3, state="off"))
    events = {"est": est, "cam": cam, "stale": stale, "dead": alive(0, up=False), "clock": clock(1, [1, 2, 3]),
              "health": [_health(1, 0, off=(2,)), _health(2, 0), _health(3, 0), _health(0, 0)]}
    for name in order.split():
        e = events[name]
        d.feed(*(e if isinstance(e, list) else [e]))
    (sel,) = d.sent_on(K.select())
    return sel


def test_the_plan_of_a_step_does_not_depend_on_when_its_faults_were_heard():
    """Issue 35: a chaos campaign's two runs planned step 2 differently: planned on the
    reference's estimate of the step before, a selection was made before or after the step's
    faults (the selector killed, a camera off, the reference killed) had reached the
    selector. Now it is planned when the step's clock comes, from the agents it lists live
    and the cameras of their health reports of the step before (waited for): whatever the
    order the reference's estimate, fault commands (a stale one sent again after a failover
    among them), liveliness and reports came in, the same selection."""
    orders = ["est cam dead health clock", "cam est clock dead health", "health dead cam stale est clock",
              "clock cam stale dead est health", "stale health clock"]
    sels = [_plan_of_step_1(o) for o in orders]
    for sel in sels:
        assert (sel.k, sel.ref_agent) == (1, 1)
        assert list(sel.observer) == list(sels[0].observer) and list(sel.target) == list(sels[0].target)
        assert all(o != 0 for o in sel.observer)


def test_the_plan_waits_for_the_health_reports_of_the_step_before():
    """The cameras it plans with are those of the live agents' reports of the step before:
    until every one of them is in, nothing is planned."""
    d, _post = _running_selector()
    d.feed(clock(1, [0, 1, 2, 3]), _health(0, 0), _health(1, 0))
    assert not d.sent_on(K.select())
    d.feed(_health(2, 0), _health(3, 0, off=(0, 1, 2, 3, 4, 5)))
    (sel,) = d.sent_on(K.select())
    assert sel.k == 1 and all(o != 3 for o in sel.observer), "satellite 3's cameras are all off"


def test_a_selector_started_during_a_step_plans_from_the_next():
    """Started during step k (a restart), it heard neither the clock nor the reports of k − 1:
    it plans k + 1, not k, whatever old clocks it is sent again."""
    sc = scenario()
    truth = initial_truth(sc)
    post = {i: initial_estimate(sc, truth, i) for i in range(4)}
    import dataclasses

    post = {i: dataclasses.replace(e, step=2, t=2.0) for i, e in post.items()}  # every agent has finished step 2
    clk = FakeClock()
    s = SelectorProtocol(sc, RUN, clock=clk)
    d = Driver(s, clk, answer=lambda q: full_estimate_msg(post[int(q.key[-1])], run=RUN, sender="x", own=int(q.key[-1])))
    d.feed(alive(0), alive(1), alive(2), alive(3))
    d.feed(clock(2, [0, 1, 2, 3]))
    assert not d.sent_on(K.select()), "no clock of step 1: step 2 is not planned"
    d.feed(clock(0, [0, 1, 2, 3]), clock(1, [0, 1, 2, 3]))  # old clocks sent again (a failover)
    assert not d.sent_on(K.select()), "nor are old steps"
    d.feed(*(_health(i, 2) for i in range(4)))
    d.feed(clock(3, [0, 1, 2, 3]))
    (sel,) = d.sent_on(K.select())
    assert sel.k == 3


def test_a_dropped_estimate_of_the_reference_agent_does_not_hold_the_plan():
    """Free-running: a drop fault loses the reference agent's estimate of step k but never
    its health report, which also follows its update: step k + 1 is planned from what it
    serves, at once (with the estimate alone the world waited a whole step timeout, then
    fell back)."""
    from swarmrt.bus.messages import Health

    d, _post = _running_selector(scenario("free"))
    health = Health(run=RUN, sender="agent-0", k=0, t_s=0.0, sat=0, camera_ok=[True] * 6, drop_rate=0.5, host="h")
    d.feed(Event(K.health(0), "health", 0, msg=health))
    (sel,) = d.sent_on(K.select())
    assert sel.k == 1 and sel.ref_agent == 0 and [q.key for q in d.queries][-1] == K.cov(0)


def test_the_clock_of_a_step_is_enough_to_plan_it_in_lockstep():
    """A router restart can lose the reference agent's estimate of step k − 1 (sent into the
    gap, resent before the selector's subscriptions were back). In lockstep the world puts
    the clock of k only once every live agent has finished k − 1: the clock and the agents'
    reports of k − 1 (which every agent sends again when the selector's token comes back) let
    the selector plan k from what the reference agent serves (CI saw the world wait 30 s for
    a selection that never came, then fall back, changing the schedule)."""
    d, _post = _running_selector()
    assert not d.sent_on(K.select())
    d.feed(*(_health(i, 0) for i in range(4)))
    d.feed(Event(K.clock(), "clock", None, msg=Clock(run=RUN, sender="world", k=1, t_s=1.0, live_agents=[0, 1, 2, 3])))
    (sel,) = d.sent_on(K.select())
    assert sel.k == 1 and sel.ref_agent == 0 and [q.key for q in d.queries][-1] == K.cov(0)
    # Its estimate arriving afterwards plans nothing twice.
    d.take()
    d.feed(Event(K.est(0), "est", 0, msg=estimate_msg(_post[0], run=RUN, sender="agent-0", own=0)))
    assert not d.sent_on(K.select())


def test_free_running_the_clock_alone_plans_nothing():
    """Free-running, the clock does not wait for the agents: a step is planned only from
    the reference agent's own estimate or health of the step before."""
    d, _post = _running_selector(scenario("free"))
    d.feed(Event(K.clock(), "clock", None, msg=Clock(run=RUN, sender="world", k=1, t_s=1.0, live_agents=[0, 1, 2, 3])))
    assert not d.sent_on(K.select())


def test_a_reference_still_behind_is_waited_for():
    """The world moved on to step 2 without the reference agent's estimate of step 1 (a
    stalled agent past the step timeout): its report of step 1 has not come and what it
    serves is of step 0, so the selector does not plan from it; once it has finished step 1
    (its report, and what it serves), it plans."""
    import dataclasses

    d, served = _running_selector()  # every agent serves its estimate of step 0
    d.feed(clock(1, [0, 1, 2, 3]), clock(2, [0, 1, 2, 3]), *(_health(i, 1) for i in (1, 2, 3)))
    d.elapse(1.0)
    assert not [s for s in d.sent_on(K.select()) if s.k == 2]
    served[0] = dataclasses.replace(served[0], step=1, t=1.0)  # it finished step 1
    d.feed(_health(0, 1))
    (sel,) = [s for s in d.sent_on(K.select()) if s.k == 2]
    assert sel.ref_agent == 0 and d.queries[-1].key == K.cov(0)


def _longer() -> Scenario:
    return Scenario.model_validate({"name": "sel", "seed": 2, "n_sats": 4, "duration_s": 12, "emulator": {"time_mode": "lockstep"},
                                    "selection": {"strategy": "greedy", "budget": 3}})


def _served_at(sc: Scenario, step: int) -> dict:
    import dataclasses

    truth = initial_truth(sc)
    return {i: dataclasses.replace(initial_estimate(sc, truth, i), step=step, t=float(step)) for i in range(sc.n_sats)}


def test_a_plan_for_a_step_the_world_has_left_is_dropped_for_the_newer_clock():
    """Issue 35 (seed 1 of the repeat benchmark): a selector planning step 1 asked its
    reference, agent 0, which had just been stopped (its next step's fault), for a step the
    world had left; the clock of step 2 came while it was asking (a query blocks the loop) and
    sat unread in its inbox: the plan of step 1 was tried again and again, and the world,
    waiting for the selection of step 2, fell back after 20 s in one run of the campaign and
    not in the other. The plan of a step is dropped as soon as a clock of a later step is in;
    step 2 is planned from its own reference (agent 1, the lowest the clock lists live)."""
    sc = _longer()
    served = _served_at(sc, 1)
    clk = FakeClock()
    asked_0 = []
    stopped = []

    def answer(q: Query):
        i = int(q.key.rsplit("/", 1)[1])
        clk.t += q.timeout_s  # (the query's wait)
        if i != 0 or not stopped:
            return full_estimate_msg(served[i], run=RUN, sender=f"agent-{i}", own=i)
        asked_0.append(q)
        assert len(asked_0) < 50, "still asking the stopped agent 0 for step 1, with the clock of step 2 in"
        if len(asked_0) == 1:  # what came meanwhile: the world went on (agent 0 stopped at step 2)
            d.arrive(clock(2, [1, 2, 3]), *(_health(i, 1) for i in (1, 2, 3)))
        return None

    s = SelectorProtocol(sc, RUN, clock=clk)
    d = Driver(s, clk, answer=answer)
    d.feed(alive(0), alive(1), alive(2), alive(3))
    d.feed(clock(0, [0, 1, 2, 3]))
    assert [s.k for s in d.sent_on(K.select())] == [0]
    d.take()
    stopped.append(0)
    d.feed(*(_health(i, 0) for i in range(4)), clock(1, [0, 1, 2, 3]))
    (sel,) = d.sent_on(K.select())
    assert (sel.k, sel.ref_agent) == (2, 1) and all(o != 0 for o in sel.observer)
    assert len(asked_0) == 1


def test_a_restarted_selector_reads_the_current_clock_rather_than_wait_for_the_next():
    """A selector that starts while the run is under way (a restart), whose subscriptions
    missed the clocks of the steps so far, reads the world's last two clocks (its ``clock``
    queryable) and plans the step the world waits for: no clock would come before it does."""
    sc = _longer()
    served = _served_at(sc, 4)
    clk = FakeClock()
    s = SelectorProtocol(sc, RUN, clock=clk)
    d = Driver(s, clk, answer=lambda q: full_estimate_msg(served[int(q.key[-1])], run=RUN, sender="x", own=int(q.key[-1])),
               clocks=lambda q: [clock(4, [0, 1, 2, 3]).msg, clock(5, [0, 1, 2, 3]).msg])
    assert [q.key for q in d.clock_queries] == [K.clock()] and d.clock_queries[0].every
    d.feed(alive(0), alive(1), alive(2), alive(3), *(_health(i, 4) for i in range(4)))
    (sel,) = d.sent_on(K.select())
    assert (sel.k, sel.ref_agent) == (5, 0)


def test_the_clock_is_read_again_when_the_bus_or_the_world_comes_back_or_none_came_for_a_while():
    """A clock lost on its way (put while a router was down) is read from the world: when this
    selector's bus comes back, when the world's token comes back, and after CATCH_UP_S with no
    new clock."""
    from selector.protocol import CATCH_UP_S

    d, _post = _running_selector()
    n = len(d.clock_queries)
    d.feed(Event("", "bus", None, alive=True))
    d.elapse(0.5)
    assert len(d.clock_queries) == n + 1
    d.feed(Event(K.alive("world", 0), "resync", None, role="world"))
    d.elapse(0.5)
    assert len(d.clock_queries) == n + 2
    d.elapse(CATCH_UP_S)
    assert len(d.clock_queries) == n + 3


def test_the_reference_of_a_step_is_the_clocks_lowest_live_agent_whoever_answers():
    """Lockstep: the agent asked for step k's estimate is the lowest the clock of k lists
    live, whatever tokens this selector has seen go or come (the order of arrival): a
    reference that does not answer (stalled) is asked again, never replaced by another."""
    sc = _longer()
    served = _served_at(sc, 0)
    clk = FakeClock()
    stalled = {0}

    def answer(q: Query):
        i = int(q.key.rsplit("/", 1)[1])
        clk.t += q.timeout_s
        assert len(d.queries) < 50, "asked again and again without a pause"
        return None if i in stalled else full_estimate_msg(served[i], run=RUN, sender=f"agent-{i}", own=i)

    s = SelectorProtocol(sc, RUN, clock=clk)
    d = Driver(s, clk, answer=answer)
    d.feed(alive(0), alive(1), alive(2), alive(3))
    d.feed(clock(0, [0, 1, 2, 3]))
    d.take()
    d.feed(alive(0, up=False), *(_health(i, 0) for i in range(4)), clock(1, [0, 1, 2, 3]))
    for _ in range(5):
        d.elapse(0.2)
    assert not d.sent_on(K.select()) and {q.key for q in d.queries[-5:]} == {K.cov(0)}
    stalled.clear()
    d.elapse(0.2)
    (sel,) = d.sent_on(K.select())
    assert (sel.k, sel.ref_agent) == (1, 0)


def test_health_reports_missed_in_a_failover_are_read_from_the_world():
    """Issue 35 (seed 10 of the repeat benchmark): a selector failing over to the other router
    missed the clock of step 23 and the agents' reports of step 22 (put while it was away);
    the clock it read from the world, the reports it waited for 20 s, as long as the world
    waits for its selection, and the world fell back in one run and not the other. The world
    has every report of k − 1 before it puts the clock of k and serves them (``health/*``):
    the selector reads them with the clocks and plans, with the cameras they give."""
    sc = _longer()
    served = _served_at(sc, 1)
    clk = FakeClock()
    reports = [_health(i, 1, off=(0, 1, 2, 3, 4, 5) if i == 3 else ()).msg for i in range(4)]
    world_at = []  # the step the world is at (it serves the reports of step 1 once at step 2)
    s = SelectorProtocol(sc, RUN, clock=clk)
    d = Driver(s, clk, answer=lambda q: full_estimate_msg(served[int(q.key[-1])], run=RUN, sender="x", own=int(q.key[-1])),
               reports=lambda q: reports if world_at else [])
    d.feed(alive(0), alive(1), alive(2), alive(3))
    world_at.append(2)
    d.feed(clock(1, [0, 1, 2, 3]), clock(2, [0, 1, 2, 3]))  # no report of step 1 comes
    d.elapse(1.0)
    assert not d.sent_on(K.select())
    d.elapse(1.5)  # CATCH_UP_S: the reports are read from the world
    (sel,) = d.sent_on(K.select())
    assert (sel.k, sel.ref_agent) == (2, 0) and all(o != 3 for o in sel.observer), "satellite 3's cameras are all off"
    assert [q.key for q in d.report_queries][-1] == K.health() and d.report_queries[-1].every
