"""Read a run's MCAP back into arrays and the ``summary.json`` contract of ``swarm sim``.

Reads recordings of the protobuf wire format (schema ``swarm.v1``). Recordings made before
it (JSON messages, schemas named ``swarm.<Message>``) are refused with a message saying so.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from swarmcore.metrics import pose_errors, pose_nees, summarize
from swarmcore.scenario import Scenario

from .bus.convert import array, pairs_from_select
from .bus.messages import Liveliness, MessageError, as_dict, decode, parse_key
from .mcaplog import iter_messages

__all__ = ["Recording", "load_recording"]


@dataclass
class Recording:
    n: int
    K: int
    t: np.ndarray
    truth_q: np.ndarray  # (K, n, 4)
    truth_r: np.ndarray
    est_q: np.ndarray  # (K, F, n, 4) NaN where missing
    est_r: np.ndarray
    P_pose: np.ndarray  # (K, F, n, 6, 6)
    P_diag: np.ndarray  # (K, F, 12n)
    alive: np.ndarray  # (K, F) an estimate exists
    gate_accepted: np.ndarray
    gate_rejected: np.ndarray
    nis: np.ndarray
    nis_dof: np.ndarray
    step_ms: np.ndarray
    schedule: np.ndarray  # (K, n, n) pairs selected for the step
    taken: np.ndarray  # (K, n, n) relative measurements actually broadcast
    faults: list = field(default_factory=list)
    fallback_steps: list = field(default_factory=list)
    select_ms: list = field(default_factory=list)
    counts: dict = field(default_factory=dict)
    liveliness: list = field(default_factory=list)

    def errors(self):
        a, dr = pose_errors(self.est_q, self.est_r, self.truth_q[:, None], self.truth_r[:, None])
        att = np.linalg.norm(a, axis=-1)
        pos = np.linalg.norm(dr, axis=-1)
        P = np.where(np.isfinite(self.P_pose), self.P_pose, np.eye(6))
        nees = pose_nees(np.nan_to_num(a), np.nan_to_num(dr), P)
        nees = np.where(self.alive[:, :, None], nees, np.nan)
        return a, dr, att, pos, nees

    def summary(self, sc: Scenario) -> dict:
        _a, _dr, att, pos, nees = self.errors()
        dof = float(np.nansum(self.nis_dof))
        return summarize(
            n_sats=self.n,
            dt=sc.dt_s,
            seed=sc.seed,
            att_err=att,
            pos_err=pos,
            nees=nees,
            gate_accepted=self.gate_accepted,
            gate_rejected=self.gate_rejected,
            step_ms=self.step_ms,
            alive=self.alive,
            extra={
                "scenario": sc.name,
                "mode": sc.filter.mode,
                "nis": {"sum": float(np.nansum(self.nis)), "dof": dof, "ratio": float(np.nansum(self.nis) / dof) if dof else None},
                "measurements_per_step_mean": float(self.taken.sum(axis=(1, 2)).mean()),
                "faults": self.faults,
                "selector_fallback_steps": self.fallback_steps,
                "messages": self.counts,
            },
        )


def _check_format(topic: str, schema: str) -> None:
    if schema.startswith("swarm.") and not schema.startswith("swarm.v1."):
        raise ValueError(
            f"{topic}: recorded with schema {schema!r}, the JSON messages of swarm-coloc before the "
            "protobuf wire format (swarm.v1); this version reads only swarm.v1 recordings"
        )


def _shape(path) -> tuple[int, int]:
    """(n, K) from the truth messages of a recording."""
    n, K = 0, 0
    for topic, schema, data, _lt, _pt in iter_messages(path):
        if topic.endswith("/truth"):
            _check_format(topic, schema)
            try:
                m = decode("truth", data)
            except MessageError:
                continue
            n = max(n, len(m.q_BI) // 4)
            K = max(K, int(m.k) + 1)
    if not n:
        raise ValueError(f"{path}: no truth messages; cannot tell the swarm's size")
    return n, K


_USED = ("truth", "est", "select", "meas", "fault")


def load_recording(path: str | Path, n: int | None = None, K: int | None = None) -> Recording:
    if n is None or K is None:
        n0, K0 = _shape(path)
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
        P_pose=np.full((K, F, n, 6, 6), nan),
        P_diag=np.full((K, F, 12 * n), nan),
        alive=np.zeros((K, F), dtype=bool),
        gate_accepted=np.zeros((K, F), dtype=int),
        gate_rejected=np.zeros((K, F), dtype=int),
        nis=np.full((K, F), nan),
        nis_dof=np.zeros((K, F), dtype=int),
        step_ms=np.full((K, F), nan),
        schedule=np.zeros((K, n, n), dtype=bool),
        taken=np.zeros((K, n, n), dtype=bool),
    )
    counts: dict[str, int] = {}
    for topic, schema, data, log_ns, _pub in iter_messages(path):
        _check_format(topic, schema)
        try:
            _run, kind, _sat = parse_key(topic)
        except MessageError:
            # Our alive / _malformed channels, and the derived Foxglove ones.
            kind = topic if topic.startswith("/") else topic.rsplit("/", 1)[-1]
        counts[kind] = counts.get(kind, 0) + 1
        if kind == "alive":
            rec.liveliness.append({**as_dict(Liveliness.FromString(data)), "log_time_ns": log_ns})
        if kind not in _USED:
            continue
        try:
            m = decode(kind, data)
        except MessageError:
            continue
        k = m.k
        if not 0 <= k < K:
            continue
        if kind == "truth":
            rec.t[k] = m.t_s
            rec.truth_q[k] = np.asarray(m.q_BI).reshape(-1, 4)
            rec.truth_r[k] = np.asarray(m.r_H_m).reshape(-1, 3)
        elif kind == "est" and m.phase == "posterior":
            f = m.own
            rec.alive[k, f] = True
            rec.est_q[k, f] = np.asarray(m.q_BI).reshape(-1, 4)
            rec.est_r[k, f] = np.asarray(m.r_H_m).reshape(-1, 3)
            rec.P_pose[k, f] = array(m.P_pose)
            rec.P_diag[k, f] = array(m.P_diag)
            rec.gate_accepted[k, f] = m.gate_accepted
            rec.gate_rejected[k, f] = m.gate_rejected
            rec.nis[k, f] = m.nis
            rec.nis_dof[k, f] = m.nis_dof
            rec.step_ms[k, f] = m.step_ms
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
            rec.faults.append({f: d[f] for f in ("k", "t_s", "action", "phase", "sender", "target", "camera", "state", "rate", "detail")})
    rec.counts = counts
    return rec
