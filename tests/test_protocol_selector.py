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


def scenario() -> Scenario:
    return Scenario.model_validate({"name": "sel", "seed": 2, "n_sats": 4, "duration_s": 3,
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


def test_next_step_planned_from_the_lowest_live_agent_and_dead_observers_masked():
    sc = scenario()
    truth = initial_truth(sc)
    post = {i: initial_estimate(sc, truth, i) for i in range(4)}
    clock = FakeClock()
    s = SelectorProtocol(sc, RUN, clock=clock)
    d = Driver(s, clock, answer=lambda q: full_estimate_msg(post[int(q.key[-1])], run=RUN, sender="x", own=int(q.key[-1])))
    d.feed(alive(0), alive(1), alive(2), alive(3))
    d.feed(Event(K.clock(), "clock", None, msg=Clock(run=RUN, sender="world", k=0, t_s=0.0, live_agents=[0, 1, 2, 3])))
    d.take()
    d.feed(alive(0, up=False))
    d.feed(Event(K.est(1), "est", 1, msg=estimate_msg(post[1], run=RUN, sender="agent-1", own=1)))
    (sel,) = d.sent_on(K.select())
    assert sel.k == 1 and sel.ref_agent == 1
    assert all(o != 0 for o in sel.observer), "a dead satellite measures nothing"
