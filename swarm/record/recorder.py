"""The recorder: every message of a run's key space into MCAP.

One channel per key expression, each with its protobuf schema (message encoding
"protobuf", the schema a serialized FileDescriptorSet of ``swarm.v1.<Message>``), so
Foxglove, the ``mcap`` CLI and any protobuf library decode every channel without the
project's code. Each message is stored exactly as it travelled, except images, stored with
their pixels cleared (``emulator.record_images`` adds them as ``foxglove.RawImage``, live).
The derived Foxglove 3-D channels (:mod:`swarm.record.foxglove`) are added when the run is over,
from the recorded messages, before the file is compacted.
Log time = when the recorder's session received the message; publish time = the
message's Zenoh timestamp, the publishing session's clock at ``put`` (every session of the
project stamps: :mod:`swarmrt.bus.session`), both Unix ns: ``log_time − publish_time`` is the
one-way bus latency (publisher → router → recorder), which :mod:`swarm.record.recording` turns
into per-sender statistics. A sample without a timestamp gets publish time = log time, as
the MCAP specification asks. The simulation time is in every message (``t_s``). Liveliness changes are recorded
on ``swarm/<run>/alive`` (``swarm.v1.Liveliness``) and messages that fail validation on
``swarm/<run>/_malformed`` (``swarm.v1.Malformed``, with the reason), so the recording
tells the whole story. Flushes at step boundaries (once every live agent's estimate of a
step is in), at least once per ``flush_every_s`` of simulated time, and once per wall
second; the file is readable after a SIGKILL at any instant (see :mod:`swarm.record.mcaplog`).

python -m swarm.record.recorder --run RUN --out FILE.mcap [--flush-every-s 1] [bus flags]
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import logging
import sys
import threading
import time
from typing import TYPE_CHECKING

from google.protobuf.message import Message

from swarm.record.mcaplog import CheckpointWriter
from swarmrt.bus.messages import (
    MODELS,
    BusGap,
    Keys,
    Liveliness,
    Malformed,
    MessageError,
    Recorded,
    encode,
    file_descriptor_set,
    parse_key,
    prepare,
    replace,
)
from swarmrt.bus.receive import receive
from swarmrt.bus.session import Inbox, RouterLinks, add_bus_args, bus_config_from_args, open_session

if TYPE_CHECKING:
    from swarm.record.foxglove import FoxgloveDeriver

log = logging.getLogger("recorder")

_STOP_DRAIN_S = 2.0  # after SIGTERM: at most this long for the messages still arriving


class _LinkChange:
    """(Put on the inbox by Zenoh's thread) some router reachable again, or none any more."""

    def __init__(self, up: bool):
        self.up = up
        self.wall_ns = time.time_ns()


#: The flood cap: the most messages of different content the recorder writes of one key and
#: step, and the most malformed ones of one key. A run puts one message per key and step; when
#: the bus came back each role sends its step again: those resends (same key, step and
#: content as a message already recorded) are not written again and not counted against the
#: cap, but counted apart (``messages.resent_not_written`` in summary.json); a flood (a stolen
#: credential putting on its own keys as fast as it can, under the router's size limits) is
#: cut at the cap and counted. A message of a step beyond the run is malformed. So a recording
#: holds at most PER_STEP · (K + 1) well-formed messages per key, each within its key's size
#: limit on the router (``swarmrt.security.size_limit_of``), and MALFORMED_PER_KEY malformed
#: ones, each kept to its first 64 KiB.
FLOOD_CAP_PER_STEP = 8
FLOOD_CAP_MALFORMED_PER_KEY = 200


class Recorder:
    def __init__(self, run: str, out: str, bus, flush_every_s: float = 1.0, derive_foxglove: bool = True, scenario=None):
        self.keys = Keys(run)
        self.run = run
        self.w = CheckpointWriter(out)
        self.flush_every_s = flush_every_s
        self.inbox = Inbox()
        prepare("meas")  # it records batches: their checks loaded before it says it is alive
        self.session = open_session(bus)
        self.stop = threading.Event()
        self.done = False
        self.final: tuple[int, set[int]] | None = None  # last step and the agents still owing it
        self.last_flush_t: float | None = None  # the simulated time of the last step-boundary flush
        self.last_flush_wall = time.monotonic()
        self.malformed = 0
        # The flood cap (above): messages written per (key, step) and malformed ones per key,
        # and those over it not written, per key.
        self.steps = scenario.steps if scenario is not None else None
        # (key, step) → the digest of the one message of it written, or the set of them when
        # several of different content were (a single digest keeps the common case small).
        self._per_key_step: dict[tuple[str, int], bytes | set[bytes]] = {}
        self.resent: dict[str, int] = {}  # key → messages identical to one already written, not written again
        self._malformed_per_key: dict[str, int] = {}
        self.not_recorded: dict[str, int] = {}
        self._subs = [
            self.session.declare_subscriber(self.keys.everything(), self.inbox.callback),
            self.session.liveliness().declare_subscriber(f"{self.keys.root}/alive/**", self.inbox.callback, history=True),
        ]
        self.token = self.session.liveliness().declare_token(self.keys.alive("recorder", 0))
        # The bounded lag: the last step whose clock it has taken in, told the world on
        # ``recorded`` at each new one, again when its bus comes back and once per wall
        # second (a put while no router is reachable is lost, and the world waits on it).
        self.acked_k = -1
        self.acked_t_s = 0.0
        self.last_ack_wall = 0.0
        self._schema_ids: dict[str, int] = {}
        self._est_at: dict[int, set[int]] = {}  # step → agents whose posterior of it is recorded
        self._live_at: dict[int, set[int]] = {}  # step → the agents its clock lists live
        # The bus's health: gaps are recorded on swarm/<run>/_gap; a bus that does not come
        # back, or a world that goes before its last step, ends the recording.
        em = scenario.emulator if scenario is not None else None
        self.bus_lost_after_s = em.bus_lost_after_s if em is not None else 30.0
        self.broken: str | None = None
        self.last_k = -1
        self.gaps: list[BusGap] = []  # closed gaps whose first step after is not known yet
        self.down: tuple[int, float] | None = None  # (wall ns, monotonic) since no router is reachable
        self._world_seen = False
        self._world_gone_at: float | None = None
        self._links = RouterLinks(self.session, lambda up: self.inbox.put_event(_LinkChange(up)))
        self.foxglove: FoxgloveDeriver | None = None
        if derive_foxglove and scenario is not None:
            from swarm.record.foxglove import FoxgloveDeriver

            self.foxglove = FoxgloveDeriver.for_scenario(self.w, scenario)

    def _link(self, ch: _LinkChange) -> None:
        if not ch.up and self.down is None:
            self.down = (ch.wall_ns, time.monotonic())
            log.warning("bus lost after step %d: no router reachable (giving up after %.0f s)", self.last_k, self.bus_lost_after_s)
        elif ch.up and self.down is not None:
            log.warning("bus back after %.2f s", (ch.wall_ns - self.down[0]) / 1e9)
            self.ack()
            self.gaps.append(BusGap(observer="recorder", down_unix_ns=self.down[0], up_unix_ns=ch.wall_ns,
                                    last_step_before=self.last_k, first_step_after=-1))
            self.down = None
            self._world_gone_at = None  # the world's token went with the bus

    def _write_gaps(self, first_after: int) -> None:
        for g in self.gaps:
            g.first_step_after = first_after
            self.w.add(self._channel(f"{self.keys.root}/_gap", "gap"), g.SerializeToString(), time.time_ns())
        self.gaps.clear()

    def _check_broken(self) -> None:
        now = time.monotonic()
        if self.down is not None and now - self.down[1] >= self.bus_lost_after_s:
            self.broken = f"bus lost: no router reachable for {now - self.down[1]:.0f} s after step {self.last_k}"
            self.gaps.append(BusGap(observer="recorder", down_unix_ns=self.down[0], up_unix_ns=0,
                                    last_step_before=self.last_k, first_step_after=-1))
        elif self._world_gone_at is not None and self.down is None and now - self._world_gone_at >= self.bus_lost_after_s:
            # (Not sooner: a world whose token went may be stalled, SIGSTOP or docker pause,
            # its session dropped by the router's lease; it comes back and resends its step.)
            self.broken = f"the world is gone after step {self.last_k}"
        if self.broken:
            log.error("%s: closing the recording", self.broken)

    def _channel(self, topic: str, kind: str) -> int:
        sid = self._schema_ids.get(kind)
        if sid is None:
            cls: type[Message] = {"alive": Liveliness, "malformed": Malformed, "gap": BusGap}.get(kind) or MODELS[kind]
            sid = self._schema_ids[kind] = self.w.schema(cls.DESCRIPTOR.full_name, "protobuf", file_descriptor_set(cls))
        return self.w.channel(topic, sid, "protobuf")

    def record(self, s) -> bool:
        """Record sample ``s``; whether it was news: a message of the run not recorded before
        (not a resend, nor malformed, nor over the flood cap), or a liveliness change."""
        now = s.received_ns or time.time_ns()
        resend = False  # the same key, step and content as a message already written: only counted
        published = s.published_ns if s.published_ns is not None else now
        try:
            # Any swarm size (no n_sats): ids up to MAX_SAT_ID, the recording keeps what it heard.
            r = receive(s.key, s.payload, self.run, delete=s.kind == "delete")
            kind, msg = r.kind, r.msg
            if kind == "recorded":
                return False  # its own word to the world (sent again each second): not part of the run's story
            if kind == "alive":
                body = Liveliness(key=s.key, role=r.role, id=s.key.split("/")[4], alive=bool(r.alive)).SerializeToString()
                if r.role == "world":
                    if r.alive:
                        self._world_seen, self._world_gone_at = True, None
                    elif self._world_seen and not self.done and self.down is None:
                        self._world_gone_at = time.monotonic()
                self.w.add(self._channel(f"{self.keys.root}/alive", "alive"), body, now)
                return True
            k_msg = getattr(msg, "k", None)
            if self.steps is not None and k_msg is not None:
                if k_msg > self.steps:
                    raise MessageError(f"step {k_msg}: beyond the run's {self.steps} steps")
                digest = hashlib.blake2b(s.payload, digest_size=8).digest()
                got = self._per_key_step.get((s.key, k_msg))
                if got is not None and (digest == got if isinstance(got, bytes) else digest in got):
                    resend = True
                    self.resent[s.key] = self.resent.get(s.key, 0) + 1
                elif got is None:
                    self._per_key_step[(s.key, k_msg)] = digest
                else:
                    if isinstance(got, bytes):
                        got = self._per_key_step[(s.key, k_msg)] = {got}
                    if len(got) >= FLOOD_CAP_PER_STEP:
                        self.not_recorded[s.key] = self.not_recorded.get(s.key, 0) + 1
                        return False
                    got.add(digest)
            if kind == "est" and msg.phase == "posterior":
                self._est_at.setdefault(msg.k, set()).add(msg.own)
                self._est_at.pop(msg.k - 3, None)
            # Images without their pixels on the bus channel (pixels as foxglove.RawImage when
            # emulator.record_images is on); every other message exactly as it travelled.
            data = s.payload
            if kind == "img":
                data = replace(msg, views=[replace(v, images_mono8=[]) for v in msg.views]).SerializeToString()
            if not resend:  # (what it says is in the recording; its bookkeeping below still runs: a clock sent again closes a gap)
                self.w.add(self._channel(s.key, kind), data, now, published)
            if self.foxglove is not None and kind == "img" and not resend:
                self.foxglove.on_message(kind, msg, now)  # pixels are not kept: now or never
            if kind == "est" and self.final is not None and msg.k == self.final[0]:
                self.final[1].discard(msg.own)
            if kind == "clock":
                if self.gaps and not msg.done and msg.k >= max(g.last_step_before for g in self.gaps):
                    self._write_gaps(msg.k)  # (not a clock of an earlier step sent again)
                self.last_k = max(self.last_k, msg.k)
                if not msg.done and msg.k > self.acked_k:
                    self.acked_k, self.acked_t_s = msg.k, msg.t_s
                    self.ack()
                if msg.done:
                    self.done = True
                    self.final = (msg.k, set(msg.live_agents) - self._seen_final(msg.k))
                else:
                    self._live_at[msg.k] = set(msg.live_agents)
                    self._live_at.pop(msg.k - 3, None)
            # Flush at step boundaries: once every agent the clock of step k listed has its
            # estimate of k recorded, so that what a SIGKILL leaves is whole steps (the
            # world's next clock and an agent's last estimate travel independently, so
            # flushing at a clock could cut a step in two).
            if (kind in ("clock", "est") and not getattr(msg, "done", False) and self._step_complete(msg.k)
                    and (self.last_flush_t is None or msg.t_s - self.last_flush_t >= self.flush_every_s)):
                self.flush(msg.t_s)
            return not resend
        except MessageError as exc:
            self.malformed += 1
            seen = self._malformed_per_key[s.key] = self._malformed_per_key.get(s.key, 0) + 1
            if self.steps is not None and seen > FLOOD_CAP_MALFORMED_PER_KEY:
                self.not_recorded[s.key] = self.not_recorded.get(s.key, 0) + 1
                return False
            body = Malformed(key=s.key, error=str(exc), payload=bytes(s.payload[:65536])).SerializeToString()
            self.w.add(self._channel(f"{self.keys.root}/_malformed", "malformed"), body, now)
            return False

    def ack(self) -> None:
        """Tell the world how far the recording has got (``recorded``: the bounded lag)."""
        if self.acked_k < 0:
            return
        self.last_ack_wall = time.monotonic()
        msg = Recorded(run=self.run, sender="recorder", k=self.acked_k, t_s=self.acked_t_s)
        with contextlib.suppress(Exception):  # (a session closing under us: the world gives up on us in time)
            self.session.put(self.keys.recorded(), encode(msg))

    def _derive_scene(self, foxglove: FoxgloveDeriver) -> None:
        """The Foxglove 3-D channels (truth, estimates, measurement lines, links, cameras, faults,
        each filter's errors: :mod:`swarm.record.scene`), from the recorded
        messages once the run is over. Derived live, they cost the recorder more CPU than
        recording itself (at n = 40: 40 scenes of 40 satellites a step) on the cores the
        agents were waiting for; a recorder killed mid-run leaves the bus channels only."""
        from swarm.record.foxglove import DERIVED_KINDS
        from swarm.record.mcaplog import iter_messages

        self.w.flush()
        t0, count = time.monotonic(), 0
        seen: set[tuple[str, int, int]] = set()  # a message sent again after a bus gap: drawn once
        for topic, _schema, data, log_ns, _pub in iter_messages(self.w.path):
            try:
                run, kind, _sat = parse_key(topic)
            except MessageError:
                continue
            if run == self.run and kind in DERIVED_KINDS:
                if (ident := (topic, len(data), hash(data))) in seen:
                    continue
                seen.add(ident)
                foxglove.on_message(kind, MODELS[kind].FromString(data), log_ns)  # recorded: already checked
                count += 1
                if count % 2000 == 0:
                    self.w.flush()
        log.info("derived the Foxglove scene from %d messages in %.1f s", count, time.monotonic() - t0)

    def _seen_final(self, k: int) -> set[int]:
        return self._est_at.get(k, set())

    def _step_complete(self, k: int) -> bool:
        live = self._live_at.get(k)
        return live is not None and live <= self._est_at.get(k, set())

    def flush(self, t_s: float | None = None) -> None:
        self.w.flush()
        if t_s is not None:
            self.last_flush_t = t_s
        self.last_flush_wall = time.monotonic()

    def run_loop(self, quiet_s: float = 0.5, max_linger_s: float = 30.0) -> None:
        """Record until the run is done (or we are asked to stop), then keep draining:
        until every agent alive at the end has delivered its last estimate (they travel
        independently of the world's final clock) and the bus has been quiet ``quiet_s``."""
        while not self.stop.is_set() and not self.done and not self.broken:
            s = self.inbox.get(0.2)
            if isinstance(s, _LinkChange):
                self._link(s)
            elif s is not None:
                self.record(s)
            self._check_broken()
            if time.monotonic() - self.last_flush_wall >= 1.0:
                self.flush()
            if time.monotonic() - self.last_ack_wall >= 1.0:
                self.ack()
        # "Quiet" counts news only: a flood that goes on after the run's end (garbage, resends,
        # what the flood cap cuts) must not keep the recorder, and everyone who waits for it,
        # lingering until max_linger_s (measured: a 10 s demo run ended 30 s late under one).
        end_by = time.monotonic() + max_linger_s
        last_news = time.monotonic()
        while time.monotonic() < end_by:
            if self.stop.is_set():
                # Asked to stop (the run was interrupted, or it is over and we were waited
                # for long enough): keep what is already in flight, owe nobody anything.
                end_by = min(end_by, time.monotonic() + _STOP_DRAIN_S)
            owed = self.final is not None and bool(self.final[1]) and not self.stop.is_set()
            quiet_left = quiet_s - (time.monotonic() - last_news)
            if not owed and quiet_left <= 0:
                break
            s = self.inbox.get(max(0.0, min(1.0, end_by - time.monotonic()) if owed else quiet_left))
            if self.broken:
                end_by = min(end_by, time.monotonic() + _STOP_DRAIN_S)
                owed = False
            if s is None and not owed:
                break
            if isinstance(s, _LinkChange):
                self._link(s)
                last_news = time.monotonic()
            elif s is not None and self.record(s):
                last_news = time.monotonic()

    def close(self) -> None:
        if self.down is not None and not self.broken:
            self.gaps.append(BusGap(observer="recorder", down_unix_ns=self.down[0], up_unix_ns=0,
                                    last_step_before=self.last_k, first_step_after=-1))
        if self.gaps:
            self._write_gaps(-1)
        # Counts per key, each on a channel of its own (the count as the payload): what the
        # flood cap cut, and resends of what is recorded (after a bus gap) not written again.
        cut = (f"over the recorder's flood cap ({FLOOD_CAP_PER_STEP} per key and step, {FLOOD_CAP_MALFORMED_PER_KEY} "
               "malformed per key)")
        for channel, counts, why in (("_not_recorded", self.not_recorded, f"not recorded: {{}} messages {cut}"),
                                     ("_resent", self.resent, "sent again: {} messages identical to one already recorded "
                                                              "(not written again)")):
            for key, count in sorted(counts.items()):
                body = Malformed(key=key, error=why.format(count), payload=str(count).encode()).SerializeToString()
                self.w.add(self._channel(f"{self.keys.root}/{channel}", "malformed"), body, time.time_ns())
                if channel == "_not_recorded":
                    log.warning("not recorded: %d messages on %s (over the flood cap)", count, key)
        for undeclare in [*(s.undeclare for s in self._subs), self._links.undeclare]:
            with contextlib.suppress(Exception):
                undeclare()
        with contextlib.suppress(Exception):
            self.token.undeclare()
        self.session.close()
        if self.foxglove is not None:
            self._derive_scene(self.foxglove)
        self.w.close(finalize=True)
        log.info("recorded %d messages (%d malformed) in %d flushes", self.w.messages, self.malformed, self.w.flushes)


def main(argv=None) -> int:
    from swarmrt import tuning

    tuning.tune_process()
    from swarmrt.node import freeze_startup_objects, install_term_handler, setup_logging

    p = argparse.ArgumentParser(description="recorder: every message of a run into MCAP")
    p.add_argument("--run", required=True)
    p.add_argument("--out", required=True, help="MCAP file to write")
    p.add_argument("--flush-every-s", type=float, default=1.0, help="flush at least this often in simulated time")
    p.add_argument("--no-foxglove", action="store_true", help="do not derive Foxglove channels")
    p.add_argument("--scenario", default=None, help="scenario YAML (needed to derive Foxglove 3-D channels and the summary)")
    p.add_argument("--set", dest="sets", action="append", default=[], help="scenario override dotted.key=value")
    p.add_argument("--summary", default=None, help="when the run is done, write summary.json here (needs --scenario)")
    p.add_argument("--router-gate", metavar="GLOB", default=None,
                   help="the routers' ingress gate counts (JSON files, e.g. /out/gate-*.json; those written since the recorder "
                        "started) to add to the summary as router_gate, summed per identity (compose)")
    p.add_argument("-v", "--verbose", action="store_true")
    add_bus_args(p)
    a = p.parse_args(argv)
    setup_logging("recorder", a.verbose)
    started = time.time() - 1.0  # (a file's time stamp is of its file system's clock; a second's slack)
    sc = None
    if a.scenario:
        from swarmrt.node import load_role_scenario

        sc = load_role_scenario(a.scenario, a.sets)
    r = Recorder(a.run, a.out, bus_config_from_args(a, sc), a.flush_every_s, derive_foxglove=not a.no_foxglove, scenario=sc)
    freeze_startup_objects()
    install_term_handler(r.stop)
    try:
        r.run_loop(max_linger_s=sc.emulator.shutdown_linger_s if sc is not None else 30.0)
    finally:
        r.close()
    if a.summary and sc is not None:
        from swarm.outputs import write_json
        from swarm.record.recording import load_recording

        if r.broken or not r.done:
            try:
                summary = load_recording(a.out, sc.n_sats, None, scenario=sc).summary(sc)
            except (ValueError, FileNotFoundError):
                summary = {"scenario": sc.name, "n_sats": sc.n_sats, "seed": sc.seed, "steps": 0, "faults": []}
            summary["interrupted"] = {"reason": r.broken or "the recorder was stopped before the run's end",
                                      "last_step": r.last_k, "steps_planned": sc.steps}
        else:
            summary = load_recording(a.out, sc.n_sats, sc.steps, scenario=sc).summary(sc)
        summary["run"] = a.run
        if a.router_gate:
            from swarm.supervise.gate import fresh_counts

            # The files written since this recorder started (a folder's earlier runs left theirs),
            # as of the run's end (the routers write them once a second while they change).
            if counts := fresh_counts(a.router_gate, started):
                summary["router_gate"] = counts
        write_json(a.summary, summary)
        logging.getLogger("recorder").info("wrote %s", a.summary)
    if r.broken:
        from swarmrt.protocol import EXIT_BUS_LOST, EXIT_WORLD_LOST

        return EXIT_BUS_LOST if r.broken.startswith("bus lost") else EXIT_WORLD_LOST
    return 0


if __name__ == "__main__":
    sys.exit(main())
