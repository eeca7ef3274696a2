"""The vocabulary of the roles' bus-free protocol machines, and the one loop that runs them.

Each role's protocol (``world_sim.protocol``, ``sat_agent.protocol``) is a state machine
written as a generator: it *yields* what it wants done — publish a message
(:class:`Send`), ask a queryable (:class:`Query`), wait until a condition on what it has
heard holds or a timeout passes (:class:`Wait`) — and is told the outcome; what arrives
in between is handed to its ``handle(event)``, which updates its knowledge and may answer
with messages of its own. The machine never touches a bus, a clock or a thread: the
process shell (:class:`swarmrt.node.Node`) moves bytes, and unit tests drive the same
machine with scripted events and a fake clock (``tests/protocol_driver.py``).

Why generators: the lockstep protocol is a sequence with waits in it ("publish the clock,
then wait for every live agent's estimate or a timeout"); written as a generator it reads
as that sequence, and the generator's frame is the machine's state.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

from swarmcore.streams import stream

__all__ = ["Event", "Send", "Query", "Wait", "Action", "Machine", "Clock", "RunBroken", "BusLost", "WorldLost",
           "EXIT_BUS_LOST", "EXIT_WORLD_LOST", "EXIT_AGENT_LOST", "BUS_LEASE_S", "world_wait_s", "Outbox", "outbox_steps", "arrival_step", "first_time", "DROP_BATCH", "DROP_ESTIMATE", "message_dropped"]

#: Exit status of a role (and of ``swarm run``) whose bus did not come back within
#: ``emulator.bus_lost_after_s``, and of one whose world is gone before the run's end.
EXIT_BUS_LOST = 3
EXIT_WORLD_LOST = 4
#: Zenoh's session lease (s; its default ``transport/link/tx/lease``): a process stalled
#: (SIGSTOP, ``docker pause``) longer than this is dropped by its router, and its
#: liveliness token goes with it; peers cannot tell it from a death until it comes back.
BUS_LEASE_S = 10.0


def world_wait_s(em) -> float:
    """How long a role waits in lockstep for the world's message of a step: the step
    timeout plus the lease. A stalled world's token goes only when the lease runs out;
    until then nothing tells a peer the world is stalled rather than slow, and once it is
    gone the wait pauses while it is held (:class:`swarmrt.node.Node`, ``hold_for``)."""
    return float(em.step_timeout_s) + BUS_LEASE_S


#: Exit status of ``swarm run`` when an agent left by itself (not by a fault) before the run's
#: end, or an agent, the selector or the recorder lost its bus session while it ran (a stall
#: past the lease): the run went on without it.
EXIT_AGENT_LOST = 5


class RunBroken(RuntimeError):
    """The run cannot go on (raised from a machine's ``handle`` or the shell's wait);
    the role's main logs the message and exits with :attr:`exit_code`."""

    exit_code = 1


class BusLost(RunBroken):
    exit_code = EXIT_BUS_LOST


class WorldLost(RunBroken):
    exit_code = EXIT_WORLD_LOST


class Event(NamedTuple):
    """A decoded sample: a message (``msg``) or a liveliness change (``alive`` True/False).
    (A named tuple: made ~120 times a step per agent at n = 40, it is the cheapest record.)"""

    key: str
    kind: str
    sat: int | None
    msg: Any = None
    alive: bool | None = None
    role: str | None = None
    size: int = 0  # the payload's encoded size on the bus (bytes)


@dataclass(frozen=True)
class Send:
    """Publish ``msg`` on ``key`` (reliably: congestion control BLOCK)."""

    key: str
    msg: Any


@dataclass(frozen=True)
class Query:
    """Ask the queryable(s) on ``key`` for a message of ``kind``; the machine is sent the
    first valid reply, or None after ``timeout_s`` (``every``: the list of every valid reply,
    possibly empty, each as it was sent: none merged with another on the same key)."""

    key: str
    kind: str
    timeout_s: float
    every: bool = False


@dataclass(frozen=True)
class Wait:
    """Hand events to the machine until ``until()`` holds (the machine is sent True) or
    ``timeout_s`` passes (False). ``wake()`` may name an earlier instant (on the machine's
    clock) at which ``until`` can turn true without a new event (a grace period ending)."""

    until: Callable[[], bool]
    timeout_s: float
    wake: Callable[[], float | None] | None = None


Action = Send | Query | Wait


class Outbox:
    """What a machine has published in its last ``keep`` steps (the current one among them),
    to publish again when the bus comes back (events ``bus`` with ``alive=True``: this
    role's link to a router is up again; ``resync``: a peer's liveliness came back before it
    counted as gone: the recorder, say, after failing over to another router).

    Why: a put while no router is reachable is dropped without an error, and a router
    killed mid-step takes what it was forwarding with it; in lockstep every receiver
    handles a message it already has as a no-op (the recorder writes it once), so sending
    the steps' messages again loses nothing and changes nothing. ``keep``: the world runs
    at most ``emulator.recorder_max_lag_steps`` steps ahead of the recorder, so
    ``recorder_max_lag_steps + 2`` steps cover whatever a recorder that comes back lacks
    (:func:`outbox_steps`).
    """

    def __init__(self, skip_keys: tuple[str, ...] = (), keep: int = 2):
        if keep < 1:
            raise ValueError(f"keep: {keep} steps (at least 1)")
        self.sends: list[Send] = []
        self._earlier: collections.deque[list[Send]] = collections.deque(maxlen=keep - 1)  # the steps before, oldest first
        self.skip = skip_keys

    @property
    def previous(self) -> list[Send]:
        """The sends of the step before the current one."""
        return self._earlier[-1] if self._earlier else []

    def clear(self) -> None:
        """A new step begins (the last ones' sends are kept ``keep - 1`` steps more)."""
        if self._earlier.maxlen:
            self._earlier.append(self.sends)
        self.sends = []

    def wrap(self, gen):
        """Run generator ``gen`` (a machine's ``run``), keeping each Send it yields."""
        reply = None
        while True:
            try:
                action = gen.send(reply)
            except StopIteration:
                return
            if isinstance(action, Send) and not action.key.endswith(self.skip):
                self.sends.append(action)
            reply = yield action

    def keep(self, sends: list[Send]) -> list[Send]:
        """Keep ``sends`` made outside the machine's run (a fault's report, made as its
        command is handled) with the current step's, to be sent again as they are; returns
        them. (Seen: an agent's drop report put while the recorder was stalled and never sent
        again, missing from the recording, issue 35.)"""
        self.sends.extend(s for s in sends if not s.key.endswith(self.skip))
        return sends

    def again(self, ev: Event) -> list[Send]:
        """The sends to repeat for event ``ev`` (none unless the bus came back): every step
        kept when this role's own bus or the recorder came back (the recorder may be up to
        ``recorder_max_lag_steps`` behind); the current and previous step when another
        peer's token did (no step ends while a peer's token is held, so that is all it can
        lack), which keeps a failover's resends small. ``again``: every step kept, once more,
        a moment after a burst of returns (:meth:`swarmrt.node.Node._echo`)."""
        if ev.kind == "again" or (ev.kind == "bus" and ev.alive) or (ev.kind == "resync" and ev.role == "recorder"):
            return [*(s for step in self._earlier for s in step), *self.sends]
        if ev.kind == "resync":
            return [*self.previous, *self.sends]
        return []


def arrival_step(t_s: float, dt_s: float) -> int:
    """The first step that begins at or after simulated time ``t_s`` (steps of ``dt_s``): from
    it on, what arrived at ``t_s`` is in use. The world and a restarted agent both work out
    from a state transfer's arrival (links on) the step at which the agent joins the swarm."""
    return max(0, math.ceil(t_s / dt_s - 1e-9))


def command_key(command) -> bytes:
    """What makes two fault commands one (:func:`first_time`): their bytes."""
    return command.SerializeToString(deterministic=True)


def first_time(seen: set[bytes], command) -> bool:
    """Whether fault ``command`` (a message) is new to ``seen`` (then noted there). The world
    sends its last steps' messages again when the bus or the recorder comes back, its fault
    commands among them, so that the recording has them: every executor carries out a
    command once, and the same command twice (the same bytes: the same step, action, target
    and parameters, from the same sender) is one command."""
    key = command_key(command)
    if key in seen:
        return False
    seen.add(key)
    return True


def outbox_steps(em) -> int:
    """How many steps a role's :class:`Outbox` keeps under emulator settings ``em``."""
    return int(em.recorder_max_lag_steps) + 2


#: What a drop fault loses (the ``what`` of :func:`message_dropped`).
DROP_BATCH = 0
DROP_ESTIMATE = 1


def message_dropped(seed: int, sat: int, k: int, what: int, rate: float) -> bool:
    """The drop fault's draw: whether satellite ``sat``'s message ``what`` of step ``k``
    is lost at ``rate``. The agent that drops and the world, whose radio must not wait for
    a batch that will never come, make the same draw (keyed by satellite, step and
    message, never by arrival order)."""
    return rate > 0 and bool(stream(seed, "drop", sat, k, what).random() < rate)


class Clock(Protocol):
    def __call__(self) -> float: ...


class Machine(Protocol):
    """What a role's protocol offers its shell."""

    def run(self) -> Generator[Action, Any, None]: ...

    def handle(self, ev: Event) -> list[Send]: ...
