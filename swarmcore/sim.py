"""In-process simulator: every satellite's filter on one machine, same core calls and order
as the distributed emulator (``world_sim`` / ``sat_agent``), so both give the same numbers.

One step k (t_k = k dt):

1. world: (k > 0) advance the truth from k−1 and emit each gyro's sample of that interval;
   absolute readings at t_k; relative measurements of the pairs scheduled for k.
2. agent i: (k > 0) predict with its own gyro sample; update with its own absolute reading
   (if it has the sensors) and the relative batch (all of it when cooperative, only its own
   rows when isolated) in canonical order.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from . import graphs
from .mekf import (
    AbsoluteMeasurement,
    FilterParams,
    RelativeMeasurements,
    SwarmEstimate,
    UpdateReport,
    observed_indices,
    predict,
    update,
)
from .metrics import pose_errors, pose_nees, summarize
from .scenario import Scenario
from .world import (
    absolute_measurements,
    filter_params,
    initial_estimate,
    initial_truth,
    relative_measurements,
    step_truth,
    world_params,
)

__all__ = ["filter_step", "SimResult", "simulate", "pose_cov_blocks"]


def filter_step(
    est: SwarmEstimate,
    params: FilterParams,
    gyro_rate_B: np.ndarray | None,
    absolute: AbsoluteMeasurement | None,
    relative: RelativeMeasurements,
    mode: str = "cooperative",
    propagate: bool = True,
) -> tuple[SwarmEstimate, UpdateReport]:
    """One agent step: predict (unless ``propagate`` is False, at k = 0), then update."""
    if propagate:
        est = predict(est, params, gyro_rate_B)
    if mode == "isolated":
        relative = relative.subset(relative.observer == params.own)
    return update(est, params, absolute, relative.canonical())


def pose_cov_blocks(P: np.ndarray, n: int) -> np.ndarray:
    """(n, 6, 6) covariance of each satellite's [a, Δr] from a full P."""
    O = observed_indices(n)
    P4 = P[np.ix_(O, O)].reshape(n, 6, n, 6)
    idx = np.arange(n)
    return P4[idx, :, idx, :]


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
        dof = float(np.nansum(self.nis_dof))
        nis_ratio = float(np.nansum(self.nis) / dof) if dof else None
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
            extra={
                "scenario": sc.name,
                "mode": sc.filter.mode,
                "nis": {"sum": float(np.nansum(self.nis)), "dof": dof, "ratio": nis_ratio},
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


def scenario_graph(sc: Scenario) -> np.ndarray:
    g = sc.graph
    return graphs.incidence(sc.n_sats, g.kind, landmark=g.landmark, matrix=g.matrix, absolute=g.absolute)


def selector_prior(est: SwarmEstimate, params: FilterParams, k: int) -> SwarmEstimate:
    """What the selector plans step k with: the reference filter's estimate at k−1 carried
    to k without its gyro (the selector never sees it), or the initial estimate at k = 0."""
    return est if est.step >= k else predict(est, params, None)


def choose_pairs(sc: Scenario, k: int, G: np.ndarray, ref_est: SwarmEstimate, ref_params: FilterParams, camera_ok: np.ndarray):
    """The (observer, target) pairs measured at step k: the graph, or the selector's choice."""
    if sc.selection.strategy == "none":
        return graphs.edges(G)
    from .selection import select_for_scenario  # the selector's brain (chapter 6)

    return select_for_scenario(sc, k, G, selector_prior(ref_est, ref_params, k), ref_params, camera_ok)


def simulate(sc: Scenario, progress: Callable[[int, int], None] | None = None) -> SimResult:
    """Run every satellite's filter over the scenario in this process."""
    n, K = sc.n_sats, sc.steps
    wp = world_params(sc)
    G = scenario_graph(sc)
    camera_ok = np.ones((n, 6), dtype=bool)
    params = [filter_params(sc, i) for i in range(n)]
    truth = initial_truth(sc)
    ests = [initial_estimate(sc, truth, i) for i in range(n)]
    rec = Recorder(K, n, n)
    vision = None
    if sc.vision.pipeline != "none":
        from swarmvision.pipeline import VisionSystem  # rendering only when asked for

        vision = VisionSystem(sc.vision, n, sc.spacecraft.half_size_m, sc.seed, sc.orbit.mean_motion_rad_s)
    gyro = None
    for k in range(K):
        if k > 0:
            truth, gyro = step_truth(wp, truth)
        rec.truth_at(k, truth)
        absm = absolute_measurements(wp, truth)
        obs, tgt = choose_pairs(sc, k, G, ests[0], params[0], camera_ok)
        rec.schedule[k, obs, tgt] = True
        ms_pred = np.zeros(n)
        if vision is not None:
            # Image pipelines start from each observer's prediction (ICP seed, ambiguity).
            for i in range(n):
                t0 = time.perf_counter()
                if k > 0:
                    ests[i] = predict(ests[i], params[i], gyro[i])
                ms_pred[i] = (time.perf_counter() - t0) * 1e3
            rel = vision.relative_measurements(k, truth.t, truth.q_BI, truth.r_H, (obs, tgt), ests)
        else:
            rel = relative_measurements(wp, truth, obs, tgt)
        for i in range(n):
            t0 = time.perf_counter()
            ests[i], rep = filter_step(
                ests[i],
                params[i],
                None if gyro is None else gyro[i],
                absm[i] if G[i, i] else None,
                rel,
                sc.filter.mode,
                propagate=k > 0 and vision is None,
            )
            ms = (time.perf_counter() - t0) * 1e3 + ms_pred[i]
            rec.estimate_at(k, i, ests[i], rep, ms)
        if progress is not None:
            progress(k + 1, K)
    return rec.result(sc)
