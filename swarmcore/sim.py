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
   prediction); then it updates with its absolute reading (if it has the sensors) and the
   batches its radio delivers (the ideal radio: every live peer's, or only its graph
   neighbours' for an estimator whose ``radio`` is ``"graph"``:
   :func:`swarmcore.graphs.radio_peers`, which the world's radio uses too) in canonical
   order.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .estimators import EstimateView, Estimator, Received, StepInputs, builtin_estimator
from .graphs import radio_peers, scenario_graph
from .links import LinkCounters, LinkModel, scenario_link_model
from .measurement import MeasurementModel
from .mekf import RelativeMeasurements
from .result import RunBuilder, RunResult
from .scenario import Scenario
from .selection import choose_pairs
from .synthetic import synthetic_model
from .world import absolute_measurements, initial_estimate, initial_truth, step_truth, world_params

__all__ = ["SimStep", "simulate", "make_estimators"]


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
             on_step: Callable[[SimStep], None] | None = None) -> RunResult:
    """Run every satellite's estimator over the scenario in this process; its
    :class:`~swarmcore.result.RunResult`.

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
    # Whose batches the ideal radio brings each agent (None: everyone's).
    hears = radio_peers(G, type(ests[0]).radio) if n else None
    hear_set = [] if hears is None else [set(h.tolist()) for h in hears]
    if lm is not None and wire_size is None:
        raise ValueError("links.enabled: the link model needs each batch's encoded size (pass wire_size, "
                         "see swarmrt.bus.convert.batch_wire_size)")
    cameras = model.cameras()
    pose = model.estimator()
    rec = RunBuilder(K, n)
    rec.estimator = ests[0].kind
    gyro = None
    outages = outages or {}
    down: set[int] = set()  # agents dead now
    cold: set[int] = set()  # restarted agents waiting for a cold start
    try:
        for k in range(K):
            if k > 0:
                truth, gyro = step_truth(wp, truth)
            rec.truth_at(k, truth.t, truth.q_BI, truth.omega_BI_B, truth.r_H, truth.v_H, truth.bias_B)
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
            rec.selected_at(k, obs, tgt)
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
                rec.taken_at(k, i, own[i][0].target)
            for i in running:  # its own absolute reading, which the centralized reference sends
                ests[i].absolute_reading(k, absm[i] if G[i, i] else None)
            sent = {i: ests[i].transmit(k) if i in running else None for i in range(n)}
            peers_of: dict[int, RelativeMeasurements] = {}
            if lm is None:
                every = [Received(j, k, own[j][0], sent[j]) for j in up]
                batch = RelativeMeasurements.concat([r.measurements for r in every])
                if hears is None:  # the whole swarm's batches, to every agent
                    received = {i: [r for r in every if r.sender != i] for i in range(n)}
                    peers_of = {i: batch.subset(batch.observer != i) for i in up}
                else:  # each agent's radio peers' (the world delivers the same: radio_peers)
                    received = {i: [r for r in every if r.sender in hear_set[i]] for i in range(n)}
                    peers_of = {i: batch.subset(np.isin(batch.observer, hears[i])) for i in up}
            else:
                assert wire_size is not None  # checked with the link model
                received = _through_links(lm, k, truth, own, sent, wire_size, rec, up)
            if sc.bound_on:
                f = sc.bound.filter
                _count_for_bound(sc, rec, k, up, own, received, G,
                                 type(ests[f]).absolute_in if f is not None and ests[f].hears_peer_absolute else None)
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
                rec.step_ms[k, i] = (time.perf_counter() - t0) * 1e3 + ms_pred[i]
                rec.cpu_ms[k, i] = (time.thread_time() - c0) * 1e3 + cpu_pred[i]
                v = e.view()
                views.append(v)
                rec.estimate_at(k, i, v.ids, v.q_BI, v.omega_BI_B, v.r_H, v.v_H, v.bias_B, v.P_diag, v.P_pose, v.P_rel_pose)
                if rep is not None:
                    rec.report_at(k, i, gate_accepted=rep.gate_accepted, gate_rejected=rep.gate_rejected, nis=rep.nis,
                                  nis_dof=rep.nis_dof, late_used=rep.late_used, late_dropped=rep.late_dropped,
                                  replayed_steps=rep.replayed_steps)
            if wire_size:
                for i in up:
                    rec.bytes_sent[k, i] = wire_size(i, k, truth.t, own[i][0], own[i][1], sent[i])
            if on_step is not None:
                on_step(SimStep(k, truth.t, truth.q_BI, truth.r_H, views, rec.taken[k].copy(),
                                None if lm is None else lm.counters))
            if progress is not None:
                progress(k + 1, K)
    finally:
        cameras.close()
    if lm is not None:
        rec.link_latencies = lm.latencies
    return rec.result(sc)


def _count_for_bound(sc: Scenario, rec: RunBuilder, k: int, up: list[int], own: dict, received: dict, G: np.ndarray,
                     absolute_in: Callable[[object], object] | None = None) -> None:
    """What the Cramér–Rao bound (``sc.bound``) counts of step k: centralized, every live
    satellite's relative measurements and absolute reading; of filter f, its own and what
    reached it (a late delivery counted at the step it was taken), and its own absolute
    reading, and (``absolute_in``: the centralized reference, whose messages carry their
    sender's reading) every peer's reading that reached it, likewise."""
    f = sc.bound.filter
    if f is None:
        for i in up:
            rec.measured_at(k, own[i][0])
        rec.absolute_at(k, [i for i in up if G[i, i]])
    elif f in up:
        rec.measured_at(k, own[f][0])
        for r in received[f]:
            rec.measured_at(r.step, r.measurements)
            if absolute_in is not None and absolute_in(r.payload) is not None:
                rec.absolute_at(r.step, [r.sender])
        rec.absolute_at(k, [f] if G[f, f] else [])


def _through_links(lm: LinkModel, k: int, truth, own: dict, sent: dict, wire_size: WireSize, rec: RunBuilder,
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
    rec.links_at(k, lm.counters, lm.queue_bytes(truth.t))
    return out
