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
import os
import random
import socket
import ssl
import threading
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

from swarm.supervise.zenoh_wire import WireCounter

log = logging.getLogger(__name__)

_READ_BYTES = 64 * 1024  # one read from a connection: the unit the bucket is charged
_BOUNDED_KINDS = {"est", "health", "fault", "recorded"}  # kinds the scenario sizes (the rest of MAX_PAYLOAD_BYTES: the world's)
OTHER = "other"  # the shared entry: identities without their own port (tools, the fault CLI)
ANY = "*"  # an entry that serves every identity at one port, each known by its handshake (compose's router)
UNIDENTIFIED = "unidentified"  # counts of connections to an ANY entry that never said who they are


@dataclass
class Entry:
    """One identity's port and its bucket's size (port 0: the kernel's choice; -1: not
    listened, the identity's limits for an :data:`ANY` entry)."""

    identity: str
    port: int
    rate_bytes_per_s: float
    burst_bytes: float
    rate_msgs_per_s: float = float("inf")  # Zenoh messages (swarm.supervise.zenoh_wire); inf: not counted
    burst_msgs: float = float("inf")
    host: str = ""  # the address it listens on ("": the gate's, loopback)
    tls_certificate: str = ""  # a certificate and key: it speaks TLS to its clients (compose's remote agents)
    tls_private_key: str = ""


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


def plan_entries(sc: Any) -> list[Entry] | None:
    """A run's gate entries (every identity but the mesh, at port 0: the plan's writer
    reserves ports for them, :meth:`PortReservation.assign`, or the gate chooses), sized from
    scenario ``sc``; None when the gate is off
    (``emulator.gate: false``, or ``SWARM_ROUTER_GATE=off`` to measure without it). The
    shared ``other`` entry (tools, the fault CLI, a kit) gets an agent's buckets."""
    from swarmrt.bus.messages import IDENTITIES
    from swarmrt.security import agent_identities

    em = sc.emulator
    if not em.gate or os.environ.get("SWARM_ROUTER_GATE", "on") == "off":
        return None
    names = [*(i for i in IDENTITIES if i != "mesh"), *agent_identities(sc.n_sats)]
    limits = gate_limits(sc.n_sats, em.recorder_max_lag_steps, sc.links.enabled, names, em.gate_steps_per_s)
    limits[OTHER] = limits["agent-0"]
    msg_limits = gate_message_limits(sc.n_sats, em.recorder_max_lag_steps, sc.links.enabled, names, em.gate_steps_per_s)
    msg_limits[OTHER] = msg_limits["agent-0"]
    return [Entry(name, 0, rate, burst, *msg_limits[name]) for name, (rate, burst) in limits.items()]


def handshake_plan(sc: Any, endpoints: list[str], certificate: str = "", private_key: str = "") -> list[Entry] | None:
    """A gate plan that serves every identity at each of ``endpoints`` (``tcp/HOST:PORT`` or
    ``tls/HOST:PORT``, the latter with the router's ``certificate`` and ``private_key``),
    each connection held to the buckets of the identity its handshake names (:data:`ANY`);
    the limits as :func:`plan_entries` sizes them, the mesh (another router, everyone's
    traffic) unlimited. None when the gate is off. Compose's router: its containers and
    remote agents know one endpoint, not a port per identity."""
    entries = plan_entries(sc)
    if entries is None:
        return None
    for e in entries:
        e.port = -1
    entries.append(Entry("mesh", -1, float("inf"), float("inf")))
    for ep in endpoints:
        scheme, _, addr = ep.partition("/")
        host, _, port = addr.rpartition(":")
        if scheme not in ("tcp", "tls") or not host or not port.isdigit():
            raise ValueError(f"a gate endpoint is tcp/HOST:PORT or tls/HOST:PORT, not {ep!r}")
        if scheme == "tls" and not (certificate and private_key):
            raise ValueError(f"{ep}: a TLS gate endpoint needs the router's certificate and key (keys made with TLS)")
        entries.append(Entry(ANY, int(port), float("inf"), float("inf"), host=host,
                             tls_certificate=certificate if scheme == "tls" else "",
                             tls_private_key=private_key if scheme == "tls" else ""))
    return entries


def loopback_endpoints(entries: list[Entry], host: str = "127.0.0.1") -> dict[str, str]:
    """Each identity's way in (``tcp/HOST:PORT``) through a gate whose ``entries`` have their ports."""
    missing = [e.identity for e in entries if e.port == 0]
    if missing:
        raise RuntimeError(f"the gate did not say which port it bound for {', '.join(missing[:3])}")
    return {e.identity: f"tcp/{host}:{e.port}" for e in entries if e.port > 0}


class Gate:
    """The relay (an asyncio loop on its own thread). ``upstream``: the router's Unix socket.

    An entry whose identity is :data:`ANY` serves every identity at one port: it reads each
    connection's identity from its Zenoh handshake (:func:`swarm.supervise.zenoh_wire.open_syn_user`,
    the user name the router then authenticates) and gives it that identity's buckets (an
    entry of the plan at port -1: limits only; an unknown user gets ``other``'s). Until then
    (the handshake's few hundred bytes) the connection is held to ``other``'s buckets. An
    entry with a certificate and key speaks TLS to its clients (it terminates TLS, as the
    router would, with the router's own certificate) and relays the plain Zenoh stream."""

    def __init__(self, entries: list[Entry], upstream: str, host: str = "127.0.0.1"):
        self.entries = entries
        self.upstream = upstream
        self.host = host
        self.count = {e.identity: _Count() for e in entries if e.identity != ANY}
        self.limits = {e.identity: e for e in entries if e.identity != ANY}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._servers: list[asyncio.base_events.Server] = []
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._cut_until: dict[str, float] = {}  # an identity whose connection was cut: none before then
        self._ports = PortReservation()  # the ports it chose for a plan's 0s

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
        self._ports.release()

    def counts(self) -> dict[str, dict[str, Any]]:
        return {k: c.as_dict() for k, c in self.count.items()}

    def _run(self) -> None:
        self._loop = loop = asyncio.new_event_loop()
        try:
            for e in self.entries:
                if e.port < 0:
                    continue  # an identity's limits only (served by an ANY entry)
                tls = None
                if e.tls_certificate:
                    tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
                    tls.load_cert_chain(e.tls_certificate, e.tls_private_key)
                serve = functools.partial(self._serve, e)
                # Port 0 in the plan: a port chosen and bound here and kept (write_plan); a
                # restarted router binds it again (its clients know it). A plan's writer that
                # outlives its routers (LocalSwarm) reserves its ports itself (PortReservation).
                port = e.port if e.port != 0 else self._ports.take(e.host or self.host)  # (held while this gate lives)
                srv = loop.run_until_complete(asyncio.start_server(
                    serve, e.host or self.host, port, reuse_address=True, limit=_READ_BYTES, ssl=tls))
                self._servers.append(srv)
                e.port = srv.sockets[0].getsockname()[1]
        except (OSError, ssl.SSLError) as err:
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

    def _cut(self, identity: str) -> bool:
        return time.monotonic() < self._cut_until.get(identity, 0.0)

    async def _serve(self, e: Entry, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        by_handshake = e.identity == ANY
        if not by_handshake and self._cut(e.identity):
            self.count[e.identity].refused += 1
            writer.close()
            return
        _nodelay(writer)
        try:
            up_r, up_w = await asyncio.open_unix_connection(self.upstream, limit=_READ_BYTES)
        except OSError:
            # the router is not (yet, or any more) there: the client retries
            self.count.setdefault(e.identity if not by_handshake else UNIDENTIFIED, _Count()).refused += 1
            writer.close()
            return
        _nodelay(up_w)
        provisional = self.limits.get(OTHER, e)
        first = e if not by_handshake else provisional
        wire = WireCounter() if by_handshake or first.rate_msgs_per_s != float("inf") else None
        conn = _Conn(first, self.count[e.identity] if not by_handshake else _Count())
        if not by_handshake:
            conn.c.connections += 1
            if wire is not None:
                conn.c.wires.append(wire)

        def identify(user: str | None) -> bool:
            """The handshake said who: that identity's buckets and counts from here on
            (what came before added to them). False: the identity is cut for now."""
            name = user if user is not None and user in self.limits else OTHER
            pre = conn.c
            conn.identified = True
            if self._cut(name):
                self.count.setdefault(name, _Count()).refused += 1
                return False
            conn.bind(self.limits.get(name, provisional), self.count.setdefault(name, _Count()))
            conn.c.connections += 1
            conn.c.bytes_in += pre.bytes_in
            conn.c.bytes_out += pre.bytes_out
            if wire is not None:
                conn.c.wires.append(wire)
            return True

        async def hold(wait: float, n_bytes: int) -> None:
            c = conn.c
            c.held += 1
            c.held_s += wait
            c.held_bytes += n_bytes
            await asyncio.sleep(wait)  # not reading: TCP holds the sender back

        counting = wire is not None

        async def inbound() -> None:
            nonlocal counting
            while data := await reader.read(_READ_BYTES):
                conn.c.bytes_in += len(data)
                if not counting or wire is None:  # bytes only
                    up_w.write(data)
                    await up_w.drain()
                    if (wait := conn.bucket.charge(len(data))) > 0:
                        await hold(wait, len(data))
                    continue
                # Counted in messages too: relayed a whole batch at a time, each once counted.
                unparsed = wire.unparsed
                for framed, n in wire.feed(data):
                    if by_handshake and not conn.identified and wire.user is not None and not identify(wire.user):
                        return  # cut a moment ago: refused
                    c, lim = conn.c, conn.e
                    if wire.unparsed != unparsed:
                        c.unparsed += wire.unparsed - unparsed
                        unparsed = wire.unparsed
                        log.warning("gate: %s sent a batch the message counter could not read (charged at the worst "
                                    "case): %s", lim.identity, wire.first_error)
                    if n > lim.burst_msgs:
                        # More messages in one batch than the identity's whole burst: no honest
                        # role sends that (its largest batch is its declarations at start, ~40);
                        # a flood of tiny puts does. Not relayed: the connection is cut.
                        c.cut += 1
                        c.cut_messages += n
                        # Its next connection waits until a burst would have refilled: a
                        # flooder that reconnects at once is refused meanwhile.
                        self._cut_until[lim.identity] = time.monotonic() + lim.burst_msgs / lim.rate_msgs_per_s
                        log.warning("gate: %s sent %d messages in one batch (its burst: %.0f): connection cut",
                                    lim.identity, n, lim.burst_msgs)
                        return
                    c.messages_in += n
                    up_w.write(framed)
                    await up_w.drain()
                    wait = conn.bucket.charge(len(framed))
                    if (wait_m := conn.messages.charge(n)) > wait:
                        wait = wait_m
                        c.held_for_messages += 1
                    if wait > 0:
                        await hold(wait, len(framed))
                if conn.identified and conn.e.rate_msgs_per_s == float("inf"):
                    # Known by its handshake as an identity whose messages are not limited (the
                    # world, the mesh): its bytes only from here on, as with a port of its own.
                    counting = False
                    if rest := wire.take_pending():
                        up_w.write(rest)
                        await up_w.drain()

        async def outbound() -> None:
            while data := await up_r.read(_READ_BYTES):
                conn.c.bytes_out += len(data)
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
        if by_handshake and not conn.identified:  # never said who (a stranger, a port scan): counted apart
            u = self.count.setdefault(UNIDENTIFIED, _Count())
            u.connections += 1
            u.bytes_in += conn.c.bytes_in
            u.bytes_out += conn.c.bytes_out


@dataclass
class _Conn:
    """One relayed connection: the entry whose buckets it is held to, its counts, its buckets."""

    e: Entry
    c: _Count
    identified: bool = False
    bucket: _Bucket = field(init=False)
    messages: _Bucket = field(init=False)

    def __post_init__(self) -> None:
        self.bind(self.e, self.c)

    def bind(self, e: Entry, c: _Count) -> None:
        self.e, self.c = e, c
        self.bucket = _Bucket(e.rate_bytes_per_s, e.burst_bytes)
        self.messages = _Bucket(e.rate_msgs_per_s, e.burst_msgs)


class PortReservation:
    """Ports held for a run's gate while its routers come and go: chosen at random *below* the
    kernel's ephemeral range (``net.ipv4.ip_local_port_range``: no outgoing connection of the
    machine is ever given one) and each claimed by an abstract Unix socket named after it
    (``@swarm-coloc-port-<port>``, held by this process: it vanishes with it, leaves no file),
    which every other swarm process of the machine honours when it chooses. So a router killed
    by a fault and restarted finds its ports free: seen without it, 3 router restarts of ~300
    in the 20-seed repeat benchmark beside a test suite failed with "address already in use"
    (another run's gate, or an outgoing connection, had taken a port meanwhile). Why by hand:
    no library reserves TCP ports across processes. The draws are not the simulation's (a
    system generator; no number of a run depends on a port)."""

    def __init__(self) -> None:
        self._held: list[socket.socket] = []

    def take(self, host: str = "127.0.0.1", tries: int = 256) -> int:
        """One free port on ``host``, held until :meth:`release`; 0 when none could be
        found below the ephemeral range (the kernel's choice then, unheld)."""
        rng = random.SystemRandom()
        lo, hi = _below_ephemeral()
        for _ in range(tries if hi > lo else 0):
            port = rng.randint(lo, hi)
            lock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            try:
                lock.bind(f"\0swarm-coloc-port-{port}")
            except OSError:
                lock.close()
                continue  # another swarm process holds it
            try:
                with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
                    probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                    probe.bind((host, port))
            except OSError:
                lock.close()
                continue  # bound by something else
            self._held.append(lock)
            return port
        return 0

    def assign(self, entries: list[Entry]) -> list[Entry]:
        """``entries`` with a port taken here for each (a copy; 0 where none could be)."""
        return [replace(e, port=self.take(e.host or "127.0.0.1")) for e in entries]

    def release(self) -> None:
        for lock in self._held:
            lock.close()
        self._held = []


def _below_ephemeral() -> tuple[int, int]:
    """The range random ports are drawn from: up to 16,384 ports just below the ephemeral
    range, none below 10,000 ((1, 0): no room)."""
    low = 32768
    with contextlib.suppress(OSError, ValueError):
        low = int(Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split()[0])
    hi = low - 1
    lo = max(10000, hi - 16383)
    return (lo, hi) if hi - lo >= 1024 else (1, 0)


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
    and at the end; a restarted router adds to what its predecessor wrote. ``own``: a file
    of this process's own instead (``gate-router.json`` becomes ``gate-router.<start ms>.json``,
    nothing carried over): where a folder outlives runs of the same name (compose's output
    folder), the reader sums the files written since the run began (:func:`fresh_counts`)."""

    def __init__(self, gate: Gate, path: str | Path, own: bool = False):
        path = Path(path)
        if own:
            path = path.with_name(f"{path.stem}.{int(time.time() * 1000)}{path.suffix}")
        self.gate, self.path = gate, path
        self.base: dict[str, dict[str, Any]] = {}
        if not own:
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


def fresh_counts(pattern: str, since: float) -> dict[str, dict[str, Any]]:
    """The counts of the files matching ``pattern`` written at or after ``since`` (a wall
    time: the run's start), summed per identity; identities nobody connected as left out."""
    import glob

    paths = []
    for f in sorted(glob.glob(pattern)):
        with contextlib.suppress(OSError):
            if os.stat(f).st_mtime >= since:
                paths.append(Path(f))
    return seen_counts(paths)


def seen_counts(paths: list[Path]) -> dict[str, dict[str, Any]]:
    """:func:`merged_counts` of ``paths`` without the identities nobody connected (or tried to) as."""
    return {k: c for k, c in merged_counts(paths).items() if c.get("connections") or c.get("refused")}


def merged_counts(paths: list[Path]) -> dict[str, dict[str, Any]]:
    """The counts of every router's gate of a run, summed per identity."""
    docs = []
    for p in paths:
        try:
            docs.append(json.loads(p.read_text()))
        except (OSError, ValueError):
            continue
    return _sum_counts(docs)
