"""An agent's lockstep protocol, driven without a bus: events in, messages out.

The world side of each step is computed with the core (truth, sensors, synthetic
cameras), so the agent's posterior can be held against the same filter run directly."""

from __future__ import annotations

import numpy as np
import pytest
from protocol_driver import Driver, FakeClock

from sat_agent.protocol import AgentProtocol
from swarmcore.agent import AgentFilter, SyntheticPoseEstimator, filter_params
from swarmcore.estimators import builtin_estimator
from swarmcore.graphs import scenario_graph
from swarmcore.mekf import RelativeMeasurements
from swarmcore.scenario import Scenario
from swarmcore.world import SyntheticCameras, absolute_measurements, initial_estimate, initial_truth, step_truth, world_params
from swarmrt.bus.convert import batch_msg, detections, full_estimate_msg, sensors_msg, step_batches_msg
from swarmrt.bus.messages import CameraOutput, Clock, Fault, Keys
from swarmrt.protocol import Event, Query

RUN = "t"
K = Keys(RUN)


def scenario(**over) -> Scenario:
    base = {"name": "proto", "seed": 4, "n_sats": 3, "duration_s": 5, "graph": {"kind": "complete"}}
    base.update(over)
    return Scenario.model_validate(base)


class WorldScript:
    """Truth and what every satellite's sensors and cameras deliver, step by step."""

    def __init__(self, sc: Scenario):
        self.sc = sc
        self.wp = world_params(sc)
        self.truth = initial_truth(sc)
        self.G = scenario_graph(sc)
        self.cams = SyntheticCameras(self.wp)
        self.gyro = None

    def advance(self, k: int) -> None:
        if k > 0:
            self.truth, self.gyro = step_truth(self.wp, self.truth)

    def events_for(self, i: int, k: int, live=(0, 1, 2), off=()) -> list[Event]:
        t = self.truth.t
        absm = absolute_measurements(self.wp, self.truth)
        obs, tgt = np.nonzero(self.G & ~np.eye(self.sc.n_sats, dtype=bool))
        seen = self.cams.observe(self.truth, obs, tgt)
        clock = Clock(run=RUN, sender="world", k=k, t_s=t, live_agents=list(live))
        sens = sensors_msg(run=RUN, k=k, t_s=t, sat=i, gyro=None if self.gyro is None else self.gyro[i], absm=absm[i],
                           sigma_star=self.wp.star_sigma, sigma_gps=self.wp.gps_sigma)
        dets = [d for d in detections(seen[i]) if d.camera not in off]
        cam = CameraOutput(run=RUN, sender="world", k=k, t_s=t, sat=i, detections=dets, cameras_off=list(off))
        return [Event(K.clock(), "clock", None, msg=clock), Event(K.sensors(i), "sensors", i, msg=sens), Event(K.cam(i), "cam", i, msg=cam)]

    def batch(self, j: int, k: int):
        obs, tgt = np.nonzero(self.G & ~np.eye(self.sc.n_sats, dtype=bool))
        rel, cams = SyntheticPoseEstimator(self.sc).measure(j, self.cams.observe(self.truth, obs, tgt)[j])
        return batch_msg(rel, cams, run=RUN, sender=f"agent-{j}", k=k, t_s=self.truth.t, observer=j)


def prior_answer(sc: Scenario, truth0):
    def answer(q: Query):
        i = int(q.key.rsplit("/", 1)[1])
        return full_estimate_msg(initial_estimate(sc, truth0, i), run=RUN, sender="world", own=i)

    return answer


def radio_event(k: int, batches) -> Event:
    """What the ideal radio (the world) delivers of step k: ``batches``, in one message."""
    return Event(K.batches(), "batches", None, msg=step_batches_msg(list(batches), run=RUN, k=k, t_s=float(k)))


def test_agent_steps_equal_the_filter_run_directly():
    """Three steps of agent 0 fed by the world and two peers give, bit for bit, the
    posterior of the same AgentFilter calls made directly (what ``swarm sim`` does)."""
    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    assert [q.key for q in d.queries] == [K.init(0)]
    (prior,) = d.sent_on(K.est(0))
    assert prior.phase == "prior" and prior.k == 0
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True), Event(K.alive("agent", 2), "alive", 2, alive=True))
    ref = AgentFilter(filter_params(sc, 0), initial_estimate(sc, world.truth, 0), sc.filter.mode)
    for k in range(3):
        world.advance(k)
        d.take()
        d.feed(*world.events_for(0, k))
        (own,) = d.sent_on(K.meas(0))
        assert own.k == k and sorted(own.target) == [1, 2]
        assert not d.sent_on(K.est(0)), "the agent waits for the radio's batches"
        peers = [world.batch(1, k), world.batch(2, k)]
        d.feed(radio_event(k, [peers[1], own, peers[0]]))
        (est,) = d.sent_on(K.est(0))
        (health,) = d.sent_on(K.health(0))
        assert est.k == k and est.batches_used == [1, 2] and health.batches_missing == 0
        from swarmrt.bus.convert import relative_from_batches

        rel = RelativeMeasurements.concat([relative_from_batches([own]), relative_from_batches(peers)])
        absm = absolute_measurements(world.wp, world.truth)[0]
        ref.step(k, None if world.gyro is None else world.gyro[0], absm, rel)
        np.testing.assert_array_equal(np.asarray(est.q_BI).reshape(-1, 4), ref.est.q_BI)
        np.testing.assert_array_equal(np.asarray(est.r_H_m).reshape(-1, 3), ref.est.r_H)
        np.testing.assert_array_equal(a.est.P, ref.est.P)


def test_cov_serves_the_last_posterior_not_the_prior_of_the_step_under_way():
    """What cov/<i> serves (the selector plans step k from it; a restarted peer starts from
    it) is the estimate at the end of the agent's last step: once the clock and sensors of
    the next step have come and the agent has predicted, still the posterior, as the
    simulator plans from it (a query that came after the clock got the prior of the new
    step; the greedy schedule then differed, seen in CI after a router restart)."""
    from swarmrt.bus.convert import estimate_from_full

    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    assert a.serve_cov(K.cov(0)).k == 0  # before its first step: its prior of step 0
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True), Event(K.alive("agent", 2), "alive", 2, alive=True))
    world.advance(0)
    d.feed(*world.events_for(0, 0))
    d.feed(radio_event(0, [world.batch(1, 0), world.batch(2, 0)]))
    posterior = a.est
    world.advance(1)
    d.feed(*world.events_for(0, 1))  # step 1 under way: predicted, its batch sent, waiting for the radio
    assert d.sent_on(K.meas(0))[-1].k == 1 and a.est.step == 1 and a.est is not posterior
    served = estimate_from_full(a.serve_cov(K.cov(0)), sc.n_sats)
    assert served.step == 0
    np.testing.assert_array_equal(served.P, posterior.P)
    np.testing.assert_array_equal(served.r_H, posterior.r_H)


def test_a_batch_the_radio_did_not_carry_is_missing_and_a_late_one_is_counted():
    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True), Event(K.alive("agent", 2), "alive", 2, alive=True))
    world.advance(0)
    d.feed(*world.events_for(0, 0))
    (own,) = d.sent_on(K.meas(0))
    d.feed(radio_event(0, [own, world.batch(1, 0)]))  # 2's batch did not reach the radio (dead, or lost)
    est = d.sent_on(K.est(0))[-1]
    assert est.phase == "posterior" and est.batches_missing == [2] and est.batches_used == [1]
    d.feed(radio_event(0, [world.batch(2, 0)]))  # step 0 is done: too late
    assert a.batches_late == 1


def test_the_agent_waits_for_the_radio_not_for_a_timeout():
    sc = scenario(emulator={"step_timeout_s": 10.0})
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True))  # 2 never comes up
    world.advance(0)
    d.feed(*world.events_for(0, 0))
    d.elapse(9.0)
    assert d.sent_on(K.est(0))[-1].phase == "prior", "no update before the radio's message of the step"
    d.feed(radio_event(0, [world.batch(1, 0)]))
    est = d.sent_on(K.est(0))[-1]
    assert est.phase == "posterior" and est.batches_missing == [2]


def test_restarted_agent_initialises_from_the_freshest_peer():
    """It asks every other satellite's agent at once, whichever tokens it has heard of (a
    dead one answers nothing); one that is stalled is waited for (the world's wait for a
    step's message), not given up on after a few seconds."""
    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    peer_est = initial_estimate(sc, world.truth, 1)

    def answer(q: Query):
        assert q.timeout_s >= 15.0, "a stalled peer (up to 6 s in a campaign) is waited for"
        return full_estimate_msg(peer_est, run=RUN, sender="agent-1", own=1) if q.key == K.cov(1) else None

    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), restart=True, clock=clock)
    d = Driver(a, clock, answer=answer)
    assert [q.key for q in d.queries] == [K.cov(1), K.cov(2)], "no liveliness needed: every other agent is asked"
    (prior,) = d.sent_on(K.est(0))
    assert prior.phase == "prior" and prior.own == 0 and not a.estimator.prior_pending


def test_a_cold_restart_waits_for_a_clock_that_lists_it_live():
    """A restarted ci agent (no warm rejoin: it starts from its own star tracker and GPS)
    whose health report crossed a clock that does not list it yet gets no sensors of that
    step: it says again that it is here and starts cold at the next step that lists it,
    rather than failing for want of a reading (seen in CI, on a loaded machine)."""
    sc = scenario(estimator={"kind": "ci"})
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), restart=True, clock=clock)
    d = Driver(a, clock)
    assert len(d.sent_on(K.health(0))) == 1  # "here" as it starts
    d.take()
    for k in range(2):
        world.advance(k)
    d.feed(Event(K.clock(), "clock", None, msg=Clock(run=RUN, sender="world", k=1, t_s=world.truth.t, live_agents=[1, 2])))
    assert [h.k for h in d.sent_on(K.health(0))] == [1] and not d.sent_on(K.meas(0)) and not a.started
    d.take()
    world.advance(2)
    d.feed(*world.events_for(0, 2), radio_event(2, [world.batch(1, 2), world.batch(2, 2)]))
    assert a.started and a.last_step == 2 and d.sent_on(K.meas(0)) and d.sent_on(K.est(0))


def test_drop_and_camera_faults_addressed_to_this_agent():
    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    d.take()
    cam_off = Fault(run=RUN, sender="cli", k=0, t_s=0.0, phase="command", action="camera", target=0, camera=2, state="off")
    other = Fault(run=RUN, sender="cli", k=0, t_s=0.0, phase="command", action="drop", target=1, rate=1.0)
    drop = Fault(run=RUN, sender="cli", k=0, t_s=0.0, phase="command", action="drop", target=0, rate=1.0)
    d.feed(*(Event(K.fault(), "fault", None, msg=f) for f in (cam_off, other, drop)))
    assert not d.sent_on(K.fault()), "an agent sends no fault commands"
    (done,) = d.sent_on(K.fault_report("agent-0"))
    assert (done.action, done.phase, done.target, done.sender, done.k) == ("drop", "done", 0, "agent-0", 0), "from step 0 on"
    world.advance(0)
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True), *world.events_for(0, 0, live=(0, 1), off=(2,)))
    d.feed(radio_event(0, [world.batch(1, 0)]))
    assert not d.sent_on(K.meas(0)) and not d.sent_on(K.est(0)[:-1] + "0"), "rate 1: every outgoing batch and estimate lost"
    assert d.sent_on(K.health(0))[-1].drop_rate == 1.0
    assert d.sent_on(K.health(0))[-1].camera_ok == [True, True, False, True, True, True], "camera 2 off, as its delivery says"
    # The recorder comes back (it was stalled, say, when the report went out): the drop's
    # report is sent again with the agent's last steps (issue 35: it was missing from a
    # recording), and the recorder writes it once.
    d.take()
    d.feed(Event(K.alive("recorder", 0), "resync", 0, role="recorder"))
    assert done in d.sent_on(K.fault_report("agent-0")), "the drop's report sent again"
    # ... and once more a moment later (the node says the return again: swarmrt.node._AGAIN_AFTER_S).
    d.take()
    d.feed(Event("", "again", None, msg="bus"))
    assert done in d.sent_on(K.fault_report("agent-0")) and d.sent_on(K.meas(0)) == [], "the last steps' sends, as kept"
    # The world says the command again (its report did not reach it: lost while a failover
    # rebuilt the routes): carried out once, the same report said again, at the rate and
    # first step of the first time.
    d.take()
    d.feed(Event(K.fault(), "fault", None, msg=drop))
    assert d.sent_on(K.fault_report("agent-0")) == [done]
    assert d.sent_on(K.health(0)) == [] and a.drop_rate == 1.0


def test_a_health_report_says_the_cameras_of_its_step_whatever_commands_came_before_it_was_sent():
    """Issue 35 (seeds 11 and 20 of the repeat benchmark): a camera command and the agent's
    health report of a step crossed. The report of step k says the cameras of step k — its
    camera delivery's ``cameras_off``, the world's state at that step — not whatever command
    reached the process last: one of the next step (the world went on while this agent was
    stalled) or an old one sent again (the world's last steps, after a failover; a restarted
    agent has never seen it) changes nothing in it."""
    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True), Event(K.alive("agent", 2), "alive", 2, alive=True))

    def cam(k: int, c: int, state: str) -> Event:
        return Event(K.fault(), "fault", None, msg=Fault(run=RUN, sender="world", k=k, t_s=float(k), phase="command",
                                                         action="camera", target=0, camera=c, state=state))

    reports = []
    for k, off, meanwhile in [(0, (4,), [cam(1, 2, "off"), cam(0, 4, "on")]), (1, (2, 4), [cam(0, 2, "on")]), (2, (2, 4), [])]:
        world.advance(k)
        d.take()
        d.feed(*world.events_for(0, k, off=off))  # its delivery of step k: the world's cameras at k
        d.feed(*meanwhile)  # commands that reach it while it waits for the radio
        d.feed(radio_event(k, [world.batch(1, k), world.batch(2, k)]))
        (h,) = d.sent_on(K.health(0))
        reports.append([c for c in range(6) if not h.camera_ok[c]])
    assert reports == [[4], [2, 4], [2, 4]]


def test_unknown_satellite_is_refused():
    with pytest.raises(ValueError, match="not one of this 3-satellite swarm"):
        AgentProtocol(scenario(), 3, RUN, SyntheticPoseEstimator(scenario()), builtin_estimator(scenario(), 0))


def test_restart_in_lockstep_asks_every_live_peer_and_takes_the_freshest():
    """In lockstep the world holds the clock while an agent restarts, so no new estimate
    comes to name the freshest peer: the agent asks every other satellite's agent (not only
    those whose tokens it had heard of yet: that depended on timing), takes the latest step,
    and breaks ties by the lowest id (deterministic)."""
    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    e1 = initial_estimate(sc, world.truth, 1)
    e2 = initial_estimate(sc, world.truth, 2)
    from dataclasses import replace as dc_replace

    e2 = dc_replace(e2, step=4, t=4.0)

    def answer(q: Query):
        j = int(q.key.rsplit("/", 1)[1])
        return full_estimate_msg({1: e1, 2: e2}[j], run=RUN, sender=f"agent-{j}", own=j)

    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), restart=True, clock=clock)
    d = Driver(a, clock, answer=answer)
    assert sorted(q.key for q in d.queries) == [K.cov(1), K.cov(2)]
    (prior,) = d.sent_on(K.est(0))
    assert prior.k == 4 and a.last_step == 4


def test_bus_back_sends_the_step_again_copies_are_no_news_and_a_lost_world_ends_the_run():
    """Issue 16: after a bus gap the agent sends its step's batch, estimate and health again;
    a batch or a world's message sent again is handled as the no-op it is (not a late
    batch); a world gone before the run's end raises WorldLost."""
    from swarmrt.protocol import WorldLost

    sc = scenario()
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    d = Driver(a, clock, answer=prior_answer(sc, world.truth))
    d.feed(Event(K.alive("world", 0), "alive", 0, alive=True, role="world"))
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True, role="agent"), Event(K.alive("agent", 2), "alive", 2, alive=True, role="agent"))
    world.advance(0)
    d.feed(*world.events_for(0, 0))
    (own,) = d.sent_on(K.meas(0))
    radio = radio_event(0, [own, world.batch(1, 0), world.batch(2, 0)])
    d.feed(radio)
    step0 = [s for s in d.take() if s.msg.k == 0 and not (s.key == K.est(0) and s.msg.phase == "prior")]
    assert [s.key for s in step0] == [K.meas(0), K.est(0), K.health(0)]
    d.feed(Event(K.alive("recorder", 0), "resync", 0, role="recorder"))
    assert d.take()[-len(step0):] == step0, "the recorder came back: the step's messages again"
    d.feed(*world.events_for(0, 0), radio)  # the world sends step 0 again
    assert a.batches_late == 0 and not d.sent and a.last_step == 0
    with pytest.raises(WorldLost):
        d.feed(Event(K.alive("world", 0), "alive", 0, alive=False, role="world"))


def test_a_peers_bad_estimator_message_is_refused_when_read_and_the_others_are_fused():
    """The ideal radio's message is decoded shallowly by an agent; a peer's estimator
    message is checked when the estimator reads it. One peer's unsound ``ci`` state (a NaN
    in its covariance) is refused and counted as malformed in the agent's health; the
    other peer's is fused."""
    from swarmcore.estimators.ci import CIEstimator, CiState
    from swarmrt.bus import messages as M
    from swarmrt.bus.convert import ci_state_msg

    sc = scenario(estimator={"kind": "ci"})
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    own_prior = full_estimate_msg(initial_estimate(sc, world.truth, 0, ids=[0]), run=RUN, sender="world", own=0, ids=[0])
    d = Driver(a, clock, answer=lambda q: own_prior)
    d.feed(Event(K.alive("agent", 1), "alive", 1, alive=True), Event(K.alive("agent", 2), "alive", 2, alive=True))
    world.advance(0)
    d.feed(*world.events_for(0, 0))
    (own,) = d.sent_on(K.meas(0))

    def with_state(j: int, sound: bool):
        tr = world.truth
        m = ci_state_msg(CiState(sat=j, step=0, q_BI=tr.q_BI[j], omega_BI_B=tr.omega_BI_B[j], r_H=tr.r_H[j], v_H=tr.v_H[j],
                                 P_pose=1e-2 * np.eye(6)))
        if not sound:
            m.P_pose.data[0] = float("nan")
        return M.replace(world.batch(j, 0), estimator=M.EstimatorMessage(kind="ci", version=CIEstimator.message_version, ci=m))

    d.feed(radio_event(0, [own, with_state(1, True), with_state(2, False)]))
    est = d.sent_on(K.est(0))[-1]
    (health,) = d.sent_on(K.health(0))
    assert est.phase == "posterior" and est.k == 0
    assert a.payloads_refused == 1 and health.malformed == 1
    assert 1 in list(est.ids) and 2 not in list(est.ids), list(est.ids)


def test_a_graph_radio_agent_waits_for_and_misses_only_its_neighbours():
    """ci hears its graph neighbours (radio "graph"): on a chain 0 → 1 → 2 → 3 agent 0's
    radio is satellite 1 alone; the peers it lists missing are its neighbours', never the
    rest of the swarm's."""
    sc = scenario(n_sats=4, graph={"kind": "chain"}, estimator={"kind": "ci"})
    world = WorldScript(sc)
    clock = FakeClock()
    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), clock=clock)
    assert a.hears == {1}

    def answer(q: Query):
        return full_estimate_msg(initial_estimate(sc, world.truth, 0, [0]), run=RUN, sender="world", own=0, ids=[0])

    d = Driver(a, clock, answer=answer)
    d.feed(*(Event(K.alive("agent", j), "alive", j, alive=True) for j in (1, 2, 3)))
    live = (0, 1, 2, 3)
    for k, delivered in ((0, [1]), (1, [])):
        world.advance(k)
        d.take()
        d.feed(*world.events_for(0, k, live))
        (own,) = d.sent_on(K.meas(0))
        assert own.k == k and list(own.target) == [1]  # it measures 1 only
        assert not d.sent_on(K.est(0)), "the agent waits for its radio"
        msg = step_batches_msg([world.batch(j, k) for j in delivered], run=RUN, k=k, t_s=float(k))
        d.feed(Event(K.batches(0), "batches", 0, msg=msg))
        (est,) = d.sent_on(K.est(0))
        assert est.k == k and list(est.batches_used) == delivered
        assert list(est.batches_missing) == [j for j in (1,) if j not in delivered], "only its neighbour can be missing"


def test_a_round_of_asks_is_all_or_nothing():
    """Links on, a restarted agent's round of asks: an ask the world does not answer (it is
    not waiting for the round yet) ends the round, and the next round starts again from the
    freshest peer. Seen in a campaign: the first ask unanswered, the second answered and
    delivered: the agent took peer 1's state in one run and peer 0's in the other."""
    from swarmrt.bus.messages import RejoinFate

    sc = scenario(links={"enabled": True})
    world = WorldScript(sc)
    clock = FakeClock()
    ests = {j: initial_estimate(sc, world.truth, j) for j in (1, 2)}
    open_ = {"gate": False}
    asks = []

    def answer(q: Query):
        if "/cov/" in q.key:
            j = int(q.key.rsplit("/", 1)[1])
            return full_estimate_msg(ests[j], run=RUN, sender=f"agent-{j}", own=j)
        peer = int(q.key.rsplit("/", 2)[1])
        asks.append((peer, open_["gate"]))
        if not open_["gate"]:
            open_["gate"] = True  # the world starts waiting for the round between two asks
            return None
        return RejoinFate(run=RUN, sender="world", k=3, t_s=3.0, sat=0, peer=peer, bytes=100, fate="delivered", arrival_t_s=3.0)

    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), restart=True, clock=clock)
    d = Driver(a, clock, answer=answer)
    assert asks[:1] == [(1, False)] and not a.started, "the unanswered first ask ends the round"
    d.elapse(2.5)
    assert asks[1:] == [(1, True)], "the next round starts again from the freshest peer (1), not peer 2"
    assert a.started and a.last_step == 2


def test_a_restarted_agent_uses_no_delivery_of_a_step_before_it_flies():
    """Links on, a restarted agent hears the world's last steps sent again whenever the bus
    comes back (a router's return): deliveries of steps before its rejoin were its previous
    process's. Whether they reach the new process depends on timing, so none is used or
    counted — before its rejoin or after it. Seen in the repeat benchmark: one run of a
    campaign counted a stale delivery's batches late and dropped (``late_dropped`` 3) at the
    restarted agent's first step, the other run 0."""
    from swarmrt.bus.messages import Delivered, Delivery, RejoinFate

    sc = scenario(links={"enabled": True})
    world = WorldScript(sc)
    clock = FakeClock()
    ests = {j: initial_estimate(sc, world.truth, j) for j in (1, 2)}
    old = {}
    for k in range(4):
        world.advance(k)
        if k in (1, 2):
            old[k] = world.batch(1, k)

    def delivery(k: int, batches) -> Event:
        return Event(K.rx(0), "rx", None, msg=Delivery(run=RUN, sender="world", k=k, t_s=float(k), sat=0,
                                                       items=[Delivered(arrival_t_s=float(k), batch=b) for b in batches]))

    def answer(q: Query):
        if "/cov/" in q.key:
            j = int(q.key.rsplit("/", 1)[1])
            return full_estimate_msg(ests[j], run=RUN, sender=f"agent-{j}", own=j)
        peer = int(q.key.rsplit("/", 2)[1])
        return RejoinFate(run=RUN, sender="world", k=3, t_s=3.0, sat=0, peer=peer, bytes=100, fate="delivered", arrival_t_s=3.0)

    a = AgentProtocol(sc, 0, RUN, SyntheticPoseEstimator(sc), builtin_estimator(sc, 0), restart=True, clock=clock)
    # The previous process's delivery of step 1, sent again, reaches this one before it rejoins.
    a.handle(delivery(1, [old[1]]))
    d = Driver(a, clock, answer=answer)
    assert a.started and a.last_step == 2, "it flies from step 3"
    d.take()
    d.feed(delivery(2, [old[2]]))  # and its delivery of step 2 after it
    d.feed(*world.events_for(0, 3), delivery(3, [world.batch(1, 3), world.batch(2, 3)]))
    (est,) = d.sent_on(K.est(0))
    assert est.k == 3 and list(est.batches_used) == [1, 2]
    assert (a.late_dropped, a.late_used, a.batches_late) == (0, 0, 0), "no stale delivery used or counted"
