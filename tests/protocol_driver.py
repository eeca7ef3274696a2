"""Drive a role's protocol machine (:mod:`swarmrt.protocol`) without a bus: scripted events
in, the messages it sends out, a fake clock. What :meth:`swarmrt.node.Node.drive` does with a
real Zenoh session, done by hand so tests can say exactly what arrives and when."""

from __future__ import annotations

from swarmrt.bus.messages import Keys, Recorded
from swarmrt.protocol import Event, Query, Send, Wait


class FakeClock:
    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


class Driver:
    """Runs ``machine.run()`` until it blocks on a :class:`Wait` that does not hold yet.

    ``answer(query) -> reply`` answers its queries (default: nothing); ``clocks(query) ->
    [Clock]`` the queries of the world's ``clock`` queryable, ``reports(query) -> [Health]``
    those of its ``health/*`` (default: none served; they are listed in ``clock_queries`` and
    ``report_queries``, not ``queries``). Events are handed in with :meth:`feed`, or
    with :meth:`arrive` while the machine is busy (they wait in an inbox until its next
    :class:`Wait`, as in :meth:`swarmrt.node.Node.wait_for`: a wait whose condition already
    holds takes nothing in); :meth:`elapse` moves the fake clock and times waits out.
    ``recorder_keeps_up``: a world's every clock is answered at once by the recorder's
    ``recorded`` (a recorder that keeps up, so the bounded recorder lag never waits); False:
    the test feeds ``recorded`` itself.
    """

    def __init__(self, machine, clock: FakeClock, answer=None, recorder_keeps_up: bool = True, clocks=None, reports=None):
        self.m = machine
        self.clock = clock
        self.recorder_keeps_up = recorder_keeps_up
        self.answer = answer or (lambda q: None)
        self.clocks = clocks or (lambda q: [])
        self.reports = reports or (lambda q: [])
        self.report_queries: list[Query] = []
        self.sent: list[Send] = []
        self.queries: list[Query] = []
        self.clock_queries: list[Query] = []
        self.inbox: list[Event] = []
        self.gen = machine.run()
        self.wait: Wait | None = None
        self.deadline = None
        self.finished = False
        self._resume(None)

    # -- what the machine did ----------------------------------------------------------
    def sent_on(self, key: str) -> list:
        return [s.msg for s in self.sent if s.key == key]

    def take(self) -> list[Send]:
        out, self.sent = self.sent, []
        return out

    # -- what happens to it --------------------------------------------------------------
    def feed(self, *events: Event) -> None:
        """Events that arrive together: all are handled before the machine looks again
        (as when they sit in a process's inbox at once)."""
        for ev in events:
            self.sent.extend(self.m.handle(ev))
        self._check()

    def arrive(self, *events: Event) -> None:
        """Events that arrive while the machine is busy (asking a query, say): handed to it
        at its next wait."""
        self.inbox.extend(events)

    def elapse(self, dt: float) -> None:
        """Let ``dt`` seconds pass with nothing arriving."""
        self.clock.t += dt
        self._check()

    def _check(self) -> None:
        while self.wait is not None and not self.finished:
            while self.inbox and not self.wait.until():
                self.sent.extend(self.m.handle(self.inbox.pop(0)))
            if self.wait.until():
                self._resume(True)
            elif self.clock() >= self.deadline:
                self._resume(False)
            else:
                return

    def _resume(self, value) -> None:
        while True:
            try:
                action = self.gen.send(value)
            except StopIteration:
                self.finished, self.wait = True, None
                return
            value = None
            if isinstance(action, Send):
                self.sent.append(action)
                if self.recorder_keeps_up and action.key.endswith("/clock") and not action.msg.done:
                    self.m.handle(Event(Keys(action.msg.run).recorded(), "recorded", None,
                                        msg=Recorded(run=action.msg.run, sender="recorder", k=action.msg.k, t_s=action.msg.t_s)))
            elif isinstance(action, Query):
                if action.key.endswith("/clock"):
                    self.clock_queries.append(action)
                    value = self.clocks(action)
                elif action.key.endswith("/health/*"):
                    self.report_queries.append(action)
                    value = self.reports(action)
                else:
                    self.queries.append(action)
                    value = self.answer(action)
            elif isinstance(action, Wait):
                if action.until():
                    value = True
                    continue
                while self.inbox and not action.until():  # what arrived meanwhile, one event at a time
                    self.sent.extend(self.m.handle(self.inbox.pop(0)))
                if action.until():
                    value = True
                    continue
                if action.timeout_s <= 0:
                    value = False
                    continue
                self.wait, self.deadline = action, self.clock() + action.timeout_s
                return
            else:
                raise TypeError(action)
