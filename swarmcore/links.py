"""Inter-satellite links: what the radio does to the messages satellites send each other.

A copy of a message for each receiver enters its transmitter's queue (first in, first
out); the transmitter sends at ``rate_Bps`` (a copy of ``s`` bytes takes ``s / rate``);
a copy that does not fit the queue (``queue_bytes``) is dropped by the stated policy.
Once sent, a copy arrives after the latency of its link,

    latency = fixed_s + range / c (speed_of_light) + per_m_s · range + jitter,

or is lost: independently (Bernoulli) or in bursts (Gilbert–Elliott; the channel state of
each link is a two-state Markov chain advanced once per step, every message sent in the
Bad state is lost; per step P(Good→Bad) = p, P(Bad→Good) = r with r = 1/mean_burst,
p = L·r/(1−L) for a long-run loss rate L, and the chain starts from its stationary law).
A link that is dead (an override), longer than ``max_range_m`` or blocked by another
satellite's body (a sphere) carries nothing; the radio's neighbour table knows it, so no
airtime is spent on it.

Determinism: every draw comes from ``stream(seed, purpose, step[, message])`` over all
n × n links (``link-ge`` per step; ``link-loss``, ``link-jitter`` per step and message,
the message named by the step it was taken at; ``rejoin-…`` for the warm-rejoin state),
so a message's fate depends on its link, step and identity, never on the order messages
were handed in.
Geometry comes from the truth: the link model belongs to the world (the radio channel is
physics); agents only ever see what is delivered to them, and when.

Written by hand because no maintained library models a per-link radio channel with
queueing, range and Gilbert–Elliott loss in simulated time (network simulators such as
ns-3 are whole event engines, not a function the filter loop can call).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .scenario import Latency, Links, Loss, Scenario
from .streams import stream

__all__ = ["scenario_link_model", "LinkModel", "Delivery", "LinkCounters", "SPEED_OF_LIGHT_M_S", "ge_probabilities"]

SPEED_OF_LIGHT_M_S = 299_792_458.0
_JITTER = {"none": 0, "uniform": 1, "normal": 2, "exponential": 3}
_LOSS = {"none": 0, "bernoulli": 1, "gilbert_elliott": 2}


def ge_probabilities(rate: float, mean_burst: float) -> tuple[float, float]:
    """Gilbert–Elliott transition probabilities ``(p, r)`` per step for a long-run loss
    ``rate`` and a mean burst of ``mean_burst`` messages (field notes: r = 1/B,
    p = L r / (1 − L))."""
    r = 1.0 / mean_burst
    p = rate * r / (1.0 - rate) if rate > 0 else 0.0
    return min(p, 1.0), r


@dataclass
class Delivery:
    """A copy that reached its receiver."""

    sender: int
    receiver: int
    payload: Any
    sent_step: int
    sent_t: float
    arrival_t: float
    size: int


@dataclass
class _Copy:
    sender: int
    receiver: int
    payload: Any
    size: int
    sent_step: int
    sent_t: float
    lost: bool
    latency: float
    start: float = 0.0
    end: float = 0.0
    batch: bool = True  # a measurement batch (delivered by ``due``); else a state transfer


@dataclass
class LinkCounters:
    """Per directed link (n × n): what became of the copies handed to the radio."""

    sent: np.ndarray  # copies that entered a transmitter's queue
    delivered: np.ndarray
    delivered_late: np.ndarray  # arrived after the step they were taken in
    lost: np.ndarray  # on the channel
    dropped_queue: np.ndarray  # did not fit the transmitter's queue
    unreachable: np.ndarray  # dead, out of range or blocked: never sent
    bytes_delivered: np.ndarray

    @classmethod
    def zeros(cls, n: int) -> LinkCounters:
        z = lambda dt=int: np.zeros((n, n), dtype=dt)  # noqa: E731
        return cls(z(), z(), z(), z(), z(), z(), z())

    def as_dict(self) -> dict[str, list]:
        return {k: getattr(self, k).tolist() for k in self.__dataclass_fields__}


@dataclass
class _Resolved:
    """Per-link parameters as (n, n) arrays."""

    dead: np.ndarray
    fixed_s: np.ndarray
    c_on: np.ndarray
    per_m_s: np.ndarray
    jitter_kind: np.ndarray
    jitter_scale: np.ndarray
    loss_kind: np.ndarray
    loss_rate: np.ndarray
    ge_p: np.ndarray
    ge_r: np.ndarray
    max_range: np.ndarray


def _resolve(links: Links, n: int) -> _Resolved:
    shape = (n, n)

    def fill(v, dt=float):
        return np.full(shape, v, dtype=dt)

    lat, loss = links.latency, links.loss
    p, r = ge_probabilities(loss.rate, loss.mean_burst)
    R = _Resolved(
        dead=np.eye(n, dtype=bool),
        fixed_s=fill(lat.fixed_s),
        c_on=fill(lat.speed_of_light, bool),
        per_m_s=fill(lat.per_m_s),
        jitter_kind=fill(_JITTER[lat.jitter.distribution], int),
        jitter_scale=fill(lat.jitter.scale_s),
        loss_kind=fill(_LOSS[loss.model], int),
        loss_rate=fill(loss.rate),
        ge_p=fill(p),
        ge_r=fill(r),
        max_range=fill(np.inf if links.max_range_m is None else links.max_range_m),
    )
    for o in links.overrides:
        i, j = o.src, o.dst
        R.dead[i, j] = o.dead
        if o.latency is not None:
            _set_latency(R, i, j, o.latency)
        if o.loss is not None:
            _set_loss(R, i, j, o.loss)
        if o.max_range_m is not None:
            R.max_range[i, j] = o.max_range_m
    return R


def _set_latency(R: _Resolved, i: int, j: int, lat: Latency) -> None:
    R.fixed_s[i, j] = lat.fixed_s
    R.c_on[i, j] = lat.speed_of_light
    R.per_m_s[i, j] = lat.per_m_s
    R.jitter_kind[i, j] = _JITTER[lat.jitter.distribution]
    R.jitter_scale[i, j] = lat.jitter.scale_s


def _set_loss(R: _Resolved, i: int, j: int, loss: Loss) -> None:
    R.loss_kind[i, j] = _LOSS[loss.model]
    R.loss_rate[i, j] = loss.rate
    R.ge_p[i, j], R.ge_r[i, j] = ge_probabilities(loss.rate, loss.mean_burst)


def _blocked(r: np.ndarray, radius: float) -> np.ndarray:
    """(n, n): the segment from i to j passes within ``radius`` of a third satellite's centre."""
    n = r.shape[0]
    out = np.zeros((n, n), dtype=bool)
    for i in range(n):
        d = r - r[i]  # (n, 3) i → j
        L2 = np.einsum("ja,ja->j", d, d)
        for m in range(n):
            if m == i:
                continue
            w = r[m] - r[i]
            s = np.where(L2 > 0, (d @ w) / np.where(L2 > 0, L2, 1.0), 0.0)  # projection of m on each segment
            inside = (s > 0.0) & (s < 1.0)
            closest = np.linalg.norm(d * s[:, None] - w, axis=1)
            hit = inside & (closest < radius)
            hit[m] = False  # m's own link is not blocked by itself
            out[i] |= hit
    np.fill_diagonal(out, False)
    return out


@dataclass
class LinkModel:
    """The radio channel of a swarm (see the module docstring). One per world."""

    links: Links
    n: int
    seed: int
    body_radius_m: float
    rate_Bps: float | None = None
    counters: LinkCounters = field(init=False)
    latencies: list = field(default_factory=list, init=False)  # (sender, receiver, sent_step, latency_s) per delivery

    def __post_init__(self) -> None:
        self.p = _resolve(self.links, self.n)
        self._p0 = _resolve(self.links, self.n)  # the scenario's parameters, which a link fault's restore gives back
        self.rate_Bps = self.links.rate_Bps
        self.counters = LinkCounters.zeros(self.n)
        self._bad = np.zeros((self.n, self.n), dtype=bool)
        self._step = -1
        self._range = np.zeros((self.n, self.n))
        self._reach = ~np.eye(self.n, dtype=bool)
        self._queues: list[list[_Copy]] = [[] for _ in range(self.n)]  # copies not yet fully sent
        self._tx_free = np.zeros(self.n)
        self._flight: list[_Copy] = []  # sent (or sending) copies not yet delivered

    # -- the channel at a step ---------------------------------------------------------
    def at_step(self, k: int, r_H: np.ndarray) -> None:
        """Geometry (true positions, H frame) and channel states of step ``k``."""
        if k <= self._step:
            raise ValueError(f"link model at step {self._step}: step {k} is not ahead")
        for s in range(self._step + 1, k + 1):
            self._advance_ge(s)
        self._step = k
        r = np.asarray(r_H, dtype=float)
        d = r[None, :, :] - r[:, None, :]
        self._range = np.linalg.norm(d, axis=-1)
        reach = ~self.p.dead & (self._range <= self.p.max_range)
        if self.links.line_of_sight:
            reach &= ~_blocked(r, self.body_radius_m)
        self._reach = reach

    def _advance_ge(self, s: int) -> None:
        u = stream(self.seed, "link-ge", s).random((self.n, self.n))
        if s == 0:
            L = np.where(self.p.ge_p > 0, self.p.ge_p / (self.p.ge_p + self.p.ge_r), 0.0)
            self._bad = u < L
        else:
            self._bad = np.where(self._bad, u >= self.p.ge_r, u < self.p.ge_p)

    # -- link faults (the world carries them out: FaultSpec action "link") ----------------
    def _fault_links(self, i: int, j: int | None) -> tuple[np.ndarray, np.ndarray]:
        """(senders, receivers) of the directed links a fault on ``i`` (→ ``j``) acts on: the
        one link i → j, or (``j`` None) every link of i both ways."""
        if not 0 <= i < self.n or (j is not None and not 0 <= j < self.n) or i == j:
            raise ValueError(f"link fault on {i} -> {j}: not a link of this {self.n}-satellite swarm")
        if j is not None:
            return np.array([i]), np.array([j])
        others = np.array([m for m in range(self.n) if m != i])
        return np.r_[np.full(len(others), i), others], np.r_[others, np.full(len(others), i)]

    def impair(self, i: int, j: int | None = None, *, dead: bool = False, delay_s: float | None = None,
               loss_rate: float | None = None) -> int:
        """A link fault from now on (what the scenario's overrides do, at run time): the
        link(s) made dead, ``delay_s`` added to their fixed latency (to the scenario's, not
        to an earlier fault's), their loss made Bernoulli at ``loss_rate``. Copies already
        on their way keep their fate. Returns the number of directed links."""
        a, b = self._fault_links(i, j)
        if dead:
            self.p.dead[a, b] = True
            self._reach[a, b] = False  # at once: nothing more is sent on them this step
        if delay_s is not None:
            self.p.fixed_s[a, b] = self._p0.fixed_s[a, b] + float(delay_s)
        if loss_rate is not None:
            self.p.loss_kind[a, b] = _LOSS["bernoulli"]
            self.p.loss_rate[a, b] = float(loss_rate)
        return len(a)

    def restore(self, i: int, j: int | None = None) -> int:
        """Give the link(s) back the scenario's parameters (undo every fault on them); a link
        brought back to life is reachable again from the next step (range, line of sight)."""
        a, b = self._fault_links(i, j)
        for name in _Resolved.__dataclass_fields__:
            getattr(self.p, name)[a, b] = getattr(self._p0, name)[a, b]
        return len(a)

    def reachable(self, i: int, j: int) -> bool:
        return bool(self._reach[i, j])

    def range_m(self, i: int, j: int) -> float:
        return float(self._range[i, j])

    # -- sending -----------------------------------------------------------------------
    def transfer(self, sender: int, receiver: int, size: int, t: float) -> tuple[str, float | None]:
        """A one-off transfer (the warm-rejoin state a restarted agent fetches from a peer):
        it takes the sender's transmitter like any copy, with its own draws
        (``rejoin-…``); returns ``(fate, arrival time)`` with fate delivered, lost, dropped
        or unreachable. It is counted per link but never returned by :meth:`due`."""
        fates = self.send(sender, [receiver], None, size, t, purpose="rejoin", batch=False)
        fate = fates[int(receiver)]
        if fate != "queued":
            return fate, None
        c = next(c for c in reversed(self._flight) if not c.batch and c.sender == sender and c.receiver == receiver)
        return ("lost" if c.lost else "delivered"), c.end + c.latency

    def send(self, sender: int, receivers, payload: Any, size: int, t: float, purpose: str = "link",
             batch: bool = True, key: int | None = None) -> dict[int, str]:
        """Hand one message of ``size`` bytes from ``sender`` to the radio at time ``t``
        (of the current step), one copy per receiver in ascending order. Returns each
        receiver's immediate fate: ``queued`` (sent, or waiting to be), ``unreachable`` or
        ``dropped``. Whether a queued copy is lost is decided now, from the channel state;
        it still takes its airtime. ``key`` names the message among the sender's (default:
        the current step; a batch uses the step it was taken at), so two messages of one
        sender in one step get their own draws."""
        k = self._step
        i = int(sender)
        m = k if key is None else int(key)
        fates: dict[int, str] = {}
        lost_u = stream(self.seed, f"{purpose}-loss", k, m).random((self.n, self.n))
        jit_u = stream(self.seed, f"{purpose}-jitter", k, m).random((self.n, self.n))
        for j in sorted(int(x) for x in receivers):
            if j == i:
                continue
            if not self._reach[i, j]:
                self.counters.unreachable[i, j] += 1
                fates[j] = "unreachable"
                continue
            c = _Copy(i, j, payload, int(size), k, float(t), self._is_lost(i, j, lost_u[i, j]), self._latency(i, j, jit_u[i, j]),
                      batch=batch)
            if not self._enqueue(c, t):
                self.counters.dropped_queue[i, j] += 1
                fates[j] = "dropped"
                continue
            self.counters.sent[i, j] += 1
            fates[j] = "queued"
        return fates

    def _is_lost(self, i: int, j: int, u: float) -> bool:
        kind = self.p.loss_kind[i, j]
        if kind == 1:
            return bool(u < self.p.loss_rate[i, j])
        if kind == 2:
            return bool(self._bad[i, j])
        return False

    def _latency(self, i: int, j: int, u: float) -> float:
        rng_m = self._range[i, j]
        lat = self.p.fixed_s[i, j] + self.p.per_m_s[i, j] * rng_m
        if self.p.c_on[i, j]:
            lat += rng_m / SPEED_OF_LIGHT_M_S
        kind, s = self.p.jitter_kind[i, j], self.p.jitter_scale[i, j]
        if kind == 1:
            lat += u * s
        elif kind == 2:
            lat += s * _half_normal_ppf(u)
        elif kind == 3:
            lat += -s * np.log1p(-u)
        return float(lat)

    def _enqueue(self, c: _Copy, t: float) -> bool:
        i = c.sender
        if self.rate_Bps is None:
            c.start = c.end = t
            self._flight.append(c)
            return True
        q = self._queues[i]
        q[:] = [x for x in q if x.end > t]  # what is still being sent or waiting at t
        backlog = sum(x.size for x in q)
        if backlog + c.size > self.links.queue_bytes:
            if self.links.queue_policy == "drop_tail":
                return False
            waiting = [x for x in q if x.start > t]
            while waiting and backlog + c.size > self.links.queue_bytes:
                old = waiting.pop(0)
                q.remove(old)
                self._flight.remove(old)
                backlog -= old.size
                self.counters.sent[old.sender, old.receiver] -= 1
                self.counters.dropped_queue[old.sender, old.receiver] += 1
            if backlog + c.size > self.links.queue_bytes:
                return False
            self._reschedule(i, t)
        start = max(t, q[-1].end if q else t)
        c.start, c.end = start, start + c.size / float(self.rate_Bps)
        q.append(c)
        self._flight.append(c)
        return True

    def _reschedule(self, i: int, t: float) -> None:
        """After head drops: the waiting copies move up behind the one being sent."""
        q = self._queues[i]
        prev_end = None
        for x in q:
            if x.start <= t:
                prev_end = x.end
                continue
            x.start = t if prev_end is None else max(t, prev_end)
            x.end = x.start + x.size / float(self.rate_Bps or np.inf)
            prev_end = x.end

    def queue_bytes(self, t: float) -> np.ndarray:
        """(n,) bytes each transmitter still has to send at ``t`` (the one being sent included)."""
        out = np.zeros(self.n, dtype=int)
        for i, q in enumerate(self._queues):
            out[i] = sum(x.size for x in q if x.end > t)
        return out

    # -- receiving ---------------------------------------------------------------------
    def due(self, t: float, step: int | None = None) -> list[Delivery]:
        """Every copy that has arrived by ``t`` (lost ones are counted, not returned), in a
        canonical order: (receiver, sent step, sender). ``step``: the receiving step, to
        count late deliveries (default: the current step)."""
        step = self._step if step is None else step
        now: list[_Copy] = []
        later: list[_Copy] = []
        for c in self._flight:
            (now if c.end + c.latency <= t else later).append(c)
        self._flight = later
        out = []
        for c in sorted(now, key=lambda c: (c.receiver, c.sent_step, c.sender)):
            if c.lost:
                self.counters.lost[c.sender, c.receiver] += 1
                continue
            arrival = c.end + c.latency
            self.counters.delivered[c.sender, c.receiver] += 1
            self.counters.bytes_delivered[c.sender, c.receiver] += c.size
            if not c.batch:
                continue  # a state transfer: the restarted agent was told when it arrives
            if step > c.sent_step:
                self.counters.delivered_late[c.sender, c.receiver] += 1
            self.latencies.append((c.sender, c.receiver, c.sent_step, arrival - c.sent_t))
            out.append(Delivery(c.sender, c.receiver, c.payload, c.sent_step, c.sent_t, arrival, c.size))
        return out

    def next_arrival(self) -> float | None:
        """When the next copy in flight arrives (or is found lost), if any."""
        return min((c.end + c.latency for c in self._flight), default=None)

    def forget(self, receiver: int) -> None:
        """Drop what is in flight to a receiver that is gone (its radio is off); counted lost."""
        keep = []
        for c in self._flight:
            if c.receiver == receiver:
                self.counters.lost[c.sender, c.receiver] += 1
            else:
                keep.append(c)
        self._flight = keep


def _half_normal_ppf(u: float) -> float:
    """Quantile of |N(0, 1)| at ``u`` (scipy's norm.ppf; the jitter of one copy)."""
    from scipy.special import ndtri

    return float(ndtri(0.5 + 0.5 * u))


def scenario_link_model(sc: Scenario) -> LinkModel | None:
    """The radio channel of a scenario (None: ``links.enabled`` is false, the ideal radio).
    A line of sight is blocked by a sphere of the cube's corner radius around each body.
    The one place a world (in-process or distributed) builds its channel."""
    if not sc.links.enabled:
        return None
    return LinkModel(sc.links, sc.n_sats, sc.seed, float(sc.spacecraft.half_size_m * np.sqrt(3.0)))
