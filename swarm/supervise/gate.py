"""The router's ingress gate: a rate limit per identity, with a burst allowance, in front of
a local Zenoh router (issue 35: a stolen credential must not slow the swarm).

Every process of a local run connects to the gate, not to the router: each identity at its
own port (``agent-3`` at one, ``world`` at another, anything else at the shared ``other``
port, which is also ``run.json``'s endpoint). The gate relays each connection to the router,
which listens only on a Unix socket in a private (0700) directory, and the bytes coming *in*
from a connection pass through a token bucket sized for that identity
(:func:`gate_limits`): up to ``burst_bytes`` at once, then ``rate_bytes_per_s``. When the
bucket is empty the gate stops reading that connection: TCP's flow control holds the sender
back, so nothing is dropped (a lockstep run loses no message to the limit, an honest burst
is at worst delayed) and a flood is throttled at its source, before the router, the world,
the recorder or any agent spends anything on it. What comes *out* to a connection (what the
router forwards to it) is not limited.

Why not Zenoh's own tools: ``downsampling`` drops what exceeds a frequency with no burst
allowance (measured in docs/security.md: it breaks quiet runs or lets the flood through),
and a router still receives and parses every put it then drops; Zenoh 1.x has no ingress
rate limit per identity. Why a relay and not ``tc``/``iptables``: it needs no privileges,
knows the identity (by port) and counts per identity; a kernel policer drops packets
(TCP then retransmits after ≥ 200 ms) and counts per rule, not per identity.

Counted per identity (``counts()``, written by the router to ``gate-<router>.json`` and read
into ``summary.json``'s ``router_gate``): connections, bytes in and out, and how often and for
how long the bucket held a connection back (``held``, ``held_s``, ``held_bytes``: bytes that
had to wait). A quiet run is never held.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import socket
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from swarm.supervise.zenoh_wire import WireCounter

log = logging.getLogger(__name__)

_READ_BYTES = 64 * 1024  # one read from a connection: the unit the bucket is charged
_BOUNDED_KINDS = {"est", "health", "fault", "recorded"}  # kinds the scenario sizes (the rest of MAX_PAYLOAD_BYTES: the world's)
OTHER = "other"  # the shared entry: identities without their own port (tools, the fault CLI)


@dataclass
class Entry:
    """One identity's port and its bucket's size."""

    identity: str
    port: int
    rate_bytes_per_s: float
    burst_bytes: float
    rate_msgs_per_s: float = float("inf")  # Zenoh messages (swarm.supervise.zenoh_wire); inf: not counted
    burst_msgs: float = float("inf")


@dataclass
class _Count:
    connections: int = 0
    bytes_in: int = 0
    bytes_out: int = 0
    held: int = 0
    held_s: float = 0.0
    held_bytes: int = 0
    refused: int = 0  # connections refused: the router not there, or the identity cut a moment ago
    messages_in: int = 0  # Zenoh messages relayed (where the identity has a message limit; by kind: every one read)
    held_for_messages: int = 0  # of ``held``: the times the message bucket was the one empty
    unparsed: int = 0  # batches the message counter could not read (charged at the worst case)
    cut: int = 0  # connections cut for a batch of more messages than the identity's burst
    cut_messages: int = 0  # the messages of those batches (not relayed)
    wires: list[WireCounter] = field(default_factory=list)  # each connection's message counter

    def as_dict(self) -> dict[str, Any]:
        return {"connections": self.connections, "bytes_in": self.bytes_in, "bytes_out": self.bytes_out, "held": self.held,
                "held_s": round(self.held_s, 4), "held_bytes": self.held_bytes, "refused": self.refused,
                "messages_in": self.messages_in, "held_for_messages": self.held_for_messages, "unparsed": self.unparsed, "cut": self.cut,
                "cut_messages": self.cut_messages,
                "messages_by_kind": _by_kind(self.wires)}


def _by_kind(wires: list[WireCounter]) -> dict[str, int]:
    out: dict[str, int] = {}
    for w in wires:
        for k, v in w.by_kind.items():
            out[k] = out.get(k, 0) + v
    return dict(sorted(out.items()))


@dataclass
class _Bucket:
    """A token bucket of bytes (the usual one: a burst of ``burst`` bytes, refilled at
    ``rate`` bytes per second). Charged after a read, so the level may go below zero: the
    next read waits until it is back at zero."""

    rate: float
    burst: float
    clock: Any = time.monotonic
    level: float = field(default=0.0)
    t: float = field(default=0.0)

    def __post_init__(self) -> None:
        self.level = self.burst
        self.t = self.clock()

    def charge(self, n: int) -> float:
        """Take ``n`` bytes; return how long to wait (s) before the next read."""
        if self.rate == float("inf"):
            return 0.0
        now = self.clock()
        self.level = min(self.burst, self.level + (now - self.t) * self.rate)
        self.t = now
        self.level -= n
        return 0.0 if self.level >= 0 else -self.level / self.rate


def gate_limits(n_sats: int, recorder_max_lag_steps: int, links: bool, identities: list[str],
                steps_per_s: float) -> dict[str, tuple[float, float]]:
    """Each identity's bucket: ``(rate_bytes_per_s, burst_bytes)``, sized from the scenario
    like the router's size limits (:func:`swarmrt.security.size_limit_of`). An identity's
    *step budget* is the sum of the size limits of the keys it may put (its grants; a kind
    the scenario does not size, a measurement or a selection, counts as an estimate; the
    world's radio batches and images make it unbounded: ``inf``, the world is not limited).
    Its rate is ``steps_per_s`` step budgets per second (``emulator.gate_steps_per_s``: more
    steps per second than a lockstep run of this machine kind ever goes, so an honest role is
    never held); its burst is what a role sends at once when its bus comes back (its last
    ``recorder_max_lag_steps + 2`` steps, :class:`swarmrt.protocol.Outbox`) and one step more."""
    from swarmrt.bus.messages import MAX_PAYLOAD_BYTES, Keys
    from swarmrt.security import put_kinds, size_limit_of

    keys = Keys("gate")
    out: dict[str, tuple[float, float]] = {}
    for name in identities:
        budget = 0.0
        for _key, kind in put_kinds(keys, name, links):
            if kind in _BOUNDED_KINDS:
                budget += size_limit_of(kind, n_sats)
            elif kind in MAX_PAYLOAD_BYTES:
                budget = float("inf")  # the world's radio and images: its job is to send them, unbounded
            else:
                budget += size_limit_of("est", n_sats)  # a measurement, a selection: counted as an estimate
        budget = max(budget, size_limit_of("health", n_sats))  # an identity that puts nothing still opens a session
        out[name] = (budget * steps_per_s, budget * (recorder_max_lag_steps + 3))
    return out


def gate_message_limits(n_sats: int, recorder_max_lag_steps: int, links: bool, identities: list[str],
                        steps_per_s: float) -> dict[str, tuple[float, float]]:
    """Each identity's message bucket: ``(rate_msgs_per_s, burst_msgs)``, counted in Zenoh
    messages (:mod:`swarm.supervise.zenoh_wire`), sized like the byte bucket: a bound on
    bytes alone lets through a flood of tiny puts that costs every receiver per message.
    An identity's *step budget* is two messages for each key it may put (a step's own and a
    resent one) and four more (a step's queries, their answers, a liveliness change); its
    rate is ``steps_per_s`` step budgets per second, its burst ``recorder_max_lag_steps + 3``
    of them (as the bytes') and what a role sends once, at its start or its return: its
    declarations (subscribers, queryables, tokens: about 40 measured) and a rejoin's query to
    every peer, ``64 + 2 n``. Measured on the demo (n = 4): an agent sends 36 messages at
    its start and 3 a step, against 12 a step here; the world is not limited (``inf``)."""
    from swarmrt.bus.messages import MAX_PAYLOAD_BYTES, Keys
    from swarmrt.security import put_kinds

    keys = Keys("gate")
    out: dict[str, tuple[float, float]] = {}
    for name in identities:
        kinds = [kind for _key, kind in put_kinds(keys, name, links)]
        if any(k in MAX_PAYLOAD_BYTES and k not in _BOUNDED_KINDS for k in kinds):
            out[name] = (float("inf"), float("inf"))  # the world: its radio and images are its job
            continue
        step = 2 * len(kinds) + 4
        out[name] = (step * steps_per_s, step * (recorder_max_lag_steps + 3) + 64 + 2 * n_sats)
    return out


class Gate:
    """The relay (an asyncio loop on its own thread). ``upstream``: the router's Unix socket."""

    def __init__(self, entries: list[Entry], upstream: str, host: str = "127.0.0.1"):
        self.entries = entries
        self.upstream = upstream
        self.host = host
        self.count = {e.identity: _Count() for e in entries}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._servers: list[asyncio.base_events.Server] = []
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._cut_until: dict[str, float] = {}  # an identity whose connection was cut: none before then

    def start(self, timeout: float = 30.0) -> None:
        self._thread = threading.Thread(target=self._run, name="gate", daemon=True)
        self._thread.start()
        if not self._ready.wait(timeout):
            raise RuntimeError("the gate did not start listening")
        if self._error is not None:
            raise RuntimeError(f"the gate could not listen: {self._error}") from self._error

    def stop(self) -> None:
        loop = self._loop
        if loop is not None and loop.is_running():
            loop.call_soon_threadsafe(loop.stop)
        if self._thread is not None:
            self._thread.join(5)

    def counts(self) -> dict[str, dict[str, Any]]:
        return {k: c.as_dict() for k, c in self.count.items()}

    def _run(self) -> None:
        self._loop = loop = asyncio.new_event_loop()
        try:
            for e in self.entries:
                srv = loop.run_until_complete(asyncio.start_server(
                    functools.partial(self._serve, e), self.host, e.port, reuse_address=True, limit=_READ_BYTES))
                self._servers.append(srv)
                # Port 0 in the plan: the kernel's choice, bound here and kept (write_plan), so
                # that no other process can take it between a pick and this bind.
                e.port = srv.sockets[0].getsockname()[1]
        except OSError as err:
            self._error = err
            self._ready.set()
            return
        self._ready.set()
        try:
            loop.run_forever()
        finally:
            for srv in self._servers:
                srv.close()
            loop.close()

    async def _serve(self, e: Entry, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        c = self.count[e.identity]
        if time.monotonic() < self._cut_until.get(e.identity, 0.0):
            c.refused += 1
            writer.close()
            return
        _nodelay(writer)
        try:
            up_r, up_w = await asyncio.open_unix_connection(self.upstream, limit=_READ_BYTES)
        except OSError:
            c.refused += 1  # the router is not (yet, or any more) there: the client retries
            writer.close()
            return
        _nodelay(up_w)
        c.connections += 1
        bucket = _Bucket(e.rate_bytes_per_s, e.burst_bytes)
        messages = _Bucket(e.rate_msgs_per_s, e.burst_msgs)
        wire = WireCounter() if e.rate_msgs_per_s != float("inf") else None
        if wire is not None:
            c.wires.append(wire)

        async def hold(wait: float, n_bytes: int) -> None:
            c.held += 1
            c.held_s += wait
            c.held_bytes += n_bytes
            await asyncio.sleep(wait)  # not reading: TCP holds the sender back

        async def inbound() -> None:
            while data := await reader.read(_READ_BYTES):
                c.bytes_in += len(data)
                if wire is None:  # bytes only
                    up_w.write(data)
                    await up_w.drain()
                    if (wait := bucket.charge(len(data))) > 0:
                        await hold(wait, len(data))
                    continue
                # Counted in messages too: relayed a whole batch at a time, each once counted.
                unparsed = wire.unparsed
                for framed, n in wire.feed(data):
                    if wire.unparsed != unparsed:
                        c.unparsed += wire.unparsed - unparsed
                        unparsed = wire.unparsed
                        log.warning("gate: %s sent a batch the message counter could not read (charged at the worst "
                                    "case): %s", e.identity, wire.first_error)
                    if n > e.burst_msgs:
                        # More messages in one batch than the identity's whole burst: no honest
                        # role sends that (its largest batch is its declarations at start, ~40);
                        # a flood of tiny puts does. Not relayed: the connection is cut.
                        c.cut += 1
                        c.cut_messages += n
                        # Its next connection waits until a burst would have refilled: a
                        # flooder that reconnects at once is refused meanwhile.
                        self._cut_until[e.identity] = time.monotonic() + e.burst_msgs / e.rate_msgs_per_s
                        log.warning("gate: %s sent %d messages in one batch (its burst: %.0f): connection cut",
                                    e.identity, n, e.burst_msgs)
                        return
                    c.messages_in += n
                    up_w.write(framed)
                    await up_w.drain()
                    wait = bucket.charge(len(framed))
                    if (wait_m := messages.charge(n)) > wait:
                        wait = wait_m
                        c.held_for_messages += 1
                    if wait > 0:
                        await hold(wait, len(framed))

        async def outbound() -> None:
            while data := await up_r.read(_READ_BYTES):
                c.bytes_out += len(data)
                writer.write(data)
                await writer.drain()

        tasks = [asyncio.ensure_future(inbound()), asyncio.ensure_future(outbound())]
        with contextlib.suppress(Exception):
            await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        for t in tasks:
            t.cancel()
        for w in (writer, up_w):
            with contextlib.suppress(Exception):
                w.close()
        if wire is not None:
            wire.release()  # its counts stay; a batch half read is let go


def _nodelay(w: asyncio.StreamWriter) -> None:
    sock = w.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


def read_plan(path: str | Path) -> tuple[list[Entry], str]:
    """A gate plan (JSON written by the supervisor): ``{"upstream": SOCKET, "entries":
    [{"identity", "port", "rate_bytes_per_s", "burst_bytes"}, ...]}``."""
    doc = json.loads(Path(path).read_text())
    return [Entry(**e) for e in doc["entries"]], doc["upstream"]


def write_plan(path: str | Path, entries: list[Entry], upstream: str) -> None:
    """Write a gate plan (atomically: a reader sees the old plan or the new one). The router
    writes its plan back once its gate listens, with the ports it bound for the plan's 0s:
    the supervisor reads them from there, and a restarted router binds the same ones."""
    path = Path(path)
    doc = {"upstream": upstream, "entries": [asdict(e) for e in entries]}  # read_plan's Entry(**e) back
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc))
    tmp.replace(path)


class CountsFile:
    """The gate's counts, written to ``path`` (atomically) once a second while they change
    and at the end; a restarted router adds to what its predecessor wrote."""

    def __init__(self, gate: Gate, path: str | Path):
        self.gate, self.path = gate, Path(path)
        self.base: dict[str, dict[str, Any]] = {}
        with contextlib.suppress(OSError, ValueError):
            self.base = json.loads(self.path.read_text())
        self._last: str | None = None

    def total(self) -> dict[str, dict[str, Any]]:
        return _sum_counts([self.base, self.gate.counts()])

    def write(self) -> None:
        text = json.dumps(self.total(), sort_keys=True)
        if text == self._last:
            return
        tmp = self.path.with_suffix(".tmp")
        try:
            tmp.write_text(text)
            tmp.replace(self.path)
            self._last = text
        except OSError as err:
            logging.warning("gate: could not write %s: %s", self.path, err)


def _sum_counts(docs: list[dict[str, dict[str, Any]]]) -> dict[str, dict[str, Any]]:
    """Counts per identity, summed over ``docs``."""
    out: dict[str, dict[str, Any]] = {}
    for doc in docs:
        for ident, c in doc.items():
            acc = out.setdefault(ident, {})
            for k, v in c.items():
                if isinstance(v, dict):  # messages by kind
                    sub = acc.setdefault(k, {})
                    for kk, vv in v.items():
                        sub[kk] = sub.get(kk, 0) + vv
                else:
                    acc[k] = round(acc.get(k, 0) + v, 4)
    return dict(sorted(out.items()))


def merged_counts(paths: list[Path]) -> dict[str, dict[str, Any]]:
    """The counts of every router's gate of a run, summed per identity."""
    docs = []
    for p in paths:
        try:
            docs.append(json.loads(p.read_text()))
        except (OSError, ValueError):
            continue
    return _sum_counts(docs)
