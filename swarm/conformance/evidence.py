"""What a conformance case's recording says about satellite i's agent.

Everything is read from ``run.mcap`` as the recorder wrote it (log times are the
recorder's receive times, Unix ns): the world's clocks, radio and faults, agent i's
messages (each checked as every receiver checks it: ``swarmrt.bus.messages.decode`` and
``check_key``), what the recorder refused (``_malformed``), liveliness and bus gaps.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from swarm.record.mcaplog import iter_messages
from swarmrt.bus.messages import BusGap, Liveliness, Malformed, MessageError, parse_key
from swarmrt.bus.receive import receive

__all__ = ["Evidence", "load_evidence", "estimate_arrays"]

#: The keys agent i may put on (``swarmrt.bus.messages.grants``), by kind.
OWN_KINDS = ("meas", "est", "health")


@dataclass
class Evidence:
    sat: int
    n: int
    clocks: dict[int, tuple[int, list[int]]] = field(default_factory=dict)  # k -> (log ns, live agents)
    done_clock_ns: int | None = None
    est: dict[int, list] = field(default_factory=dict)  # k -> [(phase, Estimate, log ns)] of agent i, in order
    meas: dict[int, list] = field(default_factory=dict)  # k -> [(MeasBatch, log ns)] of agent i
    health: dict[int, list] = field(default_factory=dict)  # k -> [(Health, log ns)] of agent i
    batches: dict[int, list[int]] = field(default_factory=dict)  # k -> observers the ideal radio carried
    rx: dict[int, list] = field(default_factory=dict)  # k -> [Delivery] to agent i
    faults: list = field(default_factory=list)  # (Fault, log ns), every one
    alive: list = field(default_factory=list)  # (role, id, alive, log ns)
    refused: list = field(default_factory=list)  # (key, reason) the recorder refused (``_malformed``)
    gaps: list = field(default_factory=list)  # BusGap
    link_lost_to_me: int = 0  # copies to agent i lost on the channel (the last LinkStats)
    link_late_to_me: int = 0  # copies to agent i delivered late
    other_rows: dict = field(default_factory=dict)  # (k, own) -> est of the other agents (posterior)
    clock_refused: tuple[int, int] = (0, 0)  # the world's last (malformed, key_mismatch)
    from_me: dict[str, int] = field(default_factory=dict)  # topic -> messages whose sender is agent i
    own_keys: set[str] = field(default_factory=set)  # the keys agent i may put on

    # -- per-step views -------------------------------------------------------------
    def posterior(self, k: int):
        """Agent i's (first) posterior estimate of step k, or None."""
        return next((m for ph, m, _t in self.est.get(k, []) if ph == "posterior"), None)

    def posterior_ns(self, k: int) -> int | None:
        return next((t for ph, _m, t in self.est.get(k, []) if ph == "posterior"), None)

    def priors(self) -> list[tuple[int, int]]:
        """(k, log ns) of every prior estimate agent i published."""
        return sorted((m.k, t) for ests in self.est.values() for ph, m, t in ests if ph == "prior")

    def steps(self) -> list[int]:
        return sorted(self.clocks)

    def last_health(self):
        if not self.health:
            return None
        return self.health[max(self.health)][-1][0]

    def token_events(self, role: str = "agent", ident: str | None = None) -> list[tuple[bool, int]]:
        ident = str(self.sat) if ident is None and role == "agent" else ident
        return [(a, t) for r, i, a, t in self.alive if r == role and (ident is None or i == ident)]

    def fault_reports(self, action: str, sender: str | None = None, phase: str = "done") -> list:
        return [(f, t) for f, t in self.faults
                if f.action == action and f.phase == phase and (sender is None or f.sender == sender)]

    def fault_commands(self, action: str) -> list:
        return [(f, t) for f, t in self.faults if f.action == action and f.phase == "command"]

    def clock_gaps_s(self) -> list[tuple[int, float]]:
        """(k, wall seconds from clock k to clock k+1, or to the done clock for the last)."""
        ks = self.steps()
        out = []
        for a, b in itertools.pairwise(ks):
            out.append((a, (self.clocks[b][0] - self.clocks[a][0]) / 1e9))
        if ks and self.done_clock_ns is not None:
            out.append((ks[-1], (self.done_clock_ns - self.clocks[ks[-1]][0]) / 1e9))
        return out


def estimate_arrays(m) -> np.ndarray:
    """The numbers of an estimate (state and covariances) in one array, for bit-for-bit
    comparison (not the timing fields, which no two runs share)."""
    parts = [m.q_BI, m.omega_BI_B_rad_s, m.r_H_m, m.v_H_m_s, m.bias_B_rad_s, m.P_pose.data, m.P_diag.data]
    return np.concatenate([np.asarray(p, dtype=float) for p in parts])


def _sender(kind: str, data: bytes) -> str:
    from swarmrt.bus.messages import MODELS

    m = MODELS[kind]()
    try:
        m.ParseFromString(data)
    except Exception:
        return ""
    return m.sender


def load_evidence(path: str | Path, run: str, sat: int, n: int) -> Evidence:
    ev = Evidence(sat=sat, n=n)
    me = f"agent-{sat}"
    own_keys = {f"swarm/{run}/{kind}/{sat}" for kind in OWN_KINDS} | {f"swarm/{run}/fault/{me}"}
    ev.own_keys = own_keys
    if not Path(path).exists():
        return ev
    seen: set[tuple[str, int, int]] = set()  # a message sent again after a bus gap: read once
    for topic, _schema, data, log_ns, _pub in iter_messages(path):
        if topic == f"swarm/{run}/alive":
            lv = Liveliness.FromString(data)
            ev.alive.append((lv.role, lv.id, lv.alive, log_ns))
            continue
        if topic == f"swarm/{run}/_malformed":
            m = Malformed.FromString(data)
            ev.refused.append((m.key, m.error))
            continue
        if topic == f"swarm/{run}/_gap":
            ev.gaps.append(BusGap.FromString(data))
            continue
        try:
            _run, kind, ksat = parse_key(topic)
        except MessageError:
            continue  # the derived Foxglove channels
        if kind not in ("alive", "claim") and _sender(kind, data) == me:
            ev.from_me[topic] = ev.from_me.get(topic, 0) + 1
        if kind not in ("clock", "est", "meas", "health", "batches", "rx", "fault", "links"):
            continue
        if kind in ("rx", "batches") and ksat is not None and ksat != sat:
            continue  # another agent's radio (rx/<j>, batches/<j>)
        try:
            msg = receive(topic, data, run, n_sats=n).msg  # checked as every receiver of the swarm checks it
        except MessageError as exc:
            if topic in own_keys:
                ev.refused.append((topic, f"(read back) {exc}"))
            continue
        ident = (topic, len(data), hash(data))
        if ident in seen:
            continue
        seen.add(ident)
        if kind == "clock":
            ev.clock_refused = (int(msg.malformed), int(msg.key_mismatch))
            if msg.done:
                ev.done_clock_ns = log_ns if ev.done_clock_ns is None else ev.done_clock_ns
            elif msg.k not in ev.clocks:
                ev.clocks[int(msg.k)] = (log_ns, list(msg.live_agents))
        elif kind == "est":
            if msg.own == sat:
                ev.est.setdefault(int(msg.k), []).append((msg.phase, msg, log_ns))
            elif msg.phase == "posterior":
                ev.other_rows[(int(msg.k), int(msg.own))] = msg
        elif kind == "meas" and msg.observer == sat:
            ev.meas.setdefault(int(msg.k), []).append((msg, log_ns))
        elif kind == "health" and msg.sat == sat:
            ev.health.setdefault(int(msg.k), []).append((msg, log_ns))
        elif kind == "batches":
            ev.batches.setdefault(int(msg.k), []).extend(int(o) for o in msg.observers)
        elif kind == "rx":
            ev.rx.setdefault(int(msg.k), []).append(msg)
        elif kind == "fault":
            ev.faults.append((msg, log_ns))
        elif kind == "links":
            from swarmrt.bus.convert import array

            ev.link_lost_to_me = int(np.rint(array(msg.lost))[:, sat].sum())
            ev.link_late_to_me = int(np.rint(array(msg.delivered_late))[:, sat].sum())
    return ev
