"""One satellite's side of the lockstep protocol, as a bus-free state machine.

The agent hears only what its satellite would: its own sensors (``sat/<i>/sensors``), its
own cameras (``sat/<i>/cam`` detections, or ``sat/<i>/img`` rendered images), what the
radio brings of its peers' relative-measurement batches, the clock, and fault commands;
never the truth. Step k:

1. wait for its own sensors and camera delivery of k (when the clock lists it live);
2. its pose estimator turns its camera delivery into relative measurements (covariance
   attached; the image pipelines start from this step's prediction); transmit them as
   one batch (an empty one too) to the radio, which the world emulates;
3. wait for what the radio delivers of step k: the ideal radio's one message with every
   live peer's batch (``batches``) or, for an estimator whose ``radio`` is ``"graph"``,
   with its graph neighbours' (``batches/<i>``; free-running: each batch as it comes,
   until the step's time is up), or with ``links`` on what the link model let through
   (``rx/<i>``);
4. run its filter (:class:`swarmcore.agent.AgentFilter`: the same calls the in-process
   simulator makes) and publish the estimate and a health report.

Start: the world's prior (a query on ``init/<i>``) or, for a restarted agent or one that
comes late, a live peer's full estimate (``cov/<j>``), re-framed for this satellite.
:class:`AgentProtocol` is driven by :class:`swarmrt.node.Node` in ``python -m sat_agent``
and by scripted events in ``tests/test_protocol_agent.py``.
"""

from __future__ import annotations

import logging
import socket
import time
from collections.abc import Callable

import numpy as np

from swarmcore.estimators import Estimator, StepInputs
from swarmcore.graphs import radio_peers, scenario_graph
from swarmcore.measurement import PoseEstimator
from swarmcore.mekf import RelativeMeasurements
from swarmcore.scenario import Scenario
from swarmrt.bus.convert import (
    absolute_from_sensors,
    batch_msg,
    detections_from_msg,
    estimate_from_full,
    full_estimate_msg,
    observation_from_images,
    radio_bytes,
    received_from_batches,
    received_from_step,
    relative_from_step,
    view_msg,
)
from swarmrt.bus.messages import (
    CameraOutput,
    Clock,
    Fault,
    Health,
    Images,
    Keys,
    MeasBatch,
    Sensors,
    StepBatches,
    check_estimator_message,
    codec_cpu_ms,
    replace,
)
from swarmrt.estimators import EstimatorCodec
from swarmrt.protocol import (
    DROP_BATCH,
    DROP_ESTIMATE,
    Event,
    Outbox,
    Query,
    Send,
    Wait,
    WorldLost,
    arrival_step,
    command_key,
    message_dropped,
    outbox_steps,
    world_wait_s,
)

__all__ = ["AgentProtocol"]

_HOST = socket.gethostname()
_INIT_RETRY_S = 0.2  # the pause between two queries for the world's prior while it serves none yet


class AgentProtocol:
    """Satellite ``sat``'s flight software on the bus (see the module docstring)."""

    def __init__(self, sc: Scenario, sat: int, run: str, pose: PoseEstimator, estimator: Estimator, restart: bool = False,
                 clock: Callable[[], float] = time.monotonic, malformed: Callable[[], int] = lambda: 0,
                 key_mismatch: Callable[[], int] = lambda: 0):
        if not 0 <= sat < sc.n_sats:
            raise ValueError(f"satellite {sat} is not one of this {sc.n_sats}-satellite swarm (0..{sc.n_sats - 1})")
        self.sc = sc
        self.i = sat
        self.n = sc.n_sats
        self.name = f"agent-{sat}"
        self.run_id = run
        self.keys = Keys(run)
        self.pose = pose  # its cameras' measurements (synthetic, or a vision pipeline)
        self.estimator = estimator  # its estimator (swarmcore.estimators): the scenario's estimator.kind
        self.codec = EstimatorCodec(type(estimator))
        self.rendered = sc.vision.pipeline != "none"
        self.clock = clock
        self.log = logging.getLogger(self.name)
        self.restart = restart
        self.started = False  # the estimator has a state (from a prior, a peer, or a cold start)
        self.cold = False  # restarted without a warm rejoin: the estimator starts at its next step
        self.bytes_sent = 0  # bytes put on the radio this step (batch and estimator message)
        # Its cameras as of its latest camera delivery (all on before the first one), and the
        # world's camera commands for this satellite, each with the step it applies from:
        # what a health report of step k says is a function of k (_cameras), never of whether
        # a command came before or after the report (issue 35).
        self.camera_ok = np.ones(6, dtype=bool)
        self._camera_cmds: list[tuple[int, int, bool]] = []  # (step, camera, on), images only: see _cameras
        self.drop_rate = 0.0
        self.clocks: dict[int, Clock] = {}
        self.sensors: dict[int, Sensors] = {}
        self.cams: dict[int, CameraOutput] = {}
        self.imgs: dict[int, Images] = {}
        self.radio: dict[int, list[StepBatches]] = {}  # step → what the ideal radio brought of it
        self.radio_obs: dict[int, set[int]] = {}  # step → the observers whose batch of it came
        self.peers_alive: set[int] = set()
        self.sent_k = -1  # the last step whose batch this agent has transmitted (or lost to a drop fault)
        self.batches_missing = 0
        self.batches_late = 0
        self.malformed = malformed  # the shell's count of malformed messages, reported in health
        self.key_mismatch = key_mismatch  # of those, messages on a key their sender may not use
        self.payloads_refused = 0  # peers' estimator messages refused when read (counted with the malformed)
        self.linked = sc.links.enabled  # peers' batches come through the radio (rx/<i>), not straight off the bus
        # The ideal radio's peers (None: every live peer, on batches; else on batches/<i>).
        hears = radio_peers(scenario_graph(sc), type(estimator).radio)
        self.hears: set[int] | None = None if hears is None else set(hears[sat].tolist())
        self.rx_steps: set[int] = set()  # steps whose delivery (lockstep) has come
        self.rx_items: list[tuple[int, MeasBatch]] = []  # delivered peer batches not yet used, with their delivery's step
        # The first step this process flies: the radio's deliveries (and the ideal radio's
        # messages) of earlier steps went to the satellite's previous process, whatever
        # reaches this one of them (the world's last steps sent again after the bus came
        # back, which depends on timing) is not its to use. See _flies_from.
        self.first_step = 0
        self.late_used = self.late_dropped = self.replayed_steps = 0
        self._missing: list[int] = []  # peers whose batch of the current step did not come
        self._peer_batch: RelativeMeasurements | None = None  # the ideal radio's peers' measurements of the step, columnar
        self.last_step = -1  # the last step this agent has processed (updated at)
        self.done = False
        self.world_seen = False
        self.outbox = Outbox(skip_keys=("/fault",), keep=outbox_steps(sc.emulator))  # its last steps' messages, sent again when the bus comes back
        # The fault commands carried out (command_key, as first_time keys them) → the reports
        # each made: a command is carried out once, its reports said again when it comes again.
        self._fault_reports: dict[bytes, list[Send]] = {}
        self._served = None  # what cov/<i> serves: the estimate at the end of the last step (serve_cov)

    @property
    def est(self):
        """The whole-swarm estimate, for estimators that keep one (None otherwise or before start)."""
        return self.estimator.rejoin_state() if self.started else None

    # -- queries and events -----------------------------------------------------
    def serve_cov(self, key: str):
        """``cov/<i>``: what this agent's estimator serves a restarted peer and the selector
        (the full estimate, for ``full``): its estimate as of the end of its last step (or
        its prior, before its first), never the prior of a step under way. The selector plans
        step k from the posterior of k − 1, as the simulator does; the estimate of the moment
        was the prior of k whenever the clock of k got here before the selector's query (a
        router restart's resends, a loaded machine: the greedy schedule then differed from the
        simulator's; CI saw it). An immutable value: safe to read from the bus's thread."""
        est = self._served
        if est is None:
            return None
        return full_estimate_msg(est, run=self.run_id, sender=self.name, own=self.i)

    def _payload(self, msg, sender: int, step: int):
        """A peer's estimator message as its value (None: not ours, or refused: counted as
        malformed). The ideal radio's message is decoded shallowly, so its estimator messages
        are checked here, when the estimator first reads one
        (:func:`swarmrt.bus.messages.check_estimator_message`); the links' deliveries were
        checked in full when decoded."""
        try:
            if not self.linked:
                check_estimator_message(msg, sender, self.n)
            return self.codec.from_msg(msg, sender, step)
        except ValueError as exc:  # MessageError is one
            self.payloads_refused += 1
            self.log.warning("estimator message of agent %d, step %d refused: %s", sender, step, exc)
            return None

    def handle(self, ev: Event) -> list[Send]:
        k: int = getattr(ev.msg, "k", -1)
        if ev.kind in ("bus", "resync", "again"):
            return self.outbox.again(ev)
        if ev.kind == "alive":
            if ev.role == "world":
                if ev.alive:
                    self.world_seen = True
                elif self.world_seen and not self.done:
                    raise WorldLost(f"{self.name}: the world is gone before the end of the run (last step {self.last_step})")
            elif ev.role in (None, "agent") and ev.sat is not None and ev.sat != self.i:
                (self.peers_alive.add if ev.alive else self.peers_alive.discard)(ev.sat)
        elif ev.kind == "clock":
            if ev.msg.done:
                self.done = True
            else:
                self.clocks[k] = ev.msg
        elif ev.kind == "sensors":
            self.sensors[k] = ev.msg
        elif ev.kind == "cam":
            self.cams[k] = ev.msg
        elif ev.kind == "img":
            self.imgs[k] = ev.msg
        elif ev.kind == "rx":
            if k in self.rx_steps or k < self.last_step - 1 or k < self.first_step:
                return []  # a delivery sent again after the bus came back, or the previous process's
            self.rx_steps.add(k)
            self.rx_items.extend((k, it.batch) for it in ev.msg.items if it.batch.observer != self.i)
        elif ev.kind == "batches":
            if k < self.first_step:
                return []  # the previous process's (sent again after the bus came back)
            obs = set(ev.msg.observers) - {self.i}
            seen = self.radio_obs.setdefault(k, set())
            if obs <= seen and (obs or k in self.radio):
                return []  # a copy sent again after the bus came back
            if k <= self.last_step:
                self.batches_late += len(obs - seen)  # its step is done: too late to use
            else:
                self.radio.setdefault(k, []).append(ev.msg)
            seen |= obs
        elif ev.kind == "fault":
            return self._on_fault(ev.msg)
        return []

    def _on_fault(self, f: Fault) -> list[Send]:
        if f.phase != "command" or f.target != self.i:
            return []
        key = command_key(f)
        if key in self._fault_reports:
            # The same command sent again (the world resends its last steps' commands, and says
            # a command again while its outcome does not show): carried out once, its report
            # said again (it may have been lost on its way: the world would wait its step
            # timeout, then count the drop as never made).
            return list(self._fault_reports[key])
        self._fault_reports[key] = self._carry_out(f)
        return self._fault_reports[key]

    def _carry_out(self, f: Fault) -> list[Send]:
        if f.action == "camera" and f.camera is not None:
            # In effect from the step the world carries it out at (its camera deliveries say so
            # from then on), not from whenever it reaches this process: see _cameras.
            if self.pose.needs_prediction:
                self._camera_cmds.append((int(f.k), int(f.camera), f.state == "on"))
            self.log.info("camera %d %s (step %d)", f.camera, f.state, f.k)
        elif f.action == "drop":
            self.drop_rate = float(f.rate or 0.0)
            first = self.sent_k + 1  # the first batch it applies to
            self.log.info("dropping %.0f%% of outgoing messages from step %d", 100 * self.drop_rate, first)
            # The report says from which step: the world's radio then knows which batches
            # will never come (it makes the same draws: swarmrt.protocol.message_dropped).
            return self.outbox.keep([Send(self.keys.fault_report(self.name), replace(f, phase="done", sender=self.name, k=first))])
        return []

    # -- start ------------------------------------------------------------------
    def initialise(self):
        em = self.sc.emulator
        if not self.restart:
            deadline = self.clock() + em.startup_timeout_s
            while not self.started and self.clock() < deadline:
                msg = yield Query(self.keys.init(self.i), "full_est", 2.0)
                if msg is not None:
                    self.estimator.start(estimate_from_full(msg, self.n), step_pending=True)
                    self.started = True
                    self.last_step = int(msg.k) - 1
                    self._flies_from(int(msg.k))
                    break
                # No prior yet (the world's queryable not declared, so the query came back at
                # once): ask again after a pause, not in a spin (seen: 7,000 queries an agent).
                yield Wait(lambda: bool(self.clocks), _INIT_RETRY_S)
                if self.clocks:
                    # The world serves priors only before the run starts: we are late.
                    self.log.info("the run is under way; initialising from a peer")
                    self.restart = True
                    break
            if not self.started and not self.restart:
                raise SystemExit(f"agent {self.i}: no prior from the world within {em.startup_timeout_s} s")
            if self.started:
                self.log.info("initialised from the world's prior at step %d", self.estimator.step_index)
        if self.restart and not self.estimator.warm_rejoin:
            # Nothing a peer holds can restart this estimator: it starts from its own
            # sensors at its next step (cold start). Its health report says it is here, so
            # that the world counts it live again and sends it its sensors.
            self.cold = True
            self.log.info("restarted: estimator %r starts cold at the next step", self.estimator.kind)
            k_now = max(self.clocks) if self.clocks else 0
            yield Send(self.keys.health(self.i), self._health(k_now, self.clocks[k_now].t_s if k_now in self.clocks else 0.0))
            return
        if self.restart:
            # A restarted agent borrows a peer's full estimate. In lockstep the world holds the
            # step while it restarts, so every running peer serves its estimate of the step
            # before (a peer still restarting serves nothing): it asks every other satellite's
            # agent, whichever tokens it has heard of yet (that depended on how fast they came:
            # a chaos campaign's two runs took different peers), waits for a stalled one, and
            # takes the latest step, then the lowest id.
            while not self.started:
                got = yield from self._peer_states()
                if not got:
                    self.log.warning("no peer serves an estimate to restart from; asking again")
                    yield Wait(lambda: False, min(em.step_timeout_s, 1.0))
                    continue
                if not self.linked:
                    msg = got[0]
                    self.estimator.rejoin(estimate_from_full(msg, self.n), int(msg.own), None)
                    break
                # The state crosses the radio: one round of asks a step (the world waits for each
                # round at a fixed point of its step, so that the transfer's fate and arrival do
                # not depend on when we ask): the freshest peer first.
                first_round = True
                asked = -1
                while not self.started:
                    msg, fate = yield from self._through_the_radio(got)
                    if msg is None and (fate is None or int(fate.k) <= asked):
                        # Not answered (the world answers a round only where it waits for it):
                        # the clock that starts it went by unseen (a failover). Ask again soon.
                        yield Wait(lambda: self.done or any(c > asked for c in self.clocks), 2.0)
                        if self.done:
                            raise SystemExit(f"agent {self.i}: the run ended before a peer's state got through the radio")
                        continue
                    if msg is not None:
                        # In use from the first step that begins at or after its arrival (and
                        # after this round: the world has put the clock of a later round's step).
                        join = max(arrival_step(fate.arrival_t_s, self.sc.dt_s), int(fate.k) + (0 if first_round else 1))
                        # Carried to the step before it (no gyro samples meanwhile: the world
                        # sends sensors only to live agents); the world lists us live from join on.
                        self.estimator.rejoin(estimate_from_full(msg, self.n), int(msg.own), join)
                        break
                    # Nothing got through this round (our radio cut off, say): say so, and try
                    # again at the next step the world puts.
                    asked = int(fate.k)
                    # (Its cameras as a process that has measured nothing yet knows them: all
                    # on; the commands it has heard by now depend on timing.)
                    yield Send(self.keys.health(self.i), self._health(asked, asked * self.sc.dt_s, cameras=np.ones(6, dtype=bool)))
                    first_round = False
                    yield Wait(lambda: self.done or any(c > asked for c in self.clocks), 2.0)
                    if self.done:
                        raise SystemExit(f"agent {self.i}: the run ended before a peer's state got through the radio")
                break
            self.started = True
            self.last_step = self.estimator.step_index
            self._flies_from(self.last_step + 1)
            self.log.info("restarted from agent %d's estimate at step %d", msg.own, self.estimator.step_index)
        self._served = self.est
        yield Send(self.keys.est(self.i), view_msg(self.estimator.view(), run=self.run_id, sender=self.name, phase="prior",
                                                    estimator=self.estimator.kind))

    def _flies_from(self, k: int) -> None:
        """This process flies from step k on: what came of earlier steps' radio is forgotten.
        A restarted agent hears the world's last steps sent again whenever the bus comes back
        (a router's return): the deliveries of steps before its rejoin were its previous
        process's, and whether they reached this one depended on timing; taken, their batches
        were counted late and dropped at its first step (a campaign's two runs reported
        different ``late_dropped``, issue 35). The world lists the agent live, and delivers
        to it, from step k on."""
        self.first_step = k
        self.rx_steps = {s for s in self.rx_steps if s >= k}
        self.rx_items = [(s, b) for s, b in self.rx_items if s >= k]
        for store in (self.radio, self.radio_obs):
            for old in [s for s in store if s < k]:
                store.pop(old, None)

    def _peer_states(self):
        """Every other satellite's agent's full estimate (those that serve one: a dead or
        restarting agent answers at once with nothing), freshest first, then lowest id. A
        stalled peer is waited for (the world's wait for a step's message): its answer comes
        when it runs again."""
        got = []
        for j in range(self.n):
            if j == self.i:
                continue
            msg = yield Query(self.keys.cov(j), "full_est", world_wait_s(self.sc.emulator))
            if msg is not None and msg.own == j:
                got.append(msg)
        got.sort(key=lambda m: (-m.k, m.own))
        return got

    def _through_the_radio(self, candidates):
        """One round: the first peer estimate (in order of preference) the radio delivers and
        its fate; (None, the last fate) if none gets through."""
        from swarmrt.bus.messages import encode

        fate = None
        for m in candidates:
            size = len(encode(m))
            fate = yield Query(self.keys.rejoin(self.i, m.own, size), "rejoin", world_wait_s(self.sc.emulator))
            if fate is None:
                # Not answered: the world is not waiting for our round (we asked on a timer,
                # its clock unseen) or the answer was lost. The round is all or nothing: asked
                # again from the first candidate (a round begun before the world waited for it
                # and finished after took another peer's state in one run than in the other).
                self.log.info("rejoin state from agent %d: no answer; asking again", m.own)
                return None, None
            if fate.fate != "delivered":
                self.log.info("rejoin state from agent %d: %s", m.own, fate.fate)
                continue
            self.log.info("rejoin state from agent %d (%d B) arrives at t = %.2f s", m.own, size, fate.arrival_t_s)
            return m, fate
        return None, fate

    # -- steps --------------------------------------------------------------------
    def _gyro_of(self, s: int):
        msg = self.sensors.pop(s, None)
        return _gyro(msg)

    def _dropped(self, k: int, what: int) -> bool:
        return message_dropped(self.sc.seed, self.i, k, what, self.drop_rate)

    def _own_measurements(self, k: int):
        """Measure our own camera delivery (image pipelines start from the prediction)."""
        e = self.estimator
        if not self.pose.needs_prediction:
            msg = self.cams.pop(k, None)
            if msg is not None:
                # The step's camera delivery says which cameras are off (the hardware's state):
                # that, not the commands this process happened to hear (a restarted agent, or
                # one whose link was down when a command went by, heard fewer), is what the
                # satellite measures with and reports in its health (the selector plans the
                # next step from those reports).
                self.camera_ok = np.ones(6, dtype=bool)
                self.camera_ok[[int(c) for c in msg.cameras_off if 0 <= int(c) < 6]] = False
            return self.pose.measure(self.i, detections_from_msg(msg, self.camera_ok) if msg is not None else None,
                                     e.prediction() if self.started else None, k)
        msg = self.imgs.pop(k, None)
        obs = None
        if msg is not None and msg.views:
            obs = observation_from_images(msg)
            ok = self._cameras(k)
            obs.views = [v for v in obs.views if v.camera >= 6 or ok[v.camera]]
        rel, cams = self.pose.measure(self.i, obs, e.prediction() if self.started else None, k)
        rep = getattr(self.pose, "last_reports", {}).get(self.i)
        if rep is not None and rep.missed:
            self.log.debug("step %d: no pose of %s from the images", k, rep.missed)
        return rel, cams

    def step(self, k: int):
        em = self.sc.emulator
        self.outbox.clear()
        clock = self.clocks.pop(k)
        t = clock.t_s
        if not self.started and self.i not in clock.live_agents:
            # Restarted cold, and this clock went out before the world counted us live again
            # (our health report crossed it): no sensors of this step will come to start
            # from. Say again that we are here and start at a step that lists us (a cold
            # start tried here failed for want of a star tracker reading: CI saw it, loaded).
            yield Send(self.keys.health(self.i), self._health(k, t))
            return
        if not self.started:
            self._flies_from(k)  # a cold start: from the first step that lists us live
        # Lockstep: what the world sends of the step may be held up by a stalled world
        # until its lease runs out (then the wait pauses while its token is held).
        timeout = world_wait_s(em) if em.time_mode == "lockstep" else 0.8 * self.sc.dt_s / em.realtime_factor
        if self.i in clock.live_agents:  # otherwise the world sends us nothing this step
            mine = self.imgs if self.rendered else self.cams
            yield Wait(lambda: k in self.sensors and k in mine, timeout)
        sens = self.sensors.pop(k, None)
        e = self.estimator
        t0, c0 = time.perf_counter(), time.thread_time()
        if self.started:
            # Its prior of step k, before anything of k is measured or sent.
            e.coast_to(k, self._gyro_of)
            e.predict(k, _gyro(sens))
        ms_pred = (time.perf_counter() - t0) * 1e3
        cpu_pred = (time.thread_time() - c0) * 1e3
        t0 = time.perf_counter()
        rel_own, cams = self._own_measurements(k)
        ms_own = (time.perf_counter() - t0) * 1e3
        absolute = None if sens is None else absolute_from_sensors(sens)
        if self.started:  # its own reading, which the centralized reference sends
            e.absolute_reading(k, absolute)
        message = self.codec.to_msg(e.transmit(k)) if self.started else None
        batch = batch_msg(rel_own, cams, run=self.run_id, sender=self.name, k=k, t_s=t, observer=self.i, estimator=message)
        self.bytes_sent = radio_bytes(batch)
        if not self._dropped(k, DROP_BATCH):
            yield Send(self.keys.meas(self.i), batch)
        self.sent_k = k
        if self.linked:
            received = yield from self._linked_radio(k, clock, timeout)
        else:
            received = yield from self._ideal_radio(k, clock, timeout)
        inputs = StepInputs(k, t, _gyro(sens), absolute, rel_own, received,
                            self._peer_batch if not self.linked else None)
        t0, c0 = time.perf_counter(), time.thread_time()
        if not self.started:
            if not e.cold_start(inputs):
                # Nothing of its own to start from (no star tracker and GPS reading): an
                # estimator without warm rejoin cannot come back on this satellite.
                raise SystemExit(f"agent {self.i}: estimator {e.kind!r} cannot restart cold without its own star tracker and "
                                 f"GPS readings (step {k})")
            self.started = True
            self.log.info("started cold at step %d", k)
            report = None
        else:
            report = e.step(inputs)
        self.last_step = k
        self._served = self.est
        ms = (time.perf_counter() - t0) * 1e3 + ms_pred + (ms_own if self.rendered else 0.0)
        if report is not None:
            self.late_used += report.late_used
            self.late_dropped += report.late_dropped
            self.replayed_steps += report.replayed_steps
        msg = view_msg(e.view(), run=self.run_id, sender=self.name, report=report, estimator=e.kind, step_ms=ms,
                       step_cpu_ms=(time.thread_time() - c0) * 1e3 + cpu_pred, codec_cpu_ms=codec_cpu_ms(),
                       batches_used=sorted(r.sender for r in received if r.step == k), batches_missing=self._missing,
                       batches_late=self.batches_late, bytes_sent=self.bytes_sent)
        if not self._dropped(k, DROP_ESTIMATE):
            yield Send(self.keys.est(self.i), msg)
        yield Send(self.keys.health(self.i), self._health(k, t))
        self._prune(k)

    def _ideal_radio(self, k: int, clock, timeout: float):
        """The ideal radio: in lockstep one message with every live peer's batch of k (or,
        radio "graph", its live graph neighbours'); free-running, each batch as it comes
        until the step's time is up."""
        em = self.sc.emulator
        expected = [j for j in clock.live_agents if j != self.i and (self.hears is None or j in self.hears)]
        if em.time_mode == "lockstep":
            yield Wait(lambda: k in self.radio, timeout)
        else:
            yield Wait(lambda: all(j in self.radio_obs.get(k, ()) or j not in self.peers_alive for j in expected), timeout)
        got = sorted(self.radio_obs.get(k, set()))
        self._missing = [j for j in expected if j not in got]
        self.batches_missing += len(self._missing)
        parts = sorted(self.radio.pop(k, []), key=lambda m: m.observers[0] if m.observers else -1)
        received = [r for m in parts for r in received_from_step(m, self.i, self._payload)]
        received.sort(key=lambda r: r.sender)
        self._peer_batch = RelativeMeasurements.concat([relative_from_step(m, skip=self.i) for m in parts])
        return received

    def _prune(self, k: int) -> None:
        for store in (self.sensors, self.cams, self.imgs, self.radio, self.radio_obs, self.clocks):
            for old in [s for s in store if s < k - 2]:
                store.pop(old, None)
        self.rx_steps = {s for s in self.rx_steps if s >= k - 2}

    def _linked_radio(self, k: int, clock, timeout: float):
        """The radio with links: what the world's link model delivered by t_k — on-time
        batches of k, and late ones of earlier steps (the estimator replays, fuses or
        drops them)."""
        self._missing = []
        if self.i in clock.live_agents and self.sc.emulator.time_mode == "lockstep":
            # Lockstep: the world delivers once per step, after every batch of k is in.
            # Free-running: take what the radio has delivered by now; the rest is late.
            yield Wait(lambda: k in self.rx_steps, timeout)
        items = [b for _s, b in self.rx_items if b.k <= k]
        self.rx_items = [(s, b) for s, b in self.rx_items if b.k > k]
        self.batches_late += sum(1 for b in items if b.k < k)
        received = received_from_batches(items, self._payload)
        received.sort(key=lambda r: (r.step, r.sender))
        return received

    def _cameras(self, k: int) -> np.ndarray:
        """The cameras that work at step k, as this satellite knows them: the latest camera
        delivery's (``cameras_off``: the world's state at that step, the hardware's) — all on
        before the first one — and, for a vision pipeline (images carry no such list), the
        world's commands for steps up to k, in step order. Never what arrived last: a command
        for step k + 1 that reached the agent before its health report of step k was sent
        (a stalled agent; a restarted one hearing the world's last steps' commands again)
        made a campaign's two runs report different cameras at one step (issue 35)."""
        if self._camera_cmds:
            for _step, c, on in sorted((x for x in self._camera_cmds if x[0] <= k), key=lambda x: x[0]):
                self.camera_ok[c] = on
            self._camera_cmds = [x for x in self._camera_cmds if x[0] > k]
        return self.camera_ok

    def _health(self, k: int, t: float, cameras=None) -> Health:
        cameras = self._cameras(k) if cameras is None else cameras
        return Health(
            run=self.run_id, sender=self.name, k=k, t_s=t, sat=self.i, camera_ok=[bool(c) for c in cameras],
            malformed=self.malformed() + self.payloads_refused, batches_missing=self.batches_missing, batches_late=self.batches_late,
            drop_rate=self.drop_rate, host=_HOST, key_mismatch=self.key_mismatch(),
        )

    def run(self):
        return self.outbox.wrap(self._run())

    def _run(self):
        yield from self.initialise()
        while not self.done:
            nxt = sorted(s for s in self.clocks if s > self.last_step)
            if nxt:
                # The newest step: in lockstep there is only ever one ahead, unless this
                # agent fell behind (cut off the bus, stalled); then it predicts across the
                # gap and rejoins the swarm's present rather than replaying stale steps.
                k = nxt[-1]
                for s in [s for s in self.clocks if s < k]:
                    self.clocks.pop(s, None)
                yield from self.step(k)
                continue
            yield Wait(lambda: self.done or any(s > self.last_step for s in self.clocks), 0.5)
        self.log.info("done at step %d; %d malformed (%d on a key not their sender's), %d missing, %d late batches",
                      self.last_step, self.malformed() + self.payloads_refused, self.key_mismatch(),
                      self.batches_missing, self.batches_late)


def _gyro(sens):
    return None if sens is None or sens.gyro_rate_B_rad_s is None else np.asarray(sens.gyro_rate_B_rad_s, dtype=float)
