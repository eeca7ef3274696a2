"""Read a run's MCAP back into its :class:`~swarmcore.result.RunResult`: the result ``swarm
sim`` gives, filled from the messages by the same :class:`~swarmcore.result.RunBuilder`
(and :attr:`~swarmcore.result.RunResult.bus`: what only the bus shows).

Reads recordings of the protobuf wire format (schema ``swarm.v1``). Recordings made before
it (JSON messages, schemas named ``swarm.<Message>``) are refused with a message saying so.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np
from google.protobuf.message import DecodeError

from swarm.record.mcaplog import iter_messages
from swarmcore.links import LinkCounters
from swarmcore.mekf import RelativeMeasurements
from swarmcore.result import BusRecord, BusTimes, RunBuilder, RunResult
from swarmcore.scenario import Scenario
from swarmrt.bus.convert import absolute_from_sensors, array, pairs_from_select, relative_from_batches, relative_from_step
from swarmrt.bus.messages import BusGap, Liveliness, Malformed, MessageError, as_dict, decode, parse_key

__all__ = ["BoundInputs", "BusTimes", "RecordingError", "load_recording"]


class RecordingError(ValueError):
    """A recording that cannot be read into a run result; the message says why."""


def _check_format(topic: str, schema: str) -> None:
    if schema.startswith("swarm.") and not schema.startswith("swarm.v1."):
        raise RecordingError(
            f"{topic}: recorded with schema {schema!r}, the JSON messages of swarm-coloc before the "
            "protobuf wire format (swarm.v1); this version reads only swarm.v1 recordings"
        )


#: A message as :func:`~swarm.record.mcaplog.iter_messages` yields it: topic, schema name,
#: data, log time and publish time (ns).
RecordedMessage = tuple[str, str, bytes, int, int]


def _read(path, messages: Sequence[RecordedMessage] | None) -> Iterable[RecordedMessage]:
    """The recording's messages: those given (read already by the caller), else the file's,
    streamed from it (a recording larger than memory loads too)."""
    return iter_messages(path) if messages is None else messages


def _shape(path, n: int | None = None, messages: Sequence[RecordedMessage] | None = None) -> tuple[int, int]:
    """(n, K) from the truth messages of a recording (of ``n`` satellites if given).

    n is the size most truth messages have. K is one past the last step k whose truth, with
    at least half of the steps 0..k recorded, belongs to a run: the world publishes a truth
    every step, so a step far beyond what was recorded is a damaged number, not a step (a
    flipped bit in one step number must not ask for terabytes of arrays)."""
    steps: dict[int, set[int]] = {}  # size → steps with a truth of that size
    for topic, schema, data, _lt, _pt in _read(path, messages):
        try:
            kind = parse_key(topic)[1]
        except MessageError:
            continue  # our own channels and the derived Foxglove ones (``/foxglove/truth`` too)
        if kind == "truth":
            _check_format(topic, schema)
            try:
                m = decode("truth", data, n_sats=n)
            except MessageError:
                continue
            size = len(m.q_BI) // 4
            if n is None or size == n:
                steps.setdefault(size, set()).add(int(m.k))
    if not steps:
        raise RecordingError(f"{path}: no truth messages{f' of {n} satellites' if n else ''}; cannot tell the swarm's size")
    n = max(steps, key=lambda size: (len(steps[size]), -size))
    K = 0
    for i, k in enumerate(sorted(steps[n]), start=1):
        if 2 * i >= k + 1:
            K = k + 1
    if not K:
        raise RecordingError(f"{path}: truth messages only of steps {sorted(steps[n])[:5]}..., fewer than half of the steps before them")
    return n, K


def _rows(values, width: int = 3) -> np.ndarray:
    """A message's per-satellite numbers as rows (n, width)."""
    return np.asarray(values).reshape(-1, width)


_NS_MAX = 2**63  # Unix nanoseconds as int64 (the year 2262)


class BoundInputs:
    """What the Cramér–Rao bound (``scenario.bound``, :mod:`swarmcore.crlb`) of a recorded run
    counts, gathered message by message as the recording is read (:meth:`add`), then handed
    to a :class:`~swarmcore.result.RunBuilder` (:meth:`count`) in the order the in-process
    simulator hands its own (``swarmcore.sim._count_for_bound``), so that a lockstep run's
    bound is ``swarm sim``'s to the bit.

    Centralized (``bound.filter`` None): every relative measurement an observer put on the
    bus (``meas/<i>``, at its step, observers ascending) and every absolute reading the
    world gave (``sat/<i>/sensors`` with a star tracker or GPS reading). Of filter f, at each
    step the world counted f live (it sent f its sensors): f's own batch (``meas/<f>``), then
    what its radio brought it: the ideal radio's batches of the step (``batches``, f's own
    rows skipped, or ``batches/<f>``) or the link model's deliveries (``rx/<f>``, each batch
    counted at the step it was taken, in (step, observer) order, late ones too), and its
    own absolute reading. The peers' absolute readings reach f only in the centralized
    reference's estimator messages (:class:`swarmcore.estimators.full.CentralMessage`, kind
    ``central`` or ``full``): those delivered to f (well formed) are counted too, each at the
    step it was taken, as the simulator counts them."""

    def __init__(self, n: int, K: int, f: int | None):
        self.n, self.K, self.f = n, K, f
        self.own: dict[tuple[int, int], RelativeMeasurements] = {}  # (step, observer) → its batch
        self.heard: dict[int, list[tuple[int, int, RelativeMeasurements]]] = {}  # step → (taken at, observer, batch) delivered
        self.absolute: dict[int, set[int]] = {}  # step → satellites given an absolute reading
        self.sensed: dict[int, set[int]] = {}  # step → satellites the world sent their sensors (live)
        self.heard_absolute: dict[int, set[tuple[int, int]]] = {}  # step → (taken at, sender) of peers' readings delivered

    def wants(self, kind: str, sat: int | None) -> bool:
        """Whether the message of ``kind`` on satellite ``sat``'s key (None: a key of no
        satellite) counts: the centralized bound reads every batch and reading, filter f's
        only its own and what was delivered to it."""
        f = self.f
        if kind in ("meas", "sensors"):
            return f is None or sat == f
        if kind == "rx":
            return f is not None and sat == f
        if kind == "batches":
            return f is not None and (sat is None or sat == f)
        return False

    def add(self, kind: str, m) -> None:
        """A decoded message of ``kind`` (one :meth:`wants`)."""
        k = int(m.k)
        if kind == "meas":
            self.own[(k, int(m.observer))] = relative_from_batches([m])
        elif kind == "sensors":
            self.sensed.setdefault(k, set()).add(int(m.sat))
            if absolute_from_sensors(m) is not None:
                self.absolute.setdefault(k, set()).add(int(m.sat))
        elif kind == "batches":  # one message of the step's batches: in observer order already
            self.heard.setdefault(k, []).append((k, -1, relative_from_step(m, skip=self.f)))
            for o, e in zip(m.observers, m.estimators, strict=False):
                if o != self.f and self._carries_reading(e):
                    self.heard_absolute.setdefault(k, set()).add((k, int(o)))
        elif kind == "rx":
            got = self.heard.setdefault(k, [])
            for it in m.items:
                if it.batch.observer != self.f and 0 <= it.batch.k < self.K:
                    got.append((int(it.batch.k), int(it.batch.observer), relative_from_batches([it.batch])))
                    if it.batch.HasField("estimator") and self._carries_reading(it.batch.estimator):
                        self.heard_absolute.setdefault(k, set()).add((int(it.batch.k), int(it.batch.observer)))

    def count(self, b) -> None:
        """Hand what was gathered to ``b`` (its ``measured_at`` and ``absolute_at``), step
        by step as the simulator does."""
        f = self.f
        for k in range(self.K):
            if f is None:
                for i in range(self.n):
                    if (k, i) in self.own:
                        b.measured_at(k, self.own[(k, i)])
                b.absolute_at(k, sorted(self.absolute.get(k, ())))
            elif f in self.sensed.get(k, ()):
                if (k, f) in self.own:
                    b.measured_at(k, self.own[(k, f)])
                for s, _o, rel in sorted(self.heard.get(k, ()), key=lambda x: (x[0], x[1])):
                    b.measured_at(s, rel)
                for s, j in sorted(self.heard_absolute.get(k, ())):
                    b.absolute_at(s, [j])
                b.absolute_at(k, [f] if f in self.absolute.get(k, ()) else [])

    @staticmethod
    def _carries_reading(e) -> bool:
        """Whether an estimator message is the centralized reference's with its sender's
        absolute reading (what its receiver applies: one it decodes)."""
        from swarmcore.estimators.full import CentralEstimator, CentralMessage

        if e.kind not in ("central", "full") or e.version != CentralEstimator.message_version or e.WhichOneof("body") != "opaque":
            return False
        try:
            CentralMessage.decode(bytes(e.opaque))
        except ValueError:
            return False
        return True


_USED = ("truth", "est", "select", "meas", "fault", "links", "rejoin")


def load_recording(path: str | Path, n: int | None = None, K: int | None = None, *,
                   messages: Sequence[RecordedMessage] | None = None, scenario: Scenario | None = None) -> RunResult:
    """The run recorded in ``path``: of ``n`` satellites and ``K`` steps, or as many as its
    truth messages say. ``messages``: the file's messages as
    :func:`~swarm.record.mcaplog.iter_messages` yields them, for a caller that has read them
    already (and loads them more than one way, as the fuzz target); by default the file is
    read here, twice if n or K is not given (once for the shape, once for the contents).
    ``scenario``: the scenario it ran (the result's, for :meth:`~swarmcore.result.RunResult.summary`);
    with it, the result has the run's Cramér–Rao bound (:class:`BoundInputs`) when the
    scenario's ``bound`` is on."""
    if n is None or K is None:
        n0, K0 = _shape(path, n, messages)
        n, K = n or n0, K or K0
    b = RunBuilder(K, n)
    bound = BoundInputs(n, K, scenario.bound.filter) if scenario is not None and scenario.bound_on and scenario.n_sats == n else None
    bound_seen: set[tuple[str, int, int, int]] = set()  # as ``seen``, for the messages only the bound reads
    bus = BusRecord()
    posteriors = []  # (k, f, message): scored once every truth is in
    counts: dict[str, int] = {}
    bus_rows: list[tuple[str, str, int, int, int]] = []
    seen: set[tuple[str, int, int, int]] = set()  # (topic, step, size, hash of the payload) read so far
    for topic, schema, data, log_ns, pub_ns in _read(path, messages):
        _check_format(topic, schema)
        try:
            _run, kind, sat = parse_key(topic)
        except MessageError:
            # Our alive / _malformed channels, and the derived Foxglove ones.
            kind, sat = topic if topic.startswith("/") else topic.rsplit("/", 1)[-1], None
        # The recorder's counts, one record per key, the count its payload: what its flood cap
        # cut, and the resends it did not write again.
        tally = {"_not_recorded": bus.not_recorded, "_resent": bus.resent_not_written}.get(kind)
        if tally is not None:
            with contextlib.suppress(DecodeError, ValueError):
                m = Malformed.FromString(data)
                tally[m.key] = tally.get(m.key, 0) + int(m.payload.decode())
            continue
        counts[kind] = counts.get(kind, 0) + 1
        if kind == "alive":
            with contextlib.suppress(DecodeError):
                bus.liveliness.append({**as_dict(Liveliness.FromString(data)), "log_time_ns": log_ns})
        if kind == "health":
            try:
                h = decode("health", data, n_sats=n)
                bus.dropped[f"agent-{h.sat}"] = (h.malformed, h.key_mismatch)
            except MessageError:
                pass
        if kind == "clock":
            try:
                c = decode("clock", data, n_sats=n)
                bus.dropped["world"] = (c.malformed, c.key_mismatch)
                if bus.recorder_waits is None or c.recorder_waited_steps >= bus.recorder_waits[0]:  # (counts only grow)
                    bus.recorder_waits = (int(c.recorder_waited_steps), float(c.recorder_waited_s))
            except MessageError:
                pass
        if kind == "_gap":
            try:
                g = BusGap.FromString(data)
            except DecodeError:
                continue
            bus.gaps.append({"observer": g.observer, "down_unix_ns": g.down_unix_ns, "up_unix_ns": g.up_unix_ns or None,
                             "duration_s": (g.up_unix_ns - g.down_unix_ns) / 1e9 if g.up_unix_ns else None,
                             "last_step_before": g.last_step_before, "first_step_after": g.first_step_after})
        if bound is not None and kind in ("sensors", "batches", "rx") and bound.wants(kind, sat):  # (meas: below)
            with contextlib.suppress(MessageError):
                mb = decode(kind, data, n_sats=n)
                ident = (topic, mb.k, len(data), hash(data))
                if ident not in bound_seen and 0 <= mb.k < K:
                    bound_seen.add(ident)
                    bound.add(kind, mb)
        if kind not in _USED:
            continue
        try:
            # Every satellite id within the swarm (the arrays below are indexed by them).
            m = decode(kind, data, n_sats=n)
        except MessageError:
            continue
        rows = len(m.ids) if kind == "est" and len(m.ids) else n  # an estimate lists the satellites it holds, or all
        if (kind in ("truth", "est") and len(m.q_BI) != 4 * rows) or (kind == "links" and len(m.queue_bytes) != n):
            continue  # of another swarm's size: not this run's (a damaged message)
        # A message sent again after a bus gap is the same bytes: read it once.
        ident = (topic, m.k, len(data), hash(data))
        if ident in seen:
            counts[kind] -= 1
            bus.resent += 1
            continue
        seen.add(ident)
        if 0 <= pub_ns < _NS_MAX and 0 <= log_ns < _NS_MAX:  # (MCAP times are uint64: a damaged one is no instant)
            bus_rows.append((m.sender, kind, m.k, pub_ns, log_ns))
        k = m.k
        if not 0 <= k < K:
            continue
        if kind == "truth":
            b.truth_at(k, m.t_s, _rows(m.q_BI, 4), _rows(m.omega_BI_B_rad_s), _rows(m.r_H_m), _rows(m.v_H_m_s),
                       _rows(m.gyro_bias_B_rad_s))
        elif kind == "est" and m.phase == "posterior":
            f = m.own
            ids = np.asarray(m.ids, dtype=int) if len(m.ids) else np.arange(n)
            if ids.size != len(m.q_BI) // 4 or ids.max() >= n or f >= n:
                continue  # an estimate of another swarm's size: not this run's
            posteriors.append((k, f, ids, m))
        elif kind == "rejoin":
            bus.rejoins.append({"k": m.k, "sat": m.sat, "peer": m.peer, "bytes": m.bytes, "fate": m.fate,
                                "arrival_t_s": m.arrival_t_s if m.HasField("arrival_t_s") else None})
        elif kind == "links":
            b.links_at(k, LinkCounters(**{name: np.rint(array(getattr(m, name))).astype(int)
                                          for name in LinkCounters.__dataclass_fields__}), list(m.queue_bytes))
            b.link_latencies.extend((x.sender, x.receiver, x.sent_k, x.latency_s) for x in m.latencies)
        elif kind == "select":
            obs, tgt = pairs_from_select(m)
            b.selected_at(k, obs, tgt)
            if m.fallback:
                bus.fallback_steps.append(k)
            bus.select_ms.append(m.select_ms)
        elif kind == "meas":
            b.taken_at(k, m.observer, np.asarray(m.target, dtype=int))
            if bound is not None and bound.wants(kind, m.observer):
                bound.add(kind, m)
        elif kind == "fault":
            d = as_dict(m)
            bus.faults.append({**{f: d[f] for f in ("k", "t_s", "action", "phase", "sender", "target", "camera", "state", "rate",
                                                  "netem", "down_s", "peer", "delay_s", "detail")}, "log_time_ns": log_ns})
    for k, f, ids, m in posteriors:  # every truth is in: scored against the truth of its step, as the simulator does
        b.estimate_at(k, f, ids, _rows(m.q_BI, 4), _rows(m.omega_BI_B_rad_s), _rows(m.r_H_m), _rows(m.v_H_m_s),
                      np.asarray(m.bias_B_rad_s), array(m.P_diag), array(m.P_pose),
                      array(m.P_rel_pose) if m.HasField("P_rel_pose") else None)
        b.report_at(k, f, gate_accepted=m.gate_accepted, gate_rejected=m.gate_rejected, nis=m.nis, nis_dof=m.nis_dof,
                    late_used=m.late_used, late_dropped=m.late_dropped, replayed_steps=m.replayed_steps)
        b.step_ms[k, f], b.cpu_ms[k, f], b.bytes_sent[k, f] = m.step_ms, m.step_cpu_ms, m.bytes_sent
        b.estimator = m.estimator or "full"
    if bus.resent:
        counts["resent_after_gap"] = bus.resent
    bus.counts = counts
    if bus_rows:
        sender, kinds, ks, pub, log = zip(*bus_rows)
        bus.times = BusTimes(np.array(sender), np.array(kinds), np.array(ks), np.array(pub, dtype=np.int64), np.array(log, dtype=np.int64))
    if bound is not None:
        bound.count(b)
    return b.result(scenario, bus)
