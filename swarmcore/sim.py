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
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from .agent import AgentFilter, filter_params
from .graphs import scenario_graph
from .measurement import MeasurementModel, synthetic_model
from .mekf import RelativeMeasurements, SwarmEstimate, UpdateReport
from .metrics import pose_cov_blocks, pose_errors, pose_nees, summarize
from .scenario import Scenario
from .selection import choose_pairs
from .world import absolute_measurements, initial_estimate, initial_truth, step_truth, world_params

__all__ = ["SimResult", "simulate"]


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
        )


def simulate(sc: Scenario, model: MeasurementModel | None = None, progress: Callable[[int, int], None] | None = None) -> SimResult:
    """Run every satellite's filter over the scenario in this process.

    ``model``: the relative-measurement model (default: the synthetic one; scenarios that
    render need :func:`swarm.models.measurement_model`)."""
    n, K = sc.n_sats, sc.steps
    model = model or synthetic_model(sc)
    wp = world_params(sc)
    G = scenario_graph(sc)
    camera_ok = np.ones((n, 6), dtype=bool)
    truth = initial_truth(sc)
    filters = [AgentFilter(filter_params(sc, i), initial_estimate(sc, truth, i), sc.filter.mode) for i in range(n)]
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
                    f.predict_to(k, gyro[i])
                    ms_pred[i] = (time.perf_counter() - t0) * 1e3
            seen = cameras.observe(truth, obs, tgt, camera_ok, predicted=[f.est for f in filters])
            batches = [estimator.measure(i, seen[i], filters[i].est, k)[0] for i in sorted(seen)]
            rel = RelativeMeasurements.concat(batches)
            for i, f in enumerate(filters):
                t0 = time.perf_counter()
                rep, _late = f.step(k, None if gyro is None else gyro[i], absm[i] if G[i, i] else None, rel)
                ms = (time.perf_counter() - t0) * 1e3 + ms_pred[i]
                rec.estimate_at(k, i, f.est, rep, ms)
            if progress is not None:
                progress(k + 1, K)
    finally:
        cameras.close()
    return rec.result(sc)
