"""Zenoh sessions from the shared bus flags, and an inbox that hands samples to one thread.

Every role accepts the same flags (as zenoh-python's examples do): ``--mode``,
``--connect``, ``--listen``, ``--config`` and ``--no-multicast-scouting`` (scouting is
off unless ``--multicast-scouting`` is given: it does not cross Docker networks and a
swarm on a shared LAN should not discover strangers).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import queue
import threading
import time
from dataclasses import dataclass, field
from typing import NamedTuple

import zenoh

log = logging.getLogger("swarmrt.bus")

__all__ = ["BusConfig", "add_bus_args", "bus_config_from_args", "open_session", "Inbox", "Sample", "RouterLinks",
           "shared_memory_enabled", "apply_shared_memory"]


@dataclass
class BusConfig:
    mode: str = "peer"
    connect: list[str] = field(default_factory=list)
    listen: list[str] = field(default_factory=list)
    config_file: str | None = None
    multicast_scouting: bool = False
    connect_timeout_ms: int = 10_000
    # This process's identity on the bus (swarmrt.security): a credential file, or one in
    # hand (an --id auto agent's, once the world has given it its satellite).
    credential_file: str | None = None
    credential: object | None = None  # a swarmrt.security.Credential

    def identity(self):
        """The credential this configuration connects with (None: none)."""
        if self.credential is None and self.credential_file:
            from swarmrt.security import load_credential

            self.credential = load_credential(self.credential_file)
        return self.credential

    def zenoh_config(self) -> zenoh.Config:
        cfg = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        if self.connect:
            cfg.insert_json5("connect/endpoints", json.dumps(self.connect))
            cfg.insert_json5("connect/timeout_ms", json.dumps(self.connect_timeout_ms))
            # Rejoin quickly after a partition heals (Zenoh's default backs off to 4 s).
            cfg.insert_json5("connect/retry", json.dumps({"period_init_ms": 250, "period_max_ms": 1000, "period_increase_factor": 2}))
        if self.listen:
            cfg.insert_json5("listen/endpoints", json.dumps(self.listen))
        cfg.insert_json5("scouting/multicast/enabled", json.dumps(self.multicast_scouting))
        # Every put carries the publishing session's clock (an HLC time, NTP64; Zenoh only
        # stamps on routers by default): the recorder's receive time minus it is the
        # message's one-way bus latency (containers share the host's clock; across hosts
        # it includes their clock offset).
        cfg.insert_json5("timestamping/enabled", "true")
        apply_shared_memory(cfg)
        if (cred := self.identity()) is not None:
            cred.apply(cfg)
        return cfg

    def as_args(self) -> list[str]:
        """The same configuration as command-line flags (for child processes)."""
        out = ["--mode", self.mode]
        for e in self.connect:
            out += ["--connect", e]
        for e in self.listen:
            out += ["--listen", e]
        if self.config_file:
            out += ["--config", self.config_file]
        if self.multicast_scouting:
            out.append("--multicast-scouting")
        if self.credential_file:
            out += ["--credential", self.credential_file]
        return out


def shared_memory_enabled() -> bool:
    """Zenoh's shared-memory transport, off unless ``SWARM_ZENOH_SHM=1``.

    Zenoh (1.6+) moves payloads of 3 KB and more through shared memory by default. For a
    swarm of clients behind a router on one host it costs more than it saves: measured at
    n = 40 (``swarm run``, loopback), an agent's Zenoh receive thread took 16.7 ms of CPU a
    step with it and 3.3 ms without, and a step 2.2 s of wall time against 1.3 s. Across
    containers it falls back to copies anyway."""
    return os.environ.get("SWARM_ZENOH_SHM", "0") == "1"


def apply_shared_memory(cfg: zenoh.Config) -> None:
    cfg.insert_json5("transport/shared_memory/enabled", json.dumps(shared_memory_enabled()))


def add_bus_args(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("bus (Zenoh)")
    g.add_argument("--mode", choices=["peer", "client", "router"], default=os.environ.get("SWARM_ZENOH_MODE", "peer"))
    g.add_argument("--connect", action="append", default=None, help="endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", action="append", default=None, help="endpoint to listen on (repeatable)")
    g.add_argument("--config", default=None, help="a Zenoh JSON5 configuration file")
    g.add_argument("--multicast-scouting", action="store_true", help="enable multicast scouting (off by default)")
    g.add_argument("--no-multicast-scouting", dest="multicast_scouting", action="store_false")
    g.add_argument("--credential", default=os.environ.get("SWARM_CREDENTIAL") or None,
                   help="this process's credential on the bus (a <identity>.json of `swarm keys`; env SWARM_CREDENTIAL)")


def bus_config_from_args(a: argparse.Namespace, sc=None) -> BusConfig:
    """The bus flags as a configuration. ``sc``: the role's scenario; with
    ``emulator.security: off`` the credential is left out (a router without a password
    dictionary refuses a session that offers one), loudly."""
    connect = a.connect if a.connect is not None else [e for e in os.environ.get("SWARM_ZENOH_CONNECT", "").split(",") if e]
    cred = a.credential
    if sc is not None and not sc.emulator.security:
        log.warning("SECURITY OFF (emulator.security: off): connecting without a credential%s",
                    f" (ignoring {cred})" if cred else "")
        cred = None
    return BusConfig(mode=a.mode, connect=connect, listen=a.listen or [], config_file=a.config, multicast_scouting=a.multicast_scouting,
                     credential_file=cred)


def open_session(cfg: BusConfig) -> zenoh.Session:
    """A Zenoh session of ``cfg``. A client given several routers reaches the first one up,
    within ``connect_timeout_ms`` in all.

    Why not one ``zenoh.open`` with every endpoint: a Zenoh 1.x client whose
    ``connect/timeout_ms`` is set retries its *first* endpoint until that timeout and never
    tries the others (measured: endpoints [a router that is down, one that is up], 10 s,
    then "Unable to connect to any of [...] Timeout!"; the live one first: connected at
    once). A chaos campaign found it: an agent restarted while the first of two meshed
    routers was down exited with that error. So each attempt puts another endpoint first,
    with a share of the timeout, until one connects or the time is up."""
    if cfg.mode != "client" or len(cfg.connect) < 2 or cfg.connect_timeout_ms <= 0:  # (0, -1: Zenoh's own meanings)
        return zenoh.open(cfg.zenoh_config())
    total_s = cfg.connect_timeout_ms / 1e3
    deadline = time.monotonic() + total_s
    share_ms = max(500, cfg.connect_timeout_ms // (2 * len(cfg.connect)))
    attempt = 0
    while True:
        first = attempt % len(cfg.connect)
        order = cfg.connect[first:] + cfg.connect[:first]
        left_ms = int((deadline - time.monotonic()) * 1e3)
        try:
            return zenoh.open(replace_config(cfg, connect=order, connect_timeout_ms=max(100, min(share_ms, left_ms))).zenoh_config())
        except zenoh.ZError:
            attempt += 1
            if time.monotonic() >= deadline:
                raise


def replace_config(cfg: BusConfig, **changes) -> BusConfig:
    """``cfg`` with ``changes`` (its credential kept as loaded)."""
    import dataclasses

    return dataclasses.replace(cfg, **changes)


class Sample(NamedTuple):
    key: str
    payload: bytes
    kind: str  # "put" or "delete"
    published_ns: int | None = None  # the sample's timestamp (publisher's clock, Unix ns), if stamped
    received_ns: int = 0  # when the callback saw it (time.time_ns())


class RouterLinks:
    """Whether a session reaches some router: ``on_change(up)`` is called (on Zenoh's thread,
    so it must only queue) each time that changes, from its links' open and close events.
    One place for every reader of the bus's health (a role's ``Node``, the recorder)."""

    def __init__(self, session: zenoh.Session, on_change):
        self._routers: set[str] = set()
        self._lock = threading.Lock()
        self._on_change = on_change
        self._listener = session.info.declare_transport_events_listener(self._on_event, history=True)

    @property
    def up(self) -> bool:
        with self._lock:
            return bool(self._routers)

    def _on_event(self, ev) -> None:
        if ev.transport.whatami != zenoh.WhatAmI.ROUTER:
            return
        with self._lock:
            before = bool(self._routers)
            (self._routers.add if ev.kind == zenoh.SampleKind.PUT else self._routers.discard)(str(ev.transport.zid))
            after = bool(self._routers)
        if before != after:
            self._on_change(after)

    def undeclare(self) -> None:
        self._listener.undeclare()


class Inbox:
    """Zenoh callbacks push here (they must never block); one worker thread pulls.

    Callbacks make no Zenoh call and touch no role state: the role's state is touched by
    the one thread that pulls. With ``decode`` (a pure function of the sample: parse and
    validate, or None to drop it), the callback decodes before queueing: the payload is
    still in the cache it just arrived in, and decoding overlaps the role's own work
    (measured at n = 40, decoding on the pulling thread cost about twice the CPU, the
    data having gone cold in the queue).
    """

    def __init__(self, maxsize: int = 100_000, decode=None):
        # SimpleQueue (in C, unbounded) with the bound kept here: a third of the cost of
        # queue.Queue's locks and conditions, paid twice for each of the ~120 samples an
        # agent handles a step at n = 40.
        self._q: queue.SimpleQueue = queue.SimpleQueue()
        self._maxsize = maxsize
        self._decode = decode
        self.dropped = 0
        self._lock = threading.Lock()

    def callback(self, sample) -> None:
        if self._q.qsize() >= self._maxsize:
            with self._lock:
                self.dropped += 1
            return
        now = time.time_ns()
        kind = "delete" if sample.kind == zenoh.SampleKind.DELETE else "put"
        ts = sample.timestamp
        pub = ts.get_time_as_ntp64().as_nanos() if ts is not None else None
        item = Sample(str(sample.key_expr), bytes(sample.payload.to_bytes()), kind, pub, now)
        if self._decode is not None:
            item = self._decode(item)
            if item is None:
                return
        self._q.put(item)

    def put_event(self, item) -> None:
        """A local event (not from the bus) for the same worker thread."""
        self._q.put(item)

    def get(self, timeout: float | None):
        """The next item (a Sample, or what ``decode`` made of it), or None after ``timeout``."""
        try:
            return self._q.get(timeout=timeout) if timeout is None or timeout > 0 else self._q.get_nowait()
        except queue.Empty:
            return None
