"""The world's side of the lockstep protocol, as a bus-free state machine.

The world owns truth and time. Lockstep step k:

1. apply the faults scheduled for k (and wait until each has taken effect);
2. (k > 0) advance the truth; publish the truth (recorder only), the clock with the live
   set, and each live agent's own sensors;
3. take the selector's choice for k (or fall back when it is dead or late);
4. publish each live agent's camera delivery (synthetic detections, or rendered images);
5. be the radio: take every live agent's batch of k and deliver it — the ideal radio
   either puts them all in one message to every agent (``batches``: an estimator that
   fuses the whole swarm's measurements) or gives each agent its graph neighbours'
   (``batches/<i>``: an estimator whose ``radio`` is ``"graph"``, so that what an agent
   receives does not grow with n; :func:`swarmcore.graphs.radio_peers`, which the
   in-process simulator delivers by too); the link model (``links.enabled``) gives each
   agent what reached it (``rx/<i>``);
6. wait until every live agent has published its health report of k, the last message of
   its step, after its estimate (or the step timeout); optionally pace against wall time.

Free-running mode paces the clock at ``realtime_factor`` × wall time instead of step 6,
and the radio passes each batch on as it comes.
Everything the world computes (truth, images) reaches an agent only as what its own
sensors and cameras deliver. :class:`WorldProtocol` is driven by :class:`swarmrt.node.Node`
in ``python -m world_sim`` and by scripted events in ``tests/test_protocol_world.py``.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

import numpy as np

from swarmcore.graphs import edges, radio_peers, scenario_graph
from swarmcore.links import LinkCounters, LinkModel, scenario_link_model
from swarmcore.measurement import CameraModel
from swarmcore.scenario import AGENT_PROCESS_FAULTS, CLUSTER_FAULTS, ROUTER_FAULTS, Scenario
from swarmcore.selection import mask_dead, select_for_scenario
from swarmcore.world import TruthState, absolute_measurements, initial_estimate, initial_truth, step_truth, world_params
from swarmrt.bus.convert import (
    detections,
    full_estimate_msg,
    images_msg,
    matrix,
    pairs_from_select,
    radio_bytes,
    select_msg,
    sensors_msg,
    step_batches_msg,
    truth_msg,
)
from swarmrt.bus.messages import (
    CameraOutput,
    Claim,
    Clock,
    Delivered,
    Delivery,
    Fault,
    Health,
    Keys,
    Latency,
    LinkStats,
    MeasBatch,
    RejoinFate,
    Select,
    replace,
)
from swarmrt.protocol import (
    DROP_BATCH,
    Event,
    Outbox,
    Send,
    Wait,
    arrival_step,
    first_time,
    message_dropped,
    outbox_steps,
    world_wait_s,
)

__all__ = ["WorldProtocol"]

log = logging.getLogger("world")
_COMMAND_AGAIN_S = 2.0  # a fault command not carried out yet is said again this often (_until_carried_out)

LINK_COUNTERS = tuple(LinkCounters.__dataclass_fields__)


class WorldProtocol:
    """Truth, time, sensors and cameras of the swarm (see the module docstring)."""

    def __init__(self, sc: Scenario, run: str, cameras: CameraModel, expect_recorder: bool = True,
                 expect_selector: bool | None = None, clock: Callable[[], float] = time.monotonic,
                 agent_passwords: dict[int, str] | None = None, malformed: Callable[[], int] = lambda: 0,
                 key_mismatch: Callable[[], int] = lambda: 0, prior_ids: Callable[[int], list[int] | None] | None = None,
                 radio: str = "all", warm_rejoin: bool = True):
        self.sc = sc
        # Security on, agents started with --id auto: satellite i's bus password, handed to
        # the claimant given satellite i (swarmrt.security says why this is safe).
        self.agent_passwords = agent_passwords or {}
        self.run_id = run
        self.n = sc.n_sats
        self.keys = Keys(run)
        self.cameras = cameras
        self.rendered = sc.vision.pipeline != "none"
        self.clock = clock
        self.malformed = malformed  # the shell's counts of refused messages, published with each clock
        self.key_mismatch = key_mismatch
        self.wp = world_params(sc)
        self.G = scenario_graph(sc)
        # The ideal radio's deliveries: None, every batch to everyone (one message); else
        # each agent's radio peers (radio: the agents' estimator's Estimator.radio).
        self.hears = radio_peers(self.G, radio)
        self.heard_by = self.hears  # the peers set is symmetric: who hears j = whom j hears
        self.truth = initial_truth(sc)
        self._ahead: tuple[TruthState, np.ndarray] | None = None  # the next step's (truth, gyro), computed ahead
        # Each agent's prior, over the satellites its estimator starts from (made when asked:
        # a whole-swarm prior of 100 satellites is 11 MB).
        self.prior_ids = prior_ids or (lambda i: None)
        self.expect_recorder = expect_recorder
        # The bounded recorder lag (lockstep): the last step whose clock the recorder says
        # it has taken in, and the steps and wall seconds the world waited for it.
        self.recorded_k = -1
        self.recorder_waits = 0
        self.recorder_wait_s = 0.0
        self._recorder_given_up = False  # it said nothing for bus_lost_after_s: not waited for again
        self.use_selector = sc.selection.strategy != "none" if expect_selector is None else expect_selector
        self.alive_agents: set[int] = set()
        self.ready: set[int] = set()  # agents with an estimate for the current step
        # Agents being restarted whose new process has reported its health (since the
        # restart command): its token and its report reach us by different paths, in
        # either order, and a report before the token must still count.
        self._reported_since_restart: set[int] = set()
        self.alive_roles: set[str] = set()
        self.camera_ok = np.ones((sc.n_sats, 6), dtype=bool)
        self.selections: dict[int, Select] = {}
        self.est_seen: dict[int, set[int]] = {}
        self.fault_done: list[Fault] = []
        self.k = 0
        self.fallback_active = False
        self.started = False
        self.finished = False
        # The radio channel (links.enabled): the world carries the agents' batches.
        self.links = scenario_link_model(sc)
        self.batches: dict[int, dict[int, tuple[MeasBatch, int]]] = {}  # step → observer → (batch, radio bytes)
        self.drops: dict[int, tuple[float, int]] = {}  # agent → (rate, first step) of its drop fault, as it reported
        self._lat_sent = 0  # latencies already reported
        self._new_batch = False
        self._radio_lock = threading.Lock()  # the link model is shared with the rejoin queryable
        self._rejoin_log: list = []  # fates given, still to be published for the recorder
        self._claims: dict[str, int] = {}
        self._claimed_at: dict[int, float] = {}
        self.progress: Callable[[int, int], None] | None = None
        # The last steps' messages, sent again when the bus (or the recorder) comes back, its
        # fault commands too (so the recording has them; every executor carries a command
        # out once: swarmrt.protocol.first_time).
        self.outbox = Outbox(keep=outbox_steps(sc.emulator))
        self._commands_seen: set[bytes] = set()
        self._aired: set[tuple[int, int]] = set()  # (step, observer) of batches already on the radio
        self.limbo: set[str] = set()  # liveliness tokens gone, not yet known whether for good (a bus gap)
        # A restarted agent's state crossing the radio (links on, an estimator with a warm
        # rejoin, the Python agent): it asks in rounds, one at its restart and then one a step
        # until a state gets through, and the world waits for each round at a fixed point of
        # its step, so that the transfer's fate, its arrival and the step the agent joins at
        # are the same whatever the machine's load (a chaos campaign's two runs differed).
        self.warm_rejoin = warm_rejoin
        self._searching: dict[int, int] = {}  # satellite → the step of its last round (nothing got through yet)
        self._round_failed: dict[int, int] = {}  # satellite → the step of its last round that brought nothing
        self._delivered: dict[int, RejoinFate] = {}  # satellite → the fate of the state it rejoins from
        self._joins: dict[int, int] = {}  # satellite → the step from which it is live again (its state arrived)
        self._selector_started_at = -1  # the step of a scheduled restart-selector (it plans from the one after next)
        self._awaiting_round: int | None = None  # the restarted agent whose round of asks the world waits for now
        self._fates: dict[tuple[int, int, int], RejoinFate] = {}  # (agent, peer, step) → the answer given
        self._clocks: tuple[Clock, ...] = ()  # the last two clocks put (or the done one), served on clock (serve_clock)
        self._reports: tuple[Health, ...] = ()  # the health reports of the last two steps, served on health/* (serve_health)

    # -- queries (answered on the bus's thread: read-only or self-contained) -------
    def serve_prior(self, key: str):
        """``init/<i>``: agent i's prior from ground operations, until the run starts."""
        i = int(key.rsplit("/", 1)[1])
        if not 0 <= i < self.n or self.started:
            return None  # once the run is under way, a (re)starting agent asks a peer
        ids = self.prior_ids(i)
        return full_estimate_msg(initial_estimate(self.sc, self.truth, i, ids), run=self.run_id, sender="world", own=i, ids=ids)

    def serve_rejoin(self, key: str):
        """``rejoin/<i>/<peer>/<bytes>``: a restarting agent asks what the radio does to the
        full estimate it fetched from ``peer`` (links on). The transfer takes the peer's
        transmitter now (the world's current step); the answer is recorded on
        ``rejoin/<i>``."""
        parts = key.rsplit("/", 3)
        i, peer, size = int(parts[1]), int(parts[2]), int(parts[3])
        if self.links is None or not (0 <= i < self.n and 0 <= peer < self.n) or i == peer:
            return None
        if i in self._searching and self._awaiting_round != i:
            return None  # asked between its rounds (it missed a clock): answered only where the world waits for it
        with self._radio_lock:
            again = self._fates.get((i, peer, self.k))
            if again is not None:
                return again  # the same ask in the same step (the agent asked again on a timer): the same answer, no new transfer
            t = self.k * self.sc.dt_s  # the step the world is at (its truth may not have reached it yet)
            fate, arrival = self.links.transfer(peer, i, size, t)
        msg = RejoinFate(run=self.run_id, sender="world", k=self.k, t_s=t, sat=i, peer=peer, bytes=size, fate=fate,
                         arrival_t_s=arrival)
        self._rejoin_log.append(msg)
        self._fates = {x: m for x, m in self._fates.items() if x[2] >= self.k - 1}
        self._fates[(i, peer, self.k)] = msg
        if fate == "delivered":
            self._delivered.setdefault(i, msg)  # the agent takes the first state that gets through
        log.info("rejoin of %d from %d (%d B): %s%s", i, peer, size, fate, "" if arrival is None else f" at t = {arrival:.2f} s")
        return msg

    def serve_clock(self, key: str):
        """``clock``: the clocks of the current step and the one before (the run's done clock
        once it is over; nothing before it starts). A selector that (re)starts, or whose bus
        comes back, reads them rather than wait for the next clock: the world waits for its
        selection of the current step, and it plans that step from both steps' live sets
        (a restarted selector that missed a clock left the world waiting 20 s, then falling
        back, in one run of a chaos campaign and not the other: issue 35)."""
        return list(self._clocks)

    def serve_health(self, key: str):
        """``health/*``: the agents' health reports of the current step and the one before,
        each on its agent's key, as they came (the agent's own message). The selector plans
        step k from the reports of k − 1, which the world has every one of before it puts the
        clock of k: a selector whose bus came back reads the ones it missed (put while it
        failed over to another router) rather than wait for them 20 s, as the world waits for
        its selection (one run of a campaign fell back there, the other not: issue 35)."""
        return [Send(self.keys.health(int(h.sat)), h) for h in self._reports]

    def serve_claim(self, key: str):
        """Give an agent started with ``--id auto`` a satellite: the lowest one with no
        live agent and no recent claim (so scaled or restarted containers need no ids),
        never one that ``emulator.agent_commands`` gives to another program (it comes with
        its own id and credential: compose.rust.yaml)."""
        token = key.rsplit("/", 1)[1]
        now = self.clock()
        sat = self._claims.get(token)
        if sat is None:
            alive = set(self.alive_agents)
            reserved = self.sc.emulator.agent_commands
            free = [i for i in range(self.n)
                    if i not in alive and i not in reserved and now - self._claimed_at.get(i, -1e9) > 30.0]
            if not free:
                return None
            sat = free[0]
            self._claims[token] = sat
            self._claimed_at[sat] = now
        return Claim(run=self.run_id, sender="world", k=self.k, t_s=self.k * self.sc.dt_s, sat=sat, token=token, running=self.started,
                     password=self.agent_passwords.get(sat, ""))

    # -- events -------------------------------------------------------------------
    def handle(self, ev: Event) -> list[Send]:
        if ev.kind == "health":  # (kept for serve_health: one assignment, it reads them on the bus's thread)
            h = ev.msg
            self._reports = (*(x for x in self._reports if x.k >= self.k - 1 and not (x.sat == h.sat and x.k == h.k)), h)
        if ev.kind == "held":
            self.limbo.add(ev.key)
            return []
        if ev.kind in ("resync", "alive"):
            self.limbo.discard(ev.key)
        if ev.kind in ("bus", "resync", "again"):
            again = self.outbox.again(ev)
            if again:
                log.info("step %d: the bus is back (%s); sending the step's %d messages again", self.k, ev.kind, len(again))
            return again
        if ev.kind == "alive":
            if ev.role == "agent" and ev.sat is not None:
                if ev.alive:
                    self.alive_agents.add(ev.sat)
                else:
                    self.alive_agents.discard(ev.sat)
                    self.ready.discard(ev.sat)
                    self._searching.pop(ev.sat, None)
                    self._joins.pop(ev.sat, None)
                    self._claimed_at.pop(ev.sat, None)  # its satellite may be claimed again at once
            elif ev.role:
                (self.alive_roles.add if ev.alive else self.alive_roles.discard)(ev.role)
        elif ev.kind == "est":
            m = ev.msg
            self.ready.add(m.own)  # a prior too: the agent is initialised
            fate = self._delivered.pop(m.own, None) if m.phase == "prior" else None
            if fate is not None:
                # Restarted from a state that crossed the radio: live from the step it arrives
                # in (no earlier than the step it was asked at; _round may put it later).
                self._joins[m.own] = max(arrival_step(fate.arrival_t_s, self.sc.dt_s), int(fate.k))
        elif ev.kind == "health" and ev.msg.sat in self._searching:
            # A restarted agent whose round of asks brought no state through the radio.
            self._round_failed[ev.msg.sat] = max(int(ev.msg.k), self._round_failed.get(ev.msg.sat, -1))
        elif ev.kind == "health":
            # An agent's health report is the last message of its step k, after its estimate
            # (lost or not: the drop fault never loses the report): the step is over for it
            # when its report is in, and only then. Counted over on the estimate too, whether
            # the report of the step was put depended on timing when the next step's fault
            # killed or stopped the agent (its estimate in, its report not yet sent), and so
            # did the recording. An agent restarted cold reports its health before it has any
            # estimate: it is ready for its sensors.
            self.est_seen.setdefault(ev.msg.k, set()).add(ev.msg.sat)
            if ev.msg.sat in self.alive_agents:
                self.ready.add(ev.msg.sat)
            self._reported_since_restart.add(ev.msg.sat)
        elif ev.kind == "meas":
            m = ev.msg
            if (m.k, m.observer) in self._aired:  # a copy sent again
                return []
            if self.links is None and self.sc.emulator.time_mode == "free":
                # The ideal radio, free-running: every batch goes on as it comes (to everyone,
                # or to the agents whose radio peers include its observer).
                self._aired.add((m.k, m.observer))
                one = step_batches_msg([m], run=self.run_id, k=m.k, t_s=m.t_s)
                if self.heard_by is None:
                    return [Send(self.keys.batches(), one)]
                to = self.heard_by[m.observer] if 0 <= m.observer < self.n else []
                return [Send(self.keys.batches(int(j)), one) for j in to if j in self.alive_agents]
            self.batches.setdefault(m.k, {})[m.observer] = (m, 0 if self.links is None else radio_bytes(m))
            self._new_batch = True
        elif ev.kind == "recorded":
            self.recorded_k = max(self.recorded_k, int(ev.msg.k))
        elif ev.kind == "select":
            if ev.msg.sender != "world":
                self.selections[ev.msg.k] = ev.msg
        elif ev.kind == "fault":
            if ev.msg.sender == "world" and ev.msg.phase == "command":
                return []  # our own scheduled command coming back over the bus: already applied
            return self._on_fault(ev.msg)
        return []

    def _on_fault(self, f: Fault) -> list[Send]:
        if f.phase == "command" and not first_time(self._commands_seen, f):
            return []  # the same command sent again (the CLI's, say, after a bus gap): carried out once
        if f.phase != "command":
            self.fault_done.append(f)
            if (f.action == "drop" and f.phase == "done" and f.HasField("target") and f.sender == f"agent-{f.target}"
                    and f.k >= self.drops.get(f.target, (0.0, -1))[1]):
                # From step f.k on, its batches are lost at this rate. The newest report rules,
                # not the last to arrive: an agent reports an old command again when it hears
                # it again (the world's last steps sent again after a failover), and that
                # report can come after a newer one (the repeat benchmark, seed 1: an old 44 %
                # over the 0 % of two steps later, and the world did not wait for a batch).
                self.drops[f.target] = (f.rate, f.k)
            return []
        if f.action == "camera" and f.target is not None and f.camera is not None:
            self.camera_ok[f.target, f.camera] = f.state == "on"
            log.info("camera %d of satellite %d %s", f.camera, f.target, f.state)
            done = replace(f, phase="done", sender="world", k=self.k, t_s=self.k * self.sc.dt_s)
            return self.outbox.keep([Send(self.keys.fault_report("world"), done)])
        if f.action == "link":
            return self.outbox.keep([Send(self.keys.fault_report("world"), self._link_fault(f))])
        return []

    def _link_fault(self, f: Fault) -> Fault:
        """A link fault on the radio (the link model): carried out at once, at the step it
        came in (a scheduled one before the radio of its step); reported done or failed."""
        at = {"sender": "world", "k": self.k, "t_s": self.k * self.sc.dt_s}
        if self.links is None:
            return replace(f, phase="failed", detail="links are off (links.enabled: false): no link model to act on", **at)
        i, j = int(f.target), (int(f.peer) if f.HasField("peer") else None)
        what = f"{i} -> {j}" if j is not None else f"every link of {i}"
        try:
            if f.HasField("state") and f.state == "on":
                count = self.links.restore(i, j)
                detail = f"{what}: the scenario's parameters back"
            else:
                count = self.links.impair(i, j, dead=f.HasField("state") and f.state == "off",
                                          delay_s=f.delay_s if f.HasField("delay_s") else None,
                                          loss_rate=f.rate if f.HasField("rate") else None)
                detail = f"{what}: " + ", ".join(x for x in (
                    "dead" if f.HasField("state") else "", f"+{f.delay_s:g} s latency" if f.HasField("delay_s") else "",
                    f"loss {f.rate:g}" if f.HasField("rate") else "") if x)
        except ValueError as exc:
            return replace(f, phase="failed", detail=str(exc)[:200], **at)
        log.info("step %d: link fault, %s (%d directed links)", self.k, detail, count)
        return replace(f, phase="done", detail=detail, **at)

    def live(self) -> list[int]:
        return sorted(i for i in self.alive_agents & self.ready if self._joins.get(i, -1) <= self.k)

    def _searches(self, t: int) -> bool:
        """Whether restarted agent t gets its state through the radio in rounds (see __init__)."""
        return self.links is not None and self.warm_rejoin and t not in self.sc.emulator.agent_commands

    def _round(self, t: int, k: int, at_restart: bool):
        """Wait for restarted agent t's round of asks at step k: its prior (a state got
        through: it is live from the first step that begins at its arrival, after this round)
        or its report that nothing did (it asks again at the next step)."""
        self._awaiting_round = t
        ok = yield Wait(lambda: t not in self.alive_agents or t in self.ready or self._round_failed.get(t, -1) >= k,
                        self.sc.emulator.startup_timeout_s)
        self._awaiting_round = None
        if not ok:
            log.warning("step %d: restarted agent %d's round of asks not over within %.0f s; going on", k, t,
                        self.sc.emulator.startup_timeout_s)
        if t not in self.alive_agents:
            self._searching.pop(t, None)
            return
        if t in self.ready:
            self._searching.pop(t, None)
            join = max(k + (0 if at_restart else 1), self._joins.get(t, -1))  # (the arrival's step: handle)
            if join > k:
                self._joins[t] = join
            else:
                self._joins.pop(t, None)
            log.info("step %d: restarted agent %d rejoins at step %d", k, t, join)
        else:
            self._searching[t] = k

    def _rounds(self, k: int):
        """The rounds of step k of the restarted agents still asking for a state."""
        for t in sorted(self._searching):
            if self._searching.get(t, k) < k:
                yield from self._round(t, k, at_restart=False)

    # -- the run ---------------------------------------------------------------------
    def run(self):
        return self.outbox.wrap(self._run())

    def _run(self):
        sc, em = self.sc, self.sc.emulator
        yield from self._startup()
        self.started = True
        t_wall0 = self.clock()
        gyro = None
        for k in range(sc.steps):
            yield from self._wait_for_recorder(k)
            self.k = k
            self.outbox.clear()
            self._aired = {(s, i) for s, i in self._aired if s >= k - 50}
            yield from self._apply_scheduled_faults(k)
            if k > 0:
                self.truth, gyro = self._ahead if self._ahead is not None else step_truth(self.wp, self.truth)
                self._ahead = None
            tr = self.truth
            t = tr.t
            yield Send(self.keys.truth(), self._truth_msg(k))
            while self._rejoin_log:
                m = self._rejoin_log.pop(0)
                yield Send(self.keys.rejoin(m.sat), m)
            yield Wait(lambda: False, 0.0)  # take in what has arrived: the live set reflects deaths up to now
            live = self.live()
            clock = Clock(run=self.run_id, sender="world", k=k, t_s=t, live_agents=live, mode=em.time_mode,
                          malformed=self.malformed(), key_mismatch=self.key_mismatch(),
                          recorder_waited_steps=self.recorder_waits, recorder_waited_s=self.recorder_wait_s)
            self._clocks = (*self._clocks[-1:], clock)  # (one assignment: serve_clock reads it on the bus's thread)
            yield Send(self.keys.clock(), clock)
            absm = absolute_measurements(self.wp, tr)
            for i in live:
                yield Send(self.keys.sensors(i), sensors_msg(
                    run=self.run_id, k=k, t_s=t, sat=i, gyro=None if gyro is None else gyro[i],
                    absm=absm[i] if self.G[i, i] else None, sigma_star=self.wp.star_sigma, sigma_gps=self.wp.gps_sigma,
                ))
            yield from self._rounds(k)
            obs, tgt = yield from self._selection(k)
            yield from self._deliver_cameras(k, t, live, obs, tgt)
            if em.time_mode == "lockstep":
                yield from (self._relay(k, t, live) if self.links is None else self._radio(k, t, live))
            if k + 1 < sc.steps:
                # The next step's truth while the agents work on this one (it depends on
                # nothing they do): off the path every step waits on.
                self._ahead = step_truth(self.wp, self.truth)
            if em.time_mode == "lockstep":
                # Not on while some role is only out of reach (the recorder would miss the step).
                # (est_seen: the agents whose health report of k, their step's last message, is in.)
                ok = yield Wait(lambda: all(i in self.est_seen.get(k, set()) or i not in self.alive_agents for i in live)
                                and not self.limbo, em.step_timeout_s)
                if not ok:
                    missing = [i for i in live if i not in self.est_seen.get(k, set())]
                    log.warning("step %d: no health report (the step's last message) from %s within %.1f s", k, missing,
                                em.step_timeout_s)
                if em.lockstep_max_realtime_factor:
                    yield from self._pace(t_wall0 + (k + 1) * sc.dt_s / em.lockstep_max_realtime_factor)
            elif self.links is not None:
                yield from self._radio_free(k, live, t_wall0, t_wall0 + (k + 1) * sc.dt_s / em.realtime_factor)
            else:
                yield from self._pace(t_wall0 + (k + 1) * sc.dt_s / em.realtime_factor)
            self.est_seen.pop(k - 2, None)
            if self.progress is not None:
                self.progress(k + 1, sc.steps)
        self.finished = True
        yield Send(self.keys.clock(), self.done_clock())

    def done_clock(self) -> Clock:
        """The clock that tells everyone the run is over (from now on the one served on ``clock``)."""
        done = Clock(run=self.run_id, sender="world", k=self.k, t_s=self.truth.t, live_agents=self.live(),
                     mode=self.sc.emulator.time_mode, done=True, malformed=self.malformed(), key_mismatch=self.key_mismatch(),
                     recorder_waited_steps=self.recorder_waits, recorder_waited_s=self.recorder_wait_s)
        self._clocks = (done,)
        return done

    def _wait_for_recorder(self, k: int):
        """Lockstep, with a recorder: begin step k only once the recorder has taken in the
        clock of step ``k - recorder_max_lag_steps`` (it keeps up, or the swarm waits for
        it), so that no role is ever further ahead of the recording than its
        :class:`~swarmrt.protocol.Outbox` reaches back. A recorder gone for good (its token
        gone, after being held: :class:`swarmrt.node.Node`) is not waited for; one that
        says nothing for ``bus_lost_after_s`` (its own limit for a bus gap) is given up on."""
        em = self.sc.emulator
        lag = em.recorder_max_lag_steps
        if em.time_mode != "lockstep" or not self.expect_recorder or self._recorder_given_up or k <= lag:
            return

        def caught_up() -> bool:
            return self.recorded_k >= k - lag or "recorder" not in self.alive_roles

        if caught_up():
            return
        t0 = self.clock()
        self.recorder_waits += 1
        ok = yield Wait(caught_up, em.bus_lost_after_s)
        self.recorder_wait_s += self.clock() - t0
        if not ok:
            self._recorder_given_up = True
            log.warning("step %d: the recorder has taken in step %d, more than %d steps behind, for %.0f s; going on without "
                        "waiting for it again", k, self.recorded_k, lag, em.bus_lost_after_s)

    def _pace(self, deadline: float):
        rem = deadline - self.clock()
        if rem > 0:
            yield Wait(lambda: False, rem)

    def _truth_msg(self, k: int):
        return truth_msg(self.truth, run=self.run_id, k=k)

    def _startup(self):
        em = self.sc.emulator
        need_roles = set()
        if self.expect_recorder:
            need_roles.add("recorder")
        if self.use_selector:
            need_roles.add("selector")
        ok = yield Wait(lambda: len(self.ready) == self.n and need_roles <= self.alive_roles and self.alive_agents >= self.ready,
                        em.startup_timeout_s)
        if not ok:
            log.warning("startup: ready agents %s, alive roles %s after %.0f s; starting anyway",
                        sorted(self.ready), sorted(self.alive_roles), em.startup_timeout_s)
        if self.use_selector:
            # The selector plans step 0 from agent 0's prior: give a live selector the
            # start-up allowance (a loaded machine starts processes slowly), not the step one.
            yield Wait(lambda: 0 in self.selections or "selector" not in self.alive_roles, em.startup_timeout_s)

    def _apply_scheduled_faults(self, k: int):
        em = self.sc.emulator
        for spec in [f for f in self.sc.faults if f.at_step == k]:
            if spec.action == "restart-agent":
                # From here on a health report of its satellite is the new process's.
                self.ready.discard(spec.target)
                self._reported_since_restart.discard(spec.target)
            cmd = Fault(run=self.run_id, sender="world", k=k, t_s=k * self.sc.dt_s, phase="command", action=spec.action, target=spec.target,
                        camera=spec.camera, state=spec.state, rate=spec.rate, down_s=spec.down_s, peer=spec.peer,
                        delay_s=spec.delay_s, detail="scheduled")
            log.info("step %d: fault %s target=%s", k, spec.action, spec.target)
            yield Send(self.keys.fault(), cmd)
            t = spec.target
            if spec.action in ("camera", "link"):
                yield from self._on_fault(cmd)
            elif spec.action in AGENT_PROCESS_FAULTS and spec.action != "restart-agent":
                yield from self._until_carried_out(cmd, lambda: t not in self.alive_agents, em.step_timeout_s)
            elif spec.action == "restart-agent" and t is not None:  # the scenario's validation names its satellite
                def back(t: int = t) -> bool:
                    return t in self.alive_agents and (t in self.ready or t in self._reported_since_restart)

                def started(t: int = t) -> bool:  # its executor says so, or it is on the bus
                    return t in self.alive_agents or self._reported("restart-agent", k, t)

                # Said again until carried out (seen: a restart-agent command put just after a
                # failover never reached the supervisor, and the world waited its 120 s).
                yield from self._until_carried_out(cmd, started, em.startup_timeout_s)
                if self._searches(t):
                    self._searching[t] = k
                    self._awaiting_round = t  # (its asks are answered from now: it may ask before its token is in)
                    self._delivered.pop(t, None)
                    self._round_failed.pop(t, None)
                    self._joins.pop(t, None)
                    if not (yield Wait(lambda: t in self.alive_agents, em.startup_timeout_s)):
                        log.warning("step %d: restarted agent %d not back within %.0f s (startup_timeout_s); going on without it",
                                    k, t, em.startup_timeout_s)
                        continue
                    yield from self._round(t, k, at_restart=True)
                    continue
                if self.links is None:
                    ok = yield Wait(back, em.startup_timeout_s)
                else:
                    # Its state crosses the radio and arrives some steps later: wait until it
                    # has asked for it (at this step, so the transfer's fate is reproducible),
                    # not until it is back.
                    ok = yield Wait(lambda: back() or (t in self.alive_agents and any(m.sat == t for m in self._rejoin_log)),
                                    em.startup_timeout_s)
                if back():
                    self.ready.add(t)  # its report came before its token: ready now that both are here
                if not ok:
                    log.warning("step %d: restarted agent %d not back within %.0f s (startup_timeout_s); going on without it",
                                k, t, em.startup_timeout_s)
            elif spec.action == "kill-selector":
                yield from self._until_carried_out(cmd, lambda: "selector" not in self.alive_roles, em.step_timeout_s)
            elif spec.action == "restart-selector":
                yield from self._until_carried_out(cmd, lambda: "selector" in self.alive_roles, em.startup_timeout_s)
                self._selector_started_at = k
            elif spec.action in CLUSTER_FAULTS:
                # A host of a cluster run killed (its agents started again on the others) or
                # two cut apart: over once the supervisor says so, and for a killed node once
                # every agent that was alive is back (as a scheduled restart-agent waits).
                before = set(self.alive_agents)
                self._reported_since_restart.difference_update(before)
                yield from self._until_carried_out(cmd, lambda: self._reported(spec.action, k), em.startup_timeout_s)
                if spec.action == "kill-node":
                    def all_back() -> bool:
                        return all(t in self.alive_agents and (t in self.ready or t in self._reported_since_restart) for t in before)

                    if not (yield Wait(all_back, em.startup_timeout_s)):
                        log.warning("step %d: agents %s not back within %.0f s after kill-node; going on without them", k,
                                    sorted(t for t in before if t not in self.alive_agents), em.startup_timeout_s)
                    self.ready.update(t for t in before if t in self.alive_agents)
            elif spec.action in ROUTER_FAULTS:
                # The bus goes down under us (this wait, like every wait, pauses while it is
                # down); a restart is over once its executor says so.
                yield from self._until_carried_out(cmd, lambda: self._reported(spec.action, k), em.startup_timeout_s)
            elif spec.action == "drop":
                yield from self._until_carried_out(cmd, lambda: self._reported("drop", k, t) or t not in self.alive_agents,
                                                   em.step_timeout_s)

    def _reported(self, action: str, k: int, target: int | None = None) -> bool:
        """Whether a fault ``action`` of step ``k`` or later (on ``target``, if given) has been
        reported carried out (or failed) by its executor."""
        return any(f.action == action and f.k >= k and (target is None or f.target == target) for f in self.fault_done)

    def _until_carried_out(self, cmd: Fault, done, timeout_s: float):
        """Wait (at most ``timeout_s``) until a command's outcome shows (``done()``), saying the
        command again every ``_COMMAND_AGAIN_S`` meanwhile. A put can be lost on its way to a
        process whose router routes are being rebuilt (seen: the supervisor never heard a
        kill-selector sent just after a failover, and the world waited its 10 s in one run of
        a campaign only); every executor carries a command out once (``first_time``), so
        saying it again changes nothing else. Returns whether it was carried out."""
        left = timeout_s
        while True:
            wait = min(_COMMAND_AGAIN_S, left)
            if (yield Wait(done, wait)):
                return True
            left -= wait
            if left <= 0:
                return False
            log.info("step %d: fault %s target=%s not carried out yet; said again", self.k, cmd.action, cmd.target)
            yield Send(self.keys.fault(), cmd)

    def _selection(self, k: int):
        """The pairs of step k: the graph's, the selector's, or (selector dead or late) a
        state-free fallback the world chooses itself and announces."""
        if not self.use_selector:
            return edges(self.G)
        em = self.sc.emulator
        if self._selector_started_at >= 0 and k - self._selector_started_at in (0, 1) and em.time_mode == "lockstep":
            # A selector started during step r heard neither the clock nor the agents' reports
            # of r − 1, which it plans r from; nor, it was seen, always the clock of r (its
            # token reached the world before its subscriptions had reached the world's router):
            # it plans from r + 2, and r and r + 1 fall back (whether a plan of its came in time
            # is no part of the run).
            self.selections.pop(k, None)
        elif "selector" in self.alive_roles:
            # Lockstep: a live selector is waited for as a live agent is (the step timeout
            # plus the lease): a stall of the selector, of the agent it plans from or of the
            # router shorter than that delays its selection and changes nothing; only a
            # selector gone (its token) or silent that long is replaced by the fallback. A
            # flat 2 s made a 2 s router stall change the schedule (a chaos campaign saw it).
            # Free-running: select_timeout_s, the clock does not wait.
            wait_s = max(em.select_timeout_s, world_wait_s(em)) if em.time_mode == "lockstep" else em.select_timeout_s
            yield Wait(lambda: k in self.selections or "selector" not in self.alive_roles, wait_s)
        sel = self.selections.pop(k, None)
        if sel is not None:
            if self.fallback_active:
                log.info("step %d: selector is back", k)
            self.fallback_active = False
            return pairs_from_select(sel)
        if not self.fallback_active:
            log.warning("step %d: no selection from the selector; falling back to %s", k, self.sc.selection.fallback)
        self.fallback_active = True
        fb = self.sc.model_copy(update={"selection": self.sc.selection.model_copy(update={"strategy": self.sc.selection.fallback})})
        t0 = time.perf_counter()
        obs, tgt = select_for_scenario(fb, k, self.G, None, None, mask_dead(self.camera_ok, self.live()))
        yield Send(self.keys.select(), select_msg(obs, tgt, run=self.run_id, sender="world", k=k, t_s=k * self.sc.dt_s,
                                                  strategy=self.sc.selection.fallback, fallback=True,
                                                  select_ms=(time.perf_counter() - t0) * 1e3))
        return obs, tgt

    def _batch_lost(self, i: int, k: int) -> bool:
        """Agent i's batch of step k will not come: its drop fault lost it (the agent's
        own draw, made again here)."""
        rate, first = self.drops.get(i, (0.0, 0))
        return k >= first and message_dropped(self.sc.seed, i, k, DROP_BATCH, rate)

    def _batches_in(self, k: int, live: list[int]):
        """Wait until the batch of step k of every live agent is in (or will never come)."""
        yield Wait(lambda: all(i in self.batches.get(k, {}) or i not in self.alive_agents or self._batch_lost(i, k) for i in live),
                   self.sc.emulator.step_timeout_s)

    def _relay(self, k: int, t: float, live: list[int]):
        """The ideal radio of step k (lockstep): every live agent's batch of k, to every
        agent, in one message; or (``radio: graph``) to each agent its radio peers' batches
        on its own ``batches/<i>`` (an empty message too: every agent waits for one). A batch
        that comes after its step's message went out is too late for anyone and is dropped."""
        yield from self._batches_in(k, live)
        got = self.batches.pop(k, {})
        for s in [s for s in self.batches if s < k]:
            late = self.batches.pop(s)
            log.warning("step %d: batches of step %d from %s came after their step; dropped", k, s, sorted(late))
        self._aired.update((k, i) for i in got)
        if self.hears is None:
            yield Send(self.keys.batches(), step_batches_msg([m for m, _size in got.values()], run=self.run_id, k=k, t_s=t))
            return
        for i in sorted(j for j in self.alive_agents | set(live) if 0 <= j < self.n):
            mine = [got[j][0] for j in self.hears[i].tolist() if j in got]
            yield Send(self.keys.batches(i), step_batches_msg(mine, run=self.run_id, k=k, t_s=t))

    def _radio(self, k: int, t: float, live: list[int]):
        """The radio channel of step k (lockstep): take every live agent's batch of k, hand
        each to the link model (copies for every other live agent, in observer order), and
        deliver to each live agent what has arrived by t_k (an empty delivery too: every
        agent waits for one)."""
        yield from self._batches_in(k, live)
        with self._radio_lock:
            arrived = self._air(k, t, live)
        for j in live:
            items = [Delivered(arrival_t_s=d.arrival_t, batch=d.payload) for d in arrived if d.receiver == j]
            yield Send(self.keys.rx(j), Delivery(run=self.run_id, sender="world", k=k, t_s=t, sat=j, items=items))
        yield from self._link_stats(k, t)

    def _air(self, k: int, t: float, live: list[int]):
        lm = self._lm()
        lm.at_step(k, self.truth.r_H)
        # Batches of earlier steps that came after their step's radio (a stalled agent) go
        # now; then this step's, in observer order.
        for s in sorted(x for x in self.batches if x <= k):
            for i, (msg, size) in sorted(self.batches.pop(s).items()):
                lm.send(i, live, msg, size, t, key=msg.k)
                self._aired.add((s, i))
        return lm.due(t)

    def _radio_free(self, k: int, live: list[int], t_wall0: float, deadline: float):
        """The radio channel in free-running mode, until the wall-clock end of step k: every
        batch goes on the air when it reaches the world (simulated time = the world's clock,
        ``realtime_factor`` × wall time since the start), and each copy is delivered on its
        own ``rx/<j>`` at the wall time of its arrival."""
        lm = self._lm()
        em = self.sc.emulator
        with self._radio_lock:
            lm.at_step(k, self.truth.r_H)

        def sim_now() -> float:
            return (self.clock() - t_wall0) * em.realtime_factor

        def wall_of(t_sim: float) -> float:
            return t_wall0 + t_sim / em.realtime_factor

        while True:
            now_s = sim_now()
            with self._radio_lock:
                for s in sorted(self.batches):
                    for i, (msg, size) in sorted(self.batches.pop(s).items()):
                        lm.send(i, [j for j in live if j in self.alive_agents], msg, size, max(now_s, msg.t_s), key=msg.k)
                        self._aired.add((s, i))
                self._new_batch = False
                arrived = lm.due(now_s)
            for d in arrived:
                item = Delivered(arrival_t_s=d.arrival_t, batch=d.payload)
                yield Send(self.keys.rx(d.receiver), Delivery(run=self.run_id, sender="world", k=k, t_s=now_s, sat=d.receiver,
                                                              items=[item]))
            rem = deadline - self.clock()
            if rem <= 0:
                break
            nxt = lm.next_arrival()
            wait = rem if nxt is None else max(0.0, min(rem, wall_of(nxt) - self.clock()))
            yield Wait(lambda: self._new_batch, wait)
        yield from self._link_stats(k, self.truth.t)

    def _lm(self) -> LinkModel:
        if self.links is None:
            raise RuntimeError("no link model: links are not enabled")
        return self.links

    def _link_stats(self, k: int, t: float):
        lm = self._lm()
        with self._radio_lock:
            msg = LinkStats(
                run=self.run_id, sender="world", k=k, t_s=t, queue_bytes=lm.queue_bytes(t).tolist(),
                latencies=[Latency(sender=int(a), receiver=int(b), sent_k=int(s), latency_s=float(x))
                           for a, b, s, x in lm.latencies[self._lat_sent:]],
                **{name: matrix(getattr(lm.counters, name).astype(float)) for name in LINK_COUNTERS},
            )
            self._lat_sent = len(lm.latencies)
        yield Send(self.keys.links(), msg)

    def _deliver_cameras(self, k: int, t: float, live: list[int], obs, tgt):
        """Each live agent's camera delivery of step k (an empty one when it has nothing
        scheduled: every agent waits for one every step)."""
        keep = np.isin(obs, live)
        seen = self.cameras.observe(self.truth, obs[keep], tgt[keep], self.camera_ok)
        off_of = {i: [int(c) for c in np.flatnonzero(~self.camera_ok[i])] for i in live}
        for i in live:
            got = seen.get(i)
            if self.rendered:
                views, targets = (got.views, got.targets) if got is not None else ([], [])
                yield Send(self.keys.img(i), images_msg(views, run=self.run_id, k=k, t_s=t, sat=i, targets=targets))
            else:
                dets = [] if got is None else detections(got)
                yield Send(self.keys.cam(i), CameraOutput(run=self.run_id, sender="world", k=k, t_s=t, sat=i, detections=dets,
                                                          cameras_off=off_of[i]))
