"""The live view's process: the bus in, the Foxglove WebSocket protocol out.

python -m swarm.live.server --run RUN --scenario FILE [--ws HOST:PORT] [--info FILE]
                            [--max-rate HZ] [bus flags: --connect ... --credential viewer.json]

It connects as ``viewer`` (read-only), subscribes to the truth, the posterior estimates, the
measurement batches, the link counters and the faults, and feeds them to the recorder's
:class:`~swarm.record.foxglove.FoxgloveDeriver` whose sink is the SDK's server
(:class:`~swarm.live.sink.LiveSink`). Nothing it does can hold the swarm back:

* it puts nothing on the bus and answers no query: no role ever waits for it;
* Zenoh's callbacks only decode and queue (:class:`~swarmrt.bus.session.Inbox`, bounded:
  beyond it samples are dropped and counted);
* the main loop takes whatever has arrived, draws only the latest of each kind and source
  (a step it had no time for is skipped, never queued), and at most ``--max-rate`` times a
  wall second; with no client subscribed it builds nothing;
* the SDK's ``log()`` never blocks: a slow client's backlog drops its oldest messages.

A client that subscribes gets the topic's last message at once (the SDK keeps none); clients
may connect and leave at any time. ``--info FILE``: once listening, a JSON file with the
address (``port`` is the one bound when asked for port 0). SIGTERM / SIGINT stop it; the SDK's
``stop()`` can wait for a client that does not read, so it is given 2 s in a daemon thread.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import queue
import sys
import threading
import time
from pathlib import Path
from typing import Any, cast

log = logging.getLogger("live")

__all__ = ["LiveView", "main", "SUBSCRIBED_KINDS"]

#: What the view subscribes to (the ``viewer`` identity's grants allow these and no more).
SUBSCRIBED_KINDS = ("truth", "est", "meas", "links", "fault")
_DRAWN_ONCE = ("truth", "est", "meas", "links")  # of these only the latest of each source (key) is drawn
_MAX_BATCH = 20_000


class _Listener:
    """SDK server callbacks (its own thread): remember who subscribed to what."""

    def __init__(self, view: LiveView):
        self.view = view

    def on_subscribe(self, client, channel) -> None:
        self.view.subscribed.put(channel.topic)
        self.view.clients_seen.add(client.id)

    def on_unsubscribe(self, client, channel) -> None:
        pass


class LiveView:
    def __init__(self, sc, run: str, bus, host: str = "127.0.0.1", port: int = 8765, max_rate_hz: float = 20.0,
                 info: str | Path | None = None):
        from swarm.live.sink import LiveSink
        from swarm.record.foxglove import FoxgloveDeriver
        from swarmrt.bus.messages import Keys, prepare
        from swarmrt.bus.session import Inbox

        self.sc = sc
        self.run = run
        self.keys = Keys(run)
        self.bus = bus
        self.host, self.port = host, port
        self.min_period = 1.0 / max_rate_hz if max_rate_hz > 0 else 0.0
        self.info = Path(info) if info else None
        self.sink = LiveSink()
        self.deriver = FoxgloveDeriver.for_scenario(self.sink, sc, images=False)
        assert self.deriver.builder is not None
        self.sink.advertise(self.deriver.builder.topics())
        self.stop = threading.Event()
        self.subscribed: queue.SimpleQueue = queue.SimpleQueue()
        self.clients_seen: set[int] = set()
        self.inbox = Inbox(maxsize=100_000, decode=self._decode)
        prepare("meas")
        self.server: Any = None  # foxglove.WebSocketServer, once started
        self.session: Any = None  # zenoh.Session
        self._subs: list = []
        self.token: Any = None
        self.last: dict[tuple[str, str], tuple[object, int]] = {}  # (kind, key) → the latest message drawn and its time
        self.drawn_batches = 0
        self.skipped = 0
        self._info: dict | None = None

    # -- the bus ---------------------------------------------------------------------------
    def _decode(self, s):
        """(In Zenoh's thread) keep what the view may draw, undecoded: decoding is left to the
        loop, for the messages it draws (the latest of each kind and source)."""
        from swarmrt.bus.messages import MessageError, parse_key

        try:
            run, kind, sat = parse_key(s.key)
        except MessageError:
            return None
        if run != self.run or kind not in SUBSCRIBED_KINDS or s.kind != "put":
            return None
        return kind, sat, s.key, s.payload, s.received_ns or time.time_ns()

    def _subscribe(self) -> None:
        """Subscribe to the bus (someone is watching): the router sends the view nothing before."""
        if self._subs or self.session is None:
            return
        k = self.keys
        self._subs = [self.session.declare_subscriber(key, self.inbox.callback)
                      for key in (k.truth(), k.est(), k.meas(), k.links(), k.faults())]
        log.info("a client subscribed: following the bus")

    def _unsubscribe(self) -> None:
        """No client wants anything: stop following the bus (it then costs the swarm nothing)."""
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        if self._subs:
            log.info("no client subscribed: not following the bus")
        self._subs = []

    def start(self) -> None:
        import foxglove

        from swarmrt.bus.session import open_session

        self.server = foxglove.start_server(name=f"swarm-coloc {self.run}", host=self.host, port=self.port,
                                            context=self.sink.context, server_listener=cast(Any, _Listener(self)))
        self.port = self.server.port
        url = f"ws://{self.host if ':' not in self.host else f'[{self.host}]'}:{self.port}"
        self._info = {"url": url, "host": self.host, "port": self.port, "run": self.run, "pid": os.getpid(), "topics": self.sink.topics}
        self._write_info()
        log.info("serving the Foxglove WebSocket protocol on %s (%d topics)", url, len(self.sink.topics))
        print(f"LIVE {url}", flush=True)
        self.session = session = open_session(self.bus)
        self.token = session.liveliness().declare_token(self.keys.alive("viewer", 0))

    def _write_info(self) -> None:
        if self.info is not None:
            tmp = self.info.with_suffix(".tmp")
            tmp.write_text(json.dumps(self._info, indent=1) + "\n")
            tmp.replace(self.info)

    def stats(self) -> dict:
        """What the view did: scene messages sent, batches drawn, bus messages not drawn
        (newer ones were), samples dropped at the inbox, clients, its process's CPU time."""
        return {"scene_messages": self.sink.sent, "batches_drawn": self.drawn_batches, "not_drawn": self.skipped,
                "inbox_dropped": self.inbox.dropped, "clients": len(self.clients_seen), "cpu_s": time.process_time()}

    # -- the loop ----------------------------------------------------------------------------
    def _batch(self, timeout: float) -> list:
        first = self.inbox.get(timeout)
        if first is None:
            return []
        out = [first]
        while len(out) < _MAX_BATCH and (item := self.inbox.get(0)) is not None:
            out.append(item)
        return out

    def _open(self, kind: str, sat, key: str, payload):
        """The message decoded and checked against its key, or None (malformed: dropped)."""
        from swarmrt.bus.messages import MessageError
        from swarmrt.bus.receive import receive

        try:
            return receive(key, payload, self.run, expect=kind).msg
        except MessageError:
            return None

    def process(self, batch: list) -> None:
        """Draw one batch: every truth (one small message a step: the errors of a step need
        its truth) and fault is read, and of the estimates, measurement batches and link
        counters only the last to arrive from each source (its newest: a publisher's messages
        arrive in order); the others are not even decoded. Link states are then what happened
        since the last step drawn."""
        last: dict[str, int] = {}
        for idx, (kind, _sat, key, _payload, _ns) in enumerate(batch):
            if kind in _DRAWN_ONCE:
                last[key] = idx
        keep = set(last.values())  # the last truth, and the last estimate, batch and counters of each source
        order = {"truth": 0, "links": 1, "fault": 1, "meas": 2, "est": 3}  # the truth first: the others' steps need it
        for idx, (kind, sat, key, payload, ns) in sorted(enumerate(batch), key=lambda e: (order[e[1][0]], e[0])):
            if kind not in ("truth", "fault") and idx not in keep:
                self.skipped += 1
                continue
            msg = self._open(kind, sat, key, payload)
            if msg is None or (kind == "est" and msg.phase != "posterior"):
                continue
            self.deriver.on_message(kind, msg, ns, draw=kind == "fault" or idx in keep)
            if kind in _DRAWN_ONCE:
                self.last[(kind, key)] = (msg, ns)
        self.drawn_batches += 1

    def _refresh(self) -> None:
        """Clients that just subscribed: the last message of their topics again, or the
        latest bus messages drawn afresh when that topic was never built (no one wanted it)."""
        topics = set()
        while True:
            try:
                topics.add(self.subscribed.get_nowait())
            except queue.Empty:
                break
        if not topics:
            return
        redraw = False
        for t in topics:
            if not self.sink.resend(t):
                redraw = True
        if redraw:
            items = sorted(self.last.items(), key=lambda kv: (kv[0][0] != "truth", kv[0][0] == "est"))
            for (kind, _src), (msg, ns) in items:
                if kind != "links":  # counters are cumulative: drawing them again shows nothing new
                    self.deriver.on_message(kind, msg, ns, draw=True)

    def run_loop(self) -> None:
        next_draw = 0.0
        idle_since: float | None = None
        while not self.stop.is_set():
            wait = max(0.0, next_draw - time.monotonic())
            if wait > 0:
                self.stop.wait(wait)  # let what arrives meanwhile pile up: only the latest is drawn
                if self.stop.is_set():
                    break
            # Follow the bus only while some client is subscribed to something (2 s of grace).
            if any(self.sink.wants(t) for t in self.sink.topics):
                idle_since = None
                self._subscribe()
            elif self._subs:
                idle_since = idle_since or time.monotonic()
                if time.monotonic() - idle_since > 2.0:
                    self._unsubscribe()
            self._refresh()
            batch = self._batch(0.2)
            if not batch:
                continue
            self.process(batch)
            next_draw = time.monotonic() + self.min_period

    def close(self) -> None:
        self._unsubscribe()
        if self.token is not None:
            with contextlib.suppress(Exception):
                self.token.undeclare()
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        if self.server is not None:
            # stop() waits for every client's close frame, with no timeout: bounded here.
            t = threading.Thread(target=self.server.stop, daemon=True)
            t.start()
            t.join(2.0)
        st = self.stats()
        log.info("stopped: %d scene messages sent, %d batches drawn, %d bus messages not drawn (newer ones were), "
                 "%d dropped at the inbox, %d clients, %.2f s CPU", st["scene_messages"], st["batches_drawn"], st["not_drawn"],
                 st["inbox_dropped"], st["clients"], st["cpu_s"])
        if self._info is not None:
            self._info["stats"] = st
            with contextlib.suppress(OSError):
                self._write_info()


def main(argv=None) -> int:
    from swarmrt import tuning

    tuning.tune_process()
    from swarm.live import DEFAULT_ADDRESS, parse_address
    from swarmrt.bus.session import bus_config_from_args
    from swarmrt.node import install_term_handler, load_role_scenario, role_arg_parser, setup_logging

    p: argparse.ArgumentParser = role_arg_parser("the live 3-D view: the bus in, the Foxglove WebSocket protocol out")
    p.add_argument("--ws", default=DEFAULT_ADDRESS, metavar="HOST:PORT", help=f"where to serve (default {DEFAULT_ADDRESS}; port 0: any)")
    p.add_argument("--info", default=None, help="write the address served (JSON) here once listening")
    p.add_argument("--max-rate", type=float, default=20.0, help="draw at most this many times a wall second (default 20)")
    a = p.parse_args(argv)
    setup_logging("live", a.verbose)
    try:
        host, port = parse_address(a.ws)
    except ValueError as exc:
        p.error(f"--ws {exc}")
    sc = load_role_scenario(a.scenario, a.sets)
    view = LiveView(sc, a.run, bus_config_from_args(a, sc), host, port, a.max_rate, a.info)
    install_term_handler(view.stop)
    try:
        view.start()
    except RuntimeError as exc:  # the SDK's: the port is taken, ...
        log.error("cannot serve on %s: %s", a.ws, exc)
        view.close()
        return 2
    try:
        view.run_loop()
    finally:
        view.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
