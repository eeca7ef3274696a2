"""What every role process shares: a session, a liveliness token, an inbox, decoding
with malformed-message accounting, and the command-line scaffolding of a role's main."""

from __future__ import annotations

import argparse
import contextlib
import gc
import logging
import signal
import sys
import threading
import time
from typing import Any

import zenoh

from swarmcore.scenario import Scenario
from swarmrt.bus.messages import MAX_PAYLOAD_DEFAULT, KeyMismatch, Keys, MessageError, counted, encode, parse_key, prepare
from swarmrt.bus.receive import receive
from swarmrt.bus.session import BusConfig, Inbox, RouterLinks, add_bus_args, bus_config_from_args, open_session
from swarmrt.protocol import BusLost, Event, Query, RunBroken, Send, Wait
from swarmrt.security import size_limit_of

__all__ = ["Node", "Event", "role_arg_parser", "setup_logging", "load_role_scenario"]

_TICK_S = 0.25  # the stall ticker's period
_STALL_S = 2.0  # a gap in its ticks this long: this process was stalled
_TOKEN_QUERY_S = 5.0  # the longest wait for the routers' answer on a token held past its hold (a loaded machine)
#: After a return (the bus back, a peer's token back), when a role sends its last steps again
#: once more (an ``again`` event): a put made while a failover still rebuilds the routers'
#: routes (the receiver's subscriptions not yet declared again where the put went) is lost
#: without a trace, and the sending again at the return itself can be such a put. (A guard:
#: of the losses the repeat benchmark saw, those traced to their cause were the supervisor's
#: connection cut by its gate, issue 35; seed 15's camera deliveries were never traced.)
_AGAIN_AFTER_S = (1.0, 3.0)
_TOKEN_ANSWER_MARGIN_S = 2.0  # past the query's timeout, before a held token whose answer never came counts gone




class Node:
    """A role's bus presence. Only the thread that calls :meth:`next_event` touches state."""

    def __init__(self, role: str, ident: int | str, run: str, n_sats: int, bus: BusConfig, announce: bool = True):
        self.role = role
        self.ident = ident
        self.name = f"{role}-{ident}" if role in ("agent",) else role
        self.n = n_sats
        self.keys = Keys(run)
        self.run = run
        self.log = logging.getLogger(self.name)
        self.inbox = Inbox(decode=self._decode)  # decoded on Zenoh's callback threads
        self._handles: list = []
        self._shallow: set[str] = set()  # message kinds decoded shallowly
        self.malformed = 0
        self.key_mismatch = 0  # of the malformed: a message on a key its sender may not use
        self._malformed_logged = 0
        # Puts of ours over the router's size limit of their key (security on: the router
        # applies swarmrt.security.size_limits; without a credential there is no limit).
        self.over_size_limit = 0
        self._malformed_lock = threading.Lock()
        self.stop = threading.Event()
        self.bus = bus
        # The bus's health as this node sees it (main thread only): router links (RouterLinks,
        # below), gaps, liveliness changes held back, limits.
        self.hold_s = 0.3
        self.bus_grace_s = 10.0
        self.bus_lost_after_s = float("inf")
        self.bus_down_since: float | None = None
        self.gaps: list[tuple[float, float]] = []  # (down, up), time.monotonic()
        self._held: dict[str, tuple[Event, float | None]] = {}  # token key -> (its DELETE, when it counts)
        self._run_over = False  # the world's last clock (done) has come
        # Held tokens whose hold is over, the routers asked whether they still have them: how
        # many times (an empty answer is asked once more, see _answered).
        self._asked: dict[str, int] = {}
        self._epoch = 0  # bumped whenever the bus came back: waits restart their timeout
        self._agains: list[float] = []  # when (monotonic, in order) an ``again`` event is due (_echo)
        # Peers whose vanished token is held longer than hold_s, by role (a stalled world:
        # agents and the selector set {"world": bus_lost_after_s}); while one is held,
        # every wait pauses, as while the bus is down.
        self.hold_for: dict[str, float] = {}
        # This process's own stalls (SIGSTOP, docker pause, starved of CPU): a ticker thread
        # notes every gap in its ticks; a wait that a stall overlapped counts its timeout
        # from the return (the peers' messages of the stall are still in the socket).
        self._tick = time.monotonic()
        self._stalls = 0
        self._ticking = False  # started by announce(): after start-up (compiling kernels holds the interpreter)
        self.session = open_session(bus)
        cred = bus.identity()
        self._size_limited = cred is not None
        self._size_limits: dict[str, int] = {}  # key → the router's limit for it (a role puts on a few keys)
        self.log.info("on the bus at %s as %s", bus.connect or bus.listen, cred.user if cred is not None else "(no credential)")
        # A link to a router opened or closed: an event ``bus`` (alive = some router
        # reachable) whenever that changes.
        self._links = RouterLinks(self.session, lambda up: self.inbox.put_event(Event("", "bus", None, alive=up)))
        self.token: zenoh.LivelinessToken | None = None
        if announce:
            self.announce()

    def set_bus_limits(self, em, hold_world: bool = False) -> None:
        """Take the bus limits of a scenario's ``emulator`` settings. ``hold_world``: a
        world whose token went may only be stalled (SIGSTOP, ``docker pause``: its session
        dropped when the lease ran out); hold it ``bus_lost_after_s`` before it counts as
        gone (agents and the selector: a world gone for good breaks the run)."""
        self.hold_s = em.liveliness_hold_s
        self.bus_grace_s = em.bus_grace_s
        self.bus_lost_after_s = em.bus_lost_after_s
        if hold_world:
            self.hold_for["world"] = em.bus_lost_after_s
        # A recorder whose token went is failing over to another router (up to Zenoh's
        # open_timeout, 10 s, when its first try is the dead router) or stalled: held as
        # long as it would itself wait for a router, every wait paused meanwhile; when it
        # comes back (a resync) each role sends its last steps again (Outbox), so the
        # recording loses nothing.
        self.hold_for["recorder"] = em.bus_lost_after_s

    # -- the bus's health -------------------------------------------------------------
    def _ticker(self) -> None:
        """(Its own thread) Tick every ``_TICK_S``; a gap over ``_STALL_S`` is a stall."""
        while not self.stop.wait(_TICK_S):
            now = time.monotonic()
            if now - self._tick > _STALL_S:
                self._stalls += 1
                self.log.warning("this process was stalled for %.1f s (stopped, paused or starved of CPU); "
                                 "waits count their timeouts from now", now - self._tick)
            self._tick = now

    def _stalled_since(self, stalls: int) -> bool:
        """Whether this process was stalled since the ticker's count was ``stalls`` (or is
        just back from one the ticker has not seen yet)."""
        return self._stalls != stalls or (self._ticking and time.monotonic() - self._tick > _STALL_S)

    def _peer_held(self) -> bool:
        """Whether the token of a role held long (``hold_for``) is gone, not yet for good."""
        return bool(self.hold_for) and any(e.role in self.hold_for for e, _t in self._held.values())

    @property
    def bus_up(self) -> bool:
        return self.bus_down_since is None

    @property
    def router_linked(self) -> bool:
        """Whether some router's link is open right now (``bus_up`` lags it: a loss is
        told the main thread through the inbox)."""
        return self._links.up

    def _filter(self, ev: Event) -> Event | None:
        """(Main thread) What the machine is told of ``ev``. A vanished liveliness token is
        held back (``hold_s``; while the bus is down and ``bus_grace_s`` after it comes back)
        and forgotten if the token comes back meanwhile: a router going down takes every
        token with it (they go a moment before the link to it is seen closed), and a client
        failing over to another router re-declares its token in milliseconds."""
        now = time.monotonic()
        if ev.kind == "clock" and getattr(ev.msg, "done", False):
            self._run_over = True  # roles leave now: their tokens' going is no news
        if ev.kind == "bus":
            if not ev.alive:
                if self.bus_down_since is not None:
                    return None
                self.bus_down_since = now
                self._agains.clear()  # no use while no router is reachable: its return sends again
                self._held = {k: (e, None) for k, (e, _t) in self._held.items()}
                self._asked.clear()  # their answers, if any come, are of no use now: asked again once the bus is back
                self.log.warning("bus lost: no Zenoh router reachable (%s); waiting for it to come back (at most %.0f s)",
                                 ",".join(self.bus.connect) or "no endpoint", self.bus_lost_after_s)
                return ev
            if self.bus_down_since is None:
                return None  # the first link, not a return
            self.gaps.append((self.bus_down_since, now))
            self.log.warning("bus back after %.2f s", now - self.bus_down_since)
            self.bus_down_since = None
            self._epoch += 1
            self._held = {k: (e, now + max(self.bus_grace_s, self.hold_for.get(e.role or "", 0.0)))
                          for k, (e, _t) in self._held.items()}
            return ev
        if ev.kind == "_declared":
            return self._answered(ev)
        if ev.kind == "alive":
            if not ev.alive:
                hold = self.hold_for.get(ev.role or "", self.hold_s)
                if ev.role in self.hold_for and not self._run_over:
                    self.log.warning("the %s's liveliness is gone: stalled or dead? waiting up to %.0f s for it to come back",
                                     ev.role, hold)
                self._held[ev.key] = (ev, None if self.bus_down_since is not None else now + hold)
                return Event(ev.key, "held", ev.sat, role=ev.role)  # gone, or only out of reach: not known yet
            self._asked.pop(ev.key, None)
            if self._held.pop(ev.key, None) is not None:
                if ev.role in self.hold_for:
                    self.log.warning("the %s is back", ev.role)
                return self._resync(ev)
        return ev

    def _due(self, now: float) -> Event | None:
        """A held token whose hold is over: the routers are asked whether they still have it
        (:meth:`_ask`); it counts gone when they answer no (:meth:`_answered`), or if no
        answer comes within ``_TOKEN_QUERY_S``."""
        for key, (ev, at) in self._held.items():
            if at is not None and at <= now:
                if key in self._asked:  # no answer in time: gone, as before there was a question
                    del self._asked[key]
                    del self._held[key]
                    return ev
                # The query's own timeout ends it first (its answer comes as an event); this
                # later deadline only in case that answer never comes.
                self._held[key] = (ev, now + _TOKEN_QUERY_S + _TOKEN_ANSWER_MARGIN_S)
                self._ask(key)
        return None

    def _ask(self, key: str) -> None:
        """Ask the routers whether a liveliness token on ``key`` is declared now (their view,
        not the order in which this node heard of its going and coming back); the answer
        comes as a local event ``_declared``, at the first reply or when the query ends with
        none. Not waited for here: a query into a mesh whose other router just died can take
        its whole timeout, and the role's loop must go on meanwhile."""
        self._asked[key] = self._asked.get(key, 0) + 1
        found: list[bool] = []

        def on_reply(reply) -> None:
            # The first reply is the answer (declared): told at once, not when the query
            # ends, which on a loaded machine can be late.
            if reply.ok is not None and not found:
                found.append(True)
                self.inbox.put_event(Event(key, "_declared", None, alive=True))

        def on_done() -> None:
            if not found:
                self.inbox.put_event(Event(key, "_declared", None, alive=False))

        try:
            self.session.liveliness().get(key, zenoh.handlers.Callback(on_reply, on_done), timeout=_TOKEN_QUERY_S)
        except zenoh.ZError as exc:
            self.log.warning("liveliness query %s: %s", key, exc)
            on_done()

    def _answered(self, ans: Event) -> Event | None:
        """The routers' answer on a held token (:meth:`_ask`)."""
        if ans.key not in self._asked:
            return None  # it came back meanwhile, or the bus went: nothing to decide
        if not ans.alive and self._asked[ans.key] < 2:
            # No reply: asked once more before it counts gone. A router's answer to a
            # liveliness query now and then holds no reply though the token stands (measured
            # with zenoh 1.10: 1 query in ~150 right after the token was seen, answered at once
            # and empty; the next one finds it).
            ev, _at = self._held[ans.key]
            self._held[ans.key] = (ev, time.monotonic() + _TOKEN_QUERY_S + _TOKEN_ANSWER_MARGIN_S)
            self._ask(ans.key)
            return None
        del self._asked[ans.key]
        ev, _at = self._held.pop(ans.key)
        if ans.alive:
            # Its going and its coming back crossed on their way here (a client failing
            # over between meshed routers: its new declaration can arrive before the old
            # one's removal, or this node is slow to read either): it is on the bus now, so
            # it never went. (Seen: a run declared broken over an agent that was back in
            # 7 ms, issue 35.)
            self.log.warning("the %s's liveliness went and is declared again: not gone", ev.role or ev.key)
            return self._resync(ev)
        return ev

    def _resync(self, ev: Event) -> Event:
        """A held token back before it counted as gone: never gone, as far as anyone need
        know (waits restart their timeout; machines send their last messages again)."""
        self._epoch += 1
        return Event(ev.key, "resync", ev.sat, role=ev.role)

    def _echo(self, ev: Event) -> Event:
        """After a return (the bus back, a peer's token back), an ``again`` event comes
        ``_AGAIN_AFTER_S`` later, on which roles send every step they keep once more
        (:meth:`swarmrt.protocol.Outbox.again`, as for their own bus's return). One series
        for a burst of returns (a failover brings every token back within milliseconds): a
        later return moves it, so that what is sent again does not grow with the number of
        peers (the routers' gates count every message). Receivers take a message they
        already have as a no-op, so this loses nothing and changes nothing."""
        if (ev.kind == "bus" and ev.alive) or ev.kind == "resync":
            now = time.monotonic()
            self._agains = [now + d for d in _AGAIN_AFTER_S]
        return ev

    def _next_wake(self) -> float | None:
        times = [at for _e, at in self._held.values() if at is not None]
        if self._agains:
            times.append(self._agains[0])
        if self.bus_down_since is not None:
            times.append(self.bus_down_since + self.bus_lost_after_s)
        return min(times) if times else None

    def announce(self) -> None:
        """Declare this node alive. Roles call it after declaring their subscribers and
        queryables, so that "alive" on the bus means "listening": whoever reacts to the
        token (the world starting the run, say) cannot publish into a gap."""
        if not self._ticking:
            self._ticking = True
            self._tick = time.monotonic()
            threading.Thread(target=self._ticker, name="stall-ticker", daemon=True).start()
        if self.token is None:
            freeze_startup_objects()
            self.token = self.session.liveliness().declare_token(self.keys.alive(self.role, self.ident))

    # -- plumbing -------------------------------------------------------------
    def subscribe(self, key: str, shallow: bool = False) -> None:
        """Samples of ``key`` go to the inbox. ``shallow``: this role reads only the header
        and scalars of these messages (estimates: who, which step, which phase), so only
        those are decoded and checked (:func:`swarmrt.bus.receive.receive`)."""
        if shallow:  # by message kind (a wildcard key parsed as one of its satellites')
            self._shallow.add(parse_key(key.replace("*", "0"))[1])
        if key in (self.keys.meas(), self.keys.batches()) or key.startswith(self.keys.batches() + "/"):
            prepare("meas")  # before this node says it is alive
        self._handles.append(self.session.declare_subscriber(key, self.inbox.callback))

    def watch_liveliness(self, pattern: str | None = None) -> None:
        pattern = pattern or self.keys.alive()
        self._handles.append(self.session.liveliness().declare_subscriber(pattern, self.inbox.callback, history=True))

    def _undeclare_all(self) -> None:
        for h in self._handles:
            with contextlib.suppress(Exception):
                h.undeclare()
        self._handles.clear()
        try:
            if self.token is not None:
                self.token.undeclare()
        except Exception:
            pass
        self.token = None

    def put(self, key: str, msg) -> None:
        payload = encode(msg)
        if self._size_limited and len(payload) > (limit := self._size_limit(key)):
            self._note_over_size_limit(key, len(payload), limit)
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def _size_limit(self, key: str) -> int:
        """The router's size limit for a put on ``key`` (:func:`swarmrt.security.size_limit_of`),
        worked out once per key: this is on every put's path."""
        limit = self._size_limits.get(key)
        if limit is None:
            try:
                limit = size_limit_of(parse_key(key)[1], self.n)
            except MessageError:
                limit = MAX_PAYLOAD_DEFAULT  # not a message key of the run: the receivers' default
            self._size_limits[key] = limit
        return limit

    def _note_over_size_limit(self, key: str, size: int, limit: int) -> None:
        """A put of ours the router's size limit will drop, unseen by anyone (Zenoh's
        low-pass filter drops silently and counts nothing): counted here, and said, so that
        a plug-in whose messages outgrew the limit is told why its peers never hear it."""
        self.over_size_limit += 1
        if self.over_size_limit <= 10 or self.over_size_limit % 1000 == 0:
            self.log.error("put on %s of %d bytes is over the router's size limit of %d bytes for its key "
                           "(swarmrt.security.size_limit_of): the router drops it (%d such puts so far)",
                           key, size, limit, self.over_size_limit)

    def queryable(self, key: str, handler, notify: bool = False) -> None:
        """``handler(query_key) -> message | None`` (or a list of messages: one reply each,
        on the query's key; or of :class:`Send`: each reply on its own key, for a wildcard
        query); runs on a Zenoh thread, keep it quick.
        ``notify``: after answering, hand the main loop a ``query`` event (a machine waiting
        on what the handler changed looks again)."""

        def cb(query):
            qkey = str(query.selector.key_expr)
            try:
                reply = handler(qkey)
            except Exception as exc:  # never let a query kill the process
                self.log.warning("query %s failed: %s", query.selector, exc)
                reply = None
            with query:
                for one in (reply if isinstance(reply, list) else [] if reply is None else [reply]):
                    if isinstance(one, Send):
                        query.reply(one.key, encode(one.msg))
                    else:
                        query.reply(qkey, encode(one))
            if notify:
                self.inbox.put_event(Event(qkey, "query", None, msg=reply))

        self._handles.append(self.session.declare_queryable(key, cb))

    def query(self, key: str, kind: str, timeout: float, every: bool = False):
        """First valid reply to a query (decoded), or None after ``timeout`` seconds;
        ``every``: the list of every valid reply (none consolidated with another)."""
        got = []
        try:
            replies = self.session.get(key, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE if every else None)
            for reply in replies:
                if reply.ok is None:
                    continue
                try:
                    msg = receive(str(reply.ok.key_expr), reply.ok.payload.to_bytes(), self.run, n_sats=self.n, expect=kind).msg
                except MessageError as exc:
                    self.count_malformed(key, exc)
                    continue
                if not every:
                    return msg
                got.append(msg)
        except zenoh.ZError as exc:
            self.log.warning("query %s: %s", key, exc)
        return got if every else None

    def count_malformed(self, key: str, err: Exception) -> None:
        """Count and log a dropped message (from any thread: subscribers decode on theirs)."""
        with self._malformed_lock:
            self.malformed += 1
            if isinstance(err, KeyMismatch):
                self.key_mismatch += 1
            count = self.malformed
            # Log the first few in full, then one line in a hundred: a flood must not become a log flood.
            log = self._malformed_logged < 20 or count % 100 == 0
            if log:
                self._malformed_logged += 1
        if log:
            self.log.warning("dropped malformed message #%d on %s: %s", count, key, err)

    def next_event(self, timeout: float | None) -> Event | None:
        """The next decoded event, or None when ``timeout`` passes. Malformed input is
        counted, logged and skipped (the wait continues within the same deadline).
        Liveliness losses come through :meth:`_filter`. Raises :class:`BusLost` once no
        router has been reachable for ``bus_lost_after_s``."""
        # An infinite timeout blocks (queue.get refuses one: "timestamp too large").
        deadline = None if timeout is None or timeout == float("inf") else time.monotonic() + timeout
        while True:
            now = time.monotonic()
            if (due := self._due(now)) is not None:
                return due
            if self._agains and self._agains[0] <= now:
                self._agains.pop(0)
                return Event("", "again", None, msg="bus")
            if self.bus_down_since is not None and now - self.bus_down_since >= self.bus_lost_after_s:
                # What is queued first: the bus may have come back while this thread was busy
                # or starved of CPU (seen on a loaded machine: a fault CLI gave up on a router
                # restart whose return was waiting in its inbox).
                queued = self.inbox.get(0)
                if queued is not None:
                    if (queued := self._filter(queued)) is not None:
                        return queued
                    continue
                raise BusLost(f"{self.name}: no Zenoh router reachable for {now - self.bus_down_since:.1f} s "
                              f"({','.join(self.bus.connect) or 'no endpoint'}): the run is broken")
            wake = self._next_wake()
            rem = None if deadline is None else max(0.0, deadline - now)
            if wake is not None:
                rem = max(0.0, wake - now) if rem is None else min(rem, max(0.0, wake - now))
            ev = self.inbox.get(rem)  # decoded, valid events only (see _decode)
            if ev is not None:
                ev = self._filter(ev)
                if ev is not None:
                    return self._echo(ev)
            elif deadline is not None and time.monotonic() >= deadline:
                return None

    @counted
    def _decode(self, s) -> Event | None:
        """A sample as an event, or None (counted, logged) if it is malformed. Runs on the
        subscribers' callback threads: it reads only what __init__ and subscribe() set."""
        try:
            r = receive(s.key, s.payload, self.run, n_sats=self.n, shallow=self._shallow, delete=s.kind == "delete")
        except MessageError as exc:
            self.count_malformed(s.key, exc)
            return None
        if r.kind == "alive":
            return Event(s.key, "alive", r.sat, alive=r.alive, role=r.role)
        return Event(s.key, r.kind, r.sat, msg=r.msg, size=len(s.payload))

    # -- running a protocol machine -------------------------------------------------
    def wait_for(self, cond, timeout: float, on_event, wake=None) -> bool:
        """Hand events to ``on_event`` until ``cond()`` holds or ``timeout`` seconds pass
        (or the node is asked to stop). ``wake()`` may name an earlier instant (monotonic)
        at which ``cond`` can change without a new event. The one wait loop of the roles."""
        deadline = time.monotonic() + timeout
        epoch, stalls = self._epoch, self._stalls
        while not cond():
            if self.stop.is_set():
                return False
            now = time.monotonic()
            if self.bus_down_since is not None or self._epoch != epoch or self._peer_held():
                # The bus is down, a long-held peer (the world) is gone but may be back, or
                # either came back meanwhile: the timeout counts from the return (the
                # lockstep world pauses rather than run on alone).
                deadline = max(deadline, now + timeout)
                epoch = self._epoch
            remaining = deadline - now
            if remaining <= 0 and self._stalled_since(stalls):
                # This process was stopped meanwhile: what its peers sent in the stall is
                # only now being read; the timeout counts from the return.
                deadline, stalls = now + timeout, self._stalls
                continue
            if remaining <= 0:
                # Take in what has already arrived before giving up (a zero wait drains).
                ev = self.next_event(0)
                if ev is None:
                    return False
                on_event(ev)
                continue
            w = wake() if wake is not None else None
            ev = self.next_event(remaining if w is None else max(0.0, min(remaining, w - now)))
            if ev is not None:
                on_event(ev)
        return True

    #: The role's protocol machine, driven by :meth:`run_loop`.
    machine: Any = None

    def run_loop(self) -> None:
        """Drive the role's protocol machine until it ends (or :attr:`stop`)."""
        self.drive(self.machine)

    @property
    def finished(self) -> bool:
        """Whether the role ended its part of the run (rather than stopping early); a
        finished role waits for the recorder before it closes its session (:func:`serve`)."""
        return True

    def drive(self, machine) -> None:
        """Run a role's protocol machine (:mod:`swarmrt.protocol`) on this node: publish what
        it sends, answer its queries, and feed it events while it waits."""

        def on_event(ev: Event) -> None:
            for out in machine.handle(ev):
                self.put(out.key, out.msg)

        gen = machine.run()
        reply = None
        while not self.stop.is_set():
            try:
                action = gen.send(reply)
            except StopIteration:
                return
            reply = None
            if isinstance(action, Send):
                self.put(action.key, action.msg)
            elif isinstance(action, Query):
                reply = self.query(action.key, action.kind, action.timeout_s, every=action.every)
            elif isinstance(action, Wait):
                reply = self.wait_for(action.until, action.timeout_s, on_event, action.wake)
            else:
                raise TypeError(f"unknown protocol action {action!r}")
        gen.close()

    def linger_while_recording(self, timeout_s: float) -> bool:
        """Keep this session open until the run's recorder (if one is alive) has finished.

        A Zenoh session that closes right after a put can take undelivered messages with
        it (seen here: every agent's last estimate missing from the recording when the
        agents left the moment the world said done). The recorder drops its liveliness
        token only once it holds every live agent's final estimate, so waiting for that
        token to go is an acknowledgement. Returns False if ``timeout_s`` passed first, or if the
        role was asked to stop meanwhile (SIGTERM: :func:`serve`'s handler sets :attr:`stop`;
        a role asked to stop leaves at once, lingering or not: docs/agent-contract.md, C20)."""
        gone = threading.Event()
        ended = self.stop  # set by SIGTERM, or below once the recorder is gone: the wait's end

        def cb(sample) -> None:
            if sample.kind == zenoh.SampleKind.DELETE:
                gone.set()
                ended.set()  # the role's last act: it closes its session next

        key = self.keys.alive("recorder")
        sub = self.session.liveliness().declare_subscriber(key, cb)
        try:
            present = False
            try:
                present = any(r.ok is not None for r in self.session.liveliness().get(key, timeout=min(5.0, timeout_s)))
            except zenoh.ZError as exc:
                self.log.warning("liveliness query %s: %s", key, exc)
            if not present:
                return True
            if not ended.wait(timeout_s):
                self.log.warning("the recorder was still running %.0f s after the run ended; leaving anyway", timeout_s)
                return False
            if not gone.is_set():
                self.log.info("asked to stop while waiting for the recorder; leaving")
            return gone.is_set()
        finally:
            with contextlib.suppress(Exception):
                sub.undeclare()

    def close(self) -> None:
        self.stop.set()  # (the stall ticker too)
        self._undeclare_all()
        with contextlib.suppress(Exception):
            self._links.undeclare()
        self.session.close()


def freeze_startup_objects() -> None:
    """Hide everything allocated so far (modules, numba's compiler, the scenario) from
    Python's cyclic garbage collector.

    A role's start-up leaves ~150,000 long-lived objects (numba alone brings most); every
    full collection walks them all, ~0.1 s on this machine kind, and the allocations of a
    step's messages trigger several a step: profiled at n = 20, two thirds of an agent's
    CPU went to collections started from the bus callback thread. ``gc.freeze`` (standard
    library) moves them to a permanent generation the collector skips; what is allocated
    afterwards is collected as before."""
    gc.collect()
    gc.freeze()


def setup_logging(name: str, verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format=f"%(asctime)s {name} %(levelname)s %(message)s",
        stream=sys.stderr,
        force=True,  # a role may learn its name late (an agent with --id auto)
    )


def role_arg_parser(description: str) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=description)
    p.add_argument("--scenario", required=True, help="resolved scenario YAML")
    p.add_argument("--run", required=True, help="run id (part of every key)")
    p.add_argument("--set", dest="sets", action="append", default=[], help="override a scenario field: dotted.key=value")
    p.add_argument("-v", "--verbose", action="store_true")
    add_bus_args(p)
    return p


def load_role_scenario(path: str, sets=()) -> Scenario:
    """The scenario a role runs (every role of a swarm must be given the same file and sets)."""
    import os

    from swarmrt.scenario_files import ScenarioError, load_scenario

    env_sets = [x for x in os.environ.get("SWARM_SET", "").split() if x]
    try:
        return load_scenario(path, [*env_sets, *sets])
    except ScenarioError as exc:
        raise SystemExit(str(exc)) from None


def serve(node: Node, linger_s: float | None = None) -> int:
    """A role's life after start-up, the same for every role: SIGTERM / SIGINT stop it
    cleanly; its machine runs to the end; a role that finished (not stopped) keeps its
    session until the recorder holds its last messages (``linger_s``; None: it does not
    wait); a broken run (the bus lost, the world gone) exits with its status; the session
    always closes. Returns the process's exit status."""
    install_term_handler(node.stop)
    try:
        node.run_loop()
        if linger_s is not None and node.finished and not node.stop.is_set():
            node.linger_while_recording(linger_s)
    except RunBroken as exc:
        node.log.error("%s; exiting", exc)
        return exc.exit_code
    finally:
        node.close()
    return 0


def install_term_handler(node_stop: threading.Event) -> None:
    """SIGTERM / SIGINT ask the main loop to stop cleanly."""

    def handler(signum, frame):
        node_stop.set()

    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)


__all__ += ["serve", "install_term_handler", "bus_config_from_args", "freeze_startup_objects", "RunBroken"]
