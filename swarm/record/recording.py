"""Read a run's MCAP back into arrays and the ``summary.json`` contract of ``swarm sim``.

Reads recordings of the protobuf wire format (schema ``swarm.v1``). Recordings made before
it (JSON messages, schemas named ``swarm.<Message>``) are refused with a message saying so.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from google.protobuf.message import DecodeError

from swarm.record.mcaplog import iter_messages
from swarmcore.links import LinkCounters
from swarmcore.metrics import pose_errors, pose_nees, relative_pose_errors, run_summary
from swarmcore.scenario import Scenario
from swarmcore.sim import link_summary
from swarmrt.bus.convert import array, pairs_from_select
from swarmrt.bus.messages import BusGap, LinkStats, Liveliness, Malformed, MessageError, as_dict, decode, parse_key

__all__ = ["Recording", "BusTimes", "RecordingError", "load_recording"]


class RecordingError(ValueError):
    """A recording that cannot be read into a run result; the message says why."""


@dataclass
class Recording:
    n: int
    K: int
    t: np.ndarray
    truth_q: np.ndarray  # (K, n, 4)
    truth_r: np.ndarray
    est_q: np.ndarray  # (K, F, n, 4) NaN where missing (not estimated, or a satellite the filter does not track)
    est_r: np.ndarray
    pose_var: np.ndarray  # (K, F, n, 6) the diagonal of each pose covariance
    P_diag: np.ndarray  # (K, F, 12n)
    alive: np.ndarray  # (K, F) an estimate exists
    gate_accepted: np.ndarray
    gate_rejected: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    step_ms: np.ndarray
    schedule: np.ndarray  # (K, n, n) pairs selected for the step
    taken: np.ndarray  # (K, n, n) relative measurements actually broadcast
    late_used: np.ndarray  # (K, F)
    late_dropped: np.ndarray
    replayed: np.ndarray
    faults: list = field(default_factory=list)
    fallback_steps: list = field(default_factory=list)
    select_ms: list = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    liveliness: list = field(default_factory=list)
    links: LinkStats | None = None  # the last LinkStats message (cumulative counters)
    link_latencies: list = field(default_factory=list)  # (sender, receiver, sent step, latency s)
    link_series: list = field(default_factory=list)  # (k, cumulative totals, queue bytes) per step
    rejoins: list = field(default_factory=list)  # the radio's fates of restarted agents' state transfers
    dropped: dict = field(default_factory=dict)  # agent-<i> or world -> (malformed, of which key mismatch): its last report's counts
    not_recorded: dict = field(default_factory=dict)  # key -> messages the recorder's flood cap did not write
    bus: BusTimes | None = None  # every bus message's sender, kind, step, publish and receive time
    gaps: list = field(default_factory=list)  # the recorder's bus gaps (no router reachable)
    resent: int = 0  # messages recorded twice (sent again after a bus gap; read once)
    bytes_sent: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (K, F) bytes each agent put on its radio per step
    cpu_ms: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))  # (K, F) CPU time of each filter step
    estimator: str = "full"
    # Each posterior's covariances as it came (step, filter, satellite ids, P_pose (m, 6, 6),
    # P_rel_pose (m, 6, 6) or None): held sparse, so a 100-satellite run of an estimator
    # that tracks a few peers needs no (K, F, n, 6, 6) array.
    cov_rows: list = field(default_factory=list)

    @property
    def P_pose(self) -> np.ndarray:
        """(K, F, n, 6, 6) dense pose covariances (NaN where none): built when asked."""
        out = np.full((self.K, len(self.alive[0]), self.n, 6, 6), np.nan)
        for k, f, ids, P, _rel in self.cov_rows:
            out[k, f, ids] = P
        return out

    def bus_latency_ms(self, published_from_ns: int | None = None, published_to_ns: int | None = None) -> dict:
        """Per sender (``agent-3``, ``world``, ...): the one-way bus latency of its messages
        (recorder receive time − the publisher's Zenoh timestamp, ms) as ``n``, ``min``,
        ``p50``, ``p95``, ``max``; optionally only messages published in
        ``[published_from_ns, published_to_ns)`` (Unix ns). Messages that carried no
        timestamp (publish time = log time in the file) are left out and counted as
        ``unstamped``."""
        return self.bus.latency_stats(published_from_ns, published_to_ns) if self.bus is not None else {}

    def errors(self):
        """Pose errors ``a``, ``Δr`` (K, F, n, 3), their norms and NEES (K, F, n) of every
        filter's estimate of every satellite it tracks (NaN elsewhere)."""
        a, dr = pose_errors(self.est_q, self.est_r, self.truth_q[:, None], self.truth_r[:, None])
        att = np.linalg.norm(a, axis=-1)
        pos = np.linalg.norm(dr, axis=-1)
        nees = np.full(att.shape, np.nan)
        for k, f, ids, P, _rel in self.cov_rows:
            if np.isfinite(a[k, f, ids]).all():
                nees[k, f, ids] = pose_nees(a[k, f, ids], dr[k, f, ids], P)
        return a, dr, att, pos, nees

    def relative_errors(self):
        """Each filter's estimate of every tracked peer relative to itself: attitude and
        position error norms and NEES against the relative covariance it claimed, (K, F, n)."""
        a, dr = relative_pose_errors(self.est_q, self.est_r, self.truth_q, self.truth_r)
        att = np.linalg.norm(a, axis=-1)
        pos = np.linalg.norm(dr, axis=-1)
        nees = np.full(att.shape, np.nan)
        for k, f, ids, _P, rel in self.cov_rows:
            if rel is None:
                continue
            keep = ids != f
            j = ids[keep]
            if np.isfinite(a[k, f, j]).all():
                nees[k, f, j] = pose_nees(a[k, f, j], dr[k, f, j], rel[keep])
        return att, pos, nees

    def summary(self, sc: Scenario) -> dict:
        _a, _dr, att, pos, nees = self.errors()
        ratt, rpos, rnees = self.relative_errors()
        return run_summary(
            sc,
            att_err=att,
            pos_err=pos,
            nees=nees,
            gate_accepted=self.gate_accepted,
            gate_rejected=self.gate_rejected,
            step_ms=self.step_ms,
            nis=self.nis,
            nis_dof=self.nis_dof,
            taken=self.taken,
            estimator=self.estimator,
            rel_att_err=ratt,
            rel_pos_err=rpos,
            rel_nees=rnees,
            bytes_sent=np.where(self.alive, self.bytes_sent, np.nan),
            cpu_ms=np.where(self.alive, self.cpu_ms, np.nan),
            late=(self.late_used, self.late_dropped, self.replayed),
            alive=self.alive,
            extra={
                **({"links": link_summary(self.link_counters(), self.link_latencies)} if self.links is not None else {}),
                **({"bus_latency_ms": lat} if (lat := self.bus_latency_ms()) else {}),
                "faults": self.faults,
                "selector_fallback_steps": self.fallback_steps,
                "messages": {**self.counts, **({"not_recorded_over_the_flood_cap": self.not_recorded} if self.not_recorded else {})},
                "security": security_summary(sc.emulator.security, self.dropped),
                **({"bus_gaps": self.gaps} if self.gaps else {}),
            },
        )

    def link_counters(self) -> LinkCounters:
        """The cumulative per-link counters of the last step recorded."""
        m = self.links
        return LinkCounters(**{name: np.rint(array(getattr(m, name))).astype(int) for name in LinkCounters.__dataclass_fields__})


def security_summary(on: bool, dropped: dict) -> dict:
    """``summary.json``'s ``security``: on or off (off says so in words), and what the world
    and each agent dropped: malformed messages, and of those the ones on a key their sender
    field may not use (someone speaking for another, whatever the router let through)."""
    out: dict = {"state": "on" if on else "off"}
    if not on:
        out["warning"] = ("emulator.security was off: no authentication and no access rules on the bus; "
                          "any process that reached the router could publish anything")
    names = sorted(dropped, key=lambda a: (a != "world", int(a.split("-")[1]) if a.startswith("agent-") else -1))
    out["malformed_dropped"] = {a: int(dropped[a][0]) for a in names}
    out["key_mismatch_dropped"] = {a: int(dropped[a][1]) for a in names}
    return out


@dataclass
class BusTimes:
    """Publish and receive times of every bus message of a recording (one row each)."""

    sender: np.ndarray  # (M,) str: the message header's sender
    kind: np.ndarray  # (M,) str: message kind (est, meas, health, ...)
    k: np.ndarray  # (M,) step
    published_ns: np.ndarray  # (M,) int64: MCAP publish time (the publisher's Zenoh timestamp)
    received_ns: np.ndarray  # (M,) int64: MCAP log time (the recorder's receive time)

    @property
    def latency_ms(self) -> np.ndarray:
        return (self.received_ns - self.published_ns) / 1e6

    def latency_stats(self, published_from_ns: int | None = None, published_to_ns: int | None = None) -> dict:
        sel = np.ones(self.k.shape, dtype=bool)
        if published_from_ns is not None:
            sel &= self.published_ns >= published_from_ns
        if published_to_ns is not None:
            sel &= self.published_ns < published_to_ns
        lat = self.latency_ms
        out = {}
        for sender in sorted(set(self.sender[sel].tolist())):
            mine = sel & (self.sender == sender)
            stamped = mine & (self.published_ns != self.received_ns)
            x = lat[stamped]
            row: dict[str, float] = {"n": int(x.size)}
            if x.size:
                row.update({"min": round(float(x.min()), 3), "p50": round(float(np.percentile(x, 50)), 3),
                            "p95": round(float(np.percentile(x, 95)), 3), "max": round(float(x.max()), 3)})
            if (unstamped := int(mine.sum() - stamped.sum())):
                row["unstamped"] = unstamped
            out[sender] = row
        return out


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


_NS_MAX = 2**63  # Unix nanoseconds as int64 (the year 2262)
_USED = ("truth", "est", "select", "meas", "fault", "links", "rejoin")


def load_recording(path: str | Path, n: int | None = None, K: int | None = None, *,
                   messages: Sequence[RecordedMessage] | None = None) -> Recording:
    """The run recorded in ``path``: of ``n`` satellites and ``K`` steps, or as many as its
    truth messages say. ``messages``: the file's messages as
    :func:`~swarm.record.mcaplog.iter_messages` yields them, for a caller that has read them
    already (and loads them more than one way, as the fuzz target); by default the file is
    read here, twice if n or K is not given (once for the shape, once for the contents)."""
    if n is None or K is None:
        n0, K0 = _shape(path, n, messages)
        n, K = n or n0, K or K0
    nan = np.nan
    F = n
    rec = Recording(
        n=n,
        K=K,
        t=np.arange(K, dtype=float) * nan,
        truth_q=np.full((K, n, 4), nan),
        truth_r=np.full((K, n, 3), nan),
        est_q=np.full((K, F, n, 4), nan),
        est_r=np.full((K, F, n, 3), nan),
        pose_var=np.full((K, F, n, 6), nan),
        P_diag=np.full((K, F, 12 * n), nan),
        alive=np.zeros((K, F), dtype=bool),
        gate_accepted=np.zeros((K, F), dtype=int),
        gate_rejected=np.zeros((K, F), dtype=int),
        nis=np.full((K, F), nan),
        nis_dof=np.zeros((K, F), dtype=int),
        step_ms=np.full((K, F), nan),
        schedule=np.zeros((K, n, n), dtype=bool),
        taken=np.zeros((K, n, n), dtype=bool),
        late_used=np.zeros((K, F), dtype=int),
        late_dropped=np.zeros((K, F), dtype=int),
        replayed=np.zeros((K, F), dtype=int),
        bytes_sent=np.full((K, F), nan),
        cpu_ms=np.full((K, F), nan),
    )
    counts: dict[str, int] = {}
    bus_rows: list[tuple[str, str, int, int, int]] = []
    seen: set[tuple[str, int, int, int]] = set()  # (topic, step, size, hash of the payload) read so far
    for topic, schema, data, log_ns, pub_ns in _read(path, messages):
        _check_format(topic, schema)
        try:
            _run, kind, _sat = parse_key(topic)
        except MessageError:
            # Our alive / _malformed channels, and the derived Foxglove ones.
            kind = topic if topic.startswith("/") else topic.rsplit("/", 1)[-1]
        if kind == "_not_recorded":  # the recorder's flood cap: one record per key it cut, the count its payload
            with contextlib.suppress(DecodeError, ValueError):
                m = Malformed.FromString(data)
                rec.not_recorded[m.key] = rec.not_recorded.get(m.key, 0) + int(m.payload.decode())
            continue
        counts[kind] = counts.get(kind, 0) + 1
        if kind == "alive":
            with contextlib.suppress(DecodeError):
                rec.liveliness.append({**as_dict(Liveliness.FromString(data)), "log_time_ns": log_ns})
        if kind == "health":
            try:
                h = decode("health", data, n_sats=n)
                rec.dropped[f"agent-{h.sat}"] = (h.malformed, h.key_mismatch)
            except MessageError:
                pass
        if kind == "clock":
            try:
                c = decode("clock", data, n_sats=n)
                rec.dropped["world"] = (c.malformed, c.key_mismatch)
            except MessageError:
                pass
        if kind == "_gap":
            try:
                g = BusGap.FromString(data)
            except DecodeError:
                continue
            rec.gaps.append({"observer": g.observer, "down_unix_ns": g.down_unix_ns, "up_unix_ns": g.up_unix_ns or None,
                             "duration_s": (g.up_unix_ns - g.down_unix_ns) / 1e9 if g.up_unix_ns else None,
                             "last_step_before": g.last_step_before, "first_step_after": g.first_step_after})
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
            rec.resent += 1
            continue
        seen.add(ident)
        if 0 <= pub_ns < _NS_MAX and 0 <= log_ns < _NS_MAX:  # (MCAP times are uint64: a damaged one is no instant)
            bus_rows.append((m.sender, kind, m.k, pub_ns, log_ns))
        k = m.k
        if not 0 <= k < K:
            continue
        if kind == "truth":
            rec.t[k] = m.t_s
            rec.truth_q[k] = np.asarray(m.q_BI).reshape(-1, 4)
            rec.truth_r[k] = np.asarray(m.r_H_m).reshape(-1, 3)
        elif kind == "est" and m.phase == "posterior":
            f = m.own
            ids = np.asarray(m.ids, dtype=int) if len(m.ids) else np.arange(n)
            if ids.size != len(m.q_BI) // 4 or ids.max() >= n or f >= F:
                continue  # an estimate of another swarm's size: not this run's
            rec.alive[k, f] = True
            rec.est_q[k, f, ids] = np.asarray(m.q_BI).reshape(-1, 4)
            rec.est_r[k, f, ids] = np.asarray(m.r_H_m).reshape(-1, 3)
            P = array(m.P_pose)
            rec.pose_var[k, f, ids] = np.diagonal(P, axis1=-2, axis2=-1)
            rec.cov_rows.append((k, f, ids, P, array(m.P_rel_pose) if m.HasField("P_rel_pose") else None))
            rec.P_diag[k, f, (12 * ids[:, None] + np.arange(12)).ravel()] = array(m.P_diag)
            rec.bytes_sent[k, f] = m.bytes_sent
            rec.estimator = m.estimator or "full"
            rec.gate_accepted[k, f] = m.gate_accepted
            rec.gate_rejected[k, f] = m.gate_rejected
            rec.nis[k, f] = m.nis
            rec.nis_dof[k, f] = m.nis_dof
            rec.step_ms[k, f] = m.step_ms
            rec.cpu_ms[k, f] = m.step_cpu_ms
            rec.late_used[k, f] = m.late_used
            rec.late_dropped[k, f] = m.late_dropped
            rec.replayed[k, f] = m.replayed_steps
        elif kind == "rejoin":
            rec.rejoins.append({"k": m.k, "sat": m.sat, "peer": m.peer, "bytes": m.bytes, "fate": m.fate,
                                "arrival_t_s": m.arrival_t_s if m.HasField("arrival_t_s") else None})
        elif kind == "links":
            if rec.links is None or m.k >= rec.links.k:
                rec.links = m
            rec.link_latencies.extend((x.sender, x.receiver, x.sent_k, x.latency_s) for x in m.latencies)
            tot = [int(np.rint(array(getattr(m, name))).sum()) for name in
                   ("sent", "delivered", "delivered_late", "lost", "dropped_queue", "unreachable")]
            rec.link_series.append((m.k, tot, list(m.queue_bytes)))
        elif kind == "select":
            obs, tgt = pairs_from_select(m)
            rec.schedule[k, obs, tgt] = True
            if m.fallback:
                rec.fallback_steps.append(k)
            rec.select_ms.append(m.select_ms)
        elif kind == "meas":
            rec.taken[k, m.observer, np.asarray(m.target, dtype=int)] = True
        elif kind == "fault":
            d = as_dict(m)
            rec.faults.append({**{f: d[f] for f in ("k", "t_s", "action", "phase", "sender", "target", "camera", "state", "rate",
                                                  "netem", "down_s", "peer", "delay_s", "detail")}, "log_time_ns": log_ns})
    if rec.resent:
        counts["resent_after_gap"] = rec.resent
    rec.counts = counts
    if bus_rows:
        sender, kinds, ks, pub, log = zip(*bus_rows)
        rec.bus = BusTimes(np.array(sender), np.array(kinds), np.array(ks), np.array(pub, dtype=np.int64), np.array(log, dtype=np.int64))
    return rec
