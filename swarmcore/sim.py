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

from .estimators import EstimateView, Estimator, Received, StepInputs, StepReport, builtin_estimator
from .graphs import scenario_graph
from .links import LinkCounters, LinkModel, scenario_link_model
from .measurement import MeasurementModel
from .mekf import RelativeMeasurements
from .metrics import pose_errors, pose_nees, relative_errors_of, run_summary
from .scenario import Scenario
from .selection import choose_pairs
from .synthetic import synthetic_model
from .world import absolute_measurements, initial_estimate, initial_truth, step_truth, world_params

__all__ = ["SimResult", "SimStep", "simulate", "make_estimators", "link_summary", "late_summary"]


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
    rel_att_err: np.ndarray | None = None  # (K, F, n) rad: filter f's estimate of j relative to itself
    rel_pos_err: np.ndarray | None = None  # (K, F, n) m
    rel_nees: np.ndarray | None = None  # (K, F, n) against the relative covariance f claims
    bytes_sent: np.ndarray | None = None  # (K, n) bytes each satellite put on its radio per step
    taken: np.ndarray | None = None  # (K, n, n) bool: relative measurements in the batches put on the radio
    estimator: str = "full"
    cpu_ms: np.ndarray | None = None  # (K, F) CPU time of each filter step (thread time: predict + update)

    def summary(self) -> dict:
        return run_summary(
            self.scenario,
            att_err=self.att_err,
            pos_err=self.pos_err,
            nees=self.nees,
            gate_accepted=self.gate_accepted,
            gate_rejected=self.gate_rejected,
            step_ms=self.step_ms,
            nis=self.nis,
            nis_dof=self.nis_dof,
            taken=self.taken if self.taken is not None else self.schedule,
            estimator=self.estimator,
            rel_att_err=self.rel_att_err,
            rel_pos_err=self.rel_pos_err,
            rel_nees=self.rel_nees,
            bytes_sent=self.bytes_sent,
            cpu_ms=self.cpu_ms,
            late=None if self.late_used is None or self.late_dropped is None or self.replayed is None
            else (self.late_used, self.late_dropped, self.replayed),
            extra=self.extra,
        )


@dataclass
class SimStep:
    """What one step of the simulator saw and did, handed to ``simulate(on_step=...)`` (the
    3-D scene of ``swarm sim`` is built from it): the truth, every filter's view after the
    step, the relative measurements each observer put on the radio (``taken[i, j]``) and,
    with links, the cumulative per-link counters (:class:`~swarmcore.links.LinkCounters`)."""

    k: int
    t: float
    q_BI: np.ndarray  # (n, 4) true attitudes
    r_H: np.ndarray  # (n, 3) true positions (m, HCW)
    views: list[EstimateView]  # the view after step k of every filter that stepped (``view.own``: whose)
    taken: np.ndarray  # (n, n) bool
    links: LinkCounters | None = None


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
        self.cpu_ms = np.full((K, F), nan)
        self.schedule = np.zeros((K, n, n), dtype=bool)
        self.taken = np.zeros((K, n, n), dtype=bool)
        self.late_used = np.zeros((K, F), dtype=int)
        self.late_dropped = np.zeros((K, F), dtype=int)
        self.replayed = np.zeros((K, F), dtype=int)
        self.rel_att_err = np.full((K, F, n), nan)
        self.rel_pos_err = np.full((K, F, n), nan)
        self.rel_nees = np.full((K, F, n), nan)
        self.bytes_sent = np.full((K, n), nan)  # bytes each satellite put on its radio per step
        self.kind = "full"
        self.n = n
        self.link_series = np.zeros((K, 6), dtype=int)  # cumulative sent, delivered, late, lost, dropped, unreachable
        self.queue_bytes = np.zeros((K, n), dtype=int)  # each transmitter's backlog at the step

    def sent_at(self, k, sizes: dict[int, int] | None) -> None:
        """Bytes each satellite put on its radio at step k (batch and estimator message)."""
        if sizes is not None:
            for i, b in sizes.items():
                self.bytes_sent[k, i] = b

    def links_at(self, k, lm) -> None:
        c = lm.counters
        self.link_series[k] = [c.sent.sum(), c.delivered.sum(), c.delivered_late.sum(), c.lost.sum(), c.dropped_queue.sum(),
                               c.unreachable.sum()]
        self.queue_bytes[k] = lm.queue_bytes(self.t[k])

    def truth_at(self, k, truth):
        self.t[k] = truth.t
        for key in self.truth:
            self.truth[key][k] = getattr(truth, key)

    def estimate_at(self, k, f, view: EstimateView, report: StepReport | None, ms: float | None):
        """Filter f's claim at step k against the truth of step k: its own and tracked peers'
        errors and NEES, and its estimate of each peer relative to itself."""
        e = self.est
        ids = view.ids
        e["q_BI"][k, f, ids] = view.q_BI
        e["omega_BI_B"][k, f, ids] = view.omega_BI_B
        e["r_H"][k, f, ids] = view.r_H
        e["v_H"][k, f, ids] = view.v_H
        e["bias_B"][k, f] = view.bias_B
        if ids.size == self.n:
            e["P_diag"][k, f] = view.P_diag
        else:
            e["P_diag"][k, f, (12 * ids[:, None] + np.arange(12)).ravel()] = view.P_diag
        q_true, r_true = self.truth["q_BI"][k], self.truth["r_H"][k]
        a, dr = pose_errors(view.q_BI, view.r_H, q_true[ids], r_true[ids])
        self.att_err[k, f, ids] = np.linalg.norm(a, axis=-1)
        self.pos_err[k, f, ids] = np.linalg.norm(dr, axis=-1)
        self.nees[k, f, ids] = pose_nees(a, dr, view.P_pose)
        own_row = view.row(f)
        if own_row is not None and ids.size > 1:
            a_rel, dr_rel = relative_errors_of(view.q_BI, view.r_H, own_row, q_true[ids], r_true[ids])
            others = ids != f
            oi = ids[others]
            self.rel_att_err[k, f, oi] = np.linalg.norm(a_rel[others], axis=-1)
            self.rel_pos_err[k, f, oi] = np.linalg.norm(dr_rel[others], axis=-1)
            self.rel_nees[k, f, oi] = pose_nees(a_rel[others], dr_rel[others], view.P_rel_pose[others])
        if report is not None:
            self.gate_accepted[k, f] = report.gate_accepted
            self.gate_rejected[k, f] = report.gate_rejected
            self.nis[k, f] = report.nis
            self.nis_dof[k, f] = report.nis_dof
            self.late_used[k, f] = report.late_used
            self.late_dropped[k, f] = report.late_dropped
            self.replayed[k, f] = report.replayed_steps
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
            rel_att_err=self.rel_att_err,
            rel_pos_err=self.rel_pos_err,
            rel_nees=self.rel_nees,
            bytes_sent=self.bytes_sent,
            taken=self.taken,
            cpu_ms=self.cpu_ms,
            estimator=self.kind,
        )


def make_estimators(sc: Scenario, truth, factory: EstimatorFactory | None = None) -> list[Estimator]:
    """Every satellite's estimator at the world's prior (:func:`swarmcore.world.initial_estimate`
    over the satellites each one starts from)."""
    factory = factory or builtin_estimator
    out = []
    for i in range(sc.n_sats):
        e = factory(sc, i)
        e.start(initial_estimate(sc, truth, i, e.prior_ids()))
        out.append(e)
    return out


#: ``wire_size(observer, k, t, rel, cameras, message)``: bytes of an observer's batch and
#: its estimator's message on the radio.
WireSize = Callable[[int, int, float, RelativeMeasurements, np.ndarray, object], int]
EstimatorFactory = Callable[[Scenario, int], Estimator]


def simulate(sc: Scenario, model: MeasurementModel | None = None, progress: Callable[[int, int], None] | None = None,
             wire_size: WireSize | None = None, estimator_factory: EstimatorFactory | None = None,
             outages: dict[int, tuple[int, int | None]] | None = None,
             on_step: Callable[[SimStep], None] | None = None) -> SimResult:
    """Run every satellite's estimator over the scenario in this process.

    ``model``: the relative-measurement model (default: the synthetic one; scenarios that
    render need :func:`swarm.simulation.measurement_model`). ``wire_size``: the encoded size
    of an observer's batch and estimator message on the bus, which the link model needs
    when ``links.enabled`` (:func:`swarmrt.bus.convert.batch_wire_size`).
    ``estimator_factory(sc, own)``: each satellite's estimator (default: the scenario's
    built-in ``estimator.kind``; plug-ins come through :func:`swarmrt.estimators.estimator_factory`).

    ``outages`` ``{sat: (kill step, restart step or None)}``: an agent killed and restarted,
    emulated in-process (studies; the scenario's ``faults`` are for distributed runs):
    from the kill step its estimator neither measures, sends nor steps, and its peers hear
    nothing of it (its satellite still flies and is measured); at the restart step it
    starts again as a restarted ``sat_agent`` does — from the lowest-id live peer's estimate
    (``warm_rejoin``) or cold from its own sensors — and resumes. ``on_step``: called after
    every step with its :class:`SimStep` (it changes no number)."""
    n, K = sc.n_sats, sc.steps
    model = model or synthetic_model(sc)
    wp = world_params(sc)
    G = scenario_graph(sc)
    camera_ok = np.ones((n, 6), dtype=bool)
    truth = initial_truth(sc)
    ests = make_estimators(sc, truth, estimator_factory)
    lm = scenario_link_model(sc)
    if lm is not None and wire_size is None:
        raise ValueError("links.enabled: the link model needs each batch's encoded size (pass wire_size, "
                         "see swarmrt.bus.convert.batch_wire_size)")
    cameras = model.cameras()
    pose = model.estimator()
    rec = Recorder(K, n, n)
    rec.kind = ests[0].kind
    gyro = None
    outages = outages or {}
    down: set[int] = set()  # agents dead now
    cold: set[int] = set()  # restarted agents waiting for a cold start
    try:
        for k in range(K):
            if k > 0:
                truth, gyro = step_truth(wp, truth)
            rec.truth_at(k, truth)
            absm = absolute_measurements(wp, truth)
            for i, (kill, back) in outages.items():
                if k == kill:
                    down.add(i)
                elif back is not None and k == back and i in down:
                    down.discard(i)
                    live = [j for j in range(n) if j not in down and j != i]
                    ests[i] = (estimator_factory or builtin_estimator)(sc, i)  # a new process: nothing remembered
                    if ests[i].warm_rejoin and live:
                        ests[i].rejoin(ests[live[0]].rejoin_state(), live[0], None)
                    else:
                        cold.add(i)
            up = [i for i in range(n) if i not in down]
            cam_ok = camera_ok.copy()
            cam_ok[sorted(down)] = False  # a dead agent's satellite measures nothing
            ref = ests[min(up)].selection_reference() if up else None
            obs, tgt = choose_pairs(sc, k, G, None if ref is None else ref[0], None if ref is None else ref[1], cam_ok)
            rec.schedule[k, obs, tgt] = True
            ms_pred = np.zeros(n)
            running = [i for i in up if i not in cold]
            cpu_pred = np.zeros(n)
            for i in running:  # each prior of step k (image pipelines start from it)
                t0, c0 = time.perf_counter(), time.thread_time()
                ests[i].predict(k, None if gyro is None else gyro[i])
                ms_pred[i] = (time.perf_counter() - t0) * 1e3
                cpu_pred[i] = (time.thread_time() - c0) * 1e3
            seen = cameras.observe(truth, obs, tgt, cam_ok, predicted=[e.prediction() if i in running else None for i, e in enumerate(ests)])
            # Each observer's pose estimator turns its own observation into measurements (those
            # the cameras delivered nothing to measure nothing), in observer order.
            none = (RelativeMeasurements.empty(), np.zeros(0, dtype=int))
            own = {i: pose.measure(i, seen[i], ests[i].prediction() if i in running else None, k) if i in seen and i in up else none
                   for i in range(n)}
            for i in up:
                rec.taken[k, i, own[i][0].target] = True
            sent = {i: ests[i].transmit(k) if i in running else None for i in range(n)}
            peers_of: dict[int, RelativeMeasurements] = {}
            if lm is None:
                every = [Received(j, k, own[j][0], sent[j]) for j in up]
                received = {i: [r for r in every if r.sender != i] for i in range(n)}
                batch = RelativeMeasurements.concat([r.measurements for r in every])
                peers_of = {i: batch.subset(batch.observer != i) for i in up}
            else:
                assert wire_size is not None  # checked with the link model
                received = _through_links(lm, k, truth, own, sent, wire_size, rec, up)
            views = []
            for i in up:
                e = ests[i]
                t0, c0 = time.perf_counter(), time.thread_time()
                inputs = StepInputs(k, truth.t, None if gyro is None else gyro[i], absm[i] if G[i, i] else None, own[i][0],
                                    received[i], peers_of.get(i))
                if i in cold:
                    if not e.cold_start(inputs):
                        continue
                    cold.discard(i)
                    rep = None
                else:
                    rep = e.step(inputs)
                ms = (time.perf_counter() - t0) * 1e3 + ms_pred[i]
                rec.cpu_ms[k, i] = (time.thread_time() - c0) * 1e3 + cpu_pred[i]
                views.append(e.view())
                rec.estimate_at(k, i, views[-1], rep, ms)
            if wire_size:
                rec.sent_at(k, {i: wire_size(i, k, truth.t, own[i][0], own[i][1], sent[i]) for i in up})
            if on_step is not None:
                on_step(SimStep(k, truth.t, truth.q_BI, truth.r_H, views, rec.taken[k].copy(),
                                None if lm is None else lm.counters))
            if progress is not None:
                progress(k + 1, K)
    finally:
        cameras.close()
    extra = {} if lm is None else {"links": link_summary(lm.counters, lm.latencies)}
    res = rec.result(sc, extra)
    if lm is not None:
        res.link_latencies = list(lm.latencies)
    return res


def _through_links(lm: LinkModel, k: int, truth, own: dict, sent: dict, wire_size: WireSize, rec: Recorder,
                   up: list[int] | None = None) -> dict[int, list[Received]]:
    """Every (live) observer's batch and estimator message through the radio; what each
    receiver holds at step k: the copies that arrived by t_k, of this step (on time) or
    earlier (late)."""
    n = len(own)
    lm.at_step(k, truth.r_H)
    for i in (range(n) if up is None else up):
        rel_i, cams_i = own[i]
        lm.send(i, range(n), (rel_i, sent[i]), wire_size(i, k, truth.t, rel_i, cams_i, sent[i]), truth.t, key=k)
    out: dict[int, list[Received]] = {i: [] for i in range(n)}
    for d in lm.due(truth.t):
        out[d.receiver].append(Received(d.sender, d.sent_step, d.payload[0], d.payload[1]))
    for i in range(n):
        out[i].sort(key=lambda r: (r.step, r.sender))
    rec.links_at(k, lm)
    return out


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
