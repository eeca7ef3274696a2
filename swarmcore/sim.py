"""In-process simulator: every satellite's filter on one machine, the same core calls in
the same order as the distributed emulator (``world_sim`` / ``sat_agent``), so both give
the same numbers.

One step k (t_k = k dt):

1. world: (k > 0) advance the truth from k−1 and emit each gyro's sample of that interval;
   absolute readings at t_k; the pairs scheduled for k (the graph, or the selector's
   choice from satellite 0's filter); what each observer's cameras deliver
   (:class:`swarmcore.measurement.CameraModel`).
2. agent i (:class:`swarmcore.agent.AgentFilter`): its pose estimator turns its own
   observation into relative measurements (predicting first when the estimator needs the
   prediction); then it updates with its absolute reading (if it has the sensors) and every
   observer's batch (all of it when cooperative, only its own rows when isolated) in
   canonical order.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .agent import AgentFilter, filter_params
from .graphs import scenario_graph
from .links import LinkCounters, LinkModel
from .measurement import MeasurementModel, synthetic_model
from .mekf import RelativeMeasurements, SwarmEstimate, UpdateReport
from .metrics import pose_cov_blocks, pose_errors, pose_nees, summarize
from .scenario import Scenario
from .selection import choose_pairs
from .world import absolute_measurements, initial_estimate, initial_truth, step_truth, world_params

__all__ = ["SimResult", "simulate", "make_filters", "link_summary", "late_summary", "link_body_radius"]


@dataclass
class SimResult:
    scenario: Scenario
    t: np.ndarray  # (K,)
    truth: dict  # q_BI (K,n,4), omega_BI_B, r_H, v_H, bias_B
    est: dict  # q_BI (K,F,n,4), omega_BI_B, r_H, v_H (K,F,n,3), bias_B (K,F,3), P_diag (K,F,12n)
    att_err: np.ndarray  # (K, F, n) rad
    pos_err: np.ndarray  # (K, F, n) m
    nees: np.ndarray  # (K, F, n)
    gate_accepted: np.ndarray  # (K, F)
    gate_rejected: np.ndarray  # (K, F)
    nis: np.ndarray  # (K, F) joint NIS of each update
    nis_dof: np.ndarray  # (K, F) its degrees of freedom
    step_ms: np.ndarray  # (K, F)
    schedule: np.ndarray  # (K, n, n) bool: relative measurements taken
    extra: dict = field(default_factory=dict)
    late_used: np.ndarray | None = None  # (K, F) late measurements inserted (replay)
    late_dropped: np.ndarray | None = None  # (K, F) late measurements dropped
    replayed: np.ndarray | None = None  # (K, F) filter steps re-run
    link_series: np.ndarray | None = None  # (K, 6) cumulative sent, delivered, late, lost, dropped, unreachable
    queue_bytes: np.ndarray | None = None  # (K, n) each transmitter's backlog at the step (bytes)
    link_latencies: list | None = None  # (sender, receiver, sent step, latency s) of each delivered batch

    def summary(self) -> dict:
        sc = self.scenario
        return summarize(
            n_sats=sc.n_sats,
            dt=sc.dt_s,
            seed=sc.seed,
            att_err=self.att_err,
            pos_err=self.pos_err,
            nees=self.nees,
            gate_accepted=self.gate_accepted,
            gate_rejected=self.gate_rejected,
            step_ms=self.step_ms,
            nis=self.nis,
            nis_dof=self.nis_dof,
            extra={
                "scenario": sc.name,
                "mode": sc.filter.mode,
                "measurements_per_step_mean": float(self.schedule.sum(axis=(1, 2)).mean()),
                **(late_summary(self.late_used, self.late_dropped, self.replayed)
                   if sc.links.enabled and self.late_used is not None and self.late_dropped is not None and self.replayed is not None
                   else {}),
                **self.extra,
            },
        )


class Recorder:
    """Collects per-step arrays (shared by the in-process and distributed paths)."""

    def __init__(self, K: int, F: int, n: int):
        self.t = np.zeros(K)
        self.truth = {
            "q_BI": np.zeros((K, n, 4)),
            "omega_BI_B": np.zeros((K, n, 3)),
            "r_H": np.zeros((K, n, 3)),
            "v_H": np.zeros((K, n, 3)),
            "bias_B": np.zeros((K, n, 3)),
        }
        nan = np.nan
        self.est = {
            "q_BI": np.full((K, F, n, 4), nan),
            "omega_BI_B": np.full((K, F, n, 3), nan),
            "r_H": np.full((K, F, n, 3), nan),
            "v_H": np.full((K, F, n, 3), nan),
            "bias_B": np.full((K, F, 3), nan),
            "P_diag": np.full((K, F, 12 * n), nan),
        }
        self.att_err = np.full((K, F, n), nan)
        self.pos_err = np.full((K, F, n), nan)
        self.nees = np.full((K, F, n), nan)
        self.gate_accepted = np.zeros((K, F), dtype=int)
        self.gate_rejected = np.zeros((K, F), dtype=int)
        self.nis = np.full((K, F), np.nan)
        self.nis_dof = np.zeros((K, F), dtype=int)
        self.step_ms = np.full((K, F), nan)
        self.schedule = np.zeros((K, n, n), dtype=bool)
        self.late_used = np.zeros((K, F), dtype=int)
        self.late_dropped = np.zeros((K, F), dtype=int)
        self.replayed = np.zeros((K, F), dtype=int)
        self.link_series = np.zeros((K, 6), dtype=int)  # cumulative sent, delivered, late, lost, dropped, unreachable
        self.queue_bytes = np.zeros((K, n), dtype=int)  # each transmitter's backlog at the step

    def late_at(self, k, f, lrep) -> None:
        self.late_used[k, f] = lrep.used
        self.late_dropped[k, f] = lrep.dropped
        self.replayed[k, f] = lrep.replayed_steps

    def links_at(self, k, lm) -> None:
        c = lm.counters
        self.link_series[k] = [c.sent.sum(), c.delivered.sum(), c.delivered_late.sum(), c.lost.sum(), c.dropped_queue.sum(),
                               c.unreachable.sum()]
        self.queue_bytes[k] = lm.queue_bytes(self.t[k])

    def truth_at(self, k, truth):
        self.t[k] = truth.t
        for key in self.truth:
            self.truth[key][k] = getattr(truth, key)

    def estimate_at(self, k, f, est: SwarmEstimate, report: UpdateReport | None, ms: float | None):
        e = self.est
        e["q_BI"][k, f] = est.q_BI
        e["omega_BI_B"][k, f] = est.omega_BI_B
        e["r_H"][k, f] = est.r_H
        e["v_H"][k, f] = est.v_H
        e["bias_B"][k, f] = est.bias_B
        e["P_diag"][k, f] = np.diag(est.P)
        a, dr = pose_errors(est.q_BI, est.r_H, self.truth["q_BI"][k], self.truth["r_H"][k])
        self.att_err[k, f] = np.linalg.norm(a, axis=-1)
        self.pos_err[k, f] = np.linalg.norm(dr, axis=-1)
        self.nees[k, f] = pose_nees(a, dr, pose_cov_blocks(est.P, est.n))
        if report is not None:
            self.gate_accepted[k, f] = report.n_accepted
            self.gate_rejected[k, f] = report.n_rejected
            self.nis[k, f] = report.nis
            self.nis_dof[k, f] = report.nis_dof
        if ms is not None:
            self.step_ms[k, f] = ms

    def result(self, sc: Scenario, extra: dict | None = None) -> SimResult:
        return SimResult(
            scenario=sc,
            t=self.t,
            truth=self.truth,
            est=self.est,
            att_err=self.att_err,
            pos_err=self.pos_err,
            nees=self.nees,
            gate_accepted=self.gate_accepted,
            gate_rejected=self.gate_rejected,
            nis=self.nis,
            nis_dof=self.nis_dof,
            step_ms=self.step_ms,
            schedule=self.schedule,
            extra=extra or {},
            late_used=self.late_used,
            late_dropped=self.late_dropped,
            replayed=self.replayed,
            link_series=self.link_series,
            queue_bytes=self.queue_bytes,
        )


def link_body_radius(sc: Scenario) -> float:
    """The sphere that blocks a line of sight (links.line_of_sight): the cube's corner radius."""
    return float(sc.spacecraft.half_size_m * np.sqrt(3.0))


def make_filters(sc: Scenario, truth) -> list[AgentFilter]:
    """Every satellite's filter at its prior, with the history its late handling needs."""
    f = sc.filter
    hist = int(np.ceil(f.history_s / sc.dt_s)) if sc.links.enabled and f.late == "replay" else 0
    return [AgentFilter(filter_params(sc, i), initial_estimate(sc, truth, i), f.mode, late=f.late, history_steps=hist)
            for i in range(sc.n_sats)]


WireSize = Callable[[int, int, float, RelativeMeasurements, np.ndarray], int]


def simulate(sc: Scenario, model: MeasurementModel | None = None, progress: Callable[[int, int], None] | None = None,
             wire_size: WireSize | None = None) -> SimResult:
    """Run every satellite's filter over the scenario in this process.

    ``model``: the relative-measurement model (default: the synthetic one; scenarios that
    render need :func:`swarm.models.measurement_model`). ``wire_size(observer, k, t, rel,
    cameras)``: the encoded size of an observer's batch on the bus, which the link model
    needs when ``links.enabled`` (:func:`swarm.models.batch_wire_size`)."""
    n, K = sc.n_sats, sc.steps
    model = model or synthetic_model(sc)
    wp = world_params(sc)
    G = scenario_graph(sc)
    camera_ok = np.ones((n, 6), dtype=bool)
    truth = initial_truth(sc)
    filters = make_filters(sc, truth)
    lm = None
    if sc.links.enabled:
        if wire_size is None:
            raise ValueError("links.enabled: the link model needs each batch's encoded size (pass wire_size, "
                             "see swarm.models.batch_wire_size)")
        lm = LinkModel(sc.links, n, sc.seed, link_body_radius(sc))
    cameras = model.cameras()
    estimator = model.estimator()
    rec = Recorder(K, n, n)
    gyro = None
    try:
        for k in range(K):
            if k > 0:
                truth, gyro = step_truth(wp, truth)
            rec.truth_at(k, truth)
            absm = absolute_measurements(wp, truth)
            obs, tgt = choose_pairs(sc, k, G, filters[0].est, filters[0].params, camera_ok)
            rec.schedule[k, obs, tgt] = True
            ms_pred = np.zeros(n)
            if estimator.needs_prediction and k > 0:
                # Image pipelines start from each observer's prediction (ICP seed, ambiguity).
                for i, f in enumerate(filters):
                    t0 = time.perf_counter()
                    f.predict_to(k, None if gyro is None else gyro[i])
                    ms_pred[i] = (time.perf_counter() - t0) * 1e3
            seen = cameras.observe(truth, obs, tgt, camera_ok, predicted=[f.est for f in filters])
            if lm is None:
                rel = RelativeMeasurements.concat([estimator.measure(i, seen[i], filters[i].est, k)[0] for i in sorted(seen)])
                inputs = dict.fromkeys(range(n), (rel, None))
            else:
                assert wire_size is not None  # checked with the link model
                inputs = _through_links(lm, k, truth, seen, estimator, filters, wire_size, rec)
            for i, f in enumerate(filters):
                t0 = time.perf_counter()
                rel_i, late_i = inputs[i]
                rep, lrep = f.step(k, None if gyro is None else gyro[i], absm[i] if G[i, i] else None, rel_i, late=late_i)
                ms = (time.perf_counter() - t0) * 1e3 + ms_pred[i]
                rec.estimate_at(k, i, f.est, rep, ms)
                rec.late_at(k, i, lrep)
            if progress is not None:
                progress(k + 1, K)
    finally:
        cameras.close()
    extra = {} if lm is None else {"links": link_summary(lm.counters, lm.latencies)}
    res = rec.result(sc, extra)
    if lm is not None:
        res.link_latencies = list(lm.latencies)
    return res


def _through_links(lm: LinkModel, k: int, truth, seen, estimator, filters, wire_size: WireSize, rec: Recorder):
    """Every observer's batch through the radio; what each receiver holds at step k: its
    own batch and the copies that arrived (on time), and the late ones by their step."""
    n = len(filters)
    own = {i: estimator.measure(i, seen.get(i), filters[i].est, k) for i in range(n)}
    lm.at_step(k, truth.r_H)
    for i in range(n):
        rel_i, cams_i = own[i]
        lm.send(i, range(n), rel_i, wire_size(i, k, truth.t, rel_i, cams_i), truth.t, key=k)
    inputs = {}
    arrived = lm.due(truth.t)
    for i in range(n):
        mine = [d for d in arrived if d.receiver == i]
        on_time = RelativeMeasurements.concat([own[i][0], *[d.payload for d in mine if d.sent_step == k]])
        late: dict[int, list] = {}
        for d in mine:
            if d.sent_step < k:
                late.setdefault(d.sent_step, []).append(d.payload)
        inputs[i] = (on_time, {s: RelativeMeasurements.concat(b) for s, b in late.items()})
    rec.links_at(k, lm)
    return inputs


def late_summary(used: np.ndarray, dropped: np.ndarray, replayed: np.ndarray) -> dict:
    """The ``late`` block of summary.json: what every filter did with late measurements."""
    return {"late": {"used": int(used.sum()), "dropped": int(dropped.sum()), "replayed_steps": int(replayed.sum())}}


def link_summary(counters: LinkCounters, latencies) -> dict:
    """The ``links`` block of summary.json: totals, per directed link, delivered latency."""
    lat = np.array([x[3] for x in latencies], dtype=float)
    tot = {k: int(np.sum(v)) for k, v in counters.as_dict().items()}
    stats = None
    if lat.size:
        stats = {"count": int(lat.size), "mean": float(lat.mean()), "p50": float(np.percentile(lat, 50)),
                 "p95": float(np.percentile(lat, 95)), "max": float(lat.max())}
    return {"totals": tot, "per_link": counters.as_dict(), "latency_s": stats}
